"""Golden-report comparison: numbers within stated tolerances, everything else exact.

Set ``AFMTOOL_UPDATE_GOLDEN=1`` to rewrite the stored reports after an
intended change (and review the diff).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"

#: Relative and absolute tolerance for every number in a golden report.  The
#: kernels are deterministic IEEE arithmetic (no fastmath); the slack covers
#: summation-order differences between numpy builds.
RTOL = 1e-6
ATOL = 1e-9


def _normalise(report: dict) -> dict:
    report = json.loads(json.dumps(report))
    for item in report.get("inputs", []):
        item["path"] = Path(item["path"]).name
    report.pop("afmtool_version", None)
    # The headline repeats numbers of results (compared here number by number) with
    # names and units for the reader; tests/test_headline.py checks it against results.
    report.pop("headline", None)
    return report


def _compare(expected, actual, where: str, problems: list[str]) -> None:
    if isinstance(expected, dict) and isinstance(actual, dict):
        for key in sorted(set(expected) | set(actual)):
            if key not in expected or key not in actual:
                problems.append(f"{where}.{key}: present in only one report")
            else:
                _compare(expected[key], actual[key], f"{where}.{key}", problems)
    elif isinstance(expected, list) and isinstance(actual, list):
        if len(expected) != len(actual):
            problems.append(f"{where}: length {len(actual)} != {len(expected)}")
        for i, (e, a) in enumerate(zip(expected, actual)):
            _compare(e, a, f"{where}[{i}]", problems)
    elif isinstance(expected, bool) or isinstance(actual, bool) or not (
        isinstance(expected, (int, float)) and isinstance(actual, (int, float))
    ):
        if expected != actual:
            problems.append(f"{where}: {actual!r} != {expected!r}")
    elif not math.isclose(actual, expected, rel_tol=RTOL, abs_tol=ATOL):
        problems.append(f"{where}: {actual!r} != {expected!r} (rtol {RTOL}, atol {ATOL})")


def assert_matches_golden(report: dict, name: str) -> None:
    path = GOLDEN_DIR / f"{name}.json"
    actual = _normalise(report)
    if os.environ.get("AFMTOOL_UPDATE_GOLDEN") or not path.exists():
        if not os.environ.get("AFMTOOL_UPDATE_GOLDEN"):
            raise AssertionError(f"no golden report {path}; run with AFMTOOL_UPDATE_GOLDEN=1 to create it")
        path.write_text(json.dumps(actual, indent=2, sort_keys=True) + "\n")
        return
    problems: list[str] = []
    _compare(json.loads(path.read_text()), actual, name, problems)
    assert not problems, "golden report differs:\n" + "\n".join(problems[:30])
