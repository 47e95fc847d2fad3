"""Where the Kalman bank gets REEP's model: binned against z, and per sample for the adaptive observer.

Two sources, one interface:

* internal: pass 1 runs REEP's stage (:class:`afmtool.analyses.reep.ReepStage`;
  its columns go to a :class:`ReepBinner`), and pass 2 runs the very
  :class:`~afmtool.estimators.reep_estimator.ReepEstimator` pass 1 built,
  chunk by chunk, with a row at every REEP sample (:class:`InternalReep`):
  at pass 1's rows the two agree bit for bit (``tests/test_kalman_bank_reep.py``);
* a finished run (``--reep``): its decimated series are binned the same way
  (:func:`reep_tables_from_file`) and its (b1, b0) are held per sample
  (:class:`HeldReepCoefficients`).

The adaptive observer runs at the capture's rate; REEP may run at fs/D
(:mod:`afmtool.estimators.rate_reduction`).  Its (b1, b0) are carried to the
capture's rate by the pole map (z = z_D^{1/D}) and held between REEP's
samples; f0′ and Q′ are taken from REEP's own (b1, b0) at its rate.

Binning at the window centroid
------------------------------
REEP's estimate at sample n weighs sample n − k by λᵏ(1 − λ); its centroid
is λ/(1 − λ) REEP samples back (199 at λ = 0.995 and D = 1), and along a ramp the
estimate describes the cantilever there.  Each estimate is therefore binned
against z that many samples earlier, as the bank's innovation RMS is
binned where its own window and error dynamics put it.  Without this, a
fast ramp (the bundled capture: 0.47 nm of z per REEP window) would shift
every design point by about one 0.5 nm bin.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.analyses.accumulators import ReepBinner
from afmtool.config.params import KalmanBankParams, ReepParams
from afmtool.errors import InputError
from afmtool.estimators.kalman_bank_verdict import ModelTable
from afmtool.io.capture import CaptureReader, Chunk
from afmtool.models.free_air import FreeAirModel

if TYPE_CHECKING:
    from afmtool.records.reep import ReepResults

__all__ = [
    "CoefficientBlock",
    "HeldReepCoefficients",
    "InternalReep",
    "PassOne",
    "ReepTiming",
    "reep_pass_one",
    "reep_tables_from_file",
    "reep_delay",
    "warmup_samples",
]

class ReepTiming(NamedTuple):
    """REEP's window as kalman-bank needs it: from the estimator, or from a finished run's report.

    Attributes
    ----------
    lam : float
        Forgetting factor per REEP sample.
    factor : int
        Capture samples per REEP sample (D).
    """

    lam: float
    factor: int = 1

    @classmethod
    def of(cls, estimator) -> ReepTiming:
        return cls(estimator.lam, estimator.factor)

    @classmethod
    def from_report(cls, results: ReepResults | None) -> ReepTiming:
        """A finished run's (its report.json's ``estimator``); λ = 0.995 at REEP's rate without a report."""
        if results is None:
            return cls(0.995, 1)
        return cls(float(results.estimator.reep_forgetting_factor), int(results.estimator.rate_reduction))

    @property
    def window_samples(self) -> float:
        """The window 1/(1 − λ) in capture samples."""
        return self.factor / (1.0 - self.lam)

    @property
    def centroid_samples(self) -> float:
        """λ/(1 − λ), the window's centroid, in capture samples."""
        return self.lam / (1.0 - self.lam) * self.factor

    @property
    def capture_lam(self) -> float:
        """The forgetting factor per capture sample with the same window."""
        return 1.0 - 1.0 / self.window_samples


def reep_delay(timing: ReepTiming, decimate: int) -> int:
    """REEP's window centroid in kept (decimated) rows."""
    return round(timing.centroid_samples / max(decimate, 1))


def warmup_samples(reep_params: ReepParams, timing: ReepTiming) -> int:
    """REEP's start-up left out of the statistics: ``warmup_windows`` windows, in capture samples."""
    from afmtool.config.samples import check_count

    windows = reep_params.warmup_windows
    return int(check_count(windows * timing.window_samples, "warmup_windows", windows))


class CoefficientBlock(NamedTuple):
    """REEP's model for each sample of a chunk, held from its last estimate (NaN before the first).

    Attributes
    ----------
    b1, b0 : numpy.ndarray
        At the capture's rate, for the adaptive observer.
    reep_b1, reep_b0 : numpy.ndarray
        As REEP estimated them, at its rate (f0′ and Q′ come from these).
    """

    b1: np.ndarray
    b0: np.ndarray
    reep_b1: np.ndarray
    reep_b0: np.ndarray


