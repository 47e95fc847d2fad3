"""The whole-record commands stream: their peak memory does not grow with the capture's length.

A synthetic reader generates its samples block by block (a drive, and the
response of a discrete resonator to it, filter state carried across blocks),
so no capture is held in memory; tracemalloc's peak then measures what the
analysis keeps.  Each analysis runs on 2e5 and 2e6 samples with the same
chunk and segment sizes (the short record's steps are longer than a chunk,
so its per-chunk work is as large as the long one's); a peak that grew with the record (concatenating
chunks) would be about 10 times larger for the longer one.

``identify freeair --sweep --sweep-method h1`` is not among them on
purpose: its Welch segment is n/16 samples (about 31 averages whatever the
length), so its memory, O(segment), grows with the record by design; the
H1 accumulation itself is flat (the gamma H1 case, at a fixed segment).
"""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
import scipy.signal

from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase

FS = 1e6
F0, Q = 50e3, 50.0
CHUNK = 1 << 12
NPERSEG = 4096
N_STEPS = 20
SHORT, LONG = 200_000, 2_000_000
WARM_UP = 50_000


def _resonator():
    """A discrete second-order resonance at F0 with quality factor about Q (bilinear transform)."""
    w0 = 2 * FS * np.tan(np.pi * F0 / FS)  # prewarped, so the digital resonance is at F0
    return scipy.signal.bilinear([w0 * w0], [1.0, w0 / Q, w0 * w0], FS)


def _steps(n: int) -> list[dict]:
    """N_STEPS equal steps from 20 to 80 kHz over n samples (longer steps for a longer record)."""
    edges = np.linspace(0.0, n / FS, N_STEPS + 1)
    freqs = np.geomspace(20e3, 80e3, N_STEPS)
    return [{"start_s": float(a), "end_s": float(b), "frequency_hz": float(f)}
            for a, b, f in zip(edges[:-1], edges[1:], freqs)]


class _GeneratedReader(ReaderBase):
    """Channel ``names[0]`` is the drive; every other channel is the resonator's response plus noise.

    ``drive="noise"``: white noise through the resonator (for H1);
    ``drive="stepped"``: the sine steps of :func:`_steps`, written into the
    metadata as ``segments``, and their steady-state responses.
    The blocks are written into a ring of buffers allocated here, before any
    measurement, so the chunks that the read-ahead holds cost the same
    however the threads are scheduled (the ring is longer than the most
    chunks in flight, and no stage measured keeps a chunk).
    """

    RING = 8

    def __init__(self, n: int, names: tuple[str, ...], drive: str) -> None:
        self._names, self._drive = names, drive
        metadata = {"segments": _steps(n)} if drive == "stepped" else {}
        specs = tuple(ChannelSpec(name) for name in names)
        self.info = CaptureInfo("<generated>", "memory", FS, specs, n, metadata, ())
        self._ring = np.zeros((self.RING, len(names), CHUNK))
        self._noise, self._phase = np.empty(CHUNK), np.empty(CHUNK)
        self._index = np.arange(CHUNK, dtype=np.float64)
        steps = metadata.get("segments", ())
        self._step_hz = np.array([s["frequency_hz"] for s in steps])

    def _step_block(self, rows: np.ndarray, start: int) -> None:
        """Each step's sine and its steady-state response |G| sin(ωn + ∠G), written in place (nothing allocated)."""
        b, a = _resonator()
        step_samples = self.info.n_samples / self._step_hz.size
        last_step = self._step_hz.size - 1
        first, last = (min(int(i / step_samples), last_step) for i in (start, start + rows.shape[1] - 1))
        for k in range(first, last + 1):  # at most two steps in a block
            lo = max(start, math.ceil(k * step_samples)) - start
            stop = start + rows.shape[1]
            hi = (stop if k == last_step else min(stop, math.ceil((k + 1) * step_samples))) - start
            w = 2 * np.pi * self._step_hz[k] / FS
            g = complex(np.polyval(b, np.exp(1j * w)) / np.polyval(a, np.exp(1j * w)))
            phase = self._phase[: hi - lo]
            np.add(self._index[: hi - lo], start + lo, out=phase)
            phase *= w
            np.sin(phase, out=rows[0, lo:hi])
            phase += np.angle(g)
            for row in rows[1:]:
                np.sin(phase, out=row[lo:hi])
                row[lo:hi] *= abs(g)

    def blocks(self, channels, block_samples):
        assert block_samples == CHUNK
        b, a = _resonator()
        state = np.zeros(max(len(a), len(b)) - 1)
        rng = np.random.default_rng(7)
        for i, start in enumerate(range(0, self.info.n_samples, block_samples)):
            n = min(block_samples, self.info.n_samples - start)
            rows = self._ring[i % self.RING, :, :n]
            if self._drive == "noise":
                rng.standard_normal(out=rows[0])
                y, state = scipy.signal.lfilter(b, a, rows[0], zi=state)
                rows[1:] = y
                del y
            else:
                self._step_block(rows, start)
            noise = self._noise[:n]
            for row in rows[1:]:
                rng.standard_normal(out=noise)
                noise *= 1e-3
                row += noise
            data = dict(zip(self._names, rows))
            yield Chunk(start, {name: data[name] for name in channels})

    def truth(self):
        return {}

    def close(self) -> None:
        pass


