"""The scratch spill that lets kalman-bank read its capture once (:mod:`afmtool.io.spill`)."""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.io.capture import ChannelSpec
from afmtool.io.memory import ArrayReader
from afmtool.io.spill import SpillingReader
from afmtool.runtime.outputs import OutputDir

CHANNELS = ("deflection", "dither", "z_piezo")


def _reader(data: dict[str, np.ndarray]) -> ArrayReader:
    specs = [ChannelSpec(name, "m") for name in data]
    return ArrayReader(1e6, specs, data)


def _data(n: int, rng: np.random.Generator, exact_float32: bool) -> dict[str, np.ndarray]:
    data = {name: rng.standard_normal(n) for name in (*CHANNELS, "current")}
    if exact_float32:
        data = {name: values.astype(np.float32).astype(np.float64) for name, values in data.items()}
    return data


def _read_all(reader, channels, block):
    parts = {name: [] for name in channels}
    for chunk in reader.blocks(list(channels), block):
        for name in channels:
            parts[name].append(chunk.data[name])
    return {name: np.concatenate(values) for name, values in parts.items()}


@pytest.mark.parametrize("exact_float32", [True, False])
def test_the_replay_is_the_pass_bit_for_bit(tmp_path, exact_float32):
    data = _data(10_007, np.random.default_rng(1), exact_float32)
    with SpillingReader(_reader(data), CHANNELS, tmp_path / "spill") as spill:
        # the pass reads fewer channels than the replay needs: the spill reads the others along
        seen = _read_all(spill, ("deflection",), 999)
        assert set(seen) == {"deflection"}
        replay = spill.replay()
        assert replay.info.n_samples == 10_007
        again = _read_all(replay, CHANNELS, 4096)
        # float32 on disk only where every sample survives it: 12 bytes a sample, else 24
        itemsize = 4 if exact_float32 else 8
        assert spill.dtype.itemsize == itemsize
        assert (tmp_path / "spill").stat().st_size == 10_007 * 3 * itemsize
    for name in CHANNELS:
        np.testing.assert_array_equal(again[name], data[name])
    assert not (tmp_path / "spill").exists()  # close removes the scratch file


def test_a_later_chunk_that_needs_float64_widens_what_was_spilled(tmp_path):
    data = _data(5_000, np.random.default_rng(2), exact_float32=True)
    data["dither"][4_321] += 1e-12  # one sample float32 cannot hold
    with SpillingReader(_reader(data), CHANNELS, tmp_path / "spill") as spill:
        _read_all(spill, CHANNELS, 1000)
        assert spill.dtype == np.float64
        again = _read_all(spill.replay(), CHANNELS, 777)
    for name in CHANNELS:
        np.testing.assert_array_equal(again[name], data[name])


def test_a_pass_that_rereads_the_start_spills_each_sample_once(tmp_path):
    data = _data(6_000, np.random.default_rng(3), exact_float32=True)
    with SpillingReader(_reader(data), CHANNELS, tmp_path / "spill") as spill:
        scan = spill.blocks(["dither"], 1500)
        next(scan), next(scan)  # a look ahead at the start (3,000 samples), abandoned
        _read_all(spill, ("deflection", "z_piezo"), 1024)  # then the pass, from sample 0
        assert spill.spilled == 6_000
        again = _read_all(spill.replay(), CHANNELS, 6_000)
    for name in CHANNELS:
        np.testing.assert_array_equal(again[name], data[name])


def test_the_scratch_folder_never_reaches_the_output(tmp_path):
    with OutputDir(tmp_path / "out") as staged:
        staged.path("report.json").write_text("{}")
        (staged.scratch_folder() / "left.spill").write_bytes(b"x")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["report.json"]


def test_the_replay_offers_no_ranges_even_where_the_capture_does(tmp_path):
    # a Dask worker would read the capture itself: the second read the spill avoids
    from afmtool.io.ranges import range_source

    class Ranged(ArrayReader):
        def ranges(self):
            return "the capture's own ranges"

    data = _data(1000, np.random.default_rng(5), exact_float32=True)
    reader = Ranged(1e6, [ChannelSpec(name, "m") for name in data], data)
    with SpillingReader(reader, CHANNELS, tmp_path / "spill") as spill:
        assert range_source(spill) == "the capture's own ranges"  # pass 1 reads the capture, workers too
        _read_all(spill, CHANNELS, 500)
        assert range_source(spill.replay()) is None
