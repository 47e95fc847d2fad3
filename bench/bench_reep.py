"""REEP end to end: `afmtool reep` on generated two-channel HDF5 captures.

Reports MS/s (input samples per second, per channel), peak RSS, and the
ratio to the raw h5py read of the same file (the I/O ceiling), at 1e6, 1e7
and 1e8 samples so that linear time and flat memory show.
"""

from __future__ import annotations

import os
import shutil
import sys

from bench.bench_io import _RAW_READ
from bench.common import generate_h5, run_command, scratch_dir, to_dict, write_results

AFMTOOL = [sys.executable, "-m", "afmtool"]


def bench_size(n: int) -> dict:
    path = generate_h5(scratch_dir() / f"reep_{n}.h5", n)
    out = scratch_dir() / f"reep_out_{n}"
    shutil.rmtree(out, ignore_errors=True)
    # one warm-up run so the numba cache is compiled before timing
    run_command([*AFMTOOL, "reep", str(path), "--out", str(out), "--quiet"])
    shutil.rmtree(out, ignore_errors=True)
    raw = run_command([sys.executable, "-c", _RAW_READ, str(path)], drop_cache_of=path)
    reep = run_command([*AFMTOOL, "reep", str(path), "--out", str(out), "--quiet"], drop_cache_of=path)
    shutil.rmtree(out, ignore_errors=True)
    rate = n / reep.seconds / 1e6
    print(
        f"reep {n:.0e} samples: {reep.seconds:.2f} s = {rate:.1f} MS/s, peak RSS {reep.peak_rss_mb:.0f} MB; "
        f"raw read {raw.seconds:.2f} s; reep at {raw.seconds / reep.seconds:.1%} of the read ceiling"
    )
    return {"samples": n, "reep": to_dict(reep), "raw_read": to_dict(raw), "ms_per_s": rate,
            "fraction_of_read_ceiling": raw.seconds / reep.seconds}


def main() -> dict:
    sizes = [int(s) for s in os.environ.get("AFMTOOL_BENCH_REEP_SIZES", "1000000,10000000,100000000").split(",")]
    runs = [bench_size(n) for n in sizes]
    largest, smallest = runs[-1], runs[0]
    results = {
        "runs": runs,
        "largest_ms_per_s": largest["ms_per_s"],
        "largest_peak_rss_mb": largest["reep"]["peak_rss_mb"],
        "rss_ratio_largest_to_smallest": largest["reep"]["peak_rss_mb"] / smallest["reep"]["peak_rss_mb"],
        "pass_20_ms_per_s": largest["ms_per_s"] >= 20.0,
        "pass_rss_under_400_mb": largest["reep"]["peak_rss_mb"] < 400.0,
    }
    write_results("reep", results)
    return results


if __name__ == "__main__":
    main()
