"""The phases of a drive that was not recorded, from the deflection it caused.

An instrument that does not record its dither still says what it drove: the
lines' frequencies F_i (Hz) and amplitudes A_i (V) (``--drive``).  What it
does not say is each line's phase relative to the capture's first sample.
On the free-air segment the deflection is

    p(t) = Σ_i A_i·|G(jω_i)|·cos(ω_i t + φ_i + ∠G(jω_i)) + noise,

with G the free-air response of eq. 3.1.  A linear least-squares fit of p on
cos ω_i t and sin ω_i t gives each line's complex amplitude D_i; G is then
found from the magnitudes alone, and φ_i = ∠D_i − ∠G(jω_i).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = [
    "DriveLine",
    "DrivePhaseFit",
    "parse_drive_lines",
    "line_amplitudes",
    "zoh_response",
    "fit_drive_phases",
    "synthesize_drive",
    "excitation_lines",
    "DriveResponse",
    "drive_phase_std",
    "drive_fit_warnings",
    "envelope_beat",
    "drive_std_rows",
]


#: ``response_source`` of the fit that uses the lines' common phase origin as well as their magnitudes.
COMMON_ORIGIN = "line magnitudes and common phase origin"

#: ``response_source`` of the fit from the magnitudes alone.
MAGNITUDES = "line magnitudes"


class DriveLine(NamedTuple):
    """One line of the dither: frequency (Hz), amplitude (V) and cosine phase (rad) at t = 0 (NaN: to be fitted).

    ``design_phase_rad`` is the line's phase at the synthesiser's own origin (a designed loop's start,
    ``lines.json``), which is not the capture's first sample: the common-origin fit (eq. D.4) keeps
    these offsets between the lines and fits the origin.  0 for lines started together.
    """

    frequency_hz: float
    amplitude_v: float
    phase_rad: float = math.nan
    design_phase_rad: float = 0.0


class DrivePhaseFit(NamedTuple):
    """The fitted lines and the second-order response their magnitudes imply.

    Attributes
    ----------
    lines : tuple of DriveLine
        With their fitted phases.
    f0_hz, q, gain : float
        G(s) = gain·ω0² / (s² + (ω0/Q)s + ω0²), discretised with a zero-order
        hold, from the lines' magnitudes (``gain`` in deflection units per V);
        from the metadata when fewer than three lines.
    response_source : str
        ``"line magnitudes and common phase origin"`` (eq. D.4),
        ``"line magnitudes"``, or where the given f0 and Q came from.
    deflection_amplitudes : tuple of float
        |D_i|, deflection units.
    f0_std_hz, q_std : float
        One-standard-deviation uncertainty of f0 and Q: from the line
        amplitudes' noise through the magnitude fit, or the given ones (0
        when the metadata gives none).
    phase_std_rad : tuple of float
        Each fitted phase's standard deviation (eq. D.2), rad.
    closure_chi2 : float
        χ² of the common-phase-origin fit (eq. D.4, 2K − 5 degrees of
        freedom): NaN when it was not tried (f0 and Q given, fewer than
        three lines or not a comb, ``common_origin=False``), infinite when
        it did not converge.  Above the 99.9 % point the lines were not in phase at
        one instant and the magnitudes alone gave f0 and Q.
    """

    lines: tuple[DriveLine, ...]
    f0_hz: float
    q: float
    gain: float
    response_source: str
    deflection_amplitudes: tuple[float, ...]
    f0_std_hz: float = 0.0
    q_std: float = 0.0
    phase_std_rad: tuple[float, ...] = ()
    closure_chi2: float = math.nan


class DriveResponse(NamedTuple):
    """A free-air resonance given for the phase fit (``--model``, ``--f0/--q``): f0 (Hz), Q, their std, where from."""

    f0_hz: float
    q: float
    f0_std_hz: float = 0.0
    q_std: float = 0.0
    source: str = ""


def parse_drive_lines(text: str) -> tuple[DriveLine, ...]:
    """``"71000:0.05,70000:0.025"`` → lines (Hz, V), for ``--drive``.

    A third field gives a line's phase at the capture's first sample in
    degrees (``"71000:0.05:-90"``, cosine phase); then it is not fitted.  Give
    it for every line or for none.  Lines without one have phase NaN.
    """
    lines = []
    for item in text.split(","):
        fields = item.strip().split(":")
        try:
            if len(fields) not in (2, 3):
                raise ValueError
            phase = math.radians(float(fields[2])) if len(fields) == 3 else math.nan
            line = DriveLine(float(fields[0]), float(fields[1]), phase)
        except ValueError:
            raise ConfigError(
                f"--drive item {item.strip()!r} must look like FREQUENCY_HZ:AMPLITUDE_V[:PHASE_DEG]"
            ) from None
        if not (math.isfinite(line.frequency_hz) and line.frequency_hz > 0):
            raise ConfigError(f"--drive item {item.strip()!r}: the frequency must be > 0")
        if not (math.isfinite(line.amplitude_v) and line.amplitude_v > 0):
            raise ConfigError(f"--drive item {item.strip()!r}: the amplitude must be > 0")
        if len(fields) == 3 and not math.isfinite(line.phase_rad):
            raise ConfigError(f"--drive item {item.strip()!r}: the phase must be finite")
        lines.append(line)
    frequencies = [line.frequency_hz for line in lines]
    if len(set(frequencies)) != len(frequencies):
        raise ConfigError(f"--drive {text!r} names a frequency twice")
    given = [math.isfinite(line.phase_rad) for line in lines]
    if any(given) and not all(given):
        raise ConfigError(f"--drive {text!r}: give a phase for every line or for none")
    return tuple(lines)


def line_amplitudes(x: np.ndarray, sample_rate_hz: float, start_sample: int, frequencies_hz) -> np.ndarray:
    """Complex amplitudes D_i with x[n] ≈ Re Σ D_i·exp(jω_i t_n) + c, t_n = (start_sample + n)/fs.

    Linear least squares on [cos ω_i t, sin ω_i t, 1]: unlike a per-line
    DFT it does not leak one line into another on a short segment.
    """
    x = np.asarray(x, dtype=np.float64)
    t = (start_sample + np.arange(x.size)) / sample_rate_hz
    omega = 2.0 * np.pi * np.asarray(frequencies_hz, dtype=np.float64)
    phase = np.outer(t, omega)
    design = np.column_stack([np.cos(phase), np.sin(phase), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    k = omega.size
    # c·cos + s·sin = Re[(c − j s)·exp(jωt)]
    return coef[:k] - 1j * coef[k : 2 * k]


def _continuous_from_magnitudes(f: np.ndarray, magnitude: np.ndarray) -> tuple[float, float] | None:
    """(f0, Q) of a continuous second-order low-pass through |H(f_i)| (≥ 3 lines), or None.

    1/|H|² = (1/g²)·[(1 − f²/f0²)² + f²/(f0²Q²)] = α + β f² + γ f⁴ is linear
    in (α, β, γ): f0 = (α/γ)^(1/4), 1/Q² = 2 + β f0²/α.  The start of the
    discrete fit.
    """
    scale = float(np.max(f))
    u = (f / scale) ** 2  # scaled, for a well-conditioned fit
    design = np.column_stack([np.ones_like(u), u, u * u])
    (alpha, beta, gamma), *_ = np.linalg.lstsq(design, 1.0 / magnitude**2, rcond=None)
    if not (alpha > 0 and gamma > 0):
        return None
    inv_q2 = 2.0 + beta * math.sqrt(alpha / gamma) / alpha
    if not inv_q2 > 0:
        return None
    return scale * (alpha / gamma) ** 0.25, 1.0 / math.sqrt(inv_q2)


def zoh_response(frequency_hz, f0_hz: float, q: float, sample_rate_hz: float) -> np.ndarray:
    """H(e^{jωT}) of G(s) = ω0²/(s² + (ω0/Q)s + ω0²) discretised with a zero-order hold (DC gain 1).

    The form of REEP's five-parameter free-air model (eq. 3.39's regressors,
    a2 = 0), so a dither whose phases follow it is explained exactly by it.
    """
    from afmtool.models.discretisation import discrete_denominator, zoh_numerator

    a2, a1, a0 = zoh_numerator(f0_hz, q, sample_rate_hz)
    b1, b0 = discrete_denominator(f0_hz, q, sample_rate_hz)
    z_inv = np.exp(-2j * np.pi * np.asarray(frequency_hz, dtype=np.float64) / sample_rate_hz)
    return (a2 + a1 * z_inv + a0 * z_inv**2) / (1.0 + b1 * z_inv + b0 * z_inv**2)


def continuous_response(frequency_hz, f0_hz: float, q: float, sample_rate_hz: float) -> np.ndarray:
    """G(jω) = ω0²/(ω0² − ω² + jωω0/Q) (eq. 3.1, DC gain 1): a continuous drive, sampled by the ADC."""
    u = np.asarray(frequency_hz, dtype=np.float64) / f0_hz
    return 1.0 / (1.0 - u * u + 1j * u / q)


#: Largest ln Q the magnitude fit tries; exp overflows at 709.8.
_MAX_LOG_Q = 700.0

#: Largest Q accepted from the line magnitudes: far above any cantilever (about 1e6 in
#: ultra-high vacuum).  The fit runs there when the side lines hold only noise.
_MAX_Q = 1e8


def _response(hold: str):
    return zoh_response if hold == "zero-order" else continuous_response


def _damped_gauss_newton(residual, x: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, residual, Jacobian) at the least squares of ``residual`` near ``x``: Gauss–Newton with Levenberg damping.

    ``x[0]`` is a frequency (Hz; its difference step 1e-7 of it), the rest are logs and phases
    (step 1e-7).  Stops when a step moves every parameter by less than ``tolerance`` (relative for
    ``x[0]``), or the damping runs away; a non-finite residual rejects a step, and a non-finite
    Jacobian ends the search (the caller checks it).
    """
    r = residual(x)
    jac = np.full((r.size, x.size), np.nan)
    if not np.all(np.isfinite(r)):
        return x, r, jac
    eye = np.eye(x.size)
    damping = 1e-3
    for _ in range(100):
        steps = np.r_[max(1e-7 * x[0], 1e-6), np.full(x.size - 1, 1e-7)]
        jac = np.column_stack([(residual(x + eye[k] * steps[k]) - r) / steps[k] for k in range(x.size)])
        if not np.all(np.isfinite(jac)):
            break
        normal = jac.T @ jac
        step = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-30), -jac.T @ r)
        trial = residual(x + step)
        if np.all(np.isfinite(trial)) and trial @ trial < r @ r:
            x, r, damping = x + step, trial, damping / 3
            if np.all(np.abs(step) <= tolerance * np.r_[x[0], np.ones(x.size - 1)]):
                break
        else:
            damping *= 10
            if damping > 1e12:
                break
    return x, r, jac


