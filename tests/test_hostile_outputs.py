"""Hostile outputs from issue 34: planted links, outputs over multi-file inputs, two batches, rates.

Each case is something a red team did to the tree: a symbolic link planted
where afmtool creates its lock, an output aimed at a file of a multi-file
input (a LabOne CSV export's header file, a file inside a ROS2 bag), two
``batch`` runs on one folder, a capture whose sample rate no writer can
represent.  Every one ends in exit 2 with one line on stderr, creates
nothing outside ``--out`` and leaves the inputs as they were.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.conftest import REPO, run_cli
from tests.test_hostile_io import _one_line_exit_2, _state, _write_capture

# -- 1. a lock planted as a link -----------------------------------------------------------------


@pytest.mark.parametrize("kind", ["dangling", "to a file", "to a folder", "fifo"])
def test_a_planted_lock_creates_nothing_outside_out(tmp_path, kind):
    from afmtool.runtime.atomic import OutputError
    from afmtool.runtime.outputs import OutputDir

    parent = tmp_path / "parent"
    parent.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    lock = parent / ".out.lock"
    target = elsewhere / "victim"
    if kind == "to a file":
        target.write_text("precious")
    elif kind == "to a folder":
        target.mkdir()
    if kind == "fifo":
        os.mkfifo(lock)
    else:
        lock.symlink_to(target)
    with pytest.raises(OutputError, match="lock"):
        with OutputDir(parent / "out") as staged:
            staged.path("report.json").write_text("{}")
    assert sorted(p.name for p in elsewhere.iterdir()) == ([] if kind in ("dangling", "fifo") else ["victim"])
    if kind == "to a file":
        assert target.read_text() == "precious"
    assert os.path.lexists(lock)  # refused, not removed: the user decides what it was
    assert sorted(p.name for p in parent.iterdir()) == [".out.lock"]  # no staging left, no --out


def test_a_planted_lock_is_one_line_from_the_cli(tmp_path):
    capture = _write_capture(tmp_path / "cap.h5", 2000)
    parent = tmp_path / "parent"
    parent.mkdir()
    (parent / ".out.lock").symlink_to(tmp_path / "victim")
    _one_line_exit_2(run_cli("reep", capture, "--out", parent / "out", "-q", "--no-input"), "symbolic link")
    assert not os.path.lexists(tmp_path / "victim")
    assert sorted(p.name for p in parent.iterdir()) == [".out.lock"]


# -- 2. inputs and outputs never overlap -------------------------------------------------------------


def _labone_export(folder: Path) -> list[Path]:
    """A LabOne CSV export: two sample files and their header files (the clockbase is in the headers)."""
    folder.mkdir()
    rows = "\n".join(f"0;{10**9 + i * 3000};{np.sin(i / 5.0):.17g};{np.cos(i / 5.0):.17g}" for i in range(300))
    files = []
    for n in range(2):
        sample = folder / f"dev1234_demods_0_sample_{n:05d}.csv"
        sample.write_text("chunk;timestamp;x;y\n" + rows + "\n")
        header = folder / f"dev1234_demods_0_sample_header_{n:05d}.csv"
        header.write_text('chunk;history_name;clockbase;createdtimestamp\n0;"sample";60000000;123\n')
        files += [sample, header]
    return files


def test_convert_onto_any_file_of_a_labone_export_is_refused(tmp_path, monkeypatch):
    from afmtool.io.registry import open_capture
    from afmtool.runtime import input_guard

    files = _labone_export(tmp_path / "export")
    source = files[0]
    before = _state(tmp_path / "export")
    _one_line_exit_2(run_cli("convert", source, files[1], "--format", "csv"), "input")  # its header file
    _one_line_exit_2(run_cli("convert", source, files[2], "--format", "hdf5"), "input")  # the next sample file
    assert _state(tmp_path / "export") == before
    monkeypatch.setattr(input_guard, "_inputs", [])
    with open_capture(source):
        for target in files:
            with pytest.raises(input_guard.InputOverwriteError):
                input_guard.refuse_output_over_inputs(target)
        with pytest.raises(input_guard.InputOverwriteError):
            input_guard.refuse_output_over_inputs(tmp_path / "export", directory=True)
        input_guard.refuse_output_over_inputs(tmp_path / "export" / "copy.h5")  # a new file beside it is fine


def test_outputs_onto_a_bag_given_by_its_storage_file_are_refused(tmp_path, shared):
    import shutil

    bag = tmp_path / "bag"
    shutil.copytree(shared / "fixtures" / "capture_v1_ros2_mcap", bag)
    storage = next(bag.glob("*.mcap"))
    before = _state(bag)
    for target in (bag / "metadata.yaml", bag / "new.h5", storage):
        _one_line_exit_2(run_cli("convert", storage, target, "--format", "hdf5"), "input")
    assert _state(bag) == before


def test_an_archive_and_a_tdms_index_are_inputs(tmp_path, shared):
    import shutil

    formats = shared / "data" / "formats"
    jpk = tmp_path / "curve.jpk-force"
    shutil.copyfile(formats / "fmt-jpk-fd_spot3-0192.jpk-force", jpk)
    os.link(jpk, tmp_path / "hard.h5")
    tdms = tmp_path / "raw1.tdms"
    shutil.copyfile(formats / "raw1.tdms", tdms)
    index = tmp_path / "raw1.tdms_index"
    index.write_bytes(b"TDSh")  # whatever it holds, it is part of the capture
    before = {p: _state(p) for p in (jpk, tdms, index)}
    _one_line_exit_2(run_cli("convert", jpk, tmp_path / "hard.h5"), "input")
    _one_line_exit_2(run_cli("convert", jpk, jpk, "--format", "hdf5"), "input")
    from afmtool.io.registry import companion_files

    assert companion_files(tdms, "tdms") == [index]
    assert {p: _state(p) for p in before} == before


def test_a_second_batch_on_one_out_is_refused_at_once(tmp_path):
    import fcntl

    pytest.importorskip("dask.distributed")
    capture = _write_capture(tmp_path / "cap.h5", 2000)
    out = tmp_path / "batch"
    with open(tmp_path / ".batch.lock", "wb") as held:  # what a running batch holds
        fcntl.flock(held, fcntl.LOCK_EX)
        start = time.monotonic()
        result = run_cli("batch", "reep", capture, "--out", out, "--workers", "1", "-q")
        assert time.monotonic() - start < 30
    _one_line_exit_2(result, "another afmtool run")
    assert not out.exists()


@pytest.mark.slow
def test_two_batches_on_one_out_one_runs_the_other_is_refused(tmp_path):
    from tests.test_hostile_io import _lock_is_held

    pytest.importorskip("dask.distributed")
    from tests.conftest import SAMPLE_DATA

    capture = tmp_path / "cap.h5"
    capture.symlink_to(SAMPLE_DATA / "ltv_step.h5")
    out = tmp_path / "batch"
    args = [sys.executable, "-m", "afmtool", "batch", "reep", str(capture), "--out", str(out), "--workers", "1", "-q"]
    first = subprocess.Popen(args, cwd=REPO, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not _lock_is_held(tmp_path / ".batch.lock"):
        assert first.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    import signal

    os.kill(first.pid, signal.SIGSTOP)
    try:
        second = subprocess.run(args, cwd=REPO, capture_output=True, timeout=120)
    finally:
        os.kill(first.pid, signal.SIGCONT)
    _one_line_exit_2(second, "another afmtool run")
    assert first.wait(timeout=300) == 0, first.stderr.read().decode()
    assert (out / "summary.csv").is_file() and len(list(out.glob("*/report.json"))) == 1


# -- 3. convert never writes a rate nothing can read ----------------------------------------------------

_FORMAT_SUFFIX = {"csv": ".csv", "hdf5": ".h5", "ros1": ".bag", "ros2-mcap": "_bag"}


def _memory_capture(rate: float, n: int = 3000):
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.memory import ArrayReader

    values = np.sin(np.arange(n) / 7.0)
    return ArrayReader(rate, [ChannelSpec("deflection", "nm")], {"deflection": values}, source="hostile.h5")


@pytest.mark.parametrize("rate", [float("inf"), float("nan"), 0.0, -1e5, 5e-324, 1e-310, 1e308, 1.7e308])
@pytest.mark.parametrize("fmt", list(_FORMAT_SUFFIX))
def test_convert_refuses_a_rate_no_writer_can_carry(tmp_path, rate, fmt):
    from afmtool.analyses.convert import convert_capture
    from afmtool.errors import InputError
    from afmtool.runtime.atomic import atomic_path

    target = tmp_path / f"out{_FORMAT_SUFFIX[fmt]}"
    with pytest.raises(InputError, match="sample rate"):
        with atomic_path(target, directory=fmt.startswith("ros2")) as tmp:
            convert_capture(_memory_capture(rate), tmp, fmt)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("rate", [1e-300, 1e-3, 1.15e6, 1e12, 1e300])
@pytest.mark.parametrize("fmt", list(_FORMAT_SUFFIX))
def test_what_convert_writes_reads_back_at_its_rate(tmp_path, rate, fmt):
    from afmtool.analyses.convert import convert_capture
    from afmtool.errors import InputError
    from afmtool.io.chunks import iter_chunks
    from afmtool.io.registry import open_capture
    from afmtool.runtime.atomic import atomic_path

    target = tmp_path / f"out{_FORMAT_SUFFIX[fmt]}"
    try:
        with atomic_path(target, directory=fmt.startswith("ros2")) as tmp:
            convert_capture(_memory_capture(rate), tmp, fmt, chunk_samples=1000)
    except InputError as refused:  # a time stamp that format cannot hold: refused, nothing left
        assert fmt in ("ros1", "ros2-mcap") and "time stamp" in str(refused)
        assert sorted(p.name for p in tmp_path.iterdir()) == []
        return
    with open_capture(target) as reader:
        assert reader.info.sample_rate_hz == pytest.approx(rate, rel=1e-12)
        got = np.concatenate([c.data["deflection"] for c in iter_chunks(reader, ["deflection"], 1024)])
    np.testing.assert_allclose(got, np.sin(np.arange(3000) / 7.0), rtol=1e-6, atol=1e-6)


def test_convert_of_a_subnormal_rate_is_one_line(tmp_path):
    path = tmp_path / "slow.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 5e-324
        f.create_dataset("channels/deflection", data=np.arange(100.0)).attrs["units"] = "nm"
    _one_line_exit_2(run_cli("convert", path, tmp_path / "out.csv"), "sample rate")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slow.h5"]


# -- 8. one outcome line -------------------------------------------------------------------------------


@pytest.fixture
def fresh_outcome():
    import signal

    from afmtool.runtime import process

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    process.new_run()
    yield process
    for s, handler in handlers.items():
        signal.signal(s, handler)


def test_an_interrupt_after_the_error_line_adds_no_line(capfd, fresh_outcome):
    """A huge_claim capture refused while a SIGTERM arrived printed its refusal and 'interrupted'."""
    with pytest.raises(SystemExit) as done:
        fresh_outcome.error("huge_claim.h5: claims 1e15 samples", 2)
    fresh_outcome.Signals().report()  # what the SIGTERM handler (or its deadline) does
    err = capfd.readouterr().err
    assert done.value.code == 2 and err.splitlines() == ["afmtool: error: huge_claim.h5: claims 1e15 samples"]


def test_a_refusal_raised_by_the_interrupt_adds_no_line(capfd, fresh_outcome):
    fresh_outcome.Signals().report()
    with pytest.raises(SystemExit) as done:
        fresh_outcome.error("x.h5: cannot read (interrupted)", 2)
    assert done.value.code == 130 and capfd.readouterr().err.splitlines() == ["afmtool: interrupted"]


# -- 8. batch: one line per failed input, the same result on a rerun ---------------------------------------


def test_batch_reruns_report_the_same_line_for_the_same_input(tmp_path, monkeypatch):
    import afmtool.analyses.batch as batch

    corrupt = tmp_path / "corrupt.h5"
    corrupt.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    (item,) = batch.plan_batch([corrupt], tmp_path / "out")
    real_run = batch.subprocess.run

    def killed(args, **kwargs):  # the worker's child killed (OOM killer, a stray signal), twice
        return subprocess.CompletedProcess(args, -9, "", "")

    monkeypatch.setattr(batch.subprocess, "run", killed)
    lost = batch.run_one(["reep"], item, [])
    assert lost.status == "failed" and lost.reason.startswith("killed by a signal")
    monkeypatch.setattr(batch.subprocess, "run", real_run)
    first = batch.run_one(["reep"], item, [])  # the rerun after the kill: the input's own verdict
    again = batch.run_one(["reep"], item, [])  # cached: not rerun, the same line
    assert first.status == again.status == "failed" and first.exit_code == again.exit_code == 2
    assert again.reason == first.reason and "\n" not in first.reason and "HDF5" in first.reason


def test_a_lost_dask_task_is_a_failed_input_not_an_internal_error(tmp_path):
    from afmtool.analyses.batch import BatchItem, _outcome

    class Lost:
        def result(self):
            raise RuntimeError("KilledWorker: ('afmtool-0', <WorkerState 'tcp://127.0.0.1:1'>)\nsecond line")

    class Full:
        def result(self):
            raise OSError(28, "No space left on device", "/x")

    item = BatchItem("cap.h5", str(tmp_path / "cap_h5"))
    lost = _outcome(Lost(), item)
    assert lost.status == "failed" and lost.reason.startswith("worker lost") and "\n" not in lost.reason and not lost.fault
    assert _outcome(Full(), item).fault  # the batch then stops and keeps nothing
