"""Estimators as stages of :func:`afmtool.pipeline.run_stream`: one pass over a capture, flat memory.

Each class here follows :class:`afmtool.pipeline.Stage` (``prepare(head)``,
``step(chunk)``, ``finish()``), returns no columns, and gives its result from
``finish``:

* :class:`ChannelMeans`: running sums, for a sweep's DC operating point
  (memory O(channels));
* :class:`ResponseStage`: frequency responses from one input channel to
  several outputs, by H1 (Welch cross spectra accumulated per segment,
  memory O(nperseg + chunk)) or stepped-sine lock-in (sums per step, memory
  O(steps)); only a stepped sine whose steps must be found from the drive
  keeps the records (:func:`~afmtool.estimators.stepped_sine.detect_segments`
  needs the whole drive);
* :class:`RecordStage`: the whole record of a few channels, for the methods
  that truly need it (the whole-record sweep fit, quasi-static ramps and
  force curves whose outputs hold every sample); memory one float64 array
  per channel;
* :class:`SegmentStage`: samples [start, end) of a few channels (the
  free-air segment).

:func:`run_stages` runs stages over chunks already in memory (tests,
arrays), exactly as ``run_stream`` steps them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse, H1Accumulator
from afmtool.estimators.stepped_sine import SineSegment, SteppedSineAccumulator, stepped_sine_response

if TYPE_CHECKING:  # an annotation only: estimators take chunks, they do not read captures
    from afmtool.io.capture import Chunk

__all__ = [
    "ChannelMeans",
    "RecordStage",
    "ResponseStage",
    "SegmentStage",
    "progress_offset",
    "run_stages",
]


class ChannelMeans:
    """Running sums of each channel of every chunk, for the DC operating point of a sweep.

    ``finish()`` returns the stage itself; :meth:`mean` then gives a
    channel's mean.  Memory O(channels).
    """

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.count = 0

    def prepare(self, head) -> None:
        """Nothing to set up."""

    def step(self, chunk: Chunk) -> None:
        for name, values in chunk.data.items():
            self.sums[name] = self.sums.get(name, 0.0) + float(np.sum(values))
        self.count += len(chunk)

    def finish(self) -> ChannelMeans:
        return self

    def mean(self, name: str) -> float:
        """Mean of channel ``name`` over the chunks stepped so far."""
        if self.count == 0:
            raise InputError("no samples were read")
        return self.sums[name] / self.count


class RecordStage:
    """Keep the whole record of ``channels``, for methods that need every sample.

    Memory: one float64 array of the capture's length per channel (held in
    one preallocated array when the reader knows its length, so the peak is
    the record itself, not twice it).  ``finish()`` returns
    ``{channel: array}``.

    Parameters
    ----------
    channels : sequence of str
        The channels to keep (a subset of those read).
    """

    def __init__(self, channels: Sequence[str]) -> None:
        self._channels = tuple(channels)
        self._arrays: dict[str, np.ndarray] | None = None
        self._blocks: dict[str, list[np.ndarray]] = {name: [] for name in self._channels}
        self._n = 0

    def prepare(self, head) -> None:
        n = head.info.n_samples
        if n:
            self._arrays = {name: np.empty(int(n)) for name in self._channels}

    def step(self, chunk: Chunk) -> None:
        stop = self._n + len(chunk)
        if self._arrays is not None and stop > next(iter(self._arrays.values())).size:
            # the reader's length was short: keep what is held as blocks and go on
            self._blocks = {name: [values[: self._n]] for name, values in self._arrays.items()}
            self._arrays = None
        for name in self._channels:
            values = chunk.data[name]
            if self._arrays is not None:
                self._arrays[name][self._n : stop] = values
            else:
                self._blocks[name].append(np.array(values, dtype=np.float64))
        self._n = stop

    def finish(self) -> dict[str, np.ndarray]:
        if self._arrays is not None:
            return {name: values[: self._n] for name, values in self._arrays.items()}
        return {
            name: np.concatenate(blocks) if blocks else np.empty(0) for name, blocks in self._blocks.items()
        }


class SegmentStage:
    """Keep samples [start_sample, end_sample) of ``channels``; memory the segment.

    ``finish()`` returns ``{channel: array}``.

    Raises
    ------
    InputError
        In ``finish``, if the capture ended before ``end_sample``.
    """

    def __init__(self, channels: Sequence[str], start_sample: int, end_sample: int) -> None:
        if not 0 <= start_sample <= end_sample:
            raise ConfigError(f"the segment needs 0 <= start <= end, got {start_sample}:{end_sample}")
        self._channels = tuple(channels)
        self._start, self._end = int(start_sample), int(end_sample)
        self._blocks: dict[str, list[np.ndarray]] = {name: [] for name in self._channels}
        self._available = 0

    def prepare(self, head) -> None:
        """Nothing to set up."""

    def step(self, chunk: Chunk) -> None:
        lo, hi = chunk.start, chunk.start + len(chunk)
        self._available = hi
        a, b = max(lo, self._start), min(hi, self._end)
        if a < b:
            for name in self._channels:
                self._blocks[name].append(np.array(chunk.data[name][a - lo : b - lo], dtype=np.float64))

    def finish(self) -> dict[str, np.ndarray]:
        if self._available < self._end:
            raise InputError(
                f"segment ends at sample {self._end} but the capture has only {self._available} samples"
            )
        return {name: np.concatenate(blocks) if blocks else np.empty(0) for name, blocks in self._blocks.items()}

    def until_end(self, chunks: Iterable[Chunk]):
        """A prologue for ``run_stream``: the chunks up to the one holding the segment's end (the rest is not read)."""
        for chunk in chunks:
            yield chunk
            if chunk.start + len(chunk) >= self._end:
                return