def _response_from_magnitudes(f: np.ndarray, magnitude: np.ndarray, fs: float, hold: str) -> tuple[float, float, float]:
    """(f0, Q, gain) of the second-order response through |H(f_i)| (≥ 3 lines).

    Gauss–Newton with Levenberg damping on the log magnitudes over (f0, ln Q),
    the gain eliminated (its log is the mean residual); started from the
    continuous closed form.
    """
    response = _response(hold)
    start = _continuous_from_magnitudes(f, magnitude)
    if start is None or not (0 < start[0] < fs / 2 and start[1] > 0.5):
        start = (float(f[int(np.argmax(magnitude))]), 50.0)
    x = np.array([start[0], math.log(max(start[1], 0.51))])
    log_m = np.log(magnitude)

    def residual(params: np.ndarray) -> np.ndarray:
        # ln Q ≥ 700 would overflow exp (lines that hold only noise walk there): a rejected step
        if not params[1] < _MAX_LOG_Q:
            return np.full(f.size, np.inf)
        f0, q = params[0], math.exp(params[1])
        if not (0 < f0 < fs / 2 and q > 0.5):
            return np.full(f.size, np.inf)
        r = log_m - np.log(np.abs(response(f, f0, q, fs)))
        return r - r.mean()

    x, r, _ = _damped_gauss_newton(residual, x, 1e-9)
    f0, q = float(x[0]), math.exp(x[1])
    if not (np.all(np.isfinite(r)) and 0 < f0 < fs / 2 and 0.5 < q < _MAX_Q):
        raise InputError(
            "the drive lines' deflection amplitudes do not fit a second-order resonance; "
            "give lines around the resonance, or metadata cantilever f0_hz and q"
        )
    gain = float(np.exp(np.mean(log_m - np.log(np.abs(response(f, f0, q, fs))))))
    return f0, q, gain


