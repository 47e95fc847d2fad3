"""Observer-design trade-offs of thesis chapter 5: A_e², its sensitivities, SNR and transients.

Model (eqs. 5.1, 5.2, 5.13)
---------------------------
The equivalent cantilever and the observer are continuous second-order
systems in the canonical form of eq. 5.1 (C = [0, 1], so the output is the
second state)::

    plant     ẋ = A x + B (g + η),           y = C x + ν
    observer  x̂' = A_k x̂ + B g + L (y − C x̂)
    error     e1 = C (x − x̂)

with A = [[0, −ωe²], [1, −ωe/Qe]], A_k = [[0, −ωk²], [1, −ωk/Qk]],
B = [c0, c1]ᵀ and L = [L1, L2]ᵀ.  The numerator (c1, c0) is the same for
the plant and the observer (eq. 5.13; docs/conventions.md: a linearised tip-sample
force changes only the denominator), and the thermal force η enters where
the dither does (B1 = B, eq. 3.50).  Three polynomials appear throughout:

* plant     P(s) = s² + (ωe/Qe) s + ωe²,
* model     M(s) = s² + (ωk/Qk) s + ωk²,
* error     E(s) = s² + (ωk/Qk + L2) s + (ωk² + L1)   (the poles of A_k − LC),

and the transfer functions of eqs. 5.11-5.12, 5.8 reduce to

.. math::

    \\frac{e_1}{g} = \\frac{(c_0 + c_1 s)\\,(M(s) - P(s))}{P(s)\\,E(s)},\\qquad
    \\frac{e_1}{\\eta} = \\frac{(c_0 + c_1 s)\\,M(s)}{P(s)\\,E(s)},\\qquad
    \\frac{e_1}{\\nu} = -\\frac{L_1 + L_2 s}{E(s)}.

Units: ω in rad/s, the dither g and η in dither units, y, ν and e1 in
deflection units (c0 in deflection units per dither unit · s⁻², c1 per
s⁻¹; for the free-air model of eq. 2.6, c0 = gain·ω0², c1 = 0).

What is computed
----------------
* :func:`decay_gain` — L that keeps the model's damped frequency and sets
  the error envelope's time constant to a number of drive periods (the
  continuous twin of :func:`afmtool.estimators.observer.gain_for_decay`).
* :func:`mismatch_amplitude` — A_e² = P1·P2 of eq. 5.17 for a drive
  g = A0 sin ωt, and its partial derivatives in ωe and Qe (eqs. 5.18,
  5.19; eq. 5.16 combines them along a direction).
* :func:`noise_terms` — S_g, S_η, N_η, N_ν and the two SNRs of eq. 5.20,
  plus the exact variances σ²_ηe and σ²_νe.
* :func:`transient_response` — the initial-state response of eq. 5.22:
  the peak of its mismatch term and the time for the whole error to settle.

Thesis doubts (each checked numerically in ``tests/test_observer_theory.py``)
---------------------------------------------------------------------------
* Eq. 5.14 writes the error polynomial's constant term as ωk² + L; with the
  gains of eq. 5.2 it is ωk² + L1 (eq. 5.17 has it right).
* Eq. 5.15 adds the RMS values of uncorrelated components; their variances
  add: RMS(e1) = (A_e²/2 + σ²_ηe + σ²_νe)^{1/2}.
* Eq. 5.20 integrates |H(jω)|² over 0 ≤ ω < ∞ against the noise variance
  without the 1/π: for white noise of two-sided intensity q (one-sided PSD
  S = 2q), the output variance is (q/π)∫₀^∞|H(jω)|²dω = (S/2π)∫₀^∞|H(jω)|²dω.
  Here σ_η² and σ_ν² of eq. 5.20 are read as two-sided intensities and
  the 1/π is applied.
* Eq. 5.20 splits σ²_ηe into a "signal" S_η (the mismatch path
  T.F.1 × T.F.6) and a "noise" N_η (T.F.3).  The two paths are driven by the
  same η, so σ²_ηe = S_η + N_η + X_η with a cross term
  X_η = (S/π)∫₀^∞ Re{H3 H16*} dω that eq. 5.20 drops.  S_η and N_η follow
  eq. 5.20; X_η is returned so the three add to the exact variance.
* In eq. 5.20's S_η the numerator is written with c0, c1 (the dither
  path), consistent with B1 = B of eq. 3.50.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "K_BOLTZMANN",
    "ObserverGain",
    "decay_gain",
    "MismatchAmplitude",
    "mismatch_amplitude",
    "directional_sensitivity",
    "thermal_psd",
    "NoiseTerms",
    "noise_terms",
    "Transient",
    "transient_response",
]

#: Boltzmann constant, J/K.
K_BOLTZMANN = 1.380649e-23


def _finite_positive(name: str, value) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr) & (arr > 0)):
        raise ConfigError(f"{name}={value!r} must be finite and > 0")
    return arr


def _check_q(name: str, value) -> np.ndarray:
    arr = _finite_positive(name, value)
    if not np.all(arr > 0.5):
        raise ConfigError(f"{name}={value!r} must be > 0.5 (an under-damped mode)")
    return arr


# ---------------------------------------------------------------------------
# Gains
# ---------------------------------------------------------------------------


class ObserverGain(NamedTuple):
    """Gains L = [L1, L2]ᵀ of eq. 5.2 (arrays of the broadcast shape).

    Attributes
    ----------
    l1 : numpy.ndarray
        L1, s⁻² (adds to ωk² in E(s)).
    l2 : numpy.ndarray
        L2, s⁻¹ (adds to ωk/Qk in E(s)).
    """

    l1: np.ndarray
    l2: np.ndarray


def decay_gain(omega_k, q_k, cycles, drive_frequency_hz: float, residual: float = math.exp(-1.0)) -> ObserverGain:
    """L that makes the matched error envelope fall by ``residual`` in ``cycles`` drive periods.

    Parameters
    ----------
    omega_k : float or array_like
        Observer model ωk, rad/s.
    q_k : float or array_like
        Observer model Qk > 1/2.
    cycles : float or array_like
        N > 0, drive periods for the envelope to fall by ``residual``.
    drive_frequency_hz : float
        Drive frequency f, Hz (one period is 1/f).
    residual : float, optional
        Envelope factor after N periods, in (0, 1); 1/e (default) makes N
        the time constant.

    Returns
    -------
    ObserverGain
        L1 = σ² − (ωk/2Qk)², L2 = 2σ − ωk/Qk with σ = −ln(residual)·f/N.

    Notes
    -----
    The model's poles −ωk/(2Qk) ± jω_d, ω_d = ωk√(1 − 1/(4Qk²)), are moved
    parallel to the real axis to −σ ± jω_d: E(s) = s² + 2σs + σ² + ω_d².
    Matching E(s) = s² + (ωk/Qk + L2)s + ωk² + L1 gives the closed form.
    Sampled at T, the poles map to e^{−σT}e^{±jω_d T}: the radial move of
    :func:`afmtool.estimators.observer.gain_for_decay` with r = e^{−σT}.
    """
    omega_k = _finite_positive("omega_k", omega_k)
    q_k = _check_q("q_k", q_k)
    n_cycles = _finite_positive("cycles", cycles)
    f = float(_finite_positive("drive_frequency_hz", drive_frequency_hz))
    if not 0.0 < residual < 1.0:
        raise ConfigError(f"residual={residual!r} must be in (0, 1)")
    # σ: e^{−σ N/f} = residual
    sigma = -math.log(residual) * f / n_cycles
    half = omega_k / (2.0 * q_k)
    return ObserverGain(sigma * sigma - half * half, 2.0 * sigma - 2.0 * half)


# ---------------------------------------------------------------------------
# A_e² and its sensitivities (eqs. 5.14-5.19)
# ---------------------------------------------------------------------------


class MismatchAmplitude(NamedTuple):
    """A_e² of eq. 5.17 and its partial derivatives (eqs. 5.18, 5.19).

    Attributes
    ----------
    ae2 : numpy.ndarray
        A_e², the squared amplitude of e1 at the drive, deflection units².
    dae2_domega_e : numpy.ndarray
        ∂A_e²/∂ωe, deflection units² per rad/s (× 2π for per Hz).
    dae2_dq_e : numpy.ndarray
        ∂A_e²/∂Qe, deflection units².
    """

    ae2: np.ndarray
    dae2_domega_e: np.ndarray
    dae2_dq_e: np.ndarray


def _check_error_poly(omega_k, q_k, gain: ObserverGain) -> tuple[np.ndarray, np.ndarray]:
    e1 = omega_k / q_k + gain.l2
    e0 = omega_k * omega_k + gain.l1
    if not np.all((e1 > 0) & (e0 > 0)):
        raise ConfigError("the gains make A_k − LC unstable (E(s) = s² + e1 s + e0 needs e1 > 0 and e0 > 0)")
    return e1, e0


def mismatch_amplitude(
    omega_e,
    q_e,
    omega_k,
    q_k,
    gain: ObserverGain,
    *,
    omega: float,
    drive_amplitude: float,
    numerator: tuple[float, float],
) -> MismatchAmplitude:
    """A_e² for g = A0 sin ωt and its sensitivities to the plant's ωe and Qe.

    Parameters
    ----------
    omega_e, q_e : float or array_like
        Equivalent plant ωe (rad/s) and Qe (eq. 5.13).
    omega_k, q_k : float or array_like
        Observer model ωk (rad/s) and Qk.
    gain : ObserverGain
        L1 (s⁻²), L2 (s⁻¹), e.g. :func:`decay_gain`.
    omega : float
        Drive ω, rad/s.
    drive_amplitude : float
        A0, dither units.
    numerator : (c1, c0)
        Fixed numerator of eq. 5.13: c1 (deflection units per dither unit
        · s⁻¹) and c0 (· s⁻²).

    Returns
    -------
    MismatchAmplitude
        Arrays of the broadcast shape of the model arguments.

    Raises
    ------
    ConfigError
        If a model is not an under-damped mode or the error dynamics are
        unstable.

    Notes
    -----
    Eq. 5.17::

        A_e² = P1 · P2
        P1 = (c0² + ω²c1²) A0² / [(ωk² + L1 − ω²)² + ω²(ωk/Qk + L2)²]
        P2 = [(ωk² − ωe²)² + ω²(ωk/Qk − ωe/Qe)²] / D
        D  = (ωe² − ω²)² + ω²ωe²/Qe²

    and ∂A_e²/∂ωe = P1 ∂P2/∂ωe, ∂A_e²/∂Qe = P1 ∂P2/∂Qe by the quotient rule
    (eqs. 5.18, 5.19, which are correct as printed).
    """
    omega_e = _finite_positive("omega_e", omega_e)
    q_e = _check_q("q_e", q_e)
    omega_k = _finite_positive("omega_k", omega_k)
    q_k = _check_q("q_k", q_k)
    w = float(_finite_positive("omega", omega))
    a0 = float(np.asarray(drive_amplitude, dtype=np.float64))
    c1, c0 = (float(v) for v in numerator)
    err1, err0 = _check_error_poly(omega_k, q_k, gain)
    w2 = w * w
    # P1 = (c0² + ω²c1²)A0² / |E(jω)|²
    p1 = (c0 * c0 + w2 * c1 * c1) * a0 * a0 / ((err0 - w2) ** 2 + w2 * err1 * err1)
    # N = |M(jω) − P(jω)|² = (ωk² − ωe²)² + ω²(ωk/Qk − ωe/Qe)²
    dk = omega_k * omega_k - omega_e * omega_e
    dd = omega_k / q_k - omega_e / q_e
    num = dk * dk + w2 * dd * dd
    # D = |P(jω)|² = (ωe² − ω²)² + ω²ωe²/Qe²
    de = omega_e * omega_e - w2
    den = de * de + w2 * omega_e * omega_e / (q_e * q_e)
    p2 = num / den
    # ∂N/∂ωe = −4ωe(ωk² − ωe²) − (2ω²/Qe)(ωk/Qk − ωe/Qe);  ∂D/∂ωe = 4ωe(ωe² − ω²) + 2ωeω²/Qe²     (eq. 5.18)
    dnum_dw = -4.0 * omega_e * dk - 2.0 * w2 / q_e * dd
    dden_dw = 4.0 * omega_e * de + 2.0 * omega_e * w2 / (q_e * q_e)
    # ∂N/∂Qe = (2ω²ωe/Qe²)(ωk/Qk − ωe/Qe);  ∂D/∂Qe = −2ω²ωe²/Qe³                               (eq. 5.19)
    dnum_dq = 2.0 * w2 * omega_e / (q_e * q_e) * dd
    dden_dq = -2.0 * w2 * omega_e * omega_e / q_e**3
    dp2_dw = (den * dnum_dw - num * dden_dw) / (den * den)
    dp2_dq = (den * dnum_dq - num * dden_dq) / (den * den)
    return MismatchAmplitude(p1 * p2, p1 * dp2_dw, p1 * dp2_dq)


def directional_sensitivity(amplitude: MismatchAmplitude, d_omega_e, d_q_e) -> np.ndarray:
    """dA_e² = ∂A_e²/∂ωe dωe + ∂A_e²/∂Qe dQe (eq. 5.16), deflection units² per unit step.

    Parameters
    ----------
    amplitude : MismatchAmplitude
        From :func:`mismatch_amplitude`.
    d_omega_e, d_q_e : float or array_like
        The step dωe (rad/s) and dQe, e.g. the force-curve direction per
        unit of its parameter.
    """
    return amplitude.dae2_domega_e * np.asarray(d_omega_e) + amplitude.dae2_dq_e * np.asarray(d_q_e)


# ---------------------------------------------------------------------------
# Noise and SNR (eq. 5.20)
# ---------------------------------------------------------------------------


def thermal_psd(omega0: float, q: float, spring_constant_n_per_m: float, temperature_k: float) -> float:
    """One-sided PSD of the thermal force as a static deflection F/k, nm²/Hz.

    S = 4 k_B T/(k ω0 Q) (m²/Hz, × 1e18 for nm²/Hz): the damping force noise
    4 k_B T c of the mode (c = k/(ω0 Q)) divided by k².  Through
    G(s) = ω0²/(s² + (ω0/Q)s + ω0²) it gives the equipartition variance
    k_B T/k.
    """
    return 4.0 * K_BOLTZMANN * temperature_k / (spring_constant_n_per_m * omega0 * q) * 1e18


class NoiseTerms(NamedTuple):
    """Eq. 5.20 with its 1/π, and the exact noise variances of e1.

    All variances in deflection units²; SNRs dimensionless.

    Attributes
    ----------
    s_g : numpy.ndarray
        A_e²/2, the variance of the drive's part of e1.
    s_eta : numpy.ndarray
        S_η, the variance of η through the mismatch path (T.F.1 × T.F.6).
    n_eta : numpy.ndarray
        N_η, the variance of η through T.F.3 alone.
    x_eta : numpy.ndarray
        X_η = σ²_ηe − S_η − N_η, the cross term eq. 5.20 leaves out.
    n_nu : numpy.ndarray
        N_ν = σ²_νe, the measurement noise's variance through T.F.4.
    snr_eta : numpy.ndarray
        S_g/(N_η + S_η).
    snr_nu : numpy.ndarray
        S_g/N_ν.
    var_eta : numpy.ndarray
        σ²_ηe = S_η + N_η + X_η, exact.
    """

    s_g: np.ndarray
    s_eta: np.ndarray
    n_eta: np.ndarray
    x_eta: np.ndarray
    n_nu: np.ndarray
    snr_eta: np.ndarray
    snr_nu: np.ndarray
    var_eta: np.ndarray


def _h2_squared(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """‖N/D‖²_H2 = (1/2π)∫_{−∞}^{∞} |N(jω)/D(jω)|² dω for batches of strictly proper N/D.

    ``num`` (..., n) and ``den`` (..., n) hold ascending coefficients
    [x0, x1, ..., x_{n−1}] of N and of the monic D = sⁿ + Σ d_i sⁱ.
    Controllable canonical form (A companion, B = e_n, C = num) and the
    Lyapunov equation A P + P Aᵀ + B Bᵀ = 0 give ‖H‖² = C P Cᵀ, solved as
    the Kronecker system (I⊗A + A⊗I) vec P = −vec(BBᵀ) for the whole batch.
    """
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    shape = np.broadcast_shapes(num.shape[:-1], den.shape[:-1])
    n = den.shape[-1]
    num = np.broadcast_to(num, (*shape, n)).reshape(-1, n)
    den = np.broadcast_to(den, (*shape, n)).reshape(-1, n)
    batch = num.shape[0]
    a = np.zeros((batch, n, n))
    a[:, np.arange(n - 1), np.arange(1, n)] = 1.0
    a[:, n - 1, :] = -den
    eye = np.eye(n)
    # I⊗A + A⊗I, row-major vec
    kron = np.einsum("ij,bkl->bikjl", eye, a).reshape(batch, n * n, n * n)
    kron += np.einsum("bij,kl->bikjl", a, eye).reshape(batch, n * n, n * n)
    rhs = np.zeros((batch, n * n))
    rhs[:, n * n - 1] = -1.0  # −vec(B Bᵀ), B = e_n
    p = np.linalg.solve(kron, rhs[..., None])[..., 0].reshape(batch, n, n)
    out = np.einsum("bi,bij,bj->b", num, p, num)
    return out.reshape(shape)


def _poly_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product of ascending-coefficient polynomials along the last axis (batched)."""
    na, nb = a.shape[-1], b.shape[-1]
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    out = np.zeros((*shape, na + nb - 1))
    for i in range(na):
        for j in range(nb):
            out[..., i + j] = out[..., i + j] + a[..., i] * b[..., j]
    return out