def _gamma(reader):
    from afmtool.analyses.gamma_outputs import _estimate
    from afmtool.config.params import GammaParams

    n, drive = reader.info.n_samples, reader._drive
    params = GammaParams(chunk_samples=CHUNK)
    method = "h1" if drive == "noise" else "stepped"
    responses, means = _estimate(reader, ("thermal_current", "deflection"), params, method, NPERSEG, None)
    assert means.count == n
    return responses["thermal_current"]


def _freeair(reader, monkeypatch):
    from afmtool.analyses import freeair_outputs
    from afmtool.config.params import FreeAirParams

    n, drive = reader.info.n_samples, reader._drive
    monkeypatch.setattr(freeair_outputs, "_CHUNK_SAMPLES", CHUNK)
    params = FreeAirParams(route="sweep", sweep_method="h1" if drive == "noise" else "stepped")
    found, samples = freeair_outputs._identify_sweep(reader, params, None)
    assert samples == n
    return found


def _info(reader):
    from afmtool.analyses.info import summarize

    return summarize(reader, chunk_samples=CHUNK)


def _peak_bytes(run) -> int:
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


GAMMA = ("v_sub", "thermal_current", "deflection")
FREEAIR = ("dither", "deflection")
#: case: (channels, drive, run(reader, monkeypatch))
CASES = {
    "gamma h1": (GAMMA, "noise", lambda reader, mp: _gamma(reader)),
    "freeair --sweep stepped": (FREEAIR, "stepped", _freeair),
    "info": (FREEAIR, "stepped", lambda reader, mp: _info(reader)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_peak_memory_does_not_grow_with_the_capture(case, monkeypatch):
    names, drive, run = CASES[case]
    run(_GeneratedReader(WARM_UP, names, drive), monkeypatch)  # imports, caches and first-call allocations
    peaks = {}
    for n in (SHORT, LONG):
        reader = _GeneratedReader(n, names, drive)  # its buffers are not the analysis's
        peaks[n] = _peak_bytes(lambda reader=reader: run(reader, monkeypatch))
    ratio = peaks[LONG] / peaks[SHORT]
    print(f"{case}: peak {peaks[SHORT] / 1e6:.2f} MB at {SHORT:,} samples, {peaks[LONG] / 1e6:.2f} MB at {LONG:,}: "
          f"ratio {ratio:.3f}")
    # a kept record would be 16 MB per channel at 2e6 samples.  Where the peak is a few tens of kB
    # (info), tracemalloc also counts what other threads allocate meanwhile (pytest-xdist's channel
    # to its controller: +30 kB once in CI), so a growth under 1 MB passes whatever its ratio
    assert ratio < 1.5 or peaks[LONG] - peaks[SHORT] < 1e6
    assert peaks[LONG] < 8e6


def test_the_generated_sweeps_give_the_resonator(monkeypatch):
    """The streamed measurements are of the generated resonance (so the memory test measures real work)."""
    for drive in ("noise", "stepped"):
        found = _freeair(_GeneratedReader(SHORT, FREEAIR, drive), monkeypatch)
        assert found.model.f0_hz == pytest.approx(F0, rel=2e-3)
        assert found.model.q == pytest.approx(Q, rel=0.05)
        assert found.response is not None and found.response.method == ("h1" if drive == "noise" else "stepped")
