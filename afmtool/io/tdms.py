"""NI TDMS files (``.tdms``) from DAQmx and LabVIEW, read with npTDMS.

The file is opened in npTDMS's streaming mode (``TdmsFile.open``): only the
metadata is read up front, and samples are read block by block with
``read_data(offset, length)``, which applies the file's scaling chain
(``NI_Scale[n]_...``, e.g. DAQmx raw int16 x ``Linear_Slope`` +
``Linear_Y_Intercept``) and returns physical values.

**The capture is the ``.tdms`` file.**  It is opened through a file handle, so
npTDMS never reads a ``.tdms_index`` lying beside it: an index that disagrees
with its file (other channel names, rate or units) cannot rewrite the capture.

**Groups.**  Every channel holding samples becomes a capture channel, named
by its TDMS channel name, or ``group.channel`` when the file has more than one
group (a ``/`` would become an HDF5 path on conversion).  ``--group NAME``
(or its number from 0) reads one group, its channels by their own names.
Groups whose channels differ in length or rate (a LabVIEW SignalExpress log
with a main group and decimated groups) cannot be read as one capture: one
must be chosen, and ``info`` lists the groups with their rates and lengths.

The sample rate is 1 / ``wf_increment`` (s), which every chosen channel must
carry and share; units come from ``unit_string`` (NI's long names such as
``Volts`` are written as their symbols; no value is converted).

**Scaling chains** are checked before npTDMS follows them: at most
:data:`MAX_SCALES` scales, each input a raw source or an earlier-declared
scale, no cycle (a scale that refers to itself made npTDMS recurse until
RecursionError).  A scale type npTDMS does not apply is reported in one
warning naming it and the channel's raw values are read, as npTDMS does;
for DAQmx raw data, which has no meaning unscaled, the file is refused for
that reason.  Neither is called damaged.

npTDMS reads a truncated or damaged file as far as it can and says so only
in a log warning ("Last segment metadata is incomplete", "Cropping data");
this reader turns any such warning into an error, so a cut file is refused
rather than read short.
"""

from __future__ import annotations

import logging
import math
import re
import struct
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import CaptureWarning, InputError, SelectionNeeded
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.text import clean_label
from afmtool.io.unit_names import unit_symbol

__all__ = ["TdmsReader", "TdmsGroup", "MAX_SCALES"]

# Relative spread allowed between the channels' wf_increment (they are float64 copies of one clock).
_RATE_TOLERANCE = 1e-9

#: Most scales in one channel's chain (DAQmx writes one or two).
MAX_SCALES = 64
#: npTDMS's marker of a scale that reads the raw samples.
_RAW_SOURCE = 0xFFFFFFFF
#: Scale types npTDMS applies (nptdms.scaling); any other is read raw.
_SUPPORTED_SCALES = frozenset({"Polynomial", "Linear", "RTD", "Strain", "Table", "Thermistor", "Thermocouple", "Add",
                               "Subtract", "AdvancedAPI"})
_SCALE_TYPE = re.compile(r"NI_Scale\[(\d+)\]_Scale_Type$")

# What npTDMS raises on a damaged file, at any depth of its parser.
_TDMS_ERRORS = (
    ValueError, struct.error, KeyError, IndexError, EOFError, TypeError, OverflowError, UnicodeDecodeError,
    NotImplementedError,  # a damaged type code: "Unsupported data type to read"
    MemoryError,
)


class TdmsGroup(NamedTuple):
    """One group of a TDMS file: its name, channels, samples and rate (None where its channels differ)."""

    name: str
    channels: tuple[str, ...]
    n_samples: int | None
    sample_rate_hz: float | None

    def describe(self) -> str:
        samples = "mixed lengths" if self.n_samples is None else f"{self.n_samples} samples"
        rate = "mixed rates" if self.sample_rate_hz is None else f"{self.sample_rate_hz:g} Hz"
        return f"{self.name} ({len(self.channels)} channels, {samples}, {rate})"


