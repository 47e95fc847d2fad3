"""Plain-Python reference for the slicer kernel of ``afmtool.estimators.bitslicer``.

Written from the module docstring's equations, one sample at a time, on
the whole record, with lists instead of ring buffers and no attention to
speed:

* delays: p[n] = primary[max(n − D_p, 0)], a[n] = aux[max(n − D_a, 0)];
* smoothing: s[n] = mean(p[max(0, n − L + 1) … n]);
* the latest crossing of ``mid``: τ = n − 1 + (s[n−1] − mid)/(s[n−1] − s[n]) − (L − 1)/2;
* hysteresis: the level goes to 1 above ``hi`` and to 0 below ``lo``; a
  change of level (not the first one) is a transition at τ;
* the PLL, locked: e = τ − (nearest boundary), b ← b + k_p·e, T ← T + k_i·e;
* integrate-and-dump: the soft value of a cell is the mean of p (and of a)
  over its central ``fraction``·T.

The kernel must agree with it to rounding (its moving average is a running
sum; this one sums each window anew).
"""

from __future__ import annotations

import math


def first_cell_start(first_boundary: float, period: float, delay_primary: int, delay_aux: int) -> float:
    """The first boundary, in delayed-primary samples, at or after both delay lines have filled."""
    boundary = first_boundary + delay_primary
    start = float(max(delay_primary, delay_aux))
    return boundary + math.ceil((start - boundary) / period) * period


def _level_after(level, smoothed: float, lo: float, hi: float):
    """The hysteresis: 1 above ``hi``, 0 below ``lo``, else the level held (None before the first)."""
    if smoothed > hi:
        return 1
    if smoothed < lo:
        return 0
    return level


def naive_slicer(primary, aux, *, lo, mid, hi, smooth, fraction, phase_gain, rate_gain, delay_primary=0,
                 delay_aux=0, clock=None):
    """(cell centres, soft primary, soft aux, transitions) of the whole record.

    ``clock`` is None to detect transitions only, or ``(first_boundary,
    period)`` in samples of the primary to integrate cells.  Times are in
    samples of the primary, its delay removed.
    """
    primary = [float(x) for x in primary]
    aux = [float(x) for x in aux]
    delayed = [primary[max(n - delay_primary, 0)] for n in range(len(primary))]
    delayed_aux = [aux[max(n - delay_aux, 0)] for n in range(len(aux))]
    locked = clock is not None
    if locked:
        period = float(clock[1])
        cell_end = first_cell_start(clock[0], period, delay_primary, delay_aux) + period
    level = None
    previous = None
    crossing = None
    sum_primary = sum_aux = 0.0
    count = 0
    centres, soft, soft_aux, transitions = [], [], [], []
    for n, value in enumerate(delayed):
        window = delayed[max(0, n - smooth + 1) : n + 1]
        smoothed = sum(window) / len(window)
        if previous is not None and (previous - mid) * (smoothed - mid) <= 0 and previous != smoothed:
            crossing = n - 1 + (previous - mid) / (previous - smoothed) - 0.5 * (smooth - 1)
        previous = smoothed
        new_level = _level_after(level, smoothed, lo, hi)
        transition = level is not None and new_level != level
        level = new_level
        if transition and crossing is not None:
            transitions.append(crossing)
            if locked:
                start = cell_end - period
                nearest = start + period * math.floor((crossing - start) / period + 0.5)
                error = crossing - nearest
                cell_end += phase_gain * error
                period += rate_gain * error
        if not locked:
            continue
        start = cell_end - period
        if n >= start:
            phase = (n - start) / period
            if 0.5 * (1 - fraction) <= phase < 0.5 * (1 + fraction):
                sum_primary += value
                sum_aux += delayed_aux[n]
                count += 1
            if n + 1 >= cell_end:
                centres.append(cell_end - 0.5 * period - delay_primary)
                soft.append(sum_primary / count if count else math.nan)
                soft_aux.append(sum_aux / count if count else math.nan)
                sum_primary = sum_aux = 0.0
                count = 0
                cell_end += period
    return centres, soft, soft_aux, [t - delay_primary for t in transitions]
