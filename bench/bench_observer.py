"""Throughput of the observer kernels (afmtool.estimators.observer).

Run as ``python bench/bench_observer.py``.  Rates are input samples per
second (a bank of 5 on 1e7 samples counts 1e7, not 5e7).  Prints and records
in bench.json under "observer":

* the fused bank of 5 Kalman filters on 1e7 samples, kernel with
  preallocated outputs (the figure the target applies to: >= 40 MS/s; the
  reference machine gave 86 MS/s), and the public ``bank_update`` in one call
  and in 2**20-sample chunks (these allocate the (5, T) output);
* the single observer (innovation + window RMS), kernel and public
  ``observer_update``, against the same observer as two ``scipy.signal.lfilter``
  calls on the innovation transfer functions with ``zi`` plus a vectorised
  cumulative-sum window RMS — the choice documented in observer.py;
* the adaptive observer (per-sample model and gain) and the window RMS alone;
* filterpy's ``KalmanFilter`` (predict/update, full covariance recursion) on
  1e4 samples, scaled per sample, measured in this run.

As a script it exits with status 1 if the bank kernel is below the target.
"""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np
from scipy import signal

try:
    from bench.common import write_results
except ImportError:  # run as a plain script: bench/ is not on sys.path as a package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.common import write_results

from afmtool.estimators.observer import (
    AdaptiveState,
    BankState,
    ObserverDesign,
    ObserverState,
    WindowState,
    _adaptive_kernel,
    _bank_kernel,
    adaptive_update,
    bank_update,
    decay_radius,
    drive_period_window,
    observer_update,
    sliding_rms_update,
    state_space,
)
from afmtool.models.discretisation import discrete_denominator, zoh_numerator

FS_HZ = 500e3
F0_HZ = 70e3
Q0 = 200.0
BANK_F0_HZ = (69.6e3, 69.8e3, 70.0e3, 70.2e3, 70.4e3)
BANK_Q = (170.0, 185.0, 200.0, 215.0, 230.0)
PROCESS_NM = 0.005
NOISE_NM = 0.05
N_KERNEL = 10_000_000
N_FILTERPY = 10_000
TARGET_MS_S = 40.0
REPEATS = 5


