"""Segment and renaming views over any reader, on an in-memory capture."""

from __future__ import annotations

import io

import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.csv import CsvReader
from afmtool.io.views import RenamedView, SegmentView, segments_from_metadata, select_segment


class _Ramp(ReaderBase):
    def __init__(self, n=1000):
        self._a, self._b = np.arange(n, dtype=float), -np.arange(n, dtype=float)
        segments = (SegmentSpec("approach", 0, 400, 10.0), SegmentSpec("dwell", 400, 100, 10.0),
                    SegmentSpec("retract", 500, 500, 10.0))
        self.info = CaptureInfo("ramp", "memory", 10.0, (ChannelSpec("a", "V"), ChannelSpec("b", "nm")), n, {}, (),
                                segments)

    def blocks(self, channels, block_samples):
        for start in range(0, len(self._a), block_samples):
            data = {"a": self._a, "b": self._b}
            yield Chunk(start, {c: data[c][start : start + block_samples] for c in channels})

    def truth(self):
        return {}


@pytest.mark.parametrize("block", [1, 7, 100, 399, 400, 401, 5000])
def test_segment_view_is_block_size_independent(block):
    view = SegmentView(_Ramp(), select_segment(_Ramp().info.segments, "dwell", "ramp"))
    chunks = list(view.blocks(["b", "a"], block))
    assert [c.start for c in chunks] == list(np.cumsum([0] + [len(c) for c in chunks[:-1]]))
    np.testing.assert_array_equal(np.concatenate([c.data["a"] for c in chunks]), np.arange(400, 500))
    assert view.info.n_samples == 100 and view.info.metadata["segment"]["name"] == "dwell"


def test_select_segment_by_name_or_number():
    segments = _Ramp().info.segments
    assert select_segment(segments, "retract", "x") == 2 and select_segment(segments, "1", "x") == 1
    for bad in ("3", "-1", "Retract", ""):
        with pytest.raises(InputError, match="no segment"):
            select_segment(segments, bad, "x")


def test_renamed_view_keeps_order_and_refuses_unknown_sources():
    view = RenamedView(_Ramp(), {"deflection": "b"})
    assert [(c.name, c.units) for c in view.info.channels] == [("a", "V"), ("deflection", "nm")]
    chunk = next(view.blocks(["deflection"], 3))
    np.testing.assert_array_equal(chunk.data["deflection"], [0, -1, -2])
    with pytest.raises(InputError, match="no channel 'CH9'"):
        RenamedView(_Ramp(), {"deflection": "CH9"})


def test_segments_from_metadata_are_checked():
    good = {"capture_segments": [{"name": "a", "start_sample": 0, "n_samples": 5, "sample_rate_hz": 10}]}
    assert segments_from_metadata(good, "f", 5) == (SegmentSpec("a", 0, 5, 10.0),)
    for bad in ([{"name": "a", "start_sample": 3, "n_samples": 5, "sample_rate_hz": 10}],
                [{"name": "a", "start_sample": -1, "n_samples": 1, "sample_rate_hz": 10}], "x", [{"name": "a"}]):
        with pytest.raises(InputError):
            segments_from_metadata({"capture_segments": bad}, "f", 5)


def test_csv_with_a_byte_order_mark_before_its_comments():
    text = "\ufeff# sample_rate_hz: 1000\n# units.deflection: nm\nt,deflection\n0,1\n0.001,2\n"
    reader = CsvReader("bom.csv", stream=io.StringIO(text))
    assert reader.info.sample_rate_hz == 1000 and reader.info.channels == (ChannelSpec("deflection", "nm"),)


def test_csv_file_with_a_byte_order_mark(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbf# sample_rate_hz: 1000\nt,deflection\n0,1\n0.001,2\n")
    reader = CsvReader(path)
    assert reader.info.sample_rate_hz == 1000 and reader.info.channel_names == ("deflection",)
    reader.close()
