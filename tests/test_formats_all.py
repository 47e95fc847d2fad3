"""Every format reads the shared fixtures; simulate -> every format -> back; convert every pair."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmtool import sim
from afmtool.analyses.convert import convert_capture
from afmtool.io.chunks import iter_chunks
from afmtool.io.memory import ArrayReader
from afmtool.io.registry import FORMATS, open_capture
from afmtool.runtime.atomic import atomic_path
from tests.conftest import REPO, run_cli

SUFFIX = {"hdf5": ".h5", "csv": ".csv", "ros1": ".bag", "ros2-mcap": "_mcap", "ros2-sqlite3": "_sqlite3"}
FIXTURES = ["capture_v1.h5", "capture_v1.csv", "capture_v1_ros1.bag", "capture_v1_ros2_mcap"]


def _read_all(path):
    with open_capture(path) as reader:
        parts = list(iter_chunks(reader, reader.info.channel_names, 1000))
        data = {n: np.concatenate([p.data[n] for p in parts]) for n in reader.info.channel_names}
        return reader.info, data


@pytest.mark.parametrize("name", FIXTURES)
def test_reads_every_fixture(shared, name):
    expected = np.load(shared / "fixtures" / "capture_v1_expected.npy")
    info, data = _read_all(shared / "fixtures" / name)
    assert info.sample_rate_hz == 500000.0
    if not name.endswith(".csv"):  # the CSV fixture carries no metadata line
        assert info.metadata["cantilever"]["f0_hz"] == 71000
    for i, channel in enumerate(("dither", "deflection", "z_piezo")):
        if name.endswith(".csv"):  # 10 significant digits
            np.testing.assert_allclose(data[channel], expected[i], rtol=1e-6, atol=1e-12)
        else:
            np.testing.assert_array_equal(data[channel], expected[i].astype(np.float64))


@pytest.fixture(scope="module")
def simulated():
    return sim.simulate("tapping", {"duration_s": 0.004, "program": "force-curve"}, seed=7)


def _write(captured_reader, path: Path, fmt: str):
    with atomic_path(path, directory=fmt.startswith("ros2")) as temp:
        convert_capture(captured_reader, temp, fmt, chunk_samples=777)


def _memory(captured):
    return ArrayReader(captured.sample_rate_hz, captured.channels, captured.data, captured.metadata, captured.truth)


@pytest.mark.parametrize("fmt", FORMATS)
def test_simulate_round_trip(tmp_path, simulated, fmt):
    path = tmp_path / f"capture{SUFFIX[fmt]}"
    _write(_memory(simulated), path, fmt)
    info, data = _read_all(path)
    assert info.sample_rate_hz == simulated.sample_rate_hz
    assert dict(info.metadata) == json.loads(json.dumps(dict(simulated.metadata)))
    assert [(c.name, c.units) for c in info.channels] == [(c.name, c.units) for c in simulated.channels]
    for name, values in simulated.data.items():
        np.testing.assert_array_equal(data[name], values)  # float64 everywhere: exact


@pytest.mark.parametrize("source", FORMATS)
@pytest.mark.parametrize("target", FORMATS)
def test_convert_every_pair(tmp_path, simulated, source, target):
    first = tmp_path / f"a{SUFFIX[source]}"
    _write(_memory(simulated), first, source)
    second = tmp_path / f"b{SUFFIX[target]}"
    with open_capture(first) as reader:
        _write(reader, second, target)
    info, data = _read_all(second)
    for name, values in simulated.data.items():
        np.testing.assert_array_equal(data[name], values)
    assert info.metadata["cantilever"] == simulated.metadata["cantilever"]


def test_convert_cli_keeps_truth_between_hdf5(tmp_path):
    src = tmp_path / "s.h5"
    assert run_cli("simulate", "ltv", "-o", src, "--set", "duration_s=0.002").returncode == 0
    dst = tmp_path / "d.h5"
    result = run_cli("convert", src, dst, "--compression", "gzip")
    assert result.returncode == 0, result.stderr.decode()
    with open_capture(dst) as reader:
        assert "f0_hz" in reader.info.truth_names


def test_stream_simulate_into_info():
    """`afmtool simulate tapping ... -o - --format csv | afmtool info - --json`."""
    producer = subprocess.Popen(
        [sys.executable, "-m", "afmtool", "simulate", "tapping", "-o", "-", "--format", "csv",
         "--set", "duration_s=0.01"],
        stdout=subprocess.PIPE,
        cwd=REPO,
    )
    consumer = subprocess.run(
        [sys.executable, "-m", "afmtool", "info", "-", "--json"],
        stdin=producer.stdout,
        capture_output=True,
        cwd=REPO,
        timeout=300,
    )
    producer.stdout.close()
    assert producer.wait(timeout=300) == 0
    assert consumer.returncode == 0, consumer.stderr.decode()
    summary = json.loads(consumer.stdout)
    assert summary["n_samples"] == 5000
    assert summary["format"] == "csv"
    assert {c["name"] for c in summary["channels"]} >= {"dither", "deflection"}


def test_info_foreign_hdf5_cli(shared):
    result = run_cli(
        "info", "--channel", "deflection=/s", "--sample-rate", "1.15e6", "--json",
        shared / "data" / "fm_kpfm_displacement.h5",
    )
    assert result.returncode == 0, result.stderr.decode()
    assert json.loads(result.stdout)["n_samples"] == 762_375
