"""``afmtool kalman-bank``: REEP checked by a bank of Kalman filters and an adaptive observer."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.calibration_options import (
    CaptureCalibration,
    DriveOpt,
    InvolsOpt,
    UnitsOpt,
    ZSensitivityOpt,
)
from afmtool.cli.common import finish_command, open_calibrated, open_input
from afmtool.cli.options import CaptureArg, ChannelOpt, ConfigOpt, DriveHoldOpt, F0Opt, JsonOpt, OutOpt, QOpt, QuietOpt, SampleRateOpt, TopicOpt
from afmtool.cli.progress import progress_bar

__all__ = ["register"]


def kalman_bank(
    capture: CaptureArg,
    out: OutOpt = Path("kalman_bank"),
    reep: Annotated[
        Optional[Path], typer.Option("--reep", help="A finished 'afmtool reep' folder or reep.h5 (default: run REEP).")
    ] = None,
    at_z: Annotated[
        Optional[str], typer.Option("--at-z", help="Design points z1,z2,... in z_piezo units (default: 5 spread).")
    ] = None,
    models: Annotated[
        Optional[str], typer.Option("--models", help="Bank models f0_hz:q,f0_hz:q,... instead of REEP's.")
    ] = None,
    n_filters: Annotated[
        Optional[int], typer.Option("--n-filters", help="Filters spread automatically.", min=1)
    ] = None,
    free_air: Annotated[
        Optional[str], typer.Option("--free-air", help="Off-sample segment START:END (s) for the free-air model.")
    ] = None,
    model: Annotated[
        Optional[Path], typer.Option("--model", help="free_air.json from 'afmtool identify freeair' (or its folder).")
    ] = None,
    f0: F0Opt = None,
    q: QOpt = None,
    drive_hold: DriveHoldOpt = None,
    noise_ratio: Annotated[
        Optional[float], typer.Option("--noise-ratio", help="Kalman σ_w/σ_v (dimensionless, default 0.03: error decay in ~10 drive periods).")
    ] = None,
    window_periods: Annotated[
        Optional[float], typer.Option("--window-periods", help="Innovation RMS window, drive periods (default 10).")
    ] = None,
    z_bin: Annotated[Optional[float], typer.Option("--z-bin", help="RMS-against-z bin width (z_piezo units).")] = None,
    f0_scale: Annotated[
        Optional[float], typer.Option("--f0-scale", help="Multiply the bank's f0 by this factor (dimensionless; negative control, e.g. 1.02).")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
    channel: ChannelOpt = None,
    topic: TopicOpt = None,
    sample_rate: SampleRateOpt = None,
    units: UnitsOpt = None,
    invols: InvolsOpt = None,
    z_sensitivity: ZSensitivityOpt = None,
    drive: DriveOpt = None,
) -> None:
    """Validate REEP's on-sample f0', Q' on a force curve by minimum innovation RMS (thesis §3.4.2).

    Builds steady-state Kalman filters from REEP's model at N points of the
    force curve (sharing the free-air numerator) and runs them in one fused
    loop beside an adaptive observer whose model follows REEP.  Verdict: each
    filter's least RMS must fall in its design z bin, and the adaptive
    observer must have the least RMS most of the time (tolerances in
    report.json).  Writes bank.h5, bank_rms_vs_z.png, report.json and
    config.toml.  Needs dither, deflection and z_piezo.
    """
    from afmtool.analyses.kalman_bank_outputs import run_kalman_bank_command

    flags = {
        "reep": str(reep) if reep else None,
        "at_z": at_z,
        "models": models,
        "n_filters": n_filters,
        "free_air": free_air,
        "model": str(model) if model else None,
        "f0_hz": f0,
        "q": q,
        "drive_hold": drive_hold,
        "noise_ratio": noise_ratio,
        "rms_window_periods": window_periods,
        "z_bin": z_bin,
        "f0_scale": f0_scale,
    }

    calibration = CaptureCalibration(units, invols, z_sensitivity, drive, free_air, accepts_drive=True)

    def reopen():
        return open_calibrated(capture, channel, topic, sample_rate, calibration)

    with open_input(capture, channel, topic, sample_rate, calibration) as reader:
        with progress_bar("kalman-bank", reader.info.n_samples, quiet) as update:
            report = run_kalman_bank_command(reader, capture, out, config, flags, update, reopen)
    finish_command(report, out, json_output, quiet)


def register(app: typer.Typer) -> None:
    app.command("kalman-bank")(kalman_bank)