def _fourth_order_eta_terms(omega_e, q_e, omega_k, q_k, err1, err0, numerator, eta_psd: float, shape) -> tuple[np.ndarray, np.ndarray]:
    """S_η and σ²_ηe of :func:`noise_terms`: white η through the fourth-order paths, by Lyapunov equation.

    S_η passes C(s)M(s)/(P(s)E(s)) with M(s) = K(s) − P(s) the model mismatch,
    σ²_ηe passes C(s)K(s)/(P(s)E(s)); P, K, E are the plant, model and error
    polynomials (monic, degree 2) and C(s) = c1 s + c0 the drive numerator.
    """
    c1, c0 = numerator
    # Fourth order: scale s = ω_r s̃ so the Lyapunov equation is well conditioned;
    # ‖H‖²_H2 = ω_r ‖H̃‖²_H2 with x̃_i = x_i ω_r^(i − n) for monic D of degree n.
    w_r = np.broadcast_to(omega_k, shape)
    we, qe = np.broadcast_to(omega_e, shape), np.broadcast_to(q_e, shape)
    wk, qk = np.broadcast_to(omega_k, shape), np.broadcast_to(q_k, shape)
    plant = np.stack([we * we, we / qe, np.ones(shape)], axis=-1)
    model = np.stack([wk * wk, wk / qk, np.ones(shape)], axis=-1)
    error = np.stack([err0, err1, np.ones(shape)], axis=-1)
    drive = np.stack([np.full(shape, c0), np.full(shape, c1)], axis=-1)
    den = _poly_mul(plant, error)  # degree 4, monic
    mismatch = model - plant  # (ωk² − ωe²) + (ωk/Qk − ωe/Qe) s
    scale = w_r[..., None] ** (np.arange(4) - 4)
    den_s = den[..., :4] * scale
    num_sig = np.zeros((*shape, 4))
    num_sig[..., :3] = _poly_mul(drive, mismatch[..., :2])
    num_all = _poly_mul(drive, model)  # degree 3
    s_eta = 0.5 * eta_psd * w_r * _h2_squared(num_sig * scale, den_s)
    var_eta = 0.5 * eta_psd * w_r * _h2_squared(num_all * scale, den_s)
    return s_eta, var_eta


