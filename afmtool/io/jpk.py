"""JPK force curves (``.jpk-force``), QI series (``.jpk-qi-series``), force maps (``.jpk-force-map``) and QI data (``.jpk-qi-data``).

All are ZIP archives of Java ``.properties`` headers and big-endian raw
channel files.  A single curve::

    header.properties                       file-format-version, instrument
    shared-data/header.properties           what the headers point to (format 2.x)
    segments/K/segment-header.properties    K-th segment: style (extend, retract,
                                            pause), duration, num-points, channels
    segments/K/channels/NAME.dat            raw samples

A map or QI data file holds many curves, ``index/N/header.properties``
(the curve's position) and ``index/N/segments/K/...``; ``--curve N`` (the
index) or ``--curve X,Y`` (its grid position, as afmformats numbers it: the
grid cell nearest the recorded position) reads one, and ``info`` lists them.

**Indirections.**  A header key ``PREFIX.MEDIATOR.*=N`` stands for every key
``MEDIATOR.N.REST`` of the shared header, as ``PREFIX.REST``: a segment's style
(``force-segment-header.force-segment-header-info.*``), a channel's encoding
and conversions (``channel.NAME.lcd-info.*``).  Every one is followed, at most
:data:`MAX_INDIRECTION_DEPTH` deep, a cycle refused, and the expanded header
bounded (:data:`MAX_RESOLVED_PROPERTIES`); each header is grouped by channel
once, so opening a file is linear in its size.  Format 0.x writes each
channel's encoding in the segment header itself; both are read.

Each channel's scaling chain is applied: raw integer x encoder multiplier +
offset gives volts, then each linear conversion of the chain in turn
(vDeflection: volts -> distance (m, the sensitivity) -> force (N, the
spring constant)).  Channels end at their default conversion, except the
deflection, which ends at *distance* (m): afmtool's deflection is a
length, and the force conversion's multiplier is reported instead as the
spring constant.  ``vDeflection`` is named ``deflection``.  The z-piezo is the
measured height where the curve has one, in this order of preference:
``strainGaugeHeight``, ``capacitiveSensorHeight``, ``measuredHeight`` (sensors of
the actual z), then ``height`` (the piezo's commanded, unlinearised height),
as afmformats ranks them; that channel is named ``z_piezo`` (the metadata's
``instrument.z_piezo_from`` says which) and ``--channel z_piezo=height``
chooses another.  Other channels keep their JPK names.  Channels stored as a
start and step (``time``) are generated.

Segments are read one at a time: ``--segment retract``.  When every
segment has the same rate and the same channels, they may also be read back
to back (the whole curve); otherwise (a QI curve's 5 kHz extend and 50 kHz
retract; a creep-compliance pause that stores fewer channels) ``--segment``
is required and ``info`` summarises each.  Samples are streamed from the
archive.
"""

from __future__ import annotations

import math
import re
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError, SegmentsAtDifferentRates, SelectionNeeded
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.text import clean_label
from afmtool.io.unit_names import unit_symbol
from afmtool.io.views import SEGMENTS_KEY, describe_segments, segments_metadata, select_segment

__all__ = ["JpkReader", "JpkCurve", "parse_properties", "resolve_indirections", "MAX_CHANNELS", "MAX_CURVES"]

#: Raw sample types by JPK's names (all big-endian).
_RAW_TYPES = {
    "integer-data": ">i4",
    "signedinteger": ">i4",
    "unsignedinteger": ">u4",
    "short-data": ">i2",
    "short": ">i2",
    "signedshort": ">i2",
    "unsignedshort": ">u2",
    "long-data": ">i8",
    "long": ">i8",
    "signedlong": ">i8",
    "float-data": ">f4",
    "float": ">f4",
    "double-data": ">f8",
    "double": ">f8",
}

