"""Bias-compensated exponentially weighted recursive least squares (BCEWRLS).

Two estimators of the sampled cantilever of eq. 3.40,

.. math:: p(n) + b_1 p(n-1) + b_0 p(n-2) = a_2 g(n) + a_1 g(n-1) + a_0 g(n-2) + e(n),

where ``p`` is the measured deflection, ``g`` the dither forcing and
e(n) = ϑ(n) + b1·ϑ(n−1) + b0·ϑ(n−2) the coloured residual left by white
measurement noise ϑ of variance σ².  Because the regressors −p(n−1), −p(n−2)
contain ϑ, plain least squares converges to θ − σ²R⁻¹Λθ (eq. 3.18), not θ.

* :func:`reep_update` / :func:`reep` — REEP (§3.3.3): the two denominator
  coefficients θ = [b1, b0] tracked sample by sample with the numerator
  fixed, Λ = I₂.  A numba kernel with its whole state in scalars, streamable
  chunk by chunk.
* :func:`bcewrls` — the general eq. 3.39 for any regressor matrix and any
  diagonal Λ (matrix P, for short segments), and :func:`identify_arx`, the
  free-air identification of all five coefficients [b1, b0, a2, a1, a0] with
  Λ = diag(1, 1, 0, 0, 0), by batch bias-compensated least squares (default),
  plain least squares, or the recursive form.

Static offset (``ReepState.static_offset``).  An attractive force adds
a static part F̄ to the equation of motion, p̈ + (ω′/Q′)ṗ + ω′²p =
ω0²g + F̄ + (the linearised, sample-dependent part that moves ω′ and Q′).
Its particular solution is the constant p̄ = F̄/ω′², so p − p̄ obeys
eq. 3.40, and substituting p = (p − p̄) + p̄ gives

.. math:: p(n) + b_1 p(n-1) + b_0 p(n-2) = a_2 g(n) + a_1 g(n-1) + a_0 g(n-2)
          + (1 + b_1 + b_0)\\,\\bar p + e(n),

exactly for any hold of g (a constant is the same under every
discretisation).  Eq. 3.40 has no constant term, so least squares
absorbs (1 + b1 + b0)p̄ into b1, b0: with an offset of a few nm beside
an oscillation of 0.3 nm (the bottom of the attractive trap) it drives
1 + b1 + b0 toward 0, a pole near z = 1, and f0′ ≈ 13 kHz, Q′ ≈ 0.7
instead of 63 kHz, 8.9.  The constant regressor restores the model:
θ = [b1, b0, c], φ(n) = [−p(n−1), −p(n−2), 1]ᵀ, c = (1 + b1 + b0)p̄,
tracked by the same exponential window, so p̄ may drift as the
separation changes.  The bias compensation stays exact with
Λ = diag(1, 1, 0): the third regressor is noise-free, so
E[φ(n)e(n)] = −σ²Λθ (eq. 3.15) and J(n)w_n → σ²(1 + θᵀΛθ̂_LS)
(eq. 3.31) hold unchanged, and eq. 3.39 reads as in :func:`reep_update` with
θ̂_C(n) = θ̂_LS(n) + (σ̂²/w_n)P(n)[b̂1_C, b̂0_C, 0]ᵀ(n−1) and the same
σ̂² denominator 1 + b̂1_C b̂1_LS + b̂0_C b̂0_LS.  (The alternative, one
high-pass on deflection and dither, keeps eq. 3.40 but colours ϑ, and
eq. 3.15 needs ϑ white; it would bias the compensation.)  The cost is
a 3 × 3 P (six scalars) instead of 2 × 2.

Start-up and guards.  The first two samples of a stream only fill p(n−1),
p(n−2) (and g): their output is θ̂(0) = 0 with σ̂² = NaN.  Two guards, inactive in normal
operation, extend eq. 3.39 (details in ``_reep_kernel``):

* the compensation of a sample is skipped (σ̂² = NaN, θ̂_C = θ̂_LS) when
  1 + θ̂_C(n−1)ᵀθ̂_LS(n) ≤ 1/2.  This happens in the first few samples
  and on a deflection that is noise only, where σ²R⁻¹ ≈ I and the
  compensation is ill-posed;
* forgetting is suspended (λ_n = 1) while trace P(n−1) ≥ 2·P0, so a
  stretch without excitation (zeros) cannot overflow P.  After a long
  stretch σ̂² reads low until it is forgotten (about 4 ms after 0.4 s of
  zeros at λ = 0.995).

Units: the default P0 = 1e6 of the thesis assumes deflection and dither in
nanometres (P(0) must be large against the steady-state P, about
(1 − λ)/mean(p²)); see :meth:`ReepState.initial`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError, InputError
from afmtool.estimators._common import as_signal, channel_rms, check_numerator, check_resolvable
from afmtool.estimators.decimation import Decimation
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "DEFAULT_FORGETTING_FACTOR",
    "DEFAULT_P0",
    "MIN_BIAS_DENOMINATOR",
    "ReepState",
    "ReepBlock",
    "ReepStep",
    "reep_update",
    "reep",
    "BcewrlsResult",
    "bcewrls",
    "arx_regressors",
    "ArxFit",
    "identify_arx",
]

#: Forgetting factor λ of the thesis (§3.3.3): a window 1/(1 − λ) = 200 samples.
DEFAULT_FORGETTING_FACTOR = 0.995

#: P(0) = P0·I of the thesis (§3.3.3), sized for deflection in nm.
DEFAULT_P0 = 1.0e6

#: Smallest accepted value of the σ̂² denominator 1 + θ̂_C(n−1)ᵀΛθ̂_LS(n) (eq. 3.33).
#: At convergence it is 1 + θᵀΛθ ≥ 1 (Λ is positive semi-definite); below 1/2 the
#: estimates are still in their start-up transient (or the compensation is
#: ill-posed, as on noise-only data), σ̂² would be meaningless or negative, and
#: the compensation of that sample is skipped (see ``_reep_kernel``).
MIN_BIAS_DENOMINATOR = 0.5

# Slots of the carried REEP state vector (float64), read at kernel entry and
# written back at exit, so that chunked and single runs are bit-for-bit equal.
_TH_LS_B1, _TH_LS_B0 = 0, 1  # θ̂_LS(n) = [b1, b0]
_TH_C_B1, _TH_C_B0 = 2, 3  # θ̂_C(n)
_P11, _P12, _P22 = 4, 5, 6  # P(n) = [[P11, P12], [P12, P22]]
_J = 7  # J(n), eq. 3.38
_N = 8  # n, regression updates so far
_S = 9  # S(n) = 1/w_n = Σ_{i<n} λ^i
_P_1, _P_2 = 10, 11  # p(n−1), p(n−2)
_G_1, _G_2 = 12, 13  # g(n−1), g(n−2)
_N_PAST = 14  # past samples held, 0…2
# the constant regressor of the static-offset variant (``_reep_offset_kernel``); unused otherwise
_TH_LS_C, _TH_C_C = 15, 16  # constant term c of θ̂_LS(n), θ̂_C(n)
_P13, _P23, _P33 = 17, 18, 19  # the third row of the 3 × 3 P(n)
_P_3 = 20  # p(n−3): φ(n−1) of the covariance's second edge term (``_edge_covariance``)
_STATE_LEN = 21



# ---------------------------------------------------------------------------
# The covariance of REEP's estimate, at the kept samples
# ---------------------------------------------------------------------------


@njit(**JIT_OPTIONS)
def _filter_gain2(b1, b0, lam, w):
    """|Ã(e^{jw})|² with Ã(x) = 1 + (b1/λ)x + (b0/λ²)x² (:func:`_edge_covariance_2`)."""
    c1 = b1 / lam
    c2 = b0 / (lam * lam)
    re = 1.0 + c1 * math.cos(w) + c2 * math.cos(2.0 * w)
    im = c1 * math.sin(w) + c2 * math.sin(2.0 * w)
    return re * re + im * im


@njit(**JIT_OPTIONS)
def _edge_covariance_2(p11, p12, p22, phi1, phi2, prev1, prev2, b1, b0, sigma2, lam, drive_w, out, k):
    r"""Cov(θ̂(n)) of the two-parameter REEP into ``out[k]`` = (var b1, cov(b1, b0), var b0).

    Derivation (white measurement noise ϑ of variance σ², module docstring).
    EW least squares gives θ̂(n) − θ = P(n)·Σ_k λ^{n−k} φ(k)e(k) with
    e(k) = ϑ(k) + b1 ϑ(k−1) + b0 ϑ(k−2).  Collecting the coefficient of
    each ϑ(j), the sum is Σ_j ϑ(j)·v(j) with

    * v(n)   = φ(n),
    * v(n−1) = λφ(n−1) + b1 φ(n),
    * v(j)   = λ^{n−j}[φ(j) + (b1/λ)φ(j+1) + (b0/λ²)φ(j+2)], j ≤ n − 2.

    For the oscillating part of φ at the drive ω the bracket of the bulk is
    φ filtered by Ã(x) = 1 + (b1/λ)x + (b0/λ²)x², whose zeros sit at the
    estimated poles scaled by 1/λ: near resonance |Ã(e^{jω})|² is of order
    ((1 − r/λ)·2 sin ω)², 1e-5 at the thesis's operating point, so the two
    newest samples dominate the variance (measured: 99.9 % of it on a
    reference capture at 70 kHz, Q 200, 500 kHz).  With Σ_j λ^{2(n−j)}φφᵀ
    ≈ P⁻¹(n)/(1 + λ) for the bulk,

    .. math:: \mathrm{Cov}\,\hat\theta(n) \approx \hat\sigma^2(n)\Big[P v(n) v(n)^T P
              + P v(n-1) v(n-1)^T P + \frac{|\tilde A(e^{j\omega})|^2}{1+\lambda} P\Big].

    The edge vectors are formed from the measured regressors: the σ² their
    noise adds is the quadratic (noise × noise) term of the same two
    samples.  The bias compensation changes the estimate by
    (I − σ̂²S_w PΛ)⁻¹, within 1e-3 of I wherever the amplitude is above the
    validity floor, and is left out, as is the spread of σ̂².  Checked by
    coverage on the reference simulator (``tests/test_reep_coverage.py``).
    """
    u1 = lam * prev1 + b1 * phi1
    u2 = lam * prev2 + b1 * phi2
    v11 = p11 * phi1 + p12 * phi2
    v12 = p12 * phi1 + p22 * phi2
    v21 = p11 * u1 + p12 * u2
    v22 = p12 * u1 + p22 * u2
    bulk = _filter_gain2(b1, b0, lam, drive_w) / (1.0 + lam) if drive_w > 0.0 else 0.0
    out[k, 0] = sigma2 * (v11 * v11 + v21 * v21 + bulk * p11)
    out[k, 1] = sigma2 * (v11 * v12 + v21 * v22 + bulk * p12)
    out[k, 2] = sigma2 * (v12 * v12 + v22 * v22 + bulk * p22)


@njit(**JIT_OPTIONS)
def _edge_covariance_3(
    p11, p12, p22, p13, p23, p33, phi1, phi2, prev1, prev2, b1, b0, c, sigma2, lam, drive_w, out, k
):
    r""":func:`_edge_covariance_2` for θ = [b1, b0, c]: the (b1, b0) block of the 3 × 3 covariance.

    φ = [−p(n−1), −p(n−2), 1], so the edge vectors carry 1 and λ + b1 in
    their third entry.  The bulk splits φ into its oscillation and its
    constant part φ_dc = [−p̄, −p̄, 1] (p̄ = c/(1 + b1 + b0), the static
    offset), filtered by Ã at the drive and at DC respectively:

    .. math:: \sigma^2\Big\{|\tilde A(e^{j\omega})|^2\Big[\frac{P}{1+\lambda}
              - \frac{P\varphi_{dc}\varphi_{dc}^T P}{1-\lambda^2}\Big]
              + |\tilde A(1)|^2 \frac{P\varphi_{dc}\varphi_{dc}^T P}{1-\lambda^2}\Big\}.
    """
    u1 = lam * prev1 + b1 * phi1
    u2 = lam * prev2 + b1 * phi2
    u3 = lam + b1
    v11 = p11 * phi1 + p12 * phi2 + p13
    v12 = p12 * phi1 + p22 * phi2 + p23
    v21 = p11 * u1 + p12 * u2 + p13 * u3
    v22 = p12 * u1 + p22 * u2 + p23 * u3
    c11 = v11 * v11 + v21 * v21
    c12 = v11 * v12 + v21 * v22
    c22 = v12 * v12 + v22 * v22
    if drive_w > 0.0:
        at_drive = _filter_gain2(b1, b0, lam, drive_w)
        at_dc = 1.0 + b1 / lam + b0 / (lam * lam)
        at_dc *= at_dc
        offset = c / (1.0 + b1 + b0)
        w1 = p13 - offset * (p11 + p12)
        w2 = p23 - offset * (p12 + p22)
        if not math.isfinite(w1 + w2):
            w1 = 0.0
            w2 = 0.0
        dc = (at_dc - at_drive) / (1.0 - lam * lam)
        bulk = at_drive / (1.0 + lam)
        c11 += bulk * p11 + dc * w1 * w1
        c12 += bulk * p12 + dc * w1 * w2
        c22 += bulk * p22 + dc * w2 * w2
    out[k, 0] = sigma2 * c11
    out[k, 1] = sigma2 * c12
    out[k, 2] = sigma2 * c22


# ---------------------------------------------------------------------------
# REEP: two-parameter kernel
# ---------------------------------------------------------------------------


@njit(**JIT_OPTIONS)
def _reep_kernel(  # noqa: PLR0915 - numba kernel: one scalar recursion
    p, g, a2, a1, a0, use_input, lam, trace_cap, bias_compensation, keep_every, drive_w, state, out_b1, out_b0,
    out_sigma2, out_cov,
):
    """Run REEP (eq. 3.39 with θ = [b1, b0], Λ = I₂) over one chunk.

    ``state`` is read at entry and overwritten at exit.  ``out_*`` are
    preallocated, one value per kept sample: those whose index n in the
    stream has (n + 1) % keep_every == 0; ``out_cov`` (K, 3) receives the
    covariance (var b1, cov, var b0) of the output θ̂ (``_edge_covariance``,
    with the drive at ``drive_w`` rad per sample; 0 leaves its bulk term out).
    Two guards, both inactive in normal operation, extend eq. 3.39:

    * anti-windup: while trace P(n−1) ≥ ``trace_cap`` (= trace P(0)) this
      sample is processed with λ_n = 1 (no forgetting), so P never grows past
      its prior when the deflection carries no excitation (zeros, gaps) and
      cannot overflow to inf.  Every other equation uses the same λ_n, so the
      update stays that of exact weighted least squares;
    * start-up: if 1 + θ̂_C(n−1)ᵀθ̂_LS(n) ≤ MIN_BIAS_DENOMINATOR the sample is
      not compensated: σ̂²(n) is NaN and θ̂_C(n) = θ̂_LS(n), which restarts the
      compensation from the LS estimate.  At convergence the denominator is
      1 + θᵀθ ≥ 1; it is small or negative only while θ̂_C and θ̂_LS are
      still far apart (first samples) or when the compensation is ill-posed
      (noise-only input, σ²R⁻¹ ≈ I).  A NaN denominator also lands here.
    """
    th_b1 = state[_TH_LS_B1]
    th_b0 = state[_TH_LS_B0]
    c_b1 = state[_TH_C_B1]
    c_b0 = state[_TH_C_B0]
    p11 = state[_P11]
    p12 = state[_P12]
    p22 = state[_P22]
    jn = state[_J]
    n = state[_N]
    s_w = state[_S]
    p_1 = state[_P_1]
    p_2 = state[_P_2]
    p_3 = state[_P_3]
    g_1 = state[_G_1]
    g_2 = state[_G_2]
    n_past = state[_N_PAST]
    inv_lam = 1.0 / lam
    nan = np.nan
    # countdown to the next kept sample; samples seen so far = n + n_past
    seen = int(n + n_past)
    until_keep = (keep_every - (seen + 1) % keep_every) % keep_every
    k = 0

    for i in range(p.shape[0]):
        p_n = p[i]
        if n_past < 2.0:
            # φ(n) needs p(n−1) and p(n−2): the first two samples of a stream
            # only fill the past buffers, like rows n ≥ 2 of arx_regressors
            n_past += 1.0
            p_3 = p_2
            p_2 = p_1
            p_1 = p_n
            if use_input:
                g_2 = g_1
                g_1 = g[i]
            if until_keep == 0:
                out_b1[k] = c_b1 if bias_compensation else th_b1
                out_b0[k] = c_b0 if bias_compensation else th_b0
                out_sigma2[k] = nan
                out_cov[k, 0] = nan
                out_cov[k, 1] = nan
                out_cov[k, 2] = nan
                k += 1
                until_keep = keep_every - 1
            else:
                until_keep -= 1
            continue
        if use_input:
            g_n = g[i]
            # z(n) = p(n) − a2 g(n) − a1 g(n−1) − a0 g(n−2)                  (eq. 3.41)
            z = p_n - a2 * g_n - a1 * g_1 - a0 * g_2
            g_2 = g_1
            g_1 = g_n
        else:
            # output-only AR(2): z(n) = p(n)
            z = p_n
        # φ(n) = [−p(n−1), −p(n−2)]ᵀ                                          (eq. 3.41)
        phi1 = -p_1
        phi2 = -p_2
        # λ_n = λ, or 1 while trace P(n−1) ≥ trace P(0) (anti-windup guard)
        if p11 + p22 < trace_cap:
            lam_n = lam
            inv_lam_n = inv_lam
        else:
            lam_n = 1.0
            inv_lam_n = 1.0
        # s = λ + φᵀ(n) P(n−1) φ(n), summed as Σ φ_i φ_j P_ij: the products of φ
        # do not wait for P(n−1), which keeps the P → s → 1/s → P chain short
        s = lam_n + ((phi1 * phi1) * p11 + (2.0 * phi1 * phi2) * p12 + (phi2 * phi2) * p22)
        inv_s = 1.0 / s
        # k = P(n−1) φ(n), computed while 1/s is pending
        k1 = p11 * phi1 + p12 * phi2
        k2 = p12 * phi1 + p22 * phi2
        # l(n) = z(n) − φᵀ(n) θ̂_LS(n−1)
        l_n = z - phi1 * th_b1 - phi2 * th_b0
        # J(n) = λ [J(n−1) + l(n)² / s]                                      (eq. 3.38)
        jn = lam_n * (jn + l_n * l_n * inv_s)
        # P(n) = [P(n−1) − k kᵀ / s] / λ                                     (eq. 3.39)
        # as three scalars, so P stays exactly symmetric, and arranged as
        # P/λ − (k kᵀ/λ)·(1/s) so only a multiply and a subtract wait for 1/s
        p11 = p11 * inv_lam_n - (k1 * k1 * inv_lam_n) * inv_s
        p12 = p12 * inv_lam_n - (k1 * k2 * inv_lam_n) * inv_s
        p22 = p22 * inv_lam_n - (k2 * k2 * inv_lam_n) * inv_s
        # θ̂_LS(n) = θ̂_LS(n−1) + P(n) φ(n) l(n), using P(n) φ(n) = k / s
        gain_l = l_n * inv_s
        th_b1 = th_b1 + k1 * gain_l
        th_b0 = th_b0 + k2 * gain_l
        # 1/w_n = (1 − λⁿ)/(1 − λ) = λ·(1/w_{n−1}) + 1, exact also for λ = 1
        s_w = lam_n * s_w + 1.0
        n += 1.0
        # d = 1 + θ̂_C(n−1)ᵀ Λ θ̂_LS(n), Λ = I₂                              (eq. 3.33)
        den = 1.0 + c_b1 * th_b1 + c_b0 * th_b0
        if den > MIN_BIAS_DENOMINATOR:
            # σ̂²(n)/w_n = J(n) / d
            r = jn / den
            # σ̂²(n) = w_n J(n) / d                                           (eq. 3.39)
            sigma2 = r / s_w
            # θ̂_C(n) = θ̂_LS(n) + (σ̂²(n)/w_n) P(n) Λ θ̂_C(n−1)               (eq. 3.39)
            new_b1 = th_b1 + r * (p11 * c_b1 + p12 * c_b0)
            new_b0 = th_b0 + r * (p12 * c_b1 + p22 * c_b0)
            c_b1 = new_b1
            c_b0 = new_b0
        else:
            # start-up guard (or NaN input): no compensation for this sample
            sigma2 = nan
            c_b1 = th_b1
            c_b0 = th_b0
        # φ(n−1) = [−p(n−2), −p(n−3)]ᵀ, for the covariance's edge term
        prev2 = -p_3
        p_3 = p_2
        p_2 = p_1
        p_1 = p_n
        if until_keep == 0:
            if bias_compensation:
                out_b1[k] = c_b1
                out_b0[k] = c_b0
            else:
                out_b1[k] = th_b1
                out_b0[k] = th_b0
            out_sigma2[k] = sigma2
            _edge_covariance_2(
                p11, p12, p22, phi1, phi2, phi2, prev2, out_b1[k], out_b0[k], sigma2, lam, drive_w, out_cov, k
            )
            k += 1
            until_keep = keep_every - 1
        else:
            until_keep -= 1

    state[_TH_LS_B1] = th_b1
    state[_TH_LS_B0] = th_b0
    state[_TH_C_B1] = c_b1
    state[_TH_C_B0] = c_b0
    state[_P11] = p11
    state[_P12] = p12
    state[_P22] = p22
    state[_J] = jn
    state[_N] = n
    state[_S] = s_w
    state[_P_1] = p_1
    state[_P_2] = p_2
    state[_P_3] = p_3
    state[_G_1] = g_1
    state[_G_2] = g_2
    state[_N_PAST] = n_past


@njit(**JIT_OPTIONS)
def _reep_offset_kernel(  # noqa: PLR0915 - numba kernel: one scalar recursion
    p, g, a2, a1, a0, use_input, lam, trace_cap, bias_compensation, keep_every, drive_w, state, out_b1, out_b0,
    out_sigma2, out_cov, out_c,
):
    """REEP with a constant regressor: eq. 3.39 with θ = [b1, b0, c], Λ = diag(1, 1, 0).

    φ(n) = [−p(n−1), −p(n−2), 1]ᵀ, so z(n) = φᵀ(n)θ + e(n) carries the static
    term c = (1 + b1 + b0)·p̄ of a deflection offset p̄ (see :func:`reep_update`,
    Notes).  The same recursion, guards and output rule as ``_reep_kernel``,
    with the symmetric 3 × 3 P(n) held as six scalars; ``trace_cap`` is
    trace P(0) = 3·P0.  ``out_c`` receives c (deflection units), ``out_cov`` the
    (b1, b0) block of its covariance (``_edge_covariance_3``).
    """
    th_b1 = state[_TH_LS_B1]
    th_b0 = state[_TH_LS_B0]
    th_c = state[_TH_LS_C]
    c_b1 = state[_TH_C_B1]
    c_b0 = state[_TH_C_B0]
    c_c = state[_TH_C_C]
    p11 = state[_P11]
    p12 = state[_P12]
    p22 = state[_P22]
    p13 = state[_P13]
    p23 = state[_P23]
    p33 = state[_P33]
    jn = state[_J]
    n = state[_N]
    s_w = state[_S]
    p_1 = state[_P_1]
    p_2 = state[_P_2]
    p_3 = state[_P_3]
    g_1 = state[_G_1]
    g_2 = state[_G_2]
    n_past = state[_N_PAST]
    inv_lam = 1.0 / lam
    nan = np.nan
    seen = int(n + n_past)
    until_keep = (keep_every - (seen + 1) % keep_every) % keep_every
    k = 0

    for i in range(p.shape[0]):
        p_n = p[i]
        if n_past < 2.0:
            n_past += 1.0
            p_3 = p_2
            p_2 = p_1
            p_1 = p_n
            if use_input:
                g_2 = g_1
                g_1 = g[i]
            if until_keep == 0:
                out_b1[k] = c_b1 if bias_compensation else th_b1
                out_b0[k] = c_b0 if bias_compensation else th_b0
                out_c[k] = c_c if bias_compensation else th_c
                out_sigma2[k] = nan
                out_cov[k, 0] = nan
                out_cov[k, 1] = nan
                out_cov[k, 2] = nan
                k += 1
                until_keep = keep_every - 1
            else:
                until_keep -= 1
            continue
        if use_input:
            g_n = g[i]
            # z(n) = p(n) − a2 g(n) − a1 g(n−1) − a0 g(n−2)                  (eq. 3.41)
            z = p_n - a2 * g_n - a1 * g_1 - a0 * g_2
            g_2 = g_1
            g_1 = g_n
        else:
            z = p_n
        # φ(n) = [−p(n−1), −p(n−2), 1]ᵀ
        phi1 = -p_1
        phi2 = -p_2
        if p11 + p22 + p33 < trace_cap:
            lam_n = lam
            inv_lam_n = inv_lam
        else:
            lam_n = 1.0
            inv_lam_n = 1.0
        # s = λ + φᵀ(n) P(n−1) φ(n), the third regressor being 1, summed as Σ φ_i φ_j P_ij
        # so that it does not wait for k (as in _reep_kernel)
        s = lam_n + (
            ((phi1 * phi1) * p11 + (2.0 * phi1 * phi2) * p12 + (phi2 * phi2) * p22)
            + ((2.0 * phi1) * p13 + (2.0 * phi2) * p23 + p33)
        )
        inv_s = 1.0 / s
        # k = P(n−1) φ(n), computed while 1/s is pending
        k1 = p11 * phi1 + p12 * phi2 + p13
        k2 = p12 * phi1 + p22 * phi2 + p23
        k3 = p13 * phi1 + p23 * phi2 + p33
        # l(n) = z(n) − φᵀ(n) θ̂_LS(n−1)
        l_n = z - phi1 * th_b1 - phi2 * th_b0 - th_c
        # J(n) = λ [J(n−1) + l(n)² / s]                                      (eq. 3.38)
        jn = lam_n * (jn + l_n * l_n * inv_s)
        # P(n) = [P(n−1) − k kᵀ / s] / λ, six scalars so P stays symmetric   (eq. 3.39)
        p11 = p11 * inv_lam_n - (k1 * k1 * inv_lam_n) * inv_s
        p12 = p12 * inv_lam_n - (k1 * k2 * inv_lam_n) * inv_s
        p22 = p22 * inv_lam_n - (k2 * k2 * inv_lam_n) * inv_s
        p13 = p13 * inv_lam_n - (k1 * k3 * inv_lam_n) * inv_s
        p23 = p23 * inv_lam_n - (k2 * k3 * inv_lam_n) * inv_s
        p33 = p33 * inv_lam_n - (k3 * k3 * inv_lam_n) * inv_s
        # θ̂_LS(n) = θ̂_LS(n−1) + P(n) φ(n) l(n), P(n) φ(n) = k / s
        gain_l = l_n * inv_s
        th_b1 = th_b1 + k1 * gain_l
        th_b0 = th_b0 + k2 * gain_l
        th_c = th_c + k3 * gain_l
        s_w = lam_n * s_w + 1.0
        n += 1.0
        # d = 1 + θ̂_C(n−1)ᵀ Λ θ̂_LS(n), Λ = diag(1, 1, 0)                      (eq. 3.33)
        den = 1.0 + c_b1 * th_b1 + c_b0 * th_b0
        if den > MIN_BIAS_DENOMINATOR:
            r = jn / den
            sigma2 = r / s_w
            # θ̂_C(n) = θ̂_LS(n) + (σ̂²(n)/w_n) P(n) Λ θ̂_C(n−1): Λθ̂_C = [c_b1, c_b0, 0]
            new_b1 = th_b1 + r * (p11 * c_b1 + p12 * c_b0)
            new_b0 = th_b0 + r * (p12 * c_b1 + p22 * c_b0)
            c_c = th_c + r * (p13 * c_b1 + p23 * c_b0)
            c_b1 = new_b1
            c_b0 = new_b0
        else:
            sigma2 = nan
            c_b1 = th_b1
            c_b0 = th_b0
            c_c = th_c
        prev2 = -p_3
        p_3 = p_2
        p_2 = p_1
        p_1 = p_n
        if until_keep == 0:
            if bias_compensation:
                out_b1[k] = c_b1
                out_b0[k] = c_b0
                out_c[k] = c_c
            else:
                out_b1[k] = th_b1
                out_b0[k] = th_b0
                out_c[k] = th_c
            out_sigma2[k] = sigma2
            _edge_covariance_3(
                p11, p12, p22, p13, p23, p33, phi1, phi2, phi2, prev2, out_b1[k], out_b0[k], out_c[k], sigma2, lam,
                drive_w, out_cov, k,
            )
            k += 1
            until_keep = keep_every - 1
        else:
            until_keep -= 1

    state[_TH_LS_B1] = th_b1
    state[_TH_LS_B0] = th_b0
    state[_TH_LS_C] = th_c
    state[_TH_C_B1] = c_b1
    state[_TH_C_B0] = c_b0
    state[_TH_C_C] = c_c
    state[_P11] = p11
    state[_P12] = p12
    state[_P22] = p22
    state[_P13] = p13
    state[_P23] = p23
    state[_P33] = p33
    state[_J] = jn
    state[_N] = n
    state[_S] = s_w
    state[_P_1] = p_1
    state[_P_2] = p_2
    state[_P_3] = p_3
    state[_G_1] = g_1
    state[_G_2] = g_2
    state[_N_PAST] = n_past


def _check_lam_p0(lam: float, p0: float) -> None:
    if not (isinstance(lam, (int, float, np.floating)) and 0.0 < lam <= 1.0):
        raise ConfigError(f"lam={lam!r} must be a forgetting factor in (0, 1]")
    if not (isinstance(p0, (int, float, np.floating)) and math.isfinite(p0) and p0 > 0.0):
        raise ConfigError(f"p0={p0!r} must be a finite number > 0")


@dataclass(frozen=True)
class ReepState:
    """Everything REEP carries from one sample to the next.

    Immutable: :func:`reep_update` returns a new state.  Build the first one
    with :meth:`initial`.  Fields are plain floats so that a state compares,
    hashes and pickles exactly.

    Attributes
    ----------
    lam, p0 : float
        Forgetting factor λ and prior P(0) = P0·I, fixed for the whole stream.
    theta_ls, theta_c : tuple of float
        θ̂_LS(n) and θ̂_C(n) as (b1, b0).
    p_matrix : tuple of float
        (P11, P12, P22) of the symmetric P(n) = [[P11, P12], [P12, P22]].
    cost : float
        J(n) of eq. 3.38, deflection units².
    n_samples : int
        n, regression updates so far (samples seen minus the first two).
    inv_weight : float
        1/w_n = (1 − λⁿ)/(1 − λ).
    p_past : tuple of float
        (p(n−1), p(n−2), p(n−3)).
    g_past : tuple of float
        (g(n−1), g(n−2)).
    n_past : int
        How many of those past samples are real (0, 1 or 2): the first two
        samples of a stream only fill them.
    static_offset : bool
        Whether θ carries the constant term c of a static deflection offset
        (θ = [b1, b0, c], see :func:`reep_update`); fixed for the stream.
    offset_ls, offset_c : float
        c of θ̂_LS(n) and θ̂_C(n), deflection units (0 without static_offset).
    p_offset : tuple of float
        (P13, P23, P33), the third row of the 3 × 3 P(n) (zeros without static_offset).
    """

    lam: float
    p0: float
    theta_ls: tuple[float, float]
    theta_c: tuple[float, float]
    p_matrix: tuple[float, float, float]
    cost: float
    n_samples: int
    inv_weight: float
    p_past: tuple[float, float, float]
    g_past: tuple[float, float]
    n_past: int
    static_offset: bool = False
    offset_ls: float = 0.0
    offset_c: float = 0.0
    p_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def initial(
        cls, *, lam: float = DEFAULT_FORGETTING_FACTOR, p0: float = DEFAULT_P0, static_offset: bool = False
    ) -> ReepState:
        """The state before the first sample (§3.3.3).

        θ̂_LS(0) = θ̂_C(0) = 0, P(0) = P0·I, J(0) = 0, and zero past samples.

        Parameters
        ----------
        lam : float, optional
            Forgetting factor λ in (0, 1]; 0.995 (thesis) is a memory of
            1/(1 − λ) = 200 samples, 0.4 ms at 500 kHz.  λ = 1 is ordinary
            growing-window least squares.
        p0 : float, optional
            Prior P0.  It must be large against the steady-state P, about
            (1 − λ)/mean(p²): 1e6 (thesis) suits deflection in nm.  P is
            never allowed to grow past trace P(0) (anti-windup), so a P0 that
            is too small pins the estimate near 0 rather than failing silently.
        static_offset : bool, optional
            Add the constant regressor of a static deflection offset,
            θ = [b1, b0, c] with Λ = diag(1, 1, 0) (:func:`reep_update`,
            Notes).  False (default) is eq. 3.39 with θ = [b1, b0] as in the
            thesis.

        Raises
        ------
        ConfigError
            If λ or P0 is out of range.
        """
        _check_lam_p0(lam, p0)
        return cls(
            lam=float(lam),
            p0=float(p0),
            theta_ls=(0.0, 0.0),
            theta_c=(0.0, 0.0),
            p_matrix=(float(p0), 0.0, float(p0)),
            cost=0.0,
            n_samples=0,
            inv_weight=0.0,
            p_past=(0.0, 0.0, 0.0),
            g_past=(0.0, 0.0),
            n_past=0,
            static_offset=bool(static_offset),
            p_offset=(0.0, 0.0, float(p0) if static_offset else 0.0),
        )

    def _to_array(self) -> np.ndarray:
        out = np.empty(_STATE_LEN, dtype=np.float64)
        out[_TH_LS_B1], out[_TH_LS_B0] = self.theta_ls
        out[_TH_C_B1], out[_TH_C_B0] = self.theta_c
        out[_P11], out[_P12], out[_P22] = self.p_matrix
        out[_J] = self.cost
        out[_N] = self.n_samples
        out[_S] = self.inv_weight
        out[_P_1], out[_P_2], out[_P_3] = self.p_past
        out[_G_1], out[_G_2] = self.g_past
        out[_N_PAST] = self.n_past
        out[_TH_LS_C] = self.offset_ls
        out[_TH_C_C] = self.offset_c
        out[_P13], out[_P23], out[_P33] = self.p_offset
        return out

    def _from_array(self, a: np.ndarray) -> ReepState:
        v = a.tolist()
        return ReepState(
            lam=self.lam,
            p0=self.p0,
            theta_ls=(v[_TH_LS_B1], v[_TH_LS_B0]),
            theta_c=(v[_TH_C_B1], v[_TH_C_B0]),
            p_matrix=(v[_P11], v[_P12], v[_P22]),
            cost=v[_J],
            n_samples=int(v[_N]),
            inv_weight=v[_S],
            p_past=(v[_P_1], v[_P_2], v[_P_3]),
            g_past=(v[_G_1], v[_G_2]),
            n_past=int(v[_N_PAST]),
            static_offset=self.static_offset,
            offset_ls=v[_TH_LS_C],
            offset_c=v[_TH_C_C],
            p_offset=(v[_P13], v[_P23], v[_P33]),
        )


class ReepBlock(NamedTuple):
    """REEP output for one chunk, one value per kept input sample (all of them by default).

    Attributes
    ----------
    b1, b0 : numpy.ndarray of float64
        θ̂_C(n) (bias compensated) or θ̂_LS(n) (plain EWRLS), dimensionless.
        Convert with :func:`afmtool.models.discretisation.resonance_from_denominator`.
    sigma2 : numpy.ndarray of float64
        σ̂²(n), the measurement-noise variance (deflection units², eq. 3.39);
        NaN where the start-up guard skipped the compensation.
    c : numpy.ndarray of float64 or None
        The constant term c(n) (deflection units) when the state has
        ``static_offset``, else None.  The static offset is
        p̄ = c / (1 + b1 + b0).
    covariance : numpy.ndarray of float64, shape (K, 3), or None
        (var b1, cov(b1, b0), var b0) of the output θ̂ at each kept sample
        (``_edge_covariance_2``); NaN where σ̂² is.
    """

    b1: np.ndarray
    b0: np.ndarray
    sigma2: np.ndarray
    c: np.ndarray | None = None
    covariance: np.ndarray | None = None


class ReepStep(NamedTuple):
    """What :func:`reep_update` returns: this chunk's output and the next state."""

    block: ReepBlock
    state: ReepState


