"""Live pipelines: rows come out while the input is still arriving; `| head` ends quietly."""

from __future__ import annotations

import io
import json
import queue
import subprocess
import sys
import threading

import pytest

from afmtool import sim
from afmtool.io.csv import CsvWriter
from afmtool.io.registry import open_capture
from tests.conftest import REPO, SAMPLE_DATA


def _csv_text(duration_s: float) -> str:
    captured = sim.simulate("ltv", {"duration_s": duration_s, "step_time_s": 10.0}, seed=0)
    buffer = io.StringIO()
    writer = CsvWriter(buffer, captured.sample_rate_hz, captured.channels, captured.metadata)
    writer.write(captured.data)
    return buffer.getvalue()


def _sample_csv_text(name: str) -> str:
    """A bundled capture as CSV text (metadata kept, /truth dropped), as a live source would send it."""
    with open_capture(SAMPLE_DATA / name) as reader:
        info = reader.info
        buffer = io.StringIO()
        writer = CsvWriter(buffer, info.sample_rate_hz, info.channels, info.metadata)
        for chunk in reader.blocks(info.channel_names, 1 << 16):
            writer.write(chunk.data)
    return buffer.getvalue()


# Each live source is long enough that its first third holds the segment the command needs before
# its first row (the free-air segment, 10 ms of 122 ms for probeloss; the 2 ms nominal segment of
# 12 ms for decode), and the rest is held back until that row has arrived.
STREAMS = {
    "reep": (lambda: _csv_text(0.1), ["--free-air", "0:0.01"], {"t", "f0_hz", "q", "amplitude", "phase_deg"}),
    "probeloss": (lambda: _sample_csv_text("raster_grating.h5"), [],
                  {"t", "index", "switch", "amplitude", "amplitude_switch"}),
    "decode": (lambda: _sample_csv_text("bits_30khz.h5"), ["--bit-rate", "30000"], {"t_mean", "innovation_mean"}),
}


@pytest.mark.parametrize("command", sorted(STREAMS))
def test_first_row_before_producer_finishes(command):
    make_text, args, columns = STREAMS[command]
    lines = make_text().splitlines(keepends=True)
    consumer = subprocess.Popen(
        [sys.executable, "-m", "afmtool", command, "-", "--stream", "--stream-format", "jsonl", *args],
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
    try:
        first = rows.get(timeout=120)  # arrives while stdin is still open
    except queue.Empty:
        consumer.kill()
        raise AssertionError(f"{command} --stream wrote no row from the first third: {consumer.stderr.read()}") from None
    assert consumer.poll() is None
    record = json.loads(first)
    assert set(record) >= columns
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
    # a loaded machine can take the 5 s of stdin_watch.NOTICE_S to simulate the first chunk: the notice
    # is then right to say so, and it is the only line allowed
    from afmtool.io.stdin_watch import WAITING_MESSAGE

    assert result.stderr in ("", WAITING_MESSAGE + "\n")


@pytest.mark.parametrize(
    ("command", "args", "header"),
    [
        ("probeloss", "sample_data/raster_grating.h5", "t,index,switch"),
        ("decode", "sample_data/bits_30khz.h5 --bit-rate 30000", "t_mean,innovation_mean"),
    ],
)
def test_closed_pipe_is_quiet_success_from_file(command, args, header):
    pipeline = (
        f"{sys.executable} -m afmtool {command} {args} --stream | head -3; "
        'echo "status ${PIPESTATUS[0]}"'
    )
    result = subprocess.run(["bash", "-c", pipeline], capture_output=True, text=True, cwd=REPO, timeout=300)
    out = result.stdout.splitlines()
    assert out[0].startswith(header)
    assert out[-1] == "status 0"
    assert result.stderr == ""
