"""One streaming runner for every command: capture → chunks → stages → columns → sink.

A command builds one or more :class:`Stage` objects (each carries its
filter state across chunks) and hands them to :func:`run_stream`, which
owns what every command used to write by hand:

- reading the capture in chunks (:func:`afmtool.io.chunks.iter_chunks`:
  missing channels, NaN and inf are refused there);
- an optional *prologue* over the chunk stream (the free-air resolution,
  which reads the free-air segment ahead and hands the stream on);
- the empty-capture error;
- read-ahead in a background thread (:func:`afmtool.io.prefetch.prefetch`);
- one side thread, on which a stage runs a second kernel beside its own
  (both release the GIL);
- progress, from the consumer thread;
- merging the stages' columns per chunk and handing them to the sink;
- with a :class:`Split`, running the stages' kernels on several chunks at
  once (local threads or a Dask cluster), each chunk's kernels started
  from a fresh state a warm-up ahead of it (:class:`ChunkKernels`), and the
  rest of each stage in capture order.  On a Dask cluster each task reads
  its chunk and warm-up from the shared file itself when the reader offers
  random access (:mod:`afmtool.io.ranges`: HDF5 and the views over it);
  otherwise the samples travel with the task.

This is the only module outside :mod:`afmtool.io` that calls
``iter_chunks`` or ``prefetch`` (``tests/test_architecture.py`` checks it).
The rule of which samples a decimated output keeps lives in
:class:`Decimation`, and the summaries' warm-up in :class:`Warmup`.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol, Self, runtime_checkable

import numpy as np

from afmtool.errors import InputError
from afmtool.estimators.decimation import Decimation
from afmtool.io.capture import CaptureInfo, CaptureReader, Chunk
from afmtool.io.chunks import iter_chunks
from afmtool.io.prefetch import prefetch
from afmtool.io.ranges import RangeSource, range_source

__all__ = [
    "ChunkKernels",
    "Decimation",
    "Head",
    "SideThread",
    "Split",
    "SplitStage",
    "Stage",
    "Warmup",
    "lead_start",
    "read_ahead",
    "read_segment",
    "replay_held",
    "run_stream",
]


@dataclass(frozen=True)
class Warmup:
    """The first ``samples`` capture samples, which the summaries leave out.

    A recursive estimator with forgetting factor λ has not forgotten its
    initial state until about ``warmup_windows / (1 − λ)`` samples; its
    output is written but not summarised before then.

    Parameters
    ----------
    samples : int
        Capture samples in the warm-up (>= 0).
    """

    samples: int

    def __post_init__(self) -> None:
        if self.samples < 0:
            raise ValueError(f"samples={self.samples!r} must be >= 0")

    @classmethod
    def of_windows(cls, windows: float, lam: float) -> Warmup:
        """``int(windows / (1 − λ))`` samples: ``windows`` exponential windows of forgetting factor ``lam``.

        Raises ConfigError when that is no sample count (``warmup_windows = 1e308``).
        """
        from afmtool.config.samples import check_count

        return cls(int(check_count(windows / (1.0 - lam), "warmup_windows", windows)))

    def first_settled(self, kept_index: np.ndarray) -> int:
        """Position in the sorted ``kept_index`` of the first sample past the warm-up."""
        return int(np.searchsorted(kept_index, self.samples))

    def settled(self, kept_index: np.ndarray) -> np.ndarray:
        """Boolean mask: True where the capture index is past the warm-up."""
        return np.asarray(kept_index) >= self.samples

    def mask(self, values: np.ndarray, kept_index: np.ndarray) -> np.ndarray:
        """``values`` with NaN where the sample is still in the warm-up."""
        return np.where(self.settled(kept_index), values, np.nan)


class SideThread:
    """One worker thread for a stage's second kernel (numba kernels release the GIL).

    ``submit(fn, *args)`` returns a :class:`concurrent.futures.Future`; the
    thread starts on the first call and ends when :func:`run_stream` does.
    """

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="afmtool-side")

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """Run ``fn(*args, **kwargs)`` on the side thread."""
        return self._pool.submit(fn, *args, **kwargs)

    def shutdown(self) -> None:
        """Wait for submitted work, then end the thread."""
        self._pool.shutdown(wait=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


@dataclass(frozen=True)
class Head:
    """What a stage sees before the first step.

    Attributes
    ----------
    reader : CaptureReader
        The open capture.
    info : CaptureInfo
        ``reader.info``.
    first : Chunk
        The first chunk (after the prologue), for spectral estimates and
        drive lines; it is also handed to ``step`` as usual.  A stage should
        not keep it past ``prepare``, so that it is freed once stepped.
    side : SideThread
        The run's side thread.
    """

    reader: CaptureReader
    info: CaptureInfo
    first: Chunk
    side: SideThread


class Stage(Protocol):
    """One analysis over the chunk stream, carrying its state across chunks."""

    def prepare(self, head: Head) -> None:
        """Set up from the capture and its first chunk, before any step."""

    def step(self, chunk: Chunk) -> Mapping[str, np.ndarray] | None:
        """Process one chunk; return columns for the sink, or None."""

    def finish(self) -> Any:
        """The stage's result, after the last chunk."""