def _reep_inputs(state, deflection, dither, numerator, use_input: bool, keep_every) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """The checked arguments of :func:`reep_update`: p(n), g(n) (empty when output-only) and (a2, a1, a0)."""
    if not isinstance(state, ReepState):
        raise ConfigError(f"state must be a ReepState, got {type(state).__name__}")
    p = as_signal("deflection", deflection)
    if not (isinstance(keep_every, (int, np.integer)) and keep_every >= 1):
        raise ConfigError(f"keep_every={keep_every!r} must be an integer >= 1")
    if not use_input:
        return p, np.empty(0, dtype=np.float64), (0.0, 0.0, 0.0)
    if dither is None or numerator is None:
        raise ConfigError("dither and numerator are required when use_input=True")
    g = as_signal("dither", dither)
    if g.shape != p.shape:
        raise InputError(f"dither has {g.shape[0]} samples but deflection has {p.shape[0]}")
    return p, g, check_numerator(numerator)


def _drive_radians(cycles_per_sample: float) -> float:
    """ω·T of the drive line (rad per sample) from f/fs, checked to lie in [0, π)."""
    if not 0.0 <= cycles_per_sample < 0.5:
        raise ConfigError(f"drive_cycles_per_sample={cycles_per_sample!r} must be in [0, 1/2)")
    return 2.0 * math.pi * float(cycles_per_sample)


