"""Streaming lock-in demodulation: amplitude and phase at one frequency.

The baseline imaging signals of tapping-mode AFM.  The signal is mixed with
``exp(-j·2πf·t)`` and the product low-passed by a Butterworth filter (second-
order sections).  Both steps are one numba kernel with carried state: the
filter's section states, and the sample count that fixes the reference phase.
Chunked and single-call results are bit-for-bit identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from afmtool.config.samples import MAX_SAMPLES
from afmtool.errors import ConfigError
from afmtool.estimators.decimation import Decimation
from afmtool.estimators.filters import butterworth_lowpass_sos
from afmtool.jit import JIT_OPTIONS

__all__ = ["LockIn", "LockInState", "LockInBlock", "default_lowpass_hz"]

#: The oscillator is recomputed exactly every this many samples of the capture
#: (aligned to the capture, not to chunks) and rotated recursively in between.
_RESYNC_SAMPLES = 4096


def default_lowpass_hz(frequency_hz: float, sideband_offset_hz: float | None = None) -> float:
    """The documented default low-pass corner, Hz.

    One tenth of the demodulation frequency, and at most half of the
    REEP side-line offset Δf so that the f0 ± Δf lines of the three-sine
    excitation (§3.3.2) do not leak into the amplitude.
    """
    corner = frequency_hz / 10.0
    if sideband_offset_hz:
        corner = min(corner, sideband_offset_hz / 2.0)
    return corner


@dataclass(frozen=True)
class LockInBlock:
    """Demodulated output at the kept samples: amplitude (input units) and phase (rad)."""

    amplitude: np.ndarray
    phase_rad: np.ndarray


@dataclass(frozen=True)
class LockInState:
    """Section states (n_sections × 2, complex) and samples processed so far."""

    zi: np.ndarray
    samples_seen: int


@njit(**JIT_OPTIONS)
def _lockin_kernel(signals, start, cycles_per_sample, sos, zi, keep_every, out):
    """Mix each row of ``signals`` with e^{-j2πfn/fs}, filter by the SOS cascade, keep 1 in N.

    Every row shares one reference oscillator.  For each section, in direct
    form II transposed: y = b0·v + s1;  s1 = b1·v − a1·y + s2;  s2 = b2·v − a2·y.
    """
    n_signals = signals.shape[0]
    n_sections = sos.shape[0]
    two_pi = 2.0 * math.pi
    step = complex(math.cos(two_pi * cycles_per_sample), -math.sin(two_pi * cycles_per_sample))
    # Rebuild the rotor exactly as an unchunked run would hold it at `start`:
    # from the last resynchronisation point, rotated forward sample by sample.
    synced = start - start % _RESYNC_SAMPLES
    frac = (synced * cycles_per_sample) % 1.0
    rotor = complex(math.cos(two_pi * frac), -math.sin(two_pi * frac))
    for _ in range(start - synced):
        rotor *= step
    k = 0
    # countdown to the next kept sample, n + 1 ≡ 0 (mod keep_every); no division per sample
    until_keep = (keep_every - (start + 1) % keep_every) % keep_every
    for i in range(signals.shape[1]):
        n = start + i
        if n % _RESYNC_SAMPLES == 0:
            frac = (n * cycles_per_sample) % 1.0
            rotor = complex(math.cos(two_pi * frac), -math.sin(two_pi * frac))
        keep = until_keep == 0
        until_keep = keep_every - 1 if keep else until_keep - 1
        for c in range(n_signals):
            v = signals[c, i] * rotor
            for s in range(n_sections):
                y = sos[s, 0] * v + zi[c, s, 0]
                zi[c, s, 0] = sos[s, 1] * v - sos[s, 4] * y + zi[c, s, 1]
                zi[c, s, 1] = sos[s, 2] * v - sos[s, 5] * y
                v = y
            if keep:
                out[c, k] = v
        if keep:
            k += 1
        rotor *= step
    return k


@njit(**JIT_OPTIONS)
def _two_sections(v, s1, s2, t1, t2, c):
    """One real lane through a 4th-order cascade (direct form II transposed); c = the 2×6 SOS flattened."""
    y = c[0] * v + s1
    s1 = c[1] * v - c[4] * y + s2
    s2 = c[2] * v - c[5] * y
    z = c[6] * y + t1
    t1 = c[7] * y - c[10] * z + t2
    t2 = c[8] * y - c[11] * z
    return z, s1, s2, t1, t2


@njit(**JIT_OPTIONS)
def _lockin_order4_kernel(signal, start, cycles_per_sample, sos, zi, keep_every, out):
    """:func:`_lockin_kernel` for one signal and two sections, with every state a scalar.

    The same operations in the same order (bit-for-bit equal results), but
    the real and imaginary lanes are separate scalar chains the compiler
    keeps in registers.  Two signals run as two calls: their eight lanes
    and the coefficients in one loop spill out of the registers, and one
    loop ran at half the rate of two (39 against 74 MS/s for REEP's pair).
    ``zi`` and ``out`` are those of this signal: shapes (1, 2, 2) and (1, K).
    """
    two_pi = 2.0 * math.pi
    step_re = math.cos(two_pi * cycles_per_sample)
    step_im = -math.sin(two_pi * cycles_per_sample)
    synced = start - start % _RESYNC_SAMPLES
    frac = (synced * cycles_per_sample) % 1.0
    rot_re = math.cos(two_pi * frac)
    rot_im = -math.sin(two_pi * frac)
    for _ in range(start - synced):
        rot_re, rot_im = rot_re * step_re - rot_im * step_im, rot_re * step_im + rot_im * step_re
    c = sos.ravel()
    # lanes: real (a) and imaginary (b)
    a1, a2, a3, a4 = zi[0, 0, 0].real, zi[0, 0, 1].real, zi[0, 1, 0].real, zi[0, 1, 1].real
    b1, b2, b3, b4 = zi[0, 0, 0].imag, zi[0, 0, 1].imag, zi[0, 1, 0].imag, zi[0, 1, 1].imag
    k = 0
    until_keep = (keep_every - (start + 1) % keep_every) % keep_every
    for i in range(signal.shape[0]):
        if (start + i) % _RESYNC_SAMPLES == 0:
            frac = ((start + i) * cycles_per_sample) % 1.0
            rot_re = math.cos(two_pi * frac)
            rot_im = -math.sin(two_pi * frac)
        x = signal[i]
        ya, a1, a2, a3, a4 = _two_sections(x * rot_re, a1, a2, a3, a4, c)
        yb, b1, b2, b3, b4 = _two_sections(x * rot_im, b1, b2, b3, b4, c)
        if until_keep == 0:
            out[0, k] = complex(ya, yb)
            k += 1
            until_keep = keep_every - 1
        else:
            until_keep -= 1
        rot_re, rot_im = rot_re * step_re - rot_im * step_im, rot_re * step_im + rot_im * step_re
    zi[0, 0, 0], zi[0, 0, 1], zi[0, 1, 0], zi[0, 1, 1] = complex(a1, b1), complex(a2, b2), complex(a3, b3), complex(a4, b4)
    return k


class LockIn:
    """Complex demodulator at ``frequency_hz`` with an order-``order`` Butterworth low-pass.

    Notes
    -----
    For ``x(t) = A cos(2πft + φ)`` the low-passed product
    ``X(t) = LP[x(t)·e^{-j2πft}] → (A/2)e^{jφ}``, so the amplitude is
    ``2|X|`` and the phase ``arg X`` (rad), relative to a cosine reference
    whose phase is zero at the capture's first sample.
    """

    def __init__(self, frequency_hz: float, sample_rate_hz: float, lowpass_hz: float, order: int = 4) -> None:
        if not 0 < frequency_hz < sample_rate_hz / 2:
            raise ValueError(f"{frequency_hz=} must be in (0, sample_rate_hz/2)")
        if not 0 < lowpass_hz < sample_rate_hz / 2:
            raise ValueError(f"{lowpass_hz=} must be in (0, sample_rate_hz/2)")
        if not sample_rate_hz / lowpass_hz <= MAX_SAMPLES:  # a corner of 1e-320 Hz: no filter, and an IndexError
            raise ConfigError(
                f"lockin_lowpass_hz={lowpass_hz!r}: its time constant of {sample_rate_hz / lowpass_hz:.3g} samples "
                f"is longer than any capture ({MAX_SAMPLES:.0e} samples)"
            )
        self.frequency_hz = float(frequency_hz)
        self.sample_rate_hz = float(sample_rate_hz)
        self.lowpass_hz = float(lowpass_hz)
        self.order = int(order)
        self._sos = np.ascontiguousarray(butterworth_lowpass_sos(order, lowpass_hz, sample_rate_hz))
        self._dispatch()

    def _run(self, rows: list[np.ndarray], start: int, zi: np.ndarray, keep_every: int, out: np.ndarray) -> None:
        """The order-4 scalar kernel signal by signal, else the generic one on the stacked rows."""
        cycles = self.frequency_hz / self.sample_rate_hz
        if self._sos.shape[0] == 2:
            for r, row in enumerate(rows):
                _lockin_order4_kernel(row, start, cycles, self._sos, zi[r:r + 1], keep_every, out[r:r + 1])
        else:
            _lockin_kernel(np.vstack(rows), start, cycles, self._sos, zi, keep_every, out)

    def _dispatch(self) -> None:
        """Compile or load the kernel now, in the constructing thread.

        The analyses call :meth:`process` from a worker thread.  Were its first
        call to find the kernel not yet loaded, it would wait for numba's
        compiler lock; a Ctrl-C or SIGTERM that lands while the main thread
        holds that lock (between its acquire and its ``with``) can leave it
        held for good, and the interrupted run would then wait for the
        worker forever.
        """
        zi = np.zeros((1, self._sos.shape[0], 2), dtype=np.complex128)
        self._run([np.zeros(1)], 0, zi, 1, np.empty((1, 1), dtype=np.complex128))

    @property
    def sos(self) -> np.ndarray:
        """The low-pass's second-order sections (a copy)."""
        return self._sos.copy()

    def initial_state(self, n_signals: int = 1, samples_seen: int = 0) -> LockInState:
        """Zero filter state for ``n_signals`` signals demodulated together.

        ``samples_seen``: the capture index of the first sample to come, which
        fixes the reference's phase and the kept samples (a chunk's warm-up
        in a split run starts there; 0 for a whole capture).
        """
        return LockInState(np.zeros((n_signals, self._sos.shape[0], 2), dtype=np.complex128), int(samples_seen))

    def process(
        self, signals: np.ndarray | tuple[np.ndarray, ...], state: LockInState, keep_every: int = 1
    ) -> tuple[tuple[LockInBlock, ...], LockInState]:
        """Demodulate one chunk of one or more equal-length signals with one reference.

        Keeps the samples whose capture index n has (n + 1) % keep_every == 0.
        Returns one :class:`LockInBlock` per signal and the state for the next chunk.
        """
        out, state = self._demodulate(signals, state, keep_every)
        return tuple(LockInBlock(2.0 * np.abs(row), np.angle(row)) for row in out), state

    def process_against(
        self, signal: np.ndarray, reference: np.ndarray, state: LockInState, keep_every: int = 1
    ) -> tuple[LockInBlock, LockInState]:
        """Demodulate ``signal`` and report its phase relative to ``reference`` (e.g. the dither).

        ``state`` is that of two signals.  The amplitude is ``signal``'s;
        the phase is arg(X_signal · X̄_reference) in (−π, π], i.e. the phase
        difference already wrapped, independent of the reference's amplitude.
        """
        out, state = self._demodulate((signal, reference), state, keep_every)
        return LockInBlock(2.0 * np.abs(out[0]), np.angle(out[0] * out[1].conj())), state

    def _demodulate(
        self, signals: np.ndarray | tuple[np.ndarray, ...], state: LockInState, keep_every: int
    ) -> tuple[np.ndarray, LockInState]:
        """The kept complex outputs X (one row per signal) and the next state."""
        # one C-contiguous float64 row per signal, without stacking (a copy of the whole chunk)
        if isinstance(signals, np.ndarray) and signals.ndim == 2:
            signals = tuple(signals)
        elif not isinstance(signals, (tuple, list)):
            signals = (signals,)
        rows = [np.ascontiguousarray(row, dtype=np.float64) for row in signals]
        if len(rows) != state.zi.shape[0]:
            raise ValueError(f"state holds {state.zi.shape[0]} signals, got {len(rows)}")
        if any(row.ndim != 1 or row.shape != rows[0].shape for row in rows):
            raise ValueError("the signals must be 1-D and of one length")
        zi = state.zi.copy()
        n = rows[0].shape[0]
        n_kept = Decimation(keep_every).count(state.samples_seen, n)
        out = np.empty((len(rows), n_kept), dtype=np.complex128)
        self._run(rows, state.samples_seen, zi, keep_every, out)
        return out, LockInState(zi, state.samples_seen + n)