def fit_drive_phases(
    deflection: np.ndarray,
    sample_rate_hz: float,
    start_sample: int,
    lines: tuple[DriveLine, ...],
    *,
    f0_hz: float | None = None,
    q: float | None = None,
    hold: str = "none",
    common_origin: bool = True,
    f0_std_hz: float | None = None,
    q_std: float | None = None,
    given_from: str = "metadata cantilever f0_hz, q",
) -> DrivePhaseFit:
    """Each drive line's phase at t = 0 from the free-air deflection.

    Parameters
    ----------
    deflection : ndarray
        Free-air segment of the deflection (any length unit).
    sample_rate_hz : float
    start_sample : int
        Index of the segment's first sample in the capture (t = 0 at sample 0).
    lines : tuple of DriveLine
        Frequencies (Hz) and amplitudes (V); phases are ignored.
    f0_hz, q : float, optional
        Free-air resonance (metadata or ``--model``): when given, the phases
        are fitted against it; without them the lines' magnitudes (three or
        more) give f0 and Q.
    common_origin : bool
        The lines started together (a synthesiser's sum of sines, the
        thesis's g(t) of §3.3.2): without f0 and Q given, fit the lines'
        complex amplitudes with one phase origin (eq. D.4), not the
        magnitudes alone.  Kept only if its χ² passes.
    f0_std_hz, q_std, given_from : float, float, str, optional
        Their uncertainties (0 when not given) and where they came from.
    hold : {"none", "zero-order"}
        How the drive reached the cantilever: a continuous signal (the
        default, a real instrument's drive) or held between samples by a DAC
        at the sample rate (a discrete-time simulator).

    Returns
    -------
    DrivePhaseFit

    Notes
    -----
    With D_i the deflection's complex amplitude at ω_i (least squares,
    :func:`line_amplitudes`) and H the free-air response G(s) = g·ω0²/(s² +
    (ω0/Q)s + ω0²) of eq. 3.1 (:func:`continuous_response`; with
    ``hold="zero-order"`` discretised with a zero-order hold,
    :func:`zoh_response`), |D_i|/A_i = |H(ω_i)| fixes g, ω0, Q from three or
    more lines (or ω0, Q are given: metadata or ``--model``), and

        φ_i = ∠D_i − ∠H(ω_i).                                   (D.2)

    Only the magnitudes carry ω0 and Q: the side lines must stand clear of
    the noise (they set ω0 to about Δf times their relative error, and the
    main line's phase at resonance with it, 2Q/f0 rad per Hz:
    :func:`_phase_uncertainty`), and the response must be the right one (a
    held and a continuous drive differ by a few % at f/fs ≈ 0.15).  A pure
    delay between drive and deflection ends up in φ_i.
    """
    fs = float(sample_rate_hz)
    frequencies = np.array([line.frequency_hz for line in lines])
    amplitudes = np.array([line.amplitude_v for line in lines])
    if hold not in ("none", "zero-order"):
        raise ConfigError(f"{hold=} must be 'none' or 'zero-order'")
    response = _response(hold)
    if np.any(frequencies >= fs / 2):
        raise ConfigError(f"--drive lines must be below the Nyquist frequency {fs / 2:g} Hz")
    if len(deflection) < 4 * len(lines) + 8:
        raise InputError(f"the free-air segment ({len(deflection)} samples) is too short to fit the drive phases")
    d = line_amplitudes(deflection, fs, start_sample, frequencies)
    magnitude = np.abs(d) / amplitudes
    if np.any(magnitude <= 0):
        raise InputError("a drive line has no response in the deflection on the free-air segment")
    f0, qf, gain, source = _free_air_of_lines(frequencies, magnitude, fs, hold, f0_hz, q, given_from)
    phases = np.angle(d) - np.angle(response(frequencies, f0, qf, fs))
    line_noise = _line_noise(deflection, fs, start_sample, frequencies, d)
    given = (f0_std_hz or 0.0, q_std or 0.0) if source != MAGNITUDES else None
    f0_std, q_std_fit, phase_std = _phase_uncertainty(frequencies, line_noise / np.abs(d), f0, qf, fs, hold, given)
    closure_chi2 = math.nan
    # with f0 and Q given the common origin adds nothing REEP feels: it fixes the side lines' mean phase, to
    # which Q′ is insensitive, and leaves their difference (the envelope's timing) as noisy as before
    if given is None and common_origin and frequencies.size >= 3 and _comb_steps(frequencies, amplitudes) is not None:
        design = np.array([line.design_phase_rad for line in lines])
        common = _common_origin_fit(frequencies, amplitudes, d, line_noise[0], fs, hold, (f0, qf, gain), phases,
                                    design)
        # a fit that does not converge fails the test as surely as one whose χ² is too large
        closure_chi2 = common.chi2 if common is not None else math.inf
        if common is not None:
            if common.chi2 <= _chi2_upper(common.dof):
                f0, qf, gain, phases = common.f0_hz, common.q, common.gain, common.phases
                f0_std, q_std_fit, phase_std = common.f0_std_hz, common.q_std, common.phase_std
                source = COMMON_ORIGIN
    fitted = tuple(DriveLine(float(f), float(a), float(p), line.design_phase_rad)
                   for f, a, p, line in zip(frequencies, amplitudes, phases, lines))
    return DrivePhaseFit(fitted, float(f0), float(qf), float(gain), source, tuple(float(v) for v in np.abs(d)),
                         f0_std, q_std_fit, tuple(float(v) for v in phase_std), closure_chi2)