#: Largest header read, bytes (real headers are tens of kB).
_MAX_HEADER_BYTES = 16 << 20
#: Most segments in one curve.
_MAX_SEGMENTS = 10_000
#: Most channels in one segment (JPK writes about 15).
MAX_CHANNELS = 1024
#: Most curves in a map (a 512 x 512 QI image is 262,144).
MAX_CURVES = 1 << 20
#: Most keys a header may hold once its indirections are followed.
MAX_RESOLVED_PROPERTIES = 1 << 21
#: Deepest chain of indirections followed (JPK writes one level).
MAX_INDIRECTION_DEPTH = 8
#: Largest ratio of a member's size to its compressed size (deflate itself stops near 1032).
_MAX_COMPRESSION = 1100
#: Relative spread of segment rates that are one clock's (num-points / duration, rounded in the header).
_RATE_TOLERANCE = 1e-9
#: Where the deflection's chain stops (see the module docstring).
_DEFLECTION_TARGET = "distance"
#: The channels that may be the z-piezo, most preferred first (see the module docstring).
Z_PIEZO_PREFERENCE = ("strainGaugeHeight", "capacitiveSensorHeight", "measuredHeight", "height")

_SEGMENT_HEADER = re.compile(r"^(?:index/(\d+)/)?segments/(\d+)/segment-header\.properties$")
_CURVE_HEADER = re.compile(r"^index/(\d+)/header\.properties$")


# --------------------------------------------------------------------------- properties