def reep_update(state: ReepState, deflection, dither=None, numerator: Sequence[float] | None = None, *,
                bias_compensation: bool = True, use_input: bool = True, keep_every: int = 1,
                drive_cycles_per_sample: float = 0.0) -> ReepStep:
    """Advance REEP over one chunk of samples (§3.3.3, eq. 3.39).

    Parameters
    ----------
    state : ReepState
        State after the previous chunk, or :meth:`ReepState.initial`.
    deflection : array_like, shape (N,)
        Measured deflection p(n), nm (see :meth:`ReepState.initial` on units).
    dither : array_like, shape (N,), optional
        Dither forcing g(n), same units as the numerator expects.  Required
        when ``use_input``; ignored otherwise.
    numerator : sequence of 3 floats, optional
        Fixed free-air numerator (a2, a1, a0) of eq. 3.40, e.g. from
        :func:`identify_arx`.  Required when ``use_input``; ignored otherwise.
    bias_compensation : bool, optional
        Output θ̂_C (True, BCEWRLS) or θ̂_LS (False, plain EWRLS).  Both are
        always computed; this only selects the output.
    use_input : bool, optional
        If False, track the output-only AR(2) model z(n) = p(n).
    keep_every : int, optional
        Output only the samples whose index n in the stream (counted from
        the stream's first sample, across chunks) has
        (n + 1) % keep_every == 0.  Every sample still updates the
        estimate; 1 (default) outputs them all.
    drive_cycles_per_sample : float, optional
        The drive's main line over the sample rate, in [0, 1/2), for the bulk term
        of the covariance (``_edge_covariance_2``); 0 (default) leaves it out.

    Returns
    -------
    ReepStep
        ``(block, state)``: the :class:`ReepBlock` of the kept samples (with the
        covariance of θ̂) and the state to pass with the next chunk.  Chunks of
        any sizes give bit-for-bit the output of one call.

    Raises
    ------
    InputError
        If the arrays are not 1-D or their lengths differ.
    ConfigError
        If ``numerator`` is missing or not three finite numbers.

    Notes
    -----
    With z(n) = p(n) − a2 g(n) − a1 g(n−1) − a0 g(n−2),
    φ(n) = [−p(n−1), −p(n−2)]ᵀ, θ = [b1, b0]ᵀ and w_n = (1 − λ)/(1 − λⁿ),
    eq. 3.39 with Λ = I₂ reads::

        l(n)    = z(n) − φᵀ(n) θ_LS(n−1)
        s(n)    = λ + φᵀ(n) P(n−1) φ(n)
        P(n)    = [P(n−1) − P(n−1)φ(n)φᵀ(n)P(n−1) / s(n)] / λ
        θ_LS(n) = θ_LS(n−1) + P(n) φ(n) l(n)
        J(n)    = λ [J(n−1) + l(n)² / s(n)]
        σ²(n)   = w_n J(n) / (1 + θ_C(n−1)ᵀ θ_LS(n))
        θ_C(n)  = θ_LS(n) + (σ²(n)/w_n) P(n) θ_C(n−1)

    Eq. 3.43 of the thesis is a garbled copy of this and is not used.

    The static-offset variant (``state.static_offset``) and the two guards
    that extend eq. 3.39 are in the module docstring.  A NaN sample makes
    every later output NaN: split records at gaps.
    """
    p, g, (a2, a1, a0) = _reep_inputs(state, deflection, dither, numerator, use_input, keep_every)
    carried = state._to_array()
    n_kept = Decimation(int(keep_every)).count(state.n_samples + state.n_past, p.shape[0])
    b1, b0, sigma2 = (np.empty(n_kept, dtype=np.float64) for _ in range(3))
    covariance = np.empty((n_kept, 3), dtype=np.float64)
    drive_w = _drive_radians(drive_cycles_per_sample)
    signals = (p, g, a2, a1, a0, bool(use_input), state.lam)
    if state.static_offset:  # trace P(0) = 3·P0 for the 3 × 3 P
        c = np.empty(n_kept, dtype=np.float64)
        _reep_offset_kernel(*signals, 3.0 * state.p0, bool(bias_compensation), int(keep_every), drive_w, carried, b1,
                            b0, sigma2, covariance, c)
        return ReepStep(ReepBlock(b1, b0, sigma2, c, covariance), state._from_array(carried))
    _reep_kernel(*signals, 2.0 * state.p0, bool(bias_compensation), int(keep_every), drive_w, carried, b1, b0, sigma2,
                 covariance)
    return ReepStep(ReepBlock(b1, b0, sigma2, None, covariance), state._from_array(carried))