class _CommonOriginFit(NamedTuple):
    f0_hz: float
    q: float
    gain: float
    phases: np.ndarray
    f0_std_hz: float
    q_std: float
    phase_std: np.ndarray
    chi2: float
    dof: int


def _comb_steps(frequencies: np.ndarray, amplitudes: np.ndarray) -> np.ndarray | None:
    """s_i with f_i = f_main + s_i·Δf, s_i integer and Δf the smallest spacing from the main line; None if not a comb."""
    main = int(np.argmax(amplitudes))
    offsets = frequencies - frequencies[main]
    spacing = np.min(np.abs(offsets[offsets != 0])) if np.any(offsets != 0) else 0.0
    if not spacing > 0:
        return None
    steps = offsets / spacing
    if np.any(np.abs(steps - np.round(steps)) > 1e-6):
        return None
    return np.round(steps)


def _chi2_upper(dof: int) -> float:
    """The 99.9 % point of χ² with ``dof`` degrees of freedom (Wilson–Hilferty; numpy only, 11.1 for dof 1 vs 10.8)."""
    z = 3.090232  # the standard normal's 99.9 % point
    k = float(dof)
    return k * (1.0 - 2.0 / (9.0 * k) + z * math.sqrt(2.0 / (9.0 * k))) ** 3


