"""Dither excitations g(t): sines, the three-sine REEP excitation, chirps, stepped sines.

Every excitation is a frozen dataclass that evaluates itself analytically at
any time (``exc(t_s)``), so an integrator can read it between samples
without interpolation error.  Values are in the dither's units (V in the
simulator; multiplied by a gain in nm/V to give the forcing g of eq. 3.1).
All phases are sine phases: a line is ``A·sin(2πft + φ)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "DRIVE_KINDS",
    "Excitation",
    "MultiSine",
    "LinearChirp",
    "SteppedSine",
    "sine",
    "three_sine",
    "build_dither",
    "drive_metadata",
]

#: Names accepted by :func:`build_dither`.
DRIVE_KINDS = ("sine", "three-sine", "chirp", "stepped")


class Excitation(Protocol):
    """A dither signal that can be evaluated at arbitrary times."""

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        """Dither value at times ``t_s`` (s)."""
        ...

    @property
    def max_frequency_hz(self) -> float:
        """Highest frequency the dither contains, Hz."""
        ...

    def to_metadata(self) -> dict:
        """JSON-ready description for the capture's ``drive`` metadata."""
        ...


def _check(name: str, value: float, *, minimum: float = 0.0, exclusive: bool = True) -> None:
    ok = isinstance(value, (int, float)) and math.isfinite(value)
    ok = ok and (value > minimum if exclusive else value >= minimum)
    if not ok:
        bound = ">" if exclusive else ">="
        raise ConfigError(f"{name}={value!r} must be a finite number {bound} {minimum:g}")


@dataclass(frozen=True)
class MultiSine:
    """A sum of sines, g(t) = Σ_k A_k·sin(2πf_k t + φ_k).

    Parameters
    ----------
    amplitudes : tuple of float
        Line amplitudes A_k (dither units), ≥ 0.
    frequencies_hz : tuple of float
        Line frequencies f_k, Hz, > 0.
    phases_rad : tuple of float
        Sine phases φ_k at t = 0, rad.
    """

    amplitudes: tuple[float, ...]
    frequencies_hz: tuple[float, ...]
    phases_rad: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (len(self.amplitudes) == len(self.frequencies_hz) == len(self.phases_rad) >= 1):
            raise ConfigError(
                f"amplitudes, frequencies_hz and phases_rad need the same length >= 1, got "
                f"{len(self.amplitudes)}, {len(self.frequencies_hz)}, {len(self.phases_rad)}"
            )
        for k, (amp, freq, phase) in enumerate(zip(self.amplitudes, self.frequencies_hz, self.phases_rad)):
            _check(f"amplitudes[{k}]", amp, exclusive=False)
            _check(f"frequencies_hz[{k}]", freq)
            _check(f"phases_rad[{k}]", phase, minimum=-math.inf)

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=np.float64)
        out = np.zeros_like(t)
        for amp, freq, phase in zip(self.amplitudes, self.frequencies_hz, self.phases_rad):
            out += amp * np.sin(2.0 * np.pi * freq * t + phase)
        return out

    @property
    def max_frequency_hz(self) -> float:
        """Highest line frequency, Hz."""
        return float(max(self.frequencies_hz))

    def steady_state(self, response: np.ndarray, t_s: float) -> tuple[float, float]:
        """Steady-state output and its derivative of a linear system driven by this signal.

        Parameters
        ----------
        response : array_like of complex
            The system's frequency response H(j2πf_k) at each line.
        t_s : float
            Time, s.

        Returns
        -------
        value, rate : float
            Σ A_k|H_k| sin(ω_k t + φ_k + ∠H_k) and its time derivative (per s).
        """
        h = np.asarray(response, dtype=np.complex128)
        value = 0.0
        rate = 0.0
        for k, (amp, freq, phase) in enumerate(zip(self.amplitudes, self.frequencies_hz, self.phases_rad)):
            w = 2.0 * math.pi * freq
            arg = w * t_s + phase + float(np.angle(h[k]))
            value += amp * abs(h[k]) * math.sin(arg)
            rate += amp * abs(h[k]) * w * math.cos(arg)
        return value, rate

    def to_metadata(self) -> dict:
        return {
            "kind": "multisine",
            "frequency_hz": float(self.frequencies_hz[0]),
            "amplitude": float(self.amplitudes[0]),
            "lines": [
                {"frequency_hz": float(f), "amplitude": float(a), "phase_rad": float(p)}
                for a, f, p in zip(self.amplitudes, self.frequencies_hz, self.phases_rad)
            ],
        }


