"""``afmtool design excitation`` (issue 17 item 2): the design rule, the exports, and the closed loop.

Truth is the independent reference simulator: its free-air response scores the
predicted lines, and a reference capture driven by the exported lines (a
continuous drive: a generator, or a DAC behind its reconstruction filter) is
analysed by ``afmtool reep``, which must meet the off-sample accuracy of
tests/test_reep_reference.py (f0' within 2 Hz, Q' within 2 %).
"""

from __future__ import annotations

import json
import math
import struct

import h5py
import numpy as np
import pytest

from afmtool.errors import ConfigError
from afmtool.models.excitation_design import (
    design_three_sine,
    response_envelope,
)
from tests import reference_sim as rs
from tests.conftest import run_cli, validate_report

F0, GAIN = 70_000.0, 0.1
ADC_RATE = 500e3


def _model_file(tmp_path, q):
    path = tmp_path / f"free_air_q{q:g}.json"
    path.write_text(json.dumps({"f0_hz": F0, "q": q, "gain": GAIN}))
    return path


def _design_cli(tmp_path, q, *extra):
    out = tmp_path / f"exc_q{q:g}"
    result = run_cli("design", "excitation", "--model", _model_file(tmp_path, q), "--amplitude", "25",
                     "--out", out, "--json", *extra)
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    return out, report


def _wav(path):
    """(format tag, channels, rate, bits, samples) parsed from the RIFF chunks by hand."""
    data = path.read_bytes()
    assert data[:4] == b"RIFF" and data[8:12] == b"WAVE"
    assert struct.unpack("<I", data[4:8])[0] == len(data) - 8
    pos, fmt, samples = 12, None, None
    while pos < len(data):
        tag, size = data[pos:pos + 4], struct.unpack("<I", data[pos + 4:pos + 8])[0]
        body = data[pos + 8:pos + 8 + size]
        if tag == b"fmt ":
            fmt = struct.unpack("<HHIIHH", body[:16])
        elif tag == b"data":
            samples = np.frombuffer(body, dtype="<f4")
        pos += 8 + size + (size & 1)
    tag, channels, rate, byte_rate, align, bits = fmt
    assert byte_rate == rate * channels * bits // 8 and align == channels * bits // 8
    return tag, channels, rate, bits, samples


@pytest.mark.parametrize("q", [200.0, 40.0])
def test_design_rule_against_the_reference_response(q):
    design = design_three_sine(F0, q, GAIN, 25.0, dac_rate_hz=1e6, beat_tolerance=0.05)
    main, lower, upper = design.lines
    truth = [rs.free_air_response(line.frequency_hz, F0, q, GAIN) for line in design.lines]
    for line, g in zip(design.lines, truth):
        assert line.response_nm == pytest.approx(abs(g) * line.amplitude_v, rel=1e-12)
    assert main.response_nm == pytest.approx(25.0, rel=1e-12)
    assert abs(main.frequency_hz - F0) <= 0.5 * F0 / (100 * q)
    assert upper.frequency_hz - main.frequency_hz == pytest.approx(main.frequency_hz - lower.frequency_hz, abs=1e-6)
    # the envelope's excursion, from a fine evaluation of the response over one beat
    t = np.arange(20_000) / (20_000 * design.offset_hz)
    env = response_envelope(design, t)
    excursion = np.max(np.abs(env / (25.0 * np.exp(1j * main.response_phase_rad)) - 1.0))
    print(f"Q {q:g}: side scale {design.side_scale:.3f}, envelope beat {excursion:.4f} (tolerance 0.05), "
          f"amplitude beat {design.amplitude_beat:.4f}")
    assert excursion <= 0.05 + 1e-9
    assert excursion == pytest.approx(design.beat, rel=1e-6)
    if q == 200.0:
        assert design.side_scale == pytest.approx(0.5)  # the thesis's B = A/2 holds the tolerance
    else:
        assert design.side_scale < 0.5 and design.beat == pytest.approx(0.05)  # scaled down at low Q
    assert design.amplitude_beat < 0.2 * design.beat  # quadrature: mostly a phase swing


def test_bad_design_inputs_are_refused():
    with pytest.raises(ConfigError, match="dac-rate"):
        design_three_sine(F0, 200.0, GAIN, 25.0, dac_rate_hz=150e3)
    with pytest.raises(ConfigError, match="amplitude_nm"):
        design_three_sine(F0, 200.0, GAIN, -1.0, dac_rate_hz=1e6)


