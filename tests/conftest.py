"""Shared fixtures: paths, a seeded RNG, and an in-process CLI runner."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SCHEMAS = REPO / "schemas"
SAMPLE_DATA = REPO / "sample_data"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


@pytest.fixture
def shared() -> Path:
    if not SHARED.is_dir():
        pytest.skip("../shared is not beside the repository")
    return SHARED


def run_cli(*args: str, input: bytes | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run ``afmtool`` in a subprocess, as a user would (exit codes, stderr)."""
    return subprocess.run(
        [sys.executable, "-m", "afmtool", *map(str, args)],
        input=input,
        capture_output=True,
        cwd=cwd,
        timeout=600,
    )


def run_cli_cpu(*args: str, input: bytes | None = None) -> tuple[subprocess.CompletedProcess, float]:
    """``run_cli`` and the CPU seconds (user + system) the command used.

    A limit on a command's cost is asserted on its CPU time, not the wall clock: on a loaded
    machine (CI's two cores shared by two xdist workers, or a developer's by several sessions)
    a run that costs 1 s of CPU can take 10 s of wall time.  ``run_cli``'s own 600 s time-out
    still catches a hang that spends no CPU.
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = run_cli(*args, input=input)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return result, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def load_schema(name: str) -> dict:
    return json.loads((SCHEMAS / name).read_text())


def validate_report(report: dict) -> None:
    """``report`` against ``report.schema.json``, and its ``results`` against the command's generated schema.

    Where the command has a result record (``afmtool.records``), the results must also read back into
    it and write out again unchanged.
    """
    import jsonschema

    jsonschema.validate(report, load_schema("report.schema.json"))
    results_schema = SCHEMAS / "results" / f"{report['command'].replace(' ', '.')}.schema.json"
    if results_schema.is_file():
        jsonschema.validate(report["results"], json.loads(results_schema.read_text()))
        from afmtool.config.commands import SPECS

        record = SPECS[report["command"]].result.load()
        assert record.from_json(report["results"]).to_json() == report["results"]
