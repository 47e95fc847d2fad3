"""Single-tone tapping: the free-air model from f0 and Q (issue 14, item 3).

f0 and Q come from the metadata, from ``--f0``/``--q`` or from a ``--model``
with continuous parameters; the gain and the drive-path phase are fitted at
the drive on the capture's own free-air segment; probeloss, reep and
kalman-bank accept the route and report it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool.analyses.freeair_route import resolve_free_air
from afmtool.errors import ConfigError
from afmtool.io.chunks import iter_chunks
from afmtool.models.free_air import FreeAirModel
from afmtool.records.common import Route
from tests import reference_sim as rs
from tests.conftest import run_cli
from tests.test_reep_reference import reference_reader

FS = 500e3
F0, Q, GAIN = 70e3, 200.0, 0.1


def _single_tone(hold="continuous", metadata_f0_q=True, duration_s=0.02, noise_nm=0.05):
    period = 1 / F0
    program, total = rs.loss_program(4e-3, 300 * period, [10 * period, 20 * period], 12.0, 40.0)
    cap = rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=min(duration_s, total),
                      drive=rs.Sine(F0 + 200.0, 30.0 / (GAIN * Q)), hold=hold, noise_nm=noise_nm, seed=5,
                      force=rs.ATTRACTIVE_SET, separation_nm=program)
    if not metadata_f0_q:
        cap.metadata.pop("cantilever")
    return cap


def _route(cap, **kwargs):
    reader = reference_reader(cap)
    route, _ = resolve_free_air(reader, iter_chunks(reader, ("deflection", "dither"), 1 << 16), **kwargs)
    return route


@pytest.mark.parametrize("hold", ["continuous", "zoh"])
def test_gain_and_delay_fitted_at_the_drive(hold):
    route = _route(_single_tone(hold), given=None)
    report = route.report
    print(f"{hold}: gain {report['fitted_gain']:.5f} nm/V, delay {report['fitted_delay_s'] * 1e9:.1f} ns; "
          f"{report['drive_hold_reason']}")
    assert report["route"] == "f0-q" and report["f0_q_from"] == "metadata"
    assert report["drive_hold"] == hold
    if hold == "continuous":
        assert report["fitted_gain"] == pytest.approx(GAIN, rel=2e-3)
        assert abs(report["fitted_delay_s"]) < 0.02 / FS
    else:  # the hold delays by half a sample and scales the line by sinc(f/fs)
        assert report["fitted_gain"] == pytest.approx(GAIN * np.sinc((F0 + 200) / FS), rel=2e-3)
        assert report["fitted_delay_s"] == pytest.approx(0.5 / FS, rel=0.02)
    # the model reproduces the capture's response at the drive
    from afmtool.analyses.freeair_route import line_response
    from afmtool.models.discretisation import sampled_response

    seg = route.segment.data
    measured = line_response(seg["deflection"], seg["dither"], FS, [F0 + 200.0])
    model = sampled_response(route.model.numerator, route.model.denominator, F0 + 200.0, FS)
    assert abs(model / measured - 1) < 1e-9


def test_flags_and_given_model_routes():
    cap = _single_tone(metadata_f0_q=False)
    flags = _route(cap, given=None, f0_hz=F0, q=Q)
    assert flags.report["f0_q_from"] == "flags" and flags.model.source == "f0-q:flags"
    thermal = FreeAirModel(F0, Q, gain=1.0, source="thermal")  # a thermal tune knows no gain
    given = _route(cap, given=thermal)
    assert given.report["f0_q_from"] == "model"
    assert given.model.gain == pytest.approx(GAIN, rel=2e-3)
    forced = _route(cap, given=None, f0_hz=F0, q=Q, drive_hold="zoh")
    assert forced.report["drive_hold"] == "zoh" and forced.report["fitted_delay_s"] == 0.0
    with pytest.raises(ConfigError, match="go together"):
        _route(cap, given=None, f0_hz=F0)
    # with neither metadata f0/Q nor a multi-line dither the ARX fit is the last resort
    no_segment = dict(cap.metadata)
    no_segment.pop("free_air")
    bare = rs.Capture(cap.sample_rate_hz, cap.channels, cap.units, cap.truth, no_segment)
    with pytest.raises(ConfigError, match="free-air segment"):
        _route(bare, given=None, f0_hz=F0, q=Q)
    assumed = _route(bare, given=thermal)
    assert assumed.report["drive_hold"] == "continuous" and "assumed" in assumed.report["drive_hold_reason"]


def test_probeloss_and_reep_cli_report_the_route(tmp_path):
    path = rs.write_capture_h5(tmp_path / "single.h5", _single_tone(metadata_f0_q=False, duration_s=0.03))
    out = tmp_path / "pl"
    cli = run_cli("probeloss", path, "--f0", F0, "--q", Q, "--out", out)
    assert cli.returncode == 0, cli.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    route = report["results"]["free_air_route"]
    assert route["route"] == "f0-q" and route["f0_q_from"] == "flags" and route["drive_hold"] == "continuous"
    assert report["results"]["truth"]["index"]["recall"] == 1.0
    assert "amplitude baseline skipped" in cli.stderr.decode()
    cli = run_cli("reep", path, "--f0", F0, "--q", Q, "--drive-hold", "zoh", "--out", tmp_path / "reep")
    assert cli.returncode == 0, cli.stderr.decode()
    route = json.loads((tmp_path / "reep" / "report.json").read_text())["results"]["free_air_route"]
    assert route["route"] == "f0-q" and route["drive_hold"] == "zoh" and route["drive_hold_option"] == "zoh"
    cli = run_cli("probeloss", path, "--f0", F0, "--out", tmp_path / "bad")
    assert cli.returncode == 2 and "give both" in cli.stderr.decode()
    assert not (tmp_path / "bad").exists()


def test_kalman_bank_accepts_the_f0_q_route():
    from afmtool.analyses.kalman_bank import run_kalman_bank
    from afmtool.config import resolve
    from afmtool.config.params import KalmanBankParams
    from tests.test_kalman_bank import Columns
    from tests.test_kalman_bank_reference import F0 as F0_BANK
    from tests.test_kalman_bank_reference import Q as Q_BANK
    from tests.test_kalman_bank_reference import _force_curve

    cap = rs.simulate(
        f0_hz=F0_BANK, q=Q_BANK, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=0.2,
        drive=rs.three_sine(F0_BANK, 6000.0, 20.0 / Q_BANK, 0.25), noise_nm=0.05, seed=1,
        force=rs.ATTRACTIVE_SET, separation_nm=_force_curve(duration_s=0.2), record_z_piezo=True,
    )
    params = resolve(KalmanBankParams, {"f0_hz": F0_BANK, "q": Q_BANK, "n_filters": 3})
    res = run_kalman_bank(reference_reader(cap), params, Columns()).results
    assert res.free_air_route.route is Route.F0_Q and res.free_air_route.f0_q_from == "flags"
    assert res.free_air_model.source == "f0-q:flags"
    assert res.free_air_model.gain == pytest.approx(1.0, rel=2e-3)
    assert len(res.filters) == 3


def test_a_phase_matching_neither_hold_is_reported():
    """f0 60 Hz off shifts the phase at the drive (200 Hz above f0) by about 9 deg: neither hold fits; a warning says so."""
    cap = _single_tone(metadata_f0_q=False)
    route = _route(cap, given=None, f0_hz=F0 + 60.0, q=Q)
    print(route.warnings)
    assert len(route.warnings) == 1
    assert "f0/Q may be off" in route.warnings[0]
    assert not _route(cap, given=None, f0_hz=F0, q=Q).warnings
