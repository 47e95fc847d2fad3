"""The electrostatically actuated cantilever of ch. 7, integrated by RK4 (shared by ``bits`` and ``vphi-step``).

Model (eq. 7.11 in the convention of :mod:`afmtool.models.electrostatic`)::

    p̈ + (ω0/Q)ṗ + ω0²p = (ω0²/k)·F_esf(p, V, z) + η,
    F_esf = −K_esf·V²/max(ℓ0 + p − z, t_h)²        (no ½; SI inside F_esf)

with p the deflection (nm, positive away from the sample), z the sample
topography (nm, positive = sample higher, lever-sample gap smaller), V the
lever-sample voltage (V) and η the thermal acceleration (nm/s², held over
each sample period, σ from :func:`afmtool.sim.tapping.thermal_accel_rms`).
The force is evaluated by the shared
:func:`~afmtool.models.electrostatic.electrostatic_force_scalar` (metres in,
newtons out) and converted to nm/s² per unit mass by ω0²/k·1e9.

It is integrated with the classical fixed-step RK4 method, ``substeps`` steps
per sample, with V and z evaluated analytically at every stage time.  A
noise-free pre-roll of ``settle_s`` before t = 0 lets the start-up transient
decay (12 amplitude time constants 2Q/ω0 by default), so the capture starts
in the periodic steady state even at Q = 1000.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.jit import JIT_OPTIONS
from afmtool.models.cantilever import Cantilever
from afmtool.models.electrostatic import ElectrostaticParams, electrostatic_force_scalar

__all__ = ["PlantResult", "integrate_electrostatic", "default_settle_s", "simulate_plant"]

_DEFAULT_CHUNK_SAMPLES = 1 << 16

#: Amplitude time constants 2Q/ω0 of noise-free pre-roll (e^-12 ≈ 6e-6 of the start-up transient left).
_SETTLE_TIME_CONSTANTS = 12.0


@njit(**JIT_OPTIONS)
def _esf_rk4_kernel(
    v_half, z_half, accel_noise, nsub, dt, w0q, w0sq, force_gain, l0_m, k_esf, tip_m, p0, v0, out_p
):
    """Integrate n sample periods of eq. 7.11 with ``nsub`` RK4 steps each.

    ``v_half[j]``, ``z_half[j]`` hold V (V) and z (nm) at t_start + j·dt/2
    (length 2·nsub·n + 1); ``accel_noise[i]`` is η over sample period i
    (nm/s²).  Writes p(t_i) (nm) to ``out_p[i]``; returns (p, ṗ) at the end.
    """
    half = 0.5 * dt
    sixth = dt / 6.0
    p = p0
    v = v0
    for i in range(out_p.shape[0]):
        out_p[i] = p
        eta = accel_noise[i]
        base = 2 * nsub * i
        for k in range(nsub):
            j = base + 2 * k
            # F/m = (ω0²/k)·F_esf, nm/s² (F_esf in N from p, z in m)
            f0 = force_gain * electrostatic_force_scalar(p * 1e-9, v_half[j], l0_m, k_esf, z_half[j] * 1e-9, tip_m)
            # k1 = f(t, y)
            a1 = eta - w0sq * p - w0q * v + f0
            p2 = p + half * v
            v2 = v + half * a1
            f1 = force_gain * electrostatic_force_scalar(
                p2 * 1e-9, v_half[j + 1], l0_m, k_esf, z_half[j + 1] * 1e-9, tip_m
            )
            # k2 = f(t + h/2, y + h/2·k1)
            a2 = eta - w0sq * p2 - w0q * v2 + f1
            p3 = p + half * v2
            v3 = v + half * a2
            f2 = force_gain * electrostatic_force_scalar(
                p3 * 1e-9, v_half[j + 1], l0_m, k_esf, z_half[j + 1] * 1e-9, tip_m
            )
            # k3 = f(t + h/2, y + h/2·k2)
            a3 = eta - w0sq * p3 - w0q * v3 + f2
            p4 = p + dt * v3
            v4 = v + dt * a3
            f3 = force_gain * electrostatic_force_scalar(
                p4 * 1e-9, v_half[j + 2], l0_m, k_esf, z_half[j + 2] * 1e-9, tip_m
            )
            # k4 = f(t + h, y + h·k3)
            a4 = eta - w0sq * p4 - w0q * v4 + f3
            # y += h/6·(k1 + 2k2 + 2k3 + k4)
            p = p + sixth * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return p, v


class PlantResult(NamedTuple):
    """Output of :func:`integrate_electrostatic`."""

    deflection_nm: np.ndarray  #: p at each sample instant t_i, nm
    p_end_nm: float  #: p after the last period, nm
    v_end_nm_per_s: float  #: ṗ after the last period, nm/s


def integrate_electrostatic(
    v_half: np.ndarray,
    z_half: np.ndarray,
    accel_noise: np.ndarray,
    *,
    substeps: int,
    sample_rate_hz: float,
    cantilever: Cantilever,
    electrostatic: ElectrostaticParams,
    p0_nm: float = 0.0,
    v0_nm_per_s: float = 0.0,
) -> PlantResult:
    """Integrate eq. 7.11 over n sample periods (RK4, ``substeps`` per period).

    Parameters
    ----------
    v_half, z_half : numpy.ndarray
        Voltage V (V) and topography z (nm) on the half-step grid
        t_0 + j·T_s/(2·substeps), j = 0 … 2·substeps·n.
    accel_noise : numpy.ndarray
        η (nm/s²) held over each of the n sample periods.
    substeps : int
        RK4 steps per sample period, ≥ 1.
    sample_rate_hz : float
        f_s = 1/T_s, Hz.
    cantilever : Cantilever
        ω0, Q and k (k converts the force to deflection, eq. 7.11).
    electrostatic : ElectrostaticParams
        K_esf, ℓ0 and t_h (α_R is not used: V is given).
    p0_nm, v0_nm_per_s : float
        State at t_0.

    Returns
    -------
    PlantResult
    """
    n = accel_noise.shape[0]
    if not (isinstance(substeps, int) and substeps >= 1):
        raise ConfigError(f"substeps={substeps!r} must be an integer >= 1")
    expected = 2 * substeps * n + 1
    if v_half.shape != (expected,) or z_half.shape != (expected,):
        raise ConfigError(
            f"v_half and z_half need {expected} values for {n} samples, got {v_half.shape} and {z_half.shape}"
        )
    w0 = cantilever.omega0_rad_s
    out_p = np.empty(n)
    p_end, v_end = _esf_rk4_kernel(
        np.ascontiguousarray(v_half, dtype=np.float64),
        np.ascontiguousarray(z_half, dtype=np.float64),
        np.ascontiguousarray(accel_noise, dtype=np.float64),
        substeps,
        1.0 / (sample_rate_hz * substeps),
        w0 / cantilever.q,
        w0 * w0,
        w0 * w0 / cantilever.spring_constant_n_per_m * 1e9,
        electrostatic.l0_m,
        electrostatic.k_esf_f_m,
        electrostatic.tip_height_m,
        float(p0_nm),
        float(v0_nm_per_s),
        out_p,
    )
    return PlantResult(out_p, float(p_end), float(v_end))


def default_settle_s(cantilever: Cantilever) -> float:
    """Noise-free pre-roll that leaves e^-12 of the start-up transient: 12·2Q/ω0, s."""
    return _SETTLE_TIME_CONSTANTS * cantilever.time_constant_s


def simulate_plant(
    voltage: Callable[[np.ndarray], np.ndarray],
    topography_nm: Callable[[np.ndarray], np.ndarray],
    accel_noise: np.ndarray,
    *,
    sample_rate_hz: float,
    substeps: int,
    cantilever: Cantilever,
    electrostatic: ElectrostaticParams,
    settle_s: float,
    chunk_samples: int = _DEFAULT_CHUNK_SAMPLES,
) -> np.ndarray:
    """Noise-free deflection (nm) at t_i = i/f_s, i < len(accel_noise), after a pre-roll.

    ``voltage(t_s)`` (V) and ``topography_nm(t_s)`` (nm) are evaluated
    analytically on the RK4 stage grid, also at negative times during the
    pre-roll of ``settle_s`` (run without thermal noise, from rest).  The
    integration is chunked (``chunk_samples`` per kernel call) to bound
    memory; the result does not depend on the chunk size.
    """
    if not (math.isfinite(settle_s) and settle_s >= 0):
        raise ConfigError(f"settle_s={settle_s!r} must be a finite number >= 0")
    fs = sample_rate_hz
    per_sample = 2 * substeps
    half_step_s = 1.0 / (per_sample * fs)
    n_pre = sample_count(settle_s, fs, "settle_s", ceil=True)
    n = accel_noise.shape[0]
    noise = np.concatenate((np.zeros(n_pre), np.asarray(accel_noise, dtype=np.float64)))
    out = np.empty(n)
    p, v = 0.0, 0.0
    for start in range(-n_pre, n, chunk_samples):
        stop = min(start + chunk_samples, n)
        t_half = np.arange(per_sample * start, per_sample * stop + 1) * half_step_s
        result = integrate_electrostatic(
            voltage(t_half),
            topography_nm(t_half),
            noise[start + n_pre : stop + n_pre],
            substeps=substeps,
            sample_rate_hz=fs,
            cantilever=cantilever,
            electrostatic=electrostatic,
            p0_nm=p,
            v0_nm_per_s=v,
        )
        if stop > 0:
            first = max(start, 0)
            out[first:stop] = result.deflection_nm[first - start :]
        p, v = result.p_end_nm, result.v_end_nm_per_s
    return out