class HeldReepCoefficients:
    """REEP's decimated (b1, b0) held per sample: sample n uses the last estimate at or before n.

    Holding keeps the adaptive observer causal; REEP's estimate moves over
    its window 1/(1 − λ) (200 samples), so a hold of under one drive period
    adds no visible lag.  Samples before the first estimate get NaN, which
    the adaptive kernel treats as "keep the previous (free-air) model".

    Parameters
    ----------
    t, b1, b0 : array_like or h5py.Dataset, shape (K,)
        Decimated times (s) and coefficients; read by slices, so datasets
        of any length stream.
    sample_rate_hz : float
        The capture's rate; t·fs must be whole samples at a uniform step.
    factor : int, optional
        The run's rate reduction D: its (b1, b0) are at fs/D.

    Raises
    ------
    InputError
        If the times are not uniform whole samples at this rate.
    """

    def __init__(self, t, b1, b0, sample_rate_hz: float, factor: int = 1) -> None:
        self._b1, self._b0 = b1, b0
        self.factor = int(factor)
        self.length = len(t)
        if self.length == 0 or len(b1) != self.length or len(b0) != self.length:
            raise InputError("REEP series t, b1, b0 must be non-empty and of one length")
        first = float(t[0]) * sample_rate_hz
        self.first_sample = round(first)
        self.step = round((float(t[1]) - float(t[0])) * sample_rate_hz) if self.length > 1 else 1
        last = float(t[self.length - 1]) * sample_rate_hz
        self.last_sample = self.first_sample + (self.length - 1) * self.step
        uniform = abs(first - self.first_sample) <= 1e-3 and abs(last - self.last_sample) <= 1e-3 * max(1.0, last)
        if self.step < 1 or not uniform:
            raise InputError(
                f"REEP series times are not uniform whole samples at {sample_rate_hz:g} Hz "
                "(a REEP run of another capture or sample rate?)"
            )

    def block(self, chunk: Chunk) -> CoefficientBlock:
        """REEP's model for the chunk's samples; NaN before the first estimate."""
        n = chunk.start + np.arange(len(chunk))
        k = np.minimum(np.floor_divide(n - self.first_sample, self.step), self.length - 1)
        lo, hi = max(int(k.min()), 0), max(int(k.max()), 0)
        b1 = np.asarray(self._b1[lo : hi + 1], dtype=np.float64)
        b0 = np.asarray(self._b0[lo : hi + 1], dtype=np.float64)
        inside = k >= 0
        out1 = np.full(n.shape, np.nan)
        out0 = np.full(n.shape, np.nan)
        out1[inside] = b1[k[inside] - lo]
        out0[inside] = b0[k[inside] - lo]
        from afmtool.estimators.reep_estimator import capture_rate_coefficients

        return CoefficientBlock(*capture_rate_coefficients(out1, out0, self.factor), out1, out0)


class InternalReep:
    """REEP run chunk by chunk beside the bank: pass 1's :class:`ReepEstimator`, a row at every REEP sample.

    Parameters
    ----------
    estimator : ReepEstimator
        The one REEP of the run (pass 1's, or built as its stage builds it).
    start : int, optional
        The capture sample it starts at (a split chunk's lead, on REEP's grid).
    """

    def __init__(self, estimator, start: int = 0) -> None:
        self.estimator = estimator.with_rows(estimator.factor)
        self.state = self.estimator.initial(start)
        self._held = (np.nan, np.nan)

    @property
    def factor(self) -> int:
        return self.estimator.factor

    def fresh(self, start: int = 0) -> InternalReep:
        """The same REEP from its initial state at ``start`` (a split chunk's warm-up)."""
        return InternalReep(self.estimator, start)

    def block(self, chunk: Chunk) -> CoefficientBlock:
        """REEP's model for every sample of the chunk: each REEP sample's (b1, b0) held until the next."""
        from afmtool.estimators.decimation import Decimation
        from afmtool.estimators.reep_estimator import capture_rate_coefficients

        run = self.estimator.run(self.state, chunk.data["deflection"], chunk.data["dither"])
        self.state = run.state
        n = len(chunk)
        # REEP sample k of this chunk is capture sample first + k·D; sample n takes the last one at or before it
        first = Decimation(self.factor).first_kept(chunk.start)
        k = np.floor_divide(np.arange(n) - first, self.factor)
        reep_b1 = np.concatenate(([self._held[0]], run.block.b1))[k + 1]
        reep_b0 = np.concatenate(([self._held[1]], run.block.b0))[k + 1]
        if len(run.block.b1):
            self._held = (float(run.block.b1[-1]), float(run.block.b0[-1]))
        return CoefficientBlock(*capture_rate_coefficients(reep_b1, reep_b0, self.factor), reep_b1, reep_b0)


