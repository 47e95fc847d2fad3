"""The streaming runner (afmtool.pipeline): order, state, errors, threads, progress, decimation."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.capture import ChannelSpec
from afmtool.io.memory import ArrayReader
from afmtool.pipeline import Decimation, Head, Warmup, run_stream


def _reader(n: int, rng: np.random.Generator | None = None, **arrays) -> ArrayReader:
    rng = rng or np.random.default_rng(0)
    data = {"x": rng.standard_normal(n), "y": rng.standard_normal(n), **arrays}
    return ArrayReader(1e6, [ChannelSpec(name) for name in data], data)


class _Recorder:
    """Records every chunk it sees; carries a running sum across chunks (its state)."""

    def __init__(self) -> None:
        self.starts: list[int] = []
        self.head: tuple | None = None
        self.total = 0.0
        self.cumulative: list[np.ndarray] = []

    def prepare(self, head: Head) -> None:
        self.head = (head.first.start, len(head.first), head.info.n_samples, head.reader.info is head.info)

    def step(self, chunk):
        self.starts.append(chunk.start)
        running = self.total + np.cumsum(chunk.data["x"])
        self.total = float(running[-1])
        self.cumulative.append(running)
        return {"cumsum": running}

    def finish(self):
        return np.concatenate(self.cumulative)


class _Sink:
    def __init__(self) -> None:
        self.rows: list[dict] = []

    def append(self, columns) -> None:
        self.rows.append(dict(columns))


def test_chunks_in_order_and_first_chunk_is_stepped() -> None:
    reader = _reader(1000)
    recorder = _Recorder()
    sink = _Sink()
    (cumsum,) = run_stream(reader, [recorder], sink, channels=["x"], chunk_samples=128)
    assert recorder.starts == list(range(0, 1000, 128))
    assert recorder.head == (0, 128, 1000, True)
    assert len(sink.rows) == len(recorder.starts)
    np.testing.assert_allclose(cumsum, np.cumsum(reader._data["x"]), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("chunk_samples", [1, 7, 333, 5000])
def test_state_across_chunks_does_not_depend_on_chunk_size(chunk_samples: int) -> None:
    reader = _reader(1000)
    (whole,) = run_stream(reader, [_Recorder()], channels=["x"], chunk_samples=1000)
    (chunked,) = run_stream(reader, [_Recorder()], channels=["x"], chunk_samples=chunk_samples)
    np.testing.assert_allclose(chunked, whole, rtol=1e-12, atol=1e-12)


def test_without_read_ahead_the_consumer_reads() -> None:
    reader = _reader(1000)
    readers: dict[int, int] = {}  # chunk start -> thread that read it
    blocks = reader.blocks

    def watched(channels, block_samples):
        for chunk in blocks(channels, block_samples):
            readers[chunk.start] = threading.get_ident()
            yield chunk

    reader.blocks = watched
    recorder = _Recorder()
    (cumsum,) = run_stream(reader, [recorder], channels=["x"], chunk_samples=300, read_ahead=0)
    assert set(readers.values()) == {threading.get_ident()}
    assert recorder.starts == [0, 300, 600, 900]
    np.testing.assert_allclose(cumsum, np.cumsum(reader._data["x"]), rtol=1e-12, atol=1e-12)
    readers.clear()
    run_stream(reader, [_Recorder()], channels=["x"], chunk_samples=300, read_ahead=2)
    # the first chunk is read before the stages are prepared; the rest by one read-ahead thread
    assert readers[0] == threading.get_ident()
    ahead = {readers[start] for start in (300, 600, 900)}
    assert len(ahead) == 1 and threading.get_ident() not in ahead
    with pytest.raises(ValueError, match="read_ahead"):
        run_stream(reader, [_Recorder()], channels=["x"], chunk_samples=300, read_ahead=-1)


def test_empty_capture_is_an_input_error() -> None:
    reader = ArrayReader(1e6, [ChannelSpec("x")], {"x": np.zeros(0)}, source="empty.h5")
    with pytest.raises(InputError, match="empty.h5: the capture has no samples"):
        run_stream(reader, [_Recorder()], channels=["x"], chunk_samples=10)


def test_missing_channel_and_nan_are_input_errors() -> None:
    with pytest.raises(InputError, match="no channel 'z'"):
        run_stream(_reader(10), [_Recorder()], channels=["z"], chunk_samples=4)
    x = np.zeros(10)
    x[6] = np.nan
    with pytest.raises(InputError, match="NaN or inf at sample 6"):
        run_stream(_reader(10, x=x), [_Recorder()], channels=["x"], chunk_samples=4)


def test_a_failing_stage_stops_the_read_ahead_thread() -> None:
    class Failing(_Recorder):
        def step(self, chunk):
            if chunk.start >= 20:
                raise InputError("bad chunk")
            return super().step(chunk)

    before = {t.ident for t in threading.enumerate()}
    with pytest.raises(InputError, match="bad chunk"):
        run_stream(_reader(1000), [Failing()], channels=["x"], chunk_samples=10)
    left = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert left == []


def test_side_thread_runs_beside_the_consumer() -> None:
    consumer = threading.get_ident()

    class Side:
        def prepare(self, head: Head) -> None:
            self.side = head.side
            self.where: set[int] = set()
            self.sums: list[float] = []

        def step(self, chunk):
            future = self.side.submit(lambda x: (threading.get_ident(), float(x.sum())), chunk.data["x"])
            ident, total = future.result()
            self.where.add(ident)
            self.sums.append(total)

        def finish(self):
            return self.where, self.sums

    reader = _reader(100)
    ((where, sums),) = run_stream(reader, [Side()], channels=["x"], chunk_samples=30)
    assert len(where) == 1 and consumer not in where  # one worker, not the consumer
    np.testing.assert_allclose(sums, [reader._data["x"][i : i + 30].sum() for i in range(0, 100, 30)])


def test_progress_from_the_consumer_thread() -> None:
    calls: list[tuple[int, int]] = []
    run_stream(
        _reader(1000), [_Recorder()], channels=["x"], chunk_samples=300,
        progress=lambda done: calls.append((done, threading.get_ident())),
    )
    assert [done for done, _ in calls] == [300, 600, 900, 1000]
    assert {ident for _, ident in calls} == {threading.get_ident()}


def test_prologue_sees_the_stream_first() -> None:
    seen: list[int] = []

    def prologue(chunks):
        held = [next(chunks), next(chunks)]  # reads ahead, as the free-air resolution does
        seen.extend(c.start for c in held)
        yield from held[1:]  # and may drop what the stages must not see
        yield from chunks

    recorder = _Recorder()
    run_stream(_reader(100), [recorder], channels=["x"], chunk_samples=25, prologue=prologue)
    assert seen == [0, 25]
    assert recorder.head[0] == 25
    assert recorder.starts == [25, 50, 75]


def test_columns_of_stages_merge_and_must_not_collide() -> None:
    class Other(_Recorder):
        def step(self, chunk):
            super().step(chunk)
            return {"y2": chunk.data["y"] * 2}

    class Silent(_Recorder):
        def step(self, chunk):
            super().step(chunk)

    sink = _Sink()
    run_stream(_reader(50), [_Recorder(), Silent(), Other()], sink, channels=["x", "y"], chunk_samples=20)
    assert [sorted(row) for row in sink.rows] == [["cumsum", "y2"]] * 3
    with pytest.raises(ValueError, match="cumsum"):
        run_stream(_reader(50), [_Recorder(), _Recorder()], sink, channels=["x"], chunk_samples=20)


def _naive_kept(start: int, n: int, every: int) -> list[int]:
    return [i for i in range(start, start + n) if (i + 1) % every == 0]


def test_decimation_matches_the_naive_rule(rng: np.random.Generator) -> None:
    for _ in range(300):
        every = int(rng.integers(1, 40))
        start = int(rng.integers(0, 10_000))
        n = int(rng.integers(0, 200))
        decimation = Decimation(every)
        expected = _naive_kept(start, n, every)
        assert decimation.kept_index(start, n).tolist() == expected
        assert decimation.count(start, n) == len(expected)
        values = np.arange(start, start + n)
        assert decimation.take(values, start).tolist() == expected
        assert np.vstack([values, values])[:, decimation.keep(start)].tolist() == [expected, expected]
        if expected:
            assert start + decimation.first_kept(start) == expected[0]
    every = 7
    whole = _naive_kept(0, 100, every)
    assert Decimation(every).index_of_kept(np.arange(len(whole))).tolist() == whole


def test_decimation_over_chunks_is_the_decimation_of_the_whole(rng: np.random.Generator) -> None:
    values = rng.standard_normal(1001)
    decimation = Decimation(13)
    pieces = [decimation.take(values[s : s + 97], s) for s in range(0, 1001, 97)]
    np.testing.assert_array_equal(np.concatenate(pieces), values[12::13])


@pytest.mark.parametrize("every", [0, -1, 1.5, True])
def test_decimation_refuses_a_bad_factor(every) -> None:
    with pytest.raises(ValueError, match="every="):
        Decimation(every)


def test_warmup_masks_the_first_samples() -> None:
    warmup = Warmup.of_windows(2.0, 0.99)
    assert warmup.samples == int(2.0 / (1 - 0.99))
    kept = Decimation(7).kept_index(150, 200)
    first = warmup.first_settled(kept)
    assert kept[first] >= warmup.samples and kept[first - 1] < warmup.samples
    masked = warmup.mask(np.ones(len(kept)), kept)
    assert np.isnan(masked[:first]).all() and (masked[first:] == 1).all()
    with pytest.raises(ValueError):
        Warmup(-1)


class _Series:
    """A ResultWriter stand-in: keeps the appended columns in memory."""

    def __init__(self) -> None:
        self.parts: dict[str, list[np.ndarray]] = {}

    def append(self, columns) -> None:
        for name, values in columns.items():
            self.parts.setdefault(name, []).append(np.asarray(values))

    def put(self, *args, **kwargs) -> None:
        """Whole arrays are not compared here."""

    def series(self, prefix: str = "") -> dict[str, np.ndarray]:
        return {prefix + name: np.concatenate(parts) for name, parts in self.parts.items()}


class _Prefixed:
    """A stage whose columns are renamed, so two analyses can share one sink."""

    def __init__(self, stage, prefix: str) -> None:
        self.stage, self.prefix = stage, prefix

    def prepare(self, head: Head) -> None:
        self.stage.prepare(head)

    def step(self, chunk):
        return {self.prefix + name: values for name, values in self.stage.step(chunk).items()}

    def finish(self):
        return self.stage.finish()


def test_two_analyses_in_one_pass_equal_their_own_runs() -> None:
    """REEP and probe loss composed on one read of the capture give what each gives alone, to the bit."""
    from afmtool.analyses.probeloss import ProbeLossStage, run_probeloss
    from afmtool.analyses.reep import ReepStage, run_reep
    from afmtool.config import resolve
    from afmtool.config.params import ProbeLossParams, ReepParams
    from afmtool.io.registry import open_capture
    from tests.conftest import SAMPLE_DATA

    reep_params = resolve(ReepParams, {"chunk_samples": 30_000})
    loss_params = resolve(ProbeLossParams, {"chunk_samples": 30_000})
    with open_capture(SAMPLE_DATA / "raster_grating.h5") as reader:
        alone_reep, alone_loss = _Series(), _Series()
        reep_result = run_reep(reader, reep_params, alone_reep)
        loss_result = run_probeloss(reader, loss_params, alone_loss)
        reep, loss = ReepStage(reader, reep_params), ProbeLossStage(reader, loss_params)

        def both_free_air(chunks):  # each reads its free-air segment ahead of the same stream
            return loss.free_air_prologue(reep.free_air_prologue(chunks))

        together = _Series()
        reep_together, loss_events = run_stream(
            reader, [_Prefixed(reep, "reep/"), _Prefixed(loss, "loss/")], together,
            channels=sorted({*reep.channels, "deflection", "dither"}), chunk_samples=30_000, prologue=both_free_air,
        )
    expected = {**alone_reep.series("reep/"), **alone_loss.series("loss/")}
    actual = together.series()
    assert sorted(actual) == sorted(expected)
    for name, values in expected.items():
        np.testing.assert_array_equal(actual[name], values, err_msg=name)
    assert reep_together.results == reep_result.results
    index_events, _ = loss_events
    assert len(index_events) == loss_result.results.events_total > 0
    n = loss_result.results.n_samples
    assert float(np.sum(index_events.duration)) / n == loss_result.results.loss_fraction
