"""Waiting on stdin (issue 34): say so once after 5 s without a chunk; --stdin-timeout ends the run."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from tests.conftest import REPO

HEADER = b"# sample_rate_hz: 1000\ndeflection\n"


def _feed(write_fd: int, parts: list[tuple[float, bytes]]) -> threading.Thread:
    """Write each (delay, bytes) to the pipe in turn, then close it; a daemon thread."""

    def run() -> None:
        try:
            for delay, data in parts:
                time.sleep(delay)
                os.write(write_fd, data)
        except OSError:
            pass
        finally:
            os.close(write_fd)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_stalled_pipe_is_noticed_once_and_a_time_out_ends_the_read():
    from afmtool.errors import InputError
    from afmtool.io.stdin_watch import WatchedStdin

    read_fd, write_fd = os.pipe()
    feeder = _feed(write_fd, [(0.0, b"12"), *((0.1, b"3") for _ in range(20))])  # bytes trickle, no chunk
    watch = WatchedStdin(read_fd, timeout_s=0.8, notice_s=0.3)
    err_read, err_write = os.pipe()
    saved = os.dup(2)
    os.dup2(err_write, 2)
    try:
        with pytest.raises(InputError, match="--stdin-timeout"):
            while watch.read(1):
                pass
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(err_write)
    said = os.read(err_read, 4096).decode()
    os.close(err_read)
    os.close(read_fd)
    feeder.join(timeout=5)
    assert said == "afmtool: waiting for input on stdin\n"  # once, though the wait went on


def test_the_clock_restarts_with_each_chunk():
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.memory import ArrayReader
    from afmtool.io.stdin_watch import WatchedReader, WatchedStdin

    read_fd, write_fd = os.pipe()
    watch = WatchedStdin(read_fd, timeout_s=0.5, notice_s=10)
    reader = WatchedReader(ArrayReader(1000.0, [ChannelSpec("x")], {"x": [1.0] * 40}), watch)
    for _ in reader.blocks(["x"], 10):
        time.sleep(0.2)  # the analysis' own time between chunks is not a wait on stdin
        watch._check_wait()
    os.close(read_fd)
    os.close(write_fd)


def _afmtool(args: list[str], parts: list[tuple[float, bytes]]) -> tuple[subprocess.CompletedProcess, float]:
    proc = subprocess.Popen([sys.executable, "-m", "afmtool", *args], cwd=REPO, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    feeder = _feed(os.dup(proc.stdin.fileno()), parts)
    proc.stdin.close()
    proc.stdin = None  # the feeder owns the pipe now
    start = time.monotonic()
    out, err = proc.communicate(timeout=120)
    feeder.join(timeout=60)
    return subprocess.CompletedProcess(args, proc.returncode, out, err), time.monotonic() - start


@pytest.mark.serial
def test_info_says_it_waits_then_reads_what_comes():
    # the rows are sent once the notice came (however long start-up took on a loaded machine)
    proc = subprocess.Popen([sys.executable, "-m", "afmtool", "info", "-", "--json"], cwd=REPO, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        proc.stdin.write(HEADER)
        proc.stdin.flush()
        start = time.monotonic()
        first = proc.stderr.readline().decode()  # blocks until the notice
        waited = time.monotonic() - start
        proc.stdin.write(b"".join(b"%d\n" % i for i in range(50)))
        proc.stdin.close()
        proc.stdin = None
        out, rest = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert first == "afmtool: waiting for input on stdin\n" and waited >= 5.0
    assert proc.returncode == 0, rest.decode()
    assert "waiting" not in rest.decode()  # once
    assert b'"n_samples": 50' in out


@pytest.mark.serial
def test_stdin_timeout_ends_a_trickled_run_with_one_error_line(tmp_path):
    trickle = [(0.0, HEADER), *((0.2, b"%d\n" % i) for i in range(100))]
    result, took = _afmtool(["reep", "-", "--out", str(tmp_path / "out"), "--stdin-timeout", "2", "-q"], trickle)
    stderr = result.stderr.decode()
    assert result.returncode == 2, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "--stdin-timeout" in lines[0] and "Traceback" not in stderr
    assert took < 2 + 15  # the time-out, plus start-up on a loaded machine
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_stdin_timeout_is_range_checked(value):
    from afmtool.errors import ConfigError
    from afmtool.io.stdin_watch import set_stdin_timeout

    try:
        with pytest.raises(ConfigError, match="--stdin-timeout"):
            set_stdin_timeout(float(value))
    finally:
        set_stdin_timeout(None)
