"""ROS1 and ROS2 bags: one topic per channel, blocks of samples as messages.

Layout::

    /afm/metadata   std_msgs/msg/String, one message: the metadata JSON with two
                    extra keys, "sample_rate_hz" and "channel_units" {name: units}
    /afm/<channel>  std_msgs/msg/Float64MultiArray or Float32MultiArray, each a
                    block of consecutive samples; or std_msgs/msg/Float64, one
                    sample per message

A message's time stamp is the time of its first sample, in ns, counted from
an epoch offset of 1 ns.  Bags are read and written through ``rosbags``: ROS1
``.bag`` files, and ROS2 bags (a directory holding ``metadata.yaml``, or the
``.mcap`` / ``.db3`` file inside it) with mcap or sqlite3 storage.  Bags carry
no ground truth, so :meth:`RosbagReader.truth` is empty and
:meth:`RosbagWriter.write_truth` does nothing.
"""

from __future__ import annotations

import importlib
import json
import math
import numbers
import re
import sqlite3
import struct
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag1 import WriterError as Ros1WriterError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.rosbag2 import WriterError as Ros2WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

from afmtool.errors import AfmtoolError, ConfigError, InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.metadata import load_json, validate_metadata

__all__ = ["METADATA_TOPIC", "TOPIC_PREFIX", "RosbagReader", "RosbagWriter"]

#: Channels live on ``TOPIC_PREFIX + name`` unless mapped with ``--topic``.
TOPIC_PREFIX = "/afm/"
#: The topic holding the metadata JSON (``std_msgs/msg/String``).
METADATA_TOPIC = "/afm/metadata"

#: Message definitions for bags that embed none, and for writing.  The std_msgs
#: types used here have the same definition (and ROS1 md5sum) in ROS1 Noetic.
_TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)

_STRING = "std_msgs/msg/String"
_FLOAT64 = "std_msgs/msg/Float64"
_FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
_FLOAT32_ARRAY = "std_msgs/msg/Float32MultiArray"
_SAMPLE_TYPES = (_FLOAT64_ARRAY, _FLOAT32_ARRAY, _FLOAT64)
_ARRAY_TYPES = {"float64": _FLOAT64_ARRAY, "float32": _FLOAT32_ARRAY}

#: Time stamp of sample 0 (and of the metadata message), in ns.
_T0_NS = 1
#: Bag time stamps are int64 nanoseconds.
_MAX_STAMP_NS = float(2**63 - 2**11)
_CHANNEL_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def _dependency_errors() -> tuple[type[Exception], ...]:
    """Error classes of rosbags' storage back ends (apsw, zstd), where installed."""
    found = []
    for module, name in (("apsw", "Error"), ("compression.zstd", "ZstdError"), ("backports.zstd", "ZstdError")):
        try:
            found.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError):
            continue
    return tuple(found)


# What rosbags and the decoders under it raise on a corrupt or truncated bag.
# It does not validate every length field, so plain decoding errors (struct,
# lookups, asserts) escape it as well; all of them are the input's fault.
_BAG_ERRORS = (
    AnyReaderError,
    Ros1ReaderError,
    Ros2ReaderError,
    SerdeError,
    TypesysError,
    *_dependency_errors(),
    sqlite3.Error,
    OSError,
    EOFError,
    struct.error,
    ValueError,
    LookupError,
    ArithmeticError,
    TypeError,
    AssertionError,
    RuntimeError,
    MemoryError,  # a corrupt length field makes rosbags read(2**60)
)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, MemoryError):
        return "a record is too large to load; corrupt length field?"
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


@contextmanager
def _bag_errors(path: Path, what: str) -> Iterator[None]:
    """Turn whatever rosbags raises into a one-line :class:`InputError`."""
    try:
        yield
    except _BAG_ERRORS as exc:
        raise InputError(f"{path}: {what} ({_reason(exc)})") from None


