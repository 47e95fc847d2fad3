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

from afmtool.report.images import _STYLE_KEYS, _check_png_path, _png_figure

__all__ = ["BodeCurve", "write_bode_png"]

#: Most points drawn per curve (thinned evenly in log f beyond this).
_MAX_POINTS = 20000


class BodeCurve(NamedTuple):
    """One frequency response to draw: frequencies (Hz), complex values, a legend label and a line style."""

    frequency_hz: ArrayLike
    response: ArrayLike
    label: str
    style: Mapping[str, Any] | None = None


def _checked(curve: BodeCurve, name: str) -> tuple[np.ndarray, np.ndarray, str, dict]:
    f = np.asarray(curve.frequency_hz, dtype=np.float64)
    h = np.asarray(curve.response, dtype=np.complex128)
    if f.ndim != 1 or f.shape != h.shape or f.size == 0:
        raise ValueError(f"{name}: frequency_hz and response must be non-empty 1-D arrays of one length")
    style = dict(curve.style or {})
    unknown = sorted(set(style) - _STYLE_KEYS)
    if unknown:
        raise ValueError(f"{name}: unknown style keys {unknown}; allowed: {sorted(_STYLE_KEYS)}")
    keep = f > 0
    order = np.argsort(f[keep])
    f, h = f[keep][order], h[keep][order]
    if f.size > _MAX_POINTS:  # thin evenly on the log axis: Agg draws a bounded number of vertices per path
        picks = np.unique(np.searchsorted(f, np.geomspace(f[0], f[-1], _MAX_POINTS)).clip(0, f.size - 1))
        f, h = f[picks], h[picks]
    return f, h, str(curve.label), style


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
        raise ValueError("curves must hold at least one response")
    checked = [_checked(BodeCurve(*c), f"curves[{i}]") for i, c in enumerate(curves)]
    with _png_figure(path, 7.0, 5.6) as fig:
        ax_mag, ax_ph = fig.subplots(2, 1, sharex=True)
        for f, h, label, style in checked:
            finite = np.isfinite(h) & (np.abs(h) > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                magnitude = np.where(finite, 20.0 * np.log10(np.abs(h)), np.nan)
            phase = np.full(f.shape, np.nan)
            if np.any(finite):
                unwrapped = np.degrees(np.unwrap(np.angle(h[finite])))
                # anchor: the phase where |H| is largest (the best-measured bin) lies in (−180°, 180°]
                anchor = unwrapped[int(np.argmax(np.abs(h[finite])))]
                phase[finite] = unwrapped - 360.0 * np.ceil((anchor - 180.0) / 360.0)
            ax_mag.semilogx(f, magnitude, label=label or None, **style)
            ax_ph.semilogx(f, phase, **style)
        for x, label in markers:
            for ax in (ax_mag, ax_ph):
                ax.axvline(float(x), color="0.35", linestyle=":", linewidth=1.0)
            ax_mag.annotate(label, xy=(float(x), 1.0), xycoords=("data", "axes fraction"), xytext=(-2, -4),
                            textcoords="offset points", rotation=90, ha="right", va="top", fontsize="small",
                            color="0.35")
        if any(label for _, _, label, _ in checked):
            ax_mag.legend(fontsize="small")
        for ax in (ax_mag, ax_ph):
            ax.grid(True, which="both", alpha=0.3)
        ax_mag.set_ylabel(magnitude_label)
        ax_ph.set_ylabel("phase (deg)")
        ax_ph.set_xlabel("frequency (Hz)")
        ax_mag.set_title(title)
