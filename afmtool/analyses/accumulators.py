"""Streaming reductions shared by analyses: force-curve bins and scan images.

Both take decimated series chunk by chunk and keep only sums and counts, so
memory is set by the number of bins or pixels, not by the capture length.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from afmtool.estimators.kalman_bank_verdict import ModelTable
from afmtool.io.metadata import ScanMetadata

__all__ = ["ScanGeometry", "ImageAccumulator", "ForceCurveAccumulator", "ForceCurveTable", "DelayLine", "ReepBinner"]


@dataclass(frozen=True)
class ScanGeometry(ScanMetadata):
    """Raster geometry: the capture's validated metadata ``scan``, with the pixel arithmetic of a scan."""

    @classmethod
    def from_scan(cls, scan: ScanMetadata | None) -> ScanGeometry | None:
        """The geometry of a capture's (validated) metadata ``scan``; None without one."""
        if scan is None:
            return None
        return cls(**dataclasses.asdict(scan))

    def pixel_index(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(direction 0=trace 1=retrace, line, pixel) for each time; line −1 outside the scan.

        Within a line period the trace comes first; the retrace is mapped
        back onto the same lateral pixels so both images are registered.
        """
        line_period = 1.0 / self.line_rate_hz
        elapsed = t_s - self.start_s
        line = np.floor(elapsed / line_period).astype(np.int64)
        fraction = elapsed / line_period - line
        if self.trace_retrace:
            retrace = fraction >= 0.5
            position = np.where(retrace, 2.0 - 2.0 * fraction, 2.0 * fraction)
        else:
            retrace = np.zeros(len(t_s), dtype=bool)
            position = fraction
        pixel = np.minimum((position * self.pixels_per_line).astype(np.int64), self.pixels_per_line - 1)
        line = np.where((elapsed >= 0) & (line < self.lines), line, -1)
        return retrace.astype(np.int64), line, pixel


class ImageAccumulator:
    """Per-pixel means of several quantities, for trace and retrace."""

    def __init__(self, geometry: ScanGeometry, names: tuple[str, ...]) -> None:
        self.geometry = geometry
        self.names = names
        size = 2 * geometry.lines * geometry.pixels_per_line
        self._sums = {name: np.zeros(size) for name in names}
        self._counts = {name: np.zeros(size, dtype=np.int64) for name in names}

    def add(self, t_s: np.ndarray, values: Mapping[str, np.ndarray]) -> None:
        g = self.geometry
        direction, line, pixel = g.pixel_index(t_s)
        inside = line >= 0
        flat = (direction * g.lines + line) * g.pixels_per_line + pixel
        size = len(self._counts[self.names[0]])
        for name in self.names:
            v = np.asarray(values[name])
            keep = inside & np.isfinite(v)
            self._sums[name] += np.bincount(flat[keep], weights=v[keep], minlength=size)
            self._counts[name] += np.bincount(flat[keep], minlength=size)

    def images(self) -> dict[str, np.ndarray]:
        """``{"f0_hz/trace": (lines, pixels) array, ...}``; NaN where no sample fell.

        Row 0 is the first line scanned; writers that want the top row first
        flip as their format requires.
        """
        g = self.geometry
        out = {}
        for name in self.names:
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = self._sums[name] / self._counts[name]
            mean = mean.reshape(2, g.lines, g.pixels_per_line)
            out[f"{name}/trace"] = mean[0]
            if g.trace_retrace:
                out[f"{name}/retrace"] = mean[1]
        return out


@dataclass(frozen=True)
class ForceCurveTable:
    """Binned means against z for one direction (approach or retract)."""

    z: np.ndarray
    count: np.ndarray
    means: Mapping[str, np.ndarray]
    sensitivities: Mapping[str, np.ndarray]


class ForceCurveAccumulator:
    """Bin quantities against z with approach and retract kept apart.

    The direction of each sample is the sign of the z change over one
    decimated step; the first direction seen is called the approach.
    """

    def __init__(self, z_bin: float, names: tuple[str, ...]) -> None:
        if not z_bin > 0:
            raise ValueError(f"{z_bin=} must be > 0")
        self.z_bin = float(z_bin)
        self.names = names
        self._bins: list[dict[int, np.ndarray]] = [{}, {}]  # bin -> [count, sums...]
        self._approach_sign = 0
        self._last_z = math.nan
        self._last_direction = 0

    def add(self, z: np.ndarray, values: Mapping[str, np.ndarray]) -> None:
        """Add a chunk's samples to their bins (:mod:`afmtool.estimators.force_curve_bins` defines which)."""
        from afmtool.estimators.force_curve_bins import force_curve_legs, leg_sums

        z = np.asarray(z, dtype=np.float64)
        if len(z) == 0:
            return
        stacked = np.vstack([np.asarray(values[n], dtype=np.float64) for n in self.names])
        legs = force_curve_legs(z, stacked, self.z_bin, self._last_z, self._last_direction, self._approach_sign)
        self._last_z, self._last_direction, self._approach_sign = float(z[-1]), legs.last_direction, legs.approach_sign
        for which in (0, 1):
            keys, sums = leg_sums(legs, stacked, which)
            bins = self._bins[which]
            for k, b in enumerate(keys.tolist()):
                if b in bins:
                    bins[b] += sums[:, k]
                else:
                    bins[b] = sums[:, k].copy()

    def tables(self) -> dict[str, ForceCurveTable]:
        out = {}
        for which, label in ((0, "approach"), (1, "retract")):
            bins = self._bins[which]
            if not bins:
                continue
            keys = np.array(sorted(bins))
            sums = np.array([bins[k] for k in keys]).T
            z = (keys + 0.5) * self.z_bin
            means = {name: sums[i + 1] / sums[0] for i, name in enumerate(self.names)}
            sensitivities = {name: np.gradient(m, z) if len(z) > 1 else np.full(len(z), np.nan) for name, m in means.items()}
            out[label] = ForceCurveTable(z, sums[0].astype(np.int64), means, sensitivities)
        return out


class DelayLine:
    """x(n − d) of a stream, carried across chunks; the first value stands in before the start."""

    def __init__(self, delay: int) -> None:
        if delay < 0:
            raise ValueError(f"{delay=} must be >= 0")
        self.delay = delay
        self._tail: np.ndarray | None = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if self.delay == 0 or len(x) == 0:
            return x
        if self._tail is None:
            self._tail = np.full(self.delay, x[0])
        extended = np.concatenate((self._tail, x))
        self._tail = extended[-self.delay :]
        return extended[: len(x)]


class ReepBinner:
    """REEP's model binned against z at the centroid of its window (module docstring).

    It takes the columns REEP writes (``t``, ``z``, ``f0_hz``, ``q`` and
    optionally ``amplitude``), so it can stand in for ``run_reep``'s writer.

    Parameters
    ----------
    z_bin : float
        Bin width, z_piezo units.
    delay : int
        λ/(1 − λ) in kept samples (:func:`afmtool.analyses.kalman_bank_reep.reep_delay`).
    warmup_s : float
        Estimates before this time are left out (REEP's start-up).
    """

    def __init__(self, z_bin: float, delay: int, warmup_s: float) -> None:
        self.accumulator = ForceCurveAccumulator(z_bin, ("f0_hz", "q", "amplitude"))
        self.z_delay = DelayLine(delay)
        self.warmup_s = warmup_s

    def append(self, columns) -> None:
        z = self.z_delay(columns["z"])
        if len(z) == 0:
            return
        settled = np.asarray(columns["t"]) >= self.warmup_s
        amplitude = columns.get("amplitude", np.zeros(len(z)))
        values = {"f0_hz": columns["f0_hz"], "q": columns["q"], "amplitude": amplitude}
        self.accumulator.add(z, {k: np.where(settled, v, np.nan) for k, v in values.items()})

    def put(self, *args, **kwargs) -> None:
        """Whole arrays of ``run_reep`` (tables, images) are not needed here."""

    def tables(self, *, amplitude_known: bool = True) -> dict[str, ModelTable]:
        """REEP's model per leg; amplitude NaN when the source had none."""
        out = {}
        for leg, t in self.accumulator.tables().items():
            amplitude = t.means["amplitude"] if amplitude_known else np.full(t.z.shape, np.nan)
            out[leg] = ModelTable(t.z, t.count.astype(np.float64), t.means["f0_hz"], t.means["q"], amplitude)
        return out
