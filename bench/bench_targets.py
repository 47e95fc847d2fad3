"""Issue 33's targets table from one run, with the Hilbert-transform baseline beside REEP.

Every capture command end to end on a float32 capture in the page cache
(``AFMTOOL_BENCH_TARGET_SAMPLES``, default 1e7: the issue's figures are at
1e8, which this shared 2-core machine cannot time meaningfully; RSS and
output size scale from it as stated in the table), all cores and
``--jobs 1``, beside the raw read of the same file; peak RSS against the
run at 1e6; reep's output size; ``reep sample_data/ltv_step.h5`` and
``afmtool --help`` as whole processes with a warm numba cache; and the
baseline a scientist would otherwise run for a resonance frequency over time
(what FreqDemod and FFTA do): ``scipy.signal.hilbert`` of the deflection,
unwrap the phase, differentiate, low-pass over the same 400 µs
(an exponential average with REEP's forgetting window), rows at REEP's
spacing, written as float32 HDF5.  Its MS/s and peak RSS, its f0
scatter in free air beside REEP's (REEP also gives Q′), and what each reads
of a resonance step under a fixed drive (``sample_data/ltv_step.h5``).

Writes ``bench.json`` under ``targets`` and prints the table.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from bench.bench_split import _EXTRA, _RAW_READ, CHANNELS, capture
from bench.common import REPO, run_command, scratch_dir, to_dict, write_results

AFMTOOL = [sys.executable, "-m", "afmtool"]
COMMANDS = ("reep", "probeloss", "decode", "kalman-bank")
REPEATS = int(os.environ.get("AFMTOOL_BENCH_TARGET_REPEATS", "2"))
#: REEP's default forgetting window, s: the Hilbert baseline's low-pass and both scatters' warm-up use it.
WINDOW_S = 400e-6

#: The Hilbert-transform demodulation, as a peer would write it: the whole record in memory.
_HILBERT = """
import sys, h5py, numpy as np
from scipy.signal import hilbert, lfilter
path, out, window_s, row_every = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
with h5py.File(path) as f:
    fs = float(f.attrs["sample_rate_hz"])
    y = f["channels/deflection"][()].astype(np.float64)
y -= y.mean()
phase = np.unwrap(np.angle(hilbert(y)))
frequency = np.diff(phase) * (fs / (2.0 * np.pi))
lam = 1.0 - 1.0 / (window_s * fs)
f0 = lfilter([1.0 - lam], [1.0, -lam], frequency)
with h5py.File(out, "w") as f:
    f.attrs["row_every_samples"] = row_every
    f.attrs["sample_rate_hz"] = fs
    f.create_dataset("f0_hz", data=f0[row_every - 1 :: row_every].astype(np.float32))
