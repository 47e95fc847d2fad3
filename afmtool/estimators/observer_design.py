"""``afmtool theory observer``: the ch. 5 trade-offs over observer models and gains.

Evaluates :mod:`afmtool.models.observer_theory` (A_e² and its
sensitivities, eqs. 5.16-5.19; S_η, N_η, N_ν and the SNRs, eq. 5.20; the
transient of eq. 5.22) two ways, as the thesis does:

* **maps** (Figs. 5.3-5.8, 5.12-5.15, 5.18a): the plant fixed at a nominal
  model (free air by default), the observer model (f_k, Q_k) over a 2-D
  grid, one map per gain;
* **lines** along the force-curve direction (Figs. 5.9-5.11, 5.16-5.20):
  the plant moves along the straight line from the free-air model
  (f0, Q) to the on-sample model (f0_low, Q_low), each observer fixed.

Gains are set by the decay of the matched error: ``cycles`` drive periods
per 1/e of its envelope (:func:`~afmtool.models.observer_theory.decay_gain`),
e.g. 4 (aggressive, "4-10 cycles") and 50 (sluggish, "the time scales of
the nominal cantilever", Q/π = 53 periods at Q = 168).

:func:`recommend` picks, among the map's observer models and gains, the
one whose |dA_e²| along the force-curve direction (eq. 5.16) is largest
while the error after a unit step of the plant's state settles below
``residual`` within ``max_cycles`` drive periods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.models.observer_theory import (
    decay_gain,
    directional_sensitivity,
    mismatch_amplitude,
    noise_terms,
    transient_response,
)

__all__ = [
    "Direction",
    "DesignSettings",
    "Metrics",
    "ObserverMap",
    "DirectionalLines",
    "Recommendation",
    "direction_from_averaging",
    "direction_from_reep_tables",
    "evaluate",
    "observer_map",
    "directional_lines",
    "recommend",
    "METRIC_UNITS",
]

#: Metric name -> (label, units with "u" the deflection units).
METRIC_UNITS = {
    "ae2": ("A_e²", "u²"),
    "dae2_dfe": ("∂A_e²/∂f_e", "u²/Hz"),
    "dae2_dqe": ("∂A_e²/∂Q_e", "u²"),
    "dae2_ds": ("dA_e²/ds along the force curve", "u²"),
    "s_eta": ("S_η", "u²"),
    "n_eta": ("N_η", "u²"),
    "x_eta": ("X_η (cross term)", "u²"),
    "n_nu": ("N_ν", "u²"),
    "snr_eta": ("S_g/(N_η + S_η)", ""),
    "snr_nu": ("S_g/N_ν", ""),
    "peak_transient": ("peak mismatch transient (eq. 5.22)", "per unit step"),
    "settling_cycles": ("settling time", "drive periods"),
}


class Direction(NamedTuple):
    """The force-curve direction: from the free-air model to the on-sample one (s = 0 to 1).

    Attributes
    ----------
    f0_free_hz, q_free : float
        Free-air (off-sample) model, s = 0.
    f0_low_hz, q_low : float
        On-sample model at the lowest amplitude considered, s = 1.
    source : str
        Where the end came from.
    """

    f0_free_hz: float
    q_free: float
    f0_low_hz: float
    q_low: float
    source: str

    def at(self, s) -> tuple[np.ndarray, np.ndarray]:
        """(f_e in Hz, Q_e) at parameter s along the straight line."""
        s = np.asarray(s, dtype=np.float64)
        return self.f0_free_hz + s * (self.f0_low_hz - self.f0_free_hz), self.q_free + s * (self.q_low - self.q_free)

    def step(self) -> tuple[float, float]:
        """(dωe/ds in rad/s, dQe/ds) per unit s."""
        return 2.0 * math.pi * (self.f0_low_hz - self.f0_free_hz), self.q_low - self.q_free


@dataclass(frozen=True)
class DesignSettings:
    """What stays fixed while models and gains vary.

    Attributes
    ----------
    drive_frequency_hz : float
        Drive f = ω/2π, Hz.
    drive_amplitude : float
        A0, dither units.
    numerator : tuple of 2 floats
        (c1, c0) of eq. 5.13.
    eta_psd : float
        One-sided PSD of η, dither units²/Hz.
    nu_psd : float
        One-sided PSD of ν, deflection units²/Hz.
    residual : float
        Settled: error below this share of a unit step.
    """

    drive_frequency_hz: float
    drive_amplitude: float
    numerator: tuple[float, float]
    eta_psd: float
    nu_psd: float
    residual: float

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.drive_frequency_hz


class Metrics(NamedTuple):
    """Every ch. 5 quantity at the broadcast shape of the models (see :data:`METRIC_UNITS`)."""

    ae2: np.ndarray
    dae2_dfe: np.ndarray
    dae2_dqe: np.ndarray
    dae2_ds: np.ndarray
    s_eta: np.ndarray
    n_eta: np.ndarray
    x_eta: np.ndarray
    n_nu: np.ndarray
    snr_eta: np.ndarray
    snr_nu: np.ndarray
    peak_transient: np.ndarray
    settling_cycles: np.ndarray


def evaluate(f_e_hz, q_e, f_k_hz, q_k, cycles: float, settings: DesignSettings, direction: Direction) -> Metrics:
    """All metrics for plants (f_e, Q_e) and observers (f_k, Q_k, gain of ``cycles``), broadcast."""
    omega_e = 2.0 * math.pi * np.asarray(f_e_hz, dtype=np.float64)
    omega_k = 2.0 * math.pi * np.asarray(f_k_hz, dtype=np.float64)
    q_e = np.asarray(q_e, dtype=np.float64)
    q_k = np.asarray(q_k, dtype=np.float64)
    gain = decay_gain(omega_k, q_k, cycles, settings.drive_frequency_hz, settings.residual)
    amp = mismatch_amplitude(
        omega_e, q_e, omega_k, q_k, gain,
        omega=settings.omega, drive_amplitude=settings.drive_amplitude, numerator=settings.numerator,
    )
    noise = noise_terms(
        omega_e, q_e, omega_k, q_k, gain,
        amplitude=amp, numerator=settings.numerator, eta_psd=settings.eta_psd, nu_psd=settings.nu_psd,
    )
    transient = transient_response(
        omega_e, q_e, omega_k, q_k, gain, drive_frequency_hz=settings.drive_frequency_hz, residual=settings.residual
    )
    shape = noise.s_g.shape
    along = directional_sensitivity(amp, *direction.step())
    return Metrics(
        np.broadcast_to(amp.ae2, shape),
        np.broadcast_to(2.0 * math.pi * amp.dae2_domega_e, shape),
        np.broadcast_to(amp.dae2_dq_e, shape),
        np.broadcast_to(along, shape),
        noise.s_eta, noise.n_eta, noise.x_eta, noise.n_nu, noise.snr_eta, noise.snr_nu,
        transient.peak_mismatch, transient.settling_cycles,
    )


class ObserverMap(NamedTuple):
    """Metrics over a grid of observer models at one nominal plant, per gain.

    Attributes
    ----------
    f_k_hz : numpy.ndarray, shape (nf,)
    q_k : numpy.ndarray, shape (nq,)
    nominal : tuple of 2 floats
        The plant (f_e in Hz, Q_e).
    cycles : tuple of float
        The gains, drive periods per 1/e.
    metrics : tuple of Metrics
        One per gain, arrays of shape (nq, nf).
    """

    f_k_hz: np.ndarray
    q_k: np.ndarray
    nominal: tuple[float, float]
    cycles: tuple[float, ...]
    metrics: tuple[Metrics, ...]


def observer_map(
    direction: Direction,
    nominal: tuple[float, float],
    cycles: tuple[float, ...],
    settings: DesignSettings,
    *,
    points: int,
    margin: float,
) -> ObserverMap:
    """The maps of Figs. 5.3-5.8: observer models over the direction's box widened by ``margin``."""
    f_lo, f_hi = sorted((direction.f0_free_hz, direction.f0_low_hz))
    q_lo, q_hi = sorted((direction.q_free, direction.q_low))
    df, dq = (f_hi - f_lo) or 0.01 * f_hi, (q_hi - q_lo) or 0.1 * q_hi
    f_axis = np.linspace(f_lo - margin * df, f_hi + margin * df, points)
    q_axis = np.linspace(max(q_lo - margin * dq, 0.51), q_hi + margin * dq, points)
    fk, qk = np.meshgrid(f_axis, q_axis)
    metrics = tuple(evaluate(nominal[0], nominal[1], fk, qk, c, settings, direction) for c in cycles)
    return ObserverMap(f_axis, q_axis, (float(nominal[0]), float(nominal[1])), tuple(cycles), metrics)