class _ReepTables:
    """REEP's stage with its model binned against z as it streams (pass 1; no series written).

    The binner's window-centroid delay is in kept samples, so it is built
    from the decimation REEP's stage chose, once that stage is prepared.
    """

    def __init__(self, reep, params: KalmanBankParams, sample_rate_hz: float) -> None:
        self.reep = reep
        self.params = params
        self.fs = sample_rate_hz
        self.binner: ReepBinner | None = None

    def prepare(self, head) -> None:
        self.reep.prepare(head)
        timing = ReepTiming.of(self.reep.estimator)
        warmup_s = warmup_samples(self.params.reep, timing) / self.fs
        self.binner = ReepBinner(self.params.z_bin, reep_delay(timing, self.reep.decimation.every), warmup_s)

    def step(self, chunk: Chunk) -> None:
        self.binner.append(self.reep.step(chunk))

    def kernels(self):
        """REEP's kernels (:meth:`afmtool.analyses.reep.ReepStage.kernels`), for a split run."""
        return self.reep.kernels()

    def account(self, chunk: Chunk, estimate) -> None:
        self.binner.append(self.reep.account(chunk, estimate))

    def finish(self):
        """(REEP's result, its model binned against z per leg)."""
        return self.reep.finish(), self.binner.tables()


class PassOne(NamedTuple):
    """REEP over the whole capture.

    Attributes
    ----------
    tables : dict of str to ModelTable
        REEP's model against z per leg, at its window centroid.
    model : FreeAirModel
        The free-air model REEP ran beside (given or identified).
    segment_s : tuple of 2 floats or None
        The free-air segment it was identified from.
    estimator : ReepEstimator
        The REEP that ran: pass 2's adaptive observer follows the same one.
    route : dict or None
        REEP's free-air route and drive hold (report.json ``free_air_route``).
    """

    tables: dict[str, ModelTable]
    model: FreeAirModel
    segment_s: tuple[float, float] | None
    estimator: object
    route: dict | None = None


def reep_pass_one(reader: CaptureReader, params: KalmanBankParams, model: FreeAirModel | None, progress,
                  split=None, on_start=None) -> PassOne:
    """Run REEP (its stage, with ``[kalman-bank.reep]`` and the bank's route, z bin and decimation) and bin its model against z.

    ``split`` (a :class:`~afmtool.pipeline.Split`) runs REEP's kernels on several chunks at once;
    ``on_start`` is called as the stream starts.
    """
    from afmtool.analyses.reep import ReepStage
    from afmtool.pipeline import run_stream

    reep_params = bank_reep_params(params)
    reep = ReepStage(reader, reep_params, model=model, force_curves=False)  # _ReepTables bins at the centroid
    ((result, tables),) = run_stream(
        reader, [_ReepTables(reep, params, reader.info.sample_rate_hz)], channels=reep.channels,
        chunk_samples=reep_params.chunk_samples, progress=progress, prologue=reep.free_air_prologue, split=split,
        on_start=on_start,
    )
    if not tables:
        raise InputError(f"{reader.info.source}: REEP found no force curve (z_piezo never moves)")
    # the model REEP ran beside: a given one as the route refined it (gain and phase fitted at the drive)
    used = FreeAirModel.from_record(result.results.free_air_model, "identified free-air model")
    return PassOne(tables, used, result.results.free_air_segment_s, reep.estimator, reep.route)


def bank_reep_params(params: KalmanBankParams) -> ReepParams:
    """``[kalman-bank.reep]`` with the bank's own route, drive, decimation, z bin and chunking."""
    import dataclasses

    return dataclasses.replace(
        params.reep, free_air=params.free_air, model=params.model, f0_hz=params.f0_hz, q=params.q,
        drive_hold=params.drive_hold, rows=params.rows, decimate=params.decimate,
        drive_frequency_hz=params.drive_frequency_hz,
        vs="z", z_bin=params.z_bin, chunk_samples=params.chunk_samples,
    )


def reep_tables_from_file(
    reep_results, params: KalmanBankParams, timing: ReepTiming, sample_rate_hz: float
) -> dict[str, ModelTable]:
    """REEP's model against z from a finished run's decimated series (streamed in slices).

    Raises
    ------
    InputError
        If the run has no ``z``, ``f0_hz`` or ``q`` series.
    """
    series = reep_results.series
    missing = [name for name in ("z", "f0_hz", "q") if name not in series]
    if missing:
        raise InputError(f"--reep {reep_results.path}: no {', '.join(missing)} series (was z_piezo recorded?)")
    t = series["t"]
    n = len(t)
    decimate = round((float(t[1]) - float(t[0])) * sample_rate_hz) if n > 1 else 1
    binner = ReepBinner(params.z_bin, reep_delay(timing, decimate), warmup_samples(params.reep, timing) / sample_rate_hz)
    names = ("t", "z", "f0_hz", "q") + (("amplitude",) if "amplitude" in series else ())
    step = 1 << 16
    for start in range(0, n, step):
        binner.append({name: np.asarray(series[name][start : start + step], dtype=np.float64) for name in names})
    return binner.tables(amplitude_known="amplitude" in series)
