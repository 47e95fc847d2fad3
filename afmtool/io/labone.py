"""Zurich Instruments LabOne saved data: HDF5 files and CSV exports.

No real LabOne file was available to this project; the layouts below are
LabOne's as documented for its data structures (a demodulator sample is
``timestamp`` in clock ticks plus ``x``, ``y``, ``frequency``, ``phase``,
...; a scope shot is a wave with its sample interval ``dt``), and the tests
build such files with h5py and csv.  A real file that departs from them is
refused with a message naming what is missing, never misread.

HDF5 (``.h5``; chosen over the afmtool layout when there is no ``/channels``
group and LabOne's groups are present)::

    /000/dev1234/demods/0/sample/    a chunk of demodulator samples
        timestamp                    uint64, device clock ticks
        x, y, r, theta, frequency, phase, auxin0, auxin1   (those present)
        clockbase                    attribute (Hz) here, on a header/ group
                                     or dataset here, or on any parent
    /001/dev1234/demods/0/sample/    the next chunk (appended in order)
    /000/dev1234/scopes/0/wave/      one scope shot
        wave                         (channels, samples) or (samples,)
        attributes dt (s), channelscaling (per channel, optional)

CSV (``.csv``, semicolon-separated, as the LabOne UI saves
``dev1234_demods_0_sample_00000.csv``)::

    chunk;timestamp;x;y;frequency;phase
    0;123456000;1.2e-3;-4.0e-4;70000;0.1

with the clockbase from a ``# clockbase: 60000000`` line, or from the
``clockbase`` column of the header file LabOne writes beside it
(``dev1234_demods_0_sample_header_00000.csv``).

Timestamps become seconds through the clockbase (t = ticks / clockbase, Hz);
the sample rate is the mean rate they imply, and they must be uniform.  A
file without a clockbase is refused.  Units are LabOne's for each field
(x, y, r and aux inputs in V, theta in deg, frequency in Hz, oscillator
phase in rad; scope channels in V after ``channelscaling``).

The demodulator samples and each scope shot are segments: with more than
one, ``--segment demods`` or ``--segment scope0`` chooses.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.csv import CsvReader

__all__ = ["LaboneHdf5Reader", "LaboneCsvReader", "sniff_labone", "FIELD_UNITS"]

#: Demodulator sample fields read as channels, and their units in LabOne.
FIELD_UNITS = {
    "x": "V",
    "y": "V",
    "r": "V",
    "theta": "deg",
    "frequency": "Hz",
    "phase": "rad",
    "auxin0": "V",
    "auxin1": "V",
}

#: Most HDF5 objects looked at when telling a LabOne file from another HDF5 file.
_SNIFF_OBJECTS = 2000
#: Largest ratio of claimed dataset bytes to file bytes (no LabOne data is that compressible).
_MAX_CLAIM_RATIO = 1000
# Uniform timestamps: within this fraction of a sample period of t0 + n / fs.
_T_TOLERANCE_PERIODS = 0.1


def sniff_labone(path: Path, fmt: str) -> str:
    """``"labone-hdf5"``/``"labone-csv"`` when ``path`` (of suffix format ``fmt``) is LabOne's, else ``fmt``."""
    if fmt == "csv":
        return "labone-csv" if _csv_header_is_labone(path) else fmt
    if fmt == "hdf5":
        return "labone-hdf5" if _hdf5_is_labone(path) else fmt
    return fmt


def _csv_header_is_labone(path: Path) -> bool:
    try:
        with open(path, "rb") as handle:
            head = handle.read(1 << 16).decode("latin-1")
    except OSError:
        return False
    for line in head.replace("\r", "\n").split("\n"):
        line = line.strip().lstrip("\ufeff").lstrip("ï»¿")
        if not line or line.startswith("#"):
            continue
        fields = [f.strip().strip('"') for f in line.split(";")]
        return len(fields) > 1 and "timestamp" in fields
    return False


def _hdf5_is_labone(path: Path) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            if "channels" in h5:
                return False
            return bool(_find_groups(h5, limit=_SNIFF_OBJECTS))
    except (OSError, RuntimeError, KeyError, ValueError, TypeError):
        return False  # the HDF5 reader reports what is wrong with it


class _Limit(Exception):
    pass


def _find_groups(h5, limit: int | None = None) -> dict[str, list[tuple[str, object]]]:
    """LabOne's data groups by kind: ``{"demods": [(path, group)], "scopes": [...]}``, in path order.

    ``visititems`` follows hard links only, so nothing behind a soft or
    external link is found.
    """
    import h5py

    found: dict[str, list] = {"demods": [], "scopes": []}
    count = [0]

    def visit(name: str, obj) -> None:
        count[0] += 1
        if limit is not None and count[0] > limit:
            raise _Limit
        if not isinstance(obj, h5py.Group):
            return
        keys = set(obj.keys())
        if "timestamp" in keys and keys & set(FIELD_UNITS):
            found["demods"].append((name, obj))
        elif name.endswith("wave") and "wave" in keys and re.search(r"(^|/)scopes/\d+/wave$", name):
            found["scopes"].append((name, obj))

    try:
        h5.visititems(visit)
    except _Limit:
        pass
    for kind in found:
        found[kind].sort(key=lambda item: item[0])
    return {k: v for k, v in found.items() if v}


