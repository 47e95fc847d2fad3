"""Shared fixtures: paths, a seeded RNG, and an in-process CLI runner."""

from __future__ import annotations

import json
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


def load_schema(name: str) -> dict:
    return json.loads((SCHEMAS / name).read_text())


def validate_report(report: dict) -> None:
    import jsonschema

    jsonschema.validate(report, load_schema("report.schema.json"))