class DirectionalLines(NamedTuple):
    """Metrics as the plant moves along the direction, per observer and gain.

    Attributes
    ----------
    s : numpy.ndarray, shape (ns,)
        Position along the direction (0 free air, 1 on-sample).
    f_e_hz, q_e : numpy.ndarray, shape (ns,)
        The plant at each s.
    observers : tuple of (float, float)
        The observer models (f_k in Hz, Q_k).
    cycles : tuple of float
    metrics : tuple of tuple of Metrics
        metrics[i][j] for observer i and gain j, arrays of shape (ns,).
    """

    s: np.ndarray
    f_e_hz: np.ndarray
    q_e: np.ndarray
    observers: tuple[tuple[float, float], ...]
    cycles: tuple[float, ...]
    metrics: tuple[tuple[Metrics, ...], ...]


def directional_lines(
    direction: Direction,
    observers: tuple[tuple[float, float], ...],
    cycles: tuple[float, ...],
    settings: DesignSettings,
    *,
    points: int,
) -> DirectionalLines:
    """Figs. 5.19/5.20: A_e², dA_e² and the rest as the plant moves from free air to on-sample."""
    s = np.linspace(0.0, 1.0, points)
    f_e, q_e = direction.at(s)
    metrics = tuple(
        tuple(evaluate(f_e, q_e, fk, qk, c, settings, direction) for c in cycles) for fk, qk in observers
    )
    return DirectionalLines(s, f_e, q_e, tuple(observers), tuple(cycles), metrics)


