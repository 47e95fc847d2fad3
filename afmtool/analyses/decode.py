"""``afmtool decode``: bits from an electrostatically actuated probe by the EKF innovation (ch. 7).

capture → nominal segment (read ahead) → measurement noise (PSD floor),
ℓ0 (§7.4: innovation RMS minimised on a grid, then golden section), process
noise (mean NIS = 1) → chunks → EKF kernel (eqs. 7.11-7.15) → innovation
and its running mean → clock acquisition on the first ``clock_window_s`` of
the bit stream, then integrate-and-dump with a tracking clock → two-class
threshold → bits.  Beside it, the lock-in amplitude of the deflection at
the actuation frequency is integrated over the same cells: the baseline.
Every filter carries its state across chunks, so the result does not depend
on the chunk size; memory is flat apart from one value per bit.

The voltage is V = α_R·V_R − V_sub from the ``v_r`` and ``v_sub`` channels
(eq. 6.3), or a channel named by ``voltage_channel``.  Model parameters
come from the parameters, ``--electrostatic`` (``identify electrostatic``'s
result) or the capture metadata, and never from the thesis's experiment:
a missing one stops the run with its name (:mod:`afmtool.analyses.decode_model`);
the report says where each came from.  Units: deflection in nm, K_esf in F·m with F = −K_esf·V²/ℓ² (no ½).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from afmtool.analyses.decode_model import ModelSetup, resolve_model
from afmtool.analyses.decode_stage import DecodeStage, DecodeTotals
from afmtool.config.params import DecodeParams
from afmtool.errors import InputError
from afmtool.estimators.bit_errors import BitErrors, ber_upper_bound, bit_errors
from afmtool.estimators.bit_stream import BitDecision, decide_bits
from afmtool.io.capture import CaptureReader
from afmtool.io.results import ResultWriter
from afmtool.pipeline import Split, run_stream
from afmtool.records.decode import (
    ActuationSource,
    BaselineBitScores,
    BitScores,
    Confusion,
    DecodeMode,
    DecodeModel,
    DecodeResults,
    EkfRecord,
    Rows,
    TruthRecord,
)

__all__ = [
    "DecodeResult",
    "run_decode",
    "BitErrors",
    "bit_errors",
    "ber_upper_bound",
    "ModelSetup",
    "resolve_model",
    "SERIES_UNITS",
]

#: Series written, with units: ``t`` and ``innovation`` per sample; the running mean of the
#: innovation (over one actuation period) at the end of each period, ``t_mean`` and ``innovation_mean``.
SERIES_UNITS = {"innovation": "nm", "t_mean": "s", "innovation_mean": "nm"}

#: Chunks read ahead in a background thread while the EKF runs on the current one.
_READ_AHEAD = 1


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class DecodeResult:
    """What :func:`run_decode` found; the command turns it into files and a report."""

    results: DecodeResults
    warnings: tuple[str, ...]
    l0_curve_nm: tuple[np.ndarray, np.ndarray] | None  #: (ℓ0, innovation RMS), nm
    psd: dict = field(default_factory=dict)  #: frequency_hz, deflection, innovation (nm²/Hz)
    eye: dict = field(default_factory=dict)  #: x (bit periods), traces (2-D, nm), threshold_nm
    step: object = None  #: StepSeries around the V_phi step (--mode step), for its figure


# --------------------------------------------------------------------------- run


def run_decode(
    reader: CaptureReader,
    params: DecodeParams,
    writer: ResultWriter,
    *,
    progress: Callable[[int], None] | None = None,
    on_stream_start: Callable[[], None] | None = None,
    split: Split | None = None,
) -> DecodeResult:
    """Decode the bits of a capture, streaming, and write the per-sample series.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection`` (nm) and ``v_sub``, ``v_r`` (V), or the channel
        ``params.voltage_channel`` (V).
    params : DecodeParams
        Effective parameters.
    writer : ResultWriter
        Receives ``t`` and ``innovation`` per sample, ``t_mean`` and
        ``innovation_mean`` once per running-mean window, and
        ``bit_times_s``, ``bits``, ``soft``, ``baseline_soft``,
        ``baseline_bits`` and the ℓ0 curve as whole arrays.
    progress : callable, optional
        Called with the samples read so far.
    on_stream_start : callable, optional
        Called once, when the model is tuned and the stream begins (the
        command starts loading its plotting library then).
    split : Split, optional
        Run the EKF on several chunks at once (:class:`~afmtool.pipeline.Split`);
        the bits are those of the sequential run (``tests/test_split.py``).

    Returns
    -------
    DecodeResult
    """
    from afmtool.io.chunks import require_channels
    from afmtool.io.electrostatic_file import read_electrostatic_file

    info = reader.info
    fs = info.sample_rate_hz
    channels = ("deflection",) + ((params.voltage_channel,) if params.voltage_channel else ("v_sub", "v_r"))
    require_channels(info, channels)  # before the model: a capture of something else is told so first
    setup = resolve_model(info, params, read_electrostatic_file(params.electrostatic) if params.electrostatic else None)
    if setup.f0_hz >= fs / 2:
        raise InputError(f"f0 = {setup.f0_hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    decoding = DecodeStage(info, params, setup, channels)
    (totals,) = run_stream(
        reader, [decoding], writer, channels=channels, chunk_samples=params.chunk_samples, progress=progress,
        prologue=decoding.nominal_prologue, read_ahead=_READ_AHEAD, split=split, on_start=on_stream_start,
    )
    tuning = decoding.tuning
    if tuning.l0_curve_nm is not None:
        writer.put("l0_search/l0_nm", tuning.l0_curve_nm[0], "nm")
        writer.put("l0_search/innovation_rms_nm", tuning.l0_curve_nm[1], "nm")
    warnings = list(tuning.warnings)
    if decoding.step_window is not None:
        from afmtool.analyses.decode_step import step_results

        series = decoding.step_window.series()
        step = step_results(series, decoding.step_window.step_sample, fs, decoding.actuation_hz, setup.f0_hz, setup.q,
                            decoding.mean_window)
        results = _results(decoding, totals, fs, DecodeMode.STEP, step=step)
        return DecodeResult(results, tuple(warnings), tuning.l0_curve_nm, decoding.psd.spectra(fs), {}, series)
    stage, mean_window = decoding.bits, decoding.mean_window
    decided = decide_bits(stage, params, mean_window, warnings)
    _write_bits(writer, decided, params)
    truth = _compare_truth(reader, tuning.l0.estimate_nm, decided, stage.clock.period_samples, 0.5 * (mean_window - 1))
    results = _results(decoding, totals, fs, DecodeMode.BITS, clock=decided.clock_record, bits=decided.bits_record,
                       baseline=decoding.baseline.record(decided.baseline_levels), truth=truth)
    eye = {"x": stage.eye_x, "traces": stage.eye_traces, "threshold_nm": decided.threshold_nm}
    eye = eye if stage.eye_traces.size else {}
    return DecodeResult(results, tuple(warnings), tuning.l0_curve_nm, decoding.psd.spectra(fs), eye)


def _results(decoding: DecodeStage, totals: DecodeTotals, fs: float, mode: DecodeMode, **sections) -> DecodeResults:
    """The model, the nominal segment, the tuning and the EKF's figures, with the ``sections`` of ``mode``."""
    nominal = decoding.nominal
    return DecodeResults(
        model=_model_record(decoding.setup, decoding.params),
        nominal_segment_s=tuple(nominal) if nominal is not None else None,
        l0=decoding.tuning.l0,
        noise=decoding.tuning.noise,
        ekf=EkfRecord(
            sample_rate_hz=fs, actuation_hz=decoding.actuation_hz,
            actuation_source=ActuationSource(decoding.actuation_source), mean_window_samples=decoding.mean_window,
            bit_stream_innovation_rms_nm=totals.bit_stream_rms_nm,
        ),
        # the series' density and what set it (issue 33): innovation_mean's rows; per-period adds every sample's
        rows=Rows(decoding.params.rows),
        row_every_samples=decoding.mean_window,
        row_rate_hz=fs / decoding.mean_window,
        innovation_every_sample=decoding.params.rows == "per-period",
        n_samples=totals.n_samples,
        duration_s=totals.n_samples / fs,
        mode=mode,
        **sections,
    )