# --------------------------------------------------------------------------- #
# Sample buffering, shared by the reader and the writer
# --------------------------------------------------------------------------- #


class _SampleQueue:
    """A FIFO of 1-D sample arrays, taken out in blocks of any length."""

    def __init__(self, dtype: str = "float64") -> None:
        self._pieces: deque[np.ndarray] = deque()
        self._size = 0
        self._dtype = np.dtype(dtype)

    def __len__(self) -> int:
        return self._size

    def push(self, values: np.ndarray) -> None:
        if len(values):
            self._pieces.append(values)
            self._size += len(values)

    def take(self, n: int) -> np.ndarray:
        """Remove the first ``n`` samples (``n <= len(self)``), as a new array."""
        out = np.empty(n, dtype=self._dtype)
        filled = 0
        while filled < n:
            piece = self._pieces[0]
            k = min(n - filled, len(piece))
            out[filled : filled + k] = piece[:k]
            if k == len(piece):
                self._pieces.popleft()
            else:
                self._pieces[0] = piece[k:]
            filled += k
        self._size -= n
        return out


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class _ChannelTopic:
    """A channel's topic and the bag connections that carry it."""

    name: str
    topic: str
    connections: tuple[Connection, ...]

    @property
    def one_sample_per_message(self) -> bool:
        return all(c.msgtype == _FLOAT64 for c in self.connections)


def _open_bag(path: Path) -> AnyReader:
    if not path.exists():
        raise InputError(f"{path}: no such file")
    with _bag_errors(path, "not a readable bag"):
        bag = AnyReader([path], default_typestore=_TYPESTORE)
        bag.open()
    return bag


def _default_channel(topic: str) -> str | None:
    """``"/afm/deflection"`` -> ``"deflection"``; None for other topics."""
    if topic == METADATA_TOPIC or not topic.startswith(TOPIC_PREFIX):
        return None
    name = topic[len(TOPIC_PREFIX) :]
    return name if name and "/" not in name else None


def _decode_samples(bag: AnyReader, raw: bytes, msgtype: str) -> np.ndarray:
    """The samples of one message; a read-only view where possible."""
    message = bag.deserialize(raw, msgtype)
    if msgtype == _FLOAT64:
        return np.array([message.data], dtype=np.float64)
    # data_offset counts padding elements at the front of data (std_msgs doc)
    return np.asarray(message.data)[message.layout.data_offset :]


def _split_metadata(raw: object, path: Path) -> tuple[object, object, dict]:
    """Pop ``sample_rate_hz`` and ``channel_units`` off the metadata JSON."""
    if not isinstance(raw, dict):
        raise InputError(f"{path}: {METADATA_TOPIC} must hold a JSON object, got {type(raw).__name__}")
    rest = dict(raw)
    sample_rate_hz = rest.pop("sample_rate_hz", None)
    channel_units = rest.pop("channel_units", {})
    try:
        metadata = validate_metadata(rest)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    return sample_rate_hz, channel_units, metadata


def _check_units(value: object, path: Path) -> dict[str, str]:
    if not isinstance(value, dict) or not all(isinstance(u, str) for u in value.values()):
        raise InputError(f"{path}: metadata channel_units must be an object of strings, got {value!r}")
    return value


def _check_sample_rate(value: object, path: Path) -> float:
    if value is None:
        raise InputError(
            f"{path}: no sample rate; give --sample-rate or put sample_rate_hz in the {METADATA_TOPIC} JSON"
        )
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        raise InputError(f"{path}: sample rate {value!r} must be a positive number")
    return float(value)