def reep(
    deflection,
    dither=None,
    numerator: Sequence[float] | None = None,
    *,
    lam: float = DEFAULT_FORGETTING_FACTOR,
    p0: float = DEFAULT_P0,
    bias_compensation: bool = True,
    use_input: bool = True,
    static_offset: bool = False,
) -> ReepBlock:
    """REEP over a whole record: :func:`reep_update` from :meth:`ReepState.initial`.

    Parameters are those of :meth:`ReepState.initial` and :func:`reep_update`.

    Returns
    -------
    ReepBlock
        b1(n), b0(n) and σ̂²(n) for every sample.
    """
    state = ReepState.initial(lam=lam, p0=p0, static_offset=static_offset)
    step = reep_update(
        state, deflection, dither, numerator, bias_compensation=bias_compensation, use_input=use_input
    )
    return step.block


# ---------------------------------------------------------------------------
# General eq. 3.39 (matrix P) and the five-parameter free-air ARX
# ---------------------------------------------------------------------------


@njit(**JIT_OPTIONS)
def _bcewrls_kernel(phi, y, lam_diag, lam, trace_cap, out_theta_c, out_theta_ls, out_sigma2):  # noqa: C901 - numba kernel: one scalar recursion
    """Eq. 3.39 for m parameters; row i of ``phi`` is φᵀ(i+1).

    Same guards as ``_reep_kernel``.  P is updated on its upper triangle
    and mirrored, so it stays exactly symmetric.
    """
    n_rows, m = phi.shape
    th_ls = np.zeros(m)
    th_c = np.zeros(m)
    new_c = np.empty(m)
    pmat = np.zeros((m, m))
    k = np.empty(m)
    for a in range(m):
        pmat[a, a] = trace_cap / m
    jn = 0.0
    s_w = 0.0
    for i in range(n_rows):
        trace = 0.0
        for a in range(m):
            trace += pmat[a, a]
        lam_n = lam if trace < trace_cap else 1.0
        # k = P(n−1) φ(n);  s = λ + φᵀ P(n−1) φ;  l = y(n) − φᵀ θ_LS(n−1)
        s = lam_n
        l_n = y[i]
        for a in range(m):
            acc = 0.0
            for b in range(m):
                acc += pmat[a, b] * phi[i, b]
            k[a] = acc
        for a in range(m):
            s += phi[i, a] * k[a]
            l_n -= phi[i, a] * th_ls[a]
        # J(n) = λ [J(n−1) + l² / s]
        jn = lam_n * (jn + l_n * l_n / s)
        # P(n) = [P(n−1) − k kᵀ / s] / λ, upper triangle then mirrored
        for a in range(m):
            for b in range(a, m):
                v = (pmat[a, b] - k[a] * k[b] / s) / lam_n
                pmat[a, b] = v
                pmat[b, a] = v
        # θ_LS(n) = θ_LS(n−1) + P(n) φ(n) l(n), P(n) φ(n) = k / s
        for a in range(m):
            th_ls[a] += k[a] / s * l_n
        # 1/w_n = λ/w_{n−1} + 1
        s_w = lam_n * s_w + 1.0
        # d = 1 + θ_C(n−1)ᵀ Λ θ_LS(n)
        den = 1.0
        for a in range(m):
            den += th_c[a] * lam_diag[a] * th_ls[a]
        if den > MIN_BIAS_DENOMINATOR:
            r = jn / den
            sigma2 = r / s_w
            # θ_C(n) = θ_LS(n) + (σ²/w_n) P(n) Λ θ_C(n−1)
            for a in range(m):
                acc = 0.0
                for b in range(m):
                    acc += pmat[a, b] * (lam_diag[b] * th_c[b])
                new_c[a] = th_ls[a] + r * acc
            for a in range(m):
                th_c[a] = new_c[a]
        else:
            sigma2 = np.nan
            for a in range(m):
                th_c[a] = th_ls[a]
        for a in range(m):
            out_theta_c[i, a] = th_c[a]
            out_theta_ls[i, a] = th_ls[a]
        out_sigma2[i] = sigma2


