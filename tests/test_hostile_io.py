"""Hostile input and faults, case by case from issue 20 (written by hand, not by the fuzzer).

Each case is a file or an environment an attacker or an unlucky user could
produce: data reached through links out of the capture, outputs aimed at
the inputs, concurrent and killed runs, full disks, claims of sizes a file
cannot hold.  Every one must end in exit 2 with one line on stderr (or a
correct success), quickly, without touching the inputs.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.conftest import REPO, run_cli

FS = 100_000.0
N = 4000


def _write_capture(path: Path, n: int = N, *, seed: int = 20) -> Path:
    """A small afmtool-layout HDF5 capture written with h5py directly."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = FS
        dither = f.create_dataset("channels/dither", data=np.sin(2 * np.pi * 5000 * t))
        dither.attrs["units"] = "V"
        deflection = f.create_dataset("channels/deflection", data=rng.normal(size=n))
        deflection.attrs["units"] = "nm"
    return path


def _state(path: Path) -> tuple[str, int]:
    """sha256 and mtime (ns) of a file, or of every file under a folder."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    for p in files:
        digest.update(p.read_bytes())
    return digest.hexdigest(), max(p.stat().st_mtime_ns for p in files)


def _one_line_exit_2(result: subprocess.CompletedProcess, *needles: str) -> str:
    stderr = result.stderr.decode()
    assert result.returncode == 2, (result.returncode, stderr[-2000:])
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# -- 1. nothing from outside the capture ------------------------------------------------------


@pytest.fixture
def secret(tmp_path) -> Path:
    """Another HDF5 file, and a raw file standing for /etc/passwd."""
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("s", data=np.full(N, 42.0))
    return other


def _soft_link_to_external(tmp_path: Path, secret: Path) -> Path:
    path = _write_capture(tmp_path / "soft.h5")
    with h5py.File(path, "a") as f:
        f["ext"] = h5py.ExternalLink(str(secret), "/")
        del f["channels/deflection"]
        f["channels/deflection"] = h5py.SoftLink("/ext/s")
    return path


def _relative_soft_link_chain(tmp_path: Path, secret: Path) -> Path:
    path = _write_capture(tmp_path / "chain.h5")
    with h5py.File(path, "a") as f:
        f["ext"] = h5py.ExternalLink(str(secret), "/")
        f["hop"] = h5py.SoftLink("ext")  # relative to the root
        f["channels/dither2"] = h5py.SoftLink("/hop/s")
        del f["channels/dither"]
    return path


def _truth_external_storage(tmp_path: Path, secret: Path) -> Path:
    passwd = tmp_path / "passwd"
    passwd.write_bytes(b"root:x:0:0:root:/root:/bin/bash\n" * 8)
    path = _write_capture(tmp_path / "truth_ext.h5")
    with h5py.File(path, "a") as f:
        f.create_dataset("truth/leak", shape=(passwd.stat().st_size,), dtype="u1", external=[(str(passwd), 0, h5py.h5f.UNLIMITED)])
    return path


def _truth_virtual(tmp_path: Path, secret: Path) -> Path:
    path = _write_capture(tmp_path / "truth_vds.h5")
    layout = h5py.VirtualLayout(shape=(N,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(secret), "s", shape=(N,))
    with h5py.File(path, "a") as f:
        f.create_virtual_dataset("truth/leak", layout)
    return path


def _truth_soft_to_external(tmp_path: Path, secret: Path) -> Path:
    path = _write_capture(tmp_path / "truth_soft.h5")
    with h5py.File(path, "a") as f:
        f["ext"] = h5py.ExternalLink(str(secret), "/")
        f["truth/leak"] = h5py.SoftLink("/ext/s")
    return path


def _truth_huge(tmp_path: Path, secret: Path) -> Path:
    path = _write_capture(tmp_path / "truth_huge.h5")
    with h5py.File(path, "a") as f:
        f.create_dataset("truth/huge", shape=(10**15,), dtype="f8", chunks=(4096,))
    return path


def _channel_huge(tmp_path: Path, secret: Path) -> Path:
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = FS
        f.create_dataset("channels/deflection", shape=(10**15,), dtype="f8", chunks=(4096,)).attrs["units"] = "nm"
    return path


OUTSIDE = {
    "soft link to external": (_soft_link_to_external, "external link"),
    "relative soft-link chain": (_relative_soft_link_chain, "external link"),
    "truth stored externally": (_truth_external_storage, "external files"),
    "truth virtual": (_truth_virtual, "virtual"),
    "truth soft link to external": (_truth_soft_to_external, "external link"),
    "truth claiming 1e15": (_truth_huge, "claim"),
    "channel claiming 1e15": (_channel_huge, "claim"),
}


@pytest.mark.parametrize("case", list(OUTSIDE))
def test_data_outside_the_capture_is_refused_by_info_and_convert(tmp_path, secret, case):
    make, needle = OUTSIDE[case]
    path = make(tmp_path, secret)
    before = _state(path)
    for args in (["info", path], ["convert", path, tmp_path / "copy.h5"]):
        start = time.monotonic()
        result = run_cli(*args)
        assert time.monotonic() - start < 10
        _one_line_exit_2(result, needle)
    assert not (tmp_path / "copy.h5").exists()
    assert _state(path) == before


@pytest.mark.parametrize("command", ["reep", "probeloss", "decode", "kalman-bank"])
def test_every_analysis_refuses_the_soft_link_and_the_truth_leak(tmp_path, secret, command):
    for make in (_soft_link_to_external, _truth_external_storage):
        path = make(tmp_path, secret)
        result = run_cli(command, path, "--out", tmp_path / "out")
        _one_line_exit_2(result)
        assert not (tmp_path / "out").exists()


def test_soft_link_loop_is_refused(tmp_path):
    path = _write_capture(tmp_path / "loop.h5")
    with h5py.File(path, "a") as f:
        f["a"] = h5py.SoftLink("/b")
        f["b"] = h5py.SoftLink("/a")
        f["channels/x"] = h5py.SoftLink("/a/s")
    _one_line_exit_2(run_cli("info", path), "soft links")


def test_local_soft_links_still_work(tmp_path):
    path = _write_capture(tmp_path / "local.h5")
    with h5py.File(path, "a") as f:
        f["data/raw"] = f["channels/deflection"][()]
        del f["channels/deflection"]
        f["alias"] = h5py.SoftLink("/data")
        f["channels/deflection"] = h5py.SoftLink("/alias/raw")
    result = run_cli("info", path, "--json")
    assert result.returncode == 0, result.stderr.decode()
    assert b'"deflection"' in result.stdout


def test_max_samples_overrides_the_ratio_check(tmp_path, secret):
    path = tmp_path / "sparse.h5"
    with h5py.File(path, "w") as f:  # 1e7 samples of fill value: claims 80 MB in a few kB
        f.attrs["sample_rate_hz"] = FS
        f.create_dataset("channels/deflection", shape=(10**7,), dtype="f8", chunks=(1 << 16,)).attrs["units"] = "nm"
    _one_line_exit_2(run_cli("info", path), "--max-samples")
    assert run_cli("--max-samples", "10000000", "info", path).returncode == 0
    _one_line_exit_2(run_cli("--max-samples", "1000", "info", path), "--max-samples 1,000")


@pytest.mark.parametrize("name", ["/x/y", "../..", "/truth/contact", "a\nb", "..", "."])
def test_csv_column_names_cannot_become_dataset_paths(tmp_path, name):
    csv = tmp_path / "cols.csv"
    header = ",".join(["deflection", '"' + name + '"' if "\n" in name else name])
    csv.write_text(f"# sample_rate_hz: 1000\n{header}\n" + "".join(f"{i},{2 * i}\n" for i in range(50)))
    out = tmp_path / "out.h5"
    result = run_cli("convert", csv, out)
    if result.returncode == 0:  # a reader may rename; then nothing may land outside /channels
        with h5py.File(out) as f:
            assert set(f) == {"channels"}
            assert all("/" not in k and k not in (".", "..") for k in f["channels"])
    else:
        _one_line_exit_2(result)
        assert not out.exists()


def test_compressed_chunks_are_each_read_once():
    from afmtool.io.hdf5 import _ChunkWindow

    class Recording:
        shape, chunks = (10_000,), (700,)

        def __init__(self):
            self.reads = []

        def read_direct(self, buffer, selection):
            sl = selection[0] if isinstance(selection, tuple) else selection
            self.reads.append((sl.start, sl.stop))
            buffer[:] = np.arange(sl.start, sl.stop)

    dataset = Recording()
    window = _ChunkWindow(dataset)
    got = np.concatenate([window.read(s, min(s + 256, 10_000)) for s in range(0, 10_000, 256)])
    np.testing.assert_array_equal(got, np.arange(10_000))
    starts = [a for a, _ in dataset.reads]
    stops = [b for _, b in dataset.reads]
    assert all(a % 700 == 0 for a in starts) and all(b % 700 == 0 or b == 10_000 for b in stops)
    assert sum(b - a for a, b in dataset.reads) == 10_000  # no sample (so no chunk) twice


def test_gzip_bomb_ends_within_10_s(tmp_path):
    path = tmp_path / "bomb.h5"
    n = 1 << 25  # 256 MiB of zeros in a few hundred kB
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = FS
        ds = f.create_dataset("channels/deflection", shape=(n,), dtype="f8", chunks=(1 << 20,), compression="gzip", compression_opts=9)
        ds.attrs["units"] = "nm"
        zeros = np.zeros(1 << 20)
        for start in range(0, n, 1 << 20):
            ds[start : start + (1 << 20)] = zeros
    start = time.monotonic()
    result = run_cli("info", path)
    assert time.monotonic() - start < 10
    if result.returncode != 0:
        _one_line_exit_2(result)
