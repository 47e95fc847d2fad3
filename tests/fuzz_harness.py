"""Mutation fuzzing of every afmtool reader.

Every generated input must either read cleanly or raise ``AfmtoolError``
(one-line message, exit status 2 from the CLI); anything else, a crash of
the interpreter, or a case slower than ``--timeout`` seconds is a finding.

CI runs a bounded budget through ``tests/test_fuzz.py``.  The long run::

    python -m tests.fuzz_harness --cases 10000            # every reader
    python -m tests.fuzz_harness --reader hdf5 --cases 20000 --seed 7

Each reader runs in a child process that is restarted after a hard crash,
so a segfault inside a C library is reported with its input, not lost.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import shutil
import signal
import sys
import tempfile
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: Beyond a case's own timeout, how long the parent waits before it kills a worker, s.
_GRACE_S = 20.0

READERS = (
    "csv", "hdf5", "ros1", "ros2-sqlite3", "ros2-mcap", "psd", "toml", "metadata",
    "ibw", "jpk", "tdms", "wav", "labone-hdf5", "labone-csv", "chiaro",
    "jpk-map", "afm-workshop", "ntmdt", "text", "mat5", "mat73", "npz", "npy", "scheduler",
)
_SUFFIX = {"csv": ".csv", "hdf5": ".h5", "ros1": ".bag", "psd": ".csv", "toml": ".toml", "metadata": ".json",
           "ibw": ".ibw", "jpk": ".jpk-force", "tdms": ".tdms", "wav": ".wav", "labone-hdf5": ".h5",
           "labone-csv": ".csv", "chiaro": ".zip", "jpk-map": ".jpk-force-map", "afm-workshop": ".csv",
           "ntmdt": ".txt", "text": ".txt", "mat5": ".mat", "mat73": ".mat", "npz": ".npz", "npy": ".npy",
           "scheduler": ".bin"}
#: Readers of instrument formats, whose seeds are real files or their libraries' own output.
VENDOR_READERS = ("ibw", "jpk", "tdms", "wav", "labone-hdf5", "labone-csv", "chiaro", "jpk-map", "afm-workshop", "ntmdt")
#: Readers of the issue-32 formats whose seeds their own libraries write (scipy, hdf5storage, numpy, text).
LIBRARY_READERS = ("text", "mat5", "mat73", "npz", "npy")
#: Readers whose files are ZIP archives: half their cases mutate one member and re-zip it.
_ZIP_READERS = ("jpk", "chiaro", "jpk-map", "npz")
#: Readers whose formats record no sample rate: the target gives one.
_NO_RATE = ("afm-workshop", "ntmdt", "npy")
_FORMATS = Path(__file__).resolve().parents[2] / "shared" / "data" / "formats"
#: The mutation corpus of the vendor readers: every real file of the format (the peers' test files,
#: ../shared/data/formats/SOURCES.md); case k mutates file k mod n.
CORPUS = {
    "ibw": ("fmt-igor-fd_SiN_FD_plot.ibw", "win-version2.ibw", "win-double.ibw", "win-version5.ibw",
            "win-textWave.ibw", "win-zeroPointWave.ibw"),
    "jpk": ("fmt-jpk-fd_spot3-0192.jpk-force", "force-save-example.jpk-force",
            "fmt-jpk-fd_flipsign_2015.05.22-15.31.49.352.jpk-force", "fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force",
            "fmt-jpk-cl_calibration_force-save-2015.02.04-11.25.21.294.jpk-force",
            "fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series"),
    "jpk-map": ("fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data", "force-map2x2-example.jpk-force-map"),
    "tdms": ("raw1.tdms",),
    "afm-workshop": ("fmt-afm-workshop-fd_single_2018-08-01_13.06.09.csv", "fmt-afm-workshop-fd_single_2021-01-15.csv"),
    "ntmdt": ("fmt-ntmdt-txt-fd_2015_01_17_gel4-0,1_mQ_adh_6B_Curve_DFL_Height_51.txt",),
}


# --------------------------------------------------------------------------- seeds

def _seed_capture(folder: Path, fmt: str) -> Path:
    """A small valid capture in ``fmt`` written by afmtool itself."""
    from afmtool import sim
    from afmtool.analyses.convert import convert_capture
    from afmtool.io.memory import ArrayReader

    captured = sim.simulate("ltv", {"duration_s": 0.0005}, seed=1)
    reader = ArrayReader(captured.sample_rate_hz, captured.channels, captured.data, captured.metadata, captured.truth)
    target = folder / ("seed" + _SUFFIX.get(fmt, ""))
    if fmt.startswith("ros2"):
        target = folder / "seed_bag"
    if fmt == "csv":
        with open(target, "w", encoding="utf-8") as handle:
            convert_capture(reader, handle, "csv")
    else:
        convert_capture(reader, target, fmt)
    return target


def _seed_vendor(path: Path, reader: str) -> Path:
    """A small valid file in a vendor format: a real instrument file, or its library's own output."""
    if reader in CORPUS:
        shutil.copyfile(_FORMATS / CORPUS[reader][0], path)
    elif reader == "chiaro":  # the real export's header and its first 300 rows, zipped as it came
        import zipfile

        with zipfile.ZipFile(_FORMATS / "fmt-chiaro-txt_AEBP1_Indentation_002.zip") as source:
            member = source.namelist()[0]
            text = source.read(member)
        cut = text.index(b"Time (s)")
        rows = text[cut:].split(b"\r\n")[:301]
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as target:
            target.writestr(member, text[:cut] + b"\r\n".join(rows) + b"\r\n")
    elif reader == "wav":
        from scipy.io import wavfile

        wavfile.write(path, 500000, np.random.default_rng(1).standard_normal((300, 2)).astype(np.float32))
    elif reader == "labone-hdf5":
        import h5py

        with h5py.File(path, "w") as f:
            for chunk in range(2):
                group = f.create_group(f"{chunk:03d}/dev1234/demods/0/sample")
                group["timestamp"] = (10**9 + (np.arange(100) + 100 * chunk) * 3000).astype(np.uint64)
                group["x"] = np.linspace(0, 1, 100)
                group["y"] = np.linspace(1, 0, 100)
                group.attrs["clockbase"] = 60e6
            wave = f.create_group("000/dev1234/scopes/0/wave")  # a second segment: --segment in the target
            wave["wave"] = np.ones((2, 64), dtype=np.int16)
            wave.attrs["dt"] = 1e-6
    else:  # labone-csv
        lines = ["# clockbase: 60000000", "chunk;timestamp;x;y;frequency"]
        lines += [f"0;{10**9 + 3000 * i};{0.001 * i};{-0.002 * i};70000" for i in range(200)]
        path.write_text("\n".join(lines) + "\n")
    return path


