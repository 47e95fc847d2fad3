"""Averaging theory of the tapping cantilever (thesis chapter 4, §3.4.3).

The cantilever of eq. 3.1/4.2, per unit mass,

.. math:: \\ddot p + (\\omega_0/Q)\\dot p + \\omega_0^2 p
          = \\omega_0^2 A\\cos\\omega t + F(p, \\dot p; l),

with the piecewise-linear force ``F`` of :mod:`afmtool.models.forces`
(positive away from the sample, surface at p = −l, dissipative terms
opposing the velocity), is replaced over one period by the linear
oscillator that has the same first harmonic: the *equivalent* resonant
frequency ωe and quality factor Qe.  This module gives

* :func:`equivalent_parameters_quadrature` — the first-harmonic integrals
  of ``docs/conventions.md`` evaluated numerically;
* :func:`equivalent_parameters_closed_form` — the same integrals in closed
  form (eq. 4.8 rewritten in the project's sign convention);
* :func:`equivalent_parameter_derivatives` — their partial derivatives in
  amplitude and separation;
* :func:`topography_sensitivities` — dωe/dl, dδe/dl, dQe/dl, da/dl and
  dφ/dl along a steady state at fixed drive (§4.4–4.6, eqs. 4.10–4.23);
* :func:`steady_states` — every steady state of the averaged
  amplitude/phase dynamics (eqs. 4.6/4.7 with ȧ = φ̇ = 0) and its
  stability;
* :func:`theoretical_force_curve` — the averaged amplitude, phase, f0,e
  and Qe followed continuously along a separation path (approach and
  retract give the hysteresis of Fig. 3.13).

Units: amplitudes, separations and the drive amplitude in nm; angular
frequencies in rad/s; ωe² in 1/s²; damping rates in 1/s.

Sign conventions against the thesis
-----------------------------------
Eq. 4.1 is the negative of the project's force (see
:mod:`afmtool.models.forces`).  The conservative integral Φ_c of eq. 4.8
nevertheless agrees with the physical force (attraction lowers ωe), but
its dissipative integral Φ_d carries eq. 4.1's literal sign, so that with
the thesis's formula a positive c_a *reduces* δe.  Here both follow the
physical force.  The sensitivities of eqs. 4.11–4.17 then come out with
the opposite overall sign to the thesis (here dωe²/dl > 0 in the
attractive regime at fixed amplitude: moving away from the sample removes
attraction and raises ωe).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce

__all__ = [
    "SinusoidalDrive",
    "EquivalentParameters",
    "EquivalentParameterDerivatives",
    "TopographySensitivities",
    "SteadyStates",
    "TheoreticalForceCurve",
    "equivalent_parameters_quadrature",
    "equivalent_parameters_closed_form",
    "equivalent_parameter_derivatives",
    "topography_sensitivities",
    "steady_states",
    "theoretical_force_curve",
]


# ---------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SinusoidalDrive:
    """The dither forcing g(t) = A·cos(ωt) of eq. 4.2 (per unit mass ω0²·g).

    Parameters
    ----------
    amplitude_nm : float
        Forcing amplitude A, nm (the free-air deflection amplitude is
        |G(jω)|·A, see :meth:`Cantilever.frequency_response`).
    frequency_hz : float
        Drive frequency f = ω/2π, Hz.

    Raises
    ------
    ConfigError
        If a parameter is not a finite number > 0.
    """

    amplitude_nm: float
    frequency_hz: float

    def __post_init__(self) -> None:
        for name in ("amplitude_nm", "frequency_hz"):
            value = getattr(self, name)
            ok = isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value) and value > 0
            if not ok:
                raise ConfigError(f"{name}={value!r} must be a finite number > 0")

    @property
    def omega_rad_s(self) -> float:
        """Angular drive frequency ω = 2πf, rad/s."""
        return 2.0 * math.pi * float(self.frequency_hz)

    @classmethod
    def for_free_amplitude(
        cls, cantilever: Cantilever, free_amplitude_nm: float, frequency_hz: float | None = None
    ) -> SinusoidalDrive:
        """The drive whose free-air steady-state amplitude is ``free_amplitude_nm``.

        Parameters
        ----------
        cantilever : Cantilever
            Free-air cantilever (f0, Q).
        free_amplitude_nm : float
            Wanted free-air deflection amplitude, nm (> 0).
        frequency_hz : float, optional
            Drive frequency, Hz; the cantilever's f0 when omitted.

        Returns
        -------
        SinusoidalDrive
            A = free_amplitude / |G(j2πf)|.
        """
        if not isinstance(cantilever, Cantilever):
            raise ConfigError(f"cantilever={cantilever!r} must be an afmtool Cantilever")
        ok = isinstance(free_amplitude_nm, (int, float, np.integer, np.floating)) and math.isfinite(free_amplitude_nm)
        if not (ok and free_amplitude_nm > 0):
            raise ConfigError(f"{free_amplitude_nm=} must be a finite number > 0")
        f = float(cantilever.f0_hz) if frequency_hz is None else frequency_hz
        probe = cls(1.0, f)  # validates frequency_hz
        gain = abs(complex(cantilever.frequency_response(probe.frequency_hz)))
        return cls(float(free_amplitude_nm) / gain, probe.frequency_hz)


class EquivalentParameters(NamedTuple):
    """Equivalent linear oscillator of the first harmonic (eqs. 4.6–4.8).

    Attributes
    ----------
    omega_e : numpy.ndarray
        Equivalent resonant frequency ωe, rad/s (NaN where ωe² < 0).
    q_e : numpy.ndarray
        Equivalent quality factor Qe = ωe/(ωe/Qe) (NaN where ωe² < 0).
    f0_e_hz : numpy.ndarray
        ωe/2π, Hz.
    omega_e2 : numpy.ndarray
        ωe², 1/s² (kept separately: finite even where ωe² < 0).
    damping_rate_per_s : numpy.ndarray
        ωe/Qe = 2δe, 1/s (δe of eq. 4.6 is half of it).
    """

    omega_e: np.ndarray
    q_e: np.ndarray
    f0_e_hz: np.ndarray
    omega_e2: np.ndarray
    damping_rate_per_s: np.ndarray


class EquivalentParameterDerivatives(NamedTuple):
    """Partial derivatives of ωe² and ωe/Qe at fixed amplitude or separation.

    Attributes
    ----------
    domega_e2_dl : numpy.ndarray
        ∂(ωe²)/∂l at fixed a, 1/s² per nm.
    domega_e2_da : numpy.ndarray
        ∂(ωe²)/∂a at fixed l, 1/s² per nm.
    ddamping_dl : numpy.ndarray
        ∂(ωe/Qe)/∂l at fixed a, 1/s per nm.
    ddamping_da : numpy.ndarray
        ∂(ωe/Qe)/∂a at fixed l, 1/s per nm.
    """

    domega_e2_dl: np.ndarray
    domega_e2_da: np.ndarray
    ddamping_dl: np.ndarray
    ddamping_da: np.ndarray


class TopographySensitivities(NamedTuple):
    """Sensitivities to the separation l along a steady state at fixed drive (§4.4–4.6).

    Attributes
    ----------
    da_dl : numpy.ndarray
        Amplitude sensitivity da/dl, nm/nm (eqs. 4.21–4.23).
    domega_e_dl : numpy.ndarray
        dωe/dl including the amplitude change, rad/s per nm (eqs. 4.10–4.17).
    ddelta_e_dl : numpy.ndarray
        dδe/dl, δe = ωe/(2Qe), 1/s per nm (eqs. 4.18–4.20).
    dq_e_dl : numpy.ndarray
        dQe/dl, 1/nm.
    dphase_dl : numpy.ndarray
        dφ/dl of the deflection phase, rad/nm.
    """

    da_dl: np.ndarray
    domega_e_dl: np.ndarray
    ddelta_e_dl: np.ndarray
    dq_e_dl: np.ndarray
    dphase_dl: np.ndarray


class SteadyStates(NamedTuple):
    """All steady states of eqs. 4.6/4.7 at one separation, by increasing amplitude.

    Attributes
    ----------
    amplitude_nm : numpy.ndarray
        Steady-state amplitudes a, nm.
    phase_rad : numpy.ndarray
        Phase φ of the deflection a·cos(ωt + φ) relative to the drive
        A·cos(ωt), rad, in (−π, 0) (−π/2 at free-air resonance).
    stable : numpy.ndarray of bool
        True for a stable node/focus of the averaged dynamics.
    f0_e_hz : numpy.ndarray
        Equivalent resonant frequency at each state, Hz.
    q_e : numpy.ndarray
        Equivalent quality factor at each state.
    """

    amplitude_nm: np.ndarray
    phase_rad: np.ndarray
    stable: np.ndarray
    f0_e_hz: np.ndarray
    q_e: np.ndarray


class TheoreticalForceCurve(NamedTuple):
    """Averaged steady state followed along a separation path.

    Attributes
    ----------
    separation_nm : numpy.ndarray
        The path, as given (nm).
    amplitude_nm, phase_rad, f0_e_hz, q_e : numpy.ndarray
        The followed stable state at each separation (nm, rad, Hz, –).
    n_stable : numpy.ndarray of int
        Number of stable states at each separation (2 where bistable).
    """

    separation_nm: np.ndarray
    amplitude_nm: np.ndarray
    phase_rad: np.ndarray
    f0_e_hz: np.ndarray
    q_e: np.ndarray
    n_stable: np.ndarray


# ---------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------


def _check_models(cantilever: Cantilever, force: PiecewiseLinearForce) -> None:
    if not isinstance(cantilever, Cantilever):
        raise ConfigError(f"cantilever={cantilever!r} must be an afmtool Cantilever")
    if not isinstance(force, PiecewiseLinearForce):
        raise ConfigError(f"force={force!r} must be a PiecewiseLinearForce")


def _check_omega(drive_omega: float) -> float:
    ok = isinstance(drive_omega, (int, float, np.integer, np.floating)) and math.isfinite(drive_omega)
    if not (ok and drive_omega > 0):
        raise ConfigError(f"{drive_omega=} must be a finite angular frequency > 0 (rad/s)")
    return float(drive_omega)


def _amplitude_separation(amplitude_nm, separation_nm) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(amplitude_nm, dtype=np.float64)
    l = np.asarray(separation_nm, dtype=np.float64)
    if not np.all(np.isfinite(a) & (a > 0)):
        raise ConfigError(f"amplitude_nm={amplitude_nm!r} must be finite and > 0 everywhere")
    if not np.all(np.isfinite(l)):
        raise ConfigError(f"separation_nm={separation_nm!r} must be finite everywhere")
    try:
        return tuple(np.broadcast_arrays(a, l))
    except ValueError:
        raise ConfigError(f"amplitude_nm shape {a.shape} and separation_nm shape {l.shape} do not broadcast") from None


def _equivalent(omega_e2: np.ndarray, damping: np.ndarray) -> EquivalentParameters:
    with np.errstate(invalid="ignore"):
        omega_e = np.sqrt(np.where(omega_e2 >= 0, omega_e2, np.nan))
    return EquivalentParameters(omega_e, omega_e / damping, omega_e / (2.0 * math.pi), omega_e2, damping)


# ---------------------------------------------------------------------------
# Quadrature
# ---------------------------------------------------------------------------


def _piecewise_gauss_nodes(a: np.ndarray, l: np.ndarray, d: float, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes θ and weights on [0, 2π], split where the force changes formula.

    The kinks are at cos S1 = (d − l)/a and cos S2 = −l/a, their mirrors
    2π − S1, 2π − S2, and π; both arrays have shape (..., 6, n_nodes).
    """
    # kink angles: cos S1 = (d − l)/a, cos S2 = −l/a (clipped: no kink ⇒ 0 or π)
    s1 = np.arccos(np.clip((d - l) / a, -1.0, 1.0))
    s2 = np.arccos(np.clip(-l / a, -1.0, 1.0))
    two_pi = 2.0 * math.pi
    breaks = np.stack(
        [np.zeros_like(a), s1, s2, np.full_like(a, math.pi), two_pi - s2, two_pi - s1, np.full_like(a, two_pi)],
        axis=-1,
    )  # (..., 7), non-decreasing because S1 ≤ S2 ≤ π
    lo, hi = breaks[..., :-1, None], breaks[..., 1:, None]  # (..., 6, 1)
    nodes, weights = np.polynomial.legendre.leggauss(n_nodes)
    half = 0.5 * (hi - lo)
    theta = 0.5 * (hi + lo) + half * nodes  # (..., 6, n)
    return theta, half * weights


