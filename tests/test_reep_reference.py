"""REEP's accuracy tests on captures afmtool did not simulate (issue 14, acceptance 2 and 3).

The same settings and tolerances as ``tests/test_reep.py`` (off-sample f0' within
2 Hz and Q' within 2 %; a step tracked to 10 % within 2 ms), on the
independent reference simulator with a continuous and a held drive, next to
afmtool's own ``ltv`` scenario.  The drive's hold is detected, not given.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool import sim
from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from afmtool.io.capture import ChannelSpec
from afmtool.io.memory import ArrayReader
from tests import reference_sim as rs
from tests.memory_sink import MemorySink

FS = 500e3
F0, Q, GAIN = 70_000.0, 200.0, 0.1
AMPLITUDE_NM = 25.0


def reference_reader(cap: rs.Capture, name: str = "reference") -> ArrayReader:
    """An in-memory afmtool reader over a reference capture (what write_capture_h5 + open_capture give)."""
    specs = tuple(ChannelSpec(k, cap.units[k]) for k in cap.channels)
    return ArrayReader(cap.sample_rate_hz, specs, cap.channels, cap.metadata, cap.truth, name)


def _three_sine_capture(hold: str, duration_s: float, seed: int, **kwargs) -> rs.Capture:
    drive = rs.three_sine(F0, 6000.0, AMPLITUDE_NM / (GAIN * Q), 0.5)
    return rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=duration_s, drive=drive,
                       hold=hold, noise_nm=0.05, seed=seed, **kwargs)


def _source(kind: str, duration_s: float, seed: int, **kwargs):
    """(reader, expected hold) for afmtool's ltv scenario or the reference simulator."""
    if kind == "afmtool-ltv":
        step = kwargs.pop("ltv_step", {"step_time_s": 1.0})
        cap = sim.simulate("ltv", {"duration_s": duration_s, **step}, seed=seed)
        return ArrayReader(cap.sample_rate_hz, cap.channels, cap.data, cap.metadata, cap.truth, "ltv"), "continuous"
    hold = kind.removeprefix("reference-")
    kwargs.pop("ltv_step", None)
    return reference_reader(_three_sine_capture(hold, duration_s, seed, **kwargs)), hold


def _run(reader, **overrides):
    columns = MemorySink()
    result = run_reep(reader, resolve(ReepParams, overrides), columns)
    return result, columns


KINDS = ["afmtool-ltv", "reference-continuous", "reference-zoh"]


@pytest.mark.parametrize("kind", KINDS)
def test_off_sample_accuracy_on_every_simulator(kind):
    reader, hold = _source(kind, 0.1, seed=3, free_air_s=0.1)
    result, columns = _run(reader, decimate=1)
    route = result.results.free_air_route
    assert route.route.value == "segment" and route.drive_hold.value == hold, route.drive_hold_reason
    t, f0, q = columns["t"], columns["f0_hz"], columns["q"]
    settled = t > 0.04
    f0_error = np.mean(f0[settled]) - F0
    q_error = np.mean(q[settled]) / Q - 1.0
    print(f"{kind}: off-sample f0' error {f0_error:+.3f} Hz, Q' error {100 * q_error:+.3f} %")
    assert abs(f0_error) <= 2.0
    assert abs(q_error) <= 0.02
    assert np.percentile(np.abs(f0[settled] - F0), 95) < 10.0


@pytest.mark.parametrize("kind", KINDS)
def test_step_tracking_on_every_simulator(kind):
    step_f0, step_q = F0 - 350.0, 90.0

    def f0_of_t(t):
        return np.where(t < 0.04, F0, step_f0)

    def q_of_t(t):
        return np.where(t < 0.04, Q, step_q)

    extra = {"f0_of_t": f0_of_t, "q_of_t": q_of_t, "free_air_s": 0.04,
             "ltv_step": {"step_time_s": 0.04, "step_f0_hz": step_f0, "step_q": step_q}}
    reader, _ = _source(kind, 0.06, seed=4, **extra)
    _, columns = _run(reader, decimate=1, free_air="0.005:0.035")
    t, f0, q = columns["t"], columns["f0_hz"], columns["q"]
    after = t >= 0.04
    ok = (np.abs(f0 - step_f0) <= 0.1 * 350.0) & (np.abs(q - step_q) <= 0.1 * (Q - step_q))
    last_bad = np.flatnonzero(after & ~ok)
    settle_s = (t[last_bad[-1]] - 0.04) if last_bad.size else 0.0
    print(f"{kind}: REEP settles to 10 % of a (-350 Hz, -110) step in {settle_s * 1e3:.3f} ms")
    assert ok[-1]
    assert settle_s <= 2e-3