class Recommendation(NamedTuple):
    """The observer model and gain of greatest |dA_e²/ds| among those that settle in time.

    Attributes
    ----------
    f_k_hz, q_k, cycles : float
        The pick.
    dae2_ds, ae2, snr_eta, snr_nu, peak_transient, settling_cycles : float
        Its metrics at the nominal plant.
    feasible : int
        Candidates that settle within ``max_cycles``.
    candidates : int
        Candidates examined.
    at_grid_edge : bool
        The pick lies on the edge of the map: the optimum may lie beyond it
        (widen ``grid_margin``).
    """

    f_k_hz: float
    q_k: float
    cycles: float
    dae2_ds: float
    ae2: float
    snr_eta: float
    snr_nu: float
    peak_transient: float
    settling_cycles: float
    feasible: int
    candidates: int
    at_grid_edge: bool


def recommend(grid: ObserverMap, max_cycles: float) -> Recommendation:
    """Maximise |dA_e²/ds| (eq. 5.16 along the force curve) subject to settling ≤ ``max_cycles``.

    Raises
    ------
    InputError
        If no candidate settles within ``max_cycles`` (more aggressive
        gains, given in ``cycles``, are needed).
    """
    if not max_cycles > 0:
        raise ConfigError(f"max_cycles={max_cycles!r} must be > 0")
    best = None
    feasible = 0
    candidates = 0
    for c, m in zip(grid.cycles, grid.metrics, strict=True):
        ok = m.settling_cycles <= max_cycles
        candidates += ok.size
        feasible += int(np.count_nonzero(ok))
        if not ok.any():
            continue
        score = np.where(ok, np.abs(m.dae2_ds), -np.inf)
        iq, jf = np.unravel_index(int(np.argmax(score)), score.shape)
        if best is None or score[iq, jf] > best[0]:
            best = (float(score[iq, jf]), c, m, iq, jf)
    if best is None:
        raise InputError(
            f"no observer model and gain in the grid settles within max_cycles={max_cycles:g} drive periods; "
            "give faster gains in cycles"
        )
    _, c, m, iq, jf = best
    return Recommendation(
        float(grid.f_k_hz[jf]), float(grid.q_k[iq]), float(c), float(m.dae2_ds[iq, jf]), float(m.ae2[iq, jf]),
        float(m.snr_eta[iq, jf]), float(m.snr_nu[iq, jf]), float(m.peak_transient[iq, jf]),
        float(m.settling_cycles[iq, jf]), feasible, candidates,
        bool(iq in (0, grid.q_k.size - 1) or jf in (0, grid.f_k_hz.size - 1)),
    )


def direction_from_averaging(
    f0_hz: float, q: float, force_set: str, free_amplitude_nm: float, setpoint_fraction: float, drive_hz: float
) -> Direction:
    """The on-sample end from averaging theory (ch. 4): the approach at ``setpoint_fraction`` of the free amplitude."""
    from afmtool.models.averaging import SinusoidalDrive, theoretical_force_curve
    from afmtool.models.cantilever import Cantilever
    from afmtool.models.forces import THESIS_FORCE_SETS

    cantilever = Cantilever(f0_hz, q)
    drive = SinusoidalDrive.for_free_amplitude(cantilever, free_amplitude_nm, drive_hz)
    path = np.linspace(free_amplitude_nm * 1.5 + 10.0, -free_amplitude_nm, 1201)
    curve = theoretical_force_curve(path, drive, cantilever, THESIS_FORCE_SETS[force_set])
    below = np.flatnonzero(curve.amplitude_nm <= setpoint_fraction * free_amplitude_nm)
    if below.size == 0:
        raise InputError(f"averaging theory never reaches {setpoint_fraction:.0%} of the free amplitude")
    k = int(below[0])
    return Direction(
        f0_hz, q, float(curve.f0_e_hz[k]), float(curve.q_e[k]),
        f"averaging theory, {force_set} force at {setpoint_fraction:.0%} of {free_amplitude_nm:g} nm",
    )


def direction_from_reep_tables(f0_hz: float, q: float, tables, setpoint_fraction: float, source: str) -> Direction:
    """The on-sample end from REEP's approach: the bin of least amplitude still above ``setpoint_fraction``."""
    table = tables.get("approach")
    if table is None:
        raise InputError(f"{source}: REEP's run has no approach leg")
    usable = (table.count > 0) & np.isfinite(table.f0_hz) & np.isfinite(table.q) & np.isfinite(table.amplitude)
    if not usable.any():
        raise InputError(f"{source}: REEP's run has no amplitude against z")
    free = float(np.nanmax(table.amplitude[usable]))
    above = usable & (table.amplitude >= setpoint_fraction * free)
    k = int(np.flatnonzero(above)[np.argmin(table.amplitude[above])])
    label = f"{source} at {setpoint_fraction:.0%} amplitude"
    return Direction(f0_hz, q, float(table.f0_hz[k]), float(table.q[k]), label)