def equivalent_parameters_quadrature(
    amplitude_nm,
    separation_nm,
    drive_omega: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    *,
    n_nodes: int = 16,
) -> EquivalentParameters:
    """Equivalent ωe and Qe by numerical quadrature of the first harmonic.

    Parameters
    ----------
    amplitude_nm : array_like of float
        Oscillation amplitude a, nm (> 0).
    separation_nm : array_like of float
        Rest tip-sample separation l, nm (broadcast against ``amplitude_nm``).
    drive_omega : float
        Oscillation (drive) angular frequency ω, rad/s (> 0).
    cantilever : Cantilever
        Free-air f0 and Q.
    force : PiecewiseLinearForce
        Tip-sample force per unit mass (project convention).
    n_nodes : int, optional
        Gauss–Legendre nodes per smooth θ-segment (≥ 2).

    Returns
    -------
    EquivalentParameters
        Arrays of the broadcast shape.

    Notes
    -----
    With p = a·cosθ, ṗ = −aω·sinθ (eq. 4.4) the first-harmonic balance
    (``docs/conventions.md``; eqs. 4.6 and 4.7 with Φ = m·F) is

    .. math::

        \\omega_e^2 = \\omega_0^2 - \\frac{1}{\\pi a}\\int_0^{2\\pi}
            F(a\\cos\\theta, -a\\omega\\sin\\theta)\\cos\\theta\\,d\\theta

        \\frac{\\omega_e}{Q_e} = \\frac{\\omega_0}{Q} + \\frac{1}{\\pi a\\omega}
            \\int_0^{2\\pi} F(a\\cos\\theta, -a\\omega\\sin\\theta)\\sin\\theta\\,d\\theta

    The force changes formula where t_s = a·cosθ + l crosses d and 0,
    i.e. at cosθ = (d − l)/a and cosθ = −l/a.  The interval [0, 2π] is
    split at those angles S1 = arccos((d − l)/a), S2 = arccos(−l/a),
    their mirrors 2π − S1, 2π − S2 and at π, and each piece is integrated
    by Gauss–Legendre.  On every piece the integrand is a trigonometric
    polynomial of degree 2 in θ, so with the default 16 nodes per piece
    the quadrature error is at round-off level (≈ 1e−15 relative to
    ω0²); it does not use any closed form of the integrals, only the
    force itself (:class:`PiecewiseLinearForce` called on the nodes).
    """
    _check_models(cantilever, force)
    omega = _check_omega(drive_omega)
    if not (isinstance(n_nodes, (int, np.integer)) and n_nodes >= 2):
        raise ConfigError(f"{n_nodes=} must be an integer >= 2")
    a, l = _amplitude_separation(amplitude_nm, separation_nm)
    theta, w = _piecewise_gauss_nodes(a, l, float(force.d_nm), int(n_nodes))

    aa = a[..., None, None]
    f = force(aa * np.cos(theta), -aa * omega * np.sin(theta), l[..., None, None])
    i_cos = np.sum(w * f * np.cos(theta), axis=(-2, -1))  # ∫F cosθ dθ
    i_sin = np.sum(w * f * np.sin(theta), axis=(-2, -1))  # ∫F sinθ dθ

    w0 = cantilever.omega0_rad_s
    # ωe² = ω0² − (1/πa)∫F cosθ dθ
    omega_e2 = w0 * w0 - i_cos / (math.pi * a)
    # ωe/Qe = ω0/Q + (1/πaω)∫F sinθ dθ
    damping = w0 / float(cantilever.q) + i_sin / (math.pi * a * omega)
    return _equivalent(omega_e2, damping)


