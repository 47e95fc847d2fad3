"""OutputDir's early flush: a finished file goes to disk while the run goes on, and its error still fails the run."""

from __future__ import annotations

import errno

import pytest

from afmtool.runtime import outputs
from afmtool.runtime.atomic import OutputError
from afmtool.runtime.outputs import OutputDir


def test_a_file_flushed_early_and_changed_later_is_committed_whole(tmp_path):
    out = tmp_path / "run"
    with OutputDir(out) as staged:
        staged.path("series.bin").write_bytes(b"a" * (1 << 20))
        staged.flush_early("series.bin")
        with staged.path("series.bin").open("ab") as more:  # e.g. reep.h5 gains its interaction series
            more.write(b"b")
        staged.path("report.json").write_text("{}")
    assert (out / "series.bin").read_bytes() == b"a" * (1 << 20) + b"b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_an_early_flush_that_fails_fails_the_commit_and_publishes_nothing(tmp_path, monkeypatch):
    def disk_error(path):
        raise OSError(errno.EIO, "Input/output error", str(path))

    out = tmp_path / "run"
    monkeypatch.setattr(outputs, "_fsync_path", disk_error)
    with pytest.raises(OutputError, match="could not be written"), OutputDir(out) as staged:
        staged.path("series.bin").write_bytes(b"data")
        staged.flush_early("series.bin")
        # the commit's own flush succeeds: only the early flush saw the error (Linux reports it once)
        monkeypatch.setattr(outputs, "_fsync_tree", lambda root: None)
        staged.path("report.json").write_text("{}")
    assert list(tmp_path.iterdir()) == []
