"""Observers, Kalman bank and adaptive observer (afmtool.estimators.observer).

Test data come from scipy: the free-air cantilever G(s) = ω0²/(s² + (ω0/Q)s + ω0²)
at f0 = 70 kHz, Q = 200, discretised by zero-order hold (``cont2discrete``) at
fs = 500 kHz, driven by a three-sine dither (f0 and f0 ± 6 kHz, amplitudes A,
A/2, A/2, sized for a 25 nm deflection), with white measurement noise and,
where stated, white process noise entering with the dither.  Plants that
switch model are simulated by ``lfilter`` segments with carried ``zi``; the
swept plant takes its denominators from ``discrete_denominator`` (checked
against ``cont2discrete`` in tests/test_sim.py and spot-checked here).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.observer import (
    AdaptiveState,
    BankState,
    ObserverDesign,
    ObserverState,
    WindowState,
    adaptive_update,
    bank_update,
    decay_radius,
    drive_period_window,
    gain_for_decay,
    kalman_gain,
    observer_update,
    sliding_rms_update,
    state_space,
)
from afmtool.models.discretisation import discrete_denominator
from tests.naive_observer import exact_window_rms, naive_adaptive, naive_bank, naive_window_rms

FS_HZ = 500e3
F0_HZ = 70e3
Q0 = 200.0
SIDEBAND_HZ = 6e3
DEFLECTION_NM = 25.0
NOISE_NM = 0.05
PERIOD = FS_HZ / F0_HZ  # drive period, samples (7.14)
WINDOW = drive_period_window(FS_HZ, F0_HZ)  # 7
PRE_ROLL = 10_000  # 20 ms, 22 amplitude time constants 2Q/ω0
BANK_F0_HZ = (69.6e3, 69.8e3, 70.0e3, 70.2e3, 70.4e3)
BANK_Q = (170.0, 185.0, 200.0, 215.0, 230.0)


def discretise(f0_hz: float = F0_HZ, q: float = Q0, method: str = "zoh"):
    """Numerator (a2, a1, a0) and denominator (b1, b0) of eq. 3.40 by ``cont2discrete``."""
    w0 = 2 * np.pi * f0_hz
    num, den, _ = signal.cont2discrete(([w0 * w0], [1.0, w0 / q, w0 * w0]), 1 / FS_HZ, method=method)
    a2, a1, a0 = np.ravel(num)
    return (float(a2), float(a1), float(a0)), (float(den[1]), float(den[2]))


NUMERATOR, DENOMINATOR = discretise()
BANK_DENOMINATORS = [discretise(f, q)[1] for f, q in zip(BANK_F0_HZ, BANK_Q)]


def three_sine(n: int, *, pre: int = 0) -> np.ndarray:
    """A sin ω0t + A/2 sin(ω0 ± Δω)t, A = 25 nm/Q; ``pre`` samples before t = 0 included."""
    t = (np.arange(n + pre) - pre) / FS_HZ
    amp = DEFLECTION_NM / Q0
    w0, dw = 2 * np.pi * F0_HZ, 2 * np.pi * SIDEBAND_HZ
    return amp * np.sin(w0 * t) + amp / 2 * np.sin((w0 + dw) * t) + amp / 2 * np.sin((w0 - dw) * t)


def free_air_record(rng, n: int, *, noise_nm: float = NOISE_NM, numerator=NUMERATOR, denominator=DENOMINATOR):
    """Steady-state deflection (nm) of the plant, with measurement noise, and its dither."""
    g = three_sine(n, pre=PRE_ROLL)
    p = signal.lfilter(numerator, [1.0, *denominator], g)[PRE_ROLL:]
    return p + noise_nm * rng.standard_normal(n), g[PRE_ROLL:]


def switching_plant(g: np.ndarray, pieces: list, numerator=NUMERATOR) -> np.ndarray:
    """Deflection of a plant with denominator ``den`` for ``count`` samples, for each (den, count) in turn.

    One lfilter per piece with the state carried: x(n+1) = A(n)x(n) + B(n)g(n)
    in the realisation of observer.py (the lfilter ``zi`` is that state).
    """
    out = np.empty_like(g)
    zi = np.zeros(2)
    start = 0
    for (b1, b0), count in pieces:
        sl = slice(start, start + count)
        out[sl], zi = signal.lfilter(numerator, [1.0, b1, b0], g[sl], zi=zi)
        start += count
    assert start == g.shape[0]
    return out


def decay_designs(cycles: float = 4.0):
    return [ObserverDesign.from_decay(den, NUMERATOR, cycles, PERIOD) for den in BANK_DENOMINATORS]


def kalman_designs(process_nm: float, measurement_nm: float):
    return [ObserverDesign.from_kalman(den, NUMERATOR, process_nm, measurement_nm) for den in BANK_DENOMINATORS]


def split_points(rng, n: int) -> list[int]:
    """Chunk boundaries with chunks of 0, 1, a few and many samples."""
    cuts = sorted({0, 1, 2, 5, 1023, 1024, 1500, *rng.integers(0, n, 6).tolist(), n})
    return [c for c in cuts if c <= n]


# ---------------------------------------------------------------------------
# Realisation and gains
# ---------------------------------------------------------------------------


def test_state_space_is_lfilter_direct_form(rng):
    """x(n+1) = Ax + Bg, p = Cx + Dg reproduces lfilter, and its state is lfilter's zi."""
    numerator, denominator = discretise(method="bilinear")  # a2 ≠ 0: D is exercised
    ss = state_space(*denominator, numerator)
    g = rng.standard_normal(500)
    x = np.zeros(2)
    p = np.empty_like(g)
    for n, gn in enumerate(g):
        p[n] = ss.C @ x + ss.D * gn
        x = ss.A @ x + ss.B * gn
    ref, zf = signal.lfilter(numerator, [1.0, *denominator], g, zi=np.zeros(2))
    np.testing.assert_allclose(p, ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))
    np.testing.assert_allclose(x, zf, rtol=0, atol=1e-12 * np.max(np.abs(zf)))