class RosbagReader(ReaderBase):
    """Read a capture from a ROS1 or ROS2 bag, streaming.

    Parameters
    ----------
    path : Path
        A ROS1 ``.bag`` file, a ROS2 bag directory, or the ``.mcap`` /
        ``.db3`` storage file inside one.
    topic_map : mapping of str to str, optional
        Channel name to topic, for bags that do not follow the
        ``/afm/<channel>`` convention.  Mapped channels use the given topic;
        the bag's other ``/afm/<channel>`` topics are channels too.
    sample_rate_hz : float, optional
        Sample rate in Hz; overrides (or supplies) ``sample_rate_hz`` from
        the ``/afm/metadata`` JSON.

    Notes
    -----
    Samples arrive as messages of all channels interleaved by time stamp.
    :meth:`blocks` keeps one queue per channel and yields as soon as every
    requested channel has a block, so memory is bounded by the block size
    plus the time skew between topics, never by the capture length.  Opening
    makes one pass over the array messages to count samples (nothing kept).
    """

    def __init__(
        self,
        path: Path,
        topic_map: Mapping[str, str] | None = None,
        sample_rate_hz: float | None = None,
    ) -> None:
        self._path = Path(path)
        self._bag: AnyReader | None = _open_bag(self._path)
        try:
            self._channels = self._find_channels(topic_map)
            self.info = self._make_info(sample_rate_hz)
        except BaseException:
            self.close()
            raise

    # -- opening ------------------------------------------------------------ #

    def _find_channels(self, topic_map: Mapping[str, str] | None) -> dict[str, _ChannelTopic]:
        path, bag = self._path, self._bag
        by_topic: dict[str, list[Connection]] = {}
        for connection in bag.connections:  # first-seen order is the writer's channel order
            by_topic.setdefault(connection.topic, []).append(connection)
        mapping = dict(topic_map or {})
        for name, topic in mapping.items():
            if topic not in by_topic:
                raise InputError(f"{path}: no topic {topic!r} for channel {name!r}; topics: {', '.join(by_topic)}")
        if len(set(mapping.values())) != len(mapping):
            raise InputError(f"{path}: --topic maps several channels to one topic: {mapping}")
        claimed = set(mapping.values())
        for topic in by_topic:
            name = _default_channel(topic)
            if name is not None and name not in mapping and topic not in claimed:
                mapping[name] = topic
        if not mapping:
            raise InputError(
                f"{path}: no channel topics (expected {TOPIC_PREFIX}<channel>, or map one with --topic NAME=/topic)"
            )
        order = {topic: i for i, topic in enumerate(by_topic)}
        channels = [_ChannelTopic(n, t, tuple(by_topic[t])) for n, t in mapping.items()]
        for channel in channels:
            self._check_types(channel)
        return {c.name: c for c in sorted(channels, key=lambda c: order[c.topic])}

    def _check_types(self, channel: _ChannelTopic) -> None:
        for connection in channel.connections:
            if connection.msgtype not in _SAMPLE_TYPES:
                raise InputError(
                    f"{self._path}: topic {channel.topic} (channel {channel.name}) has message type "
                    f"{connection.msgtype}; expected one of {', '.join(_SAMPLE_TYPES)}"
                )

    def _make_info(self, sample_rate_hz: float | None) -> CaptureInfo:
        path = self._path
        json_rate, units, metadata = _split_metadata(self._read_metadata_json(), path)
        units = _check_units(units, path)
        rate = _check_sample_rate(sample_rate_hz if sample_rate_hz is not None else json_rate, path)
        specs = tuple(ChannelSpec(name, units.get(name, "")) for name in self._channels)
        fmt = "ros2" if self._bag.is2 else "ros1"
        return CaptureInfo(str(path), fmt, rate, specs, self._count_samples(), metadata)

    def _read_metadata_json(self) -> object:
        """The first ``/afm/metadata`` message, parsed; ``{}`` when there is none."""
        path, bag = self._path, self._bag
        connections = [c for c in bag.connections if c.topic == METADATA_TOPIC]
        if not connections:
            return {}
        if any(c.msgtype != _STRING for c in connections):
            types = sorted({c.msgtype for c in connections})
            raise InputError(f"{path}: {METADATA_TOPIC} has message type {', '.join(types)}; expected {_STRING}")
        with _bag_errors(path, f"cannot read {METADATA_TOPIC}"):
            messages = bag.messages(connections=connections)
            try:
                first = next(messages, None)
            finally:
                messages.close()
            if first is None:
                return {}
            text = bag.deserialize(first[2], first[0].msgtype).data
        return load_json(text, str(path), METADATA_TOPIC)  # bounded: a deeply nested array gave RecursionError

    def _count_samples(self) -> int:
        """Samples per channel: message counts for Float64 topics, one pass for arrays."""
        counts = {c.name: sum(k.msgcount for k in c.connections) for c in self._channels.values()}
        arrays = [name for name, c in self._channels.items() if not c.one_sample_per_message]
        counts.update(dict.fromkeys(arrays, 0))
        for name, samples in self._samples(arrays):
            counts[name] += len(samples)
        if len(set(counts.values())) != 1:
            lengths = ", ".join(f"{name}={n}" for name, n in counts.items())
            raise InputError(f"{self._path}: channels have different lengths ({lengths})")
        return next(iter(counts.values()))

    # -- streaming ---------------------------------------------------------- #

    def _samples(self, names: Sequence[str]) -> Iterator[tuple[str, np.ndarray]]:
        """``(channel, samples)`` per message of ``names``, in bag time order."""
        if not names:
            return
        path, bag = self._path, self._bag
        channel_of = {self._channels[n].topic: n for n in names}
        connections = [k for n in names for k in self._channels[n].connections]
        with _bag_errors(path, "corrupt bag"):
            messages = bag.messages(connections=connections)
        try:
            while True:
                with _bag_errors(path, "corrupt bag"):
                    item = next(messages, None)
                    if item is None:
                        return
                    connection, _, raw = item
                    samples = _decode_samples(bag, raw, connection.msgtype)
                yield channel_of[connection.topic], samples
        finally:
            messages.close()

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        """Yield aligned float64 blocks of ``channels``, ``block_samples`` long but the last."""
        names = list(channels)
        for name in names:
            if name not in self._channels:
                raise InputError(f"{self._path}: no channel {name!r}; channels: {', '.join(self._channels)}")
        if block_samples < 1:
            raise ValueError(f"{block_samples=} must be >= 1")
        queues = {name: _SampleQueue() for name in names}
        start = 0
        for name, samples in self._samples(names):
            queues[name].push(samples)
            while len(queues[name]) >= block_samples and all(len(q) >= block_samples for q in queues.values()):
                yield Chunk(start, {n: q.take(block_samples) for n, q in queues.items()})
                start += block_samples
        yield from self._last_block(queues, start)

    def _last_block(self, queues: dict[str, _SampleQueue], start: int) -> Iterator[Chunk]:
        lengths = {start + len(q) for q in queues.values()}
        if lengths and lengths != {self.info.n_samples}:
            found = ", ".join(f"{n}={start + len(q)}" for n, q in queues.items())
            raise InputError(
                f"{self._path}: channel lengths changed since opening ({found}; expected {self.info.n_samples})"
            )
        rest = len(next(iter(queues.values()))) if queues else 0
        if rest:
            yield Chunk(start, {n: q.take(rest) for n, q in queues.items()})

    def truth(self) -> dict[str, np.ndarray]:
        """Bags carry no simulator ground truth."""
        return {}

    def close(self) -> None:
        bag, self._bag = self._bag, None
        if bag is not None:
            try:
                bag.close()
            except _BAG_ERRORS:
                pass