def test_exports_wav_csv_and_loop(tmp_path):
    out, report = _design_cli(tmp_path, 200.0, "--dac-rate", "1000000")
    assert {"lines.json", "lines.csv", "excitation.wav", "excitation.csv", "excitation.png"} <= set(report["outputs"])
    record = json.loads((out / "lines.json").read_text())
    n = record["loop_samples"]
    tag, channels, rate, bits, wav = _wav(out / "excitation.wav")
    assert (tag, channels, rate, bits) == (3, 1, 1_000_000, 32)  # IEEE float, mono, at --dac-rate
    assert wav.size == n and np.max(np.abs(wav)) == pytest.approx(1.0)
    table = np.loadtxt(out / "excitation.csv", delimiter=",", skiprows=1)
    assert table.shape == (n, 2)
    np.testing.assert_allclose(table[:, 0], np.arange(n) / 1e6, rtol=1e-11, atol=1e-15)
    volts = table[:, 1]
    np.testing.assert_allclose(wav * record["wav_full_scale_v"], volts, atol=1e-6 * record["wav_full_scale_v"])
    lines_csv = np.genfromtxt(out / "lines.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    np.testing.assert_allclose(lines_csv["frequency_hz"], [ln["frequency_hz"] for ln in record["lines"]], rtol=1e-11)

    def analytic(t):
        return sum(ln["amplitude_v"] * np.sin(2 * np.pi * ln["frequency_hz"] * t + math.radians(ln["phase_deg"]))
                   for ln in record["lines"])

    # the file is the lines, sampled; and it is periodic: sample n (one loop on) is sample 0
    check = np.arange(0, n, 997)
    np.testing.assert_allclose(volts[check], analytic(check / 1e6), atol=1e-8)
    assert analytic(n / 1e6) == pytest.approx(volts[0], abs=1e-6)
    for ln in record["lines"]:
        cycles = ln["frequency_hz"] * n / 1e6
        assert cycles == pytest.approx(round(cycles), abs=1e-6)
    assert record["loop_beats"] * round(1e6 / record["offset_hz"]) == n
    # looping: the jump from the last sample to the first is an ordinary step of the signal
    steps = np.abs(np.diff(volts))
    wrap = abs(volts[0] - volts[-1])
    assert wrap <= steps.max() and wrap == pytest.approx(abs(analytic(n / 1e6) - volts[-1]), abs=1e-6)


def test_bad_dac_rate_is_one_line_and_no_output(tmp_path):
    out = tmp_path / "exc"
    result = run_cli("design", "excitation", "--model", _model_file(tmp_path, 200.0), "--amplitude", "25",
                     "--dac-rate", "100000.5", "--out", out)
    assert result.returncode == 2 and not out.exists()
    assert len(result.stderr.decode().strip().splitlines()) == 1


def _drive_from_wav(path, full_scale_v: float) -> rs.MultiSine:
    """The signal the exported loop is, as the reference simulator's continuous drive.

    A DAC replaying the loop behind its reconstruction filter outputs the band-limited
    periodic signal through its samples: the loop's discrete Fourier series.  Its
    non-zero terms (the samples are float32, so the rest is rounding) become cosine lines.
    """
    _, _, rate, _, samples = _wav(path)
    volts = samples.astype(np.float64) * full_scale_v
    n = len(volts)
    spectrum = np.fft.rfft(volts) / n
    bins = np.flatnonzero(np.abs(spectrum) > 1e-4 * np.abs(spectrum).max())
    return rs.MultiSine(tuple(rs.Sine(k * rate / n, 2.0 * abs(spectrum[k]), float(np.angle(spectrum[k]))) for k in bins))


@pytest.mark.parametrize("q", [200.0, 40.0])
def test_closed_loop_reference_capture_driven_by_the_export_meets_reep_accuracy(tmp_path, q):
    out, _ = _design_cli(tmp_path, q, "--dac-rate", "1000000")
    record = json.loads((out / "lines.json").read_text())
    drive = _drive_from_wav(out / "excitation.wav", record["wav_full_scale_v"])
    # the file holds the designed lines and nothing else (sine phases are the simulator's cosines - π/2)
    assert len(drive.lines) == len(record["lines"])
    for line, designed in zip(drive.lines, sorted(record["lines"], key=lambda ln: ln["frequency_hz"])):
        assert line.frequency_hz == pytest.approx(designed["frequency_hz"], rel=1e-12)
        assert line.amplitude_v == pytest.approx(designed["amplitude_v"], rel=1e-5)
        phase = math.remainder(line.phase_rad - math.radians(designed["phase_deg"]) + math.pi / 2, 2 * math.pi)
        assert abs(phase) < 1e-4
    cap = rs.simulate(f0_hz=F0, q=q, gain_nm_per_v=GAIN, sample_rate_hz=ADC_RATE, duration_s=0.1, drive=drive,
                      hold="continuous", noise_nm=0.05, seed=17)
    capture = rs.write_capture_h5(tmp_path / "driven.h5", cap)
    reep_out = tmp_path / "reep"
    result = run_cli("reep", capture, "--out", reep_out, "--quiet")
    assert result.returncode == 0, result.stderr.decode()
    with h5py.File(reep_out / "reep.h5") as f:
        t, f0, qq, amplitude = f["t"][()], f["f0_hz"][()], f["q"][()], f["amplitude"][()]
    settled = t > 0.04
    f0_error = np.mean(f0[settled]) - F0
    q_error = np.mean(qq[settled]) / q - 1.0
    amplitude_error = np.median(amplitude[settled]) / 25.0 - 1.0
    print(f"Q {q:g}: f0' error {f0_error:+.3f} Hz (tol 2), Q' error {100 * q_error:+.3f} % (tol 2), "
          f"amplitude {100 * amplitude_error:+.2f} % of the requested 25 nm")
    assert abs(f0_error) <= 2.0
    assert abs(q_error) <= 0.02
    assert abs(amplitude_error) <= 0.02