class _WarningTrap(logging.Filter):
    """Keeps npTDMS's warnings, its only sign of a truncated file, off stderr and for the error."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING and not record.getMessage().startswith("Unsupported scale type"):
            self.messages.append(record.getMessage())  # an unsupported scale is this reader's own warning
        return False


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]


def _increment_rate(channel) -> float | None:
    try:
        increment = float(channel.properties.get("wf_increment"))
    except (TypeError, ValueError, OverflowError):
        return None
    return 1.0 / increment if math.isfinite(increment) and increment > 0 else None


def _scale_count(properties: Mapping) -> int | None:
    """npTDMS's count of scales in ``properties`` (``NI_Number_Of_Scales``, else the largest index + 1), checked."""
    if "NI_Number_Of_Scales" in properties:
        try:
            count = int(properties["NI_Number_Of_Scales"])
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"NI_Number_Of_Scales {properties['NI_Number_Of_Scales']!r} is not a count") from None
    else:
        indices = [int(m.group(1)) for key in properties if (m := _SCALE_TYPE.match(str(key)))]
        count = max(indices) + 1 if indices else None
    if count is not None and not 0 <= count <= MAX_SCALES:
        raise ValueError(f"it declares {count} scales; afmtool follows at most {MAX_SCALES}")
    return count


def _scaling_properties(chain: Sequence[Mapping]) -> Mapping | None:
    """The properties npTDMS takes the scaling from: the first of channel, group, file that has scales."""
    for properties in chain:
        count = _scale_count(properties)
        if count and properties.get("NI_Scaling_Status", "unscaled") != "scaled":
            return properties
    return None


def _inputs(scale) -> list:
    if hasattr(scale, "input_source"):
        return [scale.input_source]
    if hasattr(scale, "left_input_source"):
        return [scale.left_input_source, scale.right_input_source]
    return []  # a DAQmx scaler: reads its own stored data


def _check_graph(scales: Sequence) -> None:
    """Every scale's inputs are the raw data or another scale, and the chain from the last scale has no cycle."""
    n = len(scales)
    if not n:
        return
    state = [0] * n  # 0 not seen, 1 on the current path, 2 done
    stack = [(n - 1, iter(_inputs(scales[n - 1])))]
    state[n - 1] = 1
    while stack:
        index, pending = stack[-1]
        source = next(pending, None)
        if source is None:
            state[index] = 2
            stack.pop()
            continue
        if source == _RAW_SOURCE:
            continue
        if not (isinstance(source, (int, np.integer)) and 0 <= source < n):
            raise ValueError(f"scale {index} reads scale {source!r}, which does not exist")
        if state[source] == 1:
            raise ValueError(f"scale {index} reads scale {source}, which reads it back (a cycle)")
        if state[source] == 0:
            state[source] = 1
            stack.append((int(source), iter(_inputs(scales[source]))))


