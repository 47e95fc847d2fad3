"""REEP end to end against simulator ground truth (issue: REEP acceptance list)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from afmtool import sim
from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from afmtool.errors import InputError
from afmtool.io.memory import ArrayReader
from afmtool.models.free_air import FreeAirModel
from tests.conftest import run_cli, validate_report
from tests.memory_sink import MemorySink

FS = 500e3


def _reader(captured, name="ltv"):
    return ArrayReader(
        captured.sample_rate_hz, captured.channels, captured.data, captured.metadata, captured.truth, name
    )


def _run(captured, **overrides):
    params = resolve(ReepParams, overrides)
    columns = MemorySink()
    result = run_reep(_reader(captured), params, columns)
    return result, columns


@pytest.fixture(scope="module")
def ltv_constant():
    """The acceptance setting: 500 kHz, f0 70 kHz, Q 200, three sines (~25 nm), 0.05 nm noise."""
    return sim.simulate("ltv", {"duration_s": 0.1, "step_time_s": 1.0}, seed=3)


def test_off_sample_accuracy(ltv_constant):
    result, columns = _run(ltv_constant, decimate=1)
    t, f0, q = columns["t"], columns["f0_hz"], columns["q"]
    amplitude = result.results.summary.amplitude.mean
    assert 20 < amplitude < 30  # "about 25 nm"
    settled = t > 0.04
    f0_error = np.mean(f0[settled]) - 70_000.0
    q_error = np.mean(q[settled]) / 200.0 - 1.0
    print(f"off-sample f0' error {f0_error:+.3f} Hz, Q' error {100 * q_error:+.3f} %")
    assert abs(f0_error) <= 2.0
    assert abs(q_error) <= 0.02
    # every settled sample, not just the mean, stays near the truth
    assert np.percentile(np.abs(f0[settled] - 70_000.0), 95) < 10.0


def test_step_tracking_within_2ms():
    captured = sim.simulate(
        "ltv",
        {"duration_s": 0.06, "step_time_s": 0.04, "step_f0_hz": 70_000.0 - 350.0, "step_q": 90.0},
        seed=4,
    )
    _, columns = _run(captured, decimate=1, free_air="0.005:0.035")
    t, f0, q = columns["t"], columns["f0_hz"], columns["q"]
    after = t >= 0.04
    # time after the step from which the estimate stays within 10 % of the step size
    f0_ok = np.abs(f0 - (70_000.0 - 350.0)) <= 0.1 * 350.0
    q_ok = np.abs(q - 90.0) <= 0.1 * 110.0
    both = f0_ok & q_ok & after
    last_bad = np.flatnonzero(after & ~(f0_ok & q_ok))
    settle_s = (t[last_bad[-1]] - 0.04) if last_bad.size else 0.0
    print(f"REEP settles to 10 % of a (-350 Hz, -110) step in {settle_s * 1e3:.3f} ms at lambda=0.995")
    assert both[-1]
    assert settle_s <= 2e-3


def test_bias_compensation_helps_at_high_noise():
    captured = sim.simulate("ltv", {"duration_s": 0.1, "step_time_s": 1.0, "measurement_noise_nm": 0.5}, seed=5)
    errors = {}
    for compensated in (True, False):
        _, columns = _run(captured, decimate=1, bias_compensation=compensated, free_air="0.0:0.05")
        settled = columns["t"] > 0.03
        errors[compensated] = abs(np.mean(columns["q"][settled]) / 200.0 - 1.0)
    print(f"Q' error at 0.5 nm noise: BCEWRLS {100 * errors[True]:.2f} %, plain EWRLS {100 * errors[False]:.2f} %")
    assert errors[True] < 0.5 * errors[False]


@pytest.mark.parametrize("decimate", [1, 7])
def test_chunk_size_independence(ltv_constant, decimate):
    """1e3-, 1e5-sample and single-chunk runs agree; with 7 the kept samples straddle the chunk ends."""
    outputs = []
    for chunk in (1000, 100_000, 1 << 24):
        _, columns = _run(ltv_constant, decimate=decimate, chunk_samples=chunk)
        outputs.append({k: columns[k] for k in ("t", "f0_hz", "q", "b1", "b0", "amplitude", "phase_deg", "sigma2")})
    for other in outputs[1:]:
        for name, values in outputs[0].items():
            np.testing.assert_allclose(other[name], values, rtol=1e-9, atol=0, equal_nan=True, err_msg=name)


def test_reep_command_writes_outputs(tmp_path, ltv_constant):
    capture = tmp_path / "ltv.h5"
    result = run_cli("simulate", "ltv", "-o", capture, "--set", "duration_s=0.03", "--set", "step_time_s=0.02")
    assert result.returncode == 0, result.stderr.decode()
    out = tmp_path / "reep"
    result = run_cli("reep", capture, "--out", out, "--json", "--lambda", "0.99")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    assert report["parameters"]["lam"] == 0.99
    assert sorted(p.name for p in out.iterdir()) == sorted(report["outputs"])
    assert {"reep.h5", "report.json", "config.toml", "free_air.json"} <= set(report["outputs"])
    assert "lam = 0.99" in (out / "config.toml").read_text()
    with h5py.File(out / "reep.h5") as f:
        for name, units in (("t", "s"), ("f0_hz", "Hz"), ("q", ""), ("amplitude", "nm"), ("phase_deg", "deg")):
            assert f[name].attrs["units"] == units
        decimate = report["results"]["decimate"]
        # rows at REEP's resolution (issue 33): 8 to 11 rows per forgetting window of 100 samples
        assert 8 <= report["results"]["window_samples"] / decimate < 11
        assert f.attrs["row_every_samples"] == decimate and f.attrs["rows"] == "resolution"
        assert len(f["t"]) == 15_000 // decimate
    assert report["results"]["window_samples"] == pytest.approx(100.0)
    assert report["results"]["window_us"] == pytest.approx(200.0)
    # the segment statistics are gathered in the stream; they equal those read back from reep.h5
    from afmtool.analyses.reep_timeseries import segment_statistics

    results = report["results"]
    read_back = segment_statistics(out / "reep.h5", results["summary_after_warmup_samples"] / FS,
                                   results["free_air_segment_s"]).to_json()
    assert set(results["segments"]) == {"free_air", "after_free_air"} == set(read_back)
    # reep.h5 stores f0' and Q' as float32 (issue 33): 70 kHz to 0.004 Hz, so the file's mean agrees to
    # float32 rounding (1e-7) and its scatter of ~1 Hz to that rounding's share of it (1e-4)
    for segment, stats in read_back.items():
        assert results["segments"][segment]["t_s"] == pytest.approx(stats["t_s"], rel=1e-12)
        for name in ("f0_hz", "q"):
            assert results["segments"][segment][name]["count"] == stats[name]["count"] > 0
            assert results["segments"][segment][name]["mean"] == pytest.approx(stats[name]["mean"], rel=1e-7)
            assert results["segments"][segment][name]["std"] == pytest.approx(stats[name]["std"], rel=1e-4)
        assert results["segments"][segment]["f0_row_std_hz"] == pytest.approx(stats["f0_row_std_hz"], rel=1e-6)


def test_single_sine_warns_not_persistently_exciting():
    captured = sim.simulate("ltv", {"duration_s": 0.03, "drive": "sine", "step_time_s": 1.0}, seed=1)
    # without the cantilever's f0/Q the five-parameter free-air fit refuses a single sine, with a way out
    bare = {k: v for k, v in captured.metadata.items() if k != "cantilever"}
    with pytest.raises(InputError, match="--model"):
        run_reep(ArrayReader(FS, captured.channels, captured.data, bare, captured.truth, "bare"),
                 resolve(ReepParams, {}), MemorySink())
    # with metadata f0/Q it takes the f0/Q route (issue 14 item 3) and still warns
    routed = run_reep(_reader(captured), resolve(ReepParams, {}), MemorySink())
    assert routed.results.free_air_route.route.value == "f0-q"
    assert any("persistently exciting" in w for w in routed.warnings)
    # given a model, REEP runs and warns in its report
    model = FreeAirModel(f0_hz=70_000.0, q=200.0, gain=1.0)
    params = resolve(ReepParams, {})
    result = run_reep(_reader(captured), params, MemorySink(), model=model)
    assert any("persistently exciting" in w for w in result.warnings)
    assert len(result.results.excitation_lines_hz) == 1


def test_needs_free_air_model(tmp_path):
    capture = tmp_path / "plain.csv"
    capture.write_text("# sample_rate_hz: 500000\ndither,deflection\n" + "0.1,0.2\n" * 2000)
    out = tmp_path / "out"
    result = run_cli("reep", capture, "--out", out)
    assert result.returncode == 2
    assert "free-air" in result.stderr.decode()
    assert not out.exists()


def test_real_kpfm_record_reports_f0_and_says_q_is_not_identifiable(shared, tmp_path):
    """Issue 27 item 3: output-only REEP on the real FM-KPFM record from the CLI.

    The loop holds the oscillation, so REEP's poles sit on the unit circle
    (b0 ≈ 1, on either side): half the rows were flagged "not under-damped"
    and the Q' card read (0.0 ± 1.5)e+07.  f0' is the frequency the poles
    oscillate at, defined on either side; Q' is not identifiable and has no card.
    """
    out = tmp_path / "kpfm"
    result = run_cli("reep", shared / "data" / "fm_kpfm_displacement.h5", "--channel", "deflection=/s",
                     "--sample-rate", "1.15e6", "--no-input", "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    results = report["results"]
    assert results["q_identifiable"] is False
    assert results["drive_frequency_hz"] == pytest.approx(60_630, abs=200)
    assert results["validity"]["flags"]["fraction"] <= 0.10
    assert results["segments"]["settled"]["f0_hz"]["mean"] == pytest.approx(60_630.0, abs=15.0)
    entries = report["headline"]
    assert entries[0]["name"] == "warning" and "not identifiable" in entries[0]["text"]
    assert [e["name"] for e in entries[1:] if e["name"].startswith("f0'")] == ["f0' after the warm-up"]
    assert not any("Q'" in e["name"] for e in entries[1:])
    with h5py.File(out / "reep.h5") as f:
        flag, q, f0_std = f["flag"][()], f["q"][()], f["f0_std_hz"][()]
    assert np.isnan(q).all()
    settled = flag == 0
    assert np.isfinite(f0_std[settled]).all() and np.median(f0_std[settled]) < 5.0


def test_images_from_scan_geometry(tmp_path):
    """f0' switches every half line period, so trace and retrace images differ by the step."""
    from afmtool.io.capture import ChannelSpec  # noqa: F401 - documents the channel records used
    from afmtool.io.hdf5 import Hdf5Writer
    from afmtool.report.images import read_gsf

    captured = sim.simulate(
        "ltv",
        {"duration_s": 0.08, "step_time_s": 0.02, "step_repeat_s": 0.01, "step_f0_hz": 69_500.0, "step_q": 200.0},
        seed=2,
    )
    metadata = dict(captured.metadata)
    metadata["scan"] = {"lines": 4, "pixels_per_line": 8, "scan_size_m": 2e-6, "line_rate_hz": 50.0,
                        "trace_retrace": True}
    path = tmp_path / "scan.h5"
    writer = Hdf5Writer(path, captured.sample_rate_hz, captured.channels, metadata)
    writer.write(captured.data)
    writer.close()
    out = tmp_path / "reep"
    result = run_cli("reep", path, "--out", out, "--json", "--free-air", "0:0.02")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    for quantity in ("f0_hz", "q", "amplitude", "phase_deg"):
        for direction in ("trace", "retrace"):
            assert f"{quantity}_{direction}.png" in report["outputs"]
            assert f"{quantity}_{direction}.gsf" in report["outputs"]
    with h5py.File(out / "reep.h5") as f:
        trace = f["images/f0_hz/trace"][()]
        retrace = f["images/f0_hz/retrace"][()]
    assert trace.shape == (4, 8)
    # line 0 is all before the first switch; lines 1-3: trace after a switch to 69.5 kHz,
    # retrace after the switch back.  The settling inside each half line blurs the pixels
    # next to the switch, so compare the line means.
    # the first 2 ms (REEP's warm-up, 5 windows) are flagged not converged: pixel 0 (1.25 ms) and part of pixel 1
    assert np.isnan(trace[0, 0]) and np.isfinite(trace[0, 1:]).all() and np.isfinite(trace[1:]).all()
    assert np.mean(trace[0, 1:]) == pytest.approx(70_000.0, abs=20.0)
    for line in (1, 2, 3):
        assert np.mean(trace[line]) < np.mean(retrace[line]) - 250.0
    gsf = read_gsf(out / "f0_hz_trace.gsf")
    assert gsf.data.shape == (4, 8)
    np.testing.assert_allclose(gsf.data[::-1], trace.astype(np.float32))  # top row = last line (NaN kept)
