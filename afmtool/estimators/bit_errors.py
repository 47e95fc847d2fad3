"""Decoded bits against the ground truth: the bit error rate and its bound (thesis ch. 7).

Moved out of :mod:`afmtool.analyses.decode` (issue 29, item 6): the bit
statistics are an estimator of their own, used by decode's truth
comparison and by the tests.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = ["BitErrors", "bit_errors", "ber_upper_bound"]


class BitErrors(NamedTuple):
    """Decoded bits against the ground truth."""

    compared: int  #: decoded bits that fall on a truth bit cell
    errors: int
    ber: float  #: errors/compared (NaN if none compared)
    lag_samples: int  #: latency from the truth cell to the decoded centre (the alignment chosen)
    inverted: bool  #: the polarity was flipped (baseline only)
    confusion: dict  #: counts "truth0_decoded0", "truth0_decoded1", "truth1_decoded0", "truth1_decoded1"


def bit_errors(
    bits: np.ndarray,
    centre_samples: np.ndarray,
    truth_bit: np.ndarray,
    truth_index: np.ndarray,
    *,
    max_lag: int,
    allow_inversion: bool = False,
) -> BitErrors:
    """Compare decoded bits with the truth after aligning the latency.

    Decoded bit i (centre c_i, samples of the signal it was decoded from) is
    compared with the truth bit under the tip at sample round(c_i − L).  The
    latency L ∈ [0, max_lag] is the one with the fewest errors (a BER
    tester's pattern alignment; ties: the middle of the best range).  With
    ``allow_inversion`` the polarity is chosen the same way.

    Parameters
    ----------
    bits : numpy.ndarray
        Decoded bits (0/1).
    centre_samples : numpy.ndarray
        Their centres, samples from the capture start.
    truth_bit, truth_index : numpy.ndarray
        Per-sample truth: the bit under the tip and its cell (−1 outside).
    max_lag : int
        Largest latency tried, samples.
    allow_inversion : bool, optional
        Also try the inverted bits.
    """
    bits = np.asarray(bits).astype(bool)
    centres = np.asarray(centre_samples, dtype=np.float64)
    truth_bit = np.asarray(truth_bit).astype(bool)
    truth_index = np.asarray(truth_index)
    n = truth_bit.size
    best = None
    for lag in range(max_lag + 1):
        idx = np.rint(centres - lag).astype(np.int64)
        ok = (idx >= 0) & (idx < n)
        ok[ok] &= truth_index[idx[ok]] >= 0
        if not ok.any():
            continue
        truth = truth_bit[idx[ok]]
        decoded = bits[ok]
        for inverted in (False, True) if allow_inversion else (False,):
            errors = int(np.count_nonzero((decoded ^ inverted) != truth))
            rate = errors / ok.sum()
            if best is None or rate < best[0] - 1e-15:
                best = (rate, [(lag, inverted, errors, int(ok.sum()))])
            elif abs(rate - best[0]) <= 1e-15:
                best[1].append((lag, inverted, errors, int(ok.sum())))
    if best is None:
        return BitErrors(0, 0, math.nan, 0, False, {})
    lag, inverted, errors, compared = best[1][len(best[1]) // 2]
    idx = np.rint(centres - lag).astype(np.int64)
    ok = (idx >= 0) & (idx < n)
    ok[ok] &= truth_index[idx[ok]] >= 0
    truth = truth_bit[idx[ok]]
    decoded = bits[ok] ^ inverted
    confusion = {
        f"truth{t}_decoded{d}": int(np.count_nonzero((truth == bool(t)) & (decoded == bool(d))))
        for t in (0, 1) for d in (0, 1)
    }
    return BitErrors(compared, errors, errors / compared, int(lag), bool(inverted), confusion)


def ber_upper_bound(errors: int, compared: int, confidence: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound of a bit error rate: ``errors`` in ``compared`` bits.

    For no errors it is 1 − (1 − confidence)^(1/n) ≈ 3/n at 95 % (the rule of three).
    """
    from scipy.special import betaincinv  # scipy.stats.beta.ppf is this, and scipy.stats costs 0.4 s to import

    if not 0 <= errors <= compared or compared < 1:
        raise ConfigError(f"errors={errors!r} and compared={compared!r} must satisfy 0 <= errors <= compared, compared >= 1")
    if errors == compared:
        return 1.0
    return float(betaincinv(errors + 1, compared - errors, confidence))
