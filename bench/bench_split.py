"""Issue 19's table: every capture command end to end, one core against all, float32 and float64.

For reep, probeloss, decode and kalman-bank, at 1e6, 1e7 and 1e8 samples
(``AFMTOOL_BENCH_SPLIT_SIZES``), with the capture stored as float32 and as
float64 and held in the page cache (one untimed run reads it in first):
the whole process's time with ``--jobs 1`` and with every core, its MS/s
and peak RSS, beside

- the raw-read ceiling: h5py reading the same channels of the same file
  into float64, as the readers deliver them;
- the kernels alone: the command's per-sample recursions timed in this
  process on 2e6 in-memory samples, one core;
- the hash: XXH3-128 of the channels' float64 samples, as a share of the
  all-core run (target < 5 %).

Each time is the best of ``REPEATS`` runs.  The targets of the issue
(1e8 float32, all cores) close the printout; everything goes to
``bench.json`` under ``split``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import generate_h5, run_command, scratch_dir, to_dict, write_results

AFMTOOL = [sys.executable, "-m", "afmtool"]
REPEATS = int(os.environ.get("AFMTOOL_BENCH_SPLIT_REPEATS", "2"))
COMMANDS = ("reep", "probeloss", "decode", "kalman-bank")
#: MS/s targets of issue 19 at 1e8 float32 samples, all cores.
TARGETS = {"reep": 50.0, "probeloss": 80.0, "decode": 30.0, "kalman-bank": 20.0}
#: The channels each command reads (the raw-read ceiling and the hash read the same).
CHANNELS = {
    "reep": ("dither", "deflection"),
    "probeloss": ("dither", "deflection"),
    "decode": ("deflection", "v_sub", "v_r"),
    "kalman-bank": ("dither", "deflection", "z_piezo"),
}
_EXTRA = {"decode": ["--bit-rate", "30000"], "kalman-bank": ["--at-z=-5,-10,-15,-20,-25"]}

_RAW_READ = """
import sys, h5py, numpy as np
with h5py.File(sys.argv[1]) as f:
    for name in sys.argv[2:]:
        ds = f["channels"][name]
        buf = np.empty(1 << 20)
        for start in range(0, len(ds), 1 << 20):
            n = min(1 << 20, len(ds) - start)
            ds.read_direct(buf, np.s_[start:start + n], np.s_[:n])
"""


def capture(command: str, n: int, dtype: str) -> Path:
    """The command's generated capture of ``n`` samples stored as ``dtype`` (cached by name)."""
    scratch = scratch_dir()
    if command == "decode":
        from bench.bench_decode import generate_capture

        source = generate_capture(scratch / f"decode_{n}.h5", n)
    else:
        source = generate_h5(scratch / f"{'_'.join(CHANNELS[command])}_{n}.h5", n, CHANNELS[command])  # reep, probeloss share
    if dtype == "f8":
        return source
    return _as_float32(source, scratch / f"{source.stem}_f4.h5")


