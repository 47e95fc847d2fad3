"""NI TDMS files (``.tdms``) from DAQmx and LabVIEW, read with npTDMS.

The file is opened in npTDMS's streaming mode (``TdmsFile.open``): only the
metadata is read up front, and samples are read block by block with
``read_data(offset, length)``, which applies the file's scaling chain
(``NI_Scale[n]_...``, e.g. DAQmx raw int16 x ``Linear_Slope`` +
``Linear_Y_Intercept``) and returns physical values.

Every channel holding samples becomes a capture channel, named by its TDMS
channel name (``group.channel`` when the file has more than one group: a ``/``
would become an HDF5 path on conversion).
The sample rate is 1 / ``wf_increment`` (s), which every channel must carry
and share; units come from ``unit_string`` (NI's long names such as
``Volts`` are written as their symbols; no value is converted).

npTDMS reads a truncated or damaged file as far as it can and says so only
in a log warning ("Last segment metadata is incomplete", "Cropping data");
this reader turns any such warning into an error, so a cut file is refused
rather than read short.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.unit_names import unit_symbol

__all__ = ["TdmsReader"]

# Relative spread allowed between the channels' wf_increment (they are float64 copies of one clock).
_RATE_TOLERANCE = 1e-9

# What npTDMS raises on a damaged file, at any depth of its parser.
_TDMS_ERRORS = (
    ValueError, struct.error, KeyError, IndexError, EOFError, TypeError, OverflowError, UnicodeDecodeError,
    NotImplementedError,  # a damaged type code: "Unsupported data type to read"
    MemoryError,
)


class _WarningTrap(logging.Filter):
    """Keeps npTDMS's warnings, its only sign of a truncated file, off stderr and for the error."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.messages.append(record.getMessage())
        return False


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]


class TdmsReader(ReaderBase):
    """Read an NI TDMS file as a capture, streamed.

    Parameters
    ----------
    path : Path
        The ``.tdms`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides (or supplies) 1 / ``wf_increment``.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        from nptdms import TdmsFile
        from nptdms.log import log_manager

        self._path = Path(path)
        self._trap = _WarningTrap()
        # npTDMS writes through one shared console handler; the trap sits on it while the file is open.
        self._handler = log_manager.console_handler
        self._handler.addFilter(self._trap)
        self._file = None
        try:
            try:
                self._file = TdmsFile.open(str(self._path))
                self._check_warnings()
                self._channels = self._find_channels()
                self.info = self._make_info(sample_rate_hz)
            except OSError as exc:
                raise InputError(f"{self._path}: cannot read ({exc.strerror or _first_line(exc)})") from None
            except _TDMS_ERRORS as exc:
                raise InputError(f"{self._path}: not a readable TDMS file ({_first_line(exc)})") from None
        except BaseException:
            self.close()
            raise

    def _check_warnings(self) -> None:
        if self._trap.messages:
            raise InputError(f"{self._path}: truncated or damaged TDMS file ({self._trap.messages[0]})")

    def _find_channels(self) -> dict:
        groups = [g for g in self._file.groups() if any(len(c) for c in g.channels())]
        channels = {}
        for group in groups:
            for channel in group.channels():
                if len(channel) == 0:
                    continue
                name = channel.name if len(groups) == 1 else f"{group.name}.{channel.name}"
                if channel.dtype is None or np.dtype(channel.dtype).kind not in "fiu":
                    raise InputError(f"{self._path}: TDMS channel {name!r} holds {channel.dtype}, not numbers")
                channels[name] = channel
        if not channels:
            raise InputError(f"{self._path}: the TDMS file has no channel with samples")
        lengths = {len(c) for c in channels.values()}
        if len(lengths) != 1:
            raise InputError(f"{self._path}: TDMS channels have different lengths {sorted(lengths)}")
        return channels

    def _make_info(self, sample_rate_hz: float | None) -> CaptureInfo:
        if sample_rate_hz is None:
            rates = {}
            for name, channel in self._channels.items():
                increment = channel.properties.get("wf_increment")
                try:
                    increment = float(increment)
                except (TypeError, ValueError):
                    increment = math.nan
                if not (math.isfinite(increment) and increment > 0):
                    raise InputError(
                        f"{self._path}: TDMS channel {name!r} has no sample interval (wf_increment); give --sample-rate"
                    )
                rates[name] = 1.0 / increment
            sample_rate_hz = next(iter(rates.values()))
            if any(abs(r - sample_rate_hz) > _RATE_TOLERANCE * sample_rate_hz for r in rates.values()):
                raise InputError(f"{self._path}: TDMS channels have different sample rates {sorted(set(rates.values()))}")
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise InputError(f"{self._path}: sample rate {sample_rate_hz!r} must be a positive number")
        specs = []
        for name, channel in self._channels.items():
            unit = str(channel.properties.get("unit_string", "") or "").strip()
            specs.append(ChannelSpec(name, unit_symbol(unit)))
        first = next(iter(self._channels.values()))
        instrument: dict = {"vendor_format": "NI TDMS"}
        if self._file.properties.get("name"):
            instrument["name"] = str(self._file.properties["name"])
        if "wf_start_time" in first.properties:
            instrument["recorded"] = str(first.properties["wf_start_time"])
        n = len(first)
        return CaptureInfo(str(self._path), "tdms", float(sample_rate_hz), tuple(specs), n, {"instrument": instrument})

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        for start in range(0, n, block_samples):
            length = min(block_samples, n - start)
            data = {}
            for name in channels:
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
                    raise InputError(f"{self._path}: {name} ends at sample {start + len(values)}, before {n}")
                data[name] = values
            yield Chunk(start, data)

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        if getattr(self, "_trap", None) is not None:
            self._handler.removeFilter(self._trap)
            self._trap = None
