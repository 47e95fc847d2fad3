"""Plain-Python references for the kernels of ``afmtool.estimators.rls``.

Written straight from eq. 3.39 with numpy matrices, one sample at a time,
with no attention to speed.  The kernels must agree with these to rounding.
The only departures from the thesis text are the ones the kernels document:
the first two samples fill the past buffers, forgetting is suspended while
trace P ≥ trace P(0), and the compensation is skipped while
1 + θ_C(n−1)ᵀΛθ_LS(n) ≤ 1/2.
"""

from __future__ import annotations

import numpy as np

MIN_BIAS_DENOMINATOR = 0.5


def naive_bcewrls(phi_rows, y, lam_diag, lam, p0, p_history=None):
    """Eq. 3.39 for rows φᵀ(n) of ``phi_rows`` and targets y(n).

    Returns θ_C(n), θ_LS(n) (arrays (N, m)) and σ²(n) (array (N,)); P(n) is
    appended to ``p_history`` when a list is given.
    """
    phi_rows = np.asarray(phi_rows, dtype=float)
    n_rows, m = phi_rows.shape
    big_lambda = np.diag(np.asarray(lam_diag, dtype=float))
    theta_ls = np.zeros(m)
    theta_c = np.zeros(m)
    p_mat = p0 * np.eye(m)
    trace_p0 = np.trace(p_mat)
    j_cost = 0.0
    out_c = np.empty((n_rows, m))
    out_ls = np.empty((n_rows, m))
    out_s2 = np.empty(n_rows)
    for n in range(1, n_rows + 1):
        phi = phi_rows[n - 1]
        lam_n = lam if np.trace(p_mat) < trace_p0 else 1.0
        err = y[n - 1] - phi @ theta_ls
        denom_p = lam_n + phi @ p_mat @ phi
        # P(n) = (1/λ)[P(n−1) − P(n−1)φφᵀP(n−1) / (λ + φᵀP(n−1)φ)]
        p_new = (p_mat - np.outer(p_mat @ phi, phi @ p_mat) / denom_p) / lam_n
        p_new = 0.5 * (p_new + p_new.T)
        # J(n) = λ[J(n−1) + (y − φᵀθ_LS(n−1))² / (λ + φᵀP(n−1)φ)]
        j_cost = lam_n * (j_cost + err**2 / denom_p)
        # θ_LS(n) = θ_LS(n−1) + P(n)φ(n)[y(n) − φᵀ(n)θ_LS(n−1)]
        theta_ls = theta_ls + p_new @ phi * err
        p_mat = p_new
        # w_n = (1 − λ)/(1 − λⁿ) for constant λ; 1/n for λ = 1.  With the
        # anti-windup λ_n the weights are products of λ_k; sum them directly.
        if n == 1:
            inv_w = 1.0
        else:
            inv_w = lam_n * inv_w + 1.0
        # σ²(n) = w_n J(n) / (1 + θ_C(n−1)ᵀ Λ θ_LS(n))
        den = 1.0 + theta_c @ big_lambda @ theta_ls
        if den > MIN_BIAS_DENOMINATOR:
            sigma2 = (j_cost / inv_w) / den
            # θ_C(n) = θ_LS(n) + σ²(n) (1/w_n) P(n) Λ θ_C(n−1)
            theta_c = theta_ls + sigma2 * inv_w * (p_mat @ big_lambda @ theta_c)
        else:
            sigma2 = np.nan
            theta_c = theta_ls.copy()
        out_c[n - 1] = theta_c
        out_ls[n - 1] = theta_ls
        out_s2[n - 1] = sigma2
        if p_history is not None:
            p_history.append(p_mat.copy())
    return out_c, out_ls, out_s2


