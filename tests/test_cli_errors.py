"""Bad input: exit status 2, one line on stderr, no traceback, no output files."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tests.conftest import run_cli


def _write_h5(path, *, rate=True, values=None):
    with h5py.File(path, "w") as f:
        if rate:
            f.attrs["sample_rate_hz"] = 1000.0
        f.create_dataset("channels/deflection", data=np.zeros(100) if values is None else values)


def _make(tmp_path, case):
    if case == "missing file":
        return tmp_path / "nope.h5", []
    if case == "unknown extension":
        path = tmp_path / "capture.txt"
        path.write_text("a,b\n1,2\n")
        return path, []
    if case == "csv ragged":
        path = tmp_path / "c.csv"
        path.write_text("# sample_rate_hz: 1000\na,b\n1,2\n3\n")
        return path, []
    if case == "csv non-numeric":
        path = tmp_path / "c.csv"
        path.write_text("# sample_rate_hz: 1000\na,b\n1,2\n3,abc\n")
        return path, []
    if case == "csv non-uniform t":
        path = tmp_path / "c.csv"
        path.write_text("t,a\n0,1\n0.001,2\n0.0025,3\n0.003,4\n")
        return path, []
    if case == "hdf5 without sample rate":
        path = tmp_path / "c.h5"
        _write_h5(path, rate=False)
        return path, []
    if case == "truncated hdf5":
        good = tmp_path / "good.h5"
        _write_h5(good, values=np.arange(200_000.0))
        path = tmp_path / "c.h5"
        path.write_bytes(good.read_bytes()[:3000])
        good.unlink()
        return path, []
    if case == "missing channel":
        path = tmp_path / "c.h5"
        _write_h5(path)
        return path, ["--channel", "deflection=/no/such"]
    if case == "empty csv":
        path = tmp_path / "c.csv"
        path.write_text("")
        return path, []
    if case == "empty hdf5":
        path = tmp_path / "c.h5"
        path.write_bytes(b"")
        return path, []
    if case == "nan in channel":
        path = tmp_path / "c.h5"
        values = np.zeros(100)
        values[42] = np.inf
        _write_h5(path, values=values)
        return path, []
    raise AssertionError(case)


CASES = [
    "missing file",
    "unknown extension",
    "csv ragged",
    "csv non-numeric",
    "csv non-uniform t",
    "hdf5 without sample rate",
    "truncated hdf5",
    "missing channel",
    "empty csv",
    "empty hdf5",
    "nan in channel",
]


def assert_clean_failure(result, tmp_path, inputs_before):
    stderr = result.stderr.decode()
    assert result.returncode == 2, stderr
    assert "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr
    assert stderr.startswith("afmtool: error: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == inputs_before


@pytest.mark.parametrize("case", CASES)
def test_convert_bad_input(tmp_path, case):
    path, extra = _make(tmp_path, case)
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run_cli("convert", path, tmp_path / "out.h5", *extra)
    assert_clean_failure(result, tmp_path, before)


@pytest.mark.parametrize("case", ["missing file", "csv ragged", "nan in channel", "truncated hdf5"])
def test_info_bad_input(tmp_path, case):
    path, extra = _make(tmp_path, case)
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run_cli("info", path, *extra)
    assert_clean_failure(result, tmp_path, before)


def test_usage_error_is_one_line(tmp_path):
    result = run_cli("info")
    assert result.returncode == 2
    assert len(result.stderr.decode().strip().splitlines()) == 1


def test_input_is_never_modified(tmp_path, shared):
    source = shared / "fixtures" / "capture_v1.h5"
    before = source.read_bytes()
    result = run_cli("convert", source, tmp_path / "copy.csv")
    assert result.returncode == 0, result.stderr.decode()
    assert source.read_bytes() == before


def test_bag_with_no_matching_topic(tmp_path):
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.rosbag import RosbagWriter

    bag = tmp_path / "other.bag"
    writer = RosbagWriter(bag, 1000.0, [ChannelSpec("deflection", "nm")], {}, version="ros1")
    writer.write({"deflection": np.zeros(10)})
    writer.close()
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run_cli("info", bag, "--topic", "deflection=/not/there")
    assert_clean_failure(result, tmp_path, before)


def test_analysis_missing_channel(tmp_path):
    path = tmp_path / "c.h5"
    _write_h5(path)  # deflection only, no dither
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run_cli("reep", path, "--out", tmp_path / "out", "--free-air", "0:0.05")
    assert_clean_failure(result, tmp_path, before)
    assert "dither" in result.stderr.decode()


def test_late_bad_sample_leaves_no_partial_output(tmp_path):
    """A NaN deep in the capture stops the run after work began: nothing is published."""
    from afmtool import sim
    from afmtool.io.hdf5 import Hdf5Writer

    captured = sim.simulate("ltv", {"duration_s": 0.03, "step_time_s": 1.0}, seed=0)
    data = {k: np.array(v) for k, v in captured.data.items()}
    data["deflection"][14_000] = np.nan
    path = tmp_path / "late_nan.h5"
    writer = Hdf5Writer(path, captured.sample_rate_hz, captured.channels, captured.metadata)
    writer.write(data)
    writer.close()
    config = tmp_path / "small_chunks.toml"
    config.write_text("[reep]\nchunk_samples = 1000\n")  # reep.h5 is half written when the NaN arrives
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run_cli("reep", path, "--out", tmp_path / "out", "--config", config)
    assert_clean_failure(result, tmp_path, before)
    assert "sample 14000" in result.stderr.decode()


def test_version():
    result = run_cli("--version")
    assert result.returncode == 0
    assert result.stdout.decode().startswith("afmtool ")


def test_progress_bar_only_on_a_tty(monkeypatch, capsys):
    import sys

    from afmtool.cli.progress import progress_bar

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    with progress_bar("x", 10, quiet=False) as update:
        update(5)
    assert capsys.readouterr().err == ""
