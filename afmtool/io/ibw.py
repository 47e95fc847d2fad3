"""Igor Pro binary waves (``.ibw``): Asylum Research fast captures and force curves.

Read with ``igor2`` (the maintained fork of W. Trevor King's ``igor``).  A
wave of shape (samples, columns) becomes one channel per column, named from
the column's dimension label; Asylum's labels map to afmtool's channel
names (``Defl`` -> ``deflection``, ``ZSnsr`` -> ``z_piezo``), other labels
are kept.  Units are the wave's own data units (``"m"`` for an MFP-3D
force curve), never converted here.  The sample rate is 1 / the x scaling
when the x units are seconds, else the note's ``NumPtsPerSec``.

The wave note (``key: value`` lines, CR-separated) supplies the metadata:

=================  ==============================================
note key           metadata
=================  ==============================================
SpringConstant     cantilever.spring_constant_n_per_m (N/m)
InvOLS             cantilever.deflection_sensitivity_nm_per_v (m/V x 1e9)
ThermalFrequency   cantilever.f0_hz
ThermalQ           cantilever.q
DriveFrequency     drive.frequency_hz
DriveAmplitude     drive.amplitude_v
ScanSize           instrument.scan_size_m
NumPtsPerSec       the sample rate, if the x scaling is not in s
Indexes/Direction  segments (approach, dwell, retract)
=================  ==============================================

``Indexes`` holds the last sample of each segment (``0,1008,2015``: the
approach is samples 0..1008, where ZSnsr peaks, the retract 1009..2015);
``Direction`` gives each segment's sense (1 approach, 0 dwell, -1 retract).

igor2 reads a wave whole, so this reader holds the file in memory: Igor
waves are bounded by Igor's own in-memory model, and the reader refuses
files above :data:`MAX_IBW_BYTES`.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.views import SEGMENTS_KEY, segments_metadata

__all__ = ["IbwReader", "parse_wave_note", "MAX_IBW_BYTES"]

#: Largest .ibw read (the whole wave is held in memory), bytes.
MAX_IBW_BYTES = 2 << 30

#: Asylum Research column labels that have an afmtool channel name.
_ASYLUM_CHANNELS = {"Defl": "deflection", "ZSnsr": "z_piezo", "DeflV": "deflection_v", "Raw": "raw"}

_DIRECTION_NAMES = {1: "approach", 0: "dwell", -1: "retract"}

# What igor2 raises on a damaged or truncated wave, at any depth of its parser.
_IGOR_ERRORS = (
    ValueError, struct.error, EOFError, IndexError, KeyError, TypeError, ArithmeticError, MemoryError,
    AssertionError,  # igor2 asserts on header fields it cannot reconcile
)


def parse_wave_note(note: bytes) -> dict[str, str]:
    """The ``key: value`` lines of a wave note (CR, LF or CRLF separated) as a dict."""
    text = note.decode("latin-1")
    fields: dict[str, str] = {}
    for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        key, sep, value = line.partition(":")
        if sep and key.strip():
            fields.setdefault(key.strip(), value.strip())
    return fields


def _note_number(note: dict[str, str], key: str) -> float | None:
    try:
        value = float(note[key])
    except (KeyError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _units(raw) -> str:
    if isinstance(raw, bytes):
        return raw.decode("latin-1").strip("\x00 ")
    return b"".join(np.asarray(raw, dtype="S1").reshape(-1).tolist()).decode("latin-1").strip("\x00 ")


class IbwReader(ReaderBase):
    """Read an Igor binary wave as a capture.

    Parameters
    ----------
    path : Path
        The ``.ibw`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides the rate from the x scaling or the note.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        self._path = Path(path)
        wave = self._load()
        header = wave["wave_header"]
        data = np.asarray(wave["wData"])
        if data.dtype.kind not in "fiu" or data.ndim not in (1, 2) or data.size == 0:
            raise InputError(f"{path}: the wave is {data.shape} {data.dtype}; afmtool reads 1-D or 2-D real waves")
        self._data = data.reshape(len(data), -1)
        note = parse_wave_note(wave.get("note", b"") or b"")
        names = self._channel_names(wave, header, self._data.shape[1])
        units = _units(wave.get("data_units") or b"") or _units(header["dataUnits"])
        rate = sample_rate_hz if sample_rate_hz is not None else self._sample_rate(header, note)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{path}: sample rate {rate!r} must be a positive number")
        n = len(self._data)
        segments = self._segments(note, n, rate)
        metadata = self._metadata(note, header, segments)
        channels = tuple(ChannelSpec(name, units) for name in names)
        self.info = CaptureInfo(str(path), "ibw", float(rate), channels, n, metadata, (), segments)

    def _load(self) -> dict:
        from igor2 import binarywave

        try:
            size = self._path.stat().st_size
        except OSError as exc:
            raise InputError(f"{self._path}: cannot open ({exc.strerror})") from None
        if size > MAX_IBW_BYTES:
            raise InputError(f"{self._path}: {size} bytes is more than the {MAX_IBW_BYTES} an .ibw may have here")
        self._check_declared_sizes(size)
        igor_log = logging.getLogger("igor2")
        level = igor_log.level
        igor_log.setLevel(logging.CRITICAL)  # igor2 logs damaged waves itself; the error below says it once
        try:
            loaded = binarywave.load(str(self._path))
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or exc})") from None
        except _IGOR_ERRORS as exc:
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
            raise InputError(f"{self._path}: not a readable Igor binary wave (truncated or damaged: {reason})") from None
        finally:
            igor_log.setLevel(level)
        wave = loaded.get("wave") if isinstance(loaded, dict) else None
        if not isinstance(wave, dict) or "wData" not in wave:
            raise InputError(f"{self._path}: not a readable Igor binary wave (no wave data)")
        return wave

    def _check_declared_sizes(self, file_size: int) -> None:
        """Refuse a header whose declared section sizes exceed the file, before igor2 allocates them.

        igor2 builds its struct formats from these sizes, so a damaged ``noteSize`` of 10^12
        made it ask for that much memory (the long fuzz run, ibw cases 1345 and 1380).  The
        header is read with igor2's own structures; only the 2-byte version is read here.
        """
        from igor2 import binarywave

        try:
            with open(self._path, "rb") as handle:
                head = handle.read(128)
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror})") from None
        if len(head) < 8:
            raise InputError(f"{self._path}: not a readable Igor binary wave (truncated: {len(head)} bytes)")
        headers = {1: binarywave.BinHeader1, 2: binarywave.BinHeader2, 3: binarywave.BinHeader3, 5: binarywave.BinHeader5}
        for order in ("<", ">"):
            version = struct.unpack(order + "h", head[:2])[0]
            if version in headers:
                break
        else:
            raise InputError(f"{self._path}: not an Igor binary wave (version field {head[:2].hex()})")
        header = headers[version]
        header.byte_order = order
        header.setup()
        try:
            fields = header.unpack_from(head[2:])
        except _IGOR_ERRORS as exc:
            raise InputError(f"{self._path}: not a readable Igor binary wave (header: {exc})") from None
        sizes = [int(np.sum(value)) for key, value in fields.items() if key != "checksum"]
        negative = any(int(np.min(value)) < 0 for key, value in fields.items() if key != "checksum")
        if negative or sum(sizes) > file_size:
            raise InputError(
                f"{self._path}: not a readable Igor binary wave (its header declares {sum(sizes)} bytes of sections, "
                f"the file has {file_size}: truncated or damaged)"
            )

    def _channel_names(self, wave: dict, header: dict, n_columns: int) -> list[str]:
        labels = wave.get("labels") or []
        column_labels = []
        if len(labels) > 1 and len(labels[1]) == n_columns + 1:  # entry 0 labels the dimension itself
            column_labels = [lab.decode("latin-1").strip() for lab in labels[1][1:]]
        if n_columns == 1 and not any(column_labels):
            name = header.get("bname", b"") or b"wave"
            column_labels = [name.decode("latin-1").strip() if isinstance(name, bytes) else str(name)]
        names = []
        for i in range(n_columns):
            label = column_labels[i] if i < len(column_labels) and column_labels[i] else f"column{i}"
            names.append(_ASYLUM_CHANNELS.get(label, label))
        if len(set(names)) != len(names):
            raise InputError(f"{self._path}: column labels {names} are not distinct")
        return names

    def _sample_rate(self, header: dict, note: dict[str, str]) -> float:
        step = float(np.asarray(header["sfA"]).reshape(-1)[0])
        x_units = _units(np.asarray(header["dimUnits"])[0]) if np.asarray(header["dimUnits"]).ndim > 1 else ""
        if x_units == "s" and math.isfinite(step) and step > 0:
            return 1.0 / step
        rate = _note_number(note, "NumPtsPerSec")
        if rate is None:
            raise InputError(
                f"{self._path}: no sample rate (x units {x_units!r}, no NumPtsPerSec in the note); give --sample-rate"
            )
        return rate

    def _segments(self, note: dict[str, str], n: int, rate: float) -> tuple[SegmentSpec, ...]:
        try:
            ends = [int(float(v)) for v in note.get("Indexes", "").split(",") if v.strip()]
        except ValueError:
            return ()
        if len(ends) < 2 or ends[0] != 0 or ends != sorted(ends) or ends[-1] >= n:
            return ()
        directions = [v.strip() for v in note.get("Direction", "").split(",")]
        segments = []
        for k in range(1, len(ends)):
            first = 0 if k == 1 else ends[k - 1] + 1
            try:
                name = _DIRECTION_NAMES.get(int(float(directions[k])), f"segment{k - 1}")
            except (IndexError, ValueError):
                name = f"segment{k - 1}"
            if name in (s.name for s in segments):
                name = f"{name}{k - 1}"
            segments.append(SegmentSpec(name, first, ends[k] - first + 1, rate))
        return tuple(segments)

    def _metadata(self, note: dict[str, str], header: dict, segments: tuple[SegmentSpec, ...]) -> dict:
        cantilever = {}
        for key, target, scale in (
            ("SpringConstant", "spring_constant_n_per_m", 1.0),
            ("InvOLS", "deflection_sensitivity_nm_per_v", 1e9),  # the note's InvOLS is in m/V
            ("ThermalFrequency", "f0_hz", 1.0),
            ("ThermalQ", "q", 1.0),
        ):
            value = _note_number(note, key)
            if value is not None and value > 0:
                cantilever[target] = value * scale
        drive = {}
        for key, target in (("DriveFrequency", "frequency_hz"), ("DriveAmplitude", "amplitude_v")):
            value = _note_number(note, key)
            if value is not None and value > 0:
                drive[target] = value
        instrument = {"vendor_format": "Igor binary wave"}
        name = header.get("bname", b"")
        instrument["wave"] = name.decode("latin-1") if isinstance(name, bytes) else str(name)
        for key, target in (("MicroscopeModel", "model"), ("Version", "software_version"), ("ImagingMode", "imaging_mode")):
            if note.get(key):
                instrument[target] = note[key]
        if note.get("Date"):
            instrument["recorded"] = f"{note['Date']} {note.get('Time', '')}".strip()
        scan_size = _note_number(note, "ScanSize")
        if scan_size is not None:
            instrument["scan_size_m"] = scan_size
        temperature = _note_number(note, "ThermalTemperature")
        if temperature is not None and temperature > 0:
            instrument["thermal_temperature_k"] = temperature
        metadata: dict = {"instrument": instrument}
        if cantilever:
            metadata["cantilever"] = cantilever
        if drive:
            metadata["drive"] = drive
        if segments:
            metadata[SEGMENTS_KEY] = segments_metadata(segments)
        return metadata

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        index = {c.name: i for i, c in enumerate(self.info.channels)}
        columns = [index[name] for name in channels]
        for start in range(0, len(self._data), block_samples):
            block = self._data[start : start + block_samples]
            with np.errstate(invalid="ignore", over="ignore"):  # a NaN or inf is refused, by name, downstream
                data = {name: block[:, i].astype(np.float64) for name, i in zip(channels, columns)}
            yield Chunk(start, data)

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._data = np.empty((0, 0))
