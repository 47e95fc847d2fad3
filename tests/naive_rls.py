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


def naive_bcewrls(phi_rows, y, lam_diag, lam, p0):
    """Eq. 3.39 for rows φᵀ(n) of ``phi_rows`` and targets y(n).

    Returns θ_C(n), θ_LS(n) (arrays (N, m)) and σ²(n) (array (N,)).
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
