"""Golden reports of the commands on the bundled sample data."""

from __future__ import annotations

import json

import pytest

from tests.conftest import SAMPLE_DATA, run_cli, validate_report
from tests.golden import assert_matches_golden


@pytest.mark.parametrize(
    "name, args",
    [
        ("reep_ltv_step", ["reep", SAMPLE_DATA / "ltv_step.h5"]),
        ("reep_ltv_step_csv", ["reep", SAMPLE_DATA / "ltv_step.csv"]),
        ("reep_tapping_force_curve", ["reep", SAMPLE_DATA / "tapping_force_curve.h5"]),
        ("freeair_ltv_step", ["identify", "freeair", SAMPLE_DATA / "ltv_step.h5"]),
    ],
)
def test_golden_report(tmp_path, name, args):
    result = run_cli(*args, "--out", tmp_path / "out", "--json", "--quiet")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == report
    assert_matches_golden(report, name)


def test_golden_comparison_can_fail(monkeypatch):
    from tests.golden import GOLDEN_DIR

    monkeypatch.delenv("AFMTOOL_UPDATE_GOLDEN", raising=False)  # compare, never rewrite, here
    golden = json.loads((GOLDEN_DIR / "reep_ltv_step.json").read_text())
    golden["inputs"][0]["path"] = "ltv_step.h5"
    golden["results"]["summary"]["f0_hz"]["mean"] *= 1 + 1e-5
    with pytest.raises(AssertionError, match="f0_hz.mean"):
        assert_matches_golden(golden, "reep_ltv_step")