def _common_origin_fit(frequencies, amplitudes, d, line_sigma, fs, hold, start, start_phases,
                       design_phases) -> _CommonOriginFit | None:
    """f0, Q, g and the phases of lines that were in phase at one instant (eq. D.4); None when it does not apply.

    A synthesiser that starts its lines together (the thesis's
    g(t) = A sin ω0t + B sin(ω0 + Δω)t + B sin(ω0 − Δω)t, §3.3.2) gives them
    phases φ_i = φ_c + ω_i·τ at any later first sample, and a constant
    phase or a pure delay between drive and deflection keeps that form.
    On a comb f_i = f_main + s_i·Δf that is φ_i = ψ_i + c + s_i·m, with ψ_i
    the lines' phases at the synthesiser's origin (``design_phases``: 0 for
    lines started together; a designed loop's ``lines.json``), so

        D_i = g·A_i·H(f_i; f0, Q)·exp(j(ψ_i + c + s_i·m)) + noise       (D.4)

    has five real unknowns (f0, ln Q, ln g, c, m) for 2K measured numbers.
    For three lines the sixth number is the closure phase ∠D₊ + ∠D₋ − 2∠D₀
    = ∠H₊ + ∠H₋ − 2∠H₀, which pins the main line's phase at resonance to
    the side lines' phase noise: the magnitudes alone, whose side lines
    hardly depend on Q, leave it 0.05 rad uncertain at Q 400
    (tests/test_synthetic_drive_information.py).  Weighted least squares
    (white noise: every line's real and imaginary part has std
    ``line_sigma``), Gauss–Newton with Levenberg damping from the magnitude
    fit; the covariance is (JᵀJ)⁻¹ and χ² = |r|² tests the common origin
    with 2K − 5 degrees of freedom (the caller keeps the magnitude fit
    when it fails).
    """
    steps = _comb_steps(frequencies, amplitudes)
    if steps is None or frequencies.size < 3 or not line_sigma > 0:
        return None
    response = _response(hold)
    main = int(np.argmax(amplitudes))
    start_phases = start_phases - design_phases
    relative = np.angle(np.exp(1j * (start_phases - start_phases[main])))
    trial_m = np.linspace(-np.pi, np.pi, 721)
    agreement = np.abs(np.exp(1j * (relative[None, :] - steps[None, :] * trial_m[:, None])).sum(axis=1))
    m0 = float(trial_m[int(np.argmax(agreement))])
    c0 = float(np.angle(np.sum(np.exp(1j * (start_phases - steps * m0)))))
    x = np.array([start[0], math.log(start[1]), math.log(start[2]), c0, m0])

    def residual(params: np.ndarray) -> np.ndarray:
        if not params[1] < _MAX_LOG_Q:
            return np.full(2 * frequencies.size, np.inf)
        f0, q = params[0], math.exp(params[1])
        if not (0 < f0 < fs / 2 and q > 0.5):
            return np.full(2 * frequencies.size, np.inf)
        origin = np.exp(1j * (design_phases + params[3] + steps * params[4]))
        model = math.exp(params[2]) * amplitudes * response(frequencies, f0, q, fs) * origin
        r = (d - model) / line_sigma
        return np.concatenate([r.real, r.imag])

    x, r, jac = _damped_gauss_newton(residual, x, 1e-10)
    f0, q = float(x[0]), math.exp(x[1])
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jac)) and 0 < f0 < fs / 2 and 0.5 < q < _MAX_Q):
        return None
    covariance = np.linalg.pinv(jac.T @ jac)
    # φ_i = c + s_i·m: the line phases' covariance from (c, m)
    mapping = np.column_stack([np.ones_like(steps), steps])
    phase_var = np.einsum("ij,jk,ik->i", mapping, covariance[3:, 3:], mapping)
    return _CommonOriginFit(
        f0, q, math.exp(x[2]), design_phases + x[3] + steps * x[4], float(math.sqrt(max(covariance[0, 0], 0.0))),
        float(q * math.sqrt(max(covariance[1, 1], 0.0))), np.sqrt(np.maximum(phase_var, 0.0)),
        float(r @ r), 2 * frequencies.size - 5)


