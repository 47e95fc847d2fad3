"""Throughput of the REEP kernel (afmtool.estimators.rls).

Run as ``python bench/bench_rls.py``.  Prints samples per second of

* the numba kernel on 1e7 samples with preallocated outputs (the figure the
  target applies to: >= 50 MS/s; the reference machine gave 78 MS/s),
* the public ``reep_update`` on the same record in one call and in 2**20-sample
  chunks (these include allocating the three float64 output arrays),
* the same kernel run by CPython (``.py_func``: a pure-Python loop) on 1e4
  samples, and padasip 1.2.2 ``FilterRLS`` (plain RLS, no bias compensation)
  on 2e4 samples, both scaled per sample, measured in this run,
* eq. 3.48 conversion of the output, for scale.

As a script it exits with status 1 if the kernel is below the target; under
``python -m bench`` the numbers go to bench.json under "rls".
"""

from __future__ import annotations

import platform
import sys
import time

import numba
import numpy as np
from scipy import signal

from afmtool.estimators.rls import ReepState, _reep_kernel, reep_update
from afmtool.models.discretisation import resonance_from_denominator

FS_HZ = 500e3
F0_HZ = 70e3
Q0 = 200.0
N_KERNEL = 10_000_000
N_PYTHON = 10_000
N_PADASIP = 20_000
TARGET_MS_S = 50.0
REPEATS = 3


def make_record(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """Free-air three-sine record: deflection (nm, 0.05 nm noise), dither, ZOH numerator."""
    w0 = 2 * np.pi * F0_HZ
    num, den, _ = signal.cont2discrete(([w0 * w0], [1.0, w0 / Q0, w0 * w0]), 1 / FS_HZ, method="zoh")
    numerator = tuple(float(v) for v in np.ravel(num))
    pre = 10_000
    t = (np.arange(n + pre) - pre) / FS_HZ
    amp, dw = 25.0 / Q0, 2 * np.pi * 6e3
    g = amp * np.sin(w0 * t) + amp / 2 * np.sin((w0 + dw) * t) + amp / 2 * np.sin((w0 - dw) * t)
    p = signal.lfilter(numerator, den, g)[pre:]
    p += 0.05 * np.random.default_rng(seed).standard_normal(n)
    return p, np.ascontiguousarray(g[pre:]), numerator


def best_time(fn, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def kernel_call(kernel, p, g, numerator, state0):
    n = p.shape[0]
    out = (np.empty(n), np.empty(n), np.empty(n))
    for a in out:
        a.fill(0.0)  # touch the pages outside the timed region

    def run():
        state = state0._to_array()
        a2, a1, a0 = numerator
        # keep_every = 1: an output every sample, the kernel's full per-sample work
        kernel(p, g, a2, a1, a0, True, state0.lam, 2.0 * state0.p0, True, 1, state, *out)

    return run


def _write_results(results: dict) -> None:
    """Record in bench.json when run through ``python -m bench``."""
    try:
        from bench.common import write_results
    except ImportError:  # a plain script: bench/ is not importable as a package
        return
    write_results("rls", results)


def main() -> dict:
    print(f"python {platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, {platform.machine()}")
    results: dict = {}
    p, g, numerator = make_record(N_KERNEL)
    state0 = ReepState.initial()
    reep_update(state0, p[:1000], g[:1000], numerator)  # compile or load the cache

    t_kernel = best_time(kernel_call(_reep_kernel, p, g, numerator, state0))
    kernel_rate = N_KERNEL / t_kernel
    results["kernel_ms_per_s"] = kernel_rate / 1e6
    print(f"numba kernel, 1e7 samples, preallocated outputs: {kernel_rate / 1e6:7.1f} MS/s  ({t_kernel * 1e3:.0f} ms)")

    t_public = best_time(lambda: reep_update(state0, p, g, numerator))
    results["reep_update_one_call_ms_per_s"] = N_KERNEL / t_public / 1e6
    print(f"reep_update, one call of 1e7 samples:            {N_KERNEL / t_public / 1e6:7.1f} MS/s")

    def chunked():
        state, chunk = state0, 1 << 20
        for start in range(0, N_KERNEL, chunk):
            state = reep_update(state, p[start : start + chunk], g[start : start + chunk], numerator).state

    t_chunked = best_time(chunked)
    results["reep_update_2e20_chunks_ms_per_s"] = N_KERNEL / t_chunked / 1e6
    print(f"reep_update, 2**20-sample chunks:                {N_KERNEL / t_chunked / 1e6:7.1f} MS/s")

    t_python = best_time(kernel_call(_reep_kernel.py_func, p[:N_PYTHON], g[:N_PYTHON], numerator, state0), 1)
    python_rate = N_PYTHON / t_python
    results["pure_python_ms_per_s"] = python_rate / 1e6
    results["ratio_kernel_to_pure_python"] = kernel_rate / python_rate
    print(
        f"pure-Python loop (same kernel, CPython), 1e4:     {python_rate / 1e6:7.4f} MS/s"
        f"  -> kernel is {kernel_rate / python_rate:,.0f}x faster"
    )

    try:
        from padasip.filters import FilterRLS
    except ImportError:
        print("padasip not installed: skipped")
    else:
        a2, a1, a0 = numerator
        x = np.column_stack((-p[1 : N_PADASIP - 1], -p[: N_PADASIP - 2]))
        z = p[2:N_PADASIP] - a2 * g[2:N_PADASIP] - a1 * g[1 : N_PADASIP - 1] - a0 * g[: N_PADASIP - 2]
        flt = FilterRLS(2, mu=state0.lam, eps=1.0 / state0.p0, w="zeros")
        t0 = time.perf_counter()
        _, _, w_hist = flt.run(z, x)
        t_pada = time.perf_counter() - t0
        pada_rate = x.shape[0] / t_pada
        ours = reep_update(state0, p[:N_PADASIP], g[:N_PADASIP], numerator, bias_compensation=False).block
        # padasip records the weights before each update; ours after it
        agree = max(np.max(np.abs(w_hist[1:, 0] - ours.b1[2:-1])), np.max(np.abs(w_hist[1:, 1] - ours.b0[2:-1])))
        results["padasip_ms_per_s"] = pada_rate / 1e6
        results["ratio_kernel_to_padasip"] = kernel_rate / pada_rate
        print(
            f"padasip FilterRLS (plain RLS), 2e4 samples:      {pada_rate / 1e6:7.4f} MS/s"
            f"  -> kernel is {kernel_rate / pada_rate:,.0f}x faster"
            f"  (padasip vs our plain EWRLS: max |Δθ| = {agree:.1e})"
        )

    block = reep_update(state0, p, g, numerator).block
    t_conv = best_time(lambda: resonance_from_denominator(block.b1, block.b0, FS_HZ))
    results["conversion_ms_per_s"] = N_KERNEL / t_conv / 1e6
    print(f"eq. 3.48 conversion (numpy), 1e7 samples:        {N_KERNEL / t_conv / 1e6:7.1f} MS/s")

    results["kernel_target_met"] = bool(kernel_rate / 1e6 >= TARGET_MS_S)
    print(f"target >= {TARGET_MS_S:.0f} MS/s: {'met' if results['kernel_target_met'] else 'NOT met'}")
    _write_results(results)
    return results


if __name__ == "__main__":
    sys.exit(0 if main()["kernel_target_met"] else 1)
