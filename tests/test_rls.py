"""REEP and the bias-compensated least-squares estimators (afmtool.estimators.rls).

Test data come from scipy only: the free-air cantilever G(s) = ω0²/(s² + (ω0/Q)s + ω0²)
discretised by zero-order hold, driven by the three-sine dither of §3.3.2
(f0 and f0 ± 6 kHz, amplitudes A, A/2, A/2, sized for a 25 nm deflection),
sampled at 500 kHz, plus white measurement noise.  Every record starts after a
20 ms pre-roll so the plant is in its periodic steady state.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.rls import (
    ArxFit,
    ReepState,
    bcewrls,
    identify_arx,
    reep,
    reep_update,
)
from afmtool.models.discretisation import discrete_denominator, resonance_from_denominator
from tests.naive_rls import naive_bcewrls, naive_reep, naive_reep_covariance

FS_HZ = 500e3
F0_HZ = 70e3
Q0 = 200.0
SIDEBAND_HZ = 6e3
DEFLECTION_NM = 25.0
LAM = 0.995
PRE_ROLL = 10_000  # 20 ms, about 22 amplitude time constants 2Q/ω0


def plant(f0_hz: float = F0_HZ, q: float = Q0) -> tuple[tuple[float, float, float], tuple[float, float]]:
    """ZOH-discretised G(s): numerator (a2, a1, a0) and denominator (b1, b0) of eq. 3.40."""
    w0 = 2 * np.pi * f0_hz
    num, den, _ = signal.cont2discrete(([w0 * w0], [1.0, w0 / q, w0 * w0]), 1 / FS_HZ, method="zoh")
    a2, a1, a0 = np.ravel(num)
    return (float(a2), float(a1), float(a0)), (float(den[1]), float(den[2]))


def dither(n: int, *, pre: int = PRE_ROLL) -> np.ndarray:
    """Three-sine forcing A sin ω0t + A/2 sin(ω0 ± Δω)t, nm; |G(jω0)| = Q gives a 25 nm deflection."""
    t = (np.arange(n + pre) - pre) / FS_HZ
    amp = DEFLECTION_NM / Q0
    w0, dw = 2 * np.pi * F0_HZ, 2 * np.pi * SIDEBAND_HZ
    return amp * np.sin(w0 * t) + amp / 2 * np.sin((w0 + dw) * t) + amp / 2 * np.sin((w0 - dw) * t)


def record(rng, n: int, noise_nm: float, *, f0_hz: float = F0_HZ, q: float = Q0):
    """Noisy deflection p (nm), dither g, and the true numerator of a free-air record."""
    numerator, (b1, b0) = plant(f0_hz, q)
    g = dither(n)
    p = signal.lfilter(numerator, [1.0, b1, b0], g)[PRE_ROLL:]
    return p + noise_nm * rng.standard_normal(n), g[PRE_ROLL:], numerator


def tail_errors(block, first: int) -> tuple[float, float]:
    """Mean f0′ error (Hz) and relative Q′ error over samples ``first`` onwards."""
    f0, q, valid = resonance_from_denominator(block.b1[first:], block.b0[first:], FS_HZ)
    assert valid.all()
    return float(np.mean(f0) - F0_HZ), float(np.mean(q) / Q0 - 1.0)


def assert_same_block(a, b) -> None:
    for name in ("b1", "b0", "sigma2"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# ---------------------------------------------------------------------------
# (a) the kernels against the plain-Python eq. 3.39
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("noise_nm", [0.05, 0.5])
@pytest.mark.parametrize("use_input", [True, False])
def test_reep_matches_naive_reference(rng, noise_nm, use_input):
    # P0 = 0.01 is large against the steady-state P (~1e-5 for 25 nm) but keeps
    # the first update well conditioned, so the two forms agree from sample 0.
    p, g, num = record(rng, 3000, noise_nm)
    ref_c, ref_ls, ref_s2 = naive_reep(p, g, num, lam=LAM, p0=0.01, use_input=use_input)
    for bias_compensation, ref in ((True, ref_c), (False, ref_ls)):
        out = reep(p, g, num, lam=LAM, p0=0.01, bias_compensation=bias_compensation, use_input=use_input)
        np.testing.assert_allclose(out.b1, ref[:, 0], rtol=1e-12, atol=0)
        np.testing.assert_allclose(out.b0, ref[:, 1], rtol=1e-12, atol=0)
        np.testing.assert_allclose(out.sigma2, ref_s2, rtol=1e-12, atol=0, equal_nan=True)


def test_reep_matches_naive_reference_from_rest(rng):
    # The plant starts from rest: the amplitude builds up over ~1 ms.
    numerator, (b1, b0) = plant()
    g = dither(4000, pre=0)
    p = signal.lfilter(numerator, [1.0, b1, b0], g) + 0.05 * rng.standard_normal(4000)
    ref_c, _, ref_s2 = naive_reep(p, g, numerator, lam=LAM, p0=0.01)
    out = reep(p, g, numerator, lam=LAM, p0=0.01)
    np.testing.assert_allclose(out.b1, ref_c[:, 0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(out.b0, ref_c[:, 1], rtol=1e-12, atol=0)
    np.testing.assert_allclose(out.sigma2, ref_s2, rtol=1e-12, atol=0, equal_nan=True)


def test_reep_matches_naive_reference_thesis_prior(rng):
    # With P0 = 1e6 the first update computes P = P0 − (P0 − ~1e-3) and loses
    # ~7 digits in either form; forgetting then erases that error as λⁿ.  The
    # difference must stay inside that envelope and reach 1e-12.
    p, g, num = record(rng, 6000, 0.05)
    ref_c, _, ref_s2 = naive_reep(p, g, num, lam=LAM, p0=1e6)
    out = reep(p, g, num, lam=LAM, p0=1e6)
    envelope = 1e-4 * LAM ** np.arange(6000) + 1e-12
    for got, want in ((out.b1, ref_c[:, 0]), (out.b0, ref_c[:, 1]), (out.sigma2, ref_s2)):
        rel = np.abs(got[2:] - want[2:]) / np.abs(want[2:])
        assert np.all(rel <= envelope[2:]), float(np.max(rel / envelope[2:]))
        assert np.max(rel[3500:]) <= 1e-12


def test_general_kernel_matches_reep_and_naive(rng):
    p, g, num = record(rng, 3000, 0.05)
    a2, a1, a0 = num
    rows = np.column_stack((-p[1:-1], -p[:-2]))
    z = p[2:] - a2 * g[2:] - a1 * g[1:-1] - a0 * g[:-2]
    general = bcewrls(rows, z, [1, 1], lam=LAM, p0=0.01)
    two = reep(p, g, num, lam=LAM, p0=0.01)
    np.testing.assert_allclose(general.theta_c[:, 0], two.b1[2:], rtol=1e-12)
    np.testing.assert_allclose(general.theta_c[:, 1], two.b0[2:], rtol=1e-12)
    np.testing.assert_allclose(general.sigma2, two.sigma2[2:], rtol=1e-12)
    # five-parameter ARX with Λ = diag(1, 1, 0, 0, 0)
    rows5 = np.column_stack((-p[1:-1], -p[:-2], g[2:], g[1:-1], g[:-2]))
    mask = [1, 1, 0, 0, 0]
    got = bcewrls(rows5, p[2:], mask, lam=0.999, p0=1.0)
    ref_c, ref_ls, ref_s2 = naive_bcewrls(rows5, p[2:], mask, 0.999, 1.0)
    # the input block is ill-conditioned (three sines for five parameters):
    # compare relative to each coefficient's scale, not elementwise
    scale = np.abs(ref_c[-1])
    assert np.max(np.abs(got.theta_c - ref_c) / scale) < 1e-9
    assert np.max(np.abs(got.theta_ls - ref_ls) / scale) < 1e-9
    np.testing.assert_allclose(got.sigma2, ref_s2, rtol=1e-9, equal_nan=True)


def test_no_input_mode_equals_zero_numerator(rng):
    p, g, _ = record(rng, 2000, 0.05)
    with_zero = reep(p, g, (0.0, 0.0, 0.0))
    no_input = reep(p, use_input=False)
    assert_same_block(with_zero, no_input)


# ---------------------------------------------------------------------------
# (b) chunked streaming == one call, bit for bit
# ---------------------------------------------------------------------------


def run_chunked(p, g, num, sizes, **kw):
    state = ReepState.initial()
    blocks, start = [], 0
    for size in sizes:
        step = reep_update(state, p[start : start + size], g[start : start + size], num, **kw)
        blocks.append(step.block)
        state = step.state
        start += size
    assert start == len(p)
    joined = type(blocks[0])(*(np.concatenate([getattr(b, f) for b in blocks]) for f in ("b1", "b0", "sigma2")))
    return joined, state


@pytest.mark.parametrize("bias_compensation", [True, False])
def test_chunked_equals_single_call(rng, bias_compensation):
    n = 300_000
    p, g, num = record(rng, n, 0.05)
    single = reep_update(ReepState.initial(), p, g, num, bias_compensation=bias_compensation)
    for chunk in (1000, 100_000):
        sizes = [chunk] * (n // chunk)
        got, state = run_chunked(p, g, num, sizes, bias_compensation=bias_compensation)
        assert_same_block(got, single.block)
        assert state == single.state
    # irregular: one-sample chunks across the two-sample warm-up, an empty chunk
    sizes = [1, 0, 1, 1, 7, 990, 1000, 98_000, 200_000]
    got, state = run_chunked(p, g, num, sizes, bias_compensation=bias_compensation)
    assert_same_block(got, single.block)
    assert state == single.state


def test_one_sample_chunks_equal_single_call(rng):
    p, g, num = record(rng, 3000, 0.05)
    single = reep_update(ReepState.initial(), p, g, num)
    got, state = run_chunked(p, g, num, [1] * 3000)
    assert_same_block(got, single.block)
    assert state == single.state


def test_update_does_not_modify_inputs_or_state(rng):
    p, g, num = record(rng, 500, 0.05)
    p_copy, g_copy = p.copy(), g.copy()
    state = ReepState.initial()
    first = reep_update(state, p, g, num)
    assert state == ReepState.initial()
    np.testing.assert_array_equal(p, p_copy)
    np.testing.assert_array_equal(g, g_copy)
    again = reep_update(state, p, g, num)
    assert_same_block(first.block, again.block)
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.state.cost = 0.0


# ---------------------------------------------------------------------------
# (c) long runs: P stays positive definite, no divergence
# ---------------------------------------------------------------------------


def test_long_run_stays_positive_definite_and_converged(rng):
    n, chunk = 1_000_000, 100_000
    p, g, num = record(rng, n, 0.05)
    state = ReepState.initial(lam=LAM)
    for start in range(0, n, chunk):
        step = reep_update(state, p[start : start + chunk], g[start : start + chunk], num)
        state = step.state
        p11, p12, p22 = state.p_matrix
        assert p11 > 0 and p22 > 0 and p11 * p22 - p12 * p12 > 0
        assert p11 + p22 < 1e-3  # steady state ~1e-5; nowhere near the prior
        settled = slice(1000 if start == 0 else 0, None)  # skip the start-up transient
        f0, q, valid = resonance_from_denominator(step.block.b1[settled], step.block.b0[settled], FS_HZ)
        assert valid.all()
        assert np.max(np.abs(f0 - F0_HZ)) < 30.0
        assert np.max(np.abs(q / Q0 - 1)) < 0.1
    assert abs(np.mean(f0) - F0_HZ) < 1.0
    assert abs(np.mean(q) / Q0 - 1) < 0.005


# ---------------------------------------------------------------------------
# (d), (e) accuracy with the true numerator
# ---------------------------------------------------------------------------


def test_accuracy_with_true_numerator(rng):
    p, g, num = record(rng, 50_000, 0.05)  # 0.1 s
    df0, dq = tail_errors(reep(p, g, num), 25_000)
    print(f"\n0.05 nm, true numerator: f0' error {df0:+.3f} Hz, Q' error {100 * dq:+.3f} %")
    assert abs(df0) <= 2.0
    assert abs(dq) <= 0.02


def test_bias_compensation_reduces_q_error(rng):
    p, g, num = record(rng, 50_000, 0.5)
    df0_bc, dq_bc = tail_errors(reep(p, g, num), 25_000)
    df0_ls, dq_ls = tail_errors(reep(p, g, num, bias_compensation=False), 25_000)
    print(
        f"\n0.5 nm: BCEWRLS f0' {df0_bc:+.2f} Hz, Q' {100 * dq_bc:+.2f} %;"
        f" plain EWRLS f0' {df0_ls:+.2f} Hz, Q' {100 * dq_ls:+.2f} %"
    )
    # plain EWRLS is biased by −σ²R⁻¹θ: about −37 % in Q at this noise level
    assert abs(dq_ls) > 0.2
    assert abs(dq_bc) < 0.1 * abs(dq_ls)
    assert abs(df0_bc) < abs(df0_ls)


def test_sigma2_estimates_noise_variance(rng):
    for noise_nm in (0.05, 0.5):
        p, g, num = record(rng, 50_000, noise_nm)
        sigma2 = reep(p, g, num).sigma2[25_000:]
        assert np.mean(sigma2) == pytest.approx(noise_nm**2, rel=0.05)


# ---------------------------------------------------------------------------
# (f) eq. 3.48 and its inverse
# ---------------------------------------------------------------------------


def test_conversion_round_trip():
    f0 = np.array([1e3, 20e3, 57_185.0, 70e3, 71.5e3, 150e3, 240e3])[:, None]
    q = np.array([0.6, 1.0148, 5.0, 90.0, 200.0, 1e3, 1e4])[None, :]
    b1, b0 = discrete_denominator(f0, q, FS_HZ)
    f0_back, q_back, valid = resonance_from_denominator(b1, b0, FS_HZ)
    assert valid.all()
    np.testing.assert_allclose(f0_back, np.broadcast_to(f0, f0_back.shape), rtol=1e-9)
    np.testing.assert_allclose(q_back, np.broadcast_to(q, q_back.shape), rtol=1e-9)


def test_conversion_invalid_coefficients_are_nan():
    b1 = np.array([-1.27, -1.27, -1.27, -1.27, -2.0, 2.0, 1.9, np.nan, -1.27])
    b0 = np.array([0.0, -0.1, 1.0, 1.2, 1.0 - 1e-12, 0.9, 0.9, 0.99, np.nan])
    f0, q, valid = resonance_from_denominator(b1, b0, FS_HZ)
    # b0 ∉ (0, 1), |b1| ≥ 2√b0 (real poles, not a resonance), or NaN
    assert not valid.any()
    assert np.isnan(f0).all() and np.isnan(q).all()
    # the boundary |b1| = 2√b0 (critically damped) is invalid; just inside is valid
    edge = 2 * np.sqrt(0.99)
    assert not resonance_from_denominator(-edge, 0.99, FS_HZ).valid
    assert resonance_from_denominator(-edge * (1 - 1e-9), 0.99, FS_HZ).valid


# ---------------------------------------------------------------------------
# (g) free-air numerator without noise bias
# ---------------------------------------------------------------------------


def test_identify_arx_recovers_unbiased_coefficients(rng):
    numerator, (b1, b0) = plant()
    truth = np.array([b1, b0, *numerator])
    p, g, _ = record(rng, 10_000, 0.08)
    bc = identify_arx(p, g)
    ls = identify_arx(p, g, method="ls")
    assert isinstance(bc, ArxFit) and bc.method == "bcls" and bc.n_samples == 9998
    z_bc = (bc.theta - truth) / np.sqrt(np.diag(bc.covariance))
    z_ls = (ls.theta - truth) / np.sqrt(np.diag(ls.covariance))
    print(f"\nz-scores at 0.08 nm: bias-compensated {np.round(z_bc, 1)}, plain LS {np.round(z_ls, 1)}")
    assert np.all(np.abs(z_bc) < 4)
    assert np.max(np.abs(z_ls[:2])) > 8  # the AR entries are visibly biased
    assert bc.sigma2 == pytest.approx(0.08**2, rel=0.05)
    # the recursive form with λ = 1 converges to the batch one
    rec = identify_arx(p, g, method="bcewrls")
    assert np.all(np.abs(rec.theta - bc.theta) < 0.05 * np.sqrt(np.diag(bc.covariance)))


def test_identify_arx_covariance_matches_monte_carlo():
    numerator, (b1, b0) = plant()
    truth = np.array([b1, b0, *numerator])
    thetas, stderrs = [], []
    for seed in range(40):
        p, g, _ = record(np.random.default_rng(5000 + seed), 10_000, 0.05)
        fit = identify_arx(p, g)
        thetas.append(fit.theta)
        stderrs.append(np.sqrt(np.diag(fit.covariance)))
    thetas, stderrs = np.array(thetas), np.array(stderrs)
    ratio = np.std(thetas, axis=0, ddof=1) / np.mean(stderrs, axis=0)
    print(f"\nMonte Carlo std / predicted stderr: {np.round(ratio, 2)}")
    assert np.all((ratio > 0.7) & (ratio < 1.4))  # 40 draws: ±11 % sampling error
    mean_z = (np.mean(thetas, axis=0) - truth) / (np.mean(stderrs, axis=0) / np.sqrt(40))
    assert np.all(np.abs(mean_z) < 4)  # unbiased


def reep_error_with(numerator, rng, noise_nm):
    p, g, _ = record(rng, 50_000, noise_nm)
    return tail_errors(reep(p, g, numerator), 25_000)


def test_identified_numerator_gives_accurate_reep(rng):
    p, g, _ = record(rng, 10_000, 0.05)  # 0.02 s free-air segment
    fit = identify_arx(p, g)
    df0, dq = reep_error_with(fit.numerator, rng, 0.05)
    print(f"\n0.05 nm, identified numerator: f0' error {df0:+.3f} Hz, Q' error {100 * dq:+.3f} %")
    assert abs(df0) <= 1.0
    assert abs(dq) <= 0.01


def test_bias_compensated_numerator_beats_plain_ls(rng):
    p, g, _ = record(rng, 10_000, 0.08)
    test_rng_state = rng.bit_generator.state
    errors = {}
    for method in ("bcls", "ls"):
        rng.bit_generator.state = test_rng_state  # same REEP record for both
        errors[method] = reep_error_with(identify_arx(p, g, method=method).numerator, rng, 0.08)
    (f_bc, q_bc), (f_ls, q_ls) = errors["bcls"], errors["ls"]
    print(
        f"\n0.08 nm: bias-compensated numerator f0' {f_bc:+.2f} Hz, Q' {100 * q_bc:+.2f} %;"
        f" plain LS numerator f0' {f_ls:+.2f} Hz, Q' {100 * q_ls:+.2f} %"
    )
    assert abs(f_bc) < abs(f_ls) and abs(q_bc) < abs(q_ls)
    assert abs(f_ls) > 1.0 and abs(q_ls) > 0.01  # "measurably worse"


# ---------------------------------------------------------------------------
# (h) tracking a step in f0 and Q
# ---------------------------------------------------------------------------


def step_record(rng, n: int, n_switch: int, noise_nm: float):
    """Time-varying recursion: (70 kHz, 200) before ``n_switch``, (69.65 kHz, 90) after; numerator fixed."""
    (a2, a1, a0), (b1_a, b0_a) = plant()
    _, (b1_b, b0_b) = plant(F0_HZ - 350.0, 90.0)
    g = dither(n)
    p = np.zeros(n + PRE_ROLL)
    for k in range(2, n + PRE_ROLL):
        b1, b0 = (b1_b, b0_b) if k - PRE_ROLL >= n_switch else (b1_a, b0_a)
        # p(n) = −b1 p(n−1) − b0 p(n−2) + a2 g(n) + a1 g(n−1) + a0 g(n−2)     (eq. 3.40)
        p[k] = -b1 * p[k - 1] - b0 * p[k - 2] + a2 * g[k] + a1 * g[k - 1] + a0 * g[k - 2]
    return p[PRE_ROLL:] + noise_nm * rng.standard_normal(n), g[PRE_ROLL:], (a2, a1, a0)


def settling_time_s(estimate: np.ndarray, new: float, old: float) -> float:
    """Time after which the estimate stays within 10 % of the step of its new value."""
    outside = np.flatnonzero(np.abs(estimate - new) > 0.1 * abs(new - old))
    return 0.0 if outside.size == 0 else (outside[-1] + 1) / FS_HZ


def test_step_tracking(rng):
    n, n_switch = 50_000, 25_000  # the switch at t = 0.05 s
    p, g, num = step_record(rng, n, n_switch, 0.05)
    block = reep(p, g, num, lam=LAM)
    f0, q, _ = resonance_from_denominator(block.b1[n_switch:], block.b0[n_switch:], FS_HZ)
    t_f0 = settling_time_s(f0, F0_HZ - 350.0, F0_HZ)
    t_q = settling_time_s(q, 90.0, Q0)
    print(f"\nstep (−350 Hz, Q 200 → 90) at λ = {LAM}: f0' settles in {1e3 * t_f0:.2f} ms, Q' in {1e3 * t_q:.2f} ms")
    assert t_f0 <= 2e-3
    assert t_q <= 2e-3


# ---------------------------------------------------------------------------
# guards, hard cases and validation
# ---------------------------------------------------------------------------


def test_zero_gap_does_not_wind_up(rng):
    # 0.4 s without any deflection: plain eq. 3.39 would grow P as P0·λ⁻ⁿ and
    # overflow after ~0.28 s; the anti-windup keeps P at its prior instead.
    p, g, num = record(rng, 300_000, 0.05)
    p[50_000:250_000] = 0.0
    g[50_000:250_000] = 0.0
    step = reep_update(ReepState.initial(), p[:250_000], g[:250_000], num)
    p11, _, p22 = step.state.p_matrix
    assert p11 + p22 <= 2e6 / LAM and np.isfinite(step.state.cost)  # trace P(0) = 2·P0
    block = reep_update(step.state, p[250_000:], g[250_000:], num).block
    df0, dq = tail_errors(block, 25_000)
    assert abs(df0) < 2.0 and abs(dq) < 0.02


def test_nan_sample_propagates(rng):
    p, g, num = record(rng, 2000, 0.05)
    p[1000] = np.nan
    block = reep(p, g, num)
    assert np.isfinite(block.b1[2:1000]).all()
    assert np.isnan(block.b1[1000:]).all() and np.isnan(block.sigma2[1000:]).all()


def test_start_up_guard_on_pure_noise(rng):
    # White noise through the output-only AR(2): θ = 0 and σ²R⁻¹ ≈ I, so the
    # compensation is ill-posed; the guard must fire and keep θ̂ finite.
    x = rng.standard_normal(100_000)
    block = reep(x, use_input=False)
    guarded = np.isnan(block.sigma2[2:])
    assert guarded.any()
    assert np.isfinite(block.b1).all() and np.isfinite(block.b0).all()


def test_first_two_samples_only_fill_the_past(rng):
    p, g, num = record(rng, 10, 0.05)
    block = reep(p, g, num)
    np.testing.assert_array_equal(block.b1[:2], 0.0)
    assert np.isnan(block.sigma2[:2]).all() and np.isfinite(block.sigma2[2:]).all()
    state = reep_update(ReepState.initial(), p[:2], g[:2], num).state
    assert state.n_samples == 0 and state.n_past == 2 and state.p_past == (p[1], p[0], 0.0)


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"lam": 0.0}, ConfigError),
        ({"lam": 1.01}, ConfigError),
        ({"p0": -1.0}, ConfigError),
        ({"p0": float("inf")}, ConfigError),
    ],
)
def test_bad_parameters(kwargs, error):
    with pytest.raises(error, match=next(iter(kwargs))):
        reep(np.zeros(10), np.zeros(10), (0.0, 1.0, 0.0), **kwargs)


def test_bad_arrays_and_numerator():
    with pytest.raises(InputError, match="dither has 9 samples"):
        reep(np.zeros(10), np.zeros(9), (0.0, 1.0, 0.0))
    with pytest.raises(InputError, match="1-D"):
        reep(np.zeros((10, 2)), np.zeros(10), (0.0, 1.0, 0.0))
    with pytest.raises(ConfigError, match="numerator"):
        reep(np.zeros(10), np.zeros(10), (1.0, 2.0))
    with pytest.raises(ConfigError, match="required"):
        reep(np.zeros(10))
    with pytest.raises(ConfigError, match="method"):
        identify_arx(np.zeros(100), np.zeros(100), method="svd")
    with pytest.raises(InputError, match="deflection is all zeros"):
        identify_arx(np.zeros(100), np.zeros(100))
    with pytest.raises(InputError, match="rank deficient"):
        identify_arx(np.sin(np.arange(100.0)), np.ones(100))


# ---------------------------------------------------------------------------
# (d) static offset: the constant regressor θ = [b1, b0, c], Λ = diag(1, 1, 0)
# ---------------------------------------------------------------------------


def test_offset_kernel_matches_naive_reference(rng):
    p, g, num = record(rng, 3000, 0.05)
    p = p + 3.0
    ref_c, ref_ls, ref_s2 = naive_reep(p, g, num, lam=LAM, p0=0.01, static_offset=True)
    out = reep(p, g, num, lam=LAM, p0=0.01, static_offset=True)
    np.testing.assert_allclose(out.b1, ref_c[:, 0], rtol=1e-10, atol=0)
    np.testing.assert_allclose(out.b0, ref_c[:, 1], rtol=1e-10, atol=0)
    np.testing.assert_allclose(out.c[2:], ref_c[2:, 2], rtol=1e-9, atol=0)
    np.testing.assert_allclose(out.sigma2, ref_s2, rtol=1e-10, atol=0, equal_nan=True)
    plain = reep(p, g, num, lam=LAM, p0=0.01, static_offset=True, bias_compensation=False)
    np.testing.assert_allclose(plain.c[2:], ref_ls[2:, 2], rtol=1e-9, atol=0)


def test_offset_chunked_equals_single_call(rng):
    n = 50_000
    p, g, num = record(rng, n, 0.05)
    p = p + 2.0
    single = reep_update(ReepState.initial(static_offset=True), p, g, num, keep_every=7)
    state, blocks, start = ReepState.initial(static_offset=True), [], 0
    for size in [1, 0, 1, 5, 993, 9000, 40_000]:
        step = reep_update(state, p[start : start + size], g[start : start + size], num, keep_every=7)
        blocks.append(step.block)
        state = step.state
        start += size
    for field in ("b1", "b0", "sigma2", "c"):
        np.testing.assert_array_equal(np.concatenate([getattr(b, field) for b in blocks]), getattr(single.block, field))
    assert state == single.state


@pytest.mark.parametrize("offset_nm", [0.0, 5.0])
def test_offset_regressor_recovers_f0_q_under_a_static_offset(rng, offset_nm):
    # A small oscillation (1 nm) on a large static offset, the bottom of the attractive trap:
    # without the constant term eq. 3.40 cannot hold, and the fit collapses toward a pole at z = 1.
    n = 60_000
    p, g, num = record(rng, n, 0.0)
    p = p / DEFLECTION_NM + offset_nm + 0.02 * rng.standard_normal(n)
    g = g / DEFLECTION_NM
    settled = slice(10_000, None)
    with_c = reep(p, g, num, static_offset=True)
    f0, q, valid = resonance_from_denominator(with_c.b1[settled], with_c.b0[settled], FS_HZ)
    assert valid.all()
    print(f"offset {offset_nm} nm: f0 error {np.max(np.abs(f0 - F0_HZ)):.1f} Hz, mean Q {np.mean(q):.1f}")
    assert np.max(np.abs(f0 / F0_HZ - 1)) < 0.002
    assert abs(np.mean(q) / Q0 - 1) < 0.05
    # the static offset p̄ = c / (1 + b1 + b0) is recovered
    offset = with_c.c[settled] / (1 + with_c.b1[settled] + with_c.b0[settled])
    assert abs(np.median(offset) - offset_nm) < 0.05
    if offset_nm:
        without = reep(p, g, num)
        f0_plain, _, _ = resonance_from_denominator(without.b1[settled], without.b0[settled], FS_HZ)
        assert np.nanmedian(np.abs(f0_plain / F0_HZ - 1)) > 0.05  # the defect this regressor removes


@pytest.mark.parametrize("static_offset", [False, True])
@pytest.mark.parametrize("drive", [0.0, 0.14])
def test_covariance_matches_naive_reference(rng, static_offset, drive):
    """The kernels' per-row covariance equals the matrix form of its derivation (tests/naive_rls.py)."""
    p, g, num = record(rng, 3000, 0.05)
    p = p + (0.7 if static_offset else 0.0)
    state = ReepState.initial(lam=LAM, p0=1e6, static_offset=static_offset)
    block = reep_update(state, p, g, num, drive_cycles_per_sample=drive).block
    ref = naive_reep_covariance(p, g, num, lam=LAM, p0=1e6, static_offset=static_offset,
                                drive_cycles_per_sample=drive)
    assert np.isnan(block.covariance[:2]).all()
    settled = slice(500, None)
    scale = np.abs(ref[settled]).max(axis=0)
    assert np.max(np.abs(block.covariance[settled] - ref[settled]) / scale) < 1e-7