@pytest.mark.parametrize("residual", [math.exp(-1), 0.01])
def test_gain_for_decay_places_poles_radially(residual):
    """Eigenvalues of A − LC: the model's angle, modulus r = residual^(1/(N·P)); closed form = Ackermann."""
    ss = state_space(*DENOMINATOR, NUMERATOR)
    gain = gain_for_decay(ss.A, ss.C, 4.0, PERIOD, residual=residual)
    r = decay_radius(4.0, PERIOD, residual)
    assert r ** (4.0 * PERIOD) == pytest.approx(residual, rel=1e-12)
    poles = np.linalg.eigvals(ss.A - np.outer(gain, ss.C))
    model_poles = np.linalg.eigvals(ss.A)
    np.testing.assert_allclose(np.abs(poles), r, rtol=1e-12)
    np.testing.assert_allclose(np.sort(np.angle(poles)), np.sort(np.angle(model_poles)), rtol=1e-10)
    b1, b0 = DENOMINATOR
    # closed form in canonical coordinates: L1 = b1(r/√b0 − 1), L2 = r² − b0
    np.testing.assert_allclose(gain, [b1 * (r / math.sqrt(b0) - 1.0), r * r - b0], rtol=1e-9, atol=1e-15)
    # any other realisation (A' = TAT⁻¹, C' = CT⁻¹) gets the same error poles
    t = np.array([[2.0, 0.3], [-0.5, 1.5]])
    a_t = t @ ss.A @ np.linalg.inv(t)
    c_t = ss.C @ np.linalg.inv(t)
    gain_t = gain_for_decay(a_t, c_t, 4.0, PERIOD, residual=residual)
    poles_t = np.linalg.eigvals(a_t - np.outer(gain_t, c_t))
    np.testing.assert_allclose(np.sort_complex(poles_t), np.sort_complex(poles), rtol=1e-9)


