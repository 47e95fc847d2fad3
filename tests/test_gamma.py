"""identify gamma: Γ_IR,ts with the feed-through removed (thesis §6.6.1, eqs. 6.15 and 6.16).

Truth: the ``thermal-sweep`` scenario's continuous-time small-signal model
(:meth:`afmtool.sim.thermal_sweep.ThermalSweepParams.model`).  The sweeps are
simulated once per module: a repeated chirp (0.5 s at 1 MHz) and log-spaced
stepped sines (1 s from 100 Hz), each near the sample and in contact.
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest
from scipy.optimize import brentq

from afmtool import sim
from afmtool.errors import InputError
from afmtool.estimators.frequency_response import FrequencyResponse
from afmtool.estimators.sensing_gamma import (
    auto_nperseg,
    canonical_scale,
    combine_gamma,
    feedthrough_rise,
    fit_feedthrough,
    resample_response,
    responses_from_chunks,
    sensing_summary,
    uncorrected_response,
    usable_mask,
)
from afmtool.io.capture import Chunk
from tests.conftest import SAMPLE_DATA, run_cli, validate_report
from tests.golden import assert_matches_golden

SWEEPS = {
    "chirp": {},
    "stepped": {"drive": "stepped", "start_hz": 100.0, "duration_s": 1.0},
}
MODEL = sim.scenario_defaults("thermal-sweep").model()


def _gamma(drive: str, chunk_samples: int | None = None):
    over = SWEEPS[drive]
    near = sim.simulate("thermal-sweep", over, seed=1)
    contact = sim.simulate("thermal-sweep", {**over, "contact": True}, seed=2)
    method = "stepped" if drive == "stepped" else "h1"
    nperseg = auto_nperseg(near.n_samples)

    def responses(cap, ys):
        n = cap.n_samples
        step = chunk_samples or n
        chunks = [Chunk(a, {k: v[a : a + step] for k, v in cap.data.items()}) for a in range(0, n, step)]
        return responses_from_chunks(chunks, cap.sample_rate_hz, "v_sub", ys, method=method, nperseg=nperseg,
                                     segments=cap.metadata.get("segments"))

    r = responses(near, ("thermal_current", "deflection"))
    c = responses(contact, ("thermal_current",))
    return combine_gamma(r["thermal_current"], r["deflection"], c["thermal_current"])


@pytest.fixture(scope="module")
def gammas():
    return {drive: _gamma(drive) for drive in SWEEPS}


def _band(f):
    return (f >= 100.0) & (f <= 1e5)


def _truth_summary(summary, dense=400):
    dc = MODEL.ir_ts(np.array([0.0]))[0].real
    bw = brentq(lambda f: abs(MODEL.ir_ts(np.array([f]))[0]) - abs(dc) / math.sqrt(2), 10.0, 1e6)
    f = np.logspace(np.log10(summary.roll_off_band_hz[0]), np.log10(summary.roll_off_band_hz[1]), dense)
    slope = np.polyfit(np.log10(f), 20 * np.log10(np.abs(MODEL.ir_ts(f))), 1)[0]
    return dc, bw, slope


@pytest.mark.parametrize("drive", list(SWEEPS))
def test_sensing_function_within_1_db_and_5_degrees(gammas, drive):
    g = gammas[drive]
    f = g.frequency_hz
    band = _band(f)
    assert np.all(usable_mask(g, 0.9)[band]), "every bin from 100 Hz to 100 kHz must be usable"
    ratio = g.ir_ts.response[band] / MODEL.ir_ts(f[band])
    err_db = np.max(np.abs(20 * np.log10(np.abs(ratio))))
    err_deg = np.max(np.abs(np.angle(ratio, deg=True)))
    print(f"{drive}: |Gamma_IR,ts| max error {err_db:.3f} dB, phase {err_deg:.2f} deg over {band.sum()} bins")
    assert err_db < 1.0
    assert err_deg < 5.0


@pytest.mark.parametrize("drive", list(SWEEPS))
def test_bandwidth_and_roll_off(gammas, drive):
    g = gammas[drive]
    summary = sensing_summary(g.ir_ts, usable_mask(g, 0.9))
    dc, bw, slope = _truth_summary(summary)
    print(
        f"{drive}: DC {summary.dc_sensitivity:.5f} (truth {dc:.5f}) uA/nm, bandwidth {summary.bandwidth_hz:.1f} "
        f"(truth {bw:.1f}) Hz, roll-off {summary.roll_off_db_per_decade:.3f} (truth {slope:.3f}) dB/decade "
        f"over {summary.roll_off_band_hz}"
    )
    assert summary.bandwidth_hz == pytest.approx(bw, rel=0.05)
    assert abs(summary.roll_off_db_per_decade - slope) < 1.0
    assert summary.dc_sensitivity == pytest.approx(dc, rel=0.02)


@pytest.mark.parametrize("drive", list(SWEEPS))
def test_uncorrected_gamma_shows_the_false_high_frequency_rise(gammas, drive):
    g = gammas[drive]
    mask = usable_mask(g, 0.9)
    rise = feedthrough_rise(g.ir_ts, g.ir_ts_uncorrected, mask)
    f = g.frequency_hz
    band = _band(f)
    err_unc = np.max(np.abs(20 * np.log10(np.abs(g.ir_ts_uncorrected.response[band] / MODEL.ir_ts(f[band])))))
    print(f"{drive}: eq. 6.16 exceeds eq. 6.15 by {rise.excess_db:.2f} dB over {rise.band_hz} Hz; slopes "
          f"{rise.uncorrected_slope_db_per_decade:.1f} vs {rise.corrected_slope_db_per_decade:.1f} dB/decade; "
          f"eq. 6.16 error up to 100 kHz {err_unc:.2f} dB")
    assert rise.excess_db > 3.0
    assert rise.uncorrected_slope_db_per_decade > 0.0 > rise.corrected_slope_db_per_decade
    assert err_unc > 1.0  # leaving the feed-through in would fail the 1 dB criterion
    sp = fit_feedthrough(g.feedthrough, 0.9)  # Fig. 6.18's fit: a coupling capacitance
    print(f"{drive}: feed-through C_c {sp.capacitance_pf:.4f} pF (truth 2 pF), pole {sp.pole_hz / 1e3:.0f} kHz")
    assert sp.capacitance_pf == pytest.approx(MODEL.feedthrough_f * 1e12, rel=0.05)
    # and eq. 6.16 is eq. 6.15 with a zero feed-through
    np.testing.assert_allclose(uncorrected_response(g.ir_v, g.ts_v).response, g.ir_ts_uncorrected.response)


def test_stepped_and_chirp_agree_where_both_are_coherent(gammas):
    """The measured FRFs within 0.5 dB where both coherences exceed 0.95.

    Γ_IR,ts is derived (eq. 6.15) and has no coherence of its own; above
    ~100 kHz it is the small difference of two large currents, so it is
    compared where both propagated relative errors are below 2 %.
    """
    stepped, chirp = gammas["stepped"], gammas["chirp"]
    f = stepped.frequency_hz
    worst = {}
    for name in ("ir_v", "ts_v", "feedthrough", "ir_ts"):
        a = getattr(stepped, name)
        b = resample_response(getattr(chirp, name), f)
        if name == "ir_ts":
            ok = (a.magnitude_std < 0.02 * np.abs(a.response)) & (b.magnitude_std < 0.02 * np.abs(b.response))
        else:
            ok = (a.coherence > 0.95) & (b.coherence > 0.95)
        ok &= np.isfinite(b.response)
        diff = np.abs(20 * np.log10(np.abs(a.response[ok] / b.response[ok])))
        worst[name] = (round(float(diff.max()), 4), int(ok.sum()))
        assert np.count_nonzero(ok) >= (5 if name == "feedthrough" else 25)
        assert diff.max() < 0.5
    print("stepped vs chirp, max |dB| difference (compared steps):", worst)


def test_streaming_chunks_equal_one_batch(gammas):
    chunked = _gamma("chirp", chunk_samples=10007)
    batch = gammas["chirp"]
    for name in ("ir_v", "ts_v", "feedthrough", "ir_ts"):
        a, b = getattr(chunked, name).response, getattr(batch, name).response
        ok = np.isfinite(b)
        np.testing.assert_allclose(a[ok], b[ok], rtol=1e-12, atol=1e-12 * np.max(np.abs(b[ok])))


def test_propagated_error_matches_monte_carlo(rng):
    """σ_Γ² = (σ_A² + σ_B²)/|G|² + |Γ|²σ_G²/|G|² against scatter of (A − B)/G."""
    from afmtool.estimators.sensing_gamma import sensing_response

    f = np.array([1.0, 2.0])
    a, b, g = np.array([2.0 + 1j, 1.0]), np.array([0.3j, 0.1]), np.array([1.5 - 0.5j, 0.8j])
    sa, sb, sg = np.array([0.02, 0.01]), np.array([0.01, 0.005]), np.array([0.015, 0.01])

    def fr(h, s):
        return FrequencyResponse(f, h, np.ones(2), s, s / np.abs(h), "h1")

    est = sensing_response(fr(a, sa), fr(g, sg), fr(b, sb))
    n = 200_000

    def noisy(h, s):  # circular complex noise with σ per |H| (σ/√2 per component)
        return h + s * (rng.standard_normal((n, 2)) + 1j * rng.standard_normal((n, 2))) / math.sqrt(2)

    draws = (noisy(a, sa) - noisy(b, sb)) / noisy(g, sg)
    scatter = np.sqrt(np.mean(np.abs(draws - draws.mean(axis=0)) ** 2, axis=0))
    np.testing.assert_allclose(est.magnitude_std, scatter, rtol=0.03)


def test_resample_is_exact_for_a_power_law():
    f = np.logspace(2, 5, 31)
    h = 3.0 * (1j * f) ** -0.5
    fr = FrequencyResponse(f, h, np.ones_like(f), 0.01 * np.abs(h), np.full(f.size, 0.01), "stepped")
    target = np.array([50.0, 150.0, 3333.0, 99999.0, 2e5])
    out = resample_response(fr, target)
    np.testing.assert_allclose(out.response[1:4], 3.0 * (1j * target[1:4]) ** -0.5, rtol=1e-12)
    assert np.isnan(out.response[0]) and np.isnan(out.response[4])


def test_units_are_checked():
    assert canonical_scale("current", "A", "thermal_current") == (1e6, False)
    assert canonical_scale("length", "", "deflection") == (1.0, True)
    with pytest.raises(InputError, match="channel 'deflection' has units 'V'"):
        canonical_scale("length", "V", "deflection")


# ----------------------------------------------------------------------------- command line


def test_golden_report_for_the_sample_sweeps(tmp_path):
    out = tmp_path / "gamma"
    result = run_cli("identify", "gamma", SAMPLE_DATA / "thermal_sweep_near.h5", "--contact",
                     SAMPLE_DATA / "thermal_sweep_contact.h5", "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    assert json.loads((out / "report.json").read_text()) == report
    assert {i["role"] for i in report["inputs"]} == {"sweep", "contact"}
    for name in ("gamma_ir_ts.png", "feedthrough.png", "frf_ir_ts.csv", "frf_feedthrough.csv", "gamma.h5"):
        assert (out / name).is_file()
    with h5py.File(out / "gamma.h5") as h5:
        f = h5["frf/frequency_hz"][()]
        for name in ("ir_v", "ts_v", "feedthrough", "ir_ts", "ir_ts_uncorrected"):
            ds = h5[f"frf/{name}"]
            assert ds.dtype.kind == "c" and ds.shape == f.shape
        for name in ("coherence_ir_v", "coherence_ts_v", "coherence_feedthrough"):
            assert h5[f"frf/{name}"].shape == f.shape
        assert h5["frf/ir_ts"].attrs["units"] == "uA/nm"
    header = (out / "frf_ir_ts.csv").read_text().splitlines()[0]
    assert header == "frequency_hz,magnitude,magnitude_db,phase_deg,coherence,magnitude_std,phase_std_deg"
    res = report["results"]
    assert res["bandwidth_hz"] == pytest.approx(11_962, rel=0.05)  # the sample's truth (short, coarse sweep)
    assert res["feedthrough_rise"]["excess_db"] > 3.0
    assert_matches_golden(report, "gamma_thermal_sweep")


def test_missing_channel_and_bad_options_are_clean_errors(tmp_path):
    contact = SAMPLE_DATA / "thermal_sweep_contact.h5"
    for args, message in (
        ([SAMPLE_DATA / "thermal_sweep_near.h5", "--contact", contact, "--min-coherence", "1.5"], "min_coherence=1.5"),
        ([SAMPLE_DATA / "ltv_step.h5", "--contact", contact], "no channel 'v_sub'"),
        ([contact, "--contact", contact, "--stepped", "--h1"], "at most one"),
    ):
        result = run_cli("identify", "gamma", *args, "--out", tmp_path / "o")
        assert result.returncode == 2, result.stderr.decode()
        assert message in result.stderr.decode()
        assert not (tmp_path / "o").exists()


def test_stepped_segments_are_detected_when_the_metadata_lacks_them():
    over = SWEEPS["stepped"]
    near = sim.simulate("thermal-sweep", over, seed=1)
    contact = sim.simulate("thermal-sweep", {**over, "contact": True}, seed=2)

    def responses(cap, ys):
        return responses_from_chunks([Chunk(0, dict(cap.data))], cap.sample_rate_hz, "v_sub", ys, method="stepped",
                                     nperseg=0, segments=None)

    r, c = responses(near, ("thermal_current", "deflection")), responses(contact, ("thermal_current",))
    g = combine_gamma(r["thermal_current"], r["deflection"], c["thermal_current"])
    f = g.frequency_hz
    band = _band(f) & usable_mask(g, 0.9)
    ratio = g.ir_ts.response[band] / MODEL.ir_ts(f[band])
    print(f"detected {f.size} of {len(near.metadata['segments'])} steps; Gamma_IR,ts max error "
          f"{np.max(np.abs(20 * np.log10(np.abs(ratio)))):.3f} dB, {np.max(np.abs(np.angle(ratio, deg=True))):.2f} deg")
    assert f.size >= 30 and np.count_nonzero(band) >= 25
    assert np.max(np.abs(20 * np.log10(np.abs(ratio)))) < 1.0
    assert np.max(np.abs(np.angle(ratio, deg=True))) < 5.0


def test_split_steps_are_merged():
    from afmtool.estimators.sensing_gamma import merge_split_steps
    from afmtool.estimators.stepped_sine import SineSegment

    pieces = [SineSegment(0.0, 0.1, 100.0), SineSegment(0.1, 0.102, 103.0), SineSegment(0.1025, 0.2, 101.0),
              SineSegment(0.2, 0.3, 126.0)]
    merged = merge_split_steps(pieces)
    assert merged == (SineSegment(0.0, 0.2, 100.0), SineSegment(0.2, 0.3, 126.0))
