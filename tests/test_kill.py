"""Kill a run at a random moment: --out holds the complete previous result or the complete new one."""

from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from tests.conftest import REPO, run_cli

KILLS = 20


def _snapshot(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def _complete(folder) -> bool:
    report = json.loads((folder / "report.json").read_text())
    for name in report["outputs"]:
        assert (folder / name).is_file(), name
    with h5py.File(folder / "reep.h5") as f:
        assert len(f["t"]) > 0
    return True


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    path = tmp_path_factory.mktemp("kill") / "long.h5"
    result = run_cli("simulate", "ltv", "-o", path, "--set", "duration_s=1.0", "--set", "step_time_s=10.0")
    assert result.returncode == 0
    return path


def test_random_kills_leave_old_or_new(tmp_path, capture):
    out = tmp_path / "out"
    config = tmp_path / "slow.toml"
    config.write_text("[reep]\nchunk_samples = 20000\n")  # many chunks: kills land mid-stream
    args = [sys.executable, "-m", "afmtool", "reep", str(capture), "--out", str(out), "--config", str(config), "-q"]
    start = time.monotonic()
    assert subprocess.run(args, cwd=REPO, capture_output=True).returncode == 0
    full_run_s = time.monotonic() - start
    previous = _snapshot(out)
    rng = np.random.default_rng(2026)
    outcomes = {"interrupted": 0, "finished": 0}
    for k in range(KILLS):
        proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(rng.uniform(0.05, 1.1) * full_run_s)
        proc.send_signal(signal.SIGINT if k % 2 else signal.SIGTERM)
        code = proc.wait(timeout=120)
        stderr = proc.stderr.read().decode()
        assert "Traceback" not in stderr
        # 130: interrupted in afmtool; -2/-15: the signal arrived while Python was still starting
        assert code in (0, 130, -signal.SIGINT, -signal.SIGTERM), (code, stderr)
        outcomes["finished" if code == 0 else "interrupted"] += 1
        # no staging folders or temp files are left behind
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "slow.toml"]
        now = _snapshot(out)
        assert set(now) == set(previous)
        assert _complete(out)
        if code != 0:
            assert now == previous  # nothing new
    print(outcomes)
    assert outcomes["interrupted"] >= KILLS // 2  # the kills really landed mid-run