class BcewrlsResult(NamedTuple):
    """Per-sample output of :func:`bcewrls`.

    Attributes
    ----------
    theta_c, theta_ls : numpy.ndarray, shape (N, m)
        θ̂_C(n) and θ̂_LS(n).
    sigma2 : numpy.ndarray, shape (N,)
        σ̂²(n), NaN where the start-up guard skipped the compensation.
    """

    theta_c: np.ndarray
    theta_ls: np.ndarray
    sigma2: np.ndarray


def bcewrls(
    regressors,
    target,
    bias_mask,
    *,
    lam: float = DEFAULT_FORGETTING_FACTOR,
    p0: float = DEFAULT_P0,
) -> BcewrlsResult:
    """General bias-compensated EWRLS, eq. 3.39, for y(n) = φᵀ(n)θ + e(n).

    Parameters
    ----------
    regressors : array_like, shape (N, m)
        Row n is φᵀ(n).
    target : array_like, shape (N,)
        y(n).
    bias_mask : array_like of bool or 0/1, shape (m,)
        Diagonal of Λ: 1 for the entries of θ whose regressor is a noisy past
        output (−y(n−k)), 0 for noise-free inputs.
    lam, p0 : float, optional
        Forgetting factor in (0, 1] (λ = 1: growing window) and prior P(0) = P0·I.

    Returns
    -------
    BcewrlsResult
        θ̂_C(n), θ̂_LS(n) and σ̂²(n) for every n.

    Notes
    -----
    The same recursion and guards as :func:`reep_update`, with an m×m
    symmetric P.  O(m²) per sample with small arrays: meant for short
    segments (free-air identification), not for streaming.
    """
    _check_lam_p0(lam, p0)
    phi = np.ascontiguousarray(regressors, dtype=np.float64)
    y = as_signal("target", target)
    if phi.ndim != 2 or phi.shape[0] != y.shape[0]:
        raise InputError(f"regressors must have shape (N, m) with N = len(target) = {y.shape[0]}, got {phi.shape}")
    lam_diag = np.ascontiguousarray(bias_mask, dtype=np.float64)
    if lam_diag.shape != (phi.shape[1],) or not np.all((lam_diag == 0) | (lam_diag == 1)):
        raise ConfigError(f"bias_mask={bias_mask!r} must be {phi.shape[1]} values of 0 or 1")
    n_rows, m = phi.shape
    theta_c = np.empty((n_rows, m))
    theta_ls = np.empty((n_rows, m))
    sigma2 = np.empty(n_rows)
    _bcewrls_kernel(phi, y, lam_diag, float(lam), m * float(p0), theta_c, theta_ls, sigma2)
    return BcewrlsResult(theta_c, theta_ls, sigma2)


