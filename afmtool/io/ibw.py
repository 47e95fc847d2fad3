"""Igor Pro binary waves (``.ibw``), versions 1, 2, 3 and 5: Asylum Research fast captures and force curves.

Read here from the layout in WaveMetrics' Technical Note 003 (igor2, the
maintained reader, is the tests' independent reference): a binary header
(``BinHeader1/2/3/5``) whose 16-bit words, with the wave header's, sum to 0;
the wave header (``WaveHeader2`` for versions 1-3, ``WaveHeader5``); the
samples; then, by version, the note, the dependency formula, the extended
units and the dimension labels.  Every section size is checked against the
file's size before anything is read, and the samples are memory-mapped
(:class:`afmtool.io.mapped.MappedArray`), so a wave of any size streams in
flat memory and the note is the only section read whole (at most
:data:`MAX_NOTE_BYTES` of it).

A wave of shape (samples, columns) becomes one channel per column, named from
the column's dimension label; Asylum's labels map to afmtool's channel names
(``Defl`` -> ``deflection``, ``ZSnsr`` -> ``z_piezo``), other labels are kept;
a 1-D wave is one channel named after the wave.  Units are the wave's own data
units (``"m"`` for an MFP-3D force curve), never converted here.  The sample
rate is 1 / the x step (``hsA`` in versions 1-3, ``sfA[0]`` in version 5) when
the x units are a time (``s``, ``ms``, ...), else the note's ``NumPtsPerSec``,
else ``--sample-rate``.  Text waves, complex waves, waves of more than two
dimensions and waves without points are refused.

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
NumPtsPerSec       the sample rate, if the x scaling is not a time
Indexes/Direction  segments (approach, dwell, retract)
=================  ==============================================

``Indexes`` holds the last sample of each segment (``0,1008,2015``: the
approach is samples 0..1008, where ZSnsr peaks, the retract 1009..2015);
``Direction`` gives each segment's sense (1 approach, 0 dwell, -1 retract).
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import CaptureWarning, InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, ReaderBase, SegmentSpec
from afmtool.io.mapped import MappedArray, MappedSamples
from afmtool.io.text import clean_label, decode_file_text
from afmtool.io.views import SEGMENTS_KEY, segments_metadata

__all__ = ["IbwReader", "parse_wave_note", "MAX_NOTE_BYTES", "MAX_COLUMNS"]

#: Most bytes of a wave note read for its metadata (an Asylum force curve's note is 16 kB).
MAX_NOTE_BYTES = 1 << 20
#: Most lines of a note parsed.
MAX_NOTE_LINES = 100_000
#: Most columns (channels) of a 2-D wave.
MAX_COLUMNS = 1 << 16

#: Asylum Research column labels that have an afmtool channel name.
_ASYLUM_CHANNELS = {"Defl": "deflection", "ZSnsr": "z_piezo", "DeflV": "deflection_v", "Raw": "raw"}

_DIRECTION_NAMES = {1: "approach", 0: "dwell", -1: "retract"}

#: Each version's binary header: its size and its fields after the 2-byte version (TN003).
_BIN_HEADERS = {
    1: (8, "ih", ("wfmSize", "checksum")),
    2: (16, "iiih", ("wfmSize", "noteSize", "pictSize", "checksum")),
    3: (20, "iiiih", ("wfmSize", "noteSize", "formulaSize", "pictSize", "checksum")),
    5: (64, "hiiii4i4iiii", ("checksum", "wfmSize", "formulaSize", "noteSize", "dataEUnitsSize",
                             *(f"dimEUnitsSize{k}" for k in range(4)), *(f"dimLabelsSize{k}" for k in range(4)),
                             "sIndicesSize", "optionsSize1", "optionsSize2")),
}
#: WaveHeader2 (versions 1-3) is 110 bytes before its wData[4]; the sums cover all 126.
_WAVE2_SIZE, _WAVE2_CHECKED = 110, 126
_WAVE5_SIZE = 320
#: The leading fields of each wave header that this reader uses.
_WAVE2 = ("hi20shhi4s4sihdd", ("type", "next", "bname", "whVersion", "srcFldr", "fileName", "dataUnits", "xUnits",
                                 "npnts", "aModified", "hsA", "hsB"))
_WAVE5 = ("iIIihh6sh32sii4i4d4d4s16s", ("next", "creationDate", "modDate", "npnts", "type", "dLock", "whpad1",
                                           "whVersion", "bname", "whpad2", "dFolder", *(f"nDim{k}" for k in range(4)),
                                           *(f"sfA{k}" for k in range(4)), *(f"sfB{k}" for k in range(4)),
                                           "dataUnits", "dimUnits"))
#: Igor's numeric type codes; 0x01 marks a complex wave, 0x40 an unsigned integer one, 0 a text wave.
_TYPES = {0x02: "f4", 0x04: "f8", 0x08: "i1", 0x10: "i2", 0x20: "i4", 0x80: "i8"}


class WaveLayout(NamedTuple):
    """Where a wave's parts are in its file, and its header fields (TN003), as read by :func:`read_layout`."""

    version: int
    byte_order: str
    dtype: str
    n_samples: int
    n_columns: int
    data_offset: int
    name: str
    data_units: str
    x_units: str
    x_step: float
    note: bytes
    note_size: int
    column_labels: tuple[str, ...]