def _clockbase_hdf5(group) -> float | None:
    """The clockbase (Hz) for a sample group: on it, its header, or a parent."""
    import h5py

    node = group
    while True:
        if "clockbase" in node.attrs:
            return _positive(node.attrs["clockbase"])
        for holder in ("clockbase", "header/clockbase"):
            obj = node.get(holder, getlink=True)
            if isinstance(obj, h5py.HardLink) and isinstance(node.get(holder), h5py.Dataset):
                dataset = node.get(holder)
                if dataset.size == 1:
                    return _positive(dataset[()])
        header = node.get("header", getlink=True)
        if isinstance(header, h5py.HardLink) and isinstance(node.get("header"), h5py.Group):
            if "clockbase" in node["header"].attrs:
                return _positive(node["header"].attrs["clockbase"])
        if node.name == "/":
            return None
        node = node.parent


def _positive(value) -> float | None:
    try:
        value = float(np.asarray(value).reshape(-1)[0])
    except (TypeError, ValueError, IndexError):
        return None
    return value if math.isfinite(value) and value > 0 else None


class LaboneHdf5Reader(ReaderBase):
    """Read LabOne demodulator samples or scope shots from a LabOne HDF5 file.

    Parameters
    ----------
    path : Path
        The file; opened read-only.
    sample_rate_hz : float, optional
        Overrides the rate from the timestamps (or a scope shot's ``dt``).
    segment : str, optional
        ``demods`` or ``scopeN`` (or its number) when the file has several.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, *, segment: str | None = None) -> None:
        import h5py

        from afmtool.io.hdf5 import check_attributes_terminate

        self._path = Path(path)
        try:
            self._file = h5py.File(self._path, "r")
        except OSError as exc:
            raise InputError(f"{path}: not a readable HDF5 file ({str(exc).split('(')[0].strip()})") from None
        try:
            check_attributes_terminate(self._path)
            self._open(sample_rate_hz, segment)
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
            self._file.close()
            raise InputError(f"{self._path}: damaged LabOne HDF5 structure ({_first_line(exc)})") from None
        except BaseException:
            self._file.close()
            raise

    def _open(self, sample_rate_hz: float | None, segment: str | None) -> None:
        from afmtool.io.views import describe_segments, select_segment

        groups = _find_groups(self._file)
        sources = []  # (segment name, kind, [groups])
        if "demods" in groups:
            by_node: dict[str, list] = {}
            for name, group in groups["demods"]:
                node = re.sub(r"^\d+/", "", name)  # chunks 000, 001, ... of one demodulator
                by_node.setdefault(node, []).append(group)
            if len(by_node) > 1:
                nodes = ", ".join(by_node)
                raise InputError(f"{self._path}: demodulator samples from several nodes ({nodes}); afmtool reads one")
            sources.append(("demods", "demods", next(iter(by_node.values()))))
        for k, (_name, group) in enumerate(groups.get("scopes", [])):
            sources.append((f"scope{k}", "scope", [group]))
        if not sources:
            raise InputError(f"{self._path}: no LabOne demodulator samples or scope shots found")
        layouts = [self._layout(name, kind, members, sample_rate_hz) for name, kind, members in sources]
        segments = tuple(SegmentSpec(name, 0, layout["n"], layout["rate"]) for (name, _, _), layout in zip(sources, layouts))
        if segment is not None:
            index = select_segment(segments, segment, str(self._path))
        elif len(segments) == 1:
            index = 0
        else:
            raise InputError(
                f"{self._path}: several LabOne segments: {describe_segments(segments)}; choose one with --segment"
            )
        self._layout_used = layout = layouts[index]
        metadata = {"instrument": {"vendor_format": "Zurich Instruments LabOne HDF5", "source": sources[index][0]}}
        if layout.get("clockbase"):
            metadata["instrument"]["clockbase_hz"] = layout["clockbase"]
        self.info = CaptureInfo(
            str(self._path), "labone-hdf5", layout["rate"], layout["channels"], layout["n"], metadata, (), segments
        )

    def _member(self, group, name: str):
        """``group[name]`` when it is a dataset stored in this file: soft and external links are refused."""
        import h5py

        link = group.get(name, getlink=True)
        if not isinstance(link, h5py.HardLink):
            raise InputError(f"{self._path}: {group.name}/{name} is a {type(link).__name__}; afmtool reads no data "
                             "from outside the capture's own objects")
        dataset = group[name]
        if not isinstance(dataset, h5py.Dataset):
            raise InputError(f"{self._path}: {group.name}/{name} is not a dataset")
        self._check_claim(f"{group.name}/{name}", dataset)
        return dataset

    def _check_claim(self, name: str, dataset) -> None:
        from afmtool.io.hdf5 import _check_local

        _check_local(self._path, name, dataset)
        if dataset.dtype.kind not in "fiu":
            raise InputError(f"{self._path}: {name} holds {dataset.dtype}, not numbers")
        size = max(self._path.stat().st_size, 1)
        if dataset.size * dataset.dtype.itemsize > _MAX_CLAIM_RATIO * size:
            raise InputError(f"{self._path}: {name} claims {dataset.shape} samples, more than the file can hold")

    def _layout(self, name: str, kind: str, members: list, sample_rate_hz: float | None) -> dict:
        if kind == "scope":
            return self._scope_layout(members[0], sample_rate_hz)
        fields = [f for f in FIELD_UNITS if all(f in g for g in members)]
        pieces = []  # (group, length)
        for group in members:
            lengths = set()
            for field in ("timestamp", *fields):
                dataset = self._member(group, field)
                if dataset.ndim != 1:
                    raise InputError(f"{self._path}: {group.name}/{field} must be 1-D, is {dataset.shape}")
                lengths.add(len(dataset))
            if len(lengths) != 1:
                raise InputError(f"{self._path}: {group.name} has fields of different lengths {sorted(lengths)}")
            pieces.append((group, lengths.pop()))
        n = sum(length for _, length in pieces)
        clockbase = _clockbase_hdf5(members[0])
        if clockbase is None:
            raise InputError(f"{self._path}: no clockbase for {members[0].name}; cannot turn timestamps into seconds")
        rate = sample_rate_hz
        first_tick = self._tick(pieces[0][0]["timestamp"][0]) if n else 0
        if rate is None:
            if n < 2:
                raise InputError(f"{self._path}: fewer than 2 demodulator samples; give --sample-rate")
            last_group, last_len = pieces[-1]
            span_ticks = self._tick(last_group["timestamp"][last_len - 1]) - first_tick
            rate = (n - 1) * clockbase / span_ticks if span_ticks > 0 else math.nan
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{self._path}: timestamps give sample rate {rate!r}; they must increase")
        channels = tuple(ChannelSpec(f, FIELD_UNITS[f]) for f in fields)
        return {"kind": "demods", "pieces": pieces, "fields": fields, "n": n, "rate": float(rate),
                "channels": channels, "clockbase": clockbase, "first_tick": first_tick}

    def _tick(self, value) -> int:
        """One timestamp as an exact integer; a NaN or infinite one (a float dataset) is refused."""
        value = np.asarray(value).reshape(-1)[0]
        if value.dtype.kind == "f" and not np.isfinite(value):
            raise InputError(f"{self._path}: a timestamp is {float(value)!r}, not a clock tick")
        return int(value)

    def _scope_layout(self, group, sample_rate_hz: float | None) -> dict:
        dataset = self._member(group, "wave")
        if dataset.ndim not in (1, 2):
            raise InputError(f"{self._path}: {group.name}/wave must be (channels, samples), is {dataset.shape}")
        n_channels = 1 if dataset.ndim == 1 else dataset.shape[0]
        scaling = np.ones(n_channels)
        if "channelscaling" in group.attrs:
            scaling = np.asarray(group.attrs["channelscaling"], dtype=np.float64).reshape(-1)
            if scaling.size != n_channels or not np.all(np.isfinite(scaling)):
                raise InputError(f"{self._path}: {group.name} channelscaling {scaling.tolist()} does not fit its wave")
        rate = sample_rate_hz
        if rate is None:
            dt = _positive(group.attrs.get("dt"))
            if dt is None:
                raise InputError(f"{self._path}: scope shot {group.name} has no sample interval dt; give --sample-rate")
            rate = 1.0 / dt
        channels = tuple(ChannelSpec(f"ch{i + 1}", "V") for i in range(n_channels))
        return {"kind": "scope", "dataset": dataset, "scaling": scaling, "n": dataset.shape[-1], "rate": float(rate),
                "channels": channels}

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        layout = self._layout_used
        if layout["kind"] == "scope":
            yield from self._scope_blocks(layout, channels, block_samples)
            return
        done = 0
        clockbase, fs = layout["clockbase"], self.info.sample_rate_hz
        for group, length in layout["pieces"]:
            for lo in range(0, length, block_samples):
                hi = min(lo + block_samples, length)
                try:
                    ticks = _ticks_since(np.asarray(group["timestamp"][lo:hi]), layout["first_tick"])
                    data = {name: group[name][lo:hi].astype(np.float64) for name in channels}
                except (OSError, RuntimeError, ValueError) as exc:
                    raise InputError(f"{self._path}: cannot read {group.name} at sample {lo} ({_first_line(exc)})") from None
                expected = (done + np.arange(hi - lo)) / fs
                bad = np.flatnonzero(~(np.abs(ticks / clockbase - expected) <= _T_TOLERANCE_PERIODS / fs))
                if bad.size:
                    i = int(bad[0])
                    raise InputError(f"{self._path}: non-uniform timestamps at sample {done + i} (a gap between chunks?)")
                yield Chunk(done, data)
                done += hi - lo

    def _scope_blocks(self, layout: dict, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        dataset, scaling = layout["dataset"], layout["scaling"]
        for lo in range(0, layout["n"], block_samples):
            hi = min(lo + block_samples, layout["n"])
            try:
                block = np.asarray(dataset[..., lo:hi], dtype=np.float64).reshape(-1, hi - lo)
            except (OSError, RuntimeError, ValueError) as exc:
                raise InputError(f"{self._path}: cannot read {dataset.name} at sample {lo} ({_first_line(exc)})") from None
            data = {}
            for name in channels:
                i = int(name[2:]) - 1
                data[name] = block[i] * scaling[i]
            yield Chunk(lo, data)

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._file.close()


def _ticks_since(raw: np.ndarray, first: int) -> np.ndarray:
    """Clock ticks after ``first`` as float64: exact integer differences where they fit in int64, never an overflow.

    Timestamps are uint64; one at 2^64 - 1 (a damaged or hostile file) made the int64
    arithmetic overflow.  Out-of-range values fall back to a float difference, which the
    uniformity check then refuses.
    """
    if raw.dtype.kind in "iu" and raw.size and abs(first) < 2**62 and int(raw.max()) < 2**62 and int(raw.min()) > -(2**62):
        return (raw.astype(np.int64) - np.int64(first)).astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        return raw.astype(np.float64) - float(first)


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]


def _sibling_header_clockbase(path: Path) -> float | None:
    """The ``clockbase`` column of LabOne's header file beside a sample CSV, if there is one."""
    match = re.match(r"^(?P<stem>.*)_(?P<n>\d+)\.csv$", path.name)
    candidates = []
    if match:
        candidates.append(path.with_name(f"{match['stem']}_header_{match['n']}.csv"))
    candidates.append(path.with_name(f"{path.stem}_header.csv"))
    for candidate in candidates:
        if not candidate.is_file():
            continue
        try:
            lines = candidate.read_bytes()[: 1 << 20].decode("latin-1").replace("\r", "\n").split("\n")
        except OSError:
            continue
        lines = [ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")]
        if len(lines) < 2:
            continue
        names = [f.strip().strip('"') for f in lines[0].split(";")]
        values = lines[1].split(";")
        if "clockbase" in names and len(values) == len(names):
            return _positive_text(values[names.index("clockbase")])
    return None


def _positive_text(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


class LaboneCsvReader(CsvReader):
    """Read a LabOne CSV export of demodulator samples: a CSV whose time is ``timestamp`` in clock ticks."""

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        self._labone_path = Path(path)
        super().__init__(path, sample_rate_hz)

    def _set_columns(self, fields: list[str], delimiter: str, comments: dict, units_row: list[str] | None) -> list[str]:
        columns = super()._set_columns(fields, delimiter, comments, units_row)
        if "timestamp" not in columns:
            raise InputError(f"{self._name}: a LabOne CSV needs a timestamp column")
        self._time = "timestamp"
        self._t_relative = 0.0  # integer ticks: no rounding of printed digits to allow for
        for name in columns:
            if not self._header_units.get(name) and name in FIELD_UNITS:
                self._header_units[name] = FIELD_UNITS[name]
        return columns

    def _make_info(self, comments: dict, sample_rate_hz: float | None) -> CaptureInfo:
        clockbase = _positive_text(comments.get("clockbase", "")) or _sibling_header_clockbase(self._labone_path)
        if clockbase is None:
            raise InputError(
                f"{self._name}: no clockbase (a '# clockbase: HZ' line or the header file beside it); "
                "cannot turn timestamps into seconds"
            )
        self._t_scale = 1.0 / clockbase
        info = super()._make_info(comments, sample_rate_hz)
        channels = tuple(c for c in info.channels if c.name != "chunk")
        if not channels:
            raise InputError(f"{self._name}: no sample fields besides chunk and timestamp")
        metadata = dict(info.metadata)
        metadata["instrument"] = {"vendor_format": "Zurich Instruments LabOne CSV", "clockbase_hz": clockbase}
        return CaptureInfo(info.source, "labone-csv", info.sample_rate_hz, channels, None, metadata)
