"""Probe loss across the envelope, against its own prediction (issue 28, items 1-3).

Single-tone captures from the independent reference simulator: a free
amplitude of 30 nm, the §3.4.3 attractive force set, loss events of 5 to 40
drive periods between 300-period stretches on the sample, white measurement
noise.  probeloss gets the model from the metadata f0/Q and **no set
point**: it estimates the on-sample amplitude from the capture, predicts
its detectability before the run, and runs the detector it predicts best.

The grid (item 3): sampling at 0.5, 1 and 2 MHz; Q 50-400; noise 0.03-0.1 nm;
on-sample amplitude 0.5-0.8 of free.  The sample sits at l = ratio·A0 + 3.6 nm:
steady attractive tapping dips about 0.4 nm into the 4 nm force range, so the
tip taps at about l − 3.6 nm (the measured ratio is recorded).  On every cell
the prediction says whether the targets (recall ≥ 0.95, median latency ≤ 3
drive periods, time-weighted precision ≥ 0.9, on-sample time flagged ≤ 2 %)
are within reach:

* within: all four hold;
* beyond: the report and the headline say so first, and the measured median
  latency is within 30 % of the predicted one, at the predicted precision
  (≥ 0.9 where the prediction reaches it; where it does not, the measured
  precision is at least the predicted one less 0.05).

Everywhere, the estimated on-sample amplitude is within 10 % of the truth's.
``test_envelope_short`` runs four cells in CI; ``test_envelope_full`` (slow)
the whole grid, and prints the table for the issue's closing note.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from afmtool.config import resolve
from afmtool.config.params import ProbeLossParams
from afmtool.io.registry import open_capture
from afmtool.report.headline import headline
from tests import reference_sim as rs

F0 = 70e3
GAIN = 0.1  # nm/V
FREE_AMPLITUDE_NM = 30.0
LOSS_PERIODS = (5, 8, 12, 20, 40, 6, 15)
#: How far steady attractive tapping reaches into the 4 nm force range (module docstring), nm.
TAP_DEPTH_NM = 3.6
#: The measured median latency of a capture beyond the limit is within this of the prediction (item 2).
LATENCY_TOLERANCE = 0.3


class _Discard:
    def append(self, columns) -> None:
        pass


def envelope_capture(tmp_path, fs, q, noise_nm, ratio, *, f0_hz=F0, hold="continuous", seed=1):
    """A reference-simulator capture of the grid (module docstring); its path."""
    period = 1.0 / f0_hz
    free_s = max(4e-3, 3.0 * q / (math.pi * f0_hz))  # three free-air time constants at least
    program, duration = rs.loss_program(free_s, 300 * period, [k * period for k in LOSS_PERIODS],
                                        ratio * FREE_AMPLITUDE_NM + TAP_DEPTH_NM, FREE_AMPLITUDE_NM + 10.0)
    cap = rs.simulate(f0_hz=f0_hz, q=q, gain_nm_per_v=GAIN, sample_rate_hz=fs, duration_s=duration,
                      drive=rs.Sine(f0_hz, FREE_AMPLITUDE_NM / (GAIN * q)), hold=hold, noise_nm=noise_nm, seed=seed,
                      force=rs.ATTRACTIVE_SET, separation_nm=program)
    name = f"env_{fs:g}_{q:g}_{noise_nm:g}_{ratio:g}_{hold}.h5"
    return rs.write_capture_h5(tmp_path / name, cap)


def true_on_sample_amplitude(path, f0_hz=F0) -> float:
    """The truth's on-sample amplitude: the median half peak-to-peak of the clean deflection per drive period,
    over periods in contact at least 100 periods after the tip last came back."""
    with open_capture(path) as reader:
        truth = reader.truth()
        fs = reader.info.sample_rate_hz
    clean, contact = truth["deflection_clean"], truth["contact"]
    period = fs / f0_hz
    n = int(clean.size // period)
    edges = (np.arange(n + 1) * period).astype(int)
    amplitude = np.array([np.ptp(clean[a:b]) / 2 for a, b in zip(edges[:-1], edges[1:])])
    touching = np.array([contact[a:b].any() for a, b in zip(edges[:-1], edges[1:])])
    settled = np.zeros(n, dtype=bool)
    run = 0
    for k in range(n):
        run = run + 1 if touching[k] else 0
        settled[k] = run > 100
    return float(np.median(amplitude[settled]))


def run_probeloss_on(path, **flags):
    from afmtool.analyses.probeloss import run_probeloss

    with open_capture(path) as reader:
        return run_probeloss(reader, resolve(ProbeLossParams, flags), _Discard())


class Cell:
    """One grid cell's prediction and measurement."""

    def __init__(self, fs, q, noise_nm, ratio, result, true_amplitude):
        results = result.results
        self.key = (fs, q, noise_nm, ratio)
        self.results = results
        self.warnings = result.warnings
        self.index = results.truth.index
        self.detectability = results.detectability
        self.predicted = self.detectability.predicted
        self.true_amplitude = true_amplitude
        self.estimated_amplitude = self.detectability.on_sample.amplitude

    def row(self) -> str:
        fs, q, noise, ratio = self.key
        p, m = self.predicted, self.index
        state = "beyond" if self.detectability.beyond_limit else "within"
        return (f"| {fs / 1e6:g} | {q:g} | {noise:g} | {ratio:g} ({self.true_amplitude / FREE_AMPLITUDE_NM:.2f}) | "
                f"{self.results.index.kind.value} | {state} | {self.detectability.information_limit_periods:.2f} | "
                f"{p.latency_periods:.2f} | {p.precision:.3f} | {m.recall:.3f} | "
                f"{m.median_latency_periods:.2f} | {m.time_precision:.3f} | "
                f"{100 * m.on_sample_flagged_fraction:.2f} % | "
                f"{self.estimated_amplitude:.2f}/{self.true_amplitude:.2f} |")

    def check(self) -> None:
        """Item 3's targets where predicted within reach, else item 2's: latency within 30 % (module docstring)."""
        assert abs(self.estimated_amplitude / self.true_amplitude - 1.0) <= 0.10, self.row()
        assert self.detectability.on_sample.amplitude_source.startswith("estimated from the capture")
        m = self.index
        if not self.detectability.beyond_limit:
            assert m.recall >= 0.95, self.row()
            assert m.median_latency_periods <= 3.0, self.row()
            assert m.time_precision >= 0.9, self.row()
            assert m.on_sample_flagged_fraction <= 0.02, self.row()
            return
        predicted = self.predicted.latency_periods
        assert abs(m.median_latency_periods / predicted - 1.0) <= LATENCY_TOLERANCE, self.row()
        if self.predicted.precision >= 0.9:
            assert m.time_precision >= 0.9, self.row()
        else:
            assert m.time_precision >= self.predicted.precision - 0.05, self.row()
        # the report and the headline say so up front
        assert self.warnings[0].startswith("beyond the detection limit"), self.warnings
        entries = headline("probeloss", self.results)
        assert entries[0]["name"] == "warning" and entries[0]["source"] == "detectability.beyond_limit"
        assert entries[0]["value"].startswith("beyond the detection limit") and "predicted latency" in entries[0]["value"]


