"""Plain-Python references for the kernels of ``afmtool.estimators.observer``.

Written from the predictor equations with numpy matrices, one sample at a
time, with no attention to speed::

    e(n)       = y(n) − C x̂(n|n−1) − D g(n)
    x̂(n+1|n)   = A x̂(n|n−1) + B g(n) + L e(n)

The adaptive reference recomputes L every sample by Ackermann's formula on
the eigenvalues of A(n) moved radially to r (not the kernel's closed form).
The window RMS reference uses the kernel's arithmetic (a running sum
re-summed every 1024 samples) so the two agree to rounding;
``exact_window_rms`` is the textbook boxcar, for checking that definition.
"""

from __future__ import annotations

import numpy as np

RESYNC_SAMPLES = 1024


def canonical(b1, b0, numerator):
    """A, B, C, D of the observer canonical form (module docstring of observer.py)."""
    a2, a1, a0 = numerator
    a_mat = np.array([[-b1, 1.0], [-b0, 0.0]])
    b_vec = np.array([a1 - a2 * b1, a0 - a2 * b0])
    c_vec = np.array([1.0, 0.0])
    return a_mat, b_vec, c_vec, a2


def naive_window_rms(x, window):
    """Boxcar RMS of each row of ``x`` (N, T) with the kernels' running sum."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    n_rows, n_samples = x.shape
    ring = np.zeros((n_rows, window))
    sums = np.zeros(n_rows)
    out = np.empty_like(x)
    pos = 0
    for n in range(n_samples):
        count = min(n + 1, window)
        for k in range(n_rows):
            sq = x[k, n] * x[k, n]
            # S(n) = S(n−1) + x(n)² − x(n−W)²
            sums[k] = sums[k] + (sq - ring[k, pos])
            ring[k, pos] = sq
            out[k, n] = np.sqrt(max(sums[k] * (1.0 / count), 0.0)) if not np.isnan(sums[k]) else np.nan
        pos = (pos + 1) % window
        if (n + 1) % RESYNC_SAMPLES == 0:
            sums = np.array([sum(row) for row in ring])
    return out


def exact_window_rms(x, window):
    """√(mean of the last min(n + 1, W) squares), summed afresh at every sample."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    out = np.empty_like(x)
    for n in range(x.shape[1]):
        lo = max(0, n - window + 1)
        out[:, n] = np.sqrt(np.mean(x[:, lo : n + 1] ** 2, axis=1))
    return out


def naive_bank(y, g, models, numerator, window):
    """Innovations (N, T) and window RMS (N, T) of fixed observers.

    ``models`` is a list of (b1, b0, L1, L2).
    """
    y = np.asarray(y, dtype=float)
    g = np.asarray(g, dtype=float)
    innovations = np.empty((len(models), y.shape[0]))
    for k, (b1, b0, l1, l2) in enumerate(models):
        a_mat, b_vec, c_vec, d = canonical(b1, b0, numerator)
        gain = np.array([l1, l2])
        x_hat = np.zeros(2)
        for n in range(y.shape[0]):
            # e(n) = y(n) − C x̂(n|n−1) − D g(n)
            e = y[n] - c_vec @ x_hat - d * g[n]
            # x̂(n+1|n) = A x̂(n|n−1) + B g(n) + L e(n)
            x_hat = a_mat @ x_hat + b_vec * g[n] + gain * e
            innovations[k, n] = e
    return innovations, naive_window_rms(innovations, window)


def ackermann_radial(a_mat, c_vec, radius):
    """L placing the eigenvalues of A − LC at those of A scaled to modulus ``radius``."""
    eig = np.linalg.eigvals(a_mat)
    desired = eig * (radius / np.abs(eig))
    phi = np.real(np.poly(desired))
    phi_a = a_mat @ a_mat + phi[1] * a_mat + phi[2] * np.eye(2)
    obs = np.vstack((c_vec, c_vec @ a_mat))
    return phi_a @ np.linalg.solve(obs, np.array([0.0, 1.0]))


def naive_adaptive(y, g, b1s, b0s, numerator, radius, initial, window):
    """Innovation and window RMS of the adaptive observer, and the held-sample count.

    A sample whose (b1, b0) is not an under-damped pair keeps the last valid one.
    """
    b1, b0 = initial
    x_hat = np.zeros(2)
    held = 0
    e_out = np.empty(len(y))
    for n in range(len(y)):
        if 0.0 < b0s[n] < 1.0 and b1s[n] ** 2 < 4.0 * b0s[n]:
            b1, b0 = b1s[n], b0s[n]
        else:
            held += 1
        a_mat, b_vec, c_vec, d = canonical(b1, b0, numerator)
        gain = ackermann_radial(a_mat, c_vec, radius)
        e = y[n] - c_vec @ x_hat - d * g[n]
        x_hat = a_mat @ x_hat + b_vec * g[n] + gain * e
        e_out[n] = e
    return e_out, naive_window_rms(e_out, window)[0], held
