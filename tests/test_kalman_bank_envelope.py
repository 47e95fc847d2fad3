"""The Kalman bank's verdict across the envelope, on reference-simulator force curves (issue 27's grid, for §3.4.2).

tests/test_kalman_bank_reference.py checks the bank at the thesis's operating
point (500 kHz, 80 kHz, Q 168).  Here the same force curve (the §3.4.3
attractive set scaled to each lever, 20 nm free amplitude, 30 → 2 nm and
back in 0.4 s, side lines at ±7.5 % of f0 and a quarter of the main line)
runs at other rates, resonances and Q.  A verdict must discriminate: it
passes with REEP's models and fails with a bank 2 % high in f0.

At Q 38 and below the right answer fails (strict xfails, kept until the
cause is removed).  What the RMS tables show there: where the tip taps
hardest no linear model explains the deflection; every filter's
innovation, and the adaptive observer's, sits on a floor tens of times the
noise that falls along z, so each filter's RMS minimum moves one to three
bins off its design bin; one design point lands on the bin of the branch
jump.  The likely cause, not yet shown: a lever at low Q filters the
tapping harmonics little (at the turn the second harmonic is 17 % of the
first at Q 38, 5 % at Q 100).  If so, band-limiting the innovation to the
resonance, as REEP's decimation does, would remove the floor; that
changes every bank number and is left for its own change.
"""

from __future__ import annotations

import pytest

from tests import reference_sim as rs
from tests.reep_envelope import scaled_force
from tests.test_kalman_bank import ADAPTIVE_FRACTION
from tests.test_kalman_bank_reference import _force_curve, _run

#: (fs, f0, Q, noise nm)
CELLS = [
    (500e3, 40e3, 600.0, 0.02),
    (2e6, 75e3, 400.0, 0.05),
    (2e6, 250e3, 100.0, 0.1),
    (1e6, 150e3, 38.0, 0.05),
    (1e6, 70e3, 20.0, 0.05),
]

LOW_Q = ("at Q <= 38 the tapping harmonics' floor under the innovation moves each filter's RMS minimum 1-3 bins "
         "off its design bin, and the adaptive observer is least 57-68 % of the time (module docstring)")

_captures: dict = {}


def _capture(fs, f0, q, noise):
    key = (fs, f0, q, noise)
    if key not in _captures:
        _captures.clear()  # one capture in memory at a time
        _captures[key] = rs.simulate(
            f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.4,
            drive=rs.three_sine(f0, 0.075 * f0, 20.0 / q, 0.25), noise_nm=noise, seed=1,
            force=scaled_force("attractive", f0), separation_nm=_force_curve(), record_z_piezo=True,
        )
    return _captures[key]


def _cells(short: bool):
    chosen = CELLS[:1] if short else CELLS[1:]
    return [pytest.param(*cell, id=f"{cell[0] / 1e6:g}MHz-{cell[1] / 1e3:g}kHz-Q{cell[2]:g}",
                         marks=[pytest.mark.xfail(strict=True, reason=LOW_Q)] if cell[2] <= 38 else [])
            for cell in chosen]


def _right_answer_passes(fs, f0, q, noise):
    res = _run(_capture(fs, f0, q, noise)).results
    print(f"\n{fs / 1e6:g} MHz {f0 / 1e3:g} kHz Q {q:g}: least-RMS offsets {[f.min_bin_offset for f in res.filters]}, "
          f"adaptive least {res.adaptive.fraction_lowest:.1%}")
    assert all(f.min_bin_offset == 0 for f in res.filters)
    assert res.adaptive.fraction_lowest >= ADAPTIVE_FRACTION
    assert res.verdict.pass_, res.verdict.reasons


def _wrong_answer_fails(fs, f0, q, noise):
    verdict = _run(_capture(fs, f0, q, noise), f0_scale=1.02).results.verdict
    assert not verdict.pass_
    assert len(verdict.reasons) >= 3


@pytest.mark.parametrize(("fs", "f0", "q", "noise"), _cells(short=True))
def test_bank_verdict_discriminates_at_500_khz_and_q_600(fs, f0, q, noise):
    _right_answer_passes(fs, f0, q, noise)
    _wrong_answer_fails(fs, f0, q, noise)


@pytest.mark.slow
@pytest.mark.parametrize(("fs", "f0", "q", "noise"), _cells(short=False))
def test_bank_right_answer_passes_across_the_envelope(fs, f0, q, noise):
    _right_answer_passes(fs, f0, q, noise)


@pytest.mark.slow
@pytest.mark.parametrize(("fs", "f0", "q", "noise"), [pytest.param(*c, id=f"Q{c[2]:g}") for c in CELLS[1:]])
def test_bank_two_percent_high_fails_across_the_envelope(fs, f0, q, noise):
    _wrong_answer_fails(fs, f0, q, noise)
