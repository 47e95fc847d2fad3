"""Which samples a decimated output keeps: one rule for the kernels' wrappers and the pipeline.

It lives in ``estimators/`` because the wrappers of the lock-in, RLS and
reliability kernels apply it, and :mod:`afmtool.pipeline` (one layer up)
re-exports it for the stages.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Decimation"]


@dataclass(frozen=True)
class Decimation:
    """Keep sample n where (n + 1) % every == 0 (the one place that rule lives).

    n is the sample's index in the capture, counted from 0.  The kept
    samples are the last of each run of ``every``, the same ones the
    lock-in's and the RLS kernels' ``keep_every`` keep, so outputs of
    different estimators line up sample for sample.

    Parameters
    ----------
    every : int
        Keep one sample in ``every`` (>= 1; 1 keeps them all).
    """

    every: int

    def __post_init__(self) -> None:
        if isinstance(self.every, bool) or not isinstance(self.every, (int, np.integer)) or self.every < 1:
            raise ValueError(f"every={self.every!r} must be an integer >= 1")

    def first_kept(self, start: int) -> int:
        """Offset, within a chunk starting at sample ``start``, of its first kept sample."""
        return (-(int(start) + 1)) % self.every

    def keep(self, start: int) -> slice:
        """The kept samples of a chunk starting at sample ``start``, as a slice (``values[..., keep]``)."""
        return slice(self.first_kept(start), None, self.every)

    def take(self, values: np.ndarray, start: int) -> np.ndarray:
        """The kept samples of ``values``, a chunk starting at sample ``start``: ``values[first_kept::every]``."""
        return values[self.keep(start)]

    def kept_index(self, start: int, n: int) -> np.ndarray:
        """Capture indices (int64) of the kept samples in [start, start + n)."""
        return np.arange(start + self.first_kept(start), start + n, self.every, dtype=np.int64)

    def index_of_kept(self, k):
        """Capture index of the k-th kept sample of the stream (k from 0; int or integer array)."""
        return k * self.every + (self.every - 1)

    def count(self, start: int, n: int) -> int:
        """How many samples of [start, start + n) are kept."""
        first = self.first_kept(start)
        return 0 if n <= first else (n - first - 1) // self.every + 1