class ResponseStage:
    """Frequency responses from channel ``x`` to each channel of ``ys``, in one pass.

    Parameters
    ----------
    x : str
        The input channel (the drive or perturbed voltage).
    ys : sequence of str
        Output channels.
    method : {"h1", "stepped"}
        ``"h1"``: one :class:`~afmtool.estimators.frequency_response.H1Accumulator`
        per output, fed chunk by chunk (memory O(nperseg + chunk)).
        ``"stepped"``: lock-in per step.  With ``segments`` the sums run per
        step as the chunks pass
        (:class:`~afmtool.estimators.stepped_sine.SteppedSineAccumulator`,
        memory O(steps)); without, the records of ``x`` and ``ys`` are kept
        (memory one float64 array per channel) and the steps found by
        ``find_steps`` at the end.
    nperseg : int
        H1 segment length (``"h1"`` only).
    segments : sequence, optional
        Stepped-sine steps ``{start_s, end_s, frequency_hz}`` (metadata).
    find_steps : callable, optional
        ``(x_record, sample_rate_hz) -> steps`` when ``segments`` is None
        (``"stepped"`` only; required then).
    settle_fraction, min_periods
        As :func:`~afmtool.estimators.stepped_sine.stepped_sine_response`.

    ``finish()`` returns ``{y: FrequencyResponse}`` in the capture's units.

    Raises
    ------
    ConfigError
        A bad ``method``.
    InputError
        (``prepare``) bad segments; (``finish``) a sweep shorter than one H1
        segment, or no steps found.
    """

    def __init__(
        self,
        x: str,
        ys: Sequence[str],
        *,
        method: str,
        nperseg: int = 0,
        segments: Sequence | None = None,
        find_steps: Callable[[np.ndarray, float], Sequence[SineSegment]] | None = None,
        settle_fraction: float = 0.5,
        min_periods: int = 10,
    ) -> None:
        if method not in ("h1", "stepped"):
            raise ConfigError(f"method={method!r} must be 'h1' or 'stepped'")
        if method == "stepped" and segments is None and find_steps is None:
            raise ConfigError("a stepped sine without segments needs find_steps")
        self._x, self._ys = x, tuple(ys)
        self._method, self._nperseg = method, nperseg
        self._segments, self._find_steps = segments, find_steps
        self._settle, self._min_periods = settle_fraction, min_periods
        self._fs = 0.0
        self._accumulators: dict[str, Any] = {}
        self._record: RecordStage | None = None

    def prepare(self, head) -> None:
        self._fs = head.info.sample_rate_hz
        if self._method == "h1":
            self._accumulators = {y: H1Accumulator(self._fs, self._nperseg) for y in self._ys}
        elif self._segments is not None:
            self._accumulators = {
                y: SteppedSineAccumulator(
                    self._fs, self._segments, settle_fraction=self._settle, min_periods=self._min_periods
                )
                for y in self._ys
            }
        else:
            self._record = RecordStage((self._x, *self._ys))
            self._record.prepare(head)

    def step(self, chunk: Chunk) -> None:
        if self._record is not None:
            self._record.step(chunk)
            return
        for y, acc in self._accumulators.items():
            acc.add(chunk.data[self._x], chunk.data[y])

    def finish(self) -> dict[str, FrequencyResponse]:
        if self._record is not None:
            return self._from_record(self._record.finish())
        if self._method == "h1" and any(acc.n_segments == 0 for acc in self._accumulators.values()):
            raise InputError(f"the sweep is shorter than one H1 segment (nperseg={self._nperseg} samples)")
        return {y: acc.result() for y, acc in self._accumulators.items()}

    def _from_record(self, records: Mapping[str, np.ndarray]) -> dict[str, FrequencyResponse]:
        steps = self._find_steps(records[self._x], self._fs)
        if not steps:
            raise InputError(f"no stepped-sine steps found in channel {self._x!r}; give segments in the metadata")
        return {
            y: stepped_sine_response(
                records[self._x], records[y], self._fs, steps, settle_fraction=self._settle,
                min_periods=self._min_periods,
            )
            for y in self._ys
        }


class _ArrayHead:
    """The part of :class:`afmtool.pipeline.Head` the stages here read, for :func:`run_stages`."""

    def __init__(self, sample_rate_hz: float, n_samples: int | None) -> None:
        self.info = _ArrayInfo(sample_rate_hz, n_samples)


class _ArrayInfo:
    def __init__(self, sample_rate_hz: float, n_samples: int | None) -> None:
        self.sample_rate_hz = sample_rate_hz
        self.n_samples = n_samples


def run_stages(chunks: Iterable[Chunk], stages: Sequence, sample_rate_hz: float) -> list:
    """Step ``stages`` of this module through ``chunks`` in memory; ``[stage.finish() ...]``.

    The in-memory twin of :func:`afmtool.pipeline.run_stream` for these
    stages (which read only ``head.info.sample_rate_hz`` and
    ``head.info.n_samples``), for arrays and tests.
    """
    head = _ArrayHead(sample_rate_hz, None)
    for stage in stages:
        stage.prepare(head)
    for chunk in chunks:
        for stage in stages:
            stage.step(chunk)
    return [stage.finish() for stage in stages]


def progress_offset(progress: Callable[[int], None] | None, offset: int) -> Callable[[int], None] | None:
    """A progress callback that adds ``offset`` samples (for a second capture)."""
    if progress is None:
        return None
    return lambda done: progress(offset + done)