def parse_properties(text: str) -> dict[str, str]:
    """Java ``.properties`` text as a dict: ``key=value`` or ``key: value``, ``#``/``!`` comments,
    backslash escapes (``\\:``, ``\\uXXXX``) and continuation lines; linear in the text's length."""
    props: dict[str, str] = {}
    logical: list[str] = []
    for raw in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        line = raw.lstrip()
        if not logical and (not line or line[0] in "#!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:
            logical.append(line[:-1])
            continue
        logical.append(line)
        joined = "".join(logical)
        match = re.match(r"((?:[^\\=:\s]|\\.)*)\s*[=:]?\s*(.*)$", joined, re.S)
        props[_unescape(match.group(1))] = _unescape(match.group(2))
        logical = []
    return props


def _unescape(text: str) -> str:
    if "\\" not in text:
        return text

    def replace(match: re.Match) -> str:
        body = match.group(1)
        if body.startswith("u") and len(body) == 5:
            try:
                return chr(int(body[1:], 16))
            except ValueError:
                return body
        return {"n": "\n", "t": "\t", "r": "\r", "f": "\f"}.get(body, body)

    return re.sub(r"\\(u[0-9a-fA-F]{4}|.)", replace, text)


def _shared_groups(shared: Mapping[str, str]) -> dict[tuple[str, str], list[tuple[str, str]]]:
    """The shared header grouped by ``MEDIATOR.N.`` prefix: ``{("lcd-info", "3"): [(rest, value), ...]}``."""
    groups: dict[tuple[str, str], list[tuple[str, str]]] = {}
    for key, value in shared.items():
        parts = key.split(".", 2)
        if len(parts) == 3 and parts[1].isdigit():
            groups.setdefault((parts[0], parts[1]), []).append((parts[2], value))
    return groups


def resolve_indirections(props: Mapping[str, str], groups: Mapping, where: str) -> dict[str, str]:
    """``props`` with every ``PREFIX.MEDIATOR.*=N`` replaced by the shared keys it stands for (see the module).

    A key the header writes itself wins over one an indirection brings.  Nested
    indirections are followed up to :data:`MAX_INDIRECTION_DEPTH`; one that comes
    back to a group already on its chain is a cycle.

    Raises
    ------
    InputError
        An indirection to a group the shared header lacks, a cycle, a chain too deep,
        or more than :data:`MAX_RESOLVED_PROPERTIES` keys.
    """
    out = {key: value for key, value in props.items() if not key.endswith(".*")}
    pending = [(key, value, ()) for key, value in props.items() if key.endswith(".*")]
    while pending:
        key, value, chain = pending.pop()
        prefix, _, mediator = key[:-2].rpartition(".")
        target = (mediator, value.strip())
        if target in chain:
            raise InputError(f"{where}: {key}={value} leads back to {mediator}.{value.strip()} (a cycle)")
        if len(chain) >= MAX_INDIRECTION_DEPTH:
            raise InputError(f"{where}: {key} is more than {MAX_INDIRECTION_DEPTH} indirections deep")
        group = groups.get(target)
        if group is None:
            raise InputError(f"{where}: {key}={value} points to no {mediator}.{value.strip()}.* in the shared header")
        for rest, shared_value in group:
            name = f"{prefix}.{rest}" if prefix else rest
            if rest.endswith(".*"):
                pending.append((name, shared_value, (*chain, target)))
            else:
                out.setdefault(name, shared_value)
        if len(out) + len(pending) > MAX_RESOLVED_PROPERTIES:
            raise InputError(f"{where}: its indirections expand to more than {MAX_RESOLVED_PROPERTIES:,} keys")
    return out


def _by_channel(props: Mapping[str, str]) -> dict[str, dict[str, str]]:
    """``channel.NAME.REST`` keys grouped by channel, in one pass: ``{NAME: {REST: value}}``."""
    channels: dict[str, dict[str, str]] = {}
    for key, value in props.items():
        if key.startswith("channel."):
            parts = key.split(".", 2)
            if len(parts) == 3:
                channels.setdefault(parts[1], {})[parts[2]] = value
    return channels


def _number(props: Mapping, key: str, source: str) -> float:
    try:
        value = float(props[key])
    except KeyError:
        raise InputError(f"{source}: missing {key}") from None
    except ValueError:
        raise InputError(f"{source}: {key}={props[key]!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{source}: {key}={props[key]!r} is not finite")
    return value


def _ending(props: Mapping[str, str], suffix: str) -> str | None:
    """The value of the first key ending in ``suffix`` (the same fact sits under a format-specific prefix)."""
    return next((value for key, value in props.items() if key.endswith(suffix)), None)


def _float_or_none(text: str | None) -> float | None:
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        return None
    return value if math.isfinite(value) else None


# --------------------------------------------------------------------------- records

class _Channel:
    """One channel of one segment: where its samples are and how to scale them."""

    def __init__(self, name: str, member: str | None, dtype: str | None, n: int, steps, units: str, raster=None):
        self.name, self.member, self.dtype, self.n = name, member, dtype, n
        self.steps, self.units, self.raster = steps, units, raster
        self.encoding: Mapping[str, str] = {}  # the channel's header keys (the deflection's give the calibration)
        self.z_from: str | None = None  # the JPK channel this z_piezo was

    def scale(self, raw: np.ndarray) -> np.ndarray:
        values = raw.astype(np.float64)
        for multiplier, offset in self.steps:
            values = values * multiplier + offset
        return values


class _Segment(NamedTuple):
    name: str
    sample_rate_hz: float
    n_samples: int
    channels: dict[str, _Channel]


class JpkCurve(NamedTuple):
    """One curve of a map: its index (``index/N``), grid cell (x, y) and recorded position (m); None where unknown."""

    index: int
    grid_index: tuple[int, int] | None
    position_m: tuple[float, float] | None

    def describe(self) -> dict:
        return {"curve": self.index, "grid_index": list(self.grid_index) if self.grid_index else None,
                "position_m": list(self.position_m) if self.position_m else None}


class _Grid(NamedTuple):
    """A map's grid: cells along x and y, its centre and size (m)."""

    shape: tuple[int, int]
    center_m: tuple[float, float]
    size_m: tuple[float, float]

    def cell(self, position: tuple[float, float]) -> tuple[int, int]:
        """The grid cell whose centre is nearest ``position`` (afmformats' numbering)."""
        cell = []
        for pos, n, centre, size in zip(position, self.shape, self.center_m, self.size_m):
            step = size / n
            centres = centre - size / 2 + step * (np.arange(n) + 0.5)
            cell.append(int(np.argmin(np.abs(centres - pos))))
        return cell[0], cell[1]


def _grid(header: Mapping[str, str]) -> _Grid | None:
    values = [_float_or_none(_ending(header, f".position-pattern.grid.{k}"))
              for k in ("ilength", "jlength", "xcenter", "ycenter", "ulength", "vlength")]
    if any(v is None for v in values) or not (1 <= values[0] <= MAX_CURVES and 1 <= values[1] <= MAX_CURVES):
        return None
    if values[0] != int(values[0]) or values[1] != int(values[1]) or values[4] <= 0 or values[5] <= 0:
        return None
    return _Grid((int(values[0]), int(values[1])), (values[2], values[3]), (values[4], values[5]))


# --------------------------------------------------------------------------- the reader

class JpkReader(ReaderBase):
    """Read a JPK force curve, QI series, or one curve of a force map or QI data file.

    Parameters
    ----------
    path : Path
        The file; opened read-only.
    sample_rate_hz : float, optional
        Overrides every segment's num-points / duration.
    segment : str, optional
        A segment's name (``extend``, ``retract``) or number from 0.
    curve : str, optional
        A map's curve: its index ``N`` or its grid cell ``X,Y``.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, *, segment: str | None = None,
                 curve: str | None = None) -> None:
        self._path = Path(path)
        try:
            self._zip = zipfile.ZipFile(self._path)
        except (zipfile.BadZipFile, EOFError, ValueError, NotImplementedError) as exc:
            raise InputError(f"{path}: not a readable JPK file (not a complete ZIP archive: {_first_line(exc)})") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        try:
            self._open(sample_rate_hz, segment, curve)
        except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, KeyError, NotImplementedError, RuntimeError) as exc:
            self._zip.close()
            raise InputError(f"{path}: damaged JPK file ({_first_line(exc)})") from None
        except BaseException:
            self._zip.close()
            raise

    # -- headers -------------------------------------------------------------------------------
    def _properties(self, member: str, required: bool = True) -> dict[str, str]:
        try:
            info = self._zip.getinfo(member)
        except KeyError:
            if required:
                raise InputError(f"{self._path}: no {member} in the archive") from None
            return {}
        if info.file_size > _MAX_HEADER_BYTES:
            raise InputError(f"{self._path}: {member} is {info.file_size} bytes; headers are at most {_MAX_HEADER_BYTES}")
        return parse_properties(self._zip.read(member).decode("latin-1"))

    def _layout(self) -> dict[int | None, list[int]]:
        """Each curve's segment numbers, from the archive's member names in one pass (``None``: a single curve)."""
        curves: dict[int | None, set[int]] = {}
        for name in self._zip.namelist():
            match = _SEGMENT_HEADER.match(name)
            if match:
                curve = int(match.group(1)) if match.group(1) is not None else None
                curves.setdefault(curve, set()).add(int(match.group(2)))
                if len(curves) > MAX_CURVES:
                    raise InputError(f"{self._path}: more than {MAX_CURVES:,} curves")
        if not curves:
            raise InputError(f"{self._path}: no segments/N/segment-header.properties; not a JPK force file")
        if None in curves and len(curves) > 1:
            raise InputError(f"{self._path}: holds both a single curve (segments/) and a map's curves (index/)")
        for curve, segments in curves.items():
            if len(segments) > _MAX_SEGMENTS:
                raise InputError(f"{self._path}: curve {curve} has {len(segments)} segments; at most {_MAX_SEGMENTS}")
        return {curve: sorted(segments) for curve, segments in sorted(curves.items(), key=lambda c: -1 if c[0] is None else c[0])}

    def _open(self, sample_rate_hz: float | None, segment: str | None, curve: str | None) -> None:
        header = self._properties("header.properties")
        self._groups = _shared_groups(self._properties("shared-data/header.properties", required=False))
        layout = self._layout()
        grid = _grid(header)
        chosen_curve = self._choose_curve(layout, curve, grid)
        self._prefix = "" if chosen_curve is None else f"index/{chosen_curve.index}/"
        numbers = layout[None if chosen_curve is None else chosen_curve.index]
        self._segments = self._read_segments(numbers, sample_rate_hz)
        # durations are written as n / rate in decimal, so one clock's rates differ in their last digits
        rates = [s.sample_rate_hz for s in self._segments]
        uniform_rate = max(rates) - min(rates) <= _RATE_TOLERANCE * max(rates)
        same_channels = len({tuple(s.channels) for s in self._segments}) == 1
        starts = np.cumsum([0] + [s.n_samples for s in self._segments])[:-1]
        together = uniform_rate and same_channels
        segments = tuple(SegmentSpec(s.name, int(start) if together else 0, s.n_samples, s.sample_rate_hz)
                         for s, start in zip(self._segments, starts))
        metadata = self._metadata(header, segments if together else (), chosen_curve, grid)
        if segment is not None:
            self._chosen = [select_segment(segments, segment, str(self._path))]
            metadata["segment"] = {"name": segments[self._chosen[0]].name, "index": self._chosen[0]}
            metadata.pop(SEGMENTS_KEY, None)
        elif together:
            self._chosen = list(range(len(self._segments)))
        else:
            why = "rates" if not uniform_rate else "channels"
            detail = describe_segments(segments) if not uniform_rate else "; ".join(
                f"{i} {s.name}: {', '.join(s.channels)}" for i, s in enumerate(self._segments))
            raise SegmentsAtDifferentRates(
                f"{self._path}: segments with different {why}: {detail}; choose one with --segment", segments
            )
        first = self._segments[self._chosen[0]]
        specs = tuple(ChannelSpec(name, channel.units) for name, channel in first.channels.items())
        n_total = sum(self._segments[i].n_samples for i in self._chosen)
        self.info = CaptureInfo(str(self._path), self._format_name(chosen_curve), first.sample_rate_hz, specs,
                                n_total, metadata, (), segments)

    def _format_name(self, curve: JpkCurve | None) -> str:
        name = self._path.name.lower()
        if name.endswith((".jpk-qi-series", ".jpk-qi-data")):
            return "jpk-qi"
        return "jpk-map" if curve is not None else "jpk"

    # -- curves of a map -------------------------------------------------------------------------
    def _curves(self, layout: Mapping, grid: _Grid | None) -> list[JpkCurve]:
        """Every curve of a map, with its grid cell and position (reads each curve's small header)."""
        found = []
        for index in layout:
            props = self._properties(f"index/{index}/header.properties", required=False)
            x, y = (_float_or_none(_ending(props, f".header.position.{axis}")) for axis in ("x", "y"))
            position = (x, y) if x is not None and y is not None else None
            cell = grid.cell(position) if grid is not None and position is not None else None
            found.append(JpkCurve(index, cell, position))
        return found

    def _choose_curve(self, layout: Mapping, choice: str | None, grid: _Grid | None) -> JpkCurve | None:
        if None in layout:
            if choice is not None:
                raise InputError(f"{self._path}: --curve {choice}: this is a single force curve, not a map")
            return None
        if choice is None and len(layout) == 1:
            choice = str(next(iter(layout)))
        if choice is not None and choice.strip().isdigit():
            index = int(choice)
            if index in layout:
                return self._curves({index: layout[index]}, grid)[0]
        curves = self._curves(layout, grid)
        listing = {"format": "jpk-qi" if self._path.name.lower().endswith(".jpk-qi-data") else "jpk-map",
                   "curves": [c.describe() for c in curves], "grid_shape": list(grid.shape) if grid else None}
        if choice is None:
            raise SelectionNeeded(
                f"{self._path}: a map of {len(curves)} curves; choose one with --curve N (0..{max(layout)}) or --curve X,Y",
                "--curve", tuple(c.index for c in curves), listing,
            )
        cell = _cell(choice)
        matches = [c for c in curves if cell is not None and c.grid_index == cell]
        if len(matches) == 1:
            return matches[0]
        known = ", ".join(f"{c.index} ({c.grid_index[0]},{c.grid_index[1]})" if c.grid_index else str(c.index)
                          for c in curves[:20])
        raise InputError(f"{self._path}: no curve {choice!r}; the curves are {known}{' ...' if len(curves) > 20 else ''}")

    # -- segments and channels -------------------------------------------------------------------
    def _read_segments(self, numbers: Sequence[int], sample_rate_hz: float | None) -> list[_Segment]:
        segments, used = [], set()
        for k in numbers:
            segment = self._segment(k, sample_rate_hz)
            name = segment.name if segment.name not in used else f"{segment.name}{k}"
            used.add(name)
            segments.append(segment._replace(name=name))
        return segments

    def _segment(self, k: int, sample_rate_hz: float | None) -> _Segment:
        where = f"{self._path}: {self._prefix}segments/{k}"
        own = self._properties(f"{self._prefix}segments/{k}/segment-header.properties")
        props = resolve_indirections(own, self._groups, where)
        n = int(_number(props, "force-segment-header.num-points", where))
        duration = _number(props, "force-segment-header.duration", where)
        if n < 0 or n > (1 << 40):
            raise InputError(f"{where}: num-points {n} is not a segment length")
        rate = sample_rate_hz if sample_rate_hz is not None else (n / duration if duration > 0 else math.nan)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{where}: duration {duration!r} s for {n} points gives no sample rate")
        name = clean_label(props.get("force-segment-header.settings.style") or props.get("force-segment-header.name.name")
                           or f"segment{k}") or f"segment{k}"
        names = props.get("channels.list", "").split()
        if len(names) > MAX_CHANNELS:
            raise InputError(f"{where}: declares {len(names)} channels; afmtool reads at most {MAX_CHANNELS}")
        by_channel = _by_channel(props)
        channels = {}
        for jpk_name in names:
            channel = self._channel(k, jpk_name, by_channel.get(jpk_name, {}), n)
            channels[channel.name] = channel
        if not channels:
            raise InputError(f"{where}: no channels")
        return _Segment(name, float(rate), n, _name_z_piezo(channels))

    def _channel(self, k: int, jpk_name: str, own: dict, n: int) -> _Channel:
        where = f"{self._path}: {self._prefix}segments/{k} channel {jpk_name}"
        name = "deflection" if jpk_name == "vDeflection" else clean_label(jpk_name)
        data_type = own.get("type") or own.get("data.type", "")
        encoder_prefix = "encoder." if any(key.startswith("encoder.") for key in own) else "data.encoder."
        encoder = {key[len(encoder_prefix):]: v for key, v in own.items() if key.startswith(encoder_prefix)}
        count = int(_number(own, "data.num-points", where)) if "data.num-points" in own else n
        if count != n:
            raise InputError(f"{where}: {count} points in a segment of {n}")
        if data_type == "raster-data" or ("data.start" in own and "data.step" in own):
            start, step = _number(own, "data.start", where), _number(own, "data.step", where)
            return _Channel(name, None, None, n, [], unit_symbol(own.get("unit.unit", "")), raster=(start, step))
        dtype = _RAW_TYPES.get(encoder.get("type", "")) or _RAW_TYPES.get(data_type)
        if dtype is None:
            raise InputError(f"{where}: unknown data type {data_type or encoder.get('type')!r}")
        member = f"{self._prefix}segments/{k}/" + own.get("data.file.name", f"channels/{jpk_name}.dat")
        try:
            entry = self._zip.getinfo(member)
        except KeyError:
            raise InputError(f"{where}: no {member} in the archive") from None
        size = entry.file_size
        if size > _MAX_COMPRESSION * entry.compress_size + (1 << 16):
            raise InputError(f"{where}: {member} claims {size} bytes from {entry.compress_size}; refusing a ZIP bomb")
        if size != n * np.dtype(dtype).itemsize:
            raise InputError(f"{where}: {member} holds {size} bytes, not {n} samples of {np.dtype(dtype).itemsize}")
        steps, unit = _chain(own, encoder, name, where)
        channel = _Channel(name, member, dtype, n, steps, unit)
        if name == "deflection":
            channel.encoding = own
        return channel

    def _metadata(self, header: dict, segments: tuple[SegmentSpec, ...], curve: JpkCurve | None, grid: _Grid | None) -> dict:
        instrument: dict = {"vendor_format": "JPK", "file_format_version": header.get("file-format-version", "")}
        for key, value in header.items():
            if key.endswith("description.instrument") and value:
                instrument["instrument"] = clean_label(value)
            elif key.endswith("description.source-software") and value:
                instrument["software_version"] = clean_label(value)
        z_from = next((c.z_from for s in self._segments for c in s.channels.values() if getattr(c, "z_from", None)), None)
        if z_from:
            instrument["z_piezo_from"] = z_from
        metadata: dict = {"instrument": instrument}
        cantilever = _calibration(self._segments[0].channels.get("deflection"))
        if cantilever:
            metadata["cantilever"] = cantilever
        if curve is not None:
            metadata["curve"] = curve.describe()
            if grid is not None:
                metadata["curve"]["grid_shape"] = list(grid.shape)
        if segments:
            metadata[SEGMENTS_KEY] = segments_metadata(segments)
        return metadata

    # -- samples -------------------------------------------------------------------------------
    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        done = 0
        for index in self._chosen:
            segment = self._segments[index]
            handles = {}
            try:
                for c in channels:
                    member = segment.channels[c].member
                    handles[c] = self._zip.open(member) if member is not None else None
                for lo in range(0, segment.n_samples, block_samples):
                    count = min(block_samples, segment.n_samples - lo)
                    data = {c: self._read(segment.channels[c], handles[c], lo, count) for c in channels}
                    yield Chunk(done, data)
                    done += count
            except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError, RuntimeError, NotImplementedError) as exc:
                raise InputError(f"{self._path}: cannot read segment {segment.name} ({_first_line(exc)})") from None
            finally:
                for handle in handles.values():
                    if handle is not None:
                        handle.close()

    def _read(self, channel: _Channel, handle, lo: int, count: int) -> np.ndarray:
        if channel.raster is not None:
            start, step = channel.raster
            return start + step * (lo + np.arange(count, dtype=np.float64))
        itemsize = np.dtype(channel.dtype).itemsize
        raw = handle.read(count * itemsize)
        if len(raw) != count * itemsize:
            raise InputError(f"{self._path}: {channel.member} ends at sample {lo + len(raw) // itemsize}, before {channel.n}")
        return channel.scale(np.frombuffer(raw, dtype=channel.dtype))

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._zip.close()


def _cell(choice: str) -> tuple[int, int] | None:
    """``"X,Y"`` as a grid cell, else None."""
    parts = [p.strip() for p in choice.split(",")]
    if len(parts) == 2 and all(p.isdigit() for p in parts):
        return int(parts[0]), int(parts[1])
    return None


def _name_z_piezo(channels: dict[str, _Channel]) -> dict[str, _Channel]:
    """The preferred height channel (:data:`Z_PIEZO_PREFERENCE`) renamed ``z_piezo``, in its place."""
    if "z_piezo" in channels:
        return channels
    source = next((name for name in Z_PIEZO_PREFERENCE if name in channels), None)
    if source is None:
        return channels
    renamed = {}
    for name, channel in channels.items():
        if name == source:
            channel.name, channel.z_from = "z_piezo", source
            name = "z_piezo"
        renamed[name] = channel
    return renamed


def _chain(encoding: dict, encoder: dict, name: str, where: str):
    """Linear (multiplier, offset) steps from raw to the target conversion, and its unit."""
    steps = []
    if encoder.get("scaling.type", "linear") != "linear":
        raise InputError(f"{where}: encoder scaling {encoder.get('scaling.type')!r} is not linear")
    if "scaling.multiplier" in encoder:
        steps.append((_number(encoder, "scaling.multiplier", where), _number(encoder, "scaling.offset", where)))
        unit = encoder.get("scaling.unit.unit", "")
    else:
        unit = encoding.get("unit.unit", "")
    conversions = {key[len("conversion-set.conversion."):]: v for key, v in encoding.items()
                   if key.startswith("conversion-set.conversion.")}
    base = encoding.get("conversion-set.conversions.base", "volts")
    target = encoding.get("conversion-set.conversions.default", base)
    if name == "deflection" and conversions.get(f"{_DEFLECTION_TARGET}.defined") == "true":
        target = _DEFLECTION_TARGET
    chain = []
    seen = set()
    while target and target != base and target not in seen and len(chain) < 64:
        seen.add(target)
        if conversions.get(f"{target}.defined") != "true":
            break
        chain.append(target)
        target = conversions.get(f"{target}.base-calibration-slot", base)
    for step in reversed(chain):
        c = {key[len(step) + 1:]: v for key, v in conversions.items() if key.startswith(step + ".")}
        # "simple" and "file" (a calibration file's values, copied here) conversions are both linear
        if c.get("scaling.type") != "linear" or c.get("scaling.style", "offsetmultiplier") != "offsetmultiplier":
            raise InputError(f"{where}: conversion {step!r} scaling is {c.get('scaling.type')!r}, not linear")
        steps.append((_number(c, "scaling.multiplier", where), _number(c, "scaling.offset", where)))
        unit = c.get("scaling.unit.unit", unit)
    return steps, unit_symbol(clean_label(unit))


def _calibration(deflection: _Channel | None) -> dict:
    """The deflection's sensitivity (nm/V) and spring constant (N/m), from its distance and force conversions."""
    encoding = getattr(deflection, "encoding", None) or {}
    found = {}
    for step, target, scale in (("distance", "deflection_sensitivity_nm_per_v", 1e9),
                                ("force", "spring_constant_n_per_m", 1.0)):
        if encoding.get(f"conversion-set.conversion.{step}.defined") == "true":
            value = _float_or_none(encoding.get(f"conversion-set.conversion.{step}.scaling.multiplier"))
            if value is not None and value > 0:
                found[target] = value * scale
    return found


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]
