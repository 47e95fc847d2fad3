"""Run every benchmark: ``python -m bench [NAME ...]`` from the repository root.

Prints each module's numbers as it goes, then one table of the acceptance
criteria with the values measured in this run, and writes ``bench.json``.
"""

from __future__ import annotations

import importlib
import json
import sys

from bench.common import REPO

MODULES = [
    "bench.bench_io",
    "bench.bench_rls",
    "bench.bench_observer",
    "bench.bench_reep",
    "bench.bench_decode",
    "bench.bench_kalman_bank",
    "bench.bench_probeloss",
    "bench.bench_split",
    "bench.bench_targets",
]

#: (bench.json section, key path, criterion, test) rows of the closing table.
CRITERIA = [
    ("io", "help.help_seconds", "afmtool --help < 0.15 s", lambda v: v < 0.15),
    ("io", "info_2gb.afmtool_info.peak_rss_mb", "info on 2 GB: peak RSS < 300 MB", lambda v: v < 300),
    ("rls", "kernel_ms_per_s", "REEP kernel >= 50 MS/s", lambda v: v >= 50),
    ("rls", "ratio_kernel_to_padasip", "REEP >= 300x padasip RLS", lambda v: v >= 300),
    ("rls", "ratio_kernel_to_pure_python", "REEP vs pure Python (ratio)", lambda v: v > 1),
    ("observer", "bank5_kernel_ms_per_s", "bank of 5 >= 40 MS/s", lambda v: v >= 40),
    ("observer", "ratio_bank5_kernel_to_5_filterpy", "bank of 5 >= 500x filterpy", lambda v: v >= 500),
    ("reep", "largest_ms_per_s", "reep end to end >= 20 MS/s", lambda v: v >= 20),
    ("reep", "largest_peak_rss_mb", "reep peak RSS < 400 MB", lambda v: v < 400),
    ("reep", "rss_ratio_largest_to_smallest", "reep RSS at 1e8 <= 1.5x RSS at 1e6", lambda v: v <= 1.5),
    ("reep", "runs.-1.fraction_of_read_ceiling", "reep >= 5% of the raw-read ceiling", lambda v: v >= 0.05),
    ("probeloss", "largest_ms_per_s", "probeloss end to end >= 50 MS/s", lambda v: v >= 50),
    ("probeloss", "rss_ratio_largest_to_smallest", "probeloss RSS at 1e8 <= 1.5x RSS at 1e6", lambda v: v <= 1.5),
    ("probeloss", "runs.-1.fraction_of_read_ceiling", "probeloss >= 5% of the raw-read ceiling", lambda v: v >= 0.05),
    ("kalman_bank", "bank5_streaming_ms_per_s", "kalman-bank: bank of 5 streaming >= 40 MS/s", lambda v: v >= 40),
    ("kalman_bank", "ratio_bank5_to_filterpy_bank5", "kalman-bank: bank of 5 >= 500x filterpy", lambda v: v >= 500),
    ("kalman_bank", "rss_ratio_largest_to_smallest", "kalman-bank RSS at 1e8 <= 1.5x RSS at 1e6", lambda v: v <= 1.5),
    ("kalman_bank", "fraction_of_read_ceiling", "kalman-bank >= 5% of the raw-read ceiling", lambda v: v >= 0.05),
    ("decode", "kernel_ms_per_s", "EKF kernel >= 30 MS/s", lambda v: v >= 30),
    ("decode", "ratio_kernel_to_pure_python", "EKF vs pure Python (ratio)", lambda v: v > 1),
    ("decode", "largest_ms_per_s", "decode end to end >= 15 MS/s", lambda v: v >= 15),
    ("decode", "rss_ratio_largest_to_smallest", "decode RSS at 1e8 <= 1.5x RSS at 1e6", lambda v: v <= 1.5),
    ("decode", "fraction_of_read_ceiling", "decode >= 5% of the raw-read ceiling", lambda v: v >= 0.05),
    # issue 19: 1e8 float32 samples in the page cache, all cores (bench_split)
    ("split", "summary.reep.ms_per_s", "reep end to end >= 50 MS/s (all cores)", lambda v: v >= 50),
    ("split", "summary.probeloss.ms_per_s", "probeloss end to end >= 80 MS/s (all cores)", lambda v: v >= 80),
    ("split", "summary.decode.ms_per_s", "decode end to end >= 30 MS/s (all cores)", lambda v: v >= 30),
    ("split", "summary.kalman-bank.ms_per_s", "kalman-bank end to end >= 20 MS/s (all cores)", lambda v: v >= 20),
    *[("split", f"summary.{c}.peak_rss_mb", f"{c} peak RSS < 300 MB", lambda v: v < 300)
      for c in ("reep", "probeloss", "decode", "kalman-bank")],
    *[("split", f"summary.{c}.rss_ratio_largest_to_smallest", f"{c} RSS at 1e8 <= 1.2x RSS at 1e6", lambda v: v <= 1.2)
      for c in ("reep", "probeloss", "decode", "kalman-bank")],
    *[("split", f"summary.{c}.split_speedup", f"{c} split against sequential >= 1.8x", lambda v: v >= 1.8)
      for c in ("reep", "probeloss", "decode", "kalman-bank")],
    *[("split", f"summary.{c}.hash_share", f"{c} hash share of the run < 5 %", lambda v: v < 0.05)
      for c in ("reep", "probeloss", "decode", "kalman-bank")],
]


def _lookup(data, path: str):
    for part in path.split("."):
        if isinstance(data, list):
            data = data[int(part)]
        elif isinstance(data, dict) and part in data:
            data = data[part]
        else:
            return None
    return data


def summary_table() -> list[tuple[str, str, str]]:
    path = REPO / "bench.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    rows = []
    for section, key, label, check in CRITERIA:
        value = _lookup(data.get(section, {}), key)
        if value is None:
            rows.append((label, "not run", ""))
        else:
            rows.append((label, f"{value:.4g}", "pass" if check(value) else "FAIL"))
    return rows


def main() -> None:
    only = sys.argv[1:]
    for name in MODULES:
        if only and not any(o in name for o in only):
            continue
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            print(f"skip {name}: {exc}")
            continue
        print(f"== {name}", flush=True)
        module.main()
    print("\n== acceptance criteria (this run)")
    rows = summary_table()
    width = max(len(r[0]) for r in rows)
    for label, value, verdict in rows:
        print(f"{label:<{width}}  {value:>10}  {verdict}")
    print("results in bench.json")


if __name__ == "__main__":
    main()
