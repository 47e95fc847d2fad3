"""Live pipelines: rows come out while the input is still arriving; `| head` ends quietly."""

from __future__ import annotations

import io
import json
import queue
import subprocess
import sys
import threading

from afmtool import sim
from afmtool.io.csv import CsvWriter
from tests.conftest import REPO


def _csv_text(duration_s: float) -> str:
    captured = sim.simulate("ltv", {"duration_s": duration_s, "step_time_s": 10.0}, seed=0)
    buffer = io.StringIO()
    writer = CsvWriter(buffer, captured.sample_rate_hz, captured.channels, captured.metadata)
    writer.write(captured.data)
    return buffer.getvalue()


def test_first_row_before_producer_finishes():
    lines = _csv_text(0.1).splitlines(keepends=True)
    consumer = subprocess.Popen(
        [sys.executable, "-m", "afmtool", "reep", "-", "--stream", "--stream-format", "jsonl", "--free-air", "0:0.01"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
        text=True,
    )
    rows: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [rows.put(line) for line in consumer.stdout], daemon=True).start()
    # the slow producer: a third of the capture, then wait for output before sending the rest
    third = len(lines) // 3
    consumer.stdin.write("".join(lines[:third]))
    consumer.stdin.flush()
    first = rows.get(timeout=120)  # arrives while stdin is still open
    assert consumer.poll() is None
    record = json.loads(first)
    assert set(record) >= {"t", "f0_hz", "q", "amplitude", "phase_deg"}
    consumer.stdin.write("".join(lines[third:]))
    consumer.stdin.close()
    assert consumer.wait(timeout=120) == 0, consumer.stderr.read()


def test_closed_pipe_is_quiet_success():
    pipeline = (
        f"{sys.executable} -m afmtool simulate ltv -o - --format csv --set duration_s=0.05 "
        f"| {sys.executable} -m afmtool reep - --stream --free-air 0:0.01 | head -3; "
        'echo "status ${PIPESTATUS[0]} ${PIPESTATUS[1]}"'
    )
    result = subprocess.run(["bash", "-c", pipeline], capture_output=True, text=True, cwd=REPO, timeout=300)
    out = result.stdout.splitlines()
    assert out[0].startswith("t,f0_hz,q")
    assert out[-1] == "status 0 0"
    assert result.stderr == ""
