"""Probe-loss end to end: `afmtool probeloss` on generated two-channel HDF5 captures.

Reports MS/s (input samples per second, per channel) of the whole command
(start-up, reading, observer, index, lock-in, events, outputs and the
sha256 of the input that report.json records), its CPU time and peak RSS,
and beside it what bounds it: the raw h5py read of the same file (the I/O
ceiling), the sha256 of the file alone and the imports alone, at 1e6, 1e7
and 1e8 samples so that linear time and flat memory show.  Other processes
share the machine's CPUs: the load average before each size is recorded.  The captures are generate_h5's
(three-sine dither, free-air response, metadata free_air), shared with
bench_reep; with no set point in them the amplitude baseline gets
``--setpoint 20`` (nm).
"""

from __future__ import annotations

import os
import shutil
import sys

from bench.bench_io import _RAW_READ
from bench.common import generate_h5, run_command, scratch_dir, to_dict, write_results

AFMTOOL = [sys.executable, "-m", "afmtool"]
TARGET_MS_PER_S = 50.0


#: sha256 of the file, as report.json records it (afmtool.report.json_report.sha256_file).
_HASH = "import sys\nfrom afmtool.report.json_report import sha256_file\nprint(sha256_file(sys.argv[1]))"
#: What the command imports before it reads a sample (interpreter start-up included).
_IMPORTS = (
    "import afmtool.cli.main, afmtool.analyses.probeloss_outputs, afmtool.analyses.probeloss, "
    "afmtool.estimators.reliability, afmtool.estimators.rls, afmtool.estimators.lockin, scipy.signal"
)


def _timed(args: list[str], drop_cache_of=None) -> tuple[dict, float]:
    """run_command's wall time, peak RSS and CPU time (user + system) of the command."""
    measured = run_command(args, drop_cache_of=drop_cache_of)
    return to_dict(measured), measured.seconds


def bench_size(n: int) -> dict:
    path = generate_h5(scratch_dir() / f"reep_{n}.h5", n)
    out = scratch_dir() / f"probeloss_out_{n}"
    command = [*AFMTOOL, "probeloss", str(path), "--out", str(out), "--setpoint", "20", "--quiet"]
    shutil.rmtree(out, ignore_errors=True)
    # one warm-up run so the numba cache is compiled before timing
    run_command(command)
    shutil.rmtree(out, ignore_errors=True)
    load = os.getloadavg()[0]
    raw, _ = _timed([sys.executable, "-c", _RAW_READ, str(path)], drop_cache_of=path)
    sha, _ = _timed([sys.executable, "-c", _HASH, str(path)], drop_cache_of=path)
    imports, _ = _timed([sys.executable, "-c", _IMPORTS])
    runs = []
    for _ in range(2):
        runs.append(_timed(command, drop_cache_of=path)[0])
        shutil.rmtree(out, ignore_errors=True)
    best = min(runs, key=lambda m: m["seconds"])
    rate = n / best["seconds"] / 1e6
    print(
        f"probeloss {n:.0e} samples: {best['seconds']:.2f} s = {rate:.1f} MS/s (CPU {best['cpu_seconds']:.2f} s), "
        f"peak RSS {best['peak_rss_mb']:.0f} MB; raw read {raw['seconds']:.2f} s, sha256 {sha['seconds']:.2f} s, "
        f"imports {imports['seconds']:.2f} s; load average {load:.1f} on {os.cpu_count()} CPUs"
    )
    return {"samples": n, "probeloss": best, "raw_read": raw, "sha256": sha, "imports": imports, "ms_per_s": rate,
            "fraction_of_read_ceiling": raw["seconds"] / best["seconds"], "load_average_before": load,
            "cpus": os.cpu_count()}


def main() -> dict:
    sizes = [int(s) for s in os.environ.get("AFMTOOL_BENCH_PROBELOSS_SIZES", "1000000,10000000,100000000").split(",")]
    runs = [bench_size(n) for n in sizes]
    largest, smallest = runs[-1], runs[0]
    results = {
        "runs": runs,
        "largest_ms_per_s": largest["ms_per_s"],
        "largest_peak_rss_mb": largest["probeloss"]["peak_rss_mb"],
        "largest_cpu_seconds": largest["probeloss"]["cpu_seconds"],
        "rss_ratio_largest_to_smallest": largest["probeloss"]["peak_rss_mb"] / smallest["probeloss"]["peak_rss_mb"],
        "target_ms_per_s": TARGET_MS_PER_S,
        "pass_50_ms_per_s": largest["ms_per_s"] >= TARGET_MS_PER_S,
        "pass_flat_memory": largest["probeloss"]["peak_rss_mb"] < 1.5 * smallest["probeloss"]["peak_rss_mb"],
    }
    write_results("probeloss", results)
    return results


if __name__ == "__main__":
    main()