@dataclass(frozen=True)
class Split:
    """How :func:`run_stream` spreads the stages' kernels over one capture.

    Attributes
    ----------
    jobs : int
        Chunks whose kernels run at once on this machine's threads (numba
        kernels release the GIL); 1 runs the capture sequentially.
    scheduler : str or None
        A Dask scheduler address (``tcp://host:8786``): the kernels run on
        its workers instead of local threads.
    scheduler_timeout_s : float
        Seconds the scheduler has to accept the connection and answer it
        (:func:`afmtool.io.scheduler.probe_scheduler`).
    """

    jobs: int = 1
    scheduler: str | None = None
    scheduler_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if not (isinstance(self.jobs, int) and self.jobs >= 1):
            raise ValueError(f"jobs={self.jobs!r} must be an integer >= 1")

    @classmethod
    def of(cls, jobs: int | None, scheduler: str | None = None, scheduler_timeout_s: float = 10.0) -> Split:
        """``--jobs`` (None: every core this process may use), ``--scheduler`` and ``--scheduler-timeout``."""
        if jobs is None:
            jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return cls(int(jobs), scheduler or None, float(scheduler_timeout_s))

    @property
    def parallel(self) -> bool:
        """Whether chunks run at once (more than one job, or a cluster)."""
        return self.jobs > 1 or self.scheduler is not None


class ChunkKernels(Protocol):
    """A stage's per-sample recursions as a pure, picklable function of the samples.

    Every recursion here forgets its past (EW-RLS weighs it by λⁿ, an
    observer's error decays with its poles, a low-pass with its own), so the
    output on a chunk computed from a fresh state started ``lead_samples``
    earlier equals the sequential output to a stated tolerance.  Such an
    object runs on a worker thread or a Dask worker and touches no stage
    state.

    Attributes
    ----------
    lead_samples : int
        Warm-up W: samples before the chunk that the kernels run over first.
    alignment : int
        The warm-up starts at a capture index that is a multiple of this
        (the decimation, so that the kept samples are the sequential run's).
    """

    lead_samples: int
    alignment: int

    def estimate(self, lead: Chunk | None, chunk: Chunk) -> Any:
        """The kernels' output on ``chunk``, from a fresh state warmed on ``lead`` (which ends where ``chunk`` starts)."""


def lead_start(start: int, lead_samples: int, alignment: int) -> int:
    """The first sample of the warm-up of a chunk starting at ``start``: W early, on the alignment grid, >= 0."""
    first = max(start - lead_samples, 0)
    return first - first % alignment


