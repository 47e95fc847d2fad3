"""The hostile cases of issue 34 (and a few kept from issue 20), for :mod:`tests.hostile_runner`.

Groups: ``lock`` (links planted where afmtool creates its lock), ``overlap``
(outputs onto files of multi-file inputs, two runs on one folder), ``rate``
(sample rates no writer can carry), ``numeric`` (flags, TOML values and
captures at the numeric edges), ``scheduler`` (hostile peers on 127.0.0.1),
``diskfull`` (every writer on a tiny tmpfs), ``stdin`` (stalled and trickled
pipes), ``batch`` (failed inputs, reruns) and ``files`` (captures that point
outside themselves, claim what they cannot hold, nest too deep).

``quick=True`` marks the CI subset: cheap commands, one case per class.
"""

from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

from tests.hostile_runner import SAMPLE, Case, _copy, _labone_export

__all__ = ["all_cases"]

_HEADER = b"# sample_rate_hz: 1000\ndeflection\n"


def _reep(capture_key: str, *extra: str):
    return lambda f, c: ["reep", c[capture_key], "--out", f / "out", "-q", *extra]


def _lock_cases() -> list[Case]:
    def planted(target: str):
        def prepare(folder: Path, ctx: dict) -> None:
            (folder / "elsewhere").mkdir()
            if target == "file":
                (folder / "elsewhere" / "victim").write_text("precious")
            (folder / ".out.lock").symlink_to(folder / "elsewhere" / "victim")
        return prepare

    cases = [
        Case("lock/reep dangling link", "lock", _reep("cap"), "error", planted("dangling")),
        Case("lock/reep link to a file", "lock", _reep("cap"), "error", planted("file")),
        Case("lock/freeair dangling link", "lock", lambda f, c: ["identify", "freeair", c["cap"], "--out", f / "out", "-q"],
             "error", planted("dangling")),
        Case("lock/batch dangling link", "lock",
             lambda f, c: ["batch", "reep", c["cap"], "--out", f / "out", "--workers", "1", "-q"], "error", planted("dangling")),
        Case("lock/theory averaging link to a file", "lock", lambda f, c: ["theory", "averaging", "--out", f / "out", "-q"],
             "error", planted("file"), quick=True),
    ]
    return cases


def _overlap_cases() -> list[Case]:
    def labone(folder: Path, ctx: dict) -> None:
        _labone_export(folder / "export")

    sample = "export/dev1234_demods_0_sample_00000.csv"
    cases = [
        Case("overlap/convert onto the LabOne header (csv)", "overlap",
             lambda f, c: ["convert", f / sample, f / "export/dev1234_demods_0_sample_header_00000.csv", "--format", "csv"],
             "error", labone, quick=True),
        Case("overlap/convert onto the LabOne header (hdf5)", "overlap",
             lambda f, c: ["convert", f / sample, f / "export/dev1234_demods_0_sample_header_00000.csv", "--format", "hdf5"],
             "error", labone),
        Case("overlap/convert onto the next LabOne sample file", "overlap",
             lambda f, c: ["convert", f / sample, f / "export/dev1234_demods_0_sample_00001.csv", "--format", "csv"],
             "error", labone),
        Case("overlap/convert beside a LabOne export", "overlap", lambda f, c: ["convert", f / sample, f / "export/copy.h5"],
             "ok", labone),
        Case("overlap/info --out is not a thing; reep --out onto the export folder", "overlap",
             lambda f, c: ["reep", f / sample, "--channel", "deflection=x", "--out", f / "export", "-q"], "error", labone),
        Case("overlap/second batch on one --out", "overlap",
             lambda f, c: ["batch", "reep", c["cap"], "--out", f / "out", "--workers", "1", "-q"], "error",
             hold_lock=".out.lock", quick=True),
        Case("overlap/second reep on one --out", "overlap", _reep("cap"), "error", hold_lock=".out.lock"),
    ]
    if "mcap_bag" in _fixture_keys():
        def bag(folder: Path, ctx: dict) -> None:
            _copy(ctx["mcap_bag"], folder / "bag")

        storage = lambda f: next((f / "bag").glob("*.mcap"))  # noqa: E731 - found once the bag is copied
        cases += [
            Case("overlap/convert a bag's storage file onto its metadata.yaml", "overlap",
                 lambda f, c: ["convert", storage(f), f / "bag/metadata.yaml", "--format", "csv"], "error", bag),
            Case("overlap/convert a bag's storage file into its folder", "overlap",
                 lambda f, c: ["convert", storage(f), f / "bag/x.h5"], "error", bag),
            Case("overlap/reep --out onto the bag folder", "overlap",
                 lambda f, c: ["reep", f / "bag", "--out", f / "bag", "-q"], "error", bag),
        ]
    if "jpk" in _fixture_keys():
        def jpk(folder: Path, ctx: dict) -> None:
            _copy(ctx["jpk"], folder / "curve.jpk-force")
            os.link(folder / "curve.jpk-force", folder / "hard.h5")

        def tdms(folder: Path, ctx: dict) -> None:
            _copy(ctx["tdms"], folder / "raw1.tdms")
            (folder / "raw1.tdms_index").write_bytes(b"TDSh")

        cases += [
            Case("overlap/convert a JPK archive onto a hard link of it", "overlap",
                 lambda f, c: ["convert", f / "curve.jpk-force", f / "hard.h5"], "error", jpk),
            Case("overlap/convert a TDMS file onto its index", "overlap",
                 lambda f, c: ["convert", f / "raw1.tdms", f / "raw1.tdms_index", "--format", "csv"], "error", tdms),
        ]
    return cases


