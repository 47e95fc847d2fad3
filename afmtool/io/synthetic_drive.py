"""``--drive F1:A1,F2:A2,...``: a dither channel synthesised for captures that did not record it.

:class:`SyntheticDriveReader` wraps a reader and adds a ``dither`` channel
(V).  The first time ``dither`` is asked for, it reads the free-air segment
ahead from the same single pass (so stdin works), fits each line's phase
there (:func:`afmtool.estimators.drive_lines.fit_drive_phases`), then yields
every chunk with the dither synthesised sample by sample:

    g[n] = Σ_i A_i·cos(2π F_i n/fs + φ_i).

REEP, probeloss and kalman-bank then run unchanged.  The lines come from
``--drive`` or from metadata ``drive.lines`` (a list of
``{"frequency_hz": F, "amplitude_v": A}``).  The drive is taken to be a
continuous signal (a real instrument's); metadata ``drive.hold`` starting
with ``"zero-order"`` (or ``"zoh"``) says a DAC held it between samples (afmtool's
discrete-time simulators), which changes the response the phases are
fitted with.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace

import numpy as np

from afmtool.config.samples import interval_samples
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.drive_lines import (
    DriveLine,
    DrivePhaseFit,
    DriveResponse,
    fit_drive_phases,
    parse_drive_lines,
    synthesize_drive,
)
from afmtool.io.capture import CaptureReader, ChannelSpec, Chunk, ReaderBase
from afmtool.io.metadata import DriveMetadata

__all__ = ["DEFAULT_FIT_SAMPLES", "SyntheticDriveReader", "drive_hold", "drive_lines_from_metadata", "drive_lines_of"]

#: Without a free-air segment, the phases are fitted on the capture's first samples.
DEFAULT_FIT_SAMPLES = 1 << 16


def drive_hold(drive: DriveMetadata) -> str:
    """``"zero-order"`` when metadata ``drive.hold`` says a DAC held the drive between samples, else ``"none"``.

    ``"zero-order..."`` (afmtool's simulators) and ``"zoh"`` (tests/reference_sim.py) mean held
    (:attr:`afmtool.io.metadata.DriveMetadata.held`).
    """
    return "zero-order" if drive.held else "none"


def drive_lines_of(text: str) -> tuple[DriveLine, ...]:
    """``--drive``'s lines: ``"F1:A1,F2:A2,..."`` (:func:`~afmtool.estimators.drive_lines.parse_drive_lines`), or
    the ``lines.json`` (or its folder) that ``afmtool design excitation`` wrote.

    A designed loop's phases hold at the loop's start, not at the capture's first sample: they
    become the lines' ``design_phase_rad`` (their offsets at one origin, eq. D.4), and the origin
    is fitted on the free-air segment.
    """
    from pathlib import Path

    path = Path(text)
    if not (path.suffix.lower() == ".json" or path.is_dir()):
        return parse_drive_lines(text)
    source = path / "lines.json" if path.is_dir() else path
    try:
        lines = json.loads(source.read_text(encoding="utf-8"))["lines"]
        # lines.json's phases are sine phases (u = Σ A sin(2πft + φ)); a cosine's is φ − π/2
        parsed = tuple(DriveLine(float(x["frequency_hz"]), float(x["amplitude_v"]), math.nan,
                                 math.radians(float(x.get("phase_deg", 0.0))) - math.pi / 2) for x in lines)
    except OSError as exc:
        raise ConfigError(f"--drive {text}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, KeyError, TypeError, AttributeError):
        raise ConfigError(f"--drive {text}: not a lines.json of 'afmtool design excitation'") from None
    if not parsed or any(not (line.frequency_hz > 0 and line.amplitude_v > 0) for line in parsed):
        raise ConfigError(f"--drive {text}: its lines need frequency_hz and amplitude_v > 0")
    return parsed


def drive_lines_from_metadata(metadata: Mapping) -> tuple[DriveLine, ...]:
    """Lines from metadata ``drive.lines``; empty when there are none."""
    lines = metadata.get("drive", {}).get("lines") if isinstance(metadata.get("drive"), Mapping) else None
    if not lines:
        return ()
    try:
        parsed = tuple(
            DriveLine(float(x["frequency_hz"]), float(x["amplitude_v"]), math.radians(float(x.get("phase_deg", math.nan))))
            for x in lines
        )
    except (TypeError, KeyError, ValueError, AttributeError):
        raise InputError("metadata drive.lines must be a list of {frequency_hz, amplitude_v[, phase_deg]}") from None
    given = [math.isfinite(line.phase_rad) for line in parsed]
    if any(given) and not all(given):
        raise InputError("metadata drive.lines: give phase_deg for every line or for none")
    if any(not (line.frequency_hz > 0 and line.amplitude_v > 0) for line in parsed):
        raise InputError("metadata drive.lines: frequency_hz and amplitude_v must be > 0")
    return parsed


class SyntheticDriveReader(ReaderBase):
    """A reader with a ``dither`` channel synthesised from the drive's lines.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection``; a recorded ``dither`` is replaced.
    lines : tuple of DriveLine
        Frequencies (Hz) and amplitudes (V).
    free_air_s : (float, float) or None
        Segment where the phases are fitted; default metadata ``free_air``,
        else the first :data:`DEFAULT_FIT_SAMPLES` samples.
    response : DriveResponse or None
        The free-air f0 and Q (``--model``, ``--f0/--q``) the phases are fitted
        against; None: metadata ``cantilever``, else the lines themselves.
    phases : {"common", "independent"}
        ``--drive-phases``: the lines started together (their closure phase
        then helps pin f0 and Q, eq. D.4) or were phased apart.
    """

    def __init__(self, reader: CaptureReader, lines: tuple[DriveLine, ...], free_air_s=None,
                 response: DriveResponse | None = None, phases: str = "common") -> None:
        if phases not in ("common", "independent"):
            raise ConfigError(f"--drive-phases {phases!r} must be 'common' or 'independent'")
        self._reader = reader
        self._lines = lines
        self._response = response
        self._phases = phases
        info = reader.info
        if "deflection" not in info.channel_names:
            raise InputError(f"{info.source}: --drive needs a deflection channel to fit the drive phases against")
        if free_air_s is None and info.capture_metadata.free_air is not None:
            free_air_s = (info.capture_metadata.free_air.start_s, info.capture_metadata.free_air.end_s)
        self._interval = free_air_s
        self.replaced_recorded = "dither" in info.channel_names
        channels = tuple(c for c in info.channels if c.name != "dither") + (ChannelSpec("dither", "V"),)
        self.info = replace(info, channels=channels)
        self.fit: DrivePhaseFit | None = None
        self.conversions = getattr(reader, "conversions", {})
        self.calibration = getattr(reader, "calibration", None)

    @property
    def drive_record(self) -> dict:
        """What the report records: the lines with their fitted phases and where they were fitted."""
        record = {
            "lines": [
                {"frequency_hz": line.frequency_hz, "amplitude_v": line.amplitude_v,
                 "phase_deg": float(np.degrees(line.phase_rad)) if math.isfinite(line.phase_rad) else None}
                for line in self._lines
            ],
            "phases": "given" if all(math.isfinite(line.phase_rad) for line in self._lines) else "fitted",
        }
        if self.fit is not None:
            record["lines"] = [
                {"frequency_hz": line.frequency_hz, "amplitude_v": line.amplitude_v, "phase_deg": float(np.degrees(line.phase_rad))}
                for line in self.fit.lines
            ]
            record["fitted_on_s"] = list(self._fitted_on)
            record["response"] = {
                "f0_hz": self.fit.f0_hz, "f0_std_hz": self.fit.f0_std_hz, "q": self.fit.q, "q_std": self.fit.q_std,
                "from": self.fit.response_source, "hold": drive_hold(self.info.capture_metadata.drive),
                "line_phases": self._phases,
            }
            if math.isfinite(self.fit.closure_chi2):
                record["response"]["closure_chi2"] = self.fit.closure_chi2
            record["lines_phase_std_deg"] = [float(np.degrees(v)) for v in self.fit.phase_std_rad]
        record["replaced_recorded_dither"] = self.replaced_recorded
        return record

    def _given_response(self) -> dict:
        """f0, Q (and their std) to fit the phases against: ``--model`` or ``--f0/--q``, else the metadata's."""
        given = self._response
        if given is not None:
            return {"f0_hz": given.f0_hz, "q": given.q, "f0_std_hz": given.f0_std_hz, "q_std": given.q_std,
                    "given_from": given.source}
        cantilever = self.info.capture_metadata.cantilever
        return {"f0_hz": cantilever.f0_hz, "q": cantilever.q, "given_from": "metadata cantilever f0_hz, q"}

    @property
    def drive_fit(self) -> DrivePhaseFit | None:
        """The phase fit, once the dither has been asked for."""
        return self.fit

    def _fit_range(self) -> tuple[int, int]:
        fs = self.info.sample_rate_hz
        if self._interval is None:
            end = DEFAULT_FIT_SAMPLES if self.info.n_samples is None else min(DEFAULT_FIT_SAMPLES, self.info.n_samples)
            return 0, end
        return interval_samples(self._interval, fs, "free-air segment", self.info.n_samples)

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        if "dither" not in channels:
            yield from self._reader.blocks(channels, block_samples)
            return
        wanted = [c for c in channels if c != "dither"]
        if all(math.isfinite(line.phase_rad) for line in self._lines):
            # the phases were given: nothing to fit, nothing to read ahead
            for chunk in self._reader.blocks(list(dict.fromkeys([*wanted, "deflection"])), block_samples):
                data = {name: chunk.data[name] for name in wanted}
                data["dither"] = synthesize_drive(self._lines, self.info.sample_rate_hz, chunk.start, len(chunk))
                yield Chunk(chunk.start, {name: data[name] for name in channels})
            return
        read = list(dict.fromkeys([*wanted, "deflection"]))
        source = self._reader.blocks(read, block_samples)
        start, end = self._fit_range()
        held: list[Chunk] = []
        pieces = []
        for chunk in source:
            held.append(chunk)
            lo, hi = max(start - chunk.start, 0), min(end - chunk.start, len(chunk))
            if hi > lo:
                pieces.append(chunk.data["deflection"][lo:hi])
            if chunk.start + len(chunk) >= end:
                break
        segment = np.concatenate(pieces) if pieces else np.empty(0)
        if self._interval is None:
            end = start + segment.size
        elif segment.size < end - start:
            raise InputError(
                f"{self.info.source}: the free-air segment {self._interval[0]:g}:{self._interval[1]:g} s "
                "for the drive phases runs past the end of the capture"
            )
        self.fit = fit_drive_phases(segment, self.info.sample_rate_hz, start, self._lines,
                                    hold=drive_hold(self.info.capture_metadata.drive),
                                    common_origin=self._phases == "common", **self._given_response())
        self._fitted_on = (start / self.info.sample_rate_hz, end / self.info.sample_rate_hz)

        def with_dither(chunk: Chunk) -> Chunk:
            data = {name: chunk.data[name] for name in wanted}
            data["dither"] = synthesize_drive(self.fit.lines, self.info.sample_rate_hz, chunk.start, len(chunk))
            return Chunk(chunk.start, {name: data[name] for name in channels})

        for chunk in held:
            yield with_dither(chunk)
        held.clear()
        for chunk in source:
            yield with_dither(chunk)

    def truth(self):
        return self._reader.truth()

    def close(self) -> None:
        self._reader.close()

