"""Foundation benchmarks: `afmtool info` on a 2 GB capture (RSS) and --help start-up."""

from __future__ import annotations

import os
import sys

from bench.common import generate_h5, run_command, scratch_dir, to_dict, write_results

AFMTOOL = [sys.executable, "-m", "afmtool"]


def bench_info_2gb() -> dict:
    n = int(os.environ.get("AFMTOOL_BENCH_INFO_SAMPLES", 125_000_000))  # 2 channels x 8 B = 2 GB
    path = generate_h5(scratch_dir() / f"info_{n}.h5", n)
    size_gb = path.stat().st_size / 1e9
    raw = run_command([sys.executable, "-c", _RAW_READ, str(path)], drop_cache_of=path)
    info = run_command([*AFMTOOL, "info", str(path), "--quiet"], drop_cache_of=path)
    result = {
        "file_gb": size_gb,
        "samples_per_channel": n,
        "raw_h5py_read": to_dict(raw),
        "afmtool_info": to_dict(info),
        "info_ms_per_s": 2 * n / info.seconds / 1e6,
        "raw_read_ms_per_s": 2 * n / raw.seconds / 1e6,
        "ratio_info_to_raw_read": raw.seconds / info.seconds,
        "pass_rss_under_300mb": info.peak_rss_mb < 300,
    }
    print(
        f"info on {size_gb:.2f} GB: {info.seconds:.2f} s, peak RSS {info.peak_rss_mb:.0f} MB "
        f"(raw h5py read {raw.seconds:.2f} s; info at {result['ratio_info_to_raw_read']:.2f}x raw speed)"
    )
    return result


_RAW_READ = """
import sys, h5py, numpy as np
with h5py.File(sys.argv[1]) as f:
    for ds in f["channels"].values():
        buf = np.empty(1 << 20)
        for start in range(0, len(ds), 1 << 20):
            stop = min(start + (1 << 20), len(ds))
            ds.read_direct(buf, np.s_[start:stop], np.s_[0:stop - start])
"""


def bench_help() -> dict:
    runs = [run_command([*AFMTOOL, "--help"]) for _ in range(5)]
    baseline = [run_command([sys.executable, "-c", "pass"]) for _ in range(5)]
    best = min(r.seconds for r in runs)
    python_start = min(r.seconds for r in baseline)
    print(f"afmtool --help: {best * 1e3:.0f} ms (bare python start-up {python_start * 1e3:.0f} ms)")
    heavy = run_command([sys.executable, "-c", _HEAVY_CHECK])
    return {
        "help_seconds": best,
        "python_startup_seconds": python_start,
        "ratio_to_python_startup": best / python_start,
        "pass_under_0_3_s": best < 0.3,
        "imports_no_heavy_modules": heavy.returncode == 0,
    }


_HEAVY_CHECK = """
import sys
sys.argv = ["afmtool", "--help"]
from afmtool.cli.main import main
try:
    main()
except SystemExit:
    pass
heavy = [m for m in ("scipy", "numba", "matplotlib", "numpy", "h5py") if m in sys.modules]
sys.exit(1 if heavy else 0)
"""


def bench_numba_cache() -> dict:
    """First-call cost: `afmtool reep` on a tiny capture with an empty numba cache, then warm."""
    import tempfile

    path = generate_h5(scratch_dir() / "tiny_100000.h5", 100_000)
    cache = tempfile.mkdtemp(prefix="numba-cache-")
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    out = scratch_dir() / "tiny_out"
    args = [*AFMTOOL, "reep", str(path), "--out", str(out), "--quiet"]
    cold = run_command(args, env=env)
    warm = run_command(args, env=env)
    print(f"reep on 1e5 samples: {cold.seconds:.2f} s with an empty numba cache, {warm.seconds:.2f} s cached")
    return {"cold_seconds": cold.seconds, "warm_seconds": warm.seconds, "first_call_cost_seconds": cold.seconds - warm.seconds}


def main() -> dict:
    results = {"help": bench_help(), "numba_cache": bench_numba_cache(), "info_2gb": bench_info_2gb()}
    write_results("io", results)
    return results


if __name__ == "__main__":
    main()
