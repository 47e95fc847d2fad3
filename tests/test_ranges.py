"""Random access for Dask workers (issue 19, item 1): the workers read their segments from the shared file.

A range read through :func:`afmtool.io.ranges.range_source` must give exactly the values the chunks
carry, through every view that can sit over an HDF5 capture (a metadata segment, units converted by
``--invols`` and ``--units``).  tests/test_split.py checks that a Dask split run sends sample indices,
not samples, and still equals the sequential run.
"""

from __future__ import annotations

import json
import pickle

import h5py
import numpy as np

from afmtool.io.hdf5 import Hdf5Ranges
from afmtool.io.ranges import OffsetRanges, ScaledRanges, range_source
from afmtool.io.registry import open_capture
from afmtool.io.units import Calibration, UnitsReader


def _segmented_capture(path, rng):
    n = 10_000
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 500e3
        segments = [{"name": "approach", "start_sample": 0, "n_samples": 4000, "sample_rate_hz": 500e3},
                    {"name": "retract", "start_sample": 4000, "n_samples": 6000, "sample_rate_hz": 500e3}]
        f.attrs["metadata"] = json.dumps({"capture_segments": segments})
        group = f.create_group("channels")
        group.create_dataset("defl_raw", data=rng.normal(size=n).astype(np.float32), chunks=(512,)).attrs["units"] = "V"
        group.create_dataset("dither", data=rng.normal(size=n)).attrs["units"] = "mV"
    return path


def test_range_reads_equal_the_chunks_through_segment_and_units(tmp_path, rng):
    path = _segmented_capture(tmp_path / "seg.h5", rng)
    reader = UnitsReader(
        open_capture(path, channel_map={"deflection": "/channels/defl_raw", "dither": "/channels/dither"}, segment="retract"),
        Calibration(invols_nm_per_v=45.0),
    )
    with reader:
        channels = ("deflection", "dither")
        chunks = list(reader.blocks(channels, 1000))
        source = range_source(reader)
        assert isinstance(source, ScaledRanges) and isinstance(source.source, OffsetRanges)
        assert isinstance(source.source.source, Hdf5Ranges) and source.source.first == 4000
        source = pickle.loads(pickle.dumps(source))  # what a Dask worker receives
        for start, stop in ((0, 1000), (1500, 3700), (5999, 6000), (2000, 2000)):
            got = source.read(channels, start, stop)
            for name in channels:
                expected = np.concatenate([c.data[name] for c in chunks])[start:stop]
                np.testing.assert_array_equal(got[name], expected)
        # the deflection was scaled by the InvOLS, the dither from mV
        assert reader.conversions["deflection"].factor == 45.0
        np.testing.assert_array_equal(source.read(("dither",), 0, 3)["dither"],
                                      h5py.File(path)["channels/dither"][4000:4003] * 1e-3)


def test_no_range_source_without_random_access(tmp_path, rng):
    from afmtool.io.synthetic_drive import SyntheticDriveReader

    path = _segmented_capture(tmp_path / "seg.h5", rng)
    with open_capture(path, channel_map={"deflection": "/channels/defl_raw", "dither": "/channels/dither"}) as reader:
        assert range_source(reader) is not None
        assert range_source(SyntheticDriveReader(reader, ((70e3, 0.1),), None)) is None
    csv = tmp_path / "c.csv"
    csv.write_text("# sample_rate_hz: 1000\ndeflection,dither\n" + "".join(f"{i},{-i}\n" for i in range(50)))
    with open_capture(csv) as reader:
        assert range_source(reader) is None