def _line_noise(x: np.ndarray, fs: float, start_sample: int, frequencies: np.ndarray, d: np.ndarray) -> np.ndarray:
    """σ of each |D_i| (deflection units): σ_n·√(2/N), σ_n the rms of the deflection about the lines' fit (eq. D.1)."""
    t = (start_sample + np.arange(x.size)) / fs
    model = np.real(np.exp(1j * np.outer(t, 2.0 * np.pi * frequencies)) @ d)
    residual = x - model
    residual -= residual.mean()
    return np.full(frequencies.size, float(np.sqrt(np.mean(residual * residual))) * math.sqrt(2.0 / x.size))


def _phase_uncertainty(frequencies, relative, f0, q, fs, hold, given) -> tuple[float, float, np.ndarray]:
    """(σ_f0, σ_Q, σ_φi) of the fit (eq. D.2): φ_i = ∠D_i − ∠H(f_i; f0, Q).

    σ(∠D_i) = σ(|D_i|)/|D_i| (``relative``, eq. D.1).  With f0, Q from the
    magnitudes, their covariance is (JᵀWJ)⁻¹ over (f0, ln Q, ln g), J the
    derivatives of ln g|H(f_i)| and W = diag(1/relative²); with f0, Q
    given, their given std.  Then σ_φi² = σ(∠D_i)² + g_iᵀ·cov·g_i with
    g_i = ∂∠H(f_i)/∂(f0, ln Q): at the main line near resonance ∂∠H/∂f0 ≈
    2Q/f0, so an f0 off by δ shifts the main line's phase by 2Qδ/f0.
    """
    response = _response(hold)
    steps = np.array([1e-6 * f0, 1e-6])

    def derivative(fun, k):
        plus = np.array([f0, math.log(q)])
        minus = plus.copy()
        plus[k] += steps[k]
        minus[k] -= steps[k]
        return (fun(*plus) - fun(*minus)) / (2 * steps[k])

    def log_mag(f0_, ln_q):
        return np.log(np.abs(response(frequencies, f0_, math.exp(ln_q), fs)))

    def phase(f0_, ln_q):
        return np.unwrap(np.angle(response(frequencies, f0_, math.exp(ln_q), fs)))

    if given is None:
        jac = np.column_stack([derivative(log_mag, 0), derivative(log_mag, 1), np.ones(frequencies.size)])
        weights = 1.0 / np.maximum(relative, 1e-300) ** 2
        cov = np.linalg.pinv(jac.T @ (weights[:, None] * jac))[:2, :2]
    else:
        cov = np.diag([given[0] ** 2, (given[1] / q) ** 2])
    grad = np.column_stack([derivative(phase, 0), derivative(phase, 1)])
    phase_var = relative**2 + np.einsum("ij,jk,ik->i", grad, cov, grad)
    return float(math.sqrt(max(cov[0, 0], 0.0))), float(q * math.sqrt(max(cov[1, 1], 0.0))), np.sqrt(phase_var)


