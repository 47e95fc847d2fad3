"""``afmtool design excitation``: the three-sine REEP dither, designed and exported.

Computation is :func:`afmtool.models.excitation_design.design_three_sine`;
this module writes what an instrument needs:

- ``lines.json`` / ``lines.csv``: frequency (Hz), amplitude (V), sine phase
  (deg) of each line, with the predicted free-air response line, for a
  multi-frequency lock-in or a three-channel function generator;
- ``excitation.wav`` (IEEE float32, mono, at ``--dac-rate``, peak
  normalised to 1.0; the volts per full scale are in ``lines.json``) and
  ``excitation.csv`` (``t_s``, ``dither_v``) for an arbitrary waveform
  generator: a whole number of beat periods, every line a whole number of
  cycles, so the loop repeats without a jump;
- ``excitation.png``: the predicted free-air deflection over three beat
  periods with its envelope, and the drive.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import DesignExcitationParams
from afmtool.models.excitation_design import (
    ExcitationDesign,
    design_three_sine,
    dither_samples,
    response_envelope,
)
from afmtool.models.free_air import FreeAirModel, load_free_air_model
from afmtool.records.design import DesignModelRecord, DesignResults, ExcitationLineRecord, LineRole
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["design_record", "run_design_excitation_command", "write_wav_float32"]


def design_record(design: ExcitationDesign, model: FreeAirModel, wav_full_scale_v: float) -> DesignResults:
    """The design as ``lines.json`` and the report's results hold it."""
    return DesignResults(
        convention="u(t) = sum_k amplitude_v * sin(2 pi frequency_hz t + phase_deg); response likewise in the "
                   "model's deflection units; continuous drive (a generator or a DAC behind its reconstruction "
                   "filter)",
        lines=tuple(
            ExcitationLineRecord(role=LineRole(line.role), frequency_hz=line.frequency_hz,
                                 amplitude_v=line.amplitude_v, phase_deg=math.degrees(line.phase_rad),
                                 response_nm=line.response_nm,
                                 response_phase_deg=math.degrees(line.response_phase_rad))
            for line in design.lines
        ),
        offset_hz=design.offset_hz,
        offset_reason=design.offset_reason,
        side_scale=design.side_scale,
        envelope_beat=design.beat,
        beat_tolerance=design.beat_tolerance,
        amplitude_beat=design.amplitude_beat,
        phase_swing_deg=math.degrees(design.phase_swing_rad),
        dac_rate_hz=design.dac_rate_hz,
        loop_samples=design.loop_samples,
        loop_beats=design.loop_beats,
        loop_s=design.loop_s,
        peak_v=design.peak_v,
        wav_full_scale_v=wav_full_scale_v,
        free_air_model=DesignModelRecord(f0_hz=model.f0_hz, q=model.q, gain=model.gain),
    )


def write_wav_float32(path: Path, samples: np.ndarray, rate_hz: int) -> None:
    """Mono IEEE-float32 WAV (format tag 3) of ``samples`` at ``rate_hz``."""
    from scipy.io import wavfile

    wavfile.write(path, int(rate_hz), np.asarray(samples, dtype=np.float32))


def _write_lines_csv(path: Path, record: DesignResults) -> None:
    rows = ["role,frequency_hz,amplitude_v,phase_deg,response_nm,response_phase_deg"]
    rows += [
        f"{line.role.value},{line.frequency_hz:.12g},{line.amplitude_v:.12g},{line.phase_deg:.12g},"
        f"{line.response_nm:.12g},{line.response_phase_deg:.12g}"
        for line in record.lines
    ]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def _write_samples_csv(path: Path, samples: np.ndarray, rate_hz: float) -> None:
    t = np.arange(samples.size) / rate_hz
    np.savetxt(path, np.column_stack([t, samples]), fmt=("%.12g", "%.12g"), delimiter=",",
               header="t_s,dither_v", comments="")


def _write_figure(path: Path, design: ExcitationDesign) -> None:
    from afmtool.report.images import write_multi_panel_png

    main = design.main
    points_per_cycle = 24
    t = np.arange(int(3 * main.frequency_hz / design.offset_hz * points_per_cycle)) / (points_per_cycle * main.frequency_hz)
    envelope = response_envelope(design, t)
    deflection = np.imag(envelope * np.exp(2j * np.pi * main.frequency_hz * t))
    t_us = t * 1e6
    panels = [
        {"y_label": "deflection (nm)", "series": [
            (t_us, deflection, "predicted free-air deflection", {"linewidth": 0.5}),
            (t_us, np.abs(envelope), "envelope", {"color": "k"}),
            (t_us, -np.abs(envelope), "", {"color": "k"}),
        ]},
        {"y_label": "drive (V)", "series": [(t_us, dither_samples(design, t), "dither", {"linewidth": 0.5})]},
    ]
    write_multi_panel_png(
        path, panels, x_label="t (us)",
        title=(f"three-sine dither: {main.frequency_hz:.6g} Hz +/- {design.offset_hz:.5g} Hz, "
               f"B/A {design.side_scale:.3g}, envelope beat {100 * design.beat:.2g} %"),
    )


def run_design_excitation_command(model_path: Path, out: Path, config: Path | None, flags: Mapping) -> dict:
    """Design the three-sine dither for ``model_path`` and write every export into ``out``."""
    params = resolve_from(DesignExcitationParams, "design.excitation", load_toml(config) if config else None, flags)
    model = load_free_air_model(model_path)
    design = design_three_sine(
        model.f0_hz, model.q, model.gain, params.amplitude_nm, dac_rate_hz=params.dac_rate_hz,
        drive_hz=params.drive_frequency_hz or None, offset_hz=params.offset_hz or None,
        beat_tolerance=params.beat_tolerance, max_side_scale=params.max_side_scale,
        resolution_hz=params.resolution_hz or None,
    )
    samples = dither_samples(design)
    full_scale = float(np.max(np.abs(samples)))
    record = design_record(design, model, full_scale)
    warnings = []
    if design.side_scale < 0.05:
        warnings.append(
            f"the side lines are only {100 * design.side_scale:.2g} % of the main line to hold the "
            f"{design.beat_tolerance:g} beat tolerance: REEP's excitation is then barely rich enough; "
            "consider a larger --offset or --beat-tolerance"
        )
    source = model_path / "free_air.json" if Path(model_path).is_dir() else model_path
    with OutputDir(out) as staged:
        staged.path("lines.json").write_text(json.dumps(record.to_json(), indent=2) + "\n", encoding="utf-8")
        _write_lines_csv(staged.path("lines.csv"), record)
        write_wav_float32(staged.path("excitation.wav"), samples / full_scale, int(design.dac_rate_hz))
        _write_samples_csv(staged.path("excitation.csv"), samples, design.dac_rate_hz)
        _write_figure(staged.path("excitation.png"), design)
        return finish_run(staged, "design excitation", [input_record(source, "free-air-model")],
                          "design.excitation", params, record, warnings)