# --------------------------------------------------------------------------- #
# Writing
# --------------------------------------------------------------------------- #


def _check_writer_args(
    sample_rate_hz: float,
    channels: Sequence[ChannelSpec],
    version: str,
    storage: str,
    dtype: str,
    block_samples: int,
) -> None:
    """Refuse bad writer arguments before anything is created on disk."""
    if version not in ("ros1", "ros2"):
        raise ConfigError(f"{version=} must be 'ros1' or 'ros2'")
    if storage not in ("mcap", "sqlite3"):
        raise ConfigError(f"{storage=} must be 'mcap' or 'sqlite3'")
    if dtype not in _ARRAY_TYPES:
        raise ConfigError(f"{dtype=} must be 'float64' or 'float32'")
    if isinstance(block_samples, bool) or not isinstance(block_samples, numbers.Integral) or block_samples < 1:
        raise ConfigError(f"{block_samples=} must be an integer >= 1")
    if not (isinstance(sample_rate_hz, numbers.Real) and math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ConfigError(f"{sample_rate_hz=} must be a positive number")
    names = [c.name for c in channels]
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"channels {names} must be one or more distinct names")
    for name in names:
        if not _CHANNEL_NAME.fullmatch(name) or TOPIC_PREFIX + name == METADATA_TOPIC:
            raise ConfigError(
                f"channel name {name!r} cannot be a topic {TOPIC_PREFIX}{name}: use letters, digits and _, "
                "starting with a letter, and not 'metadata'"
            )


