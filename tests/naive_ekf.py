"""Plain-Python reference for the EKF kernel of ``afmtool.estimators.ekf``.

Written from the module's equations with numpy 2×2 matrices, one sample at a
time, with no attention to speed: x⁻ = Φx̂ + g(ℓ_mid)·w, F = Φ + w∇gᵀ (∇g at
the prior's mid-step gap), P⁻ = FPFᵀ + Q_d, then the Kalman update with the
Joseph form.  The kernel must agree with it to rounding.
"""

from __future__ import annotations

import numpy as np


def naive_ekf(design, deflection_nm, voltage_v):
    """Innovation, running mean, final x̂ and P of the EKF over a whole record."""
    phi = design.phi
    gammas = design.gammas  # rows: V² at n−4 … n
    qd = design.process_covariance
    model = design.model
    r = model.measurement_noise_nm**2
    es = model.electrostatic
    w0 = 2 * np.pi * model.f0_hz
    c = w0 * w0 * es.k_esf_f_m / es.spring_constant_n_per_m * 1e27
    l0, th = es.l0_m * 1e9, es.tip_height_m * 1e9
    half_t = 0.5 / design.sample_rate_hz
    s1, s2 = design.initial_std
    h = np.array([[1.0, 0.0]])
    y = np.asarray(deflection_nm, dtype=float)
    v2 = np.asarray(voltage_v, dtype=float) ** 2
    x = np.zeros(2)
    p = np.diag([s1**2, s2**2])
    history = None
    dg = None
    innovation = np.empty(y.size)
    for n in range(y.size):
        if n == 0:
            x_prior = np.zeros(2)
            p_prior = p.copy()
            history = np.full(5, v2[0])
        else:
            history = np.append(history[1:], v2[n])
            gap = max(l0 + x[0] + half_t * x[1], th)
            g = -c / gap**2
            w = gammas.T @ history
            x_prior = phi @ x + g * w
            f = phi + np.outer(w, dg * np.array([1.0, half_t]))
            p_prior = f @ p @ f.T + qd
        lin_gap = l0 + x_prior[0] + half_t * x_prior[1]
        dg = 2 * c / lin_gap**3 if lin_gap > th else 0.0
        e = y[n] - x_prior[0]
        s = (h @ p_prior @ h.T)[0, 0] + r
        k = p_prior @ h.T / s
        x = x_prior + k[:, 0] * e
        joseph = np.eye(2) - k @ h
        p = joseph @ p_prior @ joseph.T + r * (k @ k.T)
        innovation[n] = e
    window = design.mean_window
    mean = np.array([innovation[max(0, n - window + 1) : n + 1].mean() for n in range(y.size)])
    return innovation, mean, x, p