def sine(amplitude: float, frequency_hz: float, phase_rad: float = 0.0) -> MultiSine:
    """A single sine A·sin(2πft + φ) (dither units, Hz, rad)."""
    return MultiSine((float(amplitude),), (float(frequency_hz),), (float(phase_rad),))


def three_sine(
    amplitude: float, center_hz: float, sideband_offset_hz: float, sideband_scale: float = 0.5
) -> MultiSine:
    """The persistently exciting three-sine dither of §3.3.2.

    g(t) = A sin ω_c t + B sin(ω_c + Δω)t + B sin(ω_c − Δω)t with B =
    ``sideband_scale``·A (the thesis uses B = A/2 and Δf ≈ 6 kHz).  The
    sidebands make the deflection envelope beat by about
    ±2B|G(f_c ± Δf)|/|G(f_c)|; at low Q scale them down (docs/conventions.md).

    Parameters
    ----------
    amplitude : float
        Main-line amplitude A (dither units), > 0.
    center_hz : float
        Main-line frequency f_c, Hz (at or near f0).
    sideband_offset_hz : float
        Side-line offset Δf, Hz; 0 < Δf < f_c.
    sideband_scale : float, optional
        B/A ≥ 0.

    Returns
    -------
    MultiSine
        Lines ordered (f_c, f_c + Δf, f_c − Δf).
    """
    _check("amplitude", amplitude, exclusive=False)
    _check("center_hz", center_hz)
    _check("sideband_offset_hz", sideband_offset_hz)
    _check("sideband_scale", sideband_scale, exclusive=False)
    if sideband_offset_hz >= center_hz:
        raise ConfigError(f"sideband_offset_hz={sideband_offset_hz!r} must be below center_hz={center_hz!r}")
    side = sideband_scale * amplitude
    return MultiSine(
        (float(amplitude), float(side), float(side)),
        (float(center_hz), float(center_hz + sideband_offset_hz), float(center_hz - sideband_offset_hz)),
        (0.0, 0.0, 0.0),
    )


@dataclass(frozen=True)
class LinearChirp:
    """A linear frequency sweep with continuous phase.

    The instantaneous frequency goes linearly from ``start_hz`` at
    ``start_s`` to ``end_hz`` at ``start_s + duration_s`` and is held
    constant before and after, so g(t) = A sin φ(t) with
    φ(τ) = 2π(f_s τ + (f_e − f_s)τ²/(2T)) for τ = t − start_s in [0, T].

    Parameters
    ----------
    amplitude : float
        Amplitude A (dither units), > 0.
    start_hz, end_hz : float
        Sweep limits, Hz, > 0.
    duration_s : float
        Sweep duration T, s, > 0.
    start_s : float, optional
        Time the sweep begins, s.
    """

    amplitude: float
    start_hz: float
    end_hz: float
    duration_s: float
    start_s: float = 0.0

    def __post_init__(self) -> None:
        _check("amplitude", self.amplitude, exclusive=False)
        _check("start_hz", self.start_hz)
        _check("end_hz", self.end_hz)
        _check("duration_s", self.duration_s)
        _check("start_s", self.start_s, exclusive=False)

    @property
    def max_frequency_hz(self) -> float:
        """Highest instantaneous frequency, Hz."""
        return float(max(self.start_hz, self.end_hz))

    def phase_rad(self, t_s: np.ndarray) -> np.ndarray:
        """Unwrapped phase φ(t), rad."""
        tau = np.asarray(t_s, dtype=np.float64) - self.start_s
        inside = np.clip(tau, 0.0, self.duration_s)
        rate = (self.end_hz - self.start_hz) / self.duration_s
        phase = self.start_hz * inside + 0.5 * rate * inside * inside
        phase += self.start_hz * np.minimum(tau, 0.0) + self.end_hz * np.maximum(tau - self.duration_s, 0.0)
        return 2.0 * np.pi * phase

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return self.amplitude * np.sin(self.phase_rad(t_s))

    def to_metadata(self) -> dict:
        return {
            "kind": "chirp",
            "frequency_hz": float(0.5 * (self.start_hz + self.end_hz)),
            "amplitude": float(self.amplitude),
            "start_hz": float(self.start_hz),
            "end_hz": float(self.end_hz),
            "sweep_start_s": float(self.start_s),
            "sweep_duration_s": float(self.duration_s),
        }


