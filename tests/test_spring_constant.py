"""Spring constant from a thermal spectrum: equipartition with the Butt–Jaschke factor, and Sader (issue 16, item 3).

Acceptance: on a simulated thermal spectrum of known k, the corrected
equipartition value and the Sader value are both within 5 %.  The spectrum is
written here from beam theory (Euler–Bernoulli modes, Sader's hydrodynamic
loading in air), with its own implementation, not from afmtool's.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import kv

from afmtool.errors import ConfigError
from afmtool.estimators.spring_constant import (
    MODE1_SHARE,
    OPTICAL_LEVER_FACTOR,
    hydrodynamic_function_rectangular,
    sader_spring_constant,
)
from tests.conftest import run_cli

K_B = 1.380649e-23
# a silicon cantilever, 225 x 40 x 2 um, in air at 25 degC
E_PA, RHO_SI = 169e9, 2330.0
LENGTH, WIDTH, THICKNESS = 225e-6, 40e-6, 2.0e-6
RHO_AIR, ETA_AIR = 1.184, 1.849e-5
TEMPERATURE = 298.15


def _first_mode():
    """α1·L and χ (end deflection over 2L/3 times end slope) of the clamped-free beam's first mode."""
    a = brentq(lambda x: math.cos(x) * math.cosh(x) + 1.0, 1.0, 3.0)
    s = (math.cosh(a) + math.cos(a)) / (math.sinh(a) + math.sin(a))
    shape = math.cosh(a) - math.cos(a) - s * (math.sinh(a) - math.sin(a))
    slope = a * (math.sinh(a) + math.sin(a) - s * (math.cosh(a) - math.cos(a)))
    return a, shape / (2.0 / 3.0 * slope)


def _gamma(reynolds: float) -> complex:
    """Hydrodynamic function of a rectangular beam: the circular-cylinder Stokes result times Sader's Ω (1998)."""
    root = np.sqrt(1j * reynolds)
    circ = 1 + 4j * kv(1, -1j * root) / (root * kv(0, -1j * root))
    t = math.log10(reynolds)
    om_r = (0.91324 - 0.48274 * t + 0.46842 * t**2 - 0.12886 * t**3 + 0.044055 * t**4 - 0.0035117 * t**5
            + 0.00069085 * t**6) / (1 - 0.56964 * t + 0.48690 * t**2 - 0.13444 * t**3 + 0.045155 * t**4
                                    - 0.0035862 * t**5 + 0.00069085 * t**6)
    om_i = (-0.024134 - 0.029256 * t + 0.016294 * t**2 - 0.00010961 * t**3 + 0.000064577 * t**4
            - 0.000044510 * t**5) / (1 - 0.59702 * t + 0.55182 * t**2 - 0.18357 * t**3 + 0.079156 * t**4
                                     - 0.014369 * t**5 + 0.0028361 * t**6)
    return complex(om_r, om_i) * complex(circ)


def _cantilever_in_air():
    """k (N/m), and the first mode's resonance f (Hz) and Q in air, from beam theory and Sader (1998), eqs. 16-18."""
    a, chi = _first_mode()
    k = E_PA * WIDTH * THICKNESS**3 / (4 * LENGTH**3)
    omega_vac = a**2 / LENGTH**2 * math.sqrt(E_PA * THICKNESS**2 / (12 * RHO_SI))
    mass_ratio = math.pi * RHO_AIR * WIDTH / (4 * RHO_SI * THICKNESS)
    omega = omega_vac
    for _ in range(50):  # ω_f = ω_vac/√(1 + T·Γ_r(ω_f)): a fixed point
        gamma = _gamma(RHO_AIR * omega * WIDTH**2 / (4 * ETA_AIR))
        omega = omega_vac / math.sqrt(1 + mass_ratio * gamma.real)
    q = (1 / mass_ratio + gamma.real) / gamma.imag
    return k, omega / (2 * math.pi), q, a, chi


