"""Disk full, every writer (issue 34): one line, exit 2, no crash, nothing left.

HDF5 (captures and result files, including a failure inside HDF5's own
flush), CSV, ROS1 and ROS2 bags (mcap and SQLite db3), PNG and JSON (an
analysis folder, its figures drawn by the helper process), and ``batch``.
Each runs on a tmpfs too small for it, as the disk-full tests of issue 20
do (``tests/test_hostile_io.py``); where a tmpfs cannot be mounted they
skip with the reason.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import REPO, SAMPLE_DATA
from tests.test_hostile_io import Tmpfs, _one_line_exit_2

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small tmpfs needs root")


def _afmtool(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "afmtool", *map(str, args)], cwd=REPO, capture_output=True, timeout=600)


def _nothing_left(mnt) -> None:
    assert sorted(p.name for p in mnt.iterdir()) == []


@pytest.mark.parametrize("target, fmt", [("x.h5", "hdf5"), ("x.csv", "csv"), ("x.bag", "ros1"), ("x", "ros2-mcap"),
                                         ("x", "ros2-sqlite3")])
def test_convert_to_every_format_on_a_full_disk(tmp_path, target, fmt):
    with Tmpfs(tmp_path / "mnt", 4096) as mnt:
        result = _afmtool("convert", SAMPLE_DATA / "ltv_step.h5", mnt / target, "--format", fmt)
        _one_line_exit_2(result, "No space left on device")  # db3: SQLite's "database or disk is full" was exit 1
        _nothing_left(mnt)


@pytest.mark.parametrize("size", [4096, 16384])
def test_reep_on_a_force_curve_does_not_crash_on_a_full_disk(tmp_path, size):
    """At 4 and 16 KiB free libhdf5 crashed (SIGSEGV) closing reep.h5 after a failed write, and left
    the staging folder and the lock behind."""
    with Tmpfs(tmp_path / "mnt", size) as mnt:
        result = _afmtool("reep", SAMPLE_DATA / "tapping_force_curve.h5", "--out", mnt / "out", "-q")
        _one_line_exit_2(result, "No space left on device")
        _nothing_left(mnt)


def _write_result_file(path: str, n: int) -> None:
    import numpy as np

    from afmtool.io.results import ResultWriter

    with ResultWriter(path, {"t": "s", "f0_hz": "Hz"}, {"afmtool_command": "test"}, write_behind=True) as writer:
        for start in range(0, n, 4096):
            writer.append({"t": np.arange(start, start + 4096) * 1e-6, "f0_hz": np.full(4096, 7e4)})
        writer.put("image/f0_hz", np.ones((64, 64)))


@pytest.mark.parametrize("size_kib", [8, 812])
def test_an_hdf5_result_file_fails_cleanly_wherever_the_disk_fills(tmp_path, size_kib):
    """At 812 KiB (h5py 3, libhdf5 1.14) the data fit and HDF5's own flush at close is what fails."""
    with Tmpfs(tmp_path / "mnt", size_kib << 10) as mnt:
        code = (
            "import sys; sys.path.insert(0, sys.argv[3]); from tests.test_hostile_diskfull import _write_result_file\n"
            "from afmtool.runtime.faults import environment_fault\n"
            "try:\n    _write_result_file(sys.argv[1], int(sys.argv[2]))\n"
            "except BaseException as exc:\n"
            "    print('fault' if environment_fault(exc) == 28 else f'other {type(exc).__name__}: {exc}', flush=True)\n"
            "    import os; os._exit(2)\n"
            "print('ok')\n"
        )
        result = subprocess.run([sys.executable, "-c", code, str(mnt / "r.h5"), str(40_000), str(REPO)], cwd=REPO,
                                capture_output=True, timeout=120)
        assert result.returncode in (0, 2), (result.returncode, result.stderr.decode()[-2000:])  # never a signal
        assert result.stdout.decode().strip() in ("ok", "fault"), result.stdout.decode()


@pytest.mark.long
def test_theory_controllers_on_a_full_disk_prints_one_line(tmp_path):
    with Tmpfs(tmp_path / "mnt", 16384) as mnt:
        # not -q: no progress line before the error (the smallest run: 6 s of CPU)
        result = _afmtool("theory", "controllers", "--out", mnt / "out", "--line-rates", "30", "--lines", "1", "--figure-lines", "2")
        _one_line_exit_2(result, "No space left on device")
        _nothing_left(mnt)


@pytest.mark.long
def test_batch_on_a_full_disk_leaves_no_partial_output(tmp_path):
    pytest.importorskip("dask.distributed")
    with Tmpfs(tmp_path / "mnt", 65536) as mnt:
        result = _afmtool("batch", "reep", SAMPLE_DATA / "ltv_step.h5", SAMPLE_DATA / "tapping_force_curve.h5",
                          "--out", mnt / "out", "--workers", "1", "-q")
        _one_line_exit_2(result, "No space left on device")
        _nothing_left(mnt)


def test_a_png_and_a_json_on_a_full_disk(tmp_path):
    """The figure helper's PNG and the report's JSON: reep at 64 KiB fills the disk at one or the other."""
    with Tmpfs(tmp_path / "mnt", 65536) as mnt:
        result = _afmtool("reep", SAMPLE_DATA / "ltv_step.h5", "--out", mnt / "out", "-q")
        _one_line_exit_2(result, "No space left on device")
        _nothing_left(mnt)


def test_a_figure_on_a_full_disk_in_process(tmp_path):
    import numpy as np

    from afmtool.report.images import write_line_plot_png

    with Tmpfs(tmp_path / "mnt", 4096) as mnt:
        with pytest.raises(OSError) as full:
            write_line_plot_png(mnt / "f.png", [(np.arange(100.0), np.sin(np.arange(100.0)), "sin")], x_label="x", y_label="y",
                                title="t")
        assert full.value.errno == 28
        _nothing_left(mnt)


@pytest.mark.slow
def test_theory_fit_on_a_full_disk_does_not_crash_at_exit(tmp_path):
    """At 64 KiB the fit's PNG fails, and libhdf5's exit handler then freed datasets of reep.h5 left open
    (SIGSEGV in H5D_close after the one line); a failed run with HDF5 objects open now ends by os._exit."""
    reep = tmp_path / "reep_fc"
    assert _afmtool("reep", SAMPLE_DATA / "tapping_force_curve.h5", "--out", reep, "-q").returncode == 0
    with Tmpfs(tmp_path / "mnt", 65536) as mnt:
        result = _afmtool("theory", "fit", reep, "--out", mnt / "out", "-q")
        _one_line_exit_2(result, "No space left on device")
        _nothing_left(mnt)