def noise_terms(
    omega_e,
    q_e,
    omega_k,
    q_k,
    gain: ObserverGain,
    *,
    amplitude: MismatchAmplitude,
    numerator: tuple[float, float],
    eta_psd: float,
    nu_psd: float,
) -> NoiseTerms:
    """S_η, N_η, N_ν and the SNRs of eq. 5.20 (with its 1/π), for white η and ν.

    Parameters
    ----------
    omega_e, q_e, omega_k, q_k, gain, numerator
        As in :func:`mismatch_amplitude`.
    amplitude : MismatchAmplitude
        The drive's part, from :func:`mismatch_amplitude` at the same models.
    eta_psd : float
        One-sided PSD of η, dither units²/Hz (e.g. :func:`thermal_psd`
        divided by the dither gain²).
    nu_psd : float
        One-sided PSD of ν, deflection units²/Hz.

    Returns
    -------
    NoiseTerms

    Notes
    -----
    With S the one-sided PSD, the variance of white noise through H is
    (S/2π)∫₀^∞|H(jω)|²dω = (S/2)‖H‖²_H2.  The second-order terms have the
    closed form ‖(b1 s + b0)/(s² + a1 s + a0)‖²_H2 = (b1² a0 + b0²)/(2 a0 a1)::

        N_η = (S_η/2)(c1² e0 + c0²)/(2 e0 e1)
        N_ν = (S_ν/2)(L2² e0 + L1²)/(2 e0 e1)          E(s) = s² + e1 s + e0

    and the fourth-order ones (S_η; σ²_ηe with M(s) in the numerator) are
    solved by a Lyapunov equation on frequencies scaled by ωk.
    """
    omega_e = _finite_positive("omega_e", omega_e)
    q_e = _check_q("q_e", q_e)
    omega_k = _finite_positive("omega_k", omega_k)
    q_k = _check_q("q_k", q_k)
    c1, c0 = (float(v) for v in numerator)
    for name, value in (("eta_psd", eta_psd), ("nu_psd", nu_psd)):
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{name}={value!r} must be a finite number >= 0")
    err1, err0 = _check_error_poly(omega_k, q_k, gain)
    shape = np.broadcast_shapes(omega_e.shape, q_e.shape, omega_k.shape, q_k.shape, np.shape(gain.l1))
    err1 = np.broadcast_to(err1, shape)
    err0 = np.broadcast_to(err0, shape)
    l1 = np.broadcast_to(gain.l1, shape)
    l2 = np.broadcast_to(gain.l2, shape)
    # ‖(c1 s + c0)/E‖² and ‖(L2 s + L1)/E‖², closed form
    n_eta = 0.5 * eta_psd * (c1 * c1 * err0 + c0 * c0) / (2.0 * err0 * err1)
    n_nu = 0.5 * nu_psd * (l2 * l2 * err0 + l1 * l1) / (2.0 * err0 * err1)
    s_eta, var_eta = _fourth_order_eta_terms(omega_e, q_e, omega_k, q_k, err1, err0, (c1, c0), eta_psd, shape)
    s_g = 0.5 * np.broadcast_to(amplitude.ae2, shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr_eta = s_g / (n_eta + s_eta)
        snr_nu = s_g / n_nu
    return NoiseTerms(s_g, s_eta, n_eta, var_eta - s_eta - n_eta, n_nu, snr_eta, snr_nu, var_eta)


# ---------------------------------------------------------------------------
# Transients (eqs. 5.21, 5.22)
# ---------------------------------------------------------------------------


class Transient(NamedTuple):
    """Initial-state response of the error (eq. 5.22), per unit plant amplitude.

    Attributes
    ----------
    peak_mismatch : numpy.ndarray
        max_t ‖C M(t) T‖: the peak of the additional transient of eq. 5.22,
        M(t) = ∫₀ᵗ e^{(A_k−LC)(t−τ)}(A − A_k)e^{Aτ}dτ, for a plant state
        X0 = T[cos φ, sin φ]ᵀ of unit output amplitude and the worst phase φ.
    peak_total : numpy.ndarray
        The same for the whole error, e0 = X0 (the observer did not see the
        jump): max_t ‖C (e^{(A_k−LC)t} + M(t)) T‖ (≥ 1 at t = 0).
    settling_cycles : numpy.ndarray
        Drive periods after which the whole error stays below ``residual``;
        ``inf`` if it has not settled within the computed horizon.
    horizon_cycles : float
        The horizon, drive periods.
    """

    peak_mismatch: np.ndarray
    peak_total: np.ndarray
    settling_cycles: np.ndarray
    horizon_cycles: float


def _van_loan_system(we, qe, wk, qk, e1, e0) -> tuple[np.ndarray, np.ndarray]:
    """G = [[F, A − A_k], [0, A]] of :func:`transient_response` and its start, per model (batch, 4, 4).

    The start holds two 4 × 2 blocks side by side: [X0; X0] (the whole
    error, e0 = X0) and [0; X0] (the mismatch only, e0 = 0), with
    X0 = T[cos φ, sin φ]ᵀ.
    """
    batch = we.size
    g = np.zeros((batch, 4, 4))
    # F = A_k − LC = [[0, −e0], [1, −e1]]
    g[:, 0, 1] = -e0
    g[:, 1, 0] = 1.0
    g[:, 1, 1] = -e1
    # A − A_k = [[0, −(ωe² − ωk²)], [0, −(ωe/Qe − ωk/Qk)]]
    g[:, 0, 3] = -(we * we - wk * wk)
    g[:, 1, 3] = -(we / qe - wk / qk)
    # A = [[0, −ωe²], [1, −ωe/Qe]]
    g[:, 2, 3] = -we * we
    g[:, 3, 2] = 1.0
    g[:, 3, 3] = -we / qe
    # X0 = T [cos φ, sin φ]ᵀ, T = [[ωe/Qe, −ωe], [1, 0]]; columns: total (e0 = X0), mismatch (e0 = 0)
    t_mat = np.zeros((batch, 2, 2))
    t_mat[:, 0, 0] = we / qe
    t_mat[:, 0, 1] = -we
    t_mat[:, 1, 0] = 1.0
    state = np.zeros((batch, 4, 4))
    state[:, 0:2, 0:2] = t_mat  # total: e0 = X0
    state[:, 2:4, 0:2] = t_mat
    state[:, 2:4, 2:4] = t_mat  # mismatch only: e0 = 0
    return g, state


def transient_response(
    omega_e,
    q_e,
    omega_k,
    q_k,
    gain: ObserverGain,
    *,
    drive_frequency_hz: float,
    residual: float = math.exp(-1.0),
    horizon_cycles: float | None = None,
    points_per_cycle: int = 8,
) -> Transient:
    """Peak of the mismatch transient (eq. 5.22) and the settling time of the error.

    Parameters
    ----------
    omega_e, q_e, omega_k, q_k, gain
        As in :func:`mismatch_amplitude` (arrays broadcast together).
    drive_frequency_hz : float
        f, Hz: times are counted in drive periods 1/f.
    residual : float, optional
        Settled: ‖error‖ below this share of the unit step (1/e default).
    horizon_cycles : float, optional
        Time computed, drive periods; default six of the slower of the
        plant's and the error's envelope time constants (at least 20).
    points_per_cycle : int, optional
        Time steps per drive period (the worst-phase norm is an envelope, so
        a few per period suffice).

    Returns
    -------
    Transient

    Notes
    -----
    With F = A_k − LC the augmented matrix G = [[F, A − A_k], [0, A]] has
    e^{Gt} = [[e^{Ft}, M(t)], [0, e^{At}]] (Van Loan), so [e(t); x(t)] =
    e^{Gt}[e0; X0] gives eq. 5.22 exactly; it is propagated by one
    ``expm(G h)`` per model.  In the canonical form of eq. 5.1, y = x2 and
    ẏ = x1 − (ωe/Qe)x2, so a plant oscillation y = cos(ωe t + φ) starts at
    X0 = T[cos φ, sin φ]ᵀ with T = [[ωe/Qe, −ωe], [1, 0]]; the worst phase
    gives the 2-norm of the row C(·)T.
    """
    import scipy.linalg

    omega_e = _finite_positive("omega_e", omega_e)
    q_e = _check_q("q_e", q_e)
    omega_k = _finite_positive("omega_k", omega_k)
    q_k = _check_q("q_k", q_k)
    f = float(_finite_positive("drive_frequency_hz", drive_frequency_hz))
    if not 0.0 < residual < 1.0:
        raise ConfigError(f"residual={residual!r} must be in (0, 1)")
    err1, err0 = _check_error_poly(omega_k, q_k, gain)
    shape = np.broadcast_shapes(omega_e.shape, q_e.shape, omega_k.shape, q_k.shape, np.shape(gain.l1))
    we, qe, wk, qk, e1, e0 = (np.broadcast_to(v, shape).ravel() for v in (omega_e, q_e, omega_k, q_k, err1, err0))
    if horizon_cycles is None:
        slowest = np.max(np.maximum(2.0 * qe / we, 2.0 / e1)) * f  # envelope time constants, periods
        horizon_cycles = max(20.0, 6.0 * float(slowest))
    n_steps = int(math.ceil(horizon_cycles * points_per_cycle))
    h = 1.0 / (f * points_per_cycle)
    batch = we.size
    g, state = _van_loan_system(we, qe, wk, qk, e1, e0)
    phi = scipy.linalg.expm(g * h)
    peak_total = np.ones(batch)
    peak_mismatch = np.zeros(batch)
    last_above = np.zeros(batch)
    for step in range(1, n_steps + 1):
        state = phi @ state
        # C = [0, 1] on the error block: row 1
        total = np.hypot(state[:, 1, 0], state[:, 1, 1])
        mismatch = np.hypot(state[:, 1, 2], state[:, 1, 3])
        np.maximum(peak_total, total, out=peak_total)
        np.maximum(peak_mismatch, mismatch, out=peak_mismatch)
        last_above = np.where(total > residual, step, last_above)
    settling = np.where(last_above >= n_steps, np.inf, last_above / points_per_cycle)
    horizon = float(n_steps / points_per_cycle)
    return Transient(peak_mismatch.reshape(shape), peak_total.reshape(shape), settling.reshape(shape), horizon)
