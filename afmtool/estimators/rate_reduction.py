"""REEP's rate: the same anti-alias filter on deflection and dither, then decimation by D.

Why (issue 27, item 2).  The second-order ARX regression of eq. 3.40 has
its poles at z = e^{(−p ± jq)T}; sampled many times per period they crowd
z = 1, φ(n) = [−p(n−1), −p(n−2)] become nearly collinear, and the
equation error e = (1 + b1z⁻¹ + b0z⁻²)ϑ is the white noise's second
difference, whose power sits where the signal is not.  The estimate's
scatter grows with fs/f0 at a fixed window in time: measured on the
reference simulator (75 kHz, Q 250, 0.05 nm, window 400 µs), f0′ scatters
0.98 Hz at 500 kHz (fs/f0 = 6.7) and 3.42 Hz at 2 MHz (26.7).

Two remedies were weighed.  The δ-operator (δ = (q − 1)/T) re-parametrises
the same linear regression: its least-squares estimate spans the same
transfer functions, so it cures rounding in the coefficients but not this
statistical loss.  Band-limiting and decimating removes the cause: the
out-of-band noise that the second difference amplifies.  Decimated by D
(the same capture, fs/(D·f0) after it):

====  =========  ===========  ===========
 D    fs/(D f0)  f0′ std Hz   Q′ std %
====  =========  ===========  ===========
 1      26.7        3.42        2.28
 2      13.3        1.22        0.82
 4       6.7        0.49        0.33
 6       4.4        0.33        0.22
 8       3.3        0.32        0.20
====  =========  ===========  ===========

So D = ⌊fs/(N·f0)⌋ with N = ``samples_per_period`` (4 by default): REEP sees
N to 2N samples per period, where the scatter has flattened, and the thesis's
operating point (500 kHz, 70 kHz: 7.1 per period) is left as it was (D = 1).

The model stays exact.  Applied to both signals, one linear filter H keeps
the relation between them: at every line ω of a continuous drive the
filtered deflection over the filtered dither is still G(jω) (H cancels),
and decimation keeps each line below the new Nyquist frequency where it
was.  The free-air numerator at the new rate is matched to the capture-rate
model at the drive line and at DC
(:func:`afmtool.models.discretisation.rate_numerator`).  Harmonics of
tapping above the new Nyquist frequency, which the linear model does not
have, are removed by the filter instead of folding onto the band.

The filter: a root-raised-cosine low-pass (roll-off β = 0.35, ±8 output
periods, not windowed) whose output sampled every D samples has white
noise if the input's noise was white: |H|² is a raised cosine, a Nyquist
pulse at the new rate, so Σ_k h[n]h[n + kD] = 0 for k ≠ 0 (3e-5 of the
energy after truncation at D = 4; a window would raise it to 1e-2).  The
bias compensation of eq. 3.39 needs that whiteness (eq. 3.15).  Its DC
gain is 1, so deflection units and the static offset pass unchanged.  Its
delay is 8 output periods (two drive periods at N = 4).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.estimators.decimation import Decimation
from afmtool.jit import JIT_OPTIONS

__all__ = ["ANTI_ALIAS_ROLLOFF", "ANTI_ALIAS_SPAN", "anti_alias_taps", "decimate_block", "reduction_factor"]

#: Roll-off β of the root-raised-cosine anti-alias filter.
ANTI_ALIAS_ROLLOFF = 0.35
#: Its half-length, in output (decimated) samples.
ANTI_ALIAS_SPAN = 8


def reduction_factor(sample_rate_hz: float, resonance_hz: float, samples_per_period: float) -> int:
    """D = ⌊fs/(N·f0)⌋, at least 1; 1 when N is 0 (REEP at the capture's rate)."""
    if samples_per_period == 0:
        return 1
    if not (resonance_hz > 0 and samples_per_period > 0 and sample_rate_hz > 0):
        raise ConfigError(f"cannot reduce the rate: f0 = {resonance_hz!r} Hz, N = {samples_per_period!r}")
    return max(1, math.floor(sample_rate_hz / (samples_per_period * resonance_hz)))


def anti_alias_taps(factor: int, rolloff: float = ANTI_ALIAS_ROLLOFF, span: int = ANTI_ALIAS_SPAN) -> np.ndarray:
    """Root-raised-cosine taps for decimation by ``factor`` (module docstring), DC gain 1.

    h(t) = [sin(πt(1 − β)) + 4βt·cos(πt(1 + β))] / [πt(1 − (4βt)²)] with t in
    output periods, at t = n/D for |n| ≤ span·D; the limits at t = 0 and
    |t| = 1/(4β) are the standard ones.  ``factor`` 1 returns [1.0].
    """
    if factor == 1:
        return np.ones(1)
    t = np.arange(-span * factor, span * factor + 1) / factor
    beta = rolloff
    taps = np.empty_like(t)
    for i, ti in enumerate(t):
        if ti == 0.0:
            taps[i] = 1.0 - beta + 4.0 * beta / math.pi
        elif abs(abs(ti) - 1.0 / (4.0 * beta)) < 1e-12:
            angle = math.pi / (4.0 * beta)
            taps[i] = beta / math.sqrt(2.0) * ((1 + 2 / math.pi) * math.sin(angle) + (1 - 2 / math.pi) * math.cos(angle))
        else:
            taps[i] = (math.sin(math.pi * ti * (1 - beta)) + 4 * beta * ti * math.cos(math.pi * ti * (1 + beta))) / (
                math.pi * ti * (1 - (4 * beta * ti) ** 2)
            )
    return taps / taps.sum()


@njit(**JIT_OPTIONS)
def _decimate_kernel(x, taps, every, first, history, out):
    """y(n) = Σ_k h[k]·x(n − k) at the kept samples n = first, first + every, …; ``history`` = the L − 1 before x.

    ``history`` is read at entry and holds the last L − 1 inputs at exit.
    """
    n_taps = taps.shape[0]
    past = n_taps - 1
    k = 0
    for i in range(first, x.shape[0], every):
        acc = 0.0
        for j in range(n_taps):
            m = i - j
            acc += taps[j] * (x[m] if m >= 0 else history[past + m])
        out[k] = acc
        k += 1
    n = x.shape[0]
    if n >= past:
        for j in range(past):
            history[j] = x[n - past + j]
    else:
        for j in range(past - n):
            history[j] = history[j + n]
        for j in range(n):
            history[past - n + j] = x[j]


def decimate_block(x: np.ndarray, taps: np.ndarray, factor: int, start: int, history: np.ndarray) -> np.ndarray:
    """Filtered ``x`` at the samples Decimation(factor) keeps, ``x`` starting at capture sample ``start``.

    ``history`` (length len(taps) − 1; zeros at the stream's start) is
    updated in place, so consecutive chunks give the output of one call.
    """
    decimation = Decimation(factor)
    out = np.empty(decimation.count(start, x.shape[0]))
    _decimate_kernel(np.ascontiguousarray(x, dtype=np.float64), taps, factor, decimation.first_kept(start), history, out)
    return out