#: Diagonal of Λ over [b1, b0, a2, a1, a0]: only the AR entries see output noise.
_ARX_BIAS_MASK = np.array([1.0, 1.0, 0.0, 0.0, 0.0])
_ARX_NAMES = ("b1", "b0", "a2", "a1", "a0")


def arx_regressors(deflection, dither) -> tuple[np.ndarray, np.ndarray]:
    """Regressor matrix and target of the five-parameter ARX of eq. 3.40.

    Parameters
    ----------
    deflection, dither : array_like, shape (N,)
        p(n) and g(n), N ≥ 3.

    Returns
    -------
    phi : numpy.ndarray, shape (N − 2, 5)
        Rows φᵀ(n) = [−p(n−1), −p(n−2), g(n), g(n−1), g(n−2)] for n = 2 … N−1,
        so that θ = [b1, b0, a2, a1, a0].
    y : numpy.ndarray, shape (N − 2,)
        p(n) for the same n.
    """
    p = as_signal("deflection", deflection)
    g = as_signal("dither", dither)
    if g.shape != p.shape:
        raise InputError(f"dither has {g.shape[0]} samples but deflection has {p.shape[0]}")
    if p.shape[0] < 3:
        raise InputError(f"need at least 3 samples, got {p.shape[0]}")
    phi = np.column_stack((-p[1:-1], -p[:-2], g[2:], g[1:-1], g[:-2]))
    return phi, p[2:].copy()


