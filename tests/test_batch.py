"""afmtool batch on Dask: a local cluster, and a real scheduler + worker on 127.0.0.1."""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import time

import pytest

from tests.conftest import run_cli

pytest.importorskip("dask.distributed")


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    folder = tmp_path_factory.mktemp("captures")
    for seed in range(5):
        result = run_cli("simulate", "ltv", "-o", folder / f"c{seed}.h5", "--seed", seed, "--set", "duration_s=0.02")
        assert result.returncode == 0
    (folder / "corrupt.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    return folder


def _summary(out):
    with open(out / "summary.csv") as handle:
        return {row["input"].rsplit("/", 1)[-1]: row for row in csv.DictReader(handle)}


def test_local_cluster_batch(tmp_path, captures):
    out = tmp_path / "batch"
    result = run_cli("batch", "reep", str(captures / "*.h5"), "--out", out, "--workers", "2", "--quiet")
    assert result.returncode == 2  # one input failed, on bad input (README: exit 2)
    rows = _summary(out)
    assert len(rows) == 6
    assert [name for name, row in rows.items() if row["status"] == "failed"] == ["corrupt.h5"]
    assert "HDF5" in rows["corrupt.h5"]["reason"]
    assert sum(row["status"] == "ok" for row in rows.values()) == 5
    failed_lines = [line for line in result.stderr.decode().splitlines() if "corrupt.h5" in line]
    assert len(failed_lines) == 1 and failed_lines[0].startswith("afmtool: failed: ")  # one line, however long
    first_reason = rows["corrupt.h5"]["reason"]
    # identical to a single-file run
    single = tmp_path / "single"
    assert run_cli("reep", captures / "c3.h5", "--out", single, "--quiet").returncode == 0
    batch_report = json.loads((out / "c3_h5" / "report.json").read_text())
    single_report = json.loads((single / "report.json").read_text())
    assert batch_report["results"] == single_report["results"]
    assert float(rows["c3.h5"]["segments.free_air.f0_hz.mean"]) == single_report["results"]["segments"]["free_air"]["f0_hz"]["mean"]
    # a rerun processes nothing new
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("report.json")}
    again = run_cli("batch", "reep", str(captures), "--out", out, "--workers", "2", "--quiet")
    assert again.returncode == 2
    rows = _summary(out)
    assert sum(row["status"] == "skipped" for row in rows.values()) == 5
    assert rows["corrupt.h5"]["reason"] == first_reason  # the same result for the same input
    assert {p: p.stat().st_mtime_ns for p in out.rglob("report.json")} == stamps


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_existing_scheduler(tmp_path, captures):
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
         "--dashboard-address", ":0", "--no-show"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    worker = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--nworkers", "1",
         "--no-dashboard", "--host", "127.0.0.1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        out = tmp_path / "remote"
        result = run_cli("batch", "reep", captures / "c0.h5", captures / "c1.h5", "--out", out,
                         "--scheduler", address, "--quiet")
        assert result.returncode == 0, result.stderr.decode()
        rows = _summary(out)
        assert [row["status"] for row in rows.values()] == ["ok", "ok"]
    finally:
        for proc in (worker, scheduler):
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


@pytest.mark.parametrize(
    ("command", "capture", "extra", "column"),
    [
        ("probeloss", "raster_grating.h5", [], "loss_fraction"),
        ("decode", "bits_30khz.h5", ["--arg=--bit-rate", "--arg=30000"], "bits.count"),
    ],
)
def test_batch_runs_the_other_analyses(tmp_path, command, capture, extra, column):
    from tests.conftest import SAMPLE_DATA

    folder = tmp_path / "in"
    folder.mkdir()
    (folder / capture).symlink_to(SAMPLE_DATA / capture)
    out = tmp_path / "batch"
    result = run_cli("batch", command, folder, "--out", out, "--workers", "1", "--quiet", *extra)
    assert result.returncode == 0, result.stderr.decode()
    row = _summary(out)[capture]
    assert row["status"] == "ok"
    report = json.loads((out / capture.replace(".", "_") / "report.json").read_text())
    assert report["command"] == command
    assert row[column] != ""


def test_batch_iterates_the_curves_of_a_map(tmp_path, shared):
    """Issue 32: a JPK force map is one input per curve, each run with --curve N; a rerun skips them all."""
    source = shared / "data" / "formats" / "force-map2x2-example.jpk-force-map"
    out = tmp_path / "map"
    args = ["batch", "invols", source, "--out", out, "--workers", "2", "--quiet", "--arg=--segment", "--arg=extend"]
    result = run_cli(*args)
    assert result.returncode == 0, result.stderr.decode()
    with open(out / "summary.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["input"].rsplit(" ", 1)[-1] for row in rows] == ["0", "1", "2", "3"]
    assert all(row["input"].endswith(f"--curve {k}") and row["status"] == "ok" for k, row in enumerate(rows))
    for k in range(4):
        report = json.loads((out / f"force-map2x2-example_jpk-force-map_curve{k}" / "report.json").read_text())
        single = run_cli("identify", "invols", source, "--curve", str(k), "--segment", "extend", "--out",
                         tmp_path / f"single{k}", "--quiet", "--json")
        assert report["results"] == json.loads(single.stdout)["results"]
    again = run_cli(*args)
    with open(out / "summary.csv") as handle:
        assert [row["status"] for row in csv.DictReader(handle)] == ["skipped"] * 4, again.stderr.decode()


def test_the_resume_check_reads_the_input_with_the_runs_own_capture_options(tmp_path, captures):
    """The CLI hands batch its option parser (no import up a floor): a run read in pm is checked in pm."""
    from afmtool.analyses.batch import plan_batch, run_one
    from afmtool.cli.batch_cmd import capture_options_of

    args = ["--units", "deflection=pm", "--no-input"]
    assert capture_options_of(["reep"], str(captures / "c0.h5"), args) is not None
    (item,) = plan_batch([captures / "c0.h5"], tmp_path / "batch")
    assert run_one(["reep"], item, args, options_of=capture_options_of).status == "ok"
    assert run_one(["reep"], item, args, options_of=capture_options_of).status == "skipped"
    # read with the capture's defaults (nm), the samples hash differently from the run's (pm): redone
    assert run_one(["reep"], item, args).status == "ok"