def parse_wave_note(note: bytes) -> dict[str, str]:
    """The ``key: value`` lines of a wave note (CR, LF or CRLF separated) as a dict; the first of a repeated key wins.

    At most :data:`MAX_NOTE_LINES` lines are read: the work is bounded whatever the note holds.
    """
    text = note.decode("latin-1")
    fields: dict[str, str] = {}
    for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n", MAX_NOTE_LINES)[:MAX_NOTE_LINES]:
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


def _c_string(raw: bytes) -> str:
    """A fixed-size C string field: up to its first NUL, decoded."""
    return clean_label(raw.split(b"\x00", 1)[0])


def _damaged(path: Path, what: str) -> InputError:
    return InputError(f"{path}: not a readable Igor binary wave ({what})")


def _version_and_order(path: Path, head: bytes) -> tuple[int, str]:
    if len(head) < 8:
        raise _damaged(path, f"truncated: {len(head)} bytes")
    for order in ("<", ">"):
        version = struct.unpack(order + "h", head[:2])[0]
        if version in _BIN_HEADERS:
            return version, order
    raise InputError(f"{path}: not an Igor binary wave (version field {head[:2].hex()})")


def _fields(order: str, fmt: str, names: Sequence[str], buffer: bytes, offset: int) -> dict:
    return dict(zip(names, struct.unpack_from(order + fmt, buffer, offset)))


def _check_sum(path: Path, order: str, head: bytes, size: int) -> None:
    """Igor's header check: the 16-bit words of the binary and wave headers sum to 0 (mod 2^16)."""
    words = np.frombuffer(head[: size - size % 2], dtype=order + "i2")
    if int(words.astype(np.int64).sum()) % 65536:
        raise _damaged(path, "its header checksum is wrong: damaged")


def _section_sizes(bin_header: dict, version: int) -> list[tuple[str, int]]:
    """The sections after the samples, in file order, with their declared sizes."""
    if version == 1:
        return []
    if version == 2:
        return [("note", bin_header["noteSize"]), ("picture", bin_header["pictSize"])]
    if version == 3:
        return [("note", bin_header["noteSize"]), ("formula", bin_header["formulaSize"]), ("picture", bin_header["pictSize"])]
    names = ["formulaSize", "noteSize", "dataEUnitsSize", *(f"dimEUnitsSize{k}" for k in range(4)),
             *(f"dimLabelsSize{k}" for k in range(4)), "sIndicesSize", "optionsSize1", "optionsSize2"]
    return [(name.replace("Size", ""), bin_header[name]) for name in names]