def _free_air_of_lines(frequencies, magnitude, fs: float, hold: str, f0_hz, q,
                       given_from: str) -> tuple[float, float, float, str]:
    """(f0, Q, g, source) of H: the given f0 and Q (metadata or --model), else from |D_i|/A_i of three or more lines."""
    if not (f0_hz and q) and len(frequencies) >= 3:
        f0, qf, gain = _response_from_magnitudes(frequencies, magnitude, fs, hold)
        return f0, qf, gain, MAGNITUDES
    if f0_hz and q:
        f0, qf = float(f0_hz), float(q)
        gain = float(np.mean(magnitude / np.abs(_response(hold)(frequencies, f0, qf, fs))))
        return f0, qf, gain, given_from
    raise InputError(
        f"--drive gives {len(frequencies)} line(s): fitting their phases needs three lines around the resonance, "
        "or the resonance: metadata cantilever f0_hz and q, --model or --f0/--q"
    )


def synthesize_drive(lines: tuple[DriveLine, ...], sample_rate_hz: float, start_sample: int, n: int) -> np.ndarray:
    """g[k] = Σ_i A_i cos(ω_i t_k + φ_i), t_k = (start_sample + k)/fs: the dither as the ADC would sample it (V)."""
    index = start_sample + np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for line in lines:
        # cycles reduced to [0, 1) before the 2π keeps the cosine's argument small on long captures
        cycles = np.mod(index * (line.frequency_hz / sample_rate_hz), 1.0)
        out += line.amplitude_v * np.cos(2.0 * np.pi * cycles + line.phase_rad)
    return out


def excitation_lines(dither: np.ndarray, sample_rate_hz: float, f0_hz: float, floor_db: float = 30.0) -> list[float]:
    """Frequencies (Hz) of the distinct spectral lines of the dither near resonance.

    A line is a local maximum of the Hann-windowed periodogram within ±25 %
    of f0 and within ``floor_db`` dB of the strongest one; of two maxima closer than
    500 Hz only the higher counts.  REEP's five-parameter free-air
    identification needs three (§3.3.2).

    numpy only (``scipy.signal.periodogram``/``find_peaks`` would import
    scipy.signal, the largest part of REEP's start-up).
    """
    n = min(len(dither), 1 << 16)
    if n < 64:
        return []
    x = np.asarray(dither[:n], dtype=np.float64)
    window = np.hanning(n + 1)[:-1]  # periodic Hann, as scipy's periodogram uses
    power = np.abs(np.fft.rfft((x - x.mean()) * window)) ** 2
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate_hz)
    band = (freqs > 0.75 * f0_hz) & (freqs < 1.25 * f0_hz)
    if not band.any() or power[band].max() <= 0:
        return []
    power = np.where(band, power, 0.0)
    threshold = power.max() * 10.0 ** (-floor_db / 10.0)
    inner = power[1:-1]
    maxima = np.flatnonzero((inner > power[:-2]) & (inner >= power[2:]) & (inner >= threshold)) + 1
    min_bins = max(1, int(500 * n / sample_rate_hz))
    kept: list[int] = []
    for index in sorted(maxima, key=lambda i: -power[i]):  # highest first, as find_peaks(distance=...)
        if all(abs(index - other) >= min_bins for other in kept):
            kept.append(index)
    return [float(freqs[i]) for i in sorted(kept)]