def _model_record(setup: ModelSetup, params: DecodeParams) -> DecodeModel:
    es = setup.electrostatic
    return DecodeModel(
        f0_hz=setup.f0_hz,
        q=setup.q,
        spring_constant_n_per_m=es.spring_constant_n_per_m,
        k_esf_f_m=es.k_esf_f_m,
        alpha_r=es.alpha_r,
        tip_height_nm=es.tip_height_m * 1e9,
        l0_guess_nm=es.l0_m * 1e9 if setup.l0_known else None,
        sources=setup.sources,
        convention="F_esf = -K_esf*V^2/(l0 + p)^2 (no 1/2), K_esf in F*m; EKF state [p (nm), dp/dt (nm/s)]",
        voltage=params.voltage_channel or "alpha_r*v_r - v_sub",
    )


def _write_bits(writer: ResultWriter, decided: BitDecision, params: DecodeParams) -> None:
    """The per-bit arrays of decode.h5."""
    writer.put("bit_times_s", decided.bit_times_s, "s", {"meaning": "centre of each decoded cell, running-mean delay removed"})
    writer.put("bits", decided.bits, "", {"polarity": params.polarity})
    writer.put("soft", decided.soft, "nm",
               {"meaning": "innovation running mean averaged over the integrated part of the cell"})
    writer.put("baseline_soft", decided.baseline_soft, "nm", {"meaning": "lock-in amplitude averaged over the same cells"})
    writer.put("baseline_bits", decided.baseline_bits, "", {"polarity": "1 = larger amplitude"})


