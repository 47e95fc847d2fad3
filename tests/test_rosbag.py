"""ROS1 and ROS2 bags: fixtures, round trips, message types, topic maps, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from afmtool.errors import AfmtoolError, ConfigError, InputError
from afmtool.io.capture import ChannelSpec
from afmtool.io.registry import create_writer, open_capture
from afmtool.io.rosbag import RosbagReader, RosbagWriter

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FIXTURES = SHARED / "fixtures"
TS = get_typestore(Stores.ROS2_HUMBLE)

CHANNELS = (ChannelSpec("dither", "V"), ChannelSpec("deflection", "nm"), ChannelSpec("z_piezo", "nm"))
META = {"cantilever": {"f0_hz": 70000.0, "q": 200.0}, "note": "test"}
FS = 5e5
STRING = "std_msgs/msg/String"
F64 = "std_msgs/msg/Float64"
F64_ARRAY = "std_msgs/msg/Float64MultiArray"
F32_ARRAY = "std_msgs/msg/Float32MultiArray"

# (version, storage, bag name); ROS2 bags are directories
BAG_KINDS = [("ros1", "mcap", "c.bag"), ("ros2", "mcap", "c_mcap"), ("ros2", "sqlite3", "c_db3")]
BAG_IDS = ["ros1", "ros2-mcap", "ros2-sqlite3"]


def _fixtures() -> Path:
    if not FIXTURES.is_dir():
        pytest.skip("../shared/fixtures is not beside the repository")
    return FIXTURES


def _read_all(reader, chunk: int) -> dict[str, np.ndarray]:
    names = reader.info.channel_names
    parts = list(reader.blocks(names, chunk))
    starts = [p.start for p in parts]
    assert starts == list(range(0, reader.info.n_samples, chunk))
    assert all(len(p) == chunk for p in parts[:-1])
    if not parts:
        return {name: np.empty(0) for name in names}
    for part in parts:
        assert all(v.dtype == np.float64 for v in part.data.values())
    return {name: np.concatenate([p.data[name] for p in parts]) for name in names}


def _data(rng, n: int = 2503) -> dict[str, np.ndarray]:
    return {c.name: rng.standard_normal(n) * (1 + i) for i, c in enumerate(CHANNELS)}


def _write_afm_bag(path, data, version, storage, **kwargs) -> None:
    writer = RosbagWriter(path, FS, CHANNELS, META, version=version, storage=storage, **kwargs)
    n = len(next(iter(data.values())))
    for lo, hi in [(0, 1), (1, 1000), (1000, 1000), (1000, n)]:  # uneven calls, one empty
        writer.write({k: v[lo:hi] for k, v in data.items()})
    writer.write_truth({"separation_nm": np.zeros(3)})  # a no-op for bags
    writer.close()


# -- raw bags written with rosbags directly ------------------------------------


def _message(msgtype: str, value, data_offset: int = 0):
    types = TS.types
    if msgtype == STRING:
        return types[STRING](data=value)
    if msgtype == F64:
        return types[F64](data=float(value))
    dtype = np.float64 if msgtype == F64_ARRAY else np.float32
    layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=data_offset)
    return types[msgtype](layout=layout, data=np.asarray(value, dtype=dtype))


def _write_raw_bag(path: Path, version: str, messages) -> Path:
    """Write ``(topic, msgtype, t_ns, message)`` tuples in order with rosbags itself."""
    if version == "ros1":
        writer = Ros1Writer(path)
        serialize = TS.serialize_ros1
    else:
        writer = Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = TS.serialize_cdr
    connections = {}
    with writer:
        for topic, msgtype, t_ns, message in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=TS)
            writer.write(connections[topic], t_ns, serialize(message, msgtype))
    return path


def _metadata_message(document: dict):
    return ("/afm/metadata", STRING, 1, _message(STRING, json.dumps(document)))


def _array_messages(topic: str, values: np.ndarray, block: int, msgtype: str = F64_ARRAY):
    """Blocks of ``block`` samples, stamped 2000 ns per sample from 1 ns."""
    return [
        (topic, msgtype, 1 + i * 2000, _message(msgtype, values[i : i + block])) for i in range(0, len(values), block)
    ]


def _simple_bag(tmp_path: Path, version: str, name: str = "raw", **topics) -> Path:
    """A bag with the standard metadata and one Float64MultiArray topic per keyword."""
    path = tmp_path / (f"{name}.bag" if version == "ros1" else name)
    messages = [_metadata_message({"sample_rate_hz": FS})]
    for topic, values in topics.items():
        messages += _array_messages("/" + topic.replace("__", "/"), values, 100)
    return _write_raw_bag(path, version, sorted(messages, key=lambda m: m[2]))


# -- fixtures from an independent implementation -------------------------------


@pytest.mark.parametrize(
    "name",
    ["capture_v1_ros1.bag", "capture_v1_ros2_mcap", "capture_v1_ros2_mcap/capture_v1_ros2_mcap.mcap"],
)
@pytest.mark.parametrize("chunk", [1000, 777])
def test_fixture_bags_read_expected_samples(name, chunk):
    fixtures = _fixtures()
    expected = np.load(fixtures / "capture_v1_expected.npy")
    with RosbagReader(fixtures / name) as reader:
        info = reader.info
        assert info.format == ("ros1" if name.endswith(".bag") else "ros2")
        assert info.sample_rate_hz == 500000
        assert info.n_samples == 4000
        assert info.channel_names == ("dither", "deflection", "z_piezo")
        assert [c.units for c in info.channels] == ["", "", ""]
        assert info.metadata["cantilever"]["f0_hz"] == 71000
        assert "sample_rate_hz" not in info.metadata
        assert reader.truth() == {}
        back = _read_all(reader, chunk)
    for i, channel in enumerate(("dither", "deflection", "z_piezo")):
        np.testing.assert_array_equal(back[channel], expected[i].astype(np.float64))


def test_fixture_bags_open_through_registry():
    fixtures = _fixtures()
    for name in ("capture_v1_ros1.bag", "capture_v1_ros2_mcap"):
        with open_capture(fixtures / name) as reader:
            assert isinstance(reader, RosbagReader)
            assert reader.info.n_samples == 4000


def test_sample_rate_argument_wins_over_metadata():
    with RosbagReader(_fixtures() / "capture_v1_ros1.bag", sample_rate_hz=1e6) as reader:
        assert reader.info.sample_rate_hz == 1e6


# -- round trips ---------------------------------------------------------------


@pytest.mark.parametrize(("version", "storage", "name"), BAG_KINDS, ids=BAG_IDS)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_round_trip(tmp_path, rng, version, storage, name, dtype):
    data = _data(rng)
    path = tmp_path / name
    _write_afm_bag(path, data, version, storage, dtype=dtype, block_samples=1000)
    results = []
    for chunk in (1, 777, 10**6):
        with RosbagReader(path) as reader:
            info = reader.info
            assert info.format == version
            assert info.sample_rate_hz == FS
            assert info.n_samples == 2503
            assert info.channels == CHANNELS
            assert dict(info.metadata) == META
            results.append(_read_all(reader, chunk))
    for back in results[1:]:
        for channel in data:
            np.testing.assert_array_equal(back[channel], results[0][channel])
    for channel, values in data.items():
        if dtype == "float64":
            np.testing.assert_array_equal(results[0][channel], values)
        else:
            np.testing.assert_array_equal(results[0][channel], values.astype(np.float32).astype(np.float64))
            np.testing.assert_allclose(results[0][channel], values, rtol=2.0**-24, atol=0)


@pytest.mark.parametrize(("version", "storage", "name"), BAG_KINDS, ids=BAG_IDS)
def test_written_messages_are_blocks_stamped_by_first_sample(tmp_path, rng, version, storage, name):
    path = tmp_path / name
    _write_afm_bag(path, _data(rng), version, storage)
    with AnyReader([path], default_typestore=TS) as bag:
        topics = [c.topic for c in bag.connections]
        assert topics == ["/afm/metadata", "/afm/dither", "/afm/deflection", "/afm/z_piezo"]
        seen: dict[str, list[tuple[int, int]]] = {}
        for connection, t_ns, raw in bag.messages():
            message = bag.deserialize(raw, connection.msgtype)
            if connection.topic == "/afm/metadata":
                document = json.loads(message.data)
                assert document["sample_rate_hz"] == FS
                assert document["channel_units"] == {c.name: c.units for c in CHANNELS}
                assert t_ns == 1
                continue
            assert connection.msgtype == F64_ARRAY
            seen.setdefault(connection.topic, []).append((t_ns, len(message.data)))
    for blocks in seen.values():
        assert blocks == [(1, 1000), (1 + 1000 * 2000, 1000), (1 + 2000 * 2000, 503)]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ros2_storage_file_inside_the_directory_reads_the_same(tmp_path, rng, storage):
    data = _data(rng)
    path = tmp_path / "bag"
    _write_afm_bag(path, data, "ros2", storage)
    inner = path / ("bag.mcap" if storage == "mcap" else "bag.db3")
    with RosbagReader(inner) as reader:
        assert reader.info.format == "ros2"
        back = _read_all(reader, 1000)
    for channel, values in data.items():
        np.testing.assert_array_equal(back[channel], values)


def test_subset_of_channels_and_empty_capture(tmp_path, rng):
    data = _data(rng, 10)
    path = tmp_path / "c.bag"
    _write_afm_bag(path, data, "ros1", "mcap", block_samples=3)
    with RosbagReader(path) as reader:
        parts = list(reader.blocks(["z_piezo"], 4))
        assert [sorted(p.data) for p in parts] == [["z_piezo"]] * 3
        np.testing.assert_array_equal(np.concatenate([p.data["z_piezo"] for p in parts]), data["z_piezo"])
    empty = tmp_path / "empty"
    RosbagWriter(empty, FS, CHANNELS, None, version="ros2").close()
    with RosbagReader(empty) as reader:
        assert reader.info.n_samples == 0
        assert dict(reader.info.metadata) == {}
        assert list(reader.blocks(reader.info.channel_names, 10)) == []


def test_registry_writer_round_trip(tmp_path, rng):
    data = _data(rng, 1500)
    path = tmp_path / "reg.bag"
    writer = create_writer(path, "ros1", FS, CHANNELS, META)
    writer.write(data)
    writer.close()
    with open_capture(path) as reader:
        back = _read_all(reader, 512)
    np.testing.assert_array_equal(back["deflection"], data["deflection"])


# -- other message layouts -----------------------------------------------------


@pytest.mark.parametrize("version", ["ros1", "ros2"])
def test_float64_one_sample_per_message(tmp_path, rng, version):
    deflection = rng.standard_normal(50)
    dither = rng.standard_normal(50).astype(np.float32)
    messages = [_metadata_message({"sample_rate_hz": 1e4, "channel_units": {"deflection": "nm"}})]
    messages += [("/afm/deflection", F64, 1 + i * 100_000, _message(F64, v)) for i, v in enumerate(deflection)]
    messages += _array_messages("/afm/dither", dither, 8, F32_ARRAY)  # mixed with array blocks
    path = tmp_path / ("f64.bag" if version == "ros1" else "f64")
    _write_raw_bag(path, version, sorted(messages, key=lambda m: m[2]))
    with RosbagReader(path) as reader:
        assert reader.info.n_samples == 50
        assert reader.info.units("deflection") == "nm"
        assert reader.info.units("dither") == ""
        for chunk in (1, 7, 100):
            back = _read_all(reader, chunk)
            np.testing.assert_array_equal(back["deflection"], deflection)
            np.testing.assert_array_equal(back["dither"], dither.astype(np.float64))


def test_multiarray_data_offset_skips_padding(tmp_path):
    values = np.arange(10.0)
    messages = [
        _metadata_message({"sample_rate_hz": FS}),
        ("/afm/deflection", F64_ARRAY, 1, _message(F64_ARRAY, np.r_[-1.0, -1.0, values[:5]], data_offset=2)),
        ("/afm/deflection", F64_ARRAY, 2, _message(F64_ARRAY, values[5:])),
    ]
    with RosbagReader(_write_raw_bag(tmp_path / "pad", "ros2", messages)) as reader:
        np.testing.assert_array_equal(_read_all(reader, 4)["deflection"], values)


@pytest.mark.parametrize("version", ["ros1", "ros2"])
def test_topic_map_overrides_the_default_topic(tmp_path, rng, version):
    dither, deflection = rng.standard_normal(300), rng.standard_normal(300)
    path = _simple_bag(tmp_path, version, afm__dither=dither, other__defl=deflection)
    with RosbagReader(path) as reader:
        assert reader.info.channel_names == ("dither",)
    with RosbagReader(path, topic_map={"deflection": "/other/defl"}) as reader:
        assert set(reader.info.channel_names) == {"dither", "deflection"}
        back = _read_all(reader, 128)
    np.testing.assert_array_equal(back["deflection"], deflection)
    np.testing.assert_array_equal(back["dither"], dither)
    # a mapped /afm/ topic is that channel only, not also a channel of its own name
    with RosbagReader(path, topic_map={"deflection": "/afm/dither"}) as reader:
        assert reader.info.channel_names == ("deflection",)
    with pytest.raises(InputError, match="no topic '/afm/missing' for channel 'deflection'"):
        RosbagReader(path, topic_map={"deflection": "/afm/missing"})


# -- bad input -----------------------------------------------------------------


def _assert_one_line_input_error(excinfo, path: Path) -> None:
    message = str(excinfo.value)
    assert message.startswith(str(path))
    assert "\n" not in message
    # converted at the boundary with ``from None``: no library traceback chained
    assert excinfo.value.__cause__ is None
    assert excinfo.value.__context__ is None or excinfo.value.__suppress_context__


def test_no_matching_topic(tmp_path, rng):
    path = _simple_bag(tmp_path, "ros2", foo__bar=rng.standard_normal(10))
    with pytest.raises(InputError, match=r"no channel topics \(expected /afm/<channel>") as excinfo:
        RosbagReader(path)
    _assert_one_line_input_error(excinfo, path)


@pytest.mark.parametrize("version", ["ros1", "ros2"])
def test_no_sample_rate_anywhere(tmp_path, rng, version):
    values = rng.standard_normal(200)
    path = tmp_path / ("nofs.bag" if version == "ros1" else "nofs")
    _write_raw_bag(path, version, _array_messages("/afm/deflection", values, 100))
    with pytest.raises(InputError, match="no sample rate") as excinfo:
        RosbagReader(path)
    _assert_one_line_input_error(excinfo, path)
    with RosbagReader(path, sample_rate_hz=1e5) as reader:
        assert reader.info.sample_rate_hz == 1e5
        np.testing.assert_array_equal(_read_all(reader, 64)["deflection"], values)


def test_truncated_ros1_bag(tmp_path, rng):
    path = tmp_path / "c.bag"
    _write_afm_bag(path, _data(rng), "ros1", "mcap")
    cut = tmp_path / "cut.bag"
    blob = path.read_bytes()
    cut.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(InputError) as excinfo:
        RosbagReader(cut)
    _assert_one_line_input_error(excinfo, cut)


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_ros2_directory_with_corrupt_mcap(tmp_path, rng, damage):
    path = tmp_path / "bag"
    _write_afm_bag(path, _data(rng), "ros2", "mcap")
    storage = path / "bag.mcap"
    blob = storage.read_bytes()
    if damage == "truncated":
        storage.write_bytes(blob[: len(blob) // 2])
    else:
        storage.write_bytes(rng.integers(0, 256, len(blob), dtype=np.uint8).tobytes())
    with pytest.raises(InputError) as excinfo:
        with RosbagReader(path) as reader:
            _read_all(reader, 1000)
    _assert_one_line_input_error(excinfo, path)


def test_fuzzed_bags_raise_only_input_error(tmp_path, rng):
    """Byte flips and cuts anywhere: the bag reads, or fails with InputError."""
    sources = {}
    for version, storage, name in BAG_KINDS:
        _write_afm_bag(tmp_path / name, _data(rng, 300), version, storage, block_samples=50)
        inner = {"c.bag": "", "c_mcap": "c_mcap.mcap", "c_db3": "c_db3.db3"}[name]
        sources[tmp_path / name] = inner
    for source, inner in sources.items():
        blob = (source / inner if inner else source).read_bytes()
        for trial in range(40):
            target = tmp_path / f"fuzz_{source.stem}_{trial}{source.suffix}"
            if inner:
                shutil.copytree(source, target)
            damaged = bytearray(blob[: int(rng.integers(0, len(blob)))] if trial % 2 else blob)
            for i in rng.integers(0, max(len(damaged), 1), 4 * (trial % 2 == 0)):
                damaged[i] = int(rng.integers(0, 256))
            (target / inner if inner else target).write_bytes(bytes(damaged))
            try:
                with RosbagReader(target) as reader:
                    _read_all(reader, 64)
            except InputError as exc:
                assert str(exc).startswith(str(target)) and "\n" not in str(exc)


def test_unknown_message_type_on_channel_topic(tmp_path):
    messages = [_metadata_message({"sample_rate_hz": FS}), ("/afm/deflection", STRING, 2, _message(STRING, "1.0"))]
    path = _write_raw_bag(tmp_path / "str.bag", "ros1", messages)
    with pytest.raises(InputError, match="topic /afm/deflection .* has message type std_msgs/msg/String") as excinfo:
        RosbagReader(path)
    _assert_one_line_input_error(excinfo, path)


def test_channels_with_different_lengths(tmp_path, rng):
    path = _simple_bag(tmp_path, "ros2", afm__dither=rng.standard_normal(300), afm__deflection=rng.standard_normal(250))
    with pytest.raises(InputError, match=r"different lengths \(dither=300, deflection=250\)"):
        RosbagReader(path)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("{not json", "/afm/metadata is not valid JSON"),
        ("[1, 2]", "must hold a JSON object"),
        ('{"sample_rate_hz": 5e5, "cantilever": {"f0_hz": -1}}', r"cantilever.f0_hz=-1 must be a number > 0"),
        ('{"sample_rate_hz": "fast"}', "sample rate 'fast' must be a positive number"),
        ('{"sample_rate_hz": 5e5, "channel_units": ["nm"]}', "channel_units must be an object of strings"),
    ],
)
def test_unreadable_metadata(tmp_path, rng, text, match):
    messages = [("/afm/metadata", STRING, 1, _message(STRING, text))]
    messages += _array_messages("/afm/deflection", rng.standard_normal(10), 10)
    path = _write_raw_bag(tmp_path / "meta", "ros2", messages)
    with pytest.raises(InputError, match=match) as excinfo:
        RosbagReader(path)
    _assert_one_line_input_error(excinfo, path)


def test_missing_path_and_non_bag_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        RosbagReader(tmp_path / "nope.bag")
    text = tmp_path / "text.bag"
    text.write_text("hello\n")
    with pytest.raises(InputError, match="not a readable bag") as excinfo:
        RosbagReader(text)
    _assert_one_line_input_error(excinfo, text)


# -- writer arguments ----------------------------------------------------------


def test_writer_refuses_existing_paths_but_replaces_an_empty_placeholder(tmp_path, rng):
    existing = tmp_path / "bag"
    existing.mkdir()
    with pytest.raises(AfmtoolError, match="exists already"):
        RosbagWriter(existing, FS, CHANNELS, None, version="ros2")
    full = tmp_path / "full.bag"
    full.write_bytes(b"keep me")
    with pytest.raises(AfmtoolError, match="exists already"):
        RosbagWriter(full, FS, CHANNELS, None, version="ros1")
    assert full.read_bytes() == b"keep me"
    placeholder = tmp_path / ".out.bag.tmp-0000.bag"
    placeholder.touch()
    data = _data(rng, 20)
    with RosbagWriter(placeholder, FS, CHANNELS, META, version="ros1") as writer:
        writer.write(data)
    with RosbagReader(placeholder) as reader:
        np.testing.assert_array_equal(_read_all(reader, 20)["dither"], data["dither"])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"version": "ros3"}, "version='ros3'"),
        ({"version": "ros2", "storage": "bag"}, "storage='bag'"),
        ({"version": "ros2", "dtype": "int16"}, "dtype='int16'"),
        ({"version": "ros2", "block_samples": 0}, "block_samples=0"),
    ],
)
def test_writer_rejects_bad_arguments(tmp_path, kwargs, match):
    with pytest.raises(ConfigError, match=match):
        RosbagWriter(tmp_path / "w", FS, CHANNELS, None, **kwargs)
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("name", ["metadata", "bad name", "9lives", "a/b"])
def test_writer_rejects_channel_names_that_are_not_topics(tmp_path, name):
    with pytest.raises(ConfigError, match="cannot be a topic"):
        RosbagWriter(tmp_path / "w", FS, [ChannelSpec(name)], None, version="ros2")