@dataclass(frozen=True, eq=False)
class ArxFit:
    """Free-air ARX model of eq. 3.40, from :func:`identify_arx`.

    Attributes
    ----------
    b1, b0 : float
        Denominator (AR) coefficients.
    a2, a1, a0 : float
        Numerator coefficients multiplying g(n), g(n−1), g(n−2) — the fixed
        numerator of REEP.
    sigma2 : float
        Estimated measurement-noise variance σ̂², deflection units².
    covariance : numpy.ndarray, shape (5, 5), read-only
        Asymptotic covariance of [b1, b0, a2, a1, a0] (see :func:`identify_arx`).
    method : str
        ``"bcls"``, ``"ls"`` or ``"bcewrls"``.
    n_samples : int
        Regression rows used (input length − 2).
    n_iter : int
        Bias-compensation iterations (0 for ``"ls"`` and ``"bcewrls"``).
    """

    b1: float
    b0: float
    a2: float
    a1: float
    a0: float
    sigma2: float
    covariance: np.ndarray
    method: str
    n_samples: int
    n_iter: int

    @property
    def theta(self) -> np.ndarray:
        """[b1, b0, a2, a1, a0]."""
        return np.array([self.b1, self.b0, self.a2, self.a1, self.a0])

    @property
    def numerator(self) -> tuple[float, float, float]:
        """(a2, a1, a0), as :func:`reep_update` takes it."""
        return (self.a2, self.a1, self.a0)

    @property
    def denominator(self) -> tuple[float, float]:
        """(b1, b0)."""
        return (self.b1, self.b0)

    @property
    def stderr(self) -> dict[str, float]:
        """Standard error of each coefficient, by name."""
        return dict(zip(_ARX_NAMES, np.sqrt(np.diag(self.covariance)).tolist(), strict=True))


def _noise_pair_covariance(b1: float, b0: float) -> np.ndarray:
    """K of :func:`_arx_covariance`: long-run covariance / (Nσ⁴) of X_i = Σ_n ϑ(n−i)e(n), i = 1, 2.

    With e(n) = Σ_m c_m ϑ(n−m), c = (1, b1, b0), X_i = Σ_m c_m C_|m−i| where
    C_d = Σ_n ϑ(n)ϑ(n+d).  For white Gaussian ϑ the C_d are uncorrelated,
    Var C_0 = 2Nσ⁴ and Var C_d = Nσ⁴ (d ≥ 1).
    """
    c = (1.0, b1, b0)
    k = np.zeros((2, 2))
    for i in (1, 2):
        for j in (1, 2):
            for m in range(3):
                for mm in range(3):
                    d = abs(m - i)
                    if d == abs(mm - j):
                        k[i - 1, j - 1] += c[m] * c[mm] * (2.0 if d == 0 else 1.0)
    return k


@njit(**JIT_OPTIONS)
def _arx_output_kernel(g, a2, a1, a0, b1, b0, out, first, second):
    """ARX model output (eq. 3.40 without noise) from ŝ(0) = ``first``, ŝ(1) = ``second``.

    ŝ(n) = −b1 ŝ(n−1) − b0 ŝ(n−2) + a2 g(n) + a1 g(n−1) + a0 g(n−2): what
    ``lfilter`` with ``lfiltic`` gives, without importing scipy.signal
    (the largest part of REEP's start-up) for this one short run.
    """
    out[0] = first
    out[1] = second
    for n in range(2, g.shape[0]):
        out[n] = -b1 * out[n - 1] - b0 * out[n - 2] + a2 * g[n] + a1 * g[n - 1] + a0 * g[n - 2]


def _arx_covariance(p, g, theta, sigma2, m_inv):
    """Asymptotic covariance of an ARX fit of :func:`identify_arx`.

    θ̂ solves (1/N)Σφ(n)(y(n) − φᵀ(n)θ) + σ²Λθ = 0, so
    θ̂ − θ ≈ M⁻¹(1/N)Σh(n) with M = R − σ̂²Λ (M = R for ``"ls"``) and
    h(n) = φ(n)e(n) + σ²Λθ.  Split φ = φ_s + φ_ϑ into the noise-free part
    (model output ŝ and dither) and the noise ϑ in −p(n−1), −p(n−2):

    * Σφ_s(n)e(n) = Σϑ(n)ψ(n), ψ(n) = φ_s(n) + b1 φ_s(n+1) + b0 φ_s(n+2),
      with covariance σ²Σψψᵀ;
    * the AR block of Σφ_ϑ(n)e(n) + Nσ²Λθ is quadratic in ϑ, with
      covariance Nσ⁴K (white Gaussian ϑ; ``_noise_pair_covariance``);
    * the two are uncorrelated (odd moments vanish).

    Hence Cov θ̂ ≈ M⁻¹(σ²ΨᵀΨ/N + σ⁴K)M⁻¹/N, with ŝ simulated from the fitted
    model.  The σ⁴ term matters: near resonance the filtered signal ψ is
    small (the denominator nearly cancels the oscillation), so the
    ordinary sandwich estimate with truncated lags is not even positive.
    The uncertainty of σ̂² is neglected.  Checked against Monte Carlo in
    ``tests/test_rls.py`` (ratio 0.9–1.1).
    """
    b1, b0, a2, a1, a0 = (float(v) for v in theta)
    # noise-free model output ŝ(n), started from the measured p(0), p(1)
    s_hat = np.empty_like(p)
    _arx_output_kernel(g, a2, a1, a0, b1, b0, s_hat, p[0], p[1])
    phi_s = np.column_stack((-s_hat[1:-1], -s_hat[:-2], g[2:], g[1:-1], g[:-2]))
    n_rows = phi_s.shape[0]
    # ψ(n) = φ_s(n) + b1 φ_s(n+1) + b0 φ_s(n+2): Σ_n φ_s(n)e(n) = Σ_n ϑ(n)ψ(n)
    psi = phi_s[:-2] + b1 * phi_s[1:-1] + b0 * phi_s[2:]
    s_mat = sigma2 * (psi.T @ psi) / n_rows
    s_mat[:2, :2] += sigma2 * sigma2 * _noise_pair_covariance(b1, b0)
    cov = m_inv @ s_mat @ m_inv.T / n_rows
    return 0.5 * (cov + cov.T)