def naive_reep(deflection, dither, numerator, lam=0.995, p0=1e6, use_input=True, static_offset=False):
    """REEP (§3.3.3) by :func:`naive_bcewrls` with θ = [b1, b0] and Λ = I₂.

    With ``static_offset``, θ = [b1, b0, c], φ(n) = [−p(n−1), −p(n−2), 1]
    and Λ = diag(1, 1, 0).  Returns θ_C(n), θ_LS(n) and σ²(n) for every
    sample; the first two samples (before φ(n) is known) are θ = 0 and
    σ² = NaN.
    """
    p = np.asarray(deflection, dtype=float)
    a2, a1, a0 = numerator if use_input else (0.0, 0.0, 0.0)
    g = np.asarray(dither, dtype=float) if use_input else np.zeros_like(p)
    columns = [-p[1:-1], -p[:-2]] + ([np.ones(len(p) - 2)] if static_offset else [])
    rows = np.column_stack(columns)
    # z(n) = p(n) − a2 g(n) − a1 g(n−1) − a0 g(n−2)
    z = p[2:] - a2 * g[2:] - a1 * g[1:-1] - a0 * g[:-2]
    mask = [1.0, 1.0, 0.0] if static_offset else [1.0, 1.0]
    out_c, out_ls, out_s2 = naive_bcewrls(rows, z, mask, lam, p0)
    head = np.zeros((2, len(mask)))
    return (
        np.vstack((head, out_c)),
        np.vstack((head, out_ls)),
        np.concatenate(([np.nan, np.nan], out_s2)),
    )


def naive_reep_covariance(deflection, dither, numerator, lam=0.995, p0=1e6, static_offset=False,
                          drive_cycles_per_sample=0.0):
    """Cov of REEP's θ̂_C(n) for every sample n ≥ 3, written from the derivation in matrices.

    θ̂(n) − θ = P(n)·Σ_j ϑ(j) v(j) with v(n) = φ(n), v(n−1) = λφ(n−1) + b1 φ(n)
    and a bulk that Ã(x) = 1 + (b1/λ)x + (b0/λ²)x² filters (at the drive ω
    for the oscillation, at DC for the constant regressor φ_dc = [−p̄, −p̄, 1]):

        Cov = σ̂² [P v(n)v(n)ᵀ P + P v(n−1)v(n−1)ᵀ P
                  + |Ã(e^{jω})|² (P/(1+λ) − P φ_dc φ_dcᵀ P/(1−λ²)) + |Ã(1)|² P φ_dc φ_dcᵀ P/(1−λ²)]

    (the φ_dc terms with ``static_offset`` only).  Returns an (N, 3) array
    of (var b1, cov(b1, b0), var b0); rows 0–2 are NaN (the kernel gives row 2 with p(−1) = 0).
    """
    p = np.asarray(deflection, dtype=float)
    a2, a1, a0 = numerator
    g = np.asarray(dither, dtype=float)
    columns = [-p[1:-1], -p[:-2]] + ([np.ones(len(p) - 2)] if static_offset else [])
    rows = np.column_stack(columns)
    z = p[2:] - a2 * g[2:] - a1 * g[1:-1] - a0 * g[:-2]
    mask = [1.0, 1.0, 0.0] if static_offset else [1.0, 1.0]
    history: list[np.ndarray] = []
    theta_c, _, sigma2 = naive_bcewrls(rows, z, mask, lam, p0, history)
    w = 2.0 * np.pi * drive_cycles_per_sample
    out = np.full((len(p), 3), np.nan)
    for i in range(1, len(rows)):
        b1, b0 = theta_c[i, 0], theta_c[i, 1]
        p_mat = history[i]
        v_now = rows[i]
        v_before = lam * rows[i - 1] + b1 * rows[i]
        cov = p_mat @ (np.outer(v_now, v_now) + np.outer(v_before, v_before)) @ p_mat
        if w > 0:
            x = np.exp(1j * w)
            at_drive = abs(1.0 + b1 / lam * x + b0 / lam**2 * x * x) ** 2
            cov = cov + at_drive / (1.0 + lam) * p_mat
            if static_offset:
                offset = theta_c[i, 2] / (1.0 + b1 + b0)
                w_dc = p_mat @ np.array([-offset, -offset, 1.0])
                at_dc = (1.0 + b1 / lam + b0 / lam**2) ** 2
                cov = cov + (at_dc - at_drive) / (1.0 - lam**2) * np.outer(w_dc, w_dc)
        cov = sigma2[i] * cov
        out[i + 2] = (cov[0, 0], cov[0, 1], cov[1, 1])
    return out