@pytest.mark.parametrize("method", ["zoh", "bilinear"])
def test_kalman_gain_solves_the_riccati_equation(method):
    """P = APAᵀ + Q − (APCᵀ + S)(CPCᵀ + R)⁻¹(…)ᵀ with the cross term of a direct feed-through."""
    numerator, denominator = discretise(method=method)
    ss = state_space(*denominator, numerator)
    sw, sv, k_in = 0.03, 0.05, 2.0
    kal = kalman_gain(ss, sw, sv, input_gain=k_in)
    bw, dw = ss.B / k_in, ss.D / k_in
    q = sw**2 * np.outer(bw, bw)
    r = sv**2 + sw**2 * dw**2
    s = sw**2 * bw * dw
    p = kal.covariance
    apc = ss.A @ p @ ss.C + s
    se = ss.C @ p @ ss.C + r
    residual = ss.A @ p @ ss.A.T + q - np.outer(apc, apc) / se - p
    assert np.max(np.abs(residual)) < 1e-10 * np.max(np.abs(p))
    assert kal.innovation_variance == pytest.approx(se, rel=1e-12)
    np.testing.assert_allclose(kal.gain, apc / se, rtol=1e-12)
    poles = np.linalg.eigvals(ss.A - np.outer(kal.gain, ss.C))
    assert np.max(np.abs(poles)) < 1.0
    # no process noise: the open-loop predictor of a stable model
    assert np.max(np.abs(kalman_gain(ss, 0.0, sv).gain)) < 1e-12


# ---------------------------------------------------------------------------
# Kernels against the plain-Python reference; streaming
# ---------------------------------------------------------------------------