_FIXTURE_KEYS: set[str] = set()


def _fixture_keys() -> set[str]:
    from tests.hostile_runner import SHARED

    if not _FIXTURE_KEYS:
        _FIXTURE_KEYS.add("cap")
        if (SHARED / "fixtures" / "capture_v1_ros2_mcap").is_dir():
            _FIXTURE_KEYS.add("mcap_bag")
        if (SHARED / "data" / "formats").is_dir():
            _FIXTURE_KEYS.update(("jpk", "tdms"))
    return _FIXTURE_KEYS


_WRITE_FORMATS = {"csv": "x.csv", "hdf5": "x.h5", "ros1": "x.bag", "ros2-mcap": "x_mcap", "ros2-sqlite3": "x_db3"}


def _rate_cases() -> list[Case]:
    cases = []
    for key in ("rate_subnormal", "rate_1e-310", "rate_1e308"):
        for fmt, name in _WRITE_FORMATS.items():
            cases.append(Case(f"rate/convert {key} to {fmt}", "rate",
                              lambda f, c, key=key, fmt=fmt, name=name: ["convert", c[key], f / name, "--format", fmt],
                              "error", quick=(key == "rate_subnormal" and fmt == "csv")))
    cases += [
        Case("rate/convert 1e-300 Hz to a bag (stamps past int64)", "rate",
             lambda f, c: ["convert", c["rate_1e-300"], f / "x.bag"], "error"),
        Case("rate/convert 1e-300 Hz to csv", "rate", lambda f, c: ["convert", c["rate_1e-300"], f / "x.csv"], "ok"),
        Case("rate/--sample-rate 1e-320 on convert", "rate",
             lambda f, c: ["convert", c["cap"], f / "x.csv", "--sample-rate", "1e-320"], "error"),
        Case("rate/--sample-rate 1e309 on convert", "rate",
             lambda f, c: ["convert", c["cap"], f / "x.csv", "--sample-rate", "1e309"], "error"),
    ]
    return cases


def _toml(text: str):
    def prepare(folder: Path, ctx: dict) -> None:
        (folder / "params.toml").write_text(text)
    return prepare


def _figure_skipped(name: str):
    """A check: the run succeeded without the figure ``name``, saying why in report.json."""
    def check(folder: Path, result) -> str | None:
        import json

        report = json.loads((folder / "out" / "report.json").read_text())
        if name in report["outputs"] or (folder / "out" / name).exists():
            return f"{name} is listed or present"
        if not any(f"{name} not drawn: nothing to draw" in w for w in report["warnings"]):
            return f"no warning that {name} was skipped"
        return None
    return check


