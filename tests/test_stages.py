"""The estimator stages (afmtool.estimators.stages) and the streaming stepped-sine lock-in.

Streaming against batch: each stage stepped through uneven chunks gives
what the batch estimator (or a plain-Python reference) gives on the whole
record, to rounding.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.estimators.frequency_response import h1_estimate
from afmtool.estimators.stages import RecordStage, ResponseStage, SegmentStage, run_stages
from afmtool.estimators.stepped_sine import SteppedSineAccumulator, stepped_sine_response
from afmtool.io.capture import ChannelSpec, Chunk
from afmtool.io.memory import ArrayReader
from afmtool.pipeline import run_stream

FS = 100e3


def _uneven_chunks(data: dict[str, np.ndarray], rng) -> list[Chunk]:
    n = next(iter(data.values())).size
    cuts = np.unique(np.concatenate(([0, n], rng.integers(1, n, 25))))
    return [Chunk(int(a), {k: v[a:b] for k, v in data.items()}) for a, b in zip(cuts[:-1], cuts[1:])]


def _stepped_record(rng, n=60_000, offset=3.0):
    """Three sine steps with a DC offset (cancellation in the power sums) and noise; output = 0.5·input delayed."""
    steps = [(0.0, 0.2, 1.1e3), (0.2, 0.4, 2.7e3), (0.4, 0.6, 6.3e3)]
    t = np.arange(n) / FS
    x = np.zeros(n)
    y = np.zeros(n)
    for start, end, f in steps:
        inside = (t >= start) & (t < end)
        x[inside] = np.sin(2 * np.pi * f * t[inside])
        y[inside] = 0.5 * np.sin(2 * np.pi * f * t[inside] - 0.3)
    x += offset + 1e-3 * rng.standard_normal(n)
    y += offset + 1e-3 * rng.standard_normal(n)
    return x, y, [{"start_s": a, "end_s": b, "frequency_hz": f} for a, b, f in steps]


def _naive_lock_in(values, first, f):
    """The textbook lock-in of one window: (2/N) Σ (v − mean) e^{−j2πf n/fs}, and the mean-removed power."""
    total, power, mean = 0j, 0.0, sum(values) / len(values)
    for i, v in enumerate(values):
        total += (v - mean) * complex(math.cos(2 * math.pi * f * (first + i) / FS),
                                      -math.sin(2 * math.pi * f * (first + i) / FS))
        power += (v - mean) ** 2
    return 2 * total / len(values), power / len(values)


def test_stepped_sine_accumulator_matches_a_plain_lock_in_over_uneven_chunks(rng):
    x, y, segments = _stepped_record(rng)
    acc = SteppedSineAccumulator(FS, segments, settle_fraction=0.5, min_periods=10)
    for chunk in _uneven_chunks({"x": x, "y": y}, rng):
        acc.add(chunk.data["x"], chunk.data["y"])
    fr = acc.result()
    worst = 0.0
    for k, seg in enumerate(segments):
        stop = int(math.floor(seg["end_s"] * FS + 1e-9))
        periods = int(math.floor(0.5 * (seg["end_s"] - seg["start_s"]) * seg["frequency_hz"] + 1e-9))
        first = stop - int(round(periods * FS / seg["frequency_hz"]))
        x_amp, _ = _naive_lock_in(x[first:stop].tolist(), first, seg["frequency_hz"])
        y_amp, y_power = _naive_lock_in(y[first:stop].tolist(), first, seg["frequency_hz"])
        h = y_amp / x_amp
        worst = max(worst, abs(fr.response[k] - h) / abs(h))
        assert fr.coherence[k] == pytest.approx(min(abs(y_amp) ** 2 / 2 / y_power, 1.0), rel=1e-9)
    print(f"stepped lock-in, streamed vs plain: worst relative difference {worst:.2e}")
    assert worst < 1e-12
    assert np.allclose(np.abs(fr.response), 0.5, rtol=1e-3)
    assert np.allclose(np.angle(fr.response), -0.3, atol=1e-3)


def test_stepped_sine_accumulator_refuses_a_step_after_the_record(rng):
    x, y, segments = _stepped_record(rng)
    acc = SteppedSineAccumulator(FS, segments)
    acc.add(x[:50_000], y[:50_000])  # the last step ends at sample 60,000
    with pytest.raises(InputError, match=r"segments\[2\] ends at 0.6 s, after the records end"):
        acc.result()


def test_response_stage_h1_equals_the_batch_estimate(rng):
    n = 40_000
    x = rng.standard_normal(n)
    y = np.convolve(x, [0.5, 0.3, -0.2], mode="same") + 0.01 * rng.standard_normal(n)
    (responses,) = run_stages(_uneven_chunks({"x": x, "y": y}, rng),
                              [ResponseStage("x", ("y",), method="h1", nperseg=1024)], FS)
    batch = h1_estimate(x, y, FS, nperseg=1024)
    np.testing.assert_allclose(responses["y"].response, batch.response, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(responses["y"].coherence, batch.coherence, rtol=1e-10, atol=1e-12)


def test_response_stage_stepped_without_segments_finds_the_steps_on_the_kept_record(rng):
    x, y, segments = _stepped_record(rng)
    found = []

    def find_steps(drive, fs):
        found.append(drive.size)
        return segments

    (responses,) = run_stages(_uneven_chunks({"x": x, "y": y}, rng),
                              [ResponseStage("x", ("y",), method="stepped", find_steps=find_steps)], FS)
    assert found == [x.size]
    np.testing.assert_allclose(responses["y"].response, stepped_sine_response(x, y, FS, segments).response,
                               rtol=1e-12)


class _Announcing(ArrayReader):
    """An ArrayReader whose info announces ``announced`` samples but whose blocks hold all of its data."""

    def __init__(self, data, announced) -> None:
        super().__init__(FS, [ChannelSpec(name) for name in data], data)
        self._n = next(iter(data.values())).size
        self.info = dataclasses.replace(self.info, n_samples=announced)

    def blocks(self, channels, block_samples):
        for start in range(0, self._n, block_samples):
            yield Chunk(start, {name: self._data[name][start : start + block_samples] for name in channels})


def _reader(data, announced="true"):
    return ArrayReader(FS, [ChannelSpec(name) for name in data], data) if announced == "true" else _Announcing(
        data, announced)


@pytest.mark.parametrize("announced", [None, 1000, 0])
def test_record_stage_keeps_the_whole_record_whatever_length_the_reader_announces(rng, announced):
    data = {"a": rng.standard_normal(5000), "b": rng.standard_normal(5000)}
    (kept,) = run_stream(_reader(data, announced), [RecordStage(("b",))], channels=("a", "b"), chunk_samples=777)
    assert set(kept) == {"b"}
    np.testing.assert_array_equal(kept["b"], data["b"])


def test_segment_stage_reads_only_up_to_its_end_and_says_when_the_capture_is_short(rng):
    data = {"a": rng.standard_normal(10_000)}
    read = []

    class Counting(ArrayReader):
        def blocks(self, channels, block_samples):
            for chunk in super().blocks(channels, block_samples):
                read.append(chunk.start)
                yield chunk

    reader = Counting(FS, [ChannelSpec("a")], data)
    stage = SegmentStage(("a",), 1500, 2600)
    (segment,) = run_stream(reader, [stage], channels=("a",), chunk_samples=1000, prologue=stage.until_end)
    np.testing.assert_array_equal(segment["a"], data["a"][1500:2600])
    assert max(read) <= 4000  # the prologue stops the stream after the segment's end (read-ahead aside)
    short = SegmentStage(("a",), 9000, 12_000)
    with pytest.raises(InputError, match="segment ends at sample 12000 but the capture has only 10000 samples"):
        run_stream(_reader(data), [short], channels=("a",), chunk_samples=1000, prologue=short.until_end)


def test_info_summary_through_the_pipeline_matches_numpy(rng):
    from afmtool.analyses.info import summarize

    data = {"a": rng.standard_normal(12_345) + 2.0, "b": rng.uniform(-5, 1, 12_345)}
    summary = summarize(_reader(data), chunk_samples=1000)
    assert summary.n_samples == 12_345
    for stats in summary.channels:
        values = data[stats.name]
        assert (stats.min, stats.max) == (values.min(), values.max())
        assert stats.mean == pytest.approx(values.mean(), rel=1e-12)
        assert stats.rms == pytest.approx(np.sqrt(np.mean(values**2)), rel=1e-12)
    empty = summarize(_reader({"a": np.empty(0)}))
    assert empty.n_samples == 0 and math.isnan(empty.channels[0].mean)