def read_layout(path: Path, handle) -> WaveLayout:
    """Read and check a wave's headers and small sections from the open file ``handle``.

    Raises
    ------
    InputError
        A file that is not an Igor binary wave of version 1, 2, 3 or 5, one whose header sums
        or declared sizes do not hold, or a wave afmtool does not read (text, complex, 3-D or 4-D, empty).
    """
    file_size = handle.seek(0, 2)
    handle.seek(0)
    head = handle.read(64 + _WAVE5_SIZE)
    version, order = _version_and_order(path, head)
    bin_size, fmt, names = _BIN_HEADERS[version]
    wave_size = _WAVE5_SIZE if version == 5 else _WAVE2_SIZE
    if len(head) < bin_size + (wave_size if version == 5 else _WAVE2_CHECKED):
        raise _damaged(path, f"truncated: {len(head)} bytes")
    bin_header = _fields(order, fmt, names, head, 2)
    sections = _section_sizes(bin_header, version)
    declared = bin_header["wfmSize"] + sum(size for _, size in sections)
    if bin_header["wfmSize"] < wave_size or any(size < 0 for _, size in sections) or bin_size + declared > file_size:
        raise InputError(
            f"{path}: not a readable Igor binary wave (its header declares {bin_size + declared} bytes of sections, "
            f"the file has {file_size}: truncated or damaged)"
        )
    _check_sum(path, order, head, bin_size + (wave_size if version == 5 else _WAVE2_CHECKED))
    wave_fmt, wave_names = _WAVE5 if version == 5 else _WAVE2
    wave = _fields(order, wave_fmt, wave_names, head, bin_size)
    dtype, n_samples, n_columns = _shape(path, order, version, bin_header, wave)
    offsets, position = {}, bin_size + bin_header["wfmSize"]
    for name, size in sections:
        offsets[name] = (position, size)
        position += size
    note_at, note_size = offsets.get("note", (0, 0))
    note = _read_at(handle, note_at, min(note_size, MAX_NOTE_BYTES))
    if version == 5:
        data_units = _extended(handle, offsets["dataEUnits"]) or _c_string(wave["dataUnits"])
        x_units = _extended(handle, offsets["dimEUnits0"]) or _c_string(wave["dimUnits"][:4])
        x_step = wave["sfA0"]
        labels = _labels(handle, offsets["dimLabels1"], n_columns) if wave["nDim1"] > 0 else ()
    else:
        data_units, x_units, x_step, labels = _c_string(wave["dataUnits"]), _c_string(wave["xUnits"]), wave["hsA"], ()
    return WaveLayout(version, order, dtype, n_samples, n_columns, bin_size + wave_size, _c_string(wave["bname"]),
                      data_units, x_units, float(x_step), note, note_size, labels)


def _shape(path: Path, order: str, version: int, bin_header: dict, wave: dict) -> tuple[str, int, int]:
    """The samples' dtype (with byte order), samples and columns; refuses what afmtool does not read."""
    code = wave["type"]
    if code == 0:
        raise InputError(f"{path}: the wave holds text, not numbers; afmtool reads 1-D or 2-D real waves")
    if code & 0x01:
        raise InputError(f"{path}: the wave is complex; afmtool reads 1-D or 2-D real waves")
    kind = _TYPES.get(code & ~0x40)
    if kind is None:
        raise _damaged(path, f"unknown number type {code:#x}")
    if code & 0x40:
        kind = kind.replace("i", "u")
    dtype = np.dtype(order + kind)
    npnts = wave["npnts"]
    if version == 5:
        dims = [wave[f"nDim{k}"] for k in range(4)]
        if any(d < 0 for d in dims):
            raise _damaged(path, f"negative dimension sizes {dims}")
        shape = [d for d in dims if d > 0]
        data_bytes = bin_header["wfmSize"] - _WAVE5_SIZE
    else:
        shape = [npnts] if npnts > 0 else []
        data_bytes = bin_header["wfmSize"] - _WAVE2_SIZE - 16
    if npnts <= 0 or not shape or math.prod(shape) != npnts:
        raise InputError(f"{path}: the wave has no points (shape {shape}); afmtool reads 1-D or 2-D real waves")
    if len(shape) > 2:
        raise InputError(f"{path}: the wave is {len(shape)}-D {shape}; afmtool reads 1-D or 2-D real waves")
    if data_bytes != npnts * dtype.itemsize:
        if version == 3 and data_bytes == 0 and bin_header["formulaSize"] > 0:
            raise InputError(f"{path}: the wave's values are not stored (it is computed by a dependency formula)")
        raise _damaged(path, f"{data_bytes} bytes of samples for {npnts} points of {dtype.itemsize} bytes")
    n_columns = shape[1] if len(shape) == 2 else 1
    if n_columns > MAX_COLUMNS:
        raise InputError(f"{path}: the wave has {n_columns} columns; afmtool reads at most {MAX_COLUMNS}")
    return dtype.str, shape[0], n_columns


def _read_at(handle, offset: int, size: int) -> bytes:
    if size <= 0:
        return b""
    handle.seek(offset)
    return handle.read(size)


def _extended(handle, section: tuple[int, int]) -> str:
    """An optional extended-units section (version 5), bounded like every label."""
    offset, size = section
    return clean_label(_read_at(handle, offset, min(size, 4096)))  # sized to its text: UTF-16 holds NULs