def _numeric_cases() -> list[Case]:
    cases = []
    for interval in ("0:1e308", "1e300:1e301", "0:1e-320", "1e-320:2e-320", "0:nan", "-1:1", "0.01:0.01", "inf:inf"):
        cases.append(Case(f"numeric/reep --free-air {interval}", "numeric", _reep("cap", "--free-air", interval), "error"))
        cases.append(Case(f"numeric/identify freeair --free-air {interval}", "numeric",
                          lambda f, c, i=interval: ["identify", "freeair", c["cap"], "--free-air", i, "--out", f / "out", "-q"],
                          "error"))
    for value in ("99999999999999", "99999999999999999999999", "-1", "1e3", "0"):
        cases.append(Case(f"numeric/reep --decimate {value}", "numeric", _reep("cap", "--decimate", value), "either",
                          quick=value == "99999999999999",
                          check=_figure_skipped("reep_time_series.png") if value == "99999999999999" else None))
        cases.append(Case(f"numeric/probeloss --decimate {value}", "numeric",
                          lambda f, c, v=value: ["probeloss", c["raster"], "--decimate", v, "--out", f / "out", "-q"]))
    for section, key, value in (
        ("reep", "decimate", "99999999999999"), ("reep", "decimate", "1e30"), ("reep", "warmup_windows", "1e308"),
        ("reep", "lam", "0.9999999999999999"), ("reep", "lam", "1e-320"), ("reep", "z_bin", "1e-320"),
        ("reep", "bandpass_half_width_hz", "1e308"), ("reep", "lockin_lowpass_hz", "1e-320"),
        ("reep", "drive_frequency_hz", "1e-300"), ("reep", "drive_frequency_hz", "1e308"),
        ("reep", "max_sigma2_ratio", "1e308"), ("reep", "spring_constant_n_per_m", "1e308"),
        ("reep", "f0_hz", "1e308"), ("reep", "q", "1e308"), ("reep", "window_us", "1e12"),
    ):
        cases.append(Case(f"numeric/toml [{section}] {key} = {value}", "numeric",
                          lambda f, c: ["reep", c["cap"], "--config", f / "params.toml", "--out", f / "out", "-q"],
                          prepare=_toml(f"[{section}]\n{key} = {value}\n"),
                          # a hang (2.5e14 row spacings tried) and internal errors (a singular matrix; a 55 TiB step simulation)
                          quick=(key, value) in {("lam", "0.9999999999999999"), ("drive_frequency_hz", "1e-300"),
                                                 ("window_us", "1e12")}))
    for key, value in (("decimate", "99999999999999"), ("rms_window_periods", "1e308"), ("rms_window_periods", "1e-320"),
                       ("drive_frequency_hz", "1e-300")):
        cases.append(Case(f"numeric/toml [kalman-bank] {key} = {value}", "numeric",
                          lambda f, c: ["kalman-bank", c["fc"], "--config", f / "params.toml", "--out", f / "out", "-q"],
                          prepare=_toml(f'["kalman-bank"]\n{key} = {value}\n'), quick=key == "drive_frequency_hz"))
    for key, value in (("clock_window_s", "1e308"), ("psd_window_s", "1e308"), ("warmup_s", "1e308"),
                       ("bits_from_s", "1e308"), ("mean_window", "99999999999999")):
        cases.append(Case(f"numeric/toml [decode] {key} = {value}", "numeric",
                          lambda f, c: ["decode", c["bits"], "--bit-rate", "30000", "--config", f / "params.toml",
                                        "--out", f / "out", "-q"], prepare=_toml(f"[decode]\n{key} = {value}\n")))
    for value in ("1e308", "1e-300", "nan"):
        cases.append(Case(f"numeric/decode --bit-rate {value}", "numeric",
                          lambda f, c, v=value: ["decode", c["bits"], "--bit-rate", v, "--out", f / "out", "-q"], "error"))
    for setting in ("duration_s=1e308", "duration_s=1e-320", "duration_s=-1", "sample_rate_hz=1e308",
                    "sample_rate_hz=1e-300", "duration_s=1e9"):
        cases.append(Case(f"numeric/simulate ltv --set {setting}", "numeric",
                          lambda f, c, s=setting: ["simulate", "ltv", "-o", f / "s.h5", "--set", s], "error",
                          quick=setting == "duration_s=1e308"))
    for key in ("tiny_all_310", "tiny_all_170", "tiny_defl_300", "tiny_dither_300", "huge_values", "rate_1e12", "rate_1e-3"):
        cases.append(Case(f"numeric/reep on {key}", "numeric", _reep(key)))
        cases.append(Case(f"numeric/identify freeair on {key}", "numeric",
                          lambda f, c, k=key: ["identify", "freeair", c[k], "--out", f / "out", "-q"]))
        cases.append(Case(f"numeric/info on {key}", "numeric", lambda f, c, k=key: ["info", c[k]], "ok"))
    for flags in (["--f0", "70000", "--q", "200"], ["--f0", "1e308", "--q", "1e308"], ["--f0", "1e-300", "--q", "1"]):
        for key in ("rate_1e12", "no_free_air", "tiny_all_100"):
            cases.append(Case(f"numeric/reep {' '.join(flags)} on {key}", "numeric", _reep(key, *flags)))
    cases += [
        Case("numeric/reep --z-bin 1e-320 on a force curve", "numeric", _reep("fc", "--z-bin", "1e-320")),
        Case("numeric/kalman-bank --z-bin 1e308", "numeric",
             lambda f, c: ["kalman-bank", c["fc"], "--z-bin", "1e308", "--out", f / "out", "-q"]),
        Case("numeric/reep --lambda 1e-320", "numeric", _reep("cap", "--lambda", "1e-320")),  # a window of one sample
        Case("numeric/reep --sample-rate 1e12", "numeric", _reep("cap", "--sample-rate", "1e12")),
        Case("numeric/theory averaging --force-set nonsense", "numeric",
             lambda f, c: ["theory", "averaging", "--force-set", "nonsense", "--out", f / "out", "-q"], "error"),
    ]
    return cases