@runtime_checkable
class SplitStage(Stage, Protocol):
    """A stage whose kernels can run on several chunks at once.

    ``step(chunk)`` is ``account(chunk, <its kernels' output with carried
    state>)``; with a :class:`Split`, :func:`run_stream` calls
    ``kernels().estimate`` on workers and ``account`` in capture order.
    """

    def kernels(self) -> ChunkKernels | None:
        """The stage's kernels after ``prepare``; None if they cannot run split (then the run is sequential)."""

    def account(self, chunk: Chunk, estimate: Any) -> Mapping[str, np.ndarray] | None:
        """Everything after the kernels, in capture order: returns the chunk's columns."""


def replay_held(held: list[Chunk], rest: Iterator[Chunk]) -> Iterator[Chunk]:
    """Yield ``held`` chunks then ``rest``, dropping each held chunk once it is handed on (no reference is kept)."""
    while held:
        yield held.pop(0)
    yield from rest


def read_ahead(
    chunks: Iterator[Chunk], names: tuple[str, ...], start_sample: int, end_sample: int
) -> tuple[dict[str, np.ndarray], Iterator[Chunk]]:
    """Samples [start_sample, end_sample) of ``names`` or as many of them as the capture has, read ahead.

    As :func:`read_segment`, but a capture that ends first gives what it has
    (possibly nothing) instead of an error: a survey, not a segment the
    analysis needs whole.
    """
    held: list[Chunk] = []
    for chunk in chunks:
        held.append(chunk)
        if chunk.start + len(chunk) >= end_sample:
            break
    data = {}
    for name in names:
        parts = [c.data[name][max(0, start_sample - c.start):max(0, end_sample - c.start)] for c in held]
        data[name] = np.concatenate(parts) if parts else np.zeros(0)
    return data, replay_held(held, chunks)


def read_segment(
    chunks: Iterator[Chunk], names: tuple[str, ...], start_sample: int, end_sample: int
) -> tuple[dict[str, np.ndarray], Iterator[Chunk]]:
    """Samples [start_sample, end_sample) of ``names``, read ahead from a single-pass stream.

    Returns the segment and an iterator over every chunk of the capture, the
    read-ahead ones first, so the stream (stdin included) is read once.
    """
    held: list[Chunk] = []
    for chunk in chunks:
        held.append(chunk)
        if chunk.start + len(chunk) >= end_sample:
            break
    available = held[-1].start + len(held[-1]) if held else 0
    if available < end_sample:
        raise InputError(f"segment ends at sample {end_sample} but the capture has only {available} samples")
    segment = {
        name: np.concatenate([c.data[name] for c in held])[start_sample:end_sample] for name in names
    }
    return segment, replay_held(held, chunks)


def _merge_into(merged: dict[str, np.ndarray], columns: Mapping[str, np.ndarray] | None, stage: Stage) -> None:
    if not columns:
        return
    clash = merged.keys() & columns.keys()
    if clash:
        raise ValueError(f"{type(stage).__name__} writes column(s) {sorted(clash)} that an earlier stage writes")
    merged.update(columns)


def _merge(stages: Sequence[Stage], chunk: Chunk) -> dict[str, np.ndarray]:
    merged: dict[str, np.ndarray] = {}
    for stage in stages:
        _merge_into(merged, stage.step(chunk), stage)
    return merged