def _labels(handle, section: tuple[int, int], n_columns: int) -> tuple[str, ...]:
    """The column labels of a 2-D wave (TN003: 32-byte fields, a long label running on until a NUL).

    Entry 0 labels the dimension itself; entries 1..n label the columns.
    """
    offset, size = section
    if size <= 0 or size % 32:
        return ()
    raw = _read_at(handle, offset, size)
    labels, current = [], b""
    for at in range(0, len(raw), 32):
        field = raw[at : at + 32]
        current += field.split(b"\x00", 1)[0]
        if b"\x00" in field:
            labels.append(current)
            current = b""
    if len(labels) != n_columns + 1:
        return ()
    return tuple(clean_label(decode_file_text(label)) for label in labels[1:])


class IbwReader(MappedSamples, ReaderBase):
    """Read an Igor binary wave (version 1, 2, 3 or 5) as a capture, memory-mapped.

    Parameters
    ----------
    path : Path
        The ``.ibw`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides the rate from the x scaling or the note.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        self._path = Path(path)
        try:
            with open(self._path, "rb") as handle:
                layout = read_layout(self._path, handle)
                file_size = handle.seek(0, 2)
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or exc})") from None
        if layout.note_size > MAX_NOTE_BYTES:
            warnings.warn(f"{self._path}: the wave note is {layout.note_size:,} bytes; its metadata is read from the "
                          f"first {MAX_NOTE_BYTES:,}", CaptureWarning, stacklevel=2)
        note = parse_wave_note(layout.note)
        names = self._channel_names(layout)
        rate = sample_rate_hz if sample_rate_hz is not None else self._sample_rate(layout, note)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{path}: sample rate {rate!r} must be a positive number")
        self._array = MappedArray(str(self._path), layout.data_offset, layout.dtype, layout.n_samples,
                                  layout.n_columns, "F", {name: i for i, name in enumerate(names)})
        self._array.check_fits(file_size)
        segments = self._segments(note, layout.n_samples, rate)
        metadata = self._metadata(note, layout, segments)
        channels = tuple(ChannelSpec(name, layout.data_units) for name in names)
        self.info = CaptureInfo(str(path), "ibw", float(rate), channels, layout.n_samples, metadata, (), segments)

    def _channel_names(self, layout: WaveLayout) -> list[str]:
        labels = list(layout.column_labels)
        if layout.n_columns == 1 and not any(labels):
            labels = [layout.name or "wave"]
        names = []
        for i in range(layout.n_columns):
            label = labels[i] if i < len(labels) and labels[i] else f"column{i}"
            names.append(_ASYLUM_CHANNELS.get(label, label))
        if len(set(names)) != len(names):
            raise InputError(f"{self._path}: column labels {names[:20]} are not distinct")
        return names

    def _sample_rate(self, layout: WaveLayout, note: dict[str, str]) -> float:
        from afmtool.io.units import parse_unit

        try:
            kind, exponent = parse_unit(layout.x_units)
        except ValueError:
            kind, exponent = "", 0
        step = layout.x_step * 10.0**exponent
        if kind == "time" and math.isfinite(step) and step > 0:
            return 1.0 / step
        rate = _note_number(note, "NumPtsPerSec")
        if rate is None:
            raise InputError(
                f"{self._path}: no sample rate (x units {layout.x_units!r}, no NumPtsPerSec in the note); give --sample-rate"
            )
        return rate

    def _segments(self, note: dict[str, str], n: int, rate: float) -> tuple[SegmentSpec, ...]:
        ends = []
        text = note.get("Indexes", "")
        for value in text.split(",", 64)[:64]:
            if not value.strip():
                continue
            try:
                end = float(value)
            except ValueError:
                end = math.nan
            if not (math.isfinite(end) and end == int(end)):  # "inf" or "1e400" overflowed int() before
                raise InputError(f"{self._path}: the wave note's Indexes {text[:80]!r} are not sample numbers")
            ends.append(int(end))
        if len(ends) < 2 or ends[0] != 0 or ends != sorted(ends) or ends[-1] >= n:
            return ()
        directions = [v.strip() for v in note.get("Direction", "").split(",")]
        segments = []
        for k in range(1, len(ends)):
            first = 0 if k == 1 else ends[k - 1] + 1
            try:
                name = _DIRECTION_NAMES.get(int(float(directions[k])), f"segment{k - 1}")
            except (IndexError, ValueError, OverflowError):
                name = f"segment{k - 1}"
            if name in (s.name for s in segments):
                name = f"{name}{k - 1}"
            segments.append(SegmentSpec(name, first, ends[k] - first + 1, rate))
        return tuple(segments)

    def _metadata(self, note: dict[str, str], layout: WaveLayout, segments: tuple[SegmentSpec, ...]) -> dict:
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
        instrument = {"vendor_format": "Igor binary wave", "wave": layout.name, "igor_wave_version": layout.version}
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
