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
    from afmtool.report.atomic import OutputError
    from afmtool.report.outputs import OutputDir

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