def envelope_beat(dither: np.ndarray, sample_rate_hz: float, drive_hz: float, f0_hz: float, q: float) -> float:
    """m = Σ_side A_i·|G(f_i)| / (A_d·|G(f_d)|): how far a multi-line dither beats the free-air envelope.

    The NOTES' ±2B|G(f0 ± Δf)|/|G(f0)| of the thesis's three lines, for any
    lines (:func:`excitation_lines`, down to 60 dB below the strongest) of the
    recorded ``dither`` (V), with G the
    free-air response (eq. 3.1) and the main line the one nearest
    ``drive_hz``.  Each line's amplitude is the Hann-windowed spectrum's
    largest value within a bin of the line (no scalloping loss).  0 for
    fewer than two lines.
    """
    # 60 dB: a side line 3 % of the main one still beats a low-Q lever's envelope by a few %
    freqs = excitation_lines(dither, sample_rate_hz, f0_hz, floor_db=60.0)
    if len(freqs) < 2:
        return 0.0
    n = min(len(dither), 1 << 16)
    x = np.asarray(dither[:n], dtype=np.float64)
    weighted = (x - x.mean()) * np.hanning(n + 1)[:-1]
    t = np.arange(n) / sample_rate_hz
    bin_hz = sample_rate_hz / n
    amplitudes = []
    for f in freqs:
        trial = f + bin_hz * np.linspace(-1.0, 1.0, 41)
        amplitudes.append(np.abs(np.exp(-2j * np.pi * np.outer(trial, t)) @ weighted).max())
    response = np.abs(continuous_response(np.array(freqs), f0_hz, q, sample_rate_hz)) * np.array(amplitudes)
    main = int(np.argmin(np.abs(np.array(freqs) - drive_hz)))
    return float((response.sum() - response[main]) / response[main])


def drive_fit_warnings(fit: DrivePhaseFit | None) -> list[str]:
    """The report's warning when the lines did not fit one phase origin (eq. D.4's χ² test failed)."""
    if fit is None or fit.response_source != MAGNITUDES or math.isnan(fit.closure_chi2):
        return []
    dof = 2 * len(fit.lines) - 5
    why = (f"closure chi2 {fit.closure_chi2:.3g} for {dof} degree(s) of freedom, above {_chi2_upper(dof):.3g}"
           if math.isfinite(fit.closure_chi2) else "their common-origin fit does not converge")
    return [f"the drive lines do not share one phase origin ({why}): f0 and Q of the synthesised drive come from "
            "the lines' magnitudes alone, with their wider uncertainty; --drive-phases independent skips the test"]


def drive_phase_std(fit: DrivePhaseFit, drive_hz: float) -> float:
    """σ_φ of eq. D.3, rad: the main line's (nearest the lock-in frequency) and the side lines' mean in quadrature.

    The main line's phase error moves f0′ and Q′ directly (eq. D.3); a side
    line's moves REEP's free-air numerator and through it Q′ on a detuned
    tip by about as much per radian (measured on the reference captures).
    0 without a phase fit.
    """
    if fit is None or not fit.phase_std_rad:
        return 0.0
    main = min(range(len(fit.lines)), key=lambda i: abs(fit.lines[i].frequency_hz - drive_hz))
    sides = [v for i, v in enumerate(fit.phase_std_rad) if i != main]
    side_var = float(np.mean(np.square(sides))) if sides else 0.0
    return math.sqrt(fit.phase_std_rad[main] ** 2 + side_var)


def drive_std_rows(f0_hz: np.ndarray, q: np.ndarray, drive_hz: float, phase_std: float) -> tuple[np.ndarray, np.ndarray]:
    """REEP's f0′ and Q′ uncertainty from a synthesised drive's main-line phase uncertainty σ_φ (eq. D.3).

    REEP reads f0′ and Q′ from the deflection's response at the drive,
    g/R = 1 − f_d²/f0′² + j·f_d/(f0′Q′); a phase error δφ of the
    synthesised main line rotates it by −δφ, which moves

        δf0′ = f0′·δφ/(2Q′),   δQ′/Q′ = 2Q′|f0′ − f_d|/f_d·δφ + δφ²/2

    (first order off resonance; the second term the rotation's cosine at
    resonance, where the first vanishes: in free air a phase error leaves Q′
    nearly unchanged, and a detuned tip shows it most).
    """
    f0 = np.asarray(f0_hz, dtype=np.float64)
    qq = np.asarray(q, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        f0_std = f0 * phase_std / (2.0 * qq)
        q_std = qq * (2.0 * qq * np.abs(f0 - drive_hz) / drive_hz * phase_std + 0.5 * phase_std**2)
    return f0_std, q_std