def _as_float32(source: Path, target: Path) -> Path:
    import h5py

    if target.exists():
        return target
    tmp = target.with_suffix(".tmp.h5")
    with h5py.File(source) as src, h5py.File(tmp, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        for name, ds in src["channels"].items():
            out = dst.create_dataset(f"channels/{name}", shape=ds.shape, dtype="f4")
            out.attrs.update(dict(ds.attrs))
            for start in range(0, len(ds), 1 << 22):
                out[start : start + (1 << 22)] = ds[start : start + (1 << 22)].astype(np.float32)
    os.replace(tmp, target)
    return target


def _best(args: list[str]) -> tuple:
    runs = [run_command(args) for _ in range(REPEATS)]
    return min(runs, key=lambda m: m.seconds), [m.seconds for m in runs]


def kernel_ms_per_s(command: str, n: int = 2_000_000) -> float:
    """The command's per-sample recursions alone, on one core, MS/s (compile time excluded)."""
    from afmtool.estimators.lockin import LockIn
    from afmtool.estimators.rls import ReepState, reep_update
    from afmtool.models.discretisation import zoh_numerator

    rng = np.random.default_rng(0)
    g = np.sin(2 * np.pi * 70e3 / 500e3 * np.arange(n))
    y = 0.5 * g + 0.05 * rng.standard_normal(n)
    numerator = tuple(zoh_numerator(70e3, 200.0, 500e3))
    lockin = LockIn(70e3, 500e3, 7e3)

    def reep():
        reep_update(ReepState.initial(), y, g, numerator, keep_every=7)
        lockin.process_against(y, g, lockin.initial_state(2), 7)

    def probeloss():
        from afmtool.estimators.observer import ObserverDesign, ObserverState
        from afmtool.estimators.reliability import ReliabilityState, reliability_update

        design = ObserverDesign.from_decay((-1.27, 0.9956), numerator, 4.0, 500e3 / 70e3)
        reliability_update(ReliabilityState(ObserverState.initial(design, 7), 1.0, (0.5, 0.7)), y, g, keep_every=7)
        lockin.process(y, lockin.initial_state(1), 7)

    def decode():
        from bench.bench_decode import bench_kernel

        return bench_kernel()["kernel_ms_per_s"]

    def kalman_bank():
        from afmtool.estimators.observer import BankState, ObserverDesign, bank_update

        designs = tuple(ObserverDesign.from_decay((-1.27 + 0.001 * k, 0.9956), numerator, 4.0, 7.14) for k in range(5))
        reep()  # pass 1
        reep_update(ReepState.initial(), y, g, numerator)
        bank_update(BankState.initial(designs, 70), y, g)

    if command == "decode":
        return decode()
    fn = {"reep": reep, "probeloss": probeloss, "kalman-bank": kalman_bank}[command]
    fn()  # compile or load the cache
    start = time.perf_counter()
    fn()
    return n / (time.perf_counter() - start) / 1e6


def hash_seconds(path: Path, channels: tuple[str, ...]) -> float:
    """XXH3-128 of the channels' float64 samples in 1 Mi chunks, as the read pass hashes them."""
    from afmtool.io.provenance import SampleDigest
    from afmtool.io.registry import open_capture

    with open_capture(path) as reader:
        chunks = list(reader.blocks(list(channels), 1 << 20)) if reader.info.n_samples <= 1 << 24 else None
        if chunks is None:  # large: time the hashing of one chunk and scale
            chunk = next(reader.blocks(list(channels), 1 << 20))
            digest = SampleDigest(channels)
            start = time.perf_counter()
            digest.update(chunk)
            return (time.perf_counter() - start) * reader.info.n_samples / len(chunk)
    digest = SampleDigest(channels)
    start = time.perf_counter()
    for chunk in chunks:
        digest.update(chunk)
    return time.perf_counter() - start


def bench_one(command: str, n: int, dtype: str, kernel_rate: float) -> dict:
    path = capture(command, n, dtype)
    out = scratch_dir() / f"split_out_{command}"
    args = [*AFMTOOL, command, str(path), "--out", str(out), "--quiet", *_EXTRA.get(command, [])]
    run_command(args)  # the file into the page cache, the numba cache loaded
    row: dict = {"command": command, "samples": n, "dtype": dtype}
    raw = run_command([sys.executable, "-c", _RAW_READ, str(path), *CHANNELS[command]])
    row["raw_read"] = to_dict(raw)
    for jobs in ("1", "all"):
        measured, all_seconds = _best([*args, *(["--jobs", "1"] if jobs == "1" else [])])
        row[f"jobs_{jobs}"] = {**to_dict(measured), "all_seconds": all_seconds, "ms_per_s": n / measured.seconds / 1e6}
    best = row["jobs_all"]
    row["split_speedup"] = row["jobs_1"]["seconds"] / best["seconds"]
    row["fraction_of_read_ceiling"] = raw.seconds / best["seconds"]
    row["kernel_ms_per_s"] = kernel_rate
    row["fraction_of_kernel"] = best["ms_per_s"] / kernel_rate
    row["hash_share"] = hash_seconds(path, CHANNELS[command]) / best["seconds"]
    print(f"{command:12s} {n:8.0e} {dtype}  jobs 1: {row['jobs_1']['ms_per_s']:6.1f} MS/s  all: {best['ms_per_s']:6.1f} MS/s "
          f"({row['split_speedup']:.2f}x)  RSS {best['peak_rss_mb']:4.0f} MB  read ceiling {n / raw.seconds / 1e6:6.0f} MS/s "
          f"({row['fraction_of_read_ceiling']:.1%})  kernels {kernel_rate:5.1f} MS/s ({row['fraction_of_kernel']:.0%})  "
          f"hash {row['hash_share']:.1%}", flush=True)
    return row


def main() -> dict:
    sizes = [int(s) for s in os.environ.get("AFMTOOL_BENCH_SPLIT_SIZES", "1000000,10000000,100000000").split(",")]
    commands = [c for c in COMMANDS if c in os.environ.get("AFMTOOL_BENCH_SPLIT_COMMANDS", ",".join(COMMANDS))]
    rows = []
    for command in commands:
        kernel_rate = kernel_ms_per_s(command)
        for n in sizes:
            for dtype in ("f4", "f8"):
                rows.append(bench_one(command, n, dtype, kernel_rate))
    largest = max(sizes)
    summary = {}
    print(f"\ntargets at {largest:.0e} float32 samples, all cores:")
    for command in commands:
        row = next(r for r in rows if r["command"] == command and r["samples"] == largest and r["dtype"] == "f4")
        small = next(r for r in rows if r["command"] == command and r["samples"] == min(sizes) and r["dtype"] == "f4")
        rss_ratio = row["jobs_all"]["peak_rss_mb"] / small["jobs_all"]["peak_rss_mb"]
        summary[command] = {"ms_per_s": row["jobs_all"]["ms_per_s"], "target_ms_per_s": TARGETS[command],
                            "peak_rss_mb": row["jobs_all"]["peak_rss_mb"], "rss_ratio_largest_to_smallest": rss_ratio,
                            "split_speedup": row["split_speedup"], "hash_share": row["hash_share"]}
        verdict = "pass" if row["jobs_all"]["ms_per_s"] >= TARGETS[command] else "FAIL"
        print(f"  {command:12s} {row['jobs_all']['ms_per_s']:6.1f} MS/s (target {TARGETS[command]:g}, {verdict}); "
              f"peak RSS {row['jobs_all']['peak_rss_mb']:.0f} MB (< 300: {'pass' if row['jobs_all']['peak_rss_mb'] < 300 else 'FAIL'}), "
              f"RSS ratio {rss_ratio:.2f} (<= 1.2: {'pass' if rss_ratio <= 1.2 else 'FAIL'}); split {row['split_speedup']:.2f}x "
              f"(>= 1.8: {'pass' if row['split_speedup'] >= 1.8 else 'FAIL'}); hash {row['hash_share']:.1%} "
              f"(< 5 %: {'pass' if row['hash_share'] < 0.05 else 'FAIL'})")
    results = {"rows": rows, "summary": summary, "cores": len(os.sched_getaffinity(0))}
    write_results("split", results)
    return results


if __name__ == "__main__":
    main()
