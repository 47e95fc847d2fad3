"""A ``--scheduler`` is a peer (issue 34): local hostile sockets on 127.0.0.1 only.

Every peer in :mod:`tests.hostile_peers` (refusing, silent, garbage, garbage
frames, trickling, closing) must give one line and exit 2 within
``--scheduler-timeout``, leave nothing behind, and never make afmtool
allocate what the peer claims.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from tests.conftest import REPO, SAMPLE_DATA
from tests.hostile_peers import KINDS, HostilePeer
from tests.test_hostile_io import _one_line_exit_2 as one_line_exit_2

pytest.importorskip("distributed")

TIMEOUT_S = 1.5


@pytest.mark.parametrize("kind", KINDS)
def test_probe_refuses_every_hostile_peer(kind):
    from afmtool.errors import InputError
    from afmtool.io.scheduler import probe_scheduler

    with HostilePeer(kind, lifetime_s=30) as peer:
        with pytest.raises(InputError, match=r"^--scheduler tcp://127\.0\.0\.1:\d+: ") as refused:
            probe_scheduler(peer.address, TIMEOUT_S)
    assert "\n" not in str(refused.value)


@pytest.mark.serial
@pytest.mark.parametrize("kind", KINDS)
def test_probe_ends_within_its_time_out(kind):
    from afmtool.errors import InputError
    from afmtool.io.scheduler import probe_scheduler

    with HostilePeer(kind, lifetime_s=30) as peer:
        start = time.monotonic()
        with pytest.raises(InputError):
            probe_scheduler(peer.address, TIMEOUT_S)
        assert time.monotonic() - start < TIMEOUT_S + 1.0


def test_a_claimed_size_is_never_allocated():
    import tracemalloc

    from afmtool.errors import InputError
    from afmtool.io.scheduler import MAX_HANDSHAKE_BYTES, probe_scheduler

    for kind in ("garbage", "garbage-small", "garbage-frames"):
        with HostilePeer(kind, lifetime_s=30) as peer:
            tracemalloc.start()
            try:
                with pytest.raises(InputError):
                    probe_scheduler(peer.address, TIMEOUT_S)
                _, peak = tracemalloc.get_traced_memory()
            finally:
                tracemalloc.stop()
        assert peak < 8 * MAX_HANDSHAKE_BYTES + (4 << 20), (kind, peak)  # the claim was 2**62 bytes


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e9"])
def test_the_time_out_itself_is_range_checked(value):
    from afmtool.errors import ConfigError
    from afmtool.io.scheduler import check_timeout

    with pytest.raises(ConfigError, match="--scheduler-timeout"):
        check_timeout(float(value))


def test_malformed_addresses_are_one_line():
    from afmtool.errors import InputError
    from afmtool.io.scheduler import probe_scheduler

    for address in ("tcp://", "127.0.0.1", "tls://127.0.0.1:1", "tcp://127.0.0.1:99999", "inproc://x"):
        with pytest.raises(InputError, match="--scheduler"):
            probe_scheduler(address, TIMEOUT_S)


RUNS = {
    "reep": lambda out: ["reep", str(SAMPLE_DATA / "ltv_step.h5"), "--out", str(out)],
    "kalman-bank": lambda out: ["kalman-bank", str(SAMPLE_DATA / "tapping_force_curve.h5"), "--out", str(out)],
    "batch": lambda out: ["batch", "reep", str(SAMPLE_DATA / "ltv_step.h5"), "--out", str(out), "--workers", "1"],
}
#: Every kind against the probe is above (in process); from the command line, each command once
#: and each of the issue's four kinds once (the runner's 'scheduler' group has every pair).
CLI_CASES = [("reep", "garbage"), ("reep", "silent"), ("kalman-bank", "trickle"), ("batch", "refusing")]


@pytest.mark.serial
@pytest.mark.parametrize(("command", "kind"), CLI_CASES)
def test_every_command_with_a_scheduler_gives_one_line_in_time_and_leaves_nothing(tmp_path, command, kind):
    work = tmp_path / "work"
    work.mkdir()
    out = work / "out"
    with HostilePeer(kind, lifetime_s=60) as peer:
        args = [sys.executable, "-m", "afmtool", *RUNS[command](out), "--scheduler", peer.address,
                "--scheduler-timeout", str(TIMEOUT_S), "-q"]
        start = time.monotonic()
        result = subprocess.run(args, cwd=REPO, capture_output=True, timeout=120)
        took = time.monotonic() - start
    one_line_exit_2(result, "--scheduler")
    assert took < TIMEOUT_S + 20, took  # the time-out, plus start-up on a loaded machine
    assert list(work.iterdir()) == []  # no --out, no staging, no lock