_SCHEDULED = {
    "reep": lambda f, c: ["reep", c["cap"], "--out", f / "out"],
    "probeloss": lambda f, c: ["probeloss", c["raster"], "--out", f / "out"],
    "decode": lambda f, c: ["decode", c["bits"], "--bit-rate", "30000", "--out", f / "out"],
    "kalman-bank": lambda f, c: ["kalman-bank", c["fc"], "--out", f / "out"],
    "batch": lambda f, c: ["batch", "reep", c["cap"], "--out", f / "out", "--workers", "1"],
}


def _scheduler_cases() -> list[Case]:
    from tests.hostile_peers import KINDS

    cases = []
    for command, argv in _SCHEDULED.items():
        kinds = KINDS if command == "reep" else ("silent", "garbage", "trickle")
        for kind in kinds:
            cases.append(Case(
                f"scheduler/{command} with a {kind} peer", "scheduler",
                lambda f, c, argv=argv: [*argv(f, c), "--scheduler", c["scheduler"], "--scheduler-timeout", "2", "-q"],
                "error", peer=kind, timeout_s=60, quick=(command, kind) == ("batch", "silent"),
            ))
    return cases


_DISK_RUNS = {
    "convert to hdf5": lambda f, c: ["convert", c["cap"], c["mnt"] / "x.h5"],
    "convert to csv": lambda f, c: ["convert", c["cap"], c["mnt"] / "x.csv"],
    "convert to ros1": lambda f, c: ["convert", c["cap"], c["mnt"] / "x.bag"],
    "convert to ros2-mcap": lambda f, c: ["convert", c["cap"], c["mnt"] / "x", "--format", "ros2-mcap"],
    "convert to ros2-sqlite3": lambda f, c: ["convert", c["cap"], c["mnt"] / "x", "--format", "ros2-sqlite3"],
    "simulate": lambda f, c: ["simulate", "ltv", "-o", c["mnt"] / "s.h5", "--set", "duration_s=0.02"],
    "reep": lambda f, c: ["reep", c["cap"], "--out", c["mnt"] / "out", "-q"],
    "reep force curve": lambda f, c: ["reep", c["fc"], "--out", c["mnt"] / "out", "-q"],
    "probeloss": lambda f, c: ["probeloss", c["raster"], "--out", c["mnt"] / "out", "-q"],
    "decode": lambda f, c: ["decode", c["bits"], "--bit-rate", "30000", "--out", c["mnt"] / "out", "-q"],
    "kalman-bank": lambda f, c: ["kalman-bank", c["fc"], "--out", c["mnt"] / "out", "-q"],
    "identify freeair": lambda f, c: ["identify", "freeair", c["cap"], "--out", c["mnt"] / "out", "-q"],
    "theory fit": lambda f, c: ["theory", "fit", c["reep_fc"], "--out", c["mnt"] / "out", "-q"],
    "theory controllers": lambda f, c: ["theory", "controllers", "--out", c["mnt"] / "out", "--line-rates", "30", "--lines", "1",
                                        "--figure-lines", "2"],
    "theory averaging": lambda f, c: ["theory", "averaging", "--out", c["mnt"] / "out", "-q"],
    "design excitation": lambda f, c: ["design", "excitation", "--model", c["free_air_dir"], "--amplitude", "20",
                                       "--out", c["mnt"] / "out", "-q"],
    "batch": lambda f, c: ["batch", "reep", c["cap"], "--out", c["mnt"] / "out", "--workers", "1", "-q"],
    "report": lambda f, c: ["report", c["reep_fc"], "--output", c["mnt"] / "report.html", "-q"],
}
_DISK_SIZES = (4096, 65536, 1 << 20)


