"""The independent reference simulator (tests/reference_sim.py) against closed forms.

These tests check the reference itself, from physics and scipy alone, so
that afmtool's estimators can be scored against it.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from tests import reference_sim as rs

FS = 500e3
F0 = 70e3
Q = 200.0
GAIN = 0.1  # nm/V


def _line_phasor(x: np.ndarray, t: np.ndarray, f_hz: float) -> complex:
    """Least-squares a·cos + b·sin at f; returns the phasor a − jb (x ≈ Re(X e^{jωt}))."""
    w = 2 * np.pi * f_hz
    basis = np.column_stack([np.cos(w * t), np.sin(w * t), np.ones_like(t)])
    (a, b, _), *_ = np.linalg.lstsq(basis, x, rcond=None)
    return complex(a, -b)


def test_imports_nothing_from_afmtool():
    tree = ast.parse(Path(rs.__file__).read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add((node.module or "").split(".")[0])
    assert "afmtool" not in names
    assert names <= {"__future__", "json", "math", "collections", "dataclasses", "pathlib", "h5py", "numpy",
                     "numba", "scipy"}, names


@pytest.mark.parametrize("f_hz", [F0, F0 - 2e3, F0 + 5e3, 20e3])
def test_continuous_steady_state_matches_transfer_function(f_hz):
    """Amplitude and phase of the sampled response equal G(jω), with no start-up transient."""
    drive = rs.Sine(f_hz, 2.0, 0.3)
    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=2e-3, drive=drive)
    t = cap.t
    response = _line_phasor(cap.channels["deflection"], t, f_hz) / _line_phasor(cap.channels["dither"], t, f_hz)
    expected = rs.free_air_response(f_hz, F0, Q, GAIN)
    print(f"f={f_hz:g}: |G| rel err {abs(response) / abs(expected) - 1:.2e}, "
          f"phase err {math.degrees(np.angle(response / expected)):.2e} deg")
    assert abs(abs(response) / abs(expected) - 1) < 1e-5
    assert abs(math.degrees(np.angle(response / expected))) < 1e-3
    if f_hz == F0:
        assert abs(math.degrees(np.angle(response)) + 90.0) < 1e-3
        assert abs(abs(response) - GAIN * Q) < 1e-4 * GAIN * Q


def _plant_state_space(f0_hz=F0, q=Q, gain=GAIN):
    w0 = 2 * np.pi * f0_hz
    return (np.array([[0.0, 1.0], [-w0**2, -w0 / q]]), np.array([[0.0], [w0**2 * gain]]),
            np.array([[1.0, 0.0]]), np.array([[0.0]]))


def test_zoh_capture_matches_cont2discrete():
    """A held drive from rest: the samples equal the exact ZOH discretisation of the plant."""
    drive = rs.MultiSine((rs.Sine(F0, 1.0), rs.Sine(F0 * 0.93, 0.7, 1.0), rs.Sine(13e3, 3.0, -0.4)))
    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=4e-3, drive=drive,
                      hold="zoh", start_at_steady_state=False)
    ad, bd, cd, dd, _ = signal.cont2discrete(_plant_state_space(), 1 / FS, method="zoh")
    _, y, _ = signal.dlsim((ad, bd, cd, dd, 1 / FS), cap.channels["dither"])
    err = np.max(np.abs(cap.channels["deflection"] - y[:, 0])) / np.max(np.abs(y))
    print(f"zoh vs cont2discrete: max rel error {err:.2e}")
    # RK4 at 32 steps per sample drifts by ~1e-6 over 2000 samples; a half-sample
    # delay (the continuous-drive response) would be off by tens of percent
    assert err < 1e-5
    continuous = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=4e-3, drive=drive,
                             start_at_steady_state=False)
    assert np.max(np.abs(continuous.channels["deflection"] - y[:, 0])) / np.max(np.abs(y)) > 0.1


def test_zoh_steady_state_start_has_no_transient():
    """The held-drive initial state is the discrete steady state: the response equals H(e^{jωT})."""
    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=1e-3,
                      drive=rs.Sine(F0, 1.0), hold="zoh")
    ad, bd, cd, dd, _ = signal.cont2discrete(_plant_state_space(), 1 / FS, method="zoh")
    num, den = signal.ss2tf(ad, bd, cd, dd)
    _, h = signal.freqz(num[0], den, worN=[F0], fs=FS)
    t = cap.t
    measured = _line_phasor(cap.channels["deflection"], t, F0) / _line_phasor(cap.channels["dither"], t, F0)
    assert abs(measured / h[0] - 1) < 1e-5
    # the hold delays the drive by half a sample: 25.2° at 70 kHz sampled at 500 kHz
    delay_deg = math.degrees(np.angle(rs.free_air_response(F0, F0, Q, GAIN) / measured))
    print(f"zoh phase lag beyond -90 deg at resonance: {delay_deg:.3f} deg (half sample 25.2 deg)")
    assert abs(delay_deg - 180 * F0 / FS) < 0.1


def test_attractive_force_pulls_towards_sample():
    """No drive, tip inside the attractive range: it settles at ω0²p = −ω_a²(d − p − l)."""
    force = rs.PiecewiseLinearForce(4.0, (0.31e6) ** 2, (3.03e6) ** 2, 0.0, 0.0)
    l_nm = 3.0
    q_low = 5.0
    cap = rs.simulate(f0_hz=F0, q=q_low, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=2e-3,
                      drive=rs.Sine(F0, 0.0), force=force, separation_nm=l_nm, start_at_steady_state=False)
    w0sq = (2 * np.pi * F0) ** 2
    expected = -force.wa2 * (force.d_nm - l_nm) / (w0sq - force.wa2)
    settled = cap.truth["deflection_clean"][-100:]
    assert expected < 0
    assert np.max(np.abs(settled - expected)) < 1e-6 * abs(expected)
    assert cap.truth["contact"].all()
    assert "free_air" not in cap.metadata
    # repulsion for t_s < 0 pushes up; dissipation opposes the velocity
    assert force(-4.0, 0.0, 3.0) > force(-3.0, 0.0, 3.0) - force.wa2 * 1.0 + 1.0
    assert force(-1.0, 1e3, 3.0) == -force.wa2 * 2.0
    assert rs.PiecewiseLinearForce(4.0, 1.0, 0.0, 2.0, 0.0)(0.0, 5.0, 1.0) == -3.0 - 10.0


def test_contact_truth_and_free_air_segment():
    """A force curve: contact only once the tip reaches d; free_air ends at the first contact."""
    amplitude_nm = 10.0
    u = amplitude_nm / (GAIN * Q)

    def separation(t):
        return np.where(t < 1e-3, 30.0, 30.0 - (t - 1e-3) * 1e4)  # 30 nm, then closer at 10 nm/ms

    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=3e-3,
                      drive=rs.Sine(F0, u), force=rs.ATTRACTIVE_SET, separation_nm=separation,
                      record_z_piezo=True)
    contact = cap.truth["contact"].astype(bool)
    p = cap.truth["deflection_clean"]
    ts = p + cap.truth["separation_nm"]
    first = int(np.flatnonzero(contact)[0])
    assert not (ts[:first] < rs.ATTRACTIVE_SET.d_nm).any()
    # a sample whose own t_s is inside the range is in contact (touches between samples count too)
    assert contact[ts < rs.ATTRACTIVE_SET.d_nm].all()
    assert (ts < rs.ATTRACTIVE_SET.d_nm).sum() > 10
    assert cap.metadata["free_air"] == {"start_s": 0.0, "end_s": first / FS}
    assert first / FS > 1e-3
    assert cap.channels["z_piezo"][0] == 0.0 and cap.channels["z_piezo"][-1] < -10
    assert abs(cap.metadata["drive"]["free_amplitude_nm"] - amplitude_nm) < 1e-9


def test_drives_are_continuous_functions_of_time():
    chirp = rs.LinearChirp(60e3, 80e3, 1.0, 0.0, 1e-3)
    t = np.linspace(0, 1e-3, 200001)
    u = rs.drive_voltage(chirp, t)
    # instantaneous frequency from the analytic phase: f(t) = f_s + k t
    analytic = signal.hilbert(u)
    f_inst = np.diff(np.unwrap(np.angle(analytic))) / np.diff(t) / (2 * np.pi)
    mid = slice(20000, 180000)
    assert np.max(np.abs(f_inst[mid] - (60e3 + 2e7 * t[:-1][mid]))) < 50
    stepped = rs.SteppedSine((60e3, 65e3, 70e3), 1e-4, 1.0)
    us = rs.drive_voltage(stepped, t[:40000])
    assert np.max(np.abs(np.diff(us))) < 2 * np.pi * 70e3 * (t[1] - t[0]) * 1.01  # no phase jumps
    assert rs.drive_voltage(stepped, np.array([3e-4 + 1e-9]))[0] == 0.0
    assert [s["frequency_hz"] for s in stepped.segments()] == [60e3, 65e3, 70e3]


def test_time_varying_f0_follows_prescription():
    """A prescribed f0(t) step: the truth records it, and the ringing after it is at the new f0."""
    def f0_of_t(t):
        return np.where(t < 1e-3, F0, F0 + 500.0)

    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=10e-3,
                      drive=rs.Sine(F0, 1.0), f0_of_t=f0_of_t)
    assert cap.truth["f0_hz"][0] == F0 and cap.truth["f0_hz"][-1] == F0 + 500.0
    # late in the record the steady state at the drive is that of the new resonance
    t = cap.t[-200:]
    response = _line_phasor(cap.channels["deflection"][-200:], t, F0) / _line_phasor(cap.channels["dither"][-200:],
                                                                                    t, F0)
    w0n, w = 2 * np.pi * (F0 + 500.0), 2 * np.pi * F0
    expected = GAIN * (2 * np.pi * F0) ** 2 / (w0n**2 - w**2 + 1j * w * w0n / Q)
    # 9 ms after the step is 10 time constants (2Q/ω0 = 0.9 ms): the transient is below 1e-4
    print(f"after the f0 step: response error {abs(response / expected - 1):.2e}")
    assert abs(response / expected - 1) < 1e-3


def test_h5_capture_reads_back_in_afmtool(tmp_path):
    """The file follows afmtool's capture layout: afmtool's reader gets the same samples and truth."""
    from afmtool.io.registry import open_capture

    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=1e-3,
                      drive=rs.Sine(F0, 1.0), noise_nm=0.05, seed=3, force=rs.ATTRACTIVE_SET, separation_nm=40.0,
                      deflection_units="um")
    path = rs.write_capture_h5(tmp_path / "ref.h5", cap)
    with open_capture(path) as reader:
        assert reader.info.sample_rate_hz == FS
        assert reader.info.units("deflection") == "um"
        assert reader.info.metadata["cantilever"] == {"f0_hz": F0, "q": Q}
        assert reader.info.metadata["drive"]["hold"] == "continuous"
        blocks = list(reader.blocks(["dither", "deflection"], 1 << 20))
        truth = reader.truth()
    np.testing.assert_array_equal(blocks[0].data["deflection"], cap.channels["deflection"])
    np.testing.assert_array_equal(truth["contact"], cap.truth["contact"])
    assert not truth["contact"].any()
    assert np.std(cap.channels["deflection"] * 1e3 - cap.truth["deflection_clean"]) == pytest.approx(0.05, rel=0.1)