def _open_writer(path: Path, version: str, storage: str) -> Ros1Writer | Ros2Writer:
    try:
        if version == "ros1":
            _remove_placeholder(path)
            bag = Ros1Writer(path)
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            bag = Ros2Writer(path, version=Ros2Writer.VERSION_LATEST, storage_plugin=plugin)
        bag.open()
    except (Ros1WriterError, Ros2WriterError):
        raise AfmtoolError(f"{path}: exists already; bags are never overwritten") from None
    except OSError as exc:
        raise AfmtoolError(f"{path}: cannot create ({exc.strerror or exc})") from None
    return bag


def _remove_placeholder(path: Path) -> None:
    """Remove an empty regular file at ``path`` so that rosbags can create it.

    Callers that write atomically hand over a freshly created, empty
    temporary file (``afmtool.runtime.atomic``); rosbags only creates new
    paths.  Anything else that exists is left alone, and refused by rosbags.
    """
    if path.is_file() and not path.is_symlink() and path.stat().st_size == 0:
        path.unlink()


def _array_message(values: np.ndarray, msgtype: str) -> object:
    types = _TYPESTORE.types
    n = len(values)
    dim = types["std_msgs/msg/MultiArrayDimension"](label="samples", size=n, stride=n)
    layout = types["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
    return types[msgtype](layout=layout, data=values)


class RosbagWriter:
    """Write a capture as a ROS1 or ROS2 bag, block by block.

    Parameters
    ----------
    path : Path
        The ``.bag`` file (ROS1) or the bag directory (ROS2) to create.  An
        existing path is refused, never overwritten, except an empty file at
        a ROS1 path (the placeholder of an atomic temporary path), which is
        replaced.
    sample_rate_hz : float
        Sample rate in Hz, stored in the ``/afm/metadata`` JSON.
    channels : sequence of ChannelSpec
        One topic ``/afm/<name>`` each; units go to ``channel_units`` in the
        metadata JSON, since bags have no native units.
    metadata : mapping, optional
        Capture metadata, written as JSON on ``/afm/metadata``.
    version : {"ros1", "ros2"}
        Bag format.
    storage : {"mcap", "sqlite3"}, default "mcap"
        ROS2 storage plugin; ignored for ROS1.
    dtype : {"float64", "float32"}, default "float64"
        ``Float64MultiArray`` (samples round-trip exactly) or
        ``Float32MultiArray`` (half the size, float32 rounding).
    block_samples : int, default 1000
        Samples per message; the last message of each channel may be shorter.
    """

    def __init__(
        self,
        path: Path,
        sample_rate_hz: float,
        channels: Sequence[ChannelSpec],
        metadata: Mapping | None = None,
        *,
        version: Literal["ros1", "ros2"],
        storage: Literal["mcap", "sqlite3"] = "mcap",
        dtype: Literal["float64", "float32"] = "float64",
        block_samples: int = 1000,
    ) -> None:
        _check_writer_args(sample_rate_hz, channels, version, storage, dtype, block_samples)
        self._path = Path(path)
        self._fs = float(sample_rate_hz)
        self._block = int(block_samples)
        self._dtype = np.dtype(dtype)
        self._msgtype = _ARRAY_TYPES[dtype]
        self._serialize = _TYPESTORE.serialize_ros1 if version == "ros1" else _TYPESTORE.serialize_cdr
        self._pending = {c.name: _SampleQueue(dtype) for c in channels}
        self._written = 0
        self._bag: Ros1Writer | Ros2Writer | None = _open_writer(self._path, version, storage)
        try:
            meta_connection = self._bag.add_connection(METADATA_TOPIC, _STRING, typestore=_TYPESTORE)
            self._connections = {
                c.name: self._bag.add_connection(TOPIC_PREFIX + c.name, self._msgtype, typestore=_TYPESTORE)
                for c in channels
            }
            self._write_metadata(meta_connection, channels, metadata)
        except BaseException:
            self._abort()
            raise

    def _write_metadata(
        self, connection: Connection, channels: Sequence[ChannelSpec], metadata: Mapping | None
    ) -> None:
        document = dict(metadata or {})
        document["sample_rate_hz"] = self._fs
        document["channel_units"] = {c.name: c.units for c in channels}
        message = _TYPESTORE.types[_STRING](data=json.dumps(document))
        self._bag.write(connection, _T0_NS, self._serialize(message, _STRING))

    def _stamp_ns(self, sample: int) -> int:
        """Time stamp of ``sample``: monotonic in ``sample``, 1 ns at sample 0."""
        stamp = sample * 1e9 / self._fs
        if not stamp < _MAX_STAMP_NS:
            raise InputError(f"sample {sample:,} at {self._fs!r} Hz lies past the last time stamp a bag can hold (int64 ns); give --sample-rate")
        return _T0_NS + round(stamp)

    def _emit(self, n: int) -> None:
        """Write one message of ``n`` samples per channel."""
        stamp = self._stamp_ns(self._written)
        for name, queue in self._pending.items():
            message = _array_message(queue.take(n), self._msgtype)
            self._bag.write(self._connections[name], stamp, self._serialize(message, self._msgtype))
        self._written += n

    def write(self, data: Mapping[str, np.ndarray]) -> None:
        """Append samples; ``data`` holds a 1-D array of equal length per channel."""
        if self._bag is None:
            raise ValueError(f"{self._path}: writer is closed")
        arrays = {}
        for name in self._pending:
            if name not in data:
                raise ValueError(f"data has no channel {name!r}")
            arrays[name] = np.asarray(data[name])
        lengths = {a.shape for a in arrays.values()}
        if len(lengths) != 1 or len(next(iter(lengths))) != 1:
            raise ValueError(f"channels must be 1-D arrays of one length, got shapes {sorted(lengths)}")
        for name, values in arrays.items():
            self._pending[name].push(values.astype(self._dtype))
        while len(next(iter(self._pending.values()))) >= self._block:
            self._emit(self._block)

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        """Bags carry no ground truth; the HDF5 layout does.  Does nothing."""

    def close(self) -> None:
        """Write the last, possibly short, block and finalise the bag."""
        if self._bag is None:
            return
        try:
            rest = len(next(iter(self._pending.values())))
            if rest:
                self._emit(rest)
            self._bag.close()
        except BaseException:
            self._abort()
            raise
        self._bag = None

    def _abort(self) -> None:
        bag, self._bag = self._bag, None
        if bag is not None:
            try:
                bag.abort()
            except (OSError, Ros1WriterError, Ros2WriterError):
                pass

    def __enter__(self) -> RosbagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        """Finalise the bag, or abandon it (unindexed) when the block raised."""
        if exc_type is None:
            self.close()
        else:
            self._abort()
