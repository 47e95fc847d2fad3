"""JPK force curves (``.jpk-force``) and QI series (``.jpk-qi-series``).

Both are ZIP archives of Java ``.properties`` headers and big-endian raw
channel files::

    header.properties                       file-format-version, instrument
    shared-data/header.properties           lcd-info.N.*: channel encodings (format 2.x)
    segments/K/segment-header.properties    K-th segment: style (extend, retract,
                                            pause), duration, num-points, channels
    segments/K/channels/NAME.dat            raw samples

Format 0.x writes each channel's encoding in the segment header
(``channel.NAME.data.*`` and ``channel.NAME.conversion-set.*``); format
2.x points to ``lcd-info.N`` in the shared header.  Both are read.  Each
channel's scaling chain is applied: raw integer x encoder multiplier +
offset gives volts, then each linear conversion of the chain in turn
(vDeflection: volts -> distance (m, the sensitivity) -> force (N, the
spring constant)).  Channels end at their default conversion, except the
deflection, which ends at *distance* (m): afmtool's deflection is a
length, and the force conversion's multiplier is reported instead as the
spring constant.  ``vDeflection`` is named ``deflection``; other channels
keep their JPK names.  Channels stored as a start and step (``time``) are
generated.

Segments are read one at a time: ``--segment retract``.  When every
segment has the same rate, they may also be read back to back (the whole
curve); when rates differ (a QI curve's 5 kHz extend and 50 kHz retract),
``--segment`` is required.  Samples are streamed from the archive.
"""

from __future__ import annotations

import math
import re
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError, SegmentsAtDifferentRates
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.unit_names import unit_symbol
from afmtool.io.views import SEGMENTS_KEY, describe_segments, segments_metadata, select_segment

__all__ = ["JpkReader", "parse_properties"]

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
#: Most segments in a file.
_MAX_SEGMENTS = 10_000
#: Largest ratio of a member's size to its compressed size (deflate itself stops near 1032).
_MAX_COMPRESSION = 1100
#: Where the deflection's chain stops (see the module docstring).
_DEFLECTION_TARGET = "distance"