class TdmsReader(ReaderBase):
    """Read an NI TDMS file (or one of its groups) as a capture, streamed.

    Parameters
    ----------
    path : Path
        The ``.tdms`` file; opened read-only.  A ``.tdms_index`` beside it is not read.
    sample_rate_hz : float, optional
        Overrides (or supplies) 1 / ``wf_increment``.
    group : str, optional
        A group's name, or its number from 0 (``--group``).
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, *, group: str | None = None) -> None:
        from nptdms.log import log_manager

        self._path = Path(path)
        self._trap = _WarningTrap()
        # npTDMS writes through one shared console handler; the trap sits on it while the file is open.
        self._handler = log_manager.console_handler
        self._handler.addFilter(self._trap)
        self._file = self._handle = None
        try:
            self._open(sample_rate_hz, group)
        except BaseException:
            self.close()
            raise

    def _open(self, sample_rate_hz: float | None, group: str | None) -> None:
        from nptdms import TdmsFile

        try:
            # A handle, not a path: npTDMS would read a .tdms_index beside the path instead of the file's metadata.
            self._handle = open(self._path, "rb")  # noqa: SIM115 - closed in close()
            self._file = TdmsFile.open(self._handle)
            self._check_warnings()
            groups = self._groups()
            self._channels, chosen = self._choose(groups, group)
            self.info = self._make_info(sample_rate_hz, groups, chosen)
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        except _TDMS_ERRORS as exc:
            raise InputError(f"{self._path}: not a readable TDMS file ({_first_line(exc)})") from None

    def _check_warnings(self) -> None:
        if self._trap.messages:
            raise InputError(f"{self._path}: truncated or damaged TDMS file ({self._trap.messages[0]})")

    def _groups(self) -> dict[str, dict]:
        """Each group holding samples: its channels (checked: scaling, numeric) by name."""
        groups = {}
        for group in self._file.groups():
            channels = {}
            for channel in group.channels():
                if len(channel) == 0:
                    continue
                name = clean_label(channel.name)
                if name in channels:
                    raise InputError(f"{self._path}: group {group.name!r} has two channels named {name!r}")
                self._check_scaling(channel, group)
                if channel.dtype is None or np.dtype(channel.dtype).kind not in "fiu":
                    raise InputError(f"{self._path}: TDMS channel {name!r} holds {channel.dtype}, not numbers")
                channels[name] = channel
            if channels:
                groups[clean_label(group.name)] = channels
        if not groups:
            raise InputError(f"{self._path}: the TDMS file has no channel with samples")
        return groups

    def _check_scaling(self, channel, group) -> None:
        """Bound and check the channel's scaling chain before npTDMS follows it (see the module's notes)."""
        from nptdms import types
        from nptdms.scaling import get_scaling

        where = f"{self._path}: TDMS channel {channel.name!r}"
        chain = (channel.properties, group.properties, self._file.properties)
        try:
            properties = _scaling_properties(chain)
        except ValueError as exc:
            raise InputError(f"{where}: its scaling cannot be read ({exc})") from None
        if properties is None:
            return
        count = _scale_count(properties)
        kinds = [properties.get(f"NI_Scale[{k}]_Scale_Type") for k in range(count)]
        unsupported = sorted({str(k) for k in kinds if k is not None and k not in _SUPPORTED_SCALES})
        if unsupported:
            if channel.data_type is types.DaqMxRawData:
                raise InputError(f"{where}: DAQmx raw data with scaling {', '.join(unsupported)}, which afmtool "
                                 "cannot apply (npTDMS does not support it); the raw values have no unit")
            warnings.warn(f"{where}: scaling {', '.join(unsupported)} is not supported (npTDMS cannot apply it); "
                          "its raw, unscaled values are read", CaptureWarning, stacklevel=4)
            return
        scaling = get_scaling(*chain)
        try:
            _check_graph(scaling.scalings if scaling is not None else ())
        except ValueError as exc:
            raise InputError(f"{where}: its scaling chain is not sound ({exc})") from None

    def _choose(self, groups: dict[str, dict], group: str | None) -> tuple[dict, TdmsGroup | None]:
        """The channels to read, named as the capture names them, and the chosen group (None: all of them)."""
        described = [self._describe(name, channels) for name, channels in groups.items()]
        listing = "; ".join(f"{i} {g.describe()}" for i, g in enumerate(described))
        if group is not None:
            names = [g.name for g in described]
            if group in names:
                chosen = described[names.index(group)]
            elif group.strip().isdigit() and int(group) < len(described):
                chosen = described[int(group)]
            else:
                raise InputError(f"{self._path}: no group {group!r}; the groups are {listing}")
            return groups[chosen.name], chosen
        if len(groups) == 1:
            return next(iter(groups.values())), described[0]
        lengths = {len(c) for channels in groups.values() for c in channels.values()}
        rates = {_increment_rate(c) for channels in groups.values() for c in channels.values()}
        if len(lengths) > 1 or len(rates) > 1:
            raise SelectionNeeded(
                f"{self._path}: groups at different rates or lengths: {listing}; choose one with --group",
                "--group", tuple(range(len(described))), {"groups": [g._asdict() for g in described]},
            )
        return {f"{g}.{c}": channel for g, channels in groups.items() for c, channel in channels.items()}, None

    @staticmethod
    def _describe(name: str, channels: dict) -> TdmsGroup:
        lengths = {len(c) for c in channels.values()}
        rates = {_increment_rate(c) for c in channels.values()}
        rate = next(iter(rates)) if len(rates) == 1 else None
        return TdmsGroup(name, tuple(channels), next(iter(lengths)) if len(lengths) == 1 else None, rate)

    def _make_info(self, sample_rate_hz: float | None, groups: dict, chosen: TdmsGroup | None) -> CaptureInfo:
        lengths = {len(c) for c in self._channels.values()}
        if len(lengths) != 1:
            where = f" of group {chosen.name!r}" if chosen is not None and len(groups) > 1 else ""
            raise InputError(f"{self._path}: TDMS channels{where} have different lengths {sorted(lengths)}")
        if sample_rate_hz is None:
            sample_rate_hz = self._file_rate()
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise InputError(f"{self._path}: sample rate {sample_rate_hz!r} must be a positive number")
        specs = []
        for name, channel in self._channels.items():
            unit = clean_label(str(channel.properties.get("unit_string", "") or ""))
            specs.append(ChannelSpec(name, unit_symbol(unit)))
        first = next(iter(self._channels.values()))
        instrument: dict = {"vendor_format": "NI TDMS"}
        if self._file.properties.get("name"):
            instrument["name"] = clean_label(str(self._file.properties["name"]))
        if "wf_start_time" in first.properties:
            instrument["recorded"] = str(first.properties["wf_start_time"])
        if chosen is not None and len(groups) > 1:
            instrument["group"] = chosen.name
        if len(groups) > 1:
            instrument["groups"] = [self._describe(name, channels).describe() for name, channels in groups.items()]
        return CaptureInfo(str(self._path), "tdms", float(sample_rate_hz), tuple(specs), lengths.pop(),
                           {"instrument": instrument})

    def _file_rate(self) -> float:
        rates = {}
        for name, channel in self._channels.items():
            rate = _increment_rate(channel)
            if rate is None:
                raise InputError(
                    f"{self._path}: TDMS channel {name!r} has no sample interval (wf_increment); give --sample-rate"
                )
            rates[name] = rate
        rate = next(iter(rates.values()))
        if any(abs(r - rate) > _RATE_TOLERANCE * rate for r in rates.values()):
            raise InputError(f"{self._path}: TDMS channels have different sample rates {sorted(set(rates.values()))}")
        return rate

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        for start in range(0, n, block_samples):
            length = min(block_samples, n - start)
            yield Chunk(start, {name: self._read(name, start, length) for name in channels})

    def _read(self, name: str, start: int, length: int) -> np.ndarray:
        try:
            values = self._channels[name].read_data(start, length)
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read {name} at sample {start} ({exc.strerror})") from None
        except _TDMS_ERRORS as exc:
            raise InputError(f"{self._path}: cannot read {name} at sample {start} ({_first_line(exc)})") from None
        except Exception as exc:  # narrowed at once to npTDMS's bare Exception
            if type(exc) is not Exception:
                raise
            # npTDMS raises the base class itself for a damaged scaling chain
            # ("Invalid scaling input source for DAQmx data")
            raise InputError(f"{self._path}: cannot scale {name} ({_first_line(exc)})") from None
        self._check_warnings()
        values = np.asarray(values, dtype=np.float64)
        if len(values) != length:
            raise InputError(f"{self._path}: {name} ends at sample {start + len(values)}, before {self.info.n_samples}")
        return values

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._handle is not None:
            self._handle.close()
            self._handle = None
        if getattr(self, "_trap", None) is not None:
            self._handler.removeFilter(self._trap)
            self._trap = None