def _seed_library(path: Path, reader: str, variant: int) -> Path:
    """A small capture of an issue-32 format, written by that format's own library (variant 0 or 1)."""
    rng = np.random.default_rng(variant + 3)
    dither, deflection = rng.standard_normal(200), rng.standard_normal(200)
    variables = {"dither": dither, "deflection": deflection, "fs": np.float64(5e5)}
    if reader == "mat5":
        from scipy.io import savemat

        savemat(path, {**variables, "data": np.column_stack([dither, deflection])}, do_compression=bool(variant))
    elif reader == "mat73":
        import hdf5storage

        hdf5storage.savemat(str(path), variables, format="7.3", matlab_compatible=True)
    elif reader == "npz":
        (np.savez_compressed if variant else np.savez)(path, **variables)
    elif reader == "npy":
        np.save(path, np.column_stack([dither, deflection]) if variant else deflection)
    else:  # a vendor-style text export: a preamble, units in the header, a delimiter, perhaps decimal commas
        sep, comma = (";", True) if variant else (",", False)
        rows = "".join(f"{float(a)!r}{sep}{float(b)!r}\n".replace(".", "," if comma else ".")
                       for a, b in zip(dither, deflection))
        path.write_text(f"Export\nSample rate, kHz: 500\nSpring constant = 2.5\n\ndither (V){sep}deflection (nm)\n{rows}")
    return path