def _scores(kind: type[BitScores], found: BitErrors, fs: float, **more) -> BitScores:
    """One decoder's errors as ``kind`` (:class:`BitScores`, or the baseline's with ``inverted``)."""
    return kind(ber=found.ber, ber_upper_95=ber_upper_bound(found.errors, found.compared) if found.compared else None,
                errors=found.errors, compared=found.compared, latency_s=found.lag_samples / fs,
                confusion=Confusion(**found.confusion), **more)


def _compare_truth(
    reader: CaptureReader, l0_estimate_nm: float, decided: BitDecision, period: float, latency_known: float
) -> TruthRecord | None:
    """BER and confusion counts of the decoder and the baseline when /truth has the bits."""
    bits, base_bits, centres = decided.bits, decided.baseline_bits, decided.centres
    names = reader.info.truth_names
    if not {"bit", "bit_index"} <= set(names):
        return None
    truth = reader.truth()
    truth_bit, truth_index = truth["bit"], truth["bit_index"]
    l0_true = float(truth["l0_nm"][0]) if "l0_nm" in truth and truth["l0_nm"].size else None
    max_lag = int(math.ceil(2 * period + latency_known))
    ekf = bit_errors(bits, centres, truth_bit, truth_index, max_lag=max_lag)
    base = bit_errors(base_bits, centres, truth_bit, truth_index, max_lag=max_lag + int(math.ceil(period)),
                      allow_inversion=True)
    del truth
    fs = reader.info.sample_rate_hz
    ratio = lower_bound = None
    if ekf.compared and base.compared:
        # with no decoder error the ratio is bounded below, by the one-sided 95 % upper bound of its BER
        bound = ekf.ber if ekf.errors else ber_upper_bound(0, ekf.compared)
        ratio, lower_bound = (base.ber / bound if bound > 0 else None), ekf.errors == 0
    return TruthRecord(
        l0_nm=l0_true,
        l0_error_percent=100.0 * (l0_estimate_nm / l0_true - 1.0) if l0_true is not None else None,
        decoder=_scores(BitScores, ekf, fs),
        baseline=_scores(BaselineBitScores, base, fs, inverted=base.inverted),
        alignment="latency (0 to 2 bit periods) with the fewest errors, per decoder",
        baseline_to_decoder_ber_ratio=ratio, ratio_is_lower_bound=lower_bound,
    )
