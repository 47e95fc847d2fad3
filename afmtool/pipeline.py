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
- merging the stages' columns per chunk and handing them to the sink.

This is the only module outside :mod:`afmtool.io` that calls
``iter_chunks`` or ``prefetch`` (``tests/test_architecture.py`` checks it).
The rule of which samples a decimated output keeps lives in
:class:`Decimation`, and the summaries' warm-up in :class:`Warmup`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol, Self

import numpy as np

from afmtool.errors import InputError
from afmtool.estimators.decimation import Decimation
from afmtool.io.capture import CaptureInfo, CaptureReader, Chunk
from afmtool.io.chunks import iter_chunks
from afmtool.io.prefetch import prefetch

__all__ = ["Decimation", "Head", "SideThread", "Stage", "Warmup", "read_segment", "replay_held", "run_stream"]


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
        """``int(windows / (1 − λ))`` samples: ``windows`` exponential windows of forgetting factor ``lam``."""
        return cls(int(windows / (1.0 - lam)))

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


def replay_held(held: list[Chunk], rest: Iterator[Chunk]) -> Iterator[Chunk]:
    """Yield ``held`` chunks then ``rest``, dropping each held chunk once it is handed on (no reference is kept)."""
    while held:
        yield held.pop(0)
    yield from rest


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


def _merge(stages: Sequence[Stage], chunk: Chunk) -> dict[str, np.ndarray]:
    merged: dict[str, np.ndarray] = {}
    for stage in stages:
        columns = stage.step(chunk)
        if not columns:
            continue
        clash = merged.keys() & columns.keys()
        if clash:
            raise ValueError(f"{type(stage).__name__} writes column(s) {sorted(clash)} that an earlier stage writes")
        merged.update(columns)
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
    chunks = iter_chunks(reader, channels, chunk_samples)
    if prologue is not None:
        chunks = prologue(chunks)
    first = next(chunks, None)
    if first is None:
        raise InputError(f"{reader.info.source}: the capture has no samples")
    with SideThread() as side:
        head = Head(reader, reader.info, first, side)
        for stage in stages:
            stage.prepare(head)
        stream = replay_held([first], chunks)
        if read_ahead:
            stream = prefetch(stream, read_ahead)
        del head, first  # the stream hands the first chunk on once; keep no reference for the whole run
        try:
            for chunk in stream:
                merged = _merge(stages, chunk)
                if sink is not None and merged:
                    sink.append(merged)
                if progress is not None:
                    progress(chunk.start + len(chunk))
        finally:
            stream.close()  # stops the read-ahead thread when a stage raised
        return [stage.finish() for stage in stages]
