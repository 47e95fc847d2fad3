"""Timing and memory helpers shared by the benchmarks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

__all__ = ["Measurement", "best_of", "run_command", "generate_h5", "BENCH_DIR", "scratch_dir"]

BENCH_DIR = Path(__file__).resolve().parent
REPO = BENCH_DIR.parent


def scratch_dir() -> Path:
    path = Path(os.environ.get("AFMTOOL_BENCH_SCRATCH", "/tmp/afmtool-bench"))
    path.mkdir(parents=True, exist_ok=True)
    return path


@dataclass(frozen=True)
class Measurement:
    """One timed command: wall time and the child's peak resident set."""

    seconds: float
    peak_rss_mb: float
    returncode: int
    cpu_seconds: float = float("nan")  #: user + system time of the command


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    """Smallest wall time of ``repeat`` calls, s."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


#: Runs the measured command as its own child and reports that child's wall time and rusage.
#: A process started straight from the benchmark inherits the benchmark's resident set as its
#: own peak (Linux keeps the pre-exec mm's high-water mark in ru_maxrss), so a benchmark that
#: holds a few hundred MB of arrays would see that in every command; this small launcher has a
#: resident set of about 10 MB, which bounds what it passes on.
_LAUNCHER = """
import os, subprocess, sys, time
report, args = sys.argv[1], sys.argv[2:]
start = time.perf_counter()
proc = subprocess.Popen(args, stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(proc.pid, 0)
seconds = time.perf_counter() - start
code = os.waitstatus_to_exitcode(status)
with open(report, "w") as handle:
    handle.write(f"{seconds} {usage.ru_maxrss} {usage.ru_utime + usage.ru_stime} {code}")
sys.exit(0)
"""


def run_command(args: list[str], *, drop_cache_of: Path | None = None, env: dict | None = None) -> Measurement:
    """Run a command in a fresh process: wall time, peak RSS (MB) and CPU time of that process alone."""
    import tempfile

    if drop_cache_of is not None:
        _evict(drop_cache_of)
    with tempfile.NamedTemporaryFile("r", suffix=".rusage") as report:
        proc = subprocess.run(
            [sys.executable, "-c", _LAUNCHER, report.name, *args], stderr=subprocess.PIPE, cwd=REPO, env=env
        )
        seconds, maxrss_kb, cpu, code = report.read().split()
    if int(code) != 0 or proc.returncode != 0:
        sys.stderr.write(proc.stderr.decode(errors="replace"))
    return Measurement(float(seconds), int(maxrss_kb) / 1024.0, int(code), float(cpu))


def _evict(path: Path) -> None:
    """Ask the kernel to drop the file's pages, so the read is uncached."""
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
    except (OSError, AttributeError):
        pass


def generate_h5(path: Path, n_samples: int, channels: tuple[str, ...] = ("dither", "deflection"), *, seed: int = 0) -> Path:
    """An afmtool-layout HDF5 capture of ``n_samples`` per channel, written in blocks.

    The dither is the three-sine REEP excitation at 70 kHz ± 6 kHz and the
    deflection the ZOH-sampled free-air response (f0 70 kHz, Q 200) plus
    0.05 nm of white noise, generated with ``lfilter`` and carried state so
    any length streams in bounded memory.
    """
    import h5py
    import numpy as np
    from scipy.signal import lfilter

    from afmtool.models.discretisation import discrete_denominator, zoh_numerator

    fs, f0, q = 500e3, 70e3, 200.0
    if path.exists() and path.stat().st_size > 0:
        with h5py.File(path) as f:
            if all(f"channels/{c}" in f and len(f[f"channels/{c}"]) == n_samples for c in channels):
                return path
    rng = np.random.default_rng(seed)
    denominator = discrete_denominator(f0, q, fs)
    numerator = zoh_numerator(f0, q, fs)
    b = [numerator.a2, numerator.a1, numerator.a0]
    a = [1.0, denominator.b1, denominator.b0]
    zi = np.zeros(2)
    amplitude = 25.0 / q
    block = 1 << 22
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = fs
        f.attrs["metadata"] = json.dumps({"free_air": {"start_s": 0.002, "end_s": 0.02}})
        datasets = {c: f.create_dataset(f"channels/{c}", shape=(n_samples,), dtype="f8") for c in channels}
        for c, ds in datasets.items():
            ds.attrs["units"] = "nm" if c in ("deflection", "z_piezo") else "V"
        for start in range(0, n_samples, block):
            n = min(block, n_samples - start)
            t = (start + np.arange(n)) / fs
            dither = amplitude * (
                np.sin(2 * np.pi * f0 * t)
                + 0.5 * np.sin(2 * np.pi * (f0 + 6e3) * t)
                + 0.5 * np.sin(2 * np.pi * (f0 - 6e3) * t)
            )
            deflection, zi = lfilter(b, a, dither, zi=zi)
            values = {"dither": dither, "deflection": deflection + 0.05 * rng.standard_normal(n)}
            if "z_piezo" in datasets:  # one triangular approach-retract to -30 nm over the capture
                values["z_piezo"] = -30.0 * (1.0 - np.abs(2.0 * (start + np.arange(n)) / n_samples - 1.0))
            for c, ds in datasets.items():
                ds[start : start + n] = values.get(c, dither)
    return path


def write_results(name: str, results: dict) -> None:
    path = REPO / "bench.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data[name] = results
    path.write_text(json.dumps(data, indent=2) + "\n")


def to_dict(m: Measurement) -> dict:
    return asdict(m)