# ---------------------------------------------------------------------------
# Closed form
# ---------------------------------------------------------------------------


def _contact_integral(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """γ(u) = π − arccos(ū) + ū√(1 − ū²) and γ'(u) = 2√(1 − ū²), ū = clip(u, −1, 1)."""
    uc = np.clip(u, -1.0, 1.0)
    root = np.sqrt(1.0 - uc * uc)
    return math.pi - np.arccos(uc) + uc * root, 2.0 * root


class _Terms(NamedTuple):
    """ωe² (W), ωe/Qe (B) and their partials, for internal use."""

    w: np.ndarray
    b: np.ndarray
    w_l: np.ndarray
    w_a: np.ndarray
    b_l: np.ndarray
    b_a: np.ndarray


def _closed_form_terms(a: np.ndarray, l: np.ndarray, cantilever: Cantilever, force: PiecewiseLinearForce) -> _Terms:
    """W = ωe², B = ωe/Qe and ∂/∂l, ∂/∂a (see :func:`equivalent_parameters_closed_form`)."""
    d, wa2, wb2, ca, cb = force.as_args()
    x = (d - l) / a  # cos S1
    y = -l / a  # cos S2
    gx, gpx = _contact_integral(x)
    gy, gpy = _contact_integral(y)
    w0 = cantilever.omega0_rad_s
    # W = ω0² − (ωa²/π)γ(x) + (ωb²/π)γ(y)
    w = w0 * w0 - (wa2 / math.pi) * gx + (wb2 / math.pi) * gy
    # B = ω0/Q + (ca/π)γ(x) + (cb/π)γ(y)
    b = w0 / float(cantilever.q) + (ca / math.pi) * gx + (cb / math.pi) * gy
    # ∂x/∂l = −1/a, ∂x/∂a = −x/a (and the same for y)
    pa = math.pi * a
    w_l = (wa2 * gpx - wb2 * gpy) / pa
    w_a = (wa2 * x * gpx - wb2 * y * gpy) / pa
    b_l = -(ca * gpx + cb * gpy) / pa
    b_a = -(ca * x * gpx + cb * y * gpy) / pa
    return _Terms(w, b, w_l, w_a, b_l, b_a)


def equivalent_parameters_closed_form(
    amplitude_nm,
    separation_nm,
    drive_omega: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
) -> EquivalentParameters:
    """Equivalent ωe and Qe in closed form (eq. 4.8 in the project's convention).

    Parameters
    ----------
    amplitude_nm : array_like of float
        Oscillation amplitude a, nm (> 0).
    separation_nm : array_like of float
        Rest tip-sample separation l, nm (broadcast against ``amplitude_nm``).
    drive_omega : float
        Oscillation angular frequency ω, rad/s (> 0).  For the
        piecewise-linear force, whose dissipation is linear in ṗ, ω cancels
        from the result; it is validated and kept for a signature common
        with :func:`equivalent_parameters_quadrature`.
    cantilever : Cantilever
        Free-air f0 and Q.
    force : PiecewiseLinearForce
        Tip-sample force per unit mass (project convention).

    Returns
    -------
    EquivalentParameters
        Arrays of the broadcast shape.

    Notes
    -----
    Let x = (d − l)/a and y = −l/a (the thesis's cos S1 and cos S2).  The
    tip is in the force's attractive zone (t_s < d) where cosθ < x, i.e.
    for θ ∈ (S1, 2π − S1), S1 = arccos x, and in the repulsive zone
    (t_s < 0) for θ ∈ (S2, 2π − S2), S2 = arccos y.  Over such an arc
    (S = arccos u)

    .. math::

        \\int \\cos\\theta = -2\\sin S,\\quad
        \\int \\cos^2\\theta = \\pi - S - \\tfrac12\\sin 2S,\\quad
        \\int \\sin^2\\theta = \\pi - S + \\tfrac12\\sin 2S,

    and ∫sinθ = ∫sinθcosθ = 0.  On the arcs the force is
    F = −ωa²(d − l − a cosθ) + c_a aω sinθ (attractive zone) plus
    −ωb²(l + a cosθ) + c_b aω sinθ (repulsive zone).  With d − l = a·x,
    −l = a·y and sin 2S/2 = u√(1 − u²):

    .. math::

        \\int F\\cos\\theta = \\omega_a^2 a\\,\\gamma(x) - \\omega_b^2 a\\,\\gamma(y),\\qquad
        \\int F\\sin\\theta = c_a a\\omega\\,\\gamma(x) + c_b a\\omega\\,\\gamma(y),

        \\gamma(u) = \\pi - \\arccos u + u\\sqrt{1-u^2}\\quad (u\\text{ clipped to }[-1, 1]),

    so that γ = 0 without contact (u ≤ −1), γ = π for contact over the
    whole cycle (u ≥ 1), and γ'(u) = 2√(1 − u²) ≥ 0.  The first-harmonic
    balance (see :func:`equivalent_parameters_quadrature`) then gives

    .. math::

        \\omega_e^2 = \\omega_0^2 - \\frac{\\omega_a^2}{\\pi}\\gamma(x)
                      + \\frac{\\omega_b^2}{\\pi}\\gamma(y),\\qquad
        \\frac{\\omega_e}{Q_e} = 2\\delta_e = \\frac{\\omega_0}{Q}
                      + \\frac{c_a}{\\pi}\\gamma(x) + \\frac{c_b}{\\pi}\\gamma(y).

    Attraction lowers ωe, repulsion raises it, and both dampings raise
    ωe/Qe.  In the thesis's notation Φ_c = (a/2π)(ωa²γ(x) − ωb²γ(y)),
    identical to eq. 4.8 (whose bracket is −ωa²aγ(x) + ωb²aγ(y)), and
    Φ_d = +(aω/2π)(c_aγ(x) + c_bγ(y)), the negative of eq. 4.8's Φ_d.
    The three cases of eq. 4.8 (a < l − d, l − d ≤ a < l, a ≥ l) are the
    clipping of x and y; the formula also holds for l < d and l < 0.
    """
    _check_models(cantilever, force)
    _check_omega(drive_omega)
    a, l = _amplitude_separation(amplitude_nm, separation_nm)
    terms = _closed_form_terms(a, l, cantilever, force)
    return _equivalent(terms.w, terms.b)


def equivalent_parameter_derivatives(
    amplitude_nm,
    separation_nm,
    drive_omega: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
) -> EquivalentParameterDerivatives:
    """Partial derivatives of ωe² and ωe/Qe in separation and amplitude.

    Parameters
    ----------
    amplitude_nm, separation_nm, drive_omega, cantilever, force
        As for :func:`equivalent_parameters_closed_form`.

    Returns
    -------
    EquivalentParameterDerivatives
        ∂/∂l at fixed a and ∂/∂a at fixed l, arrays of the broadcast shape.

    Notes
    -----
    Differentiating the closed form with ∂x/∂l = −1/a, ∂x/∂a = −x/a,
    ∂y/∂l = −1/a, ∂y/∂a = −y/a and γ'(u) = 2√(1 − u²):

    .. math::

        \\frac{\\partial\\omega_e^2}{\\partial l} =
            \\frac{2\\omega_a^2}{\\pi a}\\sqrt{1-x^2} - \\frac{2\\omega_b^2}{\\pi a}\\sqrt{1-y^2},\\qquad
        \\frac{\\partial\\omega_e^2}{\\partial a} =
            \\frac{2\\omega_a^2}{\\pi a}x\\sqrt{1-x^2} - \\frac{2\\omega_b^2}{\\pi a}y\\sqrt{1-y^2},

        \\frac{\\partial(\\omega_e/Q_e)}{\\partial l} =
            -\\frac{2c_a}{\\pi a}\\sqrt{1-x^2} - \\frac{2c_b}{\\pi a}\\sqrt{1-y^2},\\qquad
        \\frac{\\partial(\\omega_e/Q_e)}{\\partial a} =
            -\\frac{2c_a}{\\pi a}x\\sqrt{1-x^2} - \\frac{2c_b}{\\pi a}y\\sqrt{1-y^2},

    with the square roots taken as 0 outside |u| < 1.  These are eqs.
    4.14, 4.17, 4.19 and 4.20 at ∂a/∂l = 0 (ωe/Qe = 2δe), up to the
    overall sign of eqs. 4.11–4.17 (module docstring).  The derivatives
    are continuous in a and l (γ is C¹ at u = ±1).
    """
    _check_models(cantilever, force)
    _check_omega(drive_omega)
    a, l = _amplitude_separation(amplitude_nm, separation_nm)
    t = _closed_form_terms(a, l, cantilever, force)
    return EquivalentParameterDerivatives(t.w_l, t.w_a, t.b_l, t.b_a)


# ---------------------------------------------------------------------------
# Steady state of the averaged dynamics and sensitivities
# ---------------------------------------------------------------------------


def topography_sensitivities(
    amplitude_nm,
    separation_nm,
    drive_omega: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
) -> TopographySensitivities:
    """Sensitivities to the separation along a steady state at fixed drive (§4.4–4.6).

    Parameters
    ----------
    amplitude_nm : array_like of float
        Steady-state amplitude a, nm.  The drive amplitude held fixed is
        the one for which ``a`` is a steady state at ``drive_omega``,
        A = a·√D/ω0² (Notes); pass the output of :func:`steady_states`
        or :func:`theoretical_force_curve`.
    separation_nm : array_like of float
        Rest tip-sample separation l, nm.
    drive_omega : float
        Drive angular frequency ω, rad/s.
    cantilever, force
        As for :func:`equivalent_parameters_closed_form`.

    Returns
    -------
    TopographySensitivities
        Arrays of the broadcast shape (±inf/NaN at a fold of the
        amplitude curve, where da/dl is unbounded).

    Notes
    -----
    Write W = ωe², B = ωe/Qe = 2δe (closed form) and
    D = (W − ω²)² + ω²B².  The steady state of eqs. 4.6/4.7 (see
    :func:`steady_states`) satisfies a²D(a, l) = (ω0²A)², the amplitude
    of §4.6.  Differentiating at fixed A and ω (implicit function, eqs.
    4.21–4.23):

    .. math::

        \\frac{da}{dl} = -\\frac{a\\,D_l}{2D + a\\,D_a},\\qquad
        D_{l} = 2(W-\\omega^2)W_{l} + 2\\omega^2 B B_{l}\\ \\ (\\text{same for } a),

    with W_l, W_a, B_l, B_a from :func:`equivalent_parameter_derivatives`.
    This is eq. 4.21 solved for ∂a/∂l (eqs. 4.22/4.23 are the same
    rearrangement: A_1, A_2 there are −a/(2D) times the ∂D/∂l terms).  Then

    .. math::

        \\frac{dW}{dl} = W_l + W_a\\frac{da}{dl},\\quad
        \\frac{d\\omega_e}{dl} = \\frac{1}{2\\omega_e}\\frac{dW}{dl}\\ (4.10),\\quad
        \\frac{d\\delta_e}{dl} = \\tfrac12\\Big(B_l + B_a\\frac{da}{dl}\\Big),

        \\frac{dQ_e}{dl} = \\frac{B\\,d\\omega_e/dl - \\omega_e\\,dB/dl}{B^2},\\qquad
        \\frac{d\\phi}{dl} = \\frac{\\omega\\,(B\\,dW/dl - (W-\\omega^2)\\,dB/dl)}{D},

    the last from φ = atan2(−ωB, W − ω²).  In the attractive regime
    W_l = (2ωa²/πa)√(1 − x²), so dW/dl = (2ωa²/πa)√(1 − x²)(1 + x·da/dl):
    eq. 4.14 with the opposite sign (module docstring).
    """
    _check_models(cantilever, force)
    omega = _check_omega(drive_omega)
    a, l = _amplitude_separation(amplitude_nm, separation_nm)
    t = _closed_form_terms(a, l, cantilever, force)
    om2 = omega * omega
    detune = t.w - om2
    # D = (W − ω²)² + ω²B²
    d = detune * detune + om2 * t.b * t.b
    d_l = 2.0 * detune * t.w_l + 2.0 * om2 * t.b * t.b_l
    d_a = 2.0 * detune * t.w_a + 2.0 * om2 * t.b * t.b_a
    with np.errstate(divide="ignore", invalid="ignore"):
        # da/dl = −a D_l / (2D + a D_a)   (eq. 4.21 solved for da/dl)
        da_dl = -a * d_l / (2.0 * d + a * d_a)
        dw_dl = t.w_l + t.w_a * da_dl
        db_dl = t.b_l + t.b_a * da_dl
        omega_e = np.sqrt(np.where(t.w >= 0, t.w, np.nan))
        domega_e_dl = dw_dl / (2.0 * omega_e)  # eq. 4.10
        dq_e_dl = (t.b * domega_e_dl - omega_e * db_dl) / (t.b * t.b)
        dphase_dl = omega * (t.b * dw_dl - detune * db_dl) / d
    return TopographySensitivities(da_dl, domega_e_dl, 0.5 * db_dl, dq_e_dl, dphase_dl)


def _residual(a: np.ndarray, l: np.ndarray, amp_force: float, omega: float, cantilever, force):
    """h(a) = a√D − ω0²A, dh/da = (2D + aD_a)/(2√D), and the closed-form terms."""
    t = _closed_form_terms(a, l, cantilever, force)
    om2 = omega * omega
    detune = t.w - om2
    d = detune * detune + om2 * t.b * t.b
    d_a = 2.0 * detune * t.w_a + 2.0 * om2 * t.b * t.b_a
    root_d = np.sqrt(d)
    return a * root_d - amp_force, (2.0 * d + a * d_a) / (2.0 * root_d), t


def _bisect(fun, lo: np.ndarray, hi: np.ndarray, f_lo: np.ndarray) -> np.ndarray:
    """Vectorised bisection of ``fun`` on brackets [lo, hi] with sign(fun(lo)) = sign(f_lo).

    Runs until no bracket can shrink further in float64 (about 60 halvings
    for the grid cells used here), so each root is exact to the last bit or
    two of its bracket.
    """
    lo, hi, f_lo = lo.copy(), hi.copy(), f_lo.copy()
    for _ in range(1100):  # bound: 1075 halvings exhaust any float64 interval
        mid = 0.5 * (lo + hi)
        active = (mid > lo) & (mid < hi)
        if not np.any(active):
            break
        f_mid = fun(mid)
        same = np.sign(f_mid) == np.sign(f_lo)
        lo = np.where(active & same, mid, lo)
        f_lo = np.where(active & same, f_mid, f_lo)
        hi = np.where(active & ~same, mid, hi)
    return 0.5 * (lo + hi)


def _check_drive(drive: SinusoidalDrive) -> None:
    if not isinstance(drive, SinusoidalDrive):
        raise ConfigError(f"drive={drive!r} must be a SinusoidalDrive")


def _check_grid(n_grid: int) -> None:
    if not (isinstance(n_grid, (int, np.integer)) and n_grid >= 16):
        raise ConfigError(f"{n_grid=} must be an integer >= 16")


def _all_steady_states(
    l: np.ndarray, drive: SinusoidalDrive, cantilever: Cantilever, force: PiecewiseLinearForce, n_grid: int
) -> tuple[np.ndarray, SteadyStates]:
    """Steady states at every separation in ``l`` (1-D) at once.

    Returns ``(owner, states)``: flat arrays of all states, ``owner[k]``
    the index into ``l`` of state k, sorted by owner then amplitude.
    """
    omega = drive.omega_rad_s
    w0 = cantilever.omega0_rad_s
    amp_force = w0 * w0 * float(drive.amplitude_nm)  # ω0²A, nm/s²
    # every root lies in (0, a_max]: a√D ≥ a·ω·ωe/Qe ≥ a·ω·ω0/Q
    a_max = 1.01 * float(cantilever.q) * w0 * float(drive.amplitude_nm) / omega
    n_l = l.size

    def h(a, ll):
        return _residual(a, ll, amp_force, omega, cantilever, force)[0]

    def h_a(a, ll):
        return _residual(a, ll, amp_force, omega, cantilever, force)[1]

    # 1. extrema of h: sign changes of h'(a) on the grid, bisected
    grid = np.linspace(a_max / n_grid, a_max, n_grid)
    slope = h_a(grid[None, :], l[:, None])  # (n_l, n_grid)
    row, col = np.nonzero(np.sign(slope[:, :-1]) * np.sign(slope[:, 1:]) < 0)
    ext = _bisect(lambda a: h_a(a, l[row]), grid[col], grid[col + 1], slope[row, col])
    # 2. cut (0, a_max] at the extrema: h is monotonic on each piece
    owner = np.concatenate([np.arange(n_l), row, np.arange(n_l)])
    cuts = np.concatenate([np.zeros(n_l), ext, np.full(n_l, a_max)])
    order = np.lexsort((cuts, owner))
    owner, cuts = owner[order], cuts[order]
    h_cuts = np.where(cuts == 0.0, -amp_force, h(np.where(cuts == 0.0, a_max, cuts), l[owner]))  # h(0⁺) = −ω0²A
    # 3. pieces whose ends have opposite signs (within one separation) hold one root each
    same_row = owner[:-1] == owner[1:]
    crossing = same_row & ((np.sign(h_cuts[:-1]) != np.sign(h_cuts[1:])) | (h_cuts[1:] == 0.0))
    k = np.flatnonzero(crossing)
    root_owner = owner[k]
    roots = _bisect(lambda a: h(a, l[root_owner]), cuts[k], cuts[k + 1], h_cuts[k])
    # 4. phase and stability (Jacobian of the averaged system, see steady_states)
    _, dh_da, t = _residual(roots, l[root_owner], amp_force, omega, cantilever, force)
    trace = -t.b - 0.5 * roots * t.b_a
    stable = (dh_da > 0) & (trace < 0)
    # φ = atan2(−ω·ωe/Qe, ωe² − ω²)
    phase = np.arctan2(-omega * t.b, t.w - omega * omega)
    eq = _equivalent(t.w, t.b)
    return root_owner, SteadyStates(roots, phase, stable, eq.f0_e_hz, eq.q_e)


def steady_states(
    separation_nm: float,
    drive: SinusoidalDrive,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    *,
    n_grid: int = 2000,
) -> SteadyStates:
    """All steady states of the averaged amplitude/phase dynamics at one separation.

    Parameters
    ----------
    separation_nm : float
        Rest tip-sample separation l, nm.
    drive : SinusoidalDrive
        Forcing amplitude A (nm) and frequency.
    cantilever : Cantilever
        Free-air f0 and Q.
    force : PiecewiseLinearForce
        Tip-sample force per unit mass (project convention).
    n_grid : int, optional
        Number of amplitude grid points used to separate the roots (≥ 16).

    Returns
    -------
    SteadyStates
        Every steady state (stable and unstable), by increasing amplitude.
        There is always at least one; where the response is bistable there
        are two stable states with an unstable one between them.

    Notes
    -----
    With p = a·cos ψ, ψ = ωt + φ, ṗ = −aω·sin ψ, eq. 4.5 averaged over ψ
    (the drive term A·cos ωt = A·cos(ψ − φ)) gives, in the project's
    convention and without the near-resonance approximation ω0 + ω ≈ 2ω,

    .. math::

        \\dot a = -\\frac{a}{2}\\frac{\\omega_e}{Q_e}
                  - \\frac{\\omega_0^2 A}{2\\omega}\\sin\\phi,\\qquad
        \\dot\\phi = \\frac{\\omega_e^2 - \\omega^2}{2\\omega}
                  - \\frac{\\omega_0^2 A}{2a\\omega}\\cos\\phi .

    (Eqs. 4.6/4.7 have ω0 + ω where this has 2ω, and ωe − ω where this
    has (ωe² − ω²)/2ω; the two agree to first order in the detuning, and
    only this form reproduces the steady-state amplitude of §4.6 and
    a = |G(jω)|·A without interaction.)  Setting ȧ = φ̇ = 0:

    .. math::

        a\\,\\omega\\,\\omega_e/Q_e = -\\omega_0^2 A\\sin\\phi,\\qquad
        a(\\omega_e^2 - \\omega^2) = \\omega_0^2 A\\cos\\phi,

    hence h(a) = a√D(a) − ω0²A = 0 with D = (ωe² − ω²)² + ω²(ωe/Qe)²
    (the amplitude of §4.6) and φ = atan2(−ω·ωe/Qe, ωe² − ω²), ωe and Qe
    from :func:`equivalent_parameters_closed_form`.  The Jacobian of the
    averaged system at a steady state has determinant (2D + aD_a)/(8ω²),
    with the sign of h'(a), and trace −B − aB_a/2 (B = ωe/Qe); a state is
    stable when det > 0 and trace < 0.

    Root finding: every root lies in (0, a_max], a_max = 1.01·Q·ω0·A/ω,
    because ωe/Qe ≥ ω0/Q.  The interval is cut at the extrema of h, found
    as sign changes of h'(a) on ``n_grid`` points and bisected, so h is
    monotonic between consecutive cuts and each piece holds at most one
    root, which is bisected to float64 precision.  Only a fold narrower
    than one grid step (a_max/n_grid) can be missed.
    """
    _check_models(cantilever, force)
    _check_drive(drive)
    if not (isinstance(separation_nm, (int, float, np.integer, np.floating)) and math.isfinite(separation_nm)):
        raise ConfigError(f"{separation_nm=} must be a finite number (nm)")
    _check_grid(n_grid)
    return _all_steady_states(np.array([float(separation_nm)]), drive, cantilever, force, int(n_grid))[1]


def theoretical_force_curve(
    separations_nm,
    drive: SinusoidalDrive,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    *,
    n_grid: int = 2000,
) -> TheoreticalForceCurve:
    """Averaged amplitude, phase, f0,e and Qe followed along a separation path.

    Parameters
    ----------
    separations_nm : array_like of float, 1-D
        The path of rest separations l, nm, in the order it is travelled:
        descending for an approach, ascending for a retract.
    drive : SinusoidalDrive
        Forcing amplitude and frequency, fixed along the path.
    cantilever, force
        As for :func:`steady_states`.
    n_grid : int, optional
        Passed to :func:`steady_states`.

    Returns
    -------
    TheoreticalForceCurve
        One followed stable state per separation.

    Notes
    -----
    The path is quasi-static: at each separation the state is the stable
    steady state (:func:`steady_states`) whose amplitude is nearest the
    previous one, so the branch is followed continuously and the state
    jumps only where its branch ends at a fold.  At the first separation
    the largest-amplitude stable state is taken (the free-air branch when
    the path starts off the sample).  Running the approach and then the
    reversed path (retract) shows the hysteresis between the attractive
    (large-amplitude, φ < −π/2 at ω = ω0) and repulsive branches of
    Fig. 3.13; ``n_stable`` marks the bistable separations.  Step the path
    finely (≪ the width of the bistable window) for the nearest-amplitude
    rule to follow the right branch.
    """
    _check_models(cantilever, force)
    _check_drive(drive)
    _check_grid(n_grid)
    l = np.asarray(separations_nm, dtype=np.float64)
    if l.ndim != 1 or l.size == 0 or not np.all(np.isfinite(l)):
        raise ConfigError(f"separations_nm must be a non-empty 1-D array of finite values, got shape {l.shape}")
    owner, states = _all_steady_states(l, drive, cantilever, force, int(n_grid))
    starts = np.searchsorted(owner, np.arange(l.size + 1))
    n_stable = np.add.reduceat(states.stable.astype(np.int64), starts[:-1])
    chosen = np.empty(l.size, dtype=np.int64)
    previous = math.nan
    for k in range(l.size):
        idx = np.arange(starts[k], starts[k + 1])
        stable = idx[states.stable[idx]]
        idx = stable if stable.size else idx  # no stable state cannot occur for c_a, c_b ≥ 0
        # first point: largest amplitude; then the stable state nearest the previous one
        j = idx[-1] if math.isnan(previous) else idx[np.argmin(np.abs(states.amplitude_nm[idx] - previous))]
        chosen[k] = j
        previous = states.amplitude_nm[j]
    return TheoreticalForceCurve(
        l.copy(),
        states.amplitude_nm[chosen],
        states.phase_rad[chosen],
        states.f0_e_hz[chosen],
        states.q_e[chosen],
        n_stable,
    )
