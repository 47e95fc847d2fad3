"""REEP as one estimator object, built once and used wherever REEP runs.

:class:`ReepEstimator` holds everything that fixes REEP's numbers: the
forgetting window (in time), P0, the static-offset regressor, the bias
compensation, the numerator at REEP's rate, the rate reduction
(:mod:`afmtool.estimators.rate_reduction`), the output-only band-pass and
the row spacing.  It is built from ``ReepParams`` and what a run resolved
(:meth:`ReepEstimator.build`); ``reep``'s stage, its free-air levels, its
split kernels and kalman-bank's adaptive observer all call
:meth:`ReepEstimator.initial` and :meth:`ReepEstimator.run`, so they agree
bit for bit (``tests/test_reep_estimator.py``).

capture (fs) ─► [band-pass, output-only] ─► anti-alias h, both signals ─► every D-th sample
            ─► [dither through B(z), continuous drive] ─► BCEWRLS at fs/D (λ for the window in time,
            eq. 3.39) ─► rows every ``row_every``

With a continuous drive and a continuous model (the ``f0-q`` route) the
numerator is not three taps but the FIR B(z) of
:func:`~afmtool.models.discretisation.continuous_input_filter`, exact
across the drive's side lines; the recursion then sees B(z)g with the
numerator (1, 0, 0).  A zero-order hold keeps the three taps, which are
exact for it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.config.samples import check_count, sample_count
from afmtool.errors import ConfigError
from afmtool.estimators.rate_reduction import ANTI_ALIAS_ROLLOFF, anti_alias_taps, decimate_block, reduction_factor
from afmtool.estimators.rls import ReepBlock, ReepState, reep_update
from afmtool.records.reep import AntiAlias, InputFilter, ReepEstimatorRecord

__all__ = [
    "ReepEstimator",
    "ReepEstimatorState",
    "ReepRun",
    "Settling",
    "capture_rate_coefficients",
    "forgetting_factor",
    "settling_samples",
    "step_settling",
]


def forgetting_factor(window_s: float, rate_hz: float) -> float:
    """λ = 1 − 1/(window·rate): the forgetting factor whose window 1/(1 − λ) lasts ``window_s`` at ``rate_hz``."""
    samples = window_s * rate_hz
    if not samples > 1.0:
        raise ConfigError(
            f"REEP's window of {window_s * 1e6:g} us is {samples:.3g} samples at its rate of {rate_hz:g} Hz; "
            "it must span more than one sample"
        )
    return 1.0 - 1.0 / samples


class ReepEstimatorState(NamedTuple):
    """What :meth:`ReepEstimator.run` carries from one chunk to the next.

    Attributes
    ----------
    rls : ReepState
        The BCEWRLS state at REEP's rate.
    start : int
        Capture index of the next sample.
    deflection_history, dither_history : numpy.ndarray
        The anti-alias filter's last inputs (not modified by ``run``).
    bandpass_zi : numpy.ndarray or None
        The output-only band-pass's state.
    skip : int
        Filtered samples still to hold back from the recursion (the filters' start).
    input_history : numpy.ndarray or None
        The input filter B(z)'s last inputs at REEP's rate (continuous drive).
    """

    rls: ReepState
    start: int
    deflection_history: np.ndarray
    dither_history: np.ndarray
    bandpass_zi: np.ndarray | None
    skip: int = 0
    input_history: np.ndarray | None = None


class ReepRun(NamedTuple):
    """:meth:`ReepEstimator.run`'s output: the rows of a chunk and the next state."""

    block: ReepBlock
    state: ReepEstimatorState


@dataclass(frozen=True, eq=False)
class ReepEstimator:
    """REEP with everything that fixes its numbers (module docstring).  Build with :meth:`build`.

    Attributes
    ----------
    sample_rate_hz : float
        The capture's rate fs, Hz.
    factor : int
        D: REEP runs at fs/D on the anti-alias-filtered signals.
    lam : float
        Forgetting factor per REEP sample.
    p0 : float
        P(0) = P0·I.
    static_offset, bias_compensation, use_input : bool
        As :func:`~afmtool.estimators.rls.reep_update` takes them.
    numerator : tuple of 3 floats or None
        (a2, a1, a0) at REEP's rate (None when output-only).
    row_every : int
        Capture samples per output row, a multiple of ``factor``.
    drive_hz : float
        The drive's main line (the covariance's bulk term), Hz.
    taps : numpy.ndarray
        The anti-alias filter ([1.0] when D = 1).
    bandpass_sos : numpy.ndarray or None
        The output-only band-pass at fs (second-order sections).
    window_s : float
        The forgetting window 1/(1 − λ), s (0: from λ).
    input_taps : numpy.ndarray or None
        B(z) at REEP's rate for a continuous drive (module docstring).
    """

    sample_rate_hz: float
    factor: int
    lam: float
    p0: float
    static_offset: bool
    bias_compensation: bool
    use_input: bool
    numerator: tuple[float, float, float] | None
    row_every: int
    drive_hz: float
    taps: np.ndarray
    bandpass_sos: np.ndarray | None = None
    #: The window 1/(1 − λ) in seconds as given (λ rounds it).
    window_s: float = 0.0
    #: B(z) at REEP's rate for a continuous drive (``numerator`` is then (1, 0, 0)); None: the three taps.
    input_taps: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.row_every % self.factor:
            raise ConfigError(f"rows every {self.row_every} samples must be a multiple of REEP's rate reduction {self.factor}")
        if not 0.0 <= self.drive_hz < self.rate_hz / 2:
            raise ConfigError(f"the drive at {self.drive_hz:g} Hz is not below REEP's Nyquist frequency {self.rate_hz / 2:g} Hz")
        if not self.window_s:
            object.__setattr__(self, "window_s", 1.0 / ((1.0 - self.lam) * self.rate_hz))

    @classmethod
    def build(cls, params, *, sample_rate_hz: float, resonance_hz: float, drive_hz: float, numerator=None,
              denominator=None, row_every: int | None = None, bandpass_half_width_hz: float = 0.0,
              segment: tuple[np.ndarray, np.ndarray] | None = None, continuous_drive: bool = False) -> ReepEstimator:
        """REEP for a run: the window, rate and numerator from ``params`` and the resolved model.

        Parameters
        ----------
        params : ReepParams
            ``window_us`` or ``lam`` (per capture sample), ``samples_per_period``,
            ``p0``, ``static_offset``, ``bias_compensation``, ``use_input``, ``decimate``.
        sample_rate_hz : float
            fs, Hz.
        resonance_hz : float
            The free-air f0 (or the spectral peak), for D = ⌊fs/(N·f0)⌋.
        drive_hz : float
            The drive's main line, Hz.
        numerator, denominator : tuple, optional
            The free-air model at fs (needed with ``use_input``); the
            numerator is carried to REEP's rate by
            :func:`~afmtool.models.discretisation.rate_numerator`.
        row_every : int, optional
            Capture samples per row; default ``params.decimate`` or one drive
            period, rounded to a multiple of D.
        bandpass_half_width_hz : float, optional
            Output-only: band-pass ±this around ``drive_hz`` before everything (0: none).
        segment : (deflection, dither), optional
            The free-air segment the model was identified on (the ``segment``
            route).  When the rate is reduced, the numerator is identified
            anew on it at REEP's rate (:func:`_model_at_rate`): an ARX fit
            at fs/f0 = 40 carries the ill-conditioning REEP avoids, and its
            numerator error biased f0′ by 0.2 Hz and Q′ by 0.7 σ at 2 MHz
            (50 kHz, Q 250, 0.1 nm), against none with the true numerator.
        continuous_drive : bool, optional
            The drive is continuous and the model continuous (f0, Q, gain
            and delay: the ``f0-q`` route): the numerator becomes the FIR of
            :func:`~afmtool.models.discretisation.continuous_input_filter`
            at REEP's rate, built from the numerator and poles REEP would
            run with (module docstring).  A segment's ARX fit is a discrete
            model with three taps; REEP keeps its structure (in free air
            REEP's mean follows the model's poles nearly one for one, so a
            filter shaped by them would change nothing).
        """
        fs = float(sample_rate_hz)
        factor = reduction_factor(fs, resonance_hz, params.samples_per_period)
        rate = fs / factor
        window_s = 1.0 / ((1.0 - params.lam) * fs) if params.lam else params.window_us / 1e6
        # a window no capture can hold is refused here, by the parameter that set it (λ = 1 − 1e-16: 9e15 samples)
        check_count(window_s * fs, *(("lam", params.lam) if params.lam else ("window_us", params.window_us)))
        # at D = 1 a given λ is used as it is, bit for bit
        lam = params.lam if (params.lam and factor == 1) else forgetting_factor(window_s, rate)
        rows = _row_spacing(params, row_every, fs, drive_hz, window_s, factor)
        reep_numerator, input_taps = None, None
        if params.use_input:
            if numerator is None or denominator is None:
                raise ConfigError("REEP with the dither needs the free-air numerator and denominator")
            reep_numerator = tuple(float(a) for a in numerator)
            reep_denominator = tuple(float(b) for b in denominator)
            if factor > 1:
                reep_numerator, reep_denominator = _model_at_rate(numerator, denominator, fs, factor, drive_hz,
                                                                  segment)
            if continuous_drive:
                from afmtool.models.discretisation import continuous_input_filter

                input_taps = _read_only(continuous_input_filter(reep_numerator, reep_denominator, rate, drive_hz))
                reep_numerator = (1.0, 0.0, 0.0)
        sos = None
        if not params.use_input and bandpass_half_width_hz > 0:
            sos = _bandpass_sos(drive_hz, bandpass_half_width_hz, fs)
        return cls(fs, factor, lam, float(params.p0), bool(params.static_offset), bool(params.bias_compensation),
                   bool(params.use_input), reep_numerator, rows, float(drive_hz), _read_only(anti_alias_taps(factor)),
                   sos, window_s, input_taps)


    # ------------------------------------------------------------------ what it is
    @property
    def rate_hz(self) -> float:
        """REEP's rate fs/D, Hz."""
        return self.sample_rate_hz / self.factor

    @property
    def capture_lam(self) -> float:
        """The forgetting factor per capture sample with the same window (λ itself when D = 1)."""
        return self.lam if self.factor == 1 else 1.0 - (1.0 - self.lam) / self.factor

    @property
    def row_rate_hz(self) -> float:
        """Rows per second."""
        return self.sample_rate_hz / self.row_every

    def with_rows(self, row_every: int) -> ReepEstimator:
        """The same estimator with another row spacing (a multiple of D); the kept rows agree bit for bit."""
        return dataclasses.replace(self, row_every=int(row_every))

    def lead_samples(self, residual: float | None = None) -> int | None:
        """Capture samples a fresh state needs before its rows equal a running one's (:mod:`~afmtool.estimators.split_lead`)."""
        from afmtool.estimators.split_lead import DEFAULT_RESIDUAL, forgetting_lead, sos_lead

        forgetting = forgetting_lead(self.lam, residual or DEFAULT_RESIDUAL)
        if forgetting is None:
            return None
        leads = [forgetting * self.factor + len(self.taps) + self.factor * self._input_order]
        if self.bandpass_sos is not None:
            leads.append(sos_lead(self.bandpass_sos))
        return None if any(lead is None for lead in leads) else max(leads)

    # ------------------------------------------------------------------ running it
    def initial(self, start: int = 0) -> ReepEstimatorState:
        """The state before capture sample ``start`` (a stream's first sample, or a split lead's, on the row grid)."""
        if start % self.row_every:
            raise ConfigError(f"a REEP stream must start on its row grid (a multiple of {self.row_every}), not at {start}")
        rls = ReepState.initial(lam=self.lam, p0=self.p0, static_offset=self.static_offset)
        # the held-back samples count as seen, so that the recursion keeps its rows on the stream's grid
        rls = dataclasses.replace(rls, n_samples=self.filter_start)
        past = np.zeros(len(self.taps) - 1)
        zi = np.zeros((self.bandpass_sos.shape[0], 2)) if self.bandpass_sos is not None else None
        inputs = np.zeros(self._input_order) if self.input_taps is not None else None
        return ReepEstimatorState(rls, int(start), past, past.copy(), zi, self.filter_start, inputs)

    @property
    def _input_order(self) -> int:
        """Past samples the input filter B(z) needs (0 without one)."""
        return 0 if self.input_taps is None else len(self.input_taps) - 1

    @property
    def filter_start(self) -> int:
        """Filtered samples held back at a stream's start, a whole number of rows.

        Until the anti-alias filter's history is filled (L − 1 inputs), its
        outputs are those of a signal that was zero before the stream, and
        deflection and dither do not obey one model there.  Fed to the
        recursion, that start stays in its memory as λⁿ: measured at 4 MHz
        (D = 12) on a noise-free free-air capture, Q′ read +40 after 0.5 ms
        and +0.8 after 2 ms.  Those samples are held back; their rows are
        the initial state's (θ = 0, σ̂² undefined: flagged not converged).
        The count does not depend on the row spacing, so estimators that
        differ only in it agree at their common rows.  The input filter
        B(z) (continuous drive) holds back its own start likewise.
        """
        anti_alias = 0 if self.factor == 1 else -(-(len(self.taps) - 1) // self.factor)
        return anti_alias + self._input_order

    def run(self, state: ReepEstimatorState, deflection, dither=None) -> ReepRun:
        """REEP over the next chunk: its rows (every ``row_every`` capture samples) and the next state.

        ``deflection`` (and ``dither`` with ``use_input``) are the capture
        samples from ``state.start`` on; chunks of any sizes give the rows of
        one call.
        """
        p = np.ascontiguousarray(deflection, dtype=np.float64)
        zi = state.bandpass_zi
        if self.bandpass_sos is not None:
            from scipy.signal import sosfilt

            p, zi = sosfilt(self.bandpass_sos, p, zi=zi)
        p_history, g_history = state.deflection_history.copy(), state.dither_history.copy()
        g = np.ascontiguousarray(dither, dtype=np.float64) if self.use_input else None
        if self.factor > 1:
            p = decimate_block(p, self.taps, self.factor, state.start, p_history)
            if g is not None:
                g = decimate_block(g, self.taps, self.factor, state.start, g_history)
        inputs = state.input_history
        if g is not None and self.input_taps is not None:
            # B(z)g with the last inputs of the previous chunk in front
            extended = np.concatenate((inputs, g))
            g = np.convolve(extended, self.input_taps, mode="valid")
            inputs = extended[len(extended) - self._input_order:].copy()
        held = min(state.skip, len(p))
        block, rls = reep_update(
            state.rls, p[held:], g[held:] if g is not None else None, self.numerator,
            bias_compensation=self.bias_compensation, use_input=self.use_input,
            keep_every=self.row_every // self.factor, drive_cycles_per_sample=self.drive_hz / self.rate_hz,
        )
        if held:
            per_row, done = self.row_every // self.factor, self.filter_start - state.skip
            block = _with_held_rows(block, (done + held) // per_row - done // per_row, state.rls.static_offset)
        next_state = ReepEstimatorState(rls, state.start + len(deflection), p_history, g_history, zi, state.skip - held,
                                        inputs)
        return ReepRun(block, next_state)

    def describe(self) -> ReepEstimatorRecord:
        """The estimator's settings for report.json."""
        return ReepEstimatorRecord(
            window_us=self.window_s * 1e6,
            window_samples=self.window_s * self.sample_rate_hz,
            forgetting_factor=self.capture_lam,
            reep_forgetting_factor=self.lam,
            rate_reduction=self.factor,
            reep_rate_hz=self.rate_hz,
            samples_per_period=self.rate_hz / self.drive_hz if self.drive_hz else None,
            anti_alias=None if self.factor == 1 else AntiAlias(
                type="root-raised-cosine", rolloff=ANTI_ALIAS_ROLLOFF, taps=len(self.taps)),
            row_every_samples=self.row_every,
            row_rate_hz=self.row_rate_hz,
            row_every_s=self.row_every / self.sample_rate_hz,
            rows_per_window=self.window_s * self.sample_rate_hz / self.row_every,
            input_filter=None if self.input_taps is None else InputFilter(
                type="FIR exact for a continuous drive across drive·(1 ± 0.2)", taps=len(self.input_taps)),
        )



#: Rows per forgetting window at the default density (``rows = "resolution"``, issue 33): the
#: estimator cannot resolve anything shorter than its window, and 8 rows per window keep its
#: 10-90 % step response (about 1.1 windows) sampled by 8 rows and stay finer than an image pixel.
ROWS_PER_WINDOW = 8


def _row_spacing(params, row_every: int | None, fs: float, drive_hz: float, window_s: float, factor: int) -> int:
    """Capture samples per row, a multiple of D: ``row_every``, ``--decimate``, else ``rows``'s rule.

    ``resolution``: at least :data:`ROWS_PER_WINDOW` rows per window, spaced to walk
    through the drive's phase (:func:`_phase_spreading`; 23 samples at 500 kHz, 70 kHz, 400 µs);
    ``per-period``: one row per drive period (rounded to the nearest multiple of D).
    """
    if row_every or params.decimate:
        return factor * max(1, round((row_every or params.decimate) / factor))
    if getattr(params, "rows", "resolution") == "per-period":
        wanted = sample_count(1.0, fs / drive_hz, "the drive period", minimum=1, per="drive period")
        return factor * max(1, round(wanted / factor))
    longest = max(1, int(window_s * fs / ROWS_PER_WINDOW) // factor)
    shortest = max(1, (3 * longest) // 4, longest - _MOST_CANDIDATES + 1)
    return factor * _phase_spreading(range(shortest, longest + 1), factor * drive_hz / fs)


#: Rows whose drive phase repeats within this many rows are avoided (:func:`_phase_spreading`).
_PHASE_ORDERS = 6
#: Spacings tried at most: a window of λ = 1 − 1e-16 (1e16 samples) offered 2.5e14 (a hang); at the
#: defaults there are 6, and any window under 250 ms at 2 MHz offers fewer than 4096.
_MOST_CANDIDATES = 4096


def _phase_spreading(candidates: range, cycles_per_unit: float) -> int:
    """The candidate spacing (in REEP samples) whose rows walk through the drive's phase; the largest on ties.

    REEP's per-sample estimate and its stated std carry a small ripple at the
    drive and its harmonic.  Rows an integer or half-integer number of drive
    periods apart sample that ripple at one or two phases only, and the rows'
    means and stated stds are then biased (at 500 kHz and 70 kHz, 25 samples are
    3.5 periods: the free-air stated std read 0.65 Hz for 1.0 Hz, the mean f0′
    moved 0.07 Hz).  The spacing is taken from the top quarter of the allowed
    range (8 to 11 rows per window then) where q·(phase step) is farthest
    from a whole cycle for every q up to :data:`_PHASE_ORDERS`.
    """
    if not cycles_per_unit > 0:
        return candidates[-1]

    def spread(n: int) -> float:
        step = n * cycles_per_unit
        return min(abs(q * step - round(q * step)) for q in range(1, _PHASE_ORDERS + 1))

    return max(reversed(candidates), key=lambda n: (round(spread(n), 3), n))


def capture_rate_coefficients(b1, b0, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(b1, b0) at the capture's rate with the poles of REEP's at fs/D: z = z_D^{1/D} (NaN where not under-damped).

    With z_D = r·e^{±jθ} (b0 = r², b1 = −2r cos θ), the capture-rate poles are
    r^{1/D}·e^{±jθ/D}, the principal roots: θ < π at REEP's rate, so θ/D is the
    capture's own angle.
    """
    b1 = np.asarray(b1, dtype=np.float64)
    b0 = np.asarray(b0, dtype=np.float64)
    if factor == 1:
        return b1, b0
    with np.errstate(invalid="ignore", divide="ignore"):
        radius = np.sqrt(b0)
        angle = np.arccos(np.clip(-b1 / (2.0 * radius), -1.0, 1.0))
        underdamped = (b0 > 0) & (b0 < 1) & (b1 * b1 < 4.0 * b0)
        radius_fs = radius ** (1.0 / factor)
        b1_fs = np.where(underdamped, -2.0 * radius_fs * np.cos(angle / factor), np.nan)
        b0_fs = np.where(underdamped, radius_fs * radius_fs, np.nan)
    return b1_fs, b0_fs


def _with_held_rows(block: ReepBlock, n_rows: int, static_offset: bool) -> ReepBlock:
    """``block`` after ``n_rows`` rows of the initial state: θ = 0, σ̂² and the covariance undefined."""
    if not n_rows:
        return block
    zeros, nans = np.zeros(n_rows), np.full(n_rows, np.nan)
    return ReepBlock(
        np.concatenate((zeros, block.b1)), np.concatenate((zeros, block.b0)), np.concatenate((nans, block.sigma2)),
        np.concatenate((zeros, block.c)) if static_offset else None,
        np.concatenate((np.full((n_rows, 3), np.nan), block.covariance)),
    )


def _model_at_rate(numerator, denominator, fs: float, factor: int, drive_hz: float,
                   segment: tuple[np.ndarray, np.ndarray] | None) -> tuple[tuple, tuple]:
    """((a2, a1, a0), (b1, b0)) at fs/D: the bias-compensated ARX fit of the filtered, decimated segment, else
    the matched numerator with the pole map of the capture-rate model.

    The fit leaves out the filter's start (its history is zero there, so the
    filtered signals do not yet obey one model).  Without a segment (a given
    or metadata model), :func:`~afmtool.models.discretisation.rate_numerator`
    matches the capture-rate model at the drive and DC.
    """
    from afmtool.models.discretisation import discrete_denominator, rate_numerator, resonance_from_denominator

    taps = anti_alias_taps(factor)
    start = -(-len(taps) // factor) + 2
    if segment is not None and len(segment[0]) // factor > start + 64:
        from afmtool.estimators.rls import identify_arx

        p, g = (decimate_block(x, taps, factor, 0, np.zeros(len(taps) - 1)) for x in segment)
        fit = identify_arx(p[start:], g[start:])
        f0_hz, q, valid = resonance_from_denominator(fit.b1, fit.b0, fs / factor)
        if valid:
            return fit.numerator, (float(fit.b1), float(fit.b0))
    f0_hz, q, _ = resonance_from_denominator(denominator[0], denominator[1], fs)
    poles = discrete_denominator(float(f0_hz), float(q), fs / factor)
    return tuple(rate_numerator(numerator, denominator, fs, fs / factor, drive_hz)), (float(poles.b1), float(poles.b0))


def _read_only(values: np.ndarray) -> np.ndarray:
    values = np.ascontiguousarray(values, dtype=np.float64)
    values.setflags(write=False)
    return values


def _bandpass_sos(centre_hz: float, half_width_hz: float, sample_rate_hz: float) -> np.ndarray:
    """Output-only: a 2nd-order Butterworth band-pass ±``half_width_hz`` around the peak (docs/conventions.md)."""
    from scipy.signal import butter

    low = max(centre_hz - half_width_hz, 1.0)
    high = min(centre_hz + half_width_hz, 0.49 * sample_rate_hz)
    if not low < high:
        raise ConfigError(f"no band of ±{half_width_hz:g} Hz around {centre_hz:g} Hz below the Nyquist frequency")
    return butter(2, [low, high], btype="bandpass", fs=sample_rate_hz, output="sos")  # sosfilt refuses a read-only one


class Settling(NamedTuple):
    """The estimator's measured response to a step of the cantilever's f0 and Q (:func:`step_settling`).

    Attributes
    ----------
    f0_s, q_s : float or None
        10–90 % settling time of f0′ and Q′, s (None: not reached within ten windows).
    f0_step_hz, q_step : float
        The step applied.
    """

    f0_s: float | None
    q_s: float | None
    f0_step_hz: float
    q_step: float


#: Windows simulated before and after the step of :func:`step_settling`.
_SETTLE_BEFORE, _SETTLE_AFTER = 5, 10


def _settling_span(estimator: ReepEstimator) -> tuple[int, int]:
    """(the step's sample, the samples simulated) of :func:`step_settling`."""
    window = int(math.ceil(estimator.window_s * estimator.sample_rate_hz))
    # the step on a REEP sample (the rows below are every REEP sample), whatever --decimate asks of the output
    step_at = estimator.factor * -(-_SETTLE_BEFORE * window // estimator.factor)
    return step_at, step_at + _SETTLE_AFTER * window


def settling_samples(estimator: ReepEstimator) -> int:
    """Capture samples :func:`step_settling` simulates (15 windows): its memory is 16 bytes a sample."""
    return _settling_span(estimator)[1]


def step_settling(estimator: ReepEstimator, numerator, denominator, dither: np.ndarray) -> Settling:
    """Run the estimator on a noise-free capture whose f0 drops by half a linewidth and Q by 10 %.

    The capture is the free-air model at the capture's rate (``numerator``,
    ``denominator``) driven by ``dither`` (the run's own, repeated as needed),
    its denominator switched at t0 to the pole map of (f0 − f0/(2Q), 0.9·Q)
    while the numerator stays (a tip–sample force changes only the
    denominator, docs/conventions.md ch. 5).  The estimator runs as it runs on the
    capture, at its rate and λ, with a row at every REEP sample; the 10–90 %
    times of f0′ and Q′ are read off the rows.
    """
    from afmtool.estimators.rls import _arx_output_kernel
    from afmtool.models.discretisation import discrete_denominator, resonance_from_denominator

    fs = estimator.sample_rate_hz
    f0, q, valid = resonance_from_denominator(denominator[0], denominator[1], fs)
    if not valid:
        raise ConfigError(f"the free-air denominator {tuple(denominator)!r} is not an under-damped mode")
    step_at, total = _settling_span(estimator)
    g = np.resize(np.ascontiguousarray(dither, dtype=np.float64), total)
    after = (f0 - f0 / (2.0 * q), 0.9 * q)
    p = np.empty(total)
    a2, a1, a0 = (float(a) for a in numerator)
    _arx_output_kernel(g[:step_at], a2, a1, a0, float(denominator[0]), float(denominator[1]), p[:step_at], 0.0, 0.0)
    b1, b0 = discrete_denominator(*after, fs)
    _arx_output_kernel(g[step_at - 2:], a2, a1, a0, float(b1), float(b0), p[step_at - 2:], p[step_at - 2], p[step_at - 1])
    rows = estimator.with_rows(estimator.factor)
    block = rows.run(rows.initial(), p, g).block
    f0_rows, q_rows, _ = resonance_from_denominator(block.b1, block.b0, estimator.rate_hz)
    t = (np.arange(len(f0_rows)) + 1) * estimator.factor - 1
    return Settling(
        _seconds(_ten_ninety(t, f0_rows, step_at, f0, after[0]), fs),
        _seconds(_ten_ninety(t, q_rows, step_at, q, after[1]), fs),
        after[0] - f0,
        after[1] - q,
    )


def _seconds(samples: int | None, fs: float) -> float | None:
    return None if samples is None else samples / fs


def _ten_ninety(t: np.ndarray, values: np.ndarray, step_at: int, before: float, after: float) -> int | None:
    """Samples from the first row 10 % of the way from ``before`` to ``after`` to the first row 90 % of the way."""
    progress = (values - before) / (after - before)
    later = t >= step_at
    ten = np.flatnonzero(later & (progress >= 0.1))
    ninety = np.flatnonzero(later & (progress >= 0.9))
    if not ten.size or not ninety.size:
        return None
    return int(t[ninety[0]] - t[ten[0]])