@dataclass(frozen=True)
class SteppedSine:
    """Sines at a list of frequencies, each held for ``dwell_s``, continuous phase.

    Segment k covers [start_s + k·dwell_s, start_s + (k+1)·dwell_s) at
    ``frequencies_hz[k]``; the first frequency runs before ``start_s`` and
    the last one after the final segment.

    Parameters
    ----------
    amplitude : float
        Amplitude (dither units), > 0.
    frequencies_hz : tuple of float
        Segment frequencies, Hz, > 0.
    dwell_s : float
        Duration of each segment, s, > 0.
    start_s : float, optional
        Start of the first segment, s.
    """

    amplitude: float
    frequencies_hz: tuple[float, ...]
    dwell_s: float
    start_s: float = 0.0

    def __post_init__(self) -> None:
        _check("amplitude", self.amplitude, exclusive=False)
        _check("dwell_s", self.dwell_s)
        _check("start_s", self.start_s, exclusive=False)
        if len(self.frequencies_hz) < 1:
            raise ConfigError("frequencies_hz needs at least one frequency")
        for k, freq in enumerate(self.frequencies_hz):
            _check(f"frequencies_hz[{k}]", freq)

    @property
    def max_frequency_hz(self) -> float:
        """Highest segment frequency, Hz."""
        return float(max(self.frequencies_hz))

    def segments(self) -> list[dict[str, float]]:
        """The segments as ``[{"start_s", "end_s", "frequency_hz"}, ...]`` (capture metadata)."""
        return [
            {
                "start_s": float(self.start_s + k * self.dwell_s),
                "end_s": float(self.start_s + (k + 1) * self.dwell_s),
                "frequency_hz": float(freq),
            }
            for k, freq in enumerate(self.frequencies_hz)
        ]

    def phase_rad(self, t_s: np.ndarray) -> np.ndarray:
        """Unwrapped phase, rad, accumulated segment by segment."""
        tau = np.asarray(t_s, dtype=np.float64) - self.start_s
        freqs = np.asarray(self.frequencies_hz, dtype=np.float64)
        index = np.clip(np.floor(tau / self.dwell_s).astype(np.int64), 0, len(freqs) - 1)
        # cycles completed at the start of each segment
        start_cycles = np.concatenate(([0.0], np.cumsum(freqs[:-1] * self.dwell_s)))
        cycles = start_cycles[index] + freqs[index] * (tau - index * self.dwell_s)
        return 2.0 * np.pi * cycles

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return self.amplitude * np.sin(self.phase_rad(t_s))

    def to_metadata(self) -> dict:
        return {
            "kind": "stepped",
            "frequency_hz": float(self.frequencies_hz[len(self.frequencies_hz) // 2]),
            "amplitude": float(self.amplitude),
        }


def build_dither(
    kind: str,
    *,
    amplitude: float,
    center_hz: float,
    sideband_offset_hz: float,
    sideband_scale: float,
    sweep_span_hz: float,
    sweep_steps: int,
    duration_s: float,
    start_s: float = 0.0,
) -> MultiSine | LinearChirp | SteppedSine:
    """Build one of the :data:`DRIVE_KINDS` from the scenario parameters.

    Parameters
    ----------
    kind : {"sine", "three-sine", "chirp", "stepped"}
        Dither type.
    amplitude : float
        Amplitude of the main line / of the sweep (dither units).
    center_hz : float
        Main-line frequency, or the centre of the sweep, Hz.
    sideband_offset_hz, sideband_scale : float
        Δf (Hz) and B/A of the three-sine dither.
    sweep_span_hz : float
        Full span of the chirp / stepped sweep, Hz, centred on ``center_hz``.
    sweep_steps : int
        Number of stepped-sine segments (≥ 1), spread evenly over the span.
    duration_s : float
        Length of the sweep, s (the stepped segments share it equally).
    start_s : float, optional
        When the sweep starts, s.

    Returns
    -------
    MultiSine, LinearChirp or SteppedSine
    """
    if kind == "sine":
        return sine(amplitude, center_hz)
    if kind == "three-sine":
        return three_sine(amplitude, center_hz, sideband_offset_hz, sideband_scale)
    low, high = center_hz - sweep_span_hz / 2, center_hz + sweep_span_hz / 2
    if kind in ("chirp", "stepped") and not low > 0:
        raise ConfigError(f"sweep_span_hz={sweep_span_hz!r} reaches below 0 Hz around {center_hz:g} Hz")
    if kind == "chirp":
        return LinearChirp(amplitude, low, high, duration_s, start_s)
    if kind == "stepped":
        if not (isinstance(sweep_steps, int) and sweep_steps >= 1):
            raise ConfigError(f"sweep_steps={sweep_steps!r} must be an integer >= 1")
        freqs = (center_hz,) if sweep_steps == 1 else tuple(np.linspace(low, high, sweep_steps).tolist())
        return SteppedSine(amplitude, freqs, duration_s / sweep_steps, start_s)
    raise ConfigError(f"drive={kind!r} must be one of {', '.join(DRIVE_KINDS)}")


def drive_metadata(params, center_hz: float, amplitude_v: float) -> dict:
    """The capture metadata ``drive`` of a simulated dither (ltv, tapping).

    ``params`` carries ``drive`` (the kind), ``amplitude_nm`` (free amplitude,
    nm), ``dither_gain_nm_per_v``, ``drive_hold`` and, for a three-sine
    drive, ``sideband_offset_hz`` and ``sideband_scale``; ``center_hz`` (Hz)
    and ``amplitude_v`` (V) are the excitation's.  A single sine says
    ``sideband_offset_hz`` 0, which the free-air route reads as one tone.
    """
    drive = {
        "kind": params.drive,
        "frequency_hz": float(center_hz),
        "amplitude_v": float(amplitude_v),
        "free_amplitude_nm": float(params.amplitude_nm),
        "dither_gain_nm_per_v": float(params.dither_gain_nm_per_v),
        "hold": params.drive_hold,
    }
    if params.drive == "three-sine":
        drive["sideband_offset_hz"] = float(params.sideband_offset_hz)
        drive["sideband_scale"] = float(params.sideband_scale)
    elif params.drive == "sine":
        drive["sideband_offset_hz"] = 0.0
    return drive


# --------------------------------------------------------------------------- a designed drive, played


def load_designed_drive(path: str) -> MultiSine:
    """The dither ``afmtool design excitation`` wrote, as the lines a simulator plays.

    ``lines.json`` (or its folder) gives the lines as designed: u(t) = Σ A_k sin(2πf_k t + φ_k).
    ``excitation.wav`` is the sampled loop an arbitrary waveform generator plays; a
    generator (or a DAC behind its reconstruction filter) plays its band-limited
    reconstruction, and because the loop holds a whole number of cycles of every
    line, that reconstruction is exactly the sum of the sines in the loop's DFT bins:
    the lines are read from the bins that carry them (above 1e-6 of the largest).  Its
    volts per full scale come from the ``lines.json`` beside it (``wav_full_scale_v``).

    Raises
    ------
    ConfigError
        The file is neither, or cannot be read as one.
    """
    import json
    from pathlib import Path

    source = Path(path)
    if source.is_dir():
        source = source / "lines.json"
    if source.suffix.lower() == ".wav":
        return _drive_from_wav(source)
    try:
        design = json.loads(source.read_text(encoding="utf-8"))
        lines = design["lines"]
        return MultiSine(
            tuple(float(line["amplitude_v"]) for line in lines),
            tuple(float(line["frequency_hz"]) for line in lines),
            tuple(math.radians(float(line.get("phase_deg", 0.0))) for line in lines),
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"drive_file {path}: not a lines.json of 'afmtool design excitation' ({exc})") from None


def _drive_from_wav(source) -> MultiSine:
    import json

    beside = source.with_name("lines.json")
    try:
        full_scale_v = float(json.loads(beside.read_text(encoding="utf-8"))["wav_full_scale_v"])
    except (OSError, ValueError, KeyError, TypeError):
        raise ConfigError(f"drive_file {source}: its volts per full scale are in the lines.json beside it "
                          f"({beside}), which cannot be read; keep the folder 'design excitation' wrote") from None
    from scipy.io import wavfile

    try:
        rate, loop = wavfile.read(str(source))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"drive_file {source}: cannot be read as a WAV loop ({exc})") from None
    if loop.ndim != 1 or loop.dtype.kind != "f":
        raise ConfigError(f"drive_file {source}: not the mono float WAV 'design excitation' writes")
    spectrum = np.fft.rfft(loop.astype(np.float64) * full_scale_v) * (2.0 / loop.size)
    bins = np.flatnonzero(np.abs(spectrum) > 1e-6 * np.abs(spectrum).max())
    bins = bins[bins > 0]
    frequencies = bins * rate / loop.size
    # X_k = A·e^{i(φ − π/2)} for A·sin(2πft + φ): the sine phase is arg X_k + π/2
    return MultiSine(tuple(np.abs(spectrum[bins]).tolist()), tuple(frequencies.tolist()),
                     tuple((np.angle(spectrum[bins]) + math.pi / 2).tolist()))