def run_stream(
    reader: CaptureReader,
    stages: Sequence[Stage],
    sink=None,
    *,
    channels: Sequence[str],
    chunk_samples: int,
    progress: Callable[[int], None] | None = None,
    prologue: Callable[[Iterator[Chunk]], Iterator[Chunk]] | None = None,
    read_ahead: int = 2,
    split: Split | None = None,
    on_start: Callable[[], None] | None = None,
) -> list[Any]:
    """Stream ``reader`` through ``stages`` once, chunk by chunk.

    Parameters
    ----------
    reader : CaptureReader
        An open capture.
    stages : sequence of Stage
        Run in order on every chunk; each ``prepare`` sees the same
        :class:`Head` before the first chunk.
    sink : object with ``append(columns)``, optional
        Receives the stages' columns of each chunk, merged into one mapping
        (a :class:`~afmtool.io.results.ResultWriter` or a row writer).
        None: the columns are dropped.  Not called for a chunk whose stages
        return no columns.
    channels : sequence of str
        Channels to read; all must exist.
    chunk_samples : int
        Samples per chunk (>= 1).
    progress : callable, optional
        Called from this (the consumer) thread after each chunk is stepped,
        with the capture samples done so far (``chunk.start + len(chunk)``).
    prologue : callable, optional
        Maps the chunk stream to the stream the stages see (e.g. reads a
        free-air segment ahead and replays it); it runs before ``prepare``.
    read_ahead : int
        Chunks read ahead in a background thread; 0 reads each chunk in
        this thread when it is needed (memory: up to ``read_ahead + 2``
        chunks are held at once with read-ahead, one without).
    split : Split, optional
        Run the kernels of ``split.jobs`` chunks at once (or on a Dask
        cluster) when every stage is a :class:`SplitStage` with kernels;
        otherwise, or by default, the run is sequential.  Up to
        ``jobs + 1`` more chunks are then held.
    on_start : callable, optional
        Called as the stream starts, every stage prepared (work for the end that can overlap the kernels).

    Returns
    -------
    list
        ``[stage.finish() for stage in stages]``.

    Raises
    ------
    InputError
        The capture has no samples, lacks a channel, or has NaN or inf
        (from :func:`~afmtool.io.chunks.iter_chunks`).
    ValueError
        Two stages write the same column.
    """
    if read_ahead < 0:
        raise ValueError(f"{read_ahead=} must be >= 0")
    first, chunks = _first_chunk(reader, channels, chunk_samples, prologue)
    with SideThread() as side:
        head = Head(reader, reader.info, first, side)
        for stage in stages:
            stage.prepare(head)
        if on_start is not None:
            on_start()
        stream = replay_held([first], chunks)
        if read_ahead:
            stream = prefetch(stream, read_ahead)
        del head, first  # the stream hands the first chunk on once; keep no reference for the whole run
        try:
            _run_chunks(stream, stages, sink, progress, split, reader)
        finally:
            stream.close()  # stops the read-ahead thread when a stage raised
        return [stage.finish() for stage in stages]


def _first_chunk(reader: CaptureReader, channels: Sequence[str], chunk_samples: int, prologue) -> tuple[Chunk, Iterator[Chunk]]:
    """The first chunk the stages see, and the rest of the stream (after the prologue)."""
    chunks = iter_chunks(reader, channels, chunk_samples)
    if prologue is not None:
        chunks = prologue(chunks)
    first = next(chunks, None)
    if first is None:
        raise InputError(f"{reader.info.source}: the capture has no samples")
    return first, chunks


def _run_chunks(stream: Iterator[Chunk], stages: Sequence[Stage], sink, progress, split: Split | None,
                reader: CaptureReader | None = None) -> None:
    """Every chunk through the stages, sequentially or split; the merged columns to the sink."""
    kernels = _split_kernels(stages, split)

    def deliver(merged: Mapping[str, np.ndarray], done: int) -> None:
        if sink is not None and merged:
            sink.append(merged)
        if progress is not None:
            progress(done)

    if kernels is None:
        for chunk in stream:
            deliver(_merge(stages, chunk), chunk.start + len(chunk))
    else:
        # a Dask worker reads its own chunk and warm-up from the shared file when the reader allows it
        ranges = range_source(reader) if reader is not None and split.scheduler is not None else None
        _run_split(stream, stages, kernels, split, deliver, ranges)


def _split_kernels(stages: Sequence[Stage], split: Split | None) -> list[ChunkKernels] | None:
    """Every stage's kernels when the run is split and all of them can be; else None (sequential)."""
    if split is None or not split.parallel or not all(isinstance(stage, SplitStage) for stage in stages):
        return None
    kernels = [stage.kernels() for stage in stages]
    return None if any(k is None for k in kernels) else kernels