def _optical_lever_spectrum(rng, k, f0, q, chi, *, averages=200, floor_asd=3e-14):
    """One-sided ASD (m/√Hz) an optical lever calibrated by a static force curve shows, M-averaged."""
    f = np.arange(1, 40001) * 3.0  # 3 Hz bins to 120 kHz
    mean_square = 12 / 1.8751040687**4 * K_B * TEMPERATURE / k  # mode 1 of the tip deflection
    shape = f0**4 / ((f0**2 - f**2) ** 2 + (f * f0 / q) ** 2)
    dc = mean_square / (0.5 * math.pi * f0 * q)  # ∫ dc·shape df = dc·π f0 Q/2
    psd = dc * shape / chi**2 + floor_asd**2  # the lever reads z1/χ
    psd = psd * rng.chisquare(2 * averages, f.size) / (2 * averages)
    return f, np.sqrt(psd)


def test_factors_from_the_mode_shape():
    a, chi = _first_mode()
    assert math.isclose(MODE1_SHARE, 12 / a**4, rel_tol=1e-9)
    assert math.isclose(OPTICAL_LEVER_FACTOR, 12 / a**4 / chi**2, rel_tol=1e-9)
    assert round(OPTICAL_LEVER_FACTOR, 3) == 0.817 and round(MODE1_SHARE, 3) == 0.971


def test_hydrodynamic_function_matches_the_independent_one():
    for re in (0.3, 3.0, 30.0, 300.0):
        assert abs(hydrodynamic_function_rectangular(re) - _gamma(re)) < 1e-9 * abs(_gamma(re))


def test_sader_on_beam_theory():
    k, f0, q, _, _ = _cantilever_in_air()
    result = sader_spring_constant(f0, q, LENGTH, WIDTH, density_kg_per_m3=RHO_AIR, viscosity_pa_s=ETA_AIR)
    print(f"beam theory k = {k:.4f} N/m, f0 = {f0:.1f} Hz, Q = {q:.1f}; Sader {result.spring_constant_n_per_m:.4f}")
    assert abs(result.spring_constant_n_per_m / k - 1) < 0.02


def test_sader_refuses_bad_input():
    with pytest.raises(ConfigError, match="fluid"):
        sader_spring_constant(5e4, 100, 1e-4, 3e-5, fluid="honey")
    with pytest.raises(ConfigError, match="length_m"):
        sader_spring_constant(5e4, 100, -1e-4, 3e-5)


def test_identify_freeair_psd_spring_constants(tmp_path, rng):
    k, f0, q, _, chi = _cantilever_in_air()
    f, asd = _optical_lever_spectrum(rng, k, f0, q, chi)
    table = tmp_path / "thermal.csv"
    table.write_text("frequency_hz,asd_m_per_sqrt_hz\n" + "\n".join(f"{a:.6g},{b:.8g}" for a, b in zip(f, asd)))
    out = tmp_path / "out"
    result = run_cli("identify", "freeair", "--psd", table, "--temperature", str(TEMPERATURE), "--length", "225",
                     "--width", "40", "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    spring = report["results"]["spring_constant"]
    thermal, sader = spring["thermal"]["value_n_per_m"], spring["sader"]["value_n_per_m"]
    plain = report["results"]["spring_constant_n_per_m"]
    print(f"k true {k:.4f} N/m; thermal corrected {thermal:.4f} ({(thermal / k - 1) * 100:+.2f} %), "
          f"uncorrected {plain:.4f} ({(plain / k - 1) * 100:+.2f} %); Sader {sader:.4f} ({(sader / k - 1) * 100:+.2f} %)")
    assert abs(thermal / k - 1) < 0.05
    assert abs(sader / k - 1) < 0.05
    assert abs(plain / k - 1) > 0.1  # the correction matters: without it k is 1/0.817 - 1 = 22 % high
    assert spring["thermal"]["temperature_k"] == TEMPERATURE
    assert (out / "thermal_fit.png").stat().st_size > 1000
