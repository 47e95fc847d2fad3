"""docs/tutorial.md is run as written, so the docs cannot rot.

Every ```bash block of the tutorial runs, in order, in one temporary folder
holding a link to sample_data/; a failing command fails the test.  So does
the README quick start's afmtool command, in a fresh folder.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from tests.conftest import REPO, SAMPLE_DATA

TUTORIAL = REPO / "docs" / "tutorial.md"
README = REPO / "README.md"

#: What the tutorial's sections leave behind, relative to its folder: a section whose command
#: stopped writing its main outputs fails here even if its shell block still exits 0.
EXPECTED_OUTPUTS = [
    "freeair/free_air.json",
    "reep_step/reep.h5",
    "reep_curve/report.html",
    "excitation/excitation.wav",
    "excitation/lines.json",
    "compare_fc/report.json",
    "fit_fc/fit.json",
    "probeloss/report.json",
    "probeloss/probeloss.h5",
    "probeloss/loss_mask_trace.png",
    "probeloss/loss_mask_trace.gsf",
    "bank/bank.h5",
    "bank/bank_rms_vs_z.png",
    "bank_thesis/bank.h5",
    "observer/observer.h5",
    "gamma/gamma.h5",
    "gamma/gamma_ir_ts.png",
    "thermal_sensor/thermal_sensor.json",
    "es/electrostatic.json",
    "es_thermal/electrostatic.json",
    "decode/decode.h5",
    "decode/eye.png",
    "decode/report.html",
]


def tutorial_blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", TUTORIAL.read_text(), flags=re.S)


def _session(tmp_path) -> dict:
    """Make tmp_path a working folder: a link to sample_data/, `afmtool` on PATH; return the env."""
    (tmp_path / "sample_data").symlink_to(SAMPLE_DATA)
    env = dict(os.environ)
    # the tests run from the source tree; make `afmtool` the same package and interpreter
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    launcher = bin_dir / "afmtool"
    launcher.write_text(f"#!/bin/sh\nexec {sys.executable} -m afmtool \"$@\"\n")
    launcher.chmod(0o755)
    # and the tutorial's `python -c` lines run in the same interpreter (with h5py), venv activated or not
    python = bin_dir / "python"
    python.write_text(f"#!/bin/sh\nexec {sys.executable} \"$@\"\n")
    python.chmod(0o755)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    env["PYTHONPATH"] = str(REPO)
    return env


def test_readme_quick_start_runs_in_a_fresh_folder(tmp_path):
    quick_start = re.search(r"## Quick start\n\n```bash\n(.*?)```", README.read_text(), flags=re.S).group(1)
    command = quick_start.splitlines()[0].split("&&", 1)[1].strip()  # after `pip install .`
    assert command.startswith("afmtool ") and "--out results/" in command
    result = subprocess.run(["bash", "-euo", "pipefail", "-c", command], cwd=tmp_path, env=_session(tmp_path),
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "results" / "reep" / "reep.h5").is_file()


def test_tutorial_commands_run(tmp_path):
    blocks = tutorial_blocks()
    assert len(blocks) >= 14
    env = _session(tmp_path)
    for number, block in enumerate(blocks, start=1):
        result = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=env,
                                capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, f"tutorial block {number} failed:\n{block}\n{result.stderr[-2000:]}"
    missing = [name for name in EXPECTED_OUTPUTS if not (tmp_path / name).is_file()]
    assert not missing, f"the tutorial did not write {missing}"