class _Tail:
    """The last ``keep`` samples of the stream's channels, copied: the warm-ups of the next chunks."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.start = 0
        self.data: dict[str, np.ndarray] = {}

    def lead(self, start: int, end: int) -> Chunk | None:
        """Samples [start, end) (end = the next chunk's start), or None when empty."""
        if start >= end:
            return None
        if start < self.start:
            raise RuntimeError(f"warm-up from {start} asked, but only samples from {self.start} are kept")
        return Chunk(start, {name: values[start - self.start:end - self.start] for name, values in self.data.items()})

    def push(self, chunk: Chunk) -> None:
        end = chunk.start + len(chunk)
        first = max(end - self.keep, 0)
        if not self.data or first >= chunk.start:
            self.data = {name: np.array(values[first - chunk.start:]) for name, values in chunk.data.items()}
        else:  # a chunk shorter than the warm-up: keep some of the older tail too
            self.data = {name: np.concatenate([self.data[name][first - self.start:], values])
                         for name, values in chunk.data.items()}
        self.start = first


def _executor(split: Split):
    """``(submit, close)``: local threads, or a Dask client for ``split.scheduler``."""
    if split.scheduler is None:
        pool = ThreadPoolExecutor(max_workers=split.jobs, thread_name_prefix="afmtool-split")
        return pool.submit, lambda: pool.shutdown(wait=True, cancel_futures=True)
    from afmtool.io.scheduler import connect_client

    client = connect_client(split.scheduler, split.scheduler_timeout_s)

    def submit(fn: Callable[..., Any], /, *args: Any) -> Any:
        return client.submit(fn, *args, pure=False)

    return submit, client.close


def _estimate_from_ranges(kernels: ChunkKernels, ranges: RangeSource, channels: tuple[str, ...], first: int,
                          start: int, stop: int) -> Any:
    """``kernels.estimate`` of samples [start, stop), warmed on [first, start), read here from ``ranges``."""
    data = ranges.read(channels, first, stop)
    lead = Chunk(first, {name: values[:start - first] for name, values in data.items()}) if first < start else None
    return kernels.estimate(lead, Chunk(start, {name: values[start - first:] for name, values in data.items()}))


def _run_split(stream: Iterator[Chunk], stages: Sequence[Stage], kernels: Sequence[ChunkKernels], split: Split,
               deliver: Callable[[Mapping[str, np.ndarray], int], None], ranges: RangeSource | None = None) -> None:
    """Kernels of up to ``jobs`` chunks at once, each warmed on its lead; ``account`` in capture order.

    With ``ranges`` each task gets only sample indices and reads its samples itself.
    """
    keep = max(k.lead_samples + k.alignment for k in kernels)
    tail = _Tail(keep)
    submit, close = _executor(split)
    depth = split.jobs if split.scheduler is None else 2 * max(split.jobs, 2)
    pending: deque = deque()

    def account_oldest() -> None:
        chunk, futures = pending.popleft()
        merged: dict[str, np.ndarray] = {}
        for stage, future in zip(stages, futures):
            columns = stage.account(chunk, future.result())
            _merge_into(merged, columns, stage)
        deliver(merged, chunk.start + len(chunk))

    try:
        for chunk in stream:
            futures = []
            for k in kernels:
                first = lead_start(chunk.start, k.lead_samples, k.alignment)
                if ranges is not None:
                    futures.append(submit(_estimate_from_ranges, k, ranges, tuple(chunk.data), first, chunk.start,
                                          chunk.start + len(chunk)))
                else:
                    futures.append(submit(k.estimate, tail.lead(first, chunk.start), chunk))
            pending.append((chunk, futures))
            if ranges is None:  # the workers read their warm-ups themselves otherwise
                tail.push(chunk)
            if len(pending) > depth:
                account_oldest()
        while pending:
            account_oldest()
    finally:
        for _, futures in pending:
            for future in futures:
                future.cancel()
        close()