def parse_properties(text: str) -> dict[str, str]:
    """Java ``.properties`` text as a dict: ``key=value`` or ``key: value``, ``#``/``!`` comments,
    backslash escapes (``\\:``, ``\\uXXXX``) and continuation lines."""
    props: dict[str, str] = {}
    logical = ""
    for raw in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        line = raw.lstrip() if not logical else raw.lstrip()
        if not logical and (not line or line[0] in "#!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:
            logical += line[:-1]
            continue
        logical += line
        match = re.match(r"((?:[^\\=:\s]|\\.)*)\s*[=:]?\s*(.*)$", logical, re.S)
        key, value = match.group(1), match.group(2)
        props[_unescape(key)] = _unescape(value)
        logical = ""
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


def _number(props: dict, key: str, source: str) -> float:
    try:
        value = float(props[key])
    except KeyError:
        raise InputError(f"{source}: missing {key}") from None
    except ValueError:
        raise InputError(f"{source}: {key}={props[key]!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{source}: {key}={props[key]!r} is not finite")
    return value


class _Channel:
    """One channel of one segment: where its samples are and how to scale them."""

    def __init__(self, name: str, member: str | None, dtype: str | None, n: int, steps, units: str, raster=None):
        self.name, self.member, self.dtype, self.n = name, member, dtype, n
        self.steps, self.units, self.raster = steps, units, raster

    def scale(self, raw: np.ndarray) -> np.ndarray:
        values = raw.astype(np.float64)
        for multiplier, offset in self.steps:
            values = values * multiplier + offset
        return values


class JpkReader(ReaderBase):
    """Read a JPK force curve or QI series, one segment or the whole curve.

    Parameters
    ----------
    path : Path
        The ``.jpk-force`` or ``.jpk-qi-series`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides every segment's num-points / duration.
    segment : str, optional
        A segment's name (``extend``, ``retract``) or number from 0.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, *, segment: str | None = None) -> None:
        self._path = Path(path)
        try:
            self._zip = zipfile.ZipFile(self._path)
        except (zipfile.BadZipFile, EOFError, ValueError, NotImplementedError) as exc:
            raise InputError(f"{path}: not a readable JPK file (not a complete ZIP archive: {_first_line(exc)})") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        try:
            self._open(sample_rate_hz, segment)
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

    def _open(self, sample_rate_hz: float | None, segment: str | None) -> None:
        header = self._properties("header.properties")
        shared = self._properties("shared-data/header.properties", required=False)
        names = {m.filename for m in self._zip.infolist()}
        indices = sorted(
            {int(m.group(1)) for n in names if (m := re.match(r"segments/(\d+)/segment-header\.properties$", n))}
        )
        if not indices:
            raise InputError(f"{self._path}: no segments/N/segment-header.properties; not a JPK force file")
        if len(indices) > _MAX_SEGMENTS:
            raise InputError(f"{self._path}: {len(indices)} segments; at most {_MAX_SEGMENTS}")
        self._segments = []  # (name, rate, n, {channel: _Channel})
        for k in indices:
            self._segments.append(self._segment(k, shared, sample_rate_hz))
        used = set()
        for i, (name, rate, n, channels) in enumerate(self._segments):
            if name in used:
                name = f"{name}{i}"
                self._segments[i] = (name, rate, n, channels)
            used.add(name)
        uniform = len({rate for _, rate, _, _ in self._segments}) == 1
        starts = np.cumsum([0] + [n for _, _, n, _ in self._segments])[:-1]
        segments = tuple(
            SegmentSpec(name, int(start) if uniform else 0, n, rate)
            for (name, rate, n, _), start in zip(self._segments, starts)
        )
        metadata = self._metadata(header, segments if uniform else ())
        if segment is not None:
            self._chosen = [select_segment(segments, segment, str(self._path))]
            metadata["segment"] = {"name": segments[self._chosen[0]].name, "index": self._chosen[0]}
            metadata.pop(SEGMENTS_KEY, None)
        elif uniform:
            self._chosen = list(range(len(self._segments)))
        else:
            raise SegmentsAtDifferentRates(
                f"{self._path}: segments at different rates: {describe_segments(segments)}; choose one with --segment",
                segments,
            )
        chosen = [self._segments[i] for i in self._chosen]
        channel_names = list(chosen[0][3])
        for name, _, _, channels in chosen[1:]:
            if list(channels) != channel_names:
                raise InputError(f"{self._path}: segment {name} has channels {list(channels)}, not {channel_names}")
        specs = tuple(ChannelSpec(c, chosen[0][3][c].units) for c in channel_names)
        n_total = sum(n for _, _, n, _ in chosen)
        fmt = "jpk-qi" if self._path.name.lower().endswith(".jpk-qi-series") else "jpk"
        self.info = CaptureInfo(str(self._path), fmt, chosen[0][1], specs, n_total, metadata, (), segments)

    def _segment(self, k: int, shared: dict, sample_rate_hz: float | None):
        where = f"{self._path}: segments/{k}"
        props = self._properties(f"segments/{k}/segment-header.properties")
        n = int(_number(props, "force-segment-header.num-points", where))
        duration = _number(props, "force-segment-header.duration", where)
        if n < 0 or n > (1 << 40):
            raise InputError(f"{where}: num-points {n} is not a segment length")
        rate = sample_rate_hz if sample_rate_hz is not None else (n / duration if duration > 0 else math.nan)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{where}: duration {duration!r} s for {n} points gives no sample rate")
        name = props.get("force-segment-header.settings.style") or props.get("force-segment-header.name.name") or f"segment{k}"
        channels = {}
        for jpk_name in props.get("channels.list", "").split():
            channel = self._channel(k, jpk_name, props, shared, n)
            channels[channel.name] = channel
        if not channels:
            raise InputError(f"{where}: no channels")
        return name, float(rate), n, channels

    def _channel(self, k: int, jpk_name: str, props: dict, shared: dict, n: int) -> _Channel:
        where = f"{self._path}: segments/{k} channel {jpk_name}"
        prefix = f"channel.{jpk_name}."
        own = {key[len(prefix):]: value for key, value in props.items() if key.startswith(prefix)}
        if "lcd-info.*" in own:  # format 2.x: the encoding lives in the shared header
            lcd = f"lcd-info.{own['lcd-info.*']}."
            encoding = {key[len(lcd):]: value for key, value in shared.items() if key.startswith(lcd)}
            if not encoding:
                raise InputError(f"{where}: no {lcd}* in shared-data/header.properties")
            data_type = encoding.get("type", "")
            encoder = {key[len("encoder."):]: v for key, v in encoding.items() if key.startswith("encoder.")}
            raw_type = encoder.get("type") or data_type
        else:  # format 0.x
            encoding = own
            data_type = own.get("data.type", "")
            encoder = {key[len("data.encoder."):]: v for key, v in own.items() if key.startswith("data.encoder.")}
            raw_type = encoder.get("type") or data_type
        name = "deflection" if jpk_name == "vDeflection" else jpk_name
        count = int(_number(own, "data.num-points", where)) if "data.num-points" in own else n
        if count != n:
            raise InputError(f"{where}: {count} points in a segment of {n}")
        if data_type == "raster-data" or ("data.start" in own and "data.step" in own):
            start, step = _number(own, "data.start", where), _number(own, "data.step", where)
            unit = unit_symbol(encoding.get("unit.unit", ""))
            return _Channel(name, None, None, n, [], unit, raster=(start, step))
        dtype = _RAW_TYPES.get(raw_type) or _RAW_TYPES.get(data_type)
        if dtype is None:
            raise InputError(f"{where}: unknown data type {data_type or raw_type!r}")
        member = f"segments/{k}/" + own.get("data.file.name", f"channels/{jpk_name}.dat")
        try:
            entry = self._zip.getinfo(member)
        except KeyError:
            raise InputError(f"{where}: no {member} in the archive") from None
        size = entry.file_size
        if size > _MAX_COMPRESSION * entry.compress_size + (1 << 16):
            raise InputError(f"{where}: {member} claims {size} bytes from {entry.compress_size}; refusing a ZIP bomb")
        if size != n * np.dtype(dtype).itemsize:
            raise InputError(f"{where}: {member} holds {size} bytes, not {n} samples of {np.dtype(dtype).itemsize}")
        steps, unit = self._chain(encoding, encoder, name, where)
        return _Channel(name, member, dtype, n, steps, unit)

    def _chain(self, encoding: dict, encoder: dict, name: str, where: str):
        """Linear (multiplier, offset) steps from raw to the target conversion, and its unit."""
        steps = []
        unit = ""
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
        while target and target != base and target not in seen:
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
        return steps, unit_symbol(unit)

    def _metadata(self, header: dict, segments: tuple[SegmentSpec, ...]) -> dict:
        instrument: dict = {"vendor_format": "JPK", "file_format_version": header.get("file-format-version", "")}
        for key, value in header.items():
            if key.endswith("description.instrument") and value:
                instrument["instrument"] = value
            elif key.endswith("description.source-software") and value:
                instrument["software_version"] = value
        metadata: dict = {"instrument": instrument}
        cantilever = {}
        deflection = self._segments[0][3].get("deflection")
        if deflection is not None:
            props = self._calibration()
            if props.get("distance"):
                cantilever["deflection_sensitivity_nm_per_v"] = props["distance"] * 1e9  # m/V in the file
            if props.get("force"):
                cantilever["spring_constant_n_per_m"] = props["force"]
        if cantilever:
            metadata["cantilever"] = cantilever
        if segments:
            metadata[SEGMENTS_KEY] = segments_metadata(segments)
        return metadata

    def _calibration(self) -> dict[str, float]:
        """The deflection's distance (m/V) and force (N/m) multipliers, where defined."""
        shared = self._properties("shared-data/header.properties", required=False)
        props = self._properties(f"segments/{self._first_index()}/segment-header.properties")
        own = {key[len("channel.vDeflection."):]: v for key, v in props.items() if key.startswith("channel.vDeflection.")}
        if "lcd-info.*" in own:
            lcd = f"lcd-info.{own['lcd-info.*']}."
            own = {key[len(lcd):]: v for key, v in shared.items() if key.startswith(lcd)}
        found = {}
        for step in ("distance", "force"):
            key = f"conversion-set.conversion.{step}.scaling.multiplier"
            if own.get(f"conversion-set.conversion.{step}.defined") == "true" and key in own:
                try:
                    value = float(own[key])
                except ValueError:
                    continue
                if math.isfinite(value) and value > 0:
                    found[step] = value
        return found

    def _first_index(self) -> int:
        names = [m.filename for m in self._zip.infolist()]
        return min(int(m.group(1)) for n in names if (m := re.match(r"segments/(\d+)/segment-header\.properties$", n)))

    # -- samples -------------------------------------------------------------------------------
    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        done = 0
        for index in self._chosen:
            name, _, n, segment_channels = self._segments[index]
            handles = {}
            try:
                for c in channels:
                    member = segment_channels[c].member
                    handles[c] = self._zip.open(member) if member is not None else None
                for lo in range(0, n, block_samples):
                    count = min(block_samples, n - lo)
                    data = {c: self._read(segment_channels[c], handles[c], lo, count) for c in channels}
                    yield Chunk(done, data)
                    done += count
            except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError, RuntimeError, NotImplementedError) as exc:
                raise InputError(f"{self._path}: cannot read segment {name} ({_first_line(exc)})") from None
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


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]