def test_bank_kernel_matches_naive(rng):
    """Fused bank (5 observers, mixed gains) = per-observer numpy reference, 1e-12 nm (RMS 1e-12·max)."""
    y, g = free_air_record(rng, 3000)  # crosses two exact re-summations of the window
    designs = decay_designs()[:3] + kalman_designs(0.02, NOISE_NM)[3:]
    step = bank_update(BankState.initial(designs, WINDOW), y, g, keep_innovation=True)
    models = [(*d.denominator, *d.gain) for d in designs]
    e_ref, rms_ref = naive_bank(y, g, models, NUMERATOR, WINDOW)
    np.testing.assert_allclose(step.block.innovation, e_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(step.block.rms, rms_ref, rtol=0, atol=1e-12 * np.max(rms_ref))
    # the bank without innovations gives the same RMS
    rms_only = bank_update(BankState.initial(designs, WINDOW), y, g).block
    assert rms_only.innovation is None
    np.testing.assert_array_equal(rms_only.rms, step.block.rms)


def test_adaptive_kernel_matches_naive(rng):
    """Adaptive observer (closed-form gain, held invalid models) = Ackermann reference, 1e-12 nm (RMS 1e-12·max)."""
    n = 2500
    y, g = free_air_record(rng, n)
    f0 = np.linspace(69.5e3, 70.5e3, n)
    b1s = np.array([discretise(f, Q0)[1][0] for f in f0[::50]]).repeat(50)
    b0s = np.array([discretise(f, Q0)[1][1] for f in f0[::50]]).repeat(50)
    b1s[:2] = b0s[:2] = 0.0  # REEP start-up: θ = 0
    b1s[700:705] = np.nan
    b0s[1200] = 1.5  # not a pole pair of a damped mode
    r = decay_radius(4.0, PERIOD)
    state = AdaptiveState.initial(NUMERATOR, DENOMINATOR, r, WINDOW)
    step = adaptive_update(state, y, g, b1s, b0s)
    e_ref, rms_ref, held = naive_adaptive(y, g, b1s, b0s, NUMERATOR, r, DENOMINATOR, WINDOW)
    np.testing.assert_allclose(step.block.innovation, e_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(step.block.rms, rms_ref, rtol=0, atol=1e-12 * np.max(rms_ref))
    assert step.state.held_samples == held == 8


def test_adaptive_with_constant_model_equals_fixed_observer(rng):
    """Fed a constant (b1, b0), the adaptive observer is the fixed decay observer (1e-12 nm, RMS 1e-12·max)."""
    y, g = free_air_record(rng, 4000)
    design = ObserverDesign.from_decay(DENOMINATOR, NUMERATOR, 4.0, PERIOD)
    fixed = observer_update(ObserverState.initial(design, WINDOW), y, g).block
    b1s = np.full(y.shape, DENOMINATOR[0])
    b0s = np.full(y.shape, DENOMINATOR[1])
    state = AdaptiveState.initial(NUMERATOR, DENOMINATOR, decay_radius(4.0, PERIOD), WINDOW)
    adaptive = adaptive_update(state, y, g, b1s, b0s).block
    np.testing.assert_allclose(adaptive.innovation, fixed.innovation, rtol=0, atol=1e-12)
    # rounding differences of 1e-15 in e move S by ε·max S, i.e. rms by ε·max S/(2W·rms):
    # the RMS comparisons are relative to the largest RMS
    np.testing.assert_allclose(adaptive.rms, fixed.rms, rtol=0, atol=1e-12 * np.max(fixed.rms))


def test_innovation_equals_its_transfer_functions(rng):
    """e = H_y(z)·y − H_g(z)·g (module docstring), by lfilter, 1e-12 nm; a2 ≠ 0 included."""
    numerator, denominator = discretise(method="bilinear")
    y, g = free_air_record(rng, 5000, numerator=numerator, denominator=denominator)
    design = ObserverDesign.from_kalman(denominator, numerator, 0.02, NOISE_NM)
    block = observer_update(ObserverState.initial(design, WINDOW), y, g).block
    hy_num, hg_num, den = design.innovation_filters()
    ref = signal.lfilter(hy_num, den, y) - signal.lfilter(hg_num, den, g)
    np.testing.assert_allclose(block.innovation, ref, rtol=0, atol=1e-12)


def test_window_rms_is_the_boxcar(rng):
    """Observer RMS = sliding_rms_update(innovation) exactly = textbook boxcar to 1e-9·max."""
    y, g = free_air_record(rng, 5000)
    design = ObserverDesign.from_decay(BANK_DENOMINATORS[0], NUMERATOR, 4.0, PERIOD)  # mismatched: large e
    block = observer_update(ObserverState.initial(design, WINDOW), y, g).block
    rms = sliding_rms_update(WindowState.initial(1, WINDOW), block.innovation).rms
    np.testing.assert_array_equal(rms, block.rms)
    np.testing.assert_allclose(rms, naive_window_rms(block.innovation, WINDOW)[0], rtol=0, atol=1e-12)
    exact = exact_window_rms(block.innovation, WINDOW)[0]
    # running-sum rounding: |ΔS| ≲ 1024·ε·max S, so |Δrms| ≤ |ΔS|/(2·rms) stays ≪ 1e-9·max rms here
    np.testing.assert_allclose(rms, exact, rtol=0, atol=1e-9 * np.max(exact))
    x = rng.standard_normal((3, 4000)) * np.array([[1.0], [1e-6], [1e3]])
    out = sliding_rms_update(WindowState.initial(3, 50), x).rms
    np.testing.assert_allclose(out, exact_window_rms(x, 50), rtol=1e-9)


def test_chunked_equals_single_call(rng):
    """Every update, split at arbitrary points (chunks of 0, 1, …), equals one call bit for bit."""
    n = 6000
    y, g = free_air_record(rng, n)
    cuts = split_points(rng, n)
    b1s = np.full(n, BANK_DENOMINATORS[1][0]) + 1e-6 * rng.standard_normal(n)
    b0s = np.full(n, BANK_DENOMINATORS[1][1])
    r = decay_radius(3.0, PERIOD)
    designs = decay_designs()
    runs = {
        "bank": (BankState.initial(designs, WINDOW), lambda s, sl: bank_update(s, y[sl], g[sl], keep_innovation=True)),
        "observer": (ObserverState.initial(designs[2], WINDOW), lambda s, sl: observer_update(s, y[sl], g[sl])),
        "adaptive": (
            AdaptiveState.initial(NUMERATOR, DENOMINATOR, r, WINDOW),
            lambda s, sl: adaptive_update(s, y[sl], g[sl], b1s[sl], b0s[sl]),
        ),
        "rms": (WindowState.initial(1, WINDOW), lambda s, sl: ((sliding_rms_update(s, y[sl]).rms,), sliding_rms_update(s, y[sl]).state)),
    }
    for name, (state0, run) in runs.items():
        whole = run(state0, slice(0, n))
        state, parts = state0, []
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            step = run(state, slice(lo, hi))
            parts.append(step)
            state = step[1]
        for field in range(len(whole[0])):
            expect = whole[0][field]
            got = np.concatenate([p[0][field] for p in parts], axis=-1)
            np.testing.assert_array_equal(got, expect, err_msg=f"{name} field {field}")
        if name != "rms":
            np.testing.assert_array_equal(state.estimate, whole[1].estimate)


def test_inputs_are_not_modified(rng):
    y, g = free_air_record(rng, 100)
    y0, g0 = y.copy(), g.copy()
    state = BankState.initial(decay_designs(), WINDOW)
    est0 = state.estimate.copy()
    bank_update(state, y, g)
    np.testing.assert_array_equal(y, y0)
    np.testing.assert_array_equal(g, g0)
    np.testing.assert_array_equal(state.estimate, est0)
    assert state.window.filled == 0


# ---------------------------------------------------------------------------
# Behaviour: decay, Kalman statistics, bank minimum, adaptive
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(("cycles", "residual"), [(2.0, math.exp(-1)), (4.0, math.exp(-1)), (3.0, 0.01)])
def test_matched_observer_error_decays_as_designed(cycles, residual):
    """Plant = model, no noise, x̂(0) = 0: |e| envelope falls by ``residual`` per ``cycles`` periods."""
    n = 4000
    g = three_sine(n, pre=PRE_ROLL)
    y = signal.lfilter(NUMERATOR, [1.0, *DENOMINATOR], g)[PRE_ROLL:]
    g = g[PRE_ROLL:]
    design = ObserverDesign.from_decay(DENOMINATOR, NUMERATOR, cycles, PERIOD, residual=residual)
    e = observer_update(ObserverState.initial(design, WINDOW), y, g).block.innovation
    r = decay_radius(cycles, PERIOD, residual)
    # the free response is r^n (α cos nθ + β sin nθ): e·r^−n is a sinusoid of constant amplitude
    span = int(round(cycles * PERIOD))
    flat = np.abs(e[: 6 * span]) / r ** np.arange(6 * span)
    peaks = [np.max(flat[j * span : (j + 1) * span]) for j in range(6)]
    np.testing.assert_allclose(peaks, peaks[0], rtol=0.02)
    # so the envelope after N periods is residual times the first period's
    first = np.max(np.abs(e[:span]))
    later = np.max(np.abs(e[span : 2 * span]))
    assert later / first == pytest.approx(residual, rel=0.1)
    # and the innovation goes to rounding level
    assert np.max(np.abs(e[-500:])) < 1e-10 * DEFLECTION_NM


@pytest.mark.parametrize("method", ["zoh", "bilinear"])
def test_kalman_innovation_is_white_with_predicted_variance(rng, method):
    """Process + measurement noise: var e = CPCᵀ + R (5 %), |autocorrelation| < 5/√N at lags 1-20."""
    numerator, denominator = discretise(method=method)
    n, burn = 200_000, 5_000
    sw, sv = 0.05, NOISE_NM
    g = three_sine(n + burn, pre=PRE_ROLL)
    w = sw * rng.standard_normal(g.shape)
    y = signal.lfilter(numerator, [1.0, *denominator], g + w)[PRE_ROLL:]
    y += sv * rng.standard_normal(y.shape)
    g = g[PRE_ROLL:]
    kal = kalman_gain(state_space(*denominator, numerator), sw, sv)
    design = ObserverDesign.from_kalman(denominator, numerator, sw, sv)
    e = observer_update(ObserverState.initial(design, WINDOW), y, g).block.innovation[burn:]
    assert np.var(e) == pytest.approx(kal.innovation_variance, rel=0.05)
    ec = e - e.mean()
    acf = np.array([ec[:-k] @ ec[k:] for k in range(1, 21)]) / (ec @ ec)
    assert np.max(np.abs(acf)) < 5 / math.sqrt(e.size)


def test_kalman_matches_filterpy_after_convergence(rng):
    """filterpy's full covariance recursion converges to our steady gain and innovations."""
    kalman = pytest.importorskip("filterpy.kalman")
    n = 5_000
    sw, sv = 0.05, NOISE_NM
    g = three_sine(n, pre=PRE_ROLL)
    y = signal.lfilter(NUMERATOR, [1.0, *DENOMINATOR], g + sw * rng.standard_normal(g.shape))[PRE_ROLL:]
    y += sv * rng.standard_normal(n)
    g = g[PRE_ROLL:]
    ss = state_space(*DENOMINATOR, NUMERATOR)  # ZOH: D = 0, as filterpy assumes
    kal = kalman_gain(ss, sw, sv)
    kf = kalman.KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    kf.F = ss.A.copy()
    kf.B = ss.B.reshape(2, 1).copy()
    kf.H = ss.C.reshape(1, 2).copy()
    kf.Q = sw**2 * np.outer(ss.B, ss.B)
    kf.R = np.array([[sv**2]])
    kf.P = 100.0 * np.eye(2)
    e_fp = np.empty(n)
    for i in range(n):
        kf.update(y[i])  # innovation y(n) − H x̂(n|n−1)
        e_fp[i] = kf.y[0, 0]
        kf.predict(u=np.array([[g[i]]]))  # x̂(n+1|n) = F x̂(n|n) + B g(n)
    design = ObserverDesign.from_kalman(DENOMINATOR, NUMERATOR, sw, sv)
    e = observer_update(ObserverState.initial(design, WINDOW), y, g).block.innovation
    # steady state: L = A K and P(n+1|n) → P
    np.testing.assert_allclose(ss.A @ kf.K[:, 0], kal.gain, rtol=1e-10)
    np.testing.assert_allclose(kf.P_prior, kal.covariance, rtol=1e-10)
    # from P(0) = 100·I the gain converges within ~100 samples (|error poles| = 0.68/period);
    # after 1000 samples the innovations agree to rounding
    tail = slice(1000, n)
    assert np.max(np.abs(e[tail] - e_fp[tail])) < 1e-9 * np.std(e[tail])


def test_bank_minimum_follows_the_plant_model(rng):
    """Eq. 3.51: the matching filter has the least RMS, and the minimum moves when the plant switches."""
    segment, settle = 20_000, 5_000
    order = [2, 0, 4, 1]
    n = segment * len(order)
    g = three_sine(n, pre=PRE_ROLL)
    pieces = [(BANK_DENOMINATORS[order[0]], PRE_ROLL)] + [(BANK_DENOMINATORS[j], segment) for j in order]
    y = switching_plant(g, pieces)[PRE_ROLL:] + NOISE_NM * rng.standard_normal(n)
    g = g[PRE_ROLL:]
    rms = bank_update(BankState.initial(kalman_designs(0.005, NOISE_NM), WINDOW), y, g).block.rms
    for j, model in enumerate(order):
        seg = rms[:, j * segment + settle : (j + 1) * segment]
        mean_square = np.mean(seg**2, axis=1)
        assert int(np.argmin(mean_square)) == model, f"segment {j}: {mean_square}"
        # matched: white noise only, var e = CPCᵀ + R ≈ R; the others carry A_e (eq. 5.14)
        assert mean_square[model] < 1.5 * NOISE_NM**2
        assert np.sort(mean_square)[1] > 10 * mean_square[model]
    # sample by sample, the argmin is the matching filter almost everywhere once settled
    winners = np.argmin(rms, axis=0)
    for j, model in enumerate(order):
        assert np.mean(winners[j * segment + settle : (j + 1) * segment] == model) > 0.95


def test_adaptive_with_true_model_beats_every_fixed_observer(rng):
    """§3.4.2, Fig. 3.6: fed the plant's true (b1(n), b0(n)), the adaptive RMS is the lowest."""
    n, step = 60_000, 25
    g = three_sine(n, pre=PRE_ROLL)
    # f0 and Q sweep across the bank's range, piecewise constant over 25 samples
    f0 = np.concatenate((np.full(PRE_ROLL, BANK_F0_HZ[0]), np.linspace(BANK_F0_HZ[0], BANK_F0_HZ[-1], n)))
    q = np.concatenate((np.full(PRE_ROLL, BANK_Q[0]), np.linspace(BANK_Q[0], BANK_Q[-1], n)))
    # pole map z = e^{sT} (the ZOH denominator), vectorised; spot-checked against cont2discrete
    b1_all, b0_all = discrete_denominator(f0[::step], q[::step], FS_HZ)
    assert (b1_all[-1], b0_all[-1]) == pytest.approx(discretise(f0[::step][-1], q[::step][-1])[1], rel=1e-12)
    dens = list(zip(b1_all, b0_all))
    y = switching_plant(g, [(d, step) for d in dens])[PRE_ROLL:] + NOISE_NM * rng.standard_normal(n)
    g = g[PRE_ROLL:]
    b1s = np.repeat([d[0] for d in dens], step)[PRE_ROLL:]
    b0s = np.repeat([d[1] for d in dens], step)[PRE_ROLL:]
    r = decay_radius(4.0, PERIOD)
    adaptive = adaptive_update(AdaptiveState.initial(NUMERATOR, BANK_DENOMINATORS[0], r, WINDOW), y, g, b1s, b0s)
    fixed = bank_update(BankState.initial(decay_designs(4.0), WINDOW), y, g).block.rms
    settle = 2_000
    ms_adaptive = np.mean(adaptive.block.rms[settle:] ** 2)
    ms_fixed = np.mean(fixed[:, settle:] ** 2, axis=1)
    assert ms_adaptive < 0.5 * np.min(ms_fixed), (ms_adaptive, ms_fixed)
    # and at every stretch of 2000 samples, not just on average
    for lo in range(settle, n, 2_000):
        sl = slice(lo, lo + 2_000)
        assert np.mean(adaptive.block.rms[sl] ** 2) < np.min(np.mean(fixed[:, sl] ** 2, axis=1))
    assert adaptive.state.held_samples == 0


def test_nan_propagates():
    """A NaN sample makes the later innovation and RMS NaN (not 0 through the clamp)."""
    y, g = free_air_record(np.random.default_rng(1), 200)
    y[50] = np.nan
    block = observer_update(ObserverState.initial(decay_designs()[2], WINDOW), y, g).block
    assert np.all(np.isfinite(block.rms[:50]))
    assert np.all(np.isnan(block.innovation[50:]))
    assert np.all(np.isnan(block.rms[50:]))


# ---------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------


def test_validation_errors():
    ss = state_space(*DENOMINATOR, NUMERATOR)
    design = ObserverDesign.from_decay(DENOMINATOR, NUMERATOR, 4.0, PERIOD)
    with pytest.raises(ConfigError, match="numerator"):
        state_space(*DENOMINATOR, (1.0, 2.0))
    with pytest.raises(ConfigError, match="measurement_noise_rms"):
        kalman_gain(ss, 0.1, 0.0)
    with pytest.raises(ConfigError, match="process_noise_rms"):
        kalman_gain(ss, -1.0, 0.1)
    with pytest.raises(ConfigError, match="cycles"):
        gain_for_decay(ss.A, ss.C, 0.0, PERIOD)
    with pytest.raises(ConfigError, match="residual"):
        gain_for_decay(ss.A, ss.C, 4.0, PERIOD, residual=1.5)
    with pytest.raises(ConfigError, match="complex pole pair"):
        gain_for_decay(np.array([[-1.5, 1.0], [-0.5, 0.0]]), ss.C, 4.0, PERIOD)  # real poles
    with pytest.raises(ConfigError, match="unstable"):
        ObserverDesign(DENOMINATOR, NUMERATOR, (0.0, 0.5))
    with pytest.raises(ConfigError, match="share the numerator"):
        BankState.initial([design, ObserverDesign(DENOMINATOR, (0.0, 0.5, 0.4), design.gain)], WINDOW)
    with pytest.raises(ConfigError, match="window_samples"):
        BankState.initial([design], 0)
    with pytest.raises(ConfigError, match="pole_radius"):
        AdaptiveState.initial(NUMERATOR, DENOMINATOR, 1.0, WINDOW)
    with pytest.raises(ConfigError, match="under-damped"):
        AdaptiveState.initial(NUMERATOR, (0.0, 0.0), 0.9, WINDOW)
    state = ObserverState.initial(design, WINDOW)
    with pytest.raises(InputError, match="dither has 3 samples"):
        observer_update(state, np.zeros(4), np.zeros(3))
    with pytest.raises(InputError, match="1-D"):
        observer_update(state, np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(InputError, match="N=2"):
        sliding_rms_update(WindowState.initial(2, 5), np.zeros(10))
    assert drive_period_window(FS_HZ, F0_HZ) == 7
