"""Bode plots (magnitude in dB and phase in degrees against a logarithmic frequency axis) as PNG.

Built on the figure helper of :mod:`afmtool.report.images` (Agg, default
style, atomic write), so matplotlib is imported only when a plot is written.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from afmtool.report.figure_process import NothingToDraw, skipped_when_empty
from afmtool.report.images import _STYLE_KEYS, _check_png_path, _png_figure

__all__ = ["BodeCurve", "write_bode_png"]

#: Most points drawn per curve (thinned evenly in log f beyond this).
_MAX_POINTS = 20000


class BodeCurve(NamedTuple):
    """One frequency response to draw: frequencies (Hz), complex values, a legend label and a line style.

    ``magnitude_std`` (same units as the response, one per frequency) draws
    the ±1σ band of |H| around the magnitude, shaded in the line's colour.
    """

    frequency_hz: ArrayLike
    response: ArrayLike
    label: str
    style: Mapping[str, Any] | None = None
    magnitude_std: ArrayLike | None = None


def _checked_std(curve: BodeCurve, f_all: np.ndarray, keep: np.ndarray, order: np.ndarray, name: str) -> np.ndarray | None:
    if curve.magnitude_std is None:
        return None
    std = np.asarray(curve.magnitude_std, dtype=np.float64)
    if std.shape != f_all.shape:
        raise ValueError(f"{name}: magnitude_std must have the shape of frequency_hz, got {std.shape}")
    return std[keep][order]


def _band_db(h: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """20·log10(|H| ∓ σ), the lower edge clipped at |H|/100 (−40 dB) where σ reaches |H|."""
    magnitude = np.abs(h)
    with np.errstate(divide="ignore", invalid="ignore"):
        lower = 20.0 * np.log10(np.maximum(magnitude - std, magnitude / 100.0))
        upper = 20.0 * np.log10(magnitude + std)
    ok = np.isfinite(lower) & np.isfinite(upper)
    return np.where(ok, lower, np.nan), np.where(ok, upper, np.nan)


def _checked(curve: BodeCurve, name: str) -> tuple[np.ndarray, np.ndarray, str, dict, np.ndarray | None]:
    f = np.asarray(curve.frequency_hz, dtype=np.float64)
    h = np.asarray(curve.response, dtype=np.complex128)
    if f.ndim != 1 or f.shape != h.shape:
        raise ValueError(f"{name}: frequency_hz and response must be non-empty 1-D arrays of one length")
    if f.size == 0:
        raise NothingToDraw(f"{name}: no frequencies")
    style = dict(curve.style or {})
    unknown = sorted(set(style) - _STYLE_KEYS)
    if unknown:
        raise ValueError(f"{name}: unknown style keys {unknown}; allowed: {sorted(_STYLE_KEYS)}")
    keep = f > 0
    order = np.argsort(f[keep])
    std = _checked_std(curve, f, keep, order, name)
    f, h = f[keep][order], h[keep][order]
    if f.size > _MAX_POINTS:  # thin evenly on the log axis: Agg draws a bounded number of vertices per path
        picks = np.unique(np.searchsorted(f, np.geomspace(f[0], f[-1], _MAX_POINTS)).clip(0, f.size - 1))
        f, h = f[picks], h[picks]
        std = std[picks] if std is not None else None
    return f, h, str(curve.label), style, std


@skipped_when_empty
def write_bode_png(
    path: Path,
    curves: Sequence[BodeCurve],
    *,
    title: str,
    magnitude_label: str,
    markers: Sequence[tuple[float, str]] = (),
) -> None:
    """Magnitude (dB) over phase (deg) of one or more responses, log frequency axis.

    Parameters
    ----------
    path : Path
        The output file; must end in ``.png``.
    curves : sequence of BodeCurve
        Drawn in order; non-positive frequencies are dropped, NaN breaks a
        line, and curves of more than 20,000 points are thinned evenly in log f.  The phase is unwrapped along each curve's finite points and
        shifted by whole turns so that it lies in (−180°, 180°] where |H| is
        largest.
    title : str
        Figure title.
    magnitude_label : str
        Label of the magnitude axis, with its units, e.g. ``"|Γ_IR,ts| (dB re 1 µA/nm)"``.
    markers : sequence of (float, str), optional
        Labelled dotted vertical lines (a bandwidth, a band edge), Hz.
    """
    path = _check_png_path(path)
    if len(curves) == 0:
        raise NothingToDraw("curves must hold at least one response")
    checked = [_checked(BodeCurve(*c), f"curves[{i}]") for i, c in enumerate(curves)]
    with _png_figure(path, 7.0, 5.6) as fig:
        ax_mag, ax_ph = fig.subplots(2, 1, sharex=True)
        for f, h, label, style, std in checked:
            finite = np.isfinite(h) & (np.abs(h) > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                magnitude = np.where(finite, 20.0 * np.log10(np.abs(h)), np.nan)
            phase = np.full(f.shape, np.nan)
            if np.any(finite):
                unwrapped = np.degrees(np.unwrap(np.angle(h[finite])))
                # anchor: the phase where |H| is largest (the best-measured bin) lies in (−180°, 180°]
                anchor = unwrapped[int(np.argmax(np.abs(h[finite])))]
                phase[finite] = unwrapped - 360.0 * np.ceil((anchor - 180.0) / 360.0)
            lines = ax_mag.semilogx(f, magnitude, label=label or None, **style)
            ax_ph.semilogx(f, phase, **style)
            if std is not None:
                lower, upper = _band_db(h, std)
                ax_mag.fill_between(f, lower, upper, color=lines[0].get_color(), alpha=0.2, linewidth=0,
                                    label=f"{label} ±1σ" if label else "±1σ")
        for x, label in markers:
            for ax in (ax_mag, ax_ph):
                ax.axvline(float(x), color="0.35", linestyle=":", linewidth=1.0)
            ax_mag.annotate(label, xy=(float(x), 1.0), xycoords=("data", "axes fraction"), xytext=(-2, -4),
                            textcoords="offset points", rotation=90, ha="right", va="top", fontsize="small",
                            color="0.35")
        if any(item[2] for item in checked):
            ax_mag.legend(fontsize="small")
        for ax in (ax_mag, ax_ph):
            ax.grid(True, which="both", alpha=0.3)
        ax_mag.set_ylabel(magnitude_label)
        ax_ph.set_ylabel("phase (deg)")
        ax_ph.set_xlabel("frequency (Hz)")
        ax_mag.set_title(title)