def identify_arx(deflection, dither, *, method: Literal["bcls", "ls", "bcewrls"] = "bcls", rtol: float = 1e-12,
                 max_iter: int = 100) -> ArxFit:
    """Identify the free-air ARX model (b1, b0, a2, a1, a0) without noise bias.

    Parameters
    ----------
    deflection : array_like, shape (N,)
        Free-air (off-sample) deflection p(n), nm.
    dither : array_like, shape (N,)
        Dither forcing g(n), nm of equivalent forcing.
    method : {"bcls", "ls", "bcewrls"}, optional
        ``"bcls"`` (default): batch bias-compensated least squares (Notes).
        ``"ls"``: plain least squares, biased by the noise (for comparison).
        ``"bcewrls"``: last sample of the recursive eq. 3.39 with λ = 1.
    rtol : float, optional
        ``"bcls"`` stops when the step of θ̂_C is below ``rtol``·|θ̂_C|.
    max_iter : int, optional
        ``"bcls"`` iteration limit.

    Returns
    -------
    ArxFit
        The coefficients, σ̂² and their covariance.

    Raises
    ------
    InputError
        If the arrays are not 1-D of equal length ≥ 8, or are not finite.
    ConfigError
        For an unknown ``method``, bad ``rtol``/``max_iter``, or if ``"bcls"``
        does not converge (σ̂²R⁻¹Λ has spectral radius ≥ 1: noise too large
        for the excitation).

    Notes
    -----
    ``"bcls"`` iterates the batch form of eq. 3.39 with λ = 1 (eqs. 3.18,
    3.32, 3.33) to its fixed point (R − σ̂²Λ)θ̂_C = r, the bias-eliminated
    normal equations, with R = ΦᵀΦ/N and r = Φᵀy/N over the N regression
    rows; the derivation is in ``_bcls_fixed_point``, R⁻¹ is applied through
    a QR factorisation of Φ (``_arx_normal_solver``).
    The covariance of the coefficients is derived in ``_arx_covariance``
    (checked against Monte Carlo in ``tests/test_rls.py``).
    """
    if method not in ("bcls", "ls", "bcewrls"):
        raise ConfigError(f"method={method!r} must be 'bcls', 'ls' or 'bcewrls'")
    if not (isinstance(rtol, (int, float)) and rtol > 0):
        raise ConfigError(f"rtol={rtol!r} must be > 0")
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise ConfigError(f"max_iter={max_iter!r} must be an integer >= 1")
    check_resolvable("deflection", as_signal("deflection", deflection), "the free-air ARX regression")
    check_resolvable("dither", as_signal("dither", dither), "the free-air ARX regression")
    phi, y = arx_regressors(deflection, dither)
    r_inv = _arx_normal_solver(phi, y)
    lam_diag = _ARX_BIAS_MASK
    n_rows = y.shape[0]
    r_vec = phi.T @ y / n_rows
    # θ̂_LS = R⁻¹ r
    theta_ls = r_inv(r_vec)
    resid = y - phi @ theta_ls
    # J/N, mean squared LS residual                                         (eq. 3.31)
    j_mean = float(resid @ resid) / n_rows
    if method == "ls":
        # σ̂² from eq. 3.32 with the LS estimate in place of θ; M = R
        theta, sigma2, m_eff, n_iter = theta_ls, j_mean / (1.0 + theta_ls @ (lam_diag * theta_ls)), 0.0, 0
    elif method == "bcewrls":
        rec = bcewrls(phi, y, lam_diag, lam=1.0)
        theta, sigma2, n_iter = rec.theta_c[-1].copy(), float(rec.sigma2[-1]), 0
        m_eff = sigma2
    else:
        theta, sigma2, n_iter = _bcls_fixed_point(r_inv, theta_ls, j_mean, rtol, max_iter)
        m_eff = sigma2
    # M⁻¹ = (R − σ̂²Λ)⁻¹ = (I − σ̂²R⁻¹Λ)⁻¹R⁻¹; the first factor is near I
    r_inv_full = r_inv(np.eye(lam_diag.shape[0]))
    m_inv = np.linalg.solve(np.eye(lam_diag.shape[0]) - m_eff * (r_inv_full * lam_diag[None, :]), r_inv_full)
    cov = _arx_covariance(as_signal("deflection", deflection), as_signal("dither", dither), theta, float(sigma2), m_inv)
    cov.setflags(write=False)
    b1, b0, a2, a1, a0 = (float(v) for v in theta)
    return ArxFit(b1, b0, a2, a1, a0, float(sigma2), cov, method, n_rows, n_iter)


def _arx_normal_solver(phi: np.ndarray, y: np.ndarray):
    """v ↦ R⁻¹v for R = ΦᵀΦ/N, through the QR factorisation of Φ (never forming ΦᵀΦ).

    Raises InputError for too few, non-finite or rank-deficient regressors.
    """
    n_rows = y.shape[0]
    if n_rows < 6:
        raise InputError(f"need at least 8 samples to identify 5 coefficients, got {n_rows + 2}")
    if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(y))):
        raise InputError("deflection and dither must be finite for identify_arx")
    # Φ = Q U (economic QR), so R = ΦᵀΦ/N = UᵀU/N and R⁻¹ v = N·U⁻¹U⁻ᵀ v.
    upper = np.linalg.qr(phi, mode="r")
    if np.min(np.abs(np.diag(upper))) <= np.max(np.abs(np.diag(upper))) * 1e-13:
        raise InputError(
            f"the regressors are rank deficient (deflection RMS {channel_rms(y):.3g}, dither RMS {channel_rms(phi[:, 2]):.3g}): "
            "the dither must hold at least three sines, on a scale the deflection's can be compared with (check the units)"
        )

    def r_inv(v: np.ndarray) -> np.ndarray:
        # U is 5 × 5: a general solve costs nothing here, and numpy spares the scipy.linalg import
        w = np.linalg.solve(upper.T, v)
        return n_rows * np.linalg.solve(upper, w)

    return r_inv


def _bcls_fixed_point(r_inv, theta_ls: np.ndarray, j_mean: float, rtol: float, max_iter: int) -> tuple[np.ndarray, float, int]:
    """The bias-compensation fixed point of :func:`identify_arx`: (θ̂_C, σ̂², iterations).

    Batch form, derived from eqs. 3.18 and 3.32 with λ = 1 (w_n = 1/N).
    With R = ΦᵀΦ/N, r = Φᵀy/N over the N regression rows,
    θ̂_LS = R⁻¹r and, since E[φ(n)e(n)] = −σ²Λθ (eq. 3.15),

    .. math:: \\hat\\theta_{LS} \\to \\theta - \\sigma^2 R^{-1}\\Lambda\\theta
              \\quad\\Longrightarrow\\quad
              \\theta = \\hat\\theta_{LS} + \\sigma^2 R^{-1}\\Lambda\\theta .

    The mean squared LS residual J/N tends to σ²(1 + θᵀΛθ̂_LS) (eq. 3.31),
    so with the current estimate in place of θ (as eq. 3.33 does),

    .. math:: \\hat\\sigma^2_k = \\frac{J/N}{1 + \\hat\\theta_{C,k}^T\\Lambda\\hat\\theta_{LS}},\\qquad
              \\hat\\theta_{C,k+1} = \\hat\\theta_{LS} + \\hat\\sigma^2_k R^{-1}\\Lambda\\hat\\theta_{C,k},

    from θ̂_C,0 = θ̂_LS.  This is a fixed-point iteration; it converges when
    σ²R⁻¹Λ has spectral radius < 1 (7e-5 for the 25 nm three-sine test
    record at 0.05 nm noise, so four iterations reach 1e-12).  At the fixed point
    (R − σ̂²Λ)θ̂_C = r, the bias-eliminated normal equations.  J uses N, not
    N − 5, following the derivation; the difference is O(5/N).
    """
    lam_diag = _ARX_BIAS_MASK
    # R⁻¹Λ, applied to θ̂_C at every iteration
    r_inv_lam = np.column_stack([r_inv(col) for col in np.diag(lam_diag)])
    theta = theta_ls.copy()
    sigma2 = float("nan")
    for n_iter in range(1, max_iter + 1):
        # σ̂²_k = (J/N) / (1 + θ̂_C,kᵀ Λ θ̂_LS)
        den = 1.0 + theta @ (lam_diag * theta_ls)
        if not den > MIN_BIAS_DENOMINATOR:
            raise ConfigError("bias-compensated ARX fit diverged (1 + θ_Cᵀ Λ θ_LS ≤ 1/2)")
        sigma2 = j_mean / den
        # θ̂_C,k+1 = θ̂_LS + σ̂²_k R⁻¹ Λ θ̂_C,k
        new = theta_ls + sigma2 * (r_inv_lam @ theta)
        step = float(np.max(np.abs(new - theta)))
        theta = new
        if step <= rtol * float(np.max(np.abs(theta))):
            return theta, sigma2, n_iter
    raise ConfigError(
        f"bias-compensated ARX fit did not converge in max_iter={max_iter} iterations "
        f"(σ̂² = {sigma2:.3g}): the noise is too large for the excitation"
    )