def make_record(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Free-air three-sine record at 500 kHz: deflection (nm, 0.05 nm noise) and dither."""
    numerator = tuple(zoh_numerator(F0_HZ, Q0, FS_HZ))
    b1, b0 = discrete_denominator(F0_HZ, Q0, FS_HZ)
    pre = 10_000
    t = (np.arange(n + pre) - pre) / FS_HZ
    w0, dw = 2 * np.pi * F0_HZ, 2 * np.pi * 6e3
    amp = 25.0 / Q0
    g = amp * np.sin(w0 * t) + amp / 2 * np.sin((w0 + dw) * t) + amp / 2 * np.sin((w0 - dw) * t)
    p = signal.lfilter(numerator, [1.0, b1, b0], g)[pre:]
    p += NOISE_NM * np.random.default_rng(seed).standard_normal(n)
    return p, np.ascontiguousarray(g[pre:])


def best_time(fn, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bank_kernel_call(state: BankState, y: np.ndarray, g: np.ndarray, keep_innovation: bool):
    """The bank kernel alone, outputs allocated and touched outside the timed region."""
    n_obs, n = len(state.designs), y.shape[0]
    out_rms = np.zeros((n_obs, n))
    out_e = np.zeros((n_obs, n if keep_innovation else 0))
    a2, b1, b0, bb1, bb2, l1, l2 = state._coefficients()

    def run():
        xhat = np.array(state.estimate)
        ring, sums, counters = state.window._unpack()
        _bank_kernel(y, g, a2, b1, b0, bb1, bb2, l1, l2, xhat, ring, sums, counters, out_rms, out_e)

    return run


def lfilter_observer(design: ObserverDesign, window: int):
    """The same observer as E = H_y·Y − H_g·G by lfilter with carried zi, and a cumsum window RMS."""
    y_num, g_num, den = design.innovation_filters()

    def run(y, g, zi_y, zi_g, tail):
        e_y, zi_y = signal.lfilter(y_num, den, y, zi=zi_y)
        e_g, zi_g = signal.lfilter(g_num, den, g, zi=zi_g)
        e = e_y - e_g
        # boxcar sum of the last W squares, with the W − 1 squares of the previous chunk carried
        c = np.cumsum(np.concatenate((tail, e * e)))
        c = np.concatenate(([0.0], c))
        s = c[window:] - c[:-window]
        rms = np.sqrt(np.maximum(s / window, 0.0))
        return e, rms, zi_y, zi_g, (e * e)[-(window - 1) :]

    return run


def main() -> dict:  # noqa: PLR0915 - a benchmark script: one printed table, top to bottom
    print(f"python {platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, {platform.machine()}")
    results: dict = {}
    y, g = make_record(N_KERNEL)
    numerator = tuple(zoh_numerator(F0_HZ, Q0, FS_HZ))
    window = drive_period_window(FS_HZ, F0_HZ)
    designs = [
        ObserverDesign.from_kalman(tuple(discrete_denominator(f, q, FS_HZ)), numerator, PROCESS_NM, NOISE_NM)
        for f, q in zip(BANK_F0_HZ, BANK_Q)
    ]
    bank0 = BankState.initial(designs, window)
    single0 = ObserverState.initial(designs[2], window)
    bank_update(bank0, y[:1000], g[:1000])  # compile or load the cache
    observer_update(single0, y[:1000], g[:1000])

    # --- bank of 5 ---------------------------------------------------------
    t_bank = best_time(bank_kernel_call(bank0, y, g, False))
    bank_rate = N_KERNEL / t_bank
    results["bank5_kernel_ms_per_s"] = bank_rate / 1e6
    print(f"bank of 5, kernel, 1e7 samples, RMS out (5, T):   {bank_rate / 1e6:7.1f} MS/s  ({t_bank * 1e3:.0f} ms)")
    t_bank_e = best_time(bank_kernel_call(bank0, y, g, True))
    results["bank5_kernel_with_innovation_ms_per_s"] = N_KERNEL / t_bank_e / 1e6
    print(f"bank of 5, kernel, RMS and innovation out:         {N_KERNEL / t_bank_e / 1e6:7.1f} MS/s")
    t_public = best_time(lambda: bank_update(bank0, y, g), 3)
    results["bank5_update_one_call_ms_per_s"] = N_KERNEL / t_public / 1e6
    print(f"bank_update, one call of 1e7 (allocates 400 MB):   {N_KERNEL / t_public / 1e6:7.1f} MS/s")

    def bank_chunked():
        state, chunk = bank0, 1 << 20
        for start in range(0, N_KERNEL, chunk):
            state = bank_update(state, y[start : start + chunk], g[start : start + chunk]).state

    t_chunked = best_time(bank_chunked, 3)
    results["bank5_update_2e20_chunks_ms_per_s"] = N_KERNEL / t_chunked / 1e6
    print(f"bank_update, 2**20-sample chunks:                  {N_KERNEL / t_chunked / 1e6:7.1f} MS/s")

    # --- single observer: numba kernel vs lfilter --------------------------
    t_single = best_time(bank_kernel_call(BankState.initial(designs[2:3], window), y, g, True))
    single_rate = N_KERNEL / t_single
    results["single_kernel_ms_per_s"] = single_rate / 1e6
    print(f"single observer, kernel (innovation + RMS):        {single_rate / 1e6:7.1f} MS/s")
    t_single_pub = best_time(lambda: observer_update(single0, y, g), 3)
    results["single_update_one_call_ms_per_s"] = N_KERNEL / t_single_pub / 1e6
    print(f"observer_update, one call of 1e7:                  {N_KERNEL / t_single_pub / 1e6:7.1f} MS/s")

    run_lfilter = lfilter_observer(designs[2], window)
    zeros = np.zeros(2)
    tail0 = np.zeros(window - 1)
    t_lf = best_time(lambda: run_lfilter(y, g, zeros, zeros, tail0), 3)
    lf_rate = N_KERNEL / t_lf
    results["single_lfilter_ms_per_s"] = lf_rate / 1e6
    results["ratio_single_kernel_to_lfilter"] = single_rate / lf_rate
    y_num, g_num, den = designs[2].innovation_filters()

    def lfilter_innovation_only():
        e_y, _ = signal.lfilter(y_num, den, y, zi=zeros)
        e_g, _ = signal.lfilter(g_num, den, g, zi=zeros)
        return e_y - e_g

    t_lf_e = best_time(lfilter_innovation_only, 3)
    results["single_lfilter_innovation_only_ms_per_s"] = N_KERNEL / t_lf_e / 1e6
    print(f"single observer, 2x lfilter, innovation only:      {N_KERNEL / t_lf_e / 1e6:7.1f} MS/s")
    e_lf, rms_lf, *_ = run_lfilter(y, g, zeros, zeros, tail0)
    ours = observer_update(single0, y, g).block
    agree_e = float(np.max(np.abs(e_lf - ours.innovation)))
    agree_rms = float(np.max(np.abs(rms_lf[window:] - ours.rms[window:])))
    results["lfilter_agreement_innovation_nm"] = agree_e
    results["lfilter_agreement_rms_nm"] = agree_rms
    print(
        f"single observer, 2x lfilter + cumsum RMS:          {lf_rate / 1e6:7.1f} MS/s"
        f"  -> kernel is {single_rate / lf_rate:.1f}x faster  (max |Δe| = {agree_e:.1e} nm, |Δrms| = {agree_rms:.1e} nm)"
    )

    # --- adaptive observer and window RMS ----------------------------------
    b1s = np.full(N_KERNEL, designs[2].denominator[0])
    b0s = np.full(N_KERNEL, designs[2].denominator[1])
    radius = decay_radius(4.0, FS_HZ / F0_HZ)
    adaptive0 = AdaptiveState.initial(numerator, designs[2].denominator, radius, window)
    adaptive_update(adaptive0, y[:1000], g[:1000], b1s[:1000], b0s[:1000])
    out_rms, out_e = np.zeros(N_KERNEL), np.zeros(N_KERNEL)
    a2, a1, a0 = numerator

    def adaptive_kernel():
        ring, sums, counters = adaptive0.window._unpack()
        model = np.array([*adaptive0.model, 0.0])
        _adaptive_kernel(y, g, b1s, b0s, a2, a1, a0, radius, model, np.zeros(2), ring, sums, counters, out_rms, out_e)

    t_adapt = best_time(adaptive_kernel)
    results["adaptive_kernel_ms_per_s"] = N_KERNEL / t_adapt / 1e6
    print(f"adaptive observer, kernel (gain every sample):     {N_KERNEL / t_adapt / 1e6:7.1f} MS/s")
    rms0 = WindowState.initial(1, window)
    sliding_rms_update(rms0, y[:100])
    t_rms = best_time(lambda: sliding_rms_update(rms0, y), 3)
    results["sliding_rms_update_ms_per_s"] = N_KERNEL / t_rms / 1e6
    print(f"sliding_rms_update, 1 channel:                     {N_KERNEL / t_rms / 1e6:7.1f} MS/s")

    # --- filterpy ------------------------------------------------------------
    try:
        from filterpy.kalman import KalmanFilter
    except ImportError:
        print("filterpy not installed: skipped")
    else:
        ss = state_space(*designs[2].denominator, numerator)
        kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
        kf.F, kf.B, kf.H = ss.A.copy(), ss.B.reshape(2, 1).copy(), ss.C.reshape(1, 2).copy()
        kf.Q = PROCESS_NM**2 * np.outer(ss.B, ss.B)
        kf.R = np.array([[NOISE_NM**2]])
        e_fp = np.empty(N_FILTERPY)
        u = g[:N_FILTERPY].reshape(-1, 1, 1)
        t0 = time.perf_counter()
        for i in range(N_FILTERPY):
            kf.update(y[i])
            e_fp[i] = kf.y[0, 0]
            kf.predict(u=u[i])
        t_fp = time.perf_counter() - t0
        fp_rate = N_FILTERPY / t_fp
        tail = slice(N_FILTERPY // 2, N_FILTERPY)
        agree = float(np.max(np.abs(e_fp[tail] - ours.innovation[:N_FILTERPY][tail])))
        results["filterpy_ms_per_s"] = fp_rate / 1e6
        results["ratio_single_kernel_to_filterpy"] = single_rate / fp_rate
        results["ratio_bank5_kernel_to_5_filterpy"] = 5 * bank_rate / fp_rate
        results["filterpy_agreement_after_convergence_nm"] = agree
        print(
            f"filterpy KalmanFilter, 1e4 samples:                {fp_rate / 1e6:7.4f} MS/s"
            f"  -> single kernel {single_rate / fp_rate:,.0f}x, bank of 5 {5 * bank_rate / fp_rate:,.0f}x faster"
            f"  (max |Δe| after convergence = {agree:.1e} nm)"
        )

    results["bank5_target_ms_per_s"] = TARGET_MS_S
    results["bank5_target_met"] = bool(bank_rate / 1e6 >= TARGET_MS_S)
    print(f"bank target >= {TARGET_MS_S:.0f} MS/s: {'met' if results['bank5_target_met'] else 'NOT met'}")
    write_results("observer", results)
    return results


if __name__ == "__main__":
    sys.exit(0 if main()["bank5_target_met"] else 1)