def run_cell(tmp_path, fs, q, noise_nm, ratio) -> Cell:
    path = envelope_capture(tmp_path, fs, q, noise_nm, ratio)
    result = run_probeloss_on(path)
    cell = Cell(fs, q, noise_nm, ratio, result, true_on_sample_amplitude(path))
    print(cell.row())
    return cell


HEADER = ("| fs (MHz) | Q | noise (nm) | A_sp/A0 set (true) | index | predicted | information limit (periods) | "
          "predicted latency | predicted precision | recall | median latency | time precision | on-sample flagged | "
          "A_sp estimated/true (nm) |\n|" + "---|" * 14)

#: The CI grid: two cells within the limit, one beyond it, one at the corner of the envelope.
SHORT = [
    (2e6, 50.0, 0.03, 0.8),
    (5e5, 200.0, 0.05, 0.5),
    (5e5, 400.0, 0.1, 0.8),
    (1e6, 150.0, 0.06, 0.65),
]


@pytest.mark.parametrize(("fs", "q", "noise_nm", "ratio"), SHORT)
def test_envelope_short(tmp_path, fs, q, noise_nm, ratio):
    run_cell(tmp_path, fs, q, noise_nm, ratio).check()


FULL = [(fs, q, noise, ratio) for fs in (5e5, 1e6, 2e6) for q in (50.0, 100.0, 200.0, 400.0)
        for noise in (0.03, 0.1) for ratio in (0.5, 0.8)]