def _disk_cases() -> list[Case]:
    cases = []
    for name, argv in _DISK_RUNS.items():
        for size in _DISK_SIZES:
            cases.append(Case(f"diskfull/{name} on {size // 1024} KiB", "diskfull", argv, tmpfs_bytes=size, timeout_s=240,
                              quick=(name, size) == ("convert to ros2-sqlite3", 4096)))
    return cases


def _stdin_cases() -> list[Case]:
    trickle = [(0.0, _HEADER), *((0.2, b"%d\n" % i) for i in range(200))]
    return [
        Case("stdin/info on a trickle with --stdin-timeout 2", "stdin", lambda f, c: ["info", "-", "--stdin-timeout", "2"],
             "error", stdin=trickle, timeout_s=60, quick=True),
        Case("stdin/reep on a trickle with --stdin-timeout 2", "stdin",
             lambda f, c: ["reep", "-", "--out", f / "out", "--stdin-timeout", "2", "-q"], "error", stdin=trickle, timeout_s=60),
        Case("stdin/convert on a header then silence, --stdin-timeout 2", "stdin",
             lambda f, c: ["convert", "-", f / "x.h5", "--stdin-timeout", "2"], "error",
             stdin=[(0.0, _HEADER), (30.0, b"")], timeout_s=60),
        Case("stdin/info on a stall then rows", "stdin", lambda f, c: ["info", "-"], "ok",
             stdin=[(0.0, _HEADER), (10.0, b"".join(b"%d\n" % i for i in range(50)))], timeout_s=60,
             check=lambda f, r: None if r.stderr.decode().count("waiting for input on stdin") == 1 else "no notice"),
        Case("stdin/info on an empty stdin", "stdin", lambda f, c: ["info", "-"], "error", stdin=[]),
    ]


def _summary(folder: Path) -> dict:
    with open(folder / "out" / "summary.csv", newline="") as handle:
        return {row["input"]: (row["status"], row["reason"]) for row in csv.DictReader(handle)}


def _batch_cases() -> list[Case]:
    def inputs(folder: Path, ctx: dict) -> None:
        (folder / "in").mkdir()
        shutil.copyfile(ctx["cap"], folder / "in" / "good.h5")
        shutil.copyfile(ctx["corrupt"], folder / "in" / "corrupt.h5")

    def rerun_is_the_same(folder: Path, result) -> str | None:
        first = _summary(folder)
        from tests.hostile_runner import _afmtool

        again = _afmtool(["batch", "reep", str(folder / "in"), "--out", str(folder / "out"), "--workers", "1", "-q"],
                         timeout=600)
        second = _summary(folder)
        failed = [line for line in again.stderr.decode().splitlines() if "corrupt.h5" in line]
        if again.returncode != result.returncode or len(failed) != 1:
            return f"rerun: exit {again.returncode}, {len(failed)} lines for the failed input"
        if first[str(folder / "in" / "corrupt.h5")] != second[str(folder / "in" / "corrupt.h5")]:
            return f"rerun reports {second} after {first}"
        return None

    return [
        Case("batch/a failed input is one line and exit 2; a rerun says the same", "batch",
             lambda f, c: ["batch", "reep", f / "in", "--out", f / "out", "--workers", "1", "-q"], "error", inputs,
             timeout_s=600, check=rerun_is_the_same, keeps_outputs=True),
    ]


def _files_cases() -> list[Case]:
    return [
        Case("files/deep JSON metadata", "files", lambda f, c: ["info", c["deep_meta"]], "error", quick=True),
        Case("files/a dataset claiming 1e15 samples", "files", lambda f, c: ["info", c["huge_claim"]], "error"),
        Case("files/reep on a claim of 1e15 samples", "files", _reep("huge_claim"), "error"),
        Case("files/a corrupt HDF5 file", "files", lambda f, c: ["convert", c["corrupt"], f / "x.csv"], "error"),
    ]


def all_cases() -> list[Case]:
    """Every case, in group order."""
    cases = (_lock_cases() + _overlap_cases() + _rate_cases() + _numeric_cases() + _scheduler_cases() + _disk_cases()
             + _stdin_cases() + _batch_cases() + _files_cases())
    names = [c.name for c in cases]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"case names repeat: {duplicated}")
    return cases


_ = SAMPLE  # the runner's sample folder, for cases that name it