"""


def _best(args: list[str]):
    runs = [run_command(args) for _ in range(REPEATS)]
    return min(runs, key=lambda m: m.seconds)


def _size_mb(folder: Path, name: str) -> float:
    path = folder / name
    return path.stat().st_size / 1e6 if path.exists() else float("nan")


def bench_command(command: str, n: int, small: int) -> dict:
    """One command at ``n`` (all cores and --jobs 1) and at ``small`` (RSS), beside the raw read."""
    path = capture(command, n, "f4")
    out = scratch_dir() / f"targets_{command}"
    args = [*AFMTOOL, command, str(path), "--out", str(out), "--quiet", *_EXTRA.get(command, [])]
    run_command(args)  # the file into the page cache, the numba cache loaded
    raw = run_command([sys.executable, "-c", _RAW_READ, str(path), *CHANNELS[command]])
    every = _best(args)
    outputs = {p.name: p.stat().st_size / 1e6 for p in out.glob("*.h5")}
    one = _best([*args, "--jobs", "1"])
    small_path = capture(command, small, "f4")
    small_args = [*AFMTOOL, command, str(small_path), "--out", str(scratch_dir() / f"targets_{command}_small"),
                  "--quiet", *_EXTRA.get(command, [])]
    run_command(small_args)
    small_run = _best(small_args)
    row = {
        "samples": n, "all_cores": to_dict(every), "jobs_1": to_dict(one), "raw_read": to_dict(raw),
        "ms_per_s": n / every.seconds / 1e6, "split_speedup": one.seconds / every.seconds,
        "time_over_raw_read": every.seconds / raw.seconds, "peak_rss_mb": every.peak_rss_mb,
        "rss_ratio_to_small": every.peak_rss_mb / small_run.peak_rss_mb, "small_samples": small,
        "small_peak_rss_mb": small_run.peak_rss_mb, "output_mb": outputs,
    }
    print(f"{command:12s} {n:.0e} f4: {row['ms_per_s']:6.1f} MS/s all cores, {n / one.seconds / 1e6:6.1f} MS/s --jobs 1 "
          f"({row['split_speedup']:.2f}x); {row['time_over_raw_read']:.1f}x the raw read ({raw.seconds:.2f} s); "
          f"RSS {every.peak_rss_mb:.0f} MB ({row['rss_ratio_to_small']:.2f}x at {small:.0e}); "
          f"outputs {', '.join(f'{k} {v:.1f} MB' for k, v in outputs.items())}", flush=True)
    return row


def _scatter(values, row_every: int, fs: float) -> dict:
    """Mean and std of a free-air f0 series after five windows (REEP's warm-up), Hz."""
    import numpy as np

    start = int(np.ceil(5 * WINDOW_S * fs / row_every))
    settled = np.asarray(values[start:], dtype=np.float64)
    settled = settled[np.isfinite(settled)]
    return {"mean_hz": float(settled.mean()), "std_hz": float(settled.std(ddof=1)), "rows": int(settled.size)}


def bench_hilbert(n: int) -> dict:
    """The Hilbert baseline and REEP on the same free-air capture: MS/s, peak RSS, f0 scatter at one row spacing."""
    import h5py

    path = capture("reep", n, "f4")
    reep_out = scratch_dir() / "targets_reep"  # bench_command("reep") wrote it from this very capture
    with h5py.File(reep_out / "reep.h5") as f:
        row_every, fs = int(f.attrs["row_every_samples"]), float(f.attrs["sample_rate_hz"])
        flag = f["flag"][()]
        f0 = f["f0_hz"][()].astype("f8")
        f0[flag != 0] = float("nan")
        reep = _scatter(f0, row_every, fs)
    target = scratch_dir() / "hilbert_f0.h5"
    args = [sys.executable, "-c", _HILBERT, str(path), str(target), str(WINDOW_S), str(row_every)]
    run_command(args)
    measured = _best(args)
    with h5py.File(target) as f:
        hilbert = _scatter(f["f0_hz"][()], row_every, fs)
    row = {"samples": n, "hilbert": {**to_dict(measured), "ms_per_s": n / measured.seconds / 1e6, **hilbert},
           "reep_scatter": reep, "window_us": WINDOW_S * 1e6, "row_every_samples": row_every}
    print(f"hilbert      {n:.0e} f4: {row['hilbert']['ms_per_s']:6.1f} MS/s, RSS {measured.peak_rss_mb:.0f} MB; "
          f"free-air f0 {hilbert['mean_hz']:.2f} +- {hilbert['std_hz']:.3f} Hz (REEP {reep['mean_hz']:.2f} +- "
          f"{reep['std_hz']:.3f} Hz, and Q'); the Hilbert phase follows the drive, not the resonance", flush=True)
    return row


def bench_hilbert_step() -> dict:
    """Both methods on ``sample_data/ltv_step.h5``: f0 steps 70000 -> 69650 Hz under a fixed three-sine drive.

    The Hilbert phase rate follows the drive, so it reads the drive's frequency before and after the
    step; REEP reads the resonance.  Means over each side, from five windows after the start and
    after the step (bench_start's reep run of the same file gives REEP's rows).
    """
    import h5py
    import numpy as np

    path = REPO / "sample_data" / "ltv_step.h5"
    with h5py.File(path) as f:
        truth = f["truth/f0_hz"][()]
        fs = float(f.attrs["sample_rate_hz"])
    step = int(np.flatnonzero(np.diff(truth))[0]) + 1
    with h5py.File(scratch_dir() / "targets_ltv" / "reep.h5") as f:
        row_every = int(f.attrs["row_every_samples"])
        reep_f0 = f["f0_hz"][()].astype("f8")
        reep_f0[f["flag"][()] != 0] = np.nan
    target = scratch_dir() / "hilbert_step_f0.h5"
    run_command([sys.executable, "-c", _HILBERT, str(path), str(target), str(WINDOW_S), str(row_every)])
    with h5py.File(target) as f:
        hilbert_f0 = f["f0_hz"][()].astype("f8")
    settle = int(np.ceil(5 * WINDOW_S * fs))

    def sides(f0: np.ndarray) -> tuple[float, float]:
        sample = (np.arange(len(f0)) + 1) * row_every - 1  # each row's last sample
        before = f0[(sample >= settle) & (sample < step)]
        after = f0[sample >= step + settle]
        return float(np.nanmean(before)), float(np.nanmean(after))

    reep, hilbert = sides(reep_f0), sides(hilbert_f0)
    row = {"truth_hz": [float(truth[0]), float(truth[-1])], "reep_hz": list(reep), "hilbert_hz": list(hilbert)}
    print(f"f0 step     ltv_step.h5 (truth {truth[0]:.0f} -> {truth[-1]:.0f} Hz): REEP {reep[0]:.1f} -> {reep[1]:.1f} Hz, "
          f"Hilbert {hilbert[0]:.1f} -> {hilbert[1]:.1f} Hz (its phase rate is the drive's)", flush=True)
    return row


def bench_start() -> dict:
    """``reep sample_data/ltv_step.h5`` and ``afmtool --help`` as whole processes, warm caches; best of 3.

    Warm: the numba cache, and afmtool's bytecode, which ``pip install .`` compiles but an editable
    install run with PYTHONDONTWRITEBYTECODE (as on this machine) never writes: compiling afmtool's
    sources on every start added 0.2 s of CPU to the reep run here.
    """
    import importlib.util
    import subprocess

    (package,) = importlib.util.find_spec("afmtool").submodule_search_locations
    subprocess.run([sys.executable, "-m", "compileall", "-q", package], check=True, stdout=subprocess.DEVNULL)
    out = scratch_dir() / "targets_ltv"
    reep_args = [*AFMTOOL, "reep", str(REPO / "sample_data" / "ltv_step.h5"), "--out", str(out), "--quiet"]
    run_command(reep_args)
    reep = min((run_command(reep_args) for _ in range(3)), key=lambda m: m.seconds)
    help_run = min((run_command([*AFMTOOL, "--help"]) for _ in range(3)), key=lambda m: m.seconds)
    print(f"start: reep ltv_step.h5 {reep.seconds:.2f} s, afmtool --help {help_run.seconds:.3f} s", flush=True)
    return {"reep_ltv_step_seconds": reep.seconds, "help_seconds": help_run.seconds}


def targets_table(results: dict) -> list[tuple[str, str, str, bool]]:
    """(target, measured, scale note, pass) rows of the issue's table."""
    c, n = results["commands"], results["samples"]
    scale = 1e8 / n
    reep, hilbert = c.get("reep"), results.get("hilbert")
    rows = []

    def add(label, value, text, ok, note=""):
        if value is not None:
            rows.append((label, text, note, bool(ok)))

    if reep:
        add("reep end to end >= 45 MS/s, <= 8x the raw read", reep["ms_per_s"],
            f"{reep['ms_per_s']:.1f} MS/s, {reep['time_over_raw_read']:.1f}x",
            reep["ms_per_s"] >= 45 and reep["time_over_raw_read"] <= 8)
    for command, target in (("probeloss", 60), ("decode", 30), ("kalman-bank", 15)):
        if command in c:
            add(f"{command} end to end >= {target} MS/s", 1, f"{c[command]['ms_per_s']:.1f} MS/s",
                c[command]["ms_per_s"] >= target)
    if reep:
        size = reep["output_mb"].get("reep.h5", float("nan")) * scale
        add("reep output at 1e8 <= 150 MB", 1, f"{size:.0f} MB", size <= 150, f"x{scale:g} from {n:.0e}")
    if c:
        worst = max(c, key=lambda k: c[k]["peak_rss_mb"])
        add("peak RSS, largest process < 350 MB", 1, f"{c[worst]['peak_rss_mb']:.0f} MB ({worst})",
            c[worst]["peak_rss_mb"] < 350, f"at {n:.0e}")
        ratio = max(c, key=lambda k: c[k]["rss_ratio_to_small"])
        add(f"RSS at {n:.0e} / RSS at 1e6 <= 1.2", 1, f"{c[ratio]['rss_ratio_to_small']:.2f} ({ratio})",
            c[ratio]["rss_ratio_to_small"] <= 1.2)
        for command in ("reep", "probeloss", "decode"):
            if command in c:
                add(f"split against --jobs 1 >= 1.6x ({command})", 1, f"{c[command]['split_speedup']:.2f}x",
                    c[command]["split_speedup"] >= 1.6)
    start = results.get("start")
    if start:
        add("reep ltv_step.h5 < 1.0 s / --help < 0.25 s", 1,
            f"{start['reep_ltv_step_seconds']:.2f} s / {start['help_seconds']:.3f} s",
            start["reep_ltv_step_seconds"] < 1.0 and start["help_seconds"] < 0.25)
    if reep and hilbert:
        h, r = hilbert["hilbert"], hilbert["reep_scatter"]
        add("reep against the Hilbert baseline: faster, lower f0 scatter", 1,
            f"{reep['ms_per_s']:.1f} vs {h['ms_per_s']:.1f} MS/s; {r['std_hz']:.3f} vs {h['std_hz']:.3f} Hz",
            reep["ms_per_s"] > h["ms_per_s"] and r["std_hz"] < h["std_hz"], "same capture, 400 us")
    step = results.get("hilbert_step")
    if step:
        truth, reep_step, hilbert_step = (v[1] - v[0] for v in (step["truth_hz"], step["reep_hz"], step["hilbert_hz"]))
        add("f0 step read (ltv_step.h5, fixed drive)", 1,
            f"truth {truth:+.0f} Hz: REEP {reep_step:+.1f}, Hilbert {hilbert_step:+.1f} Hz",
            abs(reep_step - truth) < 0.05 * abs(truth), "Hilbert reads the drive")
    return rows


def main() -> dict:
    n = int(float(os.environ.get("AFMTOOL_BENCH_TARGET_SAMPLES", "1e7")))
    small = int(float(os.environ.get("AFMTOOL_BENCH_TARGET_SMALL", "1e6")))
    only = os.environ.get("AFMTOOL_BENCH_TARGET_COMMANDS", ",".join(COMMANDS)).split(",")
    results: dict = {"samples": n, "cores": len(os.sched_getaffinity(0)), "load_average": os.getloadavg()[0],
                     "commands": {}}
    for command in COMMANDS:
        if command in only:
            results["commands"][command] = bench_command(command, n, small)
    if "reep" in results["commands"]:
        results["hilbert"] = bench_hilbert(n)
    results["start"] = bench_start()
    results["hilbert_step"] = bench_hilbert_step()
    table = targets_table(results)
    results["table"] = [{"target": t, "measured": m, "note": note, "pass": ok} for t, m, note, ok in table]
    print(f"\nissue 33 targets ({n:.0e} float32 samples in the page cache, {results['cores']} cores, "
          f"load {results['load_average']:.1f}):")
    width = max(len(t) for t, *_ in table) if table else 0
    for target, measured, note, ok in table:
        print(f"  {target:<{width}}  {measured:<34} {'pass' if ok else 'FAIL'}  {note}")
    write_results("targets", results)
    return results


if __name__ == "__main__":
    main()
