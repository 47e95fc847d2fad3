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


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    """Smallest wall time of ``repeat`` calls, s."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def run_command(args: list[str], *, drop_cache_of: Path | None = None) -> Measurement:
    """Run a command in a fresh process; peak RSS from wait4's rusage (MB)."""
    if drop_cache_of is not None:
        _evict(drop_cache_of)
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr.read().decode())
    return Measurement(seconds, usage.ru_maxrss / 1024.0, proc.returncode)


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
    """An afmtool-layout HDF5 capture of ``n_samples`` per channel, written in blocks."""
    import h5py
    import numpy as np

    if path.exists() and path.stat().st_size > 0:
        with h5py.File(path) as f:
            if all(len(f[f"channels/{c}"]) == n_samples for c in channels if f"channels/{c}" in f):
                return path
    rng = np.random.default_rng(seed)
    fs = 500e3
    block = 1 << 22
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = fs
        f.attrs["metadata"] = json.dumps({"free_air": {"start_s": 0.0, "end_s": 0.02}})
        datasets = {c: f.create_dataset(f"channels/{c}", shape=(n_samples,), dtype="f8") for c in channels}
        for c, ds in datasets.items():
            ds.attrs["units"] = "nm" if c == "deflection" else "V"
        phase_step = 2 * np.pi * 70e3 / fs
        for start in range(0, n_samples, block):
            n = min(block, n_samples - start)
            k = start + np.arange(n)
            base = np.sin(phase_step * k)
            for c, ds in datasets.items():
                ds[start : start + n] = (25.0 if c == "deflection" else 0.125) * base + 0.05 * rng.standard_normal(n)
    return path


def write_results(name: str, results: dict) -> None:
    path = REPO / "bench.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data[name] = results
    path.write_text(json.dumps(data, indent=2) + "\n")


def to_dict(m: Measurement) -> dict:
    return asdict(m)