@pytest.mark.slow
def test_envelope_full(tmp_path):
    """Every cell of the grid; the table goes to stdout (and to $AFMTOOL_ENVELOPE_TABLE if set)."""
    cells, failures = [], []
    for fs, q, noise, ratio in FULL:
        cell = run_cell(tmp_path, fs, q, noise, ratio)
        cells.append(cell)
        try:
            cell.check()
        except AssertionError as exc:
            failures.append(f"{cell.row()} {exc}")
    table = "\n".join([HEADER, *(c.row() for c in cells)])
    print("\n" + table)
    if os.environ.get("AFMTOOL_ENVELOPE_TABLE"):
        with open(os.environ["AFMTOOL_ENVELOPE_TABLE"], "w") as f:
            f.write(table + "\n")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize(("fs", "q", "noise_nm", "ratio", "kind"), [
    (2e6, 100.0, 0.03, 0.8, "forcing"),
    (5e5, 400.0, 0.03, 0.5, "rms"),
])
def test_auto_and_explicit_agree_and_the_set_point_is_estimated(tmp_path, fs, q, noise_nm, ratio, kind):
    """Item 1: the index auto chose, given explicitly, is the same detector (same design, same switch, same
    scores), and the on-sample amplitude estimated without a set point is within 10 % of the truth's.  The
    two cells are ones where auto chooses the forcing detector and the thesis's index (the grid's table)."""
    path = envelope_capture(tmp_path, fs, q, noise_nm, ratio)
    auto = run_probeloss_on(path)
    assert auto.results.index.kind.value == kind
    explicit = run_probeloss_on(path, index=kind)
    a, e = auto.results.to_json(), explicit.results.to_json()
    for key in ("index", "truth", "events", "loss_fraction"):
        if key == "index":
            a[key].pop("reason"), e[key].pop("reason")
        assert json.dumps(a[key], sort_keys=True) == json.dumps(e[key], sort_keys=True), key
    estimated = auto.results.detectability.on_sample.amplitude
    true = true_on_sample_amplitude(path)
    print(f"on-sample amplitude estimated {estimated:.3f} nm, true {true:.3f} nm")
    assert abs(estimated / true - 1.0) <= 0.10


def test_latency_periods_trades_latency_for_precision(tmp_path):
    """Item 2: ``--latency-periods N`` gives the most precise design predicted within N periods; the default is
    the fastest predicted at precision >= 0.9."""
    path = envelope_capture(tmp_path, 5e5, 400.0, 0.1, 0.5)
    default = run_probeloss_on(path).results.detectability.predicted
    slower = run_probeloss_on(path, latency_periods=6.0).results.detectability.predicted
    faster = run_probeloss_on(path, latency_periods=2.0).results.detectability.predicted
    for name, p in (("default", default), ("N = 6", slower), ("N = 2", faster)):
        print(f"{name}: {p.latency_periods:.2f} periods at precision {p.precision:.3f}")
    assert default.precision >= 0.9
    assert slower.latency_periods <= 6.0 and slower.precision >= default.precision
    # no design reaches 2 periods here: the fastest one is taken, with the precision that costs
    assert faster.latency_periods < default.latency_periods and faster.precision < default.precision


def test_false_alarm_rate_by_rice_formula_matches_the_filter():
    """Item 1's false-alarm rate: Rice's formula (crossing_rate) against crossings counted on the forcing filter's
    own output of white noise, at margins where they are countable."""
    from afmtool.estimators.forcing_design import crossing_rate, reference_gain
    from afmtool.estimators.forcing_observer import forcing_model, forcing_phasors
    from afmtool.models.discretisation import discrete_denominator, line_numerator

    fs, f0, q, sigma = 5e5, 70e3, 200.0, 0.05
    model = forcing_model(tuple(discrete_denominator(f0, q, fs)), tuple(0.1 * np.asarray(line_numerator(f0, q, fs))),
                          2 * math.pi * f0 / fs)
    gain = reference_gain(model, sigma, fs / f0, 1.0)
    noise = sigma * np.random.default_rng(11).standard_normal(2_000_000)
    z = forcing_phasors(model, gain, noise, np.zeros(noise.size))[20_000:].real
    z = (z - z.mean()) / z.std()
    lag1 = float(np.corrcoef(z[1:], z[:-1])[0, 1])
    for margin in (1.5, 2.0, 2.5):
        counted = np.count_nonzero((z[1:] < -margin) & (z[:-1] >= -margin)) / (z.size - 1)
        predicted = crossing_rate(margin, lag1)
        print(f"{margin} std: {counted:.3e} crossings per sample counted, {predicted:.3e} predicted")
        assert abs(counted / predicted - 1.0) < 0.3