def seed_inputs(folder: Path, reader: str) -> list[Path]:
    """The reader's mutation corpus: its real files (vendor formats) or two library-written variants."""
    if reader in CORPUS:
        paths = []
        for k, name in enumerate(CORPUS[reader]):
            target = folder / f"seed{k}{_SUFFIX[reader]}"
            shutil.copyfile(_FORMATS / name, target)
            paths.append(target)
        return paths
    if reader in LIBRARY_READERS:
        return [_seed_library(folder / f"seed{k}{_SUFFIX[reader]}", reader, k) for k in (0, 1)]
    return [seed_input(folder, reader)]


def seed_input(folder: Path, reader: str) -> Path:
    if reader in ("csv", "hdf5", "ros1", "ros2-sqlite3", "ros2-mcap"):
        return _seed_capture(folder, reader)
    path = folder / ("seed" + _SUFFIX[reader])
    if reader in LIBRARY_READERS:
        return _seed_library(path, reader, 0)
    if reader in VENDOR_READERS:
        return _seed_vendor(path, reader)
    if reader == "psd":
        f = np.arange(1, 400) * 250.0
        asd = 1e-13 + 1e-11 / np.sqrt((1 - (f / 5e4) ** 2) ** 2 + (f / 5e4 / 300) ** 2)
        path.write_text("frequency_hz,asd_m_per_sqrt_hz\n" + "".join(f"{a:.6f},{b:.6e}\n" for a, b in zip(f, asd)))
    elif reader == "toml":
        from afmtool.config.defaults import default_toml

        path.write_text(default_toml())
    elif reader == "scheduler":
        path.write_bytes(_dask_handshake())
    else:
        path.write_text(json.dumps({"cantilever": {"f0_hz": 7e4, "q": 200}, "free_air": {"start_s": 0, "end_s": 0.01},
                                    "scan": {"lines": 4, "pixels_per_line": 8, "scan_size_m": 1e-6, "line_rate_hz": 2.0}}))
    return path


# ----------------------------------------------------------------------- mutation

