"""The Kalman bank's verdict across the envelope, on reference-simulator force curves (issue 27's grid, for §3.4.2).

tests/test_kalman_bank_reference.py checks the bank at the thesis's operating
point (500 kHz, 80 kHz, Q 168).  Here the same force curve (the §3.4.3
attractive set scaled to each lever, 20 nm free amplitude, 30 → 2 nm and
back in 0.4 s, side lines at ±7.5 % of f0) runs at 0.5–2 MHz, 30–300 kHz and
Q 20–600.  A verdict must discriminate: it passes with REEP's models and
fails with a bank 2 % high in f0.

The side lines are scaled so that they beat the free-air envelope by at
most 1.5 % (a quarter of the main line, the thesis's reference scale, where
that is less).  With a quarter of the main line at every Q, the beat grows
as Q falls: 8.6 % at Q 38 and 16 % at Q 20, and there the verdict fails on
the right answer (strict xfails below).  Where the tip taps hardest the
force then changes over each beat, which no linear model follows: every
innovation sits on a floor tens of times the noise, in band (removing the
deflection's content above 1.5 f0 leaves it; the tapping harmonics are not
the cause), and each filter's RMS minimum moves up to twelve bins off its
design bin.  The run says so: ``results.envelope_beat`` and a warning above
3 % (the verdict passed at 1.5 % at every Q and 3.5 % at Q 38, failed at
6–16 %, and was borderline at 3.2 % at Q 20).
"""

from __future__ import annotations

import pytest

from tests import reference_sim as rs
from tests.reep_envelope import scaled_force
from tests.test_kalman_bank import ADAPTIVE_FRACTION
from tests.test_kalman_bank_reference import _force_curve, _run

SIDE_OFFSET = 0.075  # side lines at ±7.5 % of f0
BEAT = 0.015  # the side lines' largest envelope beat in the grid
THESIS_SIDE = 0.25  # side lines at a quarter of the main line (tests/test_kalman_bank_reference.py)

#: (fs, f0, Q, noise nm): every rate, Q 20 to 600, f0 30 to 300 kHz.
CELLS = [
    (500e3, 40e3, 600.0, 0.02),
    (2e6, 75e3, 400.0, 0.05),
    (2e6, 250e3, 100.0, 0.1),
    (1e6, 150e3, 38.0, 0.05),
    (2e6, 300e3, 38.0, 0.1),
    (1e6, 70e3, 20.0, 0.05),
    (500e3, 30e3, 20.0, 0.05),
    (2e6, 150e3, 20.0, 0.02),
]

#: Side lines at a quarter of the main line at low Q: a beat of 8.6 % and 15 %.
BEATING = [(1e6, 150e3, 38.0, 0.05), (1e6, 70e3, 20.0, 0.05)]


def _beat_per_side(q: float) -> float:
    """Envelope beat per unit side-line scale: (|G(f0 − Δf)| + |G(f0 + Δf)|)/|G(f0)| (eq. 3.1)."""
    def gain(r):
        return 1.0 / abs(1.0 - r * r + 1j * r / q)
    return (gain(1.0 - SIDE_OFFSET) + gain(1.0 + SIDE_OFFSET)) / q


def side_scale(q: float) -> float:
    """The side lines' scale that holds the envelope beat to :data:`BEAT`, at most :data:`THESIS_SIDE`."""
    return min(THESIS_SIDE, BEAT / _beat_per_side(q))


_captures: dict = {}


def _capture(fs, f0, q, noise, side):
    key = (fs, f0, q, noise, side)
    if key not in _captures:
        _captures.clear()  # one capture in memory at a time
        _captures[key] = rs.simulate(
            f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.4,
            drive=rs.three_sine(f0, SIDE_OFFSET * f0, 20.0 / q, side), noise_nm=noise, seed=1,
            force=scaled_force("attractive", f0), separation_nm=_force_curve(), record_z_piezo=True,
        )
    return _captures[key]


def _id(cell) -> str:
    return f"{cell[0] / 1e6:g}MHz-{cell[1] / 1e3:g}kHz-Q{cell[2]:g}"


def _right_answer_passes(cell, side):
    result = _run(_capture(*cell, side))
    res = result.results
    print(f"\n{_id(cell)}, side lines {side:.3g}: beat {res.envelope_beat:.2%}, least-RMS offsets "
          f"{[f.min_bin_offset for f in res.filters]}, adaptive least {res.adaptive.fraction_lowest:.1%}")
    assert all(f.min_bin_offset == 0 for f in res.filters)
    assert res.adaptive.fraction_lowest >= ADAPTIVE_FRACTION
    assert res.verdict.pass_, res.verdict.reasons
    assert not any("beat" in w for w in result.warnings)


def _wrong_answer_fails(cell, side):
    verdict = _run(_capture(*cell, side), f0_scale=1.02).results.verdict
    assert not verdict.pass_
    assert len(verdict.reasons) >= 3


def test_side_scale_holds_the_beat():
    assert side_scale(600.0) == THESIS_SIDE
    for q in (20.0, 38.0, 100.0):
        assert side_scale(q) * _beat_per_side(q) == pytest.approx(min(BEAT, THESIS_SIDE * _beat_per_side(q)))


def test_bank_verdict_discriminates_at_500_khz_and_q_600():
    cell = CELLS[0]
    _right_answer_passes(cell, side_scale(cell[2]))
    _wrong_answer_fails(cell, side_scale(cell[2]))


@pytest.mark.slow
@pytest.mark.parametrize("cell", CELLS[1:], ids=_id)
def test_bank_verdict_discriminates_across_the_envelope(cell):
    _right_answer_passes(cell, side_scale(cell[2]))
    _wrong_answer_fails(cell, side_scale(cell[2]))


@pytest.mark.slow
@pytest.mark.parametrize("cell", BEATING, ids=_id)
def test_a_beating_drive_is_measured_and_warned_about(cell):
    """A quarter-scale side line at Q 38 and 20: the report gives the beat (as eq. 3.1 has it) and warns."""
    result = _run(_capture(*cell, THESIS_SIDE))
    expected = THESIS_SIDE * _beat_per_side(cell[2])
    assert result.results.envelope_beat == pytest.approx(expected, rel=0.02)
    assert any("beat the free-air envelope" in w for w in result.warnings)


@pytest.mark.slow
@pytest.mark.parametrize("cell", [pytest.param(c, marks=pytest.mark.xfail(
    strict=True, reason="a quarter-scale side line beats the envelope by 8.6-16 % at Q 38-20 (module docstring)"))
    for c in BEATING], ids=_id)
def test_bank_right_answer_with_a_beating_drive(cell):
    _right_answer_passes(cell, THESIS_SIDE)


def test_the_thesis_reference_point_beats_under_the_warning():
    """The thesis's operating point (Q 168, a quarter-scale side line at ±7.5 %) beats by 2.0 %: no warning there."""
    from afmtool.analyses.kalman_bank import BEAT_WARNING

    thesis = THESIS_SIDE * _beat_per_side(168.0)
    assert thesis == pytest.approx(0.0199, abs=2e-4) and thesis < BEAT_WARNING
    assert THESIS_SIDE * _beat_per_side(38.0) > BEAT_WARNING
