"""How well the drive lines alone can pin Q′: information bounds, independent of afmtool (issue 27, item 6).

Without the recorded dither, ``--drive`` knows each line's frequency and amplitude but not its
phase.  REEP reads Q′ on the sample through the main line's phase, which comes from a free-air
model G(f; f0, Q, g) fitted to the lines.  Every estimator of that phase has at least the
Cramér–Rao spread; this test computes it with numpy only (no afmtool code) and carries it to Q′
on the reference captures' detuned tip (f0′ = 0.996 f0, Q′ = 0.8 Q, driven at f0;
tests/test_synthetic_drive_reference.py), for two things one may know of the lines:

* **phased apart** (each line's phase unknown): only the magnitudes |R_k| = g·A_k·|H(f_k)| carry
  f0, Q, g (three numbers for three unknowns).  The Fisher information of (f0, ln Q, ln g) is
  JᵀJ/σ², J = ∂|R_k|/∂θ, σ = σ_n·√(2/N) each line's amplitude noise.  At Q 400 the side lines
  hardly depend on Q and the bound on Q′'s relative std is 15 % (0.02 nm, 0.5 MHz), 76 % (0.1 nm)
  and 17 % (2 MHz, 0.05 nm): 3 % cannot be met this way by any unbiased estimator;
* **started together** (the thesis's g(t) = A sin ω0t + B sin(ω0 + Δω)t + B sin(ω0 − Δω)t): the
  phases are φ_k = c + s_k·m at any first sample, and the complex amplitudes
  R_k = g·A_k·H(f_k)·e^{j(c + s_k m)} carry (f0, ln Q, ln g, c, m), six numbers for five.  The
  closure phase pins the main line's phase to the side lines' phase noise, and the bound is
  0.2–1.1 % at Q 400.  That is what afmtool's default (``--drive-phases common``) uses.

The main line's phase error δφ carries to Q′: with g/R = 1 − r² + j·r/Q′ (r = f_d/f0′),
Q′(δφ) = r/Im(g/R·e^{jδφ}).
"""

from __future__ import annotations

import numpy as np
import pytest

FREE_AIR_S = 0.05  # the reference captures' free-air segment
SIDE_OFFSET_HZ = 6000.0


def _response(f, f0, q, gain=1.0):
    r = f / f0
    return gain / (1.0 - r * r + 1j * r / q)


def q_relative_std_bound(fs: float, f0: float, q: float, noise_nm: float, *, common_origin: bool = False
                         ) -> tuple[float, float]:
    """(σ_f0 in Hz, relative std of Q′ on the detuned tip): the Cramér–Rao bound of the lines' fit.

    ``common_origin``: the lines started together, and their complex amplitudes, not only their
    magnitudes, carry the resonance.
    """
    amplitude = 20.0 / q  # tests/reference_sim.three_sine(f0, 6 kHz, 20/Q, 0.5)
    lines = np.array([f0, f0 - SIDE_OFFSET_HZ, f0 + SIDE_OFFSET_HZ])
    steps_k = np.array([0.0, -1.0, 1.0])
    amplitudes = np.array([amplitude, 0.5 * amplitude, 0.5 * amplitude])
    sigma = noise_nm * np.sqrt(2.0 / (fs * FREE_AIR_S))
    theta = np.array([f0, np.log(q), 0.0, 0.0, 0.0])  # f0, ln Q, ln g, c, m
    size = 5 if common_origin else 3
    steps = np.array([1e-7 * f0, 1e-7, 1e-7, 1e-7, 1e-7])[:size]
    theta = theta[:size]

    def measured(t):
        response = _response(lines, t[0], np.exp(t[1]), np.exp(t[2])) * amplitudes
        if not common_origin:
            return np.abs(response)
        complex_amplitude = response * np.exp(1j * (t[3] + steps_k * t[4]))
        return np.concatenate([complex_amplitude.real, complex_amplitude.imag])

    def main_phase(t):
        # the main line's drive phase REEP is given: c when the lines started together; else the
        # measured phase less the model's, whose error is the model's (∠R₀ itself is measured far better)
        return t[3] if common_origin else -np.angle(_response(f0, t[0], np.exp(t[1]), np.exp(t[2])))

    def gradient(fun):
        eye = np.eye(size)
        return np.array([(fun(theta + steps[k] * eye[k]) - fun(theta - steps[k] * eye[k])) / (2 * steps[k])
                         for k in range(size)])

    jacobian = gradient(measured).T  # rows: measured numbers; columns: parameters
    covariance = np.linalg.inv(jacobian.T @ jacobian / sigma**2)
    phase_gradient = gradient(main_phase)
    phase_std = float(np.sqrt(phase_gradient @ covariance @ phase_gradient))
    tip_f0, tip_q = 0.996 * f0, 0.8 * q
    read = 1.0 / _response(f0, tip_f0, tip_q)  # g/R at the drive

    def q_read(dphi):
        rotated = read * np.exp(1j * dphi)
        return np.sqrt(1.0 - rotated.real) / rotated.imag

    dq_dphi = (q_read(1e-6) - q_read(-1e-6)) / 2e-6
    return float(np.sqrt(covariance[0, 0])), abs(dq_dphi) * phase_std / tip_q


def test_the_q_read_recovers_the_tip_without_a_phase_error():
    read = 1.0 / _response(70e3, 0.996 * 70e3, 320.0)
    assert np.sqrt(1.0 - read.real) / read.imag == pytest.approx(320.0)


@pytest.mark.parametrize(("fs", "f0", "q", "noise", "at_least"), [
    (500e3, 70e3, 400.0, 0.02, 0.10),
    (500e3, 70e3, 400.0, 0.1, 0.50),
    (2e6, 75e3, 400.0, 0.05, 0.10),
])
def test_at_q_400_the_lines_alone_cannot_pin_q_to_3_percent(fs, f0, q, noise, at_least):
    sigma_f0, q_std = q_relative_std_bound(fs, f0, q, noise)
    print(f"\n{fs / 1e6:g} MHz f0 {f0:g} Q {q:g} {noise} nm: sigma_f0 >= {sigma_f0:.2f} Hz, Q' rel std >= {100 * q_std:.1f} %")
    assert q_std >= at_least  # so |error| <= 3 % is a coin toss at best: P < 2*Phi(0.3)-1 = 24 %


@pytest.mark.parametrize(("fs", "f0", "q", "noise"), [(500e3, 70e3, 100.0, 0.1), (2e6, 75e3, 100.0, 0.05)])
def test_at_q_100_the_bound_allows_3_percent(fs, f0, q, noise):
    assert q_relative_std_bound(fs, f0, q, noise)[1] < 0.015


@pytest.mark.parametrize(("fs", "f0", "q", "noise"), [
    (500e3, 70e3, 400.0, 0.02), (500e3, 70e3, 400.0, 0.1), (2e6, 75e3, 400.0, 0.05), (2e6, 250e3, 600.0, 0.02),
])
def test_lines_that_started_together_can_pin_q_to_3_percent(fs, f0, q, noise):
    """The same captures, with the lines' common phase origin known: 3 % is at least two of the bound's std."""
    apart = q_relative_std_bound(fs, f0, q, noise)[1]
    sigma_f0, together = q_relative_std_bound(fs, f0, q, noise, common_origin=True)
    print(f"\n{fs / 1e6:g} MHz f0 {f0:g} Q {q:g} {noise} nm: Q' rel std >= {100 * together:.2f} % started together, "
          f">= {100 * apart:.1f} % phased apart (sigma_f0 >= {sigma_f0:.3f} Hz)")
    assert together <= 0.015 and together < apart / 10  # 3 % is at least two of its std