def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """1-4 random byte-level mutations: flips, truncation, duplication, insertion, zeroing."""
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        if not buf:
            buf = bytearray(rng.bytes(int(rng.integers(1, 64))))
            continue
        kind = int(rng.integers(0, 6))
        i = int(rng.integers(0, len(buf)))
        if kind == 0:
            buf[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:
            del buf[i:]
        elif kind == 2:
            j = min(len(buf), i + int(rng.integers(1, 256)))
            buf[i:i] = buf[i:j]
        elif kind == 3:
            buf[i:i] = rng.bytes(int(rng.integers(1, 32)))
        elif kind == 4:
            j = min(len(buf), i + int(rng.integers(1, 64)))
            buf[i:j] = bytes(j - i)
        else:
            buf[i] = int(rng.choice([0, 0xFF, 0x7F, 0x80, ord(","), ord("\n"), ord("#"), ord("n")]))
    return bytes(buf)


def mutate_zip(data: bytes, rng: np.random.Generator) -> bytes:
    """Mutate one member of a ZIP archive and re-zip it (so its CRC still matches), or the archive itself."""
    import io
    import zipfile

    if rng.random() < 0.5:
        return mutate(data, rng)
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as source:
            members = [(item, source.read(item)) for item in source.infolist()]
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return mutate(data, rng)
    if not members:
        return data
    victim = int(rng.integers(0, len(members)))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as target:
        for i, (item, body) in enumerate(members):
            target.writestr(item, mutate(body, rng) if i == victim else body)
    return out.getvalue()


def materialise(seed: Path, data: bytes, folder: Path) -> Path:
    """Write a mutated copy of ``seed``; a ROS2 bag keeps its other file intact."""
    if seed.is_dir():
        target = folder / "case_bag"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(seed, target)
        storage = next(p for p in target.iterdir() if p.suffix in (".mcap", ".db3"))
        if storage.stem != target.name:  # rosbags names the storage after the folder
            storage = storage.rename(target / f"{target.name}{storage.suffix}")
            meta = (target / "metadata.yaml").read_text().replace(seed.name, target.name)
            (target / "metadata.yaml").write_text(meta)
        victim = storage if data[:1] != b"\x00" or len(data) % 7 else target / "metadata.yaml"
        victim.write_bytes(data if victim is storage else mutate(victim.read_bytes(), np.random.default_rng(len(data))))
        return target
    target = folder / ("case" + seed.suffix)
    target.write_bytes(data)
    return target


# ------------------------------------------------------------ structural mutations

#: One case in this many is a structural mutation (issue 20) instead of a byte-level one.
STRUCTURAL_EVERY = 8


def _hdf5_hostile(seed: Path, folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """A copy of the HDF5 seed made hostile in one way; ``True`` if it must be refused."""
    import h5py

    target = folder / "case.h5"
    shutil.copyfile(seed, target)
    other = folder / "outside.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("s", data=np.full(64, 42.0))
        f.create_dataset("g/s", data=np.full(64, 43.0))
    kind = int(rng.integers(0, 8))
    where = "channels" if rng.random() < 0.5 else "truth"
    with h5py.File(target, "a") as f:
        if kind == 0:  # size claim: unallocated chunks read as fill values
            f.create_dataset(f"{where}/claim", shape=(10 ** int(rng.integers(7, 16)),), dtype="f8", chunks=(4096,))
            return target, False  # refused by the ratio check, or read within budget (small claims)
        if kind == 1:  # compression bomb: zeros, gzip
            n = 1 << int(rng.integers(16, 22))
            ds = f.create_dataset(f"{where}/bomb", shape=(n,), dtype="f8", chunks=(min(n, 1 << 18),), compression="gzip")
            ds[:] = 0.0
            return target, False
        if kind == 2:  # soft links (a chain of 1-3) to an external link
            f["ext"] = h5py.ExternalLink(str(other), "/" if rng.random() < 0.5 else "/g")
            previous = "/ext/s"
            for hop in range(int(rng.integers(0, 3))):
                f[f"hop{hop}"] = h5py.SoftLink(previous.rsplit("/", 1)[0])
                previous = f"/hop{hop}/s"
            f[f"{where}/leak"] = h5py.SoftLink(previous)
            return target, True
        if kind == 3:  # external raw storage
            raw = folder / "raw.bin"
            raw.write_bytes(b"secret!!" * 64)
            f.create_dataset(f"{where}/leak", shape=(64,), dtype="f8", external=[(str(raw), 0, 512)])
            return target, True
        if kind == 4:  # virtual dataset
            layout = h5py.VirtualLayout(shape=(64,), dtype="f8")
            layout[:] = h5py.VirtualSource(str(other), "s", shape=(64,))
            f.create_virtual_dataset(f"{where}/leak", layout)
            return target, True
        if kind == 5:  # deep metadata JSON
            depth = int(rng.integers(10, 20_000))
            f.attrs["metadata"] = "[" * depth + "]" * depth
            return target, depth > 64
        if kind == 7:  # issue 34: a metadata block of up to 100,000 keys: read (or refused) within the case's time
            keys = int(rng.integers(1000, 100_001))
            f.attrs["metadata"] = json.dumps({"instrument": {f"k{i}": i for i in range(keys)}})
            return target, False
        f["a"] = h5py.SoftLink("/b")  # a soft-link loop
        f["b"] = h5py.SoftLink("/a")
        f[f"{where}/loop"] = h5py.SoftLink("/a/x")
        return target, True


def _text_hostile(reader: str, seed: Path, folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Huge CSV headers and lines, deeply nested JSON and TOML."""
    target = folder / ("case" + seed.suffix)
    depth = int(rng.integers(10, 20_000))
    if reader == "csv":
        lines = seed.read_text(encoding="utf-8").splitlines(keepends=True)
        header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
        if rng.random() < 0.5:  # a header of up to 5,000 columns
            extra = int(rng.integers(1, 5000))
            lines[header] = lines[header].rstrip("\n") + "".join(f",c{i}" for i in range(extra)) + "\n"
        else:  # one very long row
            lines.insert(header + 1, ",".join(["1"] * int(rng.integers(1000, 200_000))) + "\n")
        target.write_text("".join(lines), encoding="utf-8")
        return target, False
    if reader == "metadata":
        target.write_text('{"a":' * depth + "1" + "}" * depth)
        return target, depth > 64
    target.write_text("x = " + "[" * depth + "]" * depth + "\n")  # toml
    return target, depth > 16


def _tdms_hostile(folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: scaling chains that refer to themselves or each other, huge scale counts; an unsupported scaling."""
    from nptdms import ChannelObject, TdmsWriter

    target = folder / "case.tdms"
    kind = int(rng.integers(0, 4))
    count = 2
    scales: dict = {}
    if kind == 2:
        count = 10 ** int(rng.integers(3, 13))
    for k in range(2):
        source = {0: {1: 1}, 1: {0: 1, 1: 0}}.get(kind, {}).get(k, 0xFFFFFFFF)
        scales |= {f"NI_Scale[{k}]_Scale_Type": "Reciprocal" if kind == 3 else "Linear", f"NI_Scale[{k}]_Linear_Slope": 2.0,
                   f"NI_Scale[{k}]_Linear_Y_Intercept": 0.0, f"NI_Scale[{k}]_Linear_Input_Source": source}
    props = {"wf_increment": 1e-5, "NI_Scaling_Status": "unscaled", "NI_Number_Of_Scales": count, **scales}
    with TdmsWriter(str(target)) as writer:
        writer.write_segment([ChannelObject("g", "deflection", np.arange(64.0), properties=props)])
    return target, kind in (0, 1, 2)


def _jpk_hostile(folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: a header declaring tens of thousands of channels; indirections in a cycle or too deep."""
    import zipfile

    target = folder / "case.jpk-force"
    kind = int(rng.integers(0, 3))
    segment = ["force-segment-header.num-points=4", "force-segment-header.duration=0.004"]
    shared = []
    if kind == 0:
        names = [f"c{i}" for i in range(int(rng.integers(1025, 40_000)))]
        segment += [f"channels.list={' '.join(names)}"] + [f"channel.{n}.data.type=short" for n in names]
    else:
        depth = 1 if kind == 1 else int(rng.integers(9, 2000))
        segment += ["channels.list=h", "channel.h.lcd-info.*=0"]
        shared = [f"lcd-info.{i}.next.lcd-info.*={(i + 1) % depth if kind == 1 else i + 1}" for i in range(depth)]
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("header.properties", "file-format-version=2.0\n")
        archive.writestr("shared-data/header.properties", "\n".join(shared) + "\n")
        archive.writestr("segments/0/segment-header.properties", "\n".join(segment) + "\n")
    return target, True


def _ibw_hostile(seed: Path, folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: a note whose Indexes are infinite; a note size claimed far past the file."""
    import struct

    raw = (_FORMATS / "fmt-igor-fd_SiN_FD_plot.ibw").read_bytes()
    sizes = list(struct.unpack_from("<hhiiii4i4iiii", raw, 0))
    note_at, note_size = 64 + sizes[2] + sizes[3], sizes[4]
    if rng.random() < 0.5:
        note = b"Indexes: 0," + rng.choice([b"inf", b"1e400", b"-inf", b"nan"]) + b",2015\r"
        body = raw[384:note_at] + note + raw[note_at + note_size :]
        sizes[4] = len(note)
    else:
        body = raw[384:]
        sizes[4] = int(rng.integers(1 << 30, 1 << 31))
    head = bytearray(struct.pack("<hhiiii4i4iiii", *sizes) + raw[64:384])
    struct.pack_into("<h", head, 2, 0)
    struct.pack_into("<h", head, 2, ((-sum(struct.unpack("<192h", bytes(head))) + 32768) % 65536) - 32768)
    target = folder / "case.ibw"
    target.write_bytes(bytes(head) + body)
    return target, True


def _bag_hostile(reader: str, folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: a bag whose metadata JSON nests arrays 65-20,000 deep (RecursionError in ROS1, db3, mcap)."""
    from unittest import mock

    import afmtool.io.rosbag as rosbag
    from afmtool.io.capture import ChannelSpec

    depth = int(rng.integers(65, 20_000))

    def deep(self, connection, channels, metadata):
        message = rosbag._TYPESTORE.types[rosbag._STRING](data="[" * depth + "]" * depth)
        self._bag.write(connection, rosbag._T0_NS, self._serialize(message, rosbag._STRING))

    target = folder / ("case.bag" if reader == "ros1" else "case_bag")
    shutil.rmtree(target, ignore_errors=True)
    if target.exists():
        target.unlink()
    storage = "sqlite3" if reader == "ros2-sqlite3" else "mcap"
    with mock.patch.object(rosbag.RosbagWriter, "_write_metadata", deep):
        writer = rosbag.RosbagWriter(target, 1000.0, [ChannelSpec("deflection", "nm")], None,
                                     version="ros1" if reader == "ros1" else "ros2", storage=storage)
        writer.write({"deflection": np.zeros(10)})
        writer.close()
    return target, True


def _cut_or_doubled(reader: str, seed: Path, folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: a text file whose last line is cut short; a WAV with two data chunks."""
    target = folder / ("case" + seed.suffix)
    raw = seed.read_bytes()
    if reader == "wav":
        import struct

        at = raw.index(b"data")
        doubled = raw[:at] + raw[at:] + raw[at:]
        target.write_bytes(doubled[:4] + struct.pack("<I", len(doubled) - 8) + doubled[8:])
        return target, True
    body = raw.rstrip(b"\r\n")
    target.write_bytes(body[: len(body) - int(rng.integers(0, 3))])  # ends inside its last line
    return target, True


def _labone_hostile(folder: Path, rng: np.random.Generator) -> tuple[Path, bool]:
    """Issue 34: demodulator timestamps at the uint64 maximum (OverflowError)."""
    import h5py

    target = folder / "case.h5"
    with h5py.File(target, "w") as f:
        group = f.create_group("000/dev1234/demods/0/sample")
        stamps = np.arange(100, dtype=np.uint64) * 3000
        stamps[int(rng.integers(0, 100))] = np.iinfo(np.uint64).max
        group["timestamp"] = stamps if rng.random() < 0.5 else stamps[::-1].copy()
        group["x"] = np.zeros(100)
        group.attrs["clockbase"] = 60e6
    return target, False  # refused (non-uniform) or read; never an overflow


def structural_case(reader: str, seed: Path, folder: Path, rng: np.random.Generator) -> tuple[Path, bool] | None:
    """A hostile input of the kinds issues 20 and 34 list, or ``None`` where the reader has none.

    Returns the path and whether it must be refused (data from outside the
    file, nesting past the limits, a chain without end, a misread): reading it
    cleanly is then a finding.
    """
    if reader == "hdf5":
        return _hdf5_hostile(seed, folder, rng)
    if reader in ("csv", "metadata", "toml"):
        if reader == "csv" and rng.random() < 0.25:
            return _cut_or_doubled(reader, seed, folder, rng)
        return _text_hostile(reader, seed, folder, rng)
    hostile = {
        "tdms": lambda: _tdms_hostile(folder, rng),
        "jpk": lambda: _jpk_hostile(folder, rng),
        "ibw": lambda: _ibw_hostile(seed, folder, rng),
        "ros1": lambda: _bag_hostile(reader, folder, rng),
        "ros2-sqlite3": lambda: _bag_hostile(reader, folder, rng),
        "ros2-mcap": lambda: _bag_hostile(reader, folder, rng),
        "text": lambda: _cut_or_doubled(reader, seed, folder, rng),
        "wav": lambda: _cut_or_doubled(reader, seed, folder, rng),
        "labone-hdf5": lambda: _labone_hostile(folder, rng),
    }
    return hostile[reader]() if reader in hostile else None


# ------------------------------------------------------------------------- targets

def read_target(reader: str) -> Callable[[Path], None]:
    """The code under test for ``reader``: parse everything, raise AfmtoolError on bad input."""
    if reader in ("csv", "hdf5", "ros1", "ros2-sqlite3", "ros2-mcap", *VENDOR_READERS, *LIBRARY_READERS):
        from afmtool.errors import AfmtoolError, SelectionNeeded
        from afmtool.io.chunks import iter_chunks
        from afmtool.io.registry import open_capture

        options = {"segment": "demods" if reader == "labone-hdf5" else None,
                   "sample_rate_hz": 1000.0 if reader in _NO_RATE else None}

        def run(path: Path) -> None:
            try:
                capture = open_capture(path, **options)
            except SelectionNeeded as exc:  # several captures in one file: read the first, as a user would choose it
                capture = open_capture(path, **{**options, exc.option.lstrip("-"): exc.choices[0]})
            except AfmtoolError as exc:  # a file that records no rate: read it as a user would, with --sample-rate
                if "give --sample-rate" not in str(exc) or options["sample_rate_hz"] is not None:
                    raise
                capture = open_capture(path, **{**options, "sample_rate_hz": 1000.0})
            with capture:
                for _ in iter_chunks(capture, capture.info.channel_names, 257):
                    pass
                capture.truth()

        return run
    if reader == "psd":
        from afmtool.estimators.thermal_noise import fit_thermal_spectrum
        from afmtool.io.psd import read_psd_csv

        def run(path: Path) -> None:
            table = read_psd_csv(path)
            try:
                fit_thermal_spectrum(table.frequency_hz, table.asd_m_per_sqrt_hz)
            except (ValueError, ArithmeticError):
                pass  # a garbled spectrum may not fit; reading it must still be clean

        return run
    if reader == "toml":
        from afmtool.config import load_toml, resolve_from
        from afmtool.config.params import SECTIONS

        def run(path: Path) -> None:
            document = load_toml(path)
            for section, cls in SECTIONS.items():
                resolve_from(cls, section, document, {})

        return run

    if reader == "scheduler":
        return _probe_target

    from afmtool.io.metadata import parse_metadata_json

    return lambda path: parse_metadata_json(path.read_bytes().decode("utf-8", errors="replace"), str(path))


def _dask_handshake() -> bytes:
    """What a Dask scheduler sends first on a TCP connection: an 8-byte length, then its handshake's frames."""
    import struct

    from distributed.protocol.core import dumps
    from distributed.protocol.utils import pack_frames

    body = pack_frames(dumps({"compression": None, "python": tuple(sys.version_info[:3]), "pickle-protocol": 5}))
    return struct.pack("Q", len(body)) + body


def _probe_target(path: Path) -> None:
    """Serve ``path``'s bytes as a peer on 127.0.0.1 (then close), and probe it as ``--scheduler`` (issue 34)."""
    import socket
    import threading

    from afmtool.io.scheduler import probe_scheduler

    data = path.read_bytes()
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)

    def serve() -> None:
        with server:
            server.settimeout(5)
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with conn:
                try:
                    conn.sendall(data)
                except OSError:
                    pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        probe_scheduler(f"tcp://127.0.0.1:{server.getsockname()[1]}", 2.0)
    finally:
        thread.join(timeout=5)


# --------------------------------------------------------------------------- driver

def _worker(reader: str, seed_dir: str, start: int, stop: int, rng_seed: int, timeout: float, conn) -> None:
    from afmtool.errors import AfmtoolError

    def on_alarm(signum, frame):
        raise TimeoutError

    signal.signal(signal.SIGALRM, on_alarm)
    seeds = seed_inputs(Path(seed_dir), reader)
    originals = []
    for seed in seeds:
        if seed.is_dir():
            originals.append(next(p for p in seed.iterdir() if p.suffix in (".mcap", ".db3")).read_bytes())
        else:
            originals.append(seed.read_bytes())
    target = read_target(reader)
    work = Path(tempfile.mkdtemp(prefix=f"fuzz-{reader}-"))
    try:
        for case in range(start, stop):
            case_rng = np.random.default_rng([rng_seed, case])
            seed, original = seeds[case % len(seeds)], originals[case % len(seeds)]
            structural = structural_case(reader, seed, work, case_rng) if case % STRUCTURAL_EVERY == 0 else None
            if structural is None:
                data = mutate_zip(original, case_rng) if reader in _ZIP_READERS else mutate(original, case_rng)
                must_refuse = False
                path = materialise(seed, data, work)
            else:
                path, must_refuse = structural
                data = f"structural case {case}".encode()
            conn.send(("start", case, data))
            signal.setitimer(signal.ITIMER_REAL, timeout)
            try:
                target(path)
                outcome = ("leak", case, "read cleanly, must be refused") if must_refuse else ("ok", case, None)
            except AfmtoolError as exc:
                message = str(exc)
                outcome = ("rejected", case, None) if "\n" not in message.strip() else ("multiline", case, message)
            except TimeoutError:
                outcome = ("hang", case, None)
            except Exception:  # noqa: BLE001 - any other exception is the finding
                outcome = ("crash", case, traceback.format_exc(limit=6))
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            conn.send(outcome)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        conn.send(("done", stop, None))


def fuzz_reader(reader: str, cases: int, seed: int = 0, timeout: float = 10.0) -> dict:
    """Run ``cases`` mutated inputs through ``reader``; return counts and findings."""
    counts = {"ok": 0, "rejected": 0, "crash": 0, "hang": 0, "multiline": 0, "died": 0, "leak": 0}
    findings: list[dict] = []
    seed_dir = tempfile.mkdtemp(prefix=f"fuzz-seed-{reader}-")
    context = mp.get_context("spawn")
    start = 0
    try:
        while start < cases:
            parent, child = context.Pipe()
            proc = context.Process(target=_worker, args=(reader, seed_dir, start, cases, seed, timeout, child))
            proc.start()
            child.close()
            current, data, running = start, b"", False
            while True:
                # A case stuck inside C code holding the GIL never sees its SIGALRM: the parent
                # waits a little longer, then kills the worker and records a hang.
                if running and not parent.poll(timeout + _GRACE_S):
                    proc.kill()
                    counts["hang"] += 1
                    findings.append({"reader": reader, "case": current, "kind": "hang", "detail": "killed by the parent",
                                     "input_hex": data[:4096].hex()})
                    start = current + 1
                    break
                try:
                    kind, case, detail = parent.recv()
                except EOFError:  # the interpreter died on `current`
                    counts["died"] += 1
                    findings.append({"reader": reader, "case": current, "kind": "died", "input_hex": data[:4096].hex()})
                    start = current + 1
                    break
                running = kind == "start"
                if kind == "start":
                    current, data = case, detail
                    continue
                if kind == "done":
                    start = cases
                    break
                counts[kind] += 1
                if kind not in ("ok", "rejected"):
                    findings.append({"reader": reader, "case": case, "kind": kind, "detail": detail,
                                     "input_hex": data[:4096].hex()})
            proc.join(timeout=30)
    finally:
        shutil.rmtree(seed_dir, ignore_errors=True)
    return {"reader": reader, "cases": cases, "counts": counts, "findings": findings}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reader", choices=READERS, action="append")
    parser.add_argument("--cases", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=10.0)
    parser.add_argument("--findings", type=Path, default=Path("fuzz-findings.json"))
    args = parser.parse_args(argv)
    results = []
    for reader in args.reader or READERS:
        result = fuzz_reader(reader, args.cases, args.seed, args.timeout)
        print(f"{reader:14s} {json.dumps(result['counts'])}", flush=True)
        results.append(result)
    findings = [f for r in results for f in r["findings"]]
    args.findings.write_text(json.dumps(results, indent=1))
    print(f"{len(findings)} findings; details in {args.findings}")
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
