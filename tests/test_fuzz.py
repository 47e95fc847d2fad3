"""Bounded fuzzing of every reader in CI (the long run: python -m tests.fuzz_harness --cases 10000)."""

from __future__ import annotations

import json
import time

import pytest

from tests.fuzz_harness import _FORMATS, READERS, VENDOR_READERS, fuzz_reader

#: Mutated inputs per reader in CI; the documented long run uses 10,000.
CI_CASES = 120


@pytest.mark.parametrize("reader", READERS)
def test_reader_survives_mutations(reader):
    if reader in VENDOR_READERS and not _FORMATS.is_dir():
        pytest.skip("../shared/data/formats (the vendor seeds) is not beside the repository")
    if reader == "scheduler":
        pytest.importorskip("distributed")
    start = time.monotonic()
    result = fuzz_reader(reader, CI_CASES, seed=20261122, timeout=10.0)
    counts = result["counts"]
    print(reader, counts, f"{(time.monotonic() - start) / CI_CASES * 1000:.1f} ms per case")
    assert counts["ok"] + counts["rejected"] == CI_CASES, json.dumps(result["findings"][:3], indent=1)[:4000]
    assert counts["rejected"] > 0  # the mutations really produce bad input


# Regression tests for what fuzzing found.


def test_toml_with_invalid_utf8_is_a_config_error(tmp_path):
    from afmtool.config import load_toml
    from afmtool.errors import ConfigError

    path = tmp_path / "bad.toml"
    path.write_bytes(b"[reep]\nlam = 0.99 # \xb8\xff\n")
    with pytest.raises(ConfigError, match="UTF-8"):
        load_toml(path)


def test_hdf5_with_damaged_btree_is_an_input_error(tmp_path):
    """h5py raised RuntimeError ('wrong B-tree signature') while listing /channels."""
    import numpy as np

    from afmtool.errors import InputError
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.hdf5 import Hdf5Writer
    from afmtool.io.registry import open_capture

    path = tmp_path / "c.h5"
    writer = Hdf5Writer(path, 1000.0, [ChannelSpec("deflection", "nm")])
    writer.write({"deflection": np.arange(100.0)})
    writer.close()
    data = bytearray(path.read_bytes())
    signature = data.find(b"TREE")
    assert signature > 0
    data[signature : signature + 4] = b"XXXX"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError):
        with open_capture(path) as reader:
            list(reader.blocks(reader.info.channel_names, 10))


def test_error_messages_stay_on_one_line():
    """Long run, ros1 case 7474: a damaged bag's topic name held a newline, and the message split."""
    from afmtool.errors import InputError

    message = str(InputError("case.bag: topic /afm/metadat\n (channel metadat\n) has message type x\x00"))
    assert "\n" not in message and message.isprintable()
    assert message == "case.bag: topic /afm/metadat\\n (channel metadat\\n) has message type x\\x00"
    assert str(InputError("  Γ_IR,ts in µA/nm  ")) == "Γ_IR,ts in µA/nm"  # printable text is left alone


def test_tdms_with_a_damaged_scaling_chain_is_an_input_error(tmp_path):
    """Long run, tdms cases 397, 747, 1172, 1385, 2174: npTDMS raised a bare Exception
    ("Invalid scaling input source for DAQmx data") while scaling a channel."""
    import numpy as np

    from afmtool.errors import InputError
    from afmtool.io.chunks import iter_chunks
    from afmtool.io.registry import open_capture
    from tests.fuzz_harness import _FORMATS, mutate

    if not _FORMATS.is_dir():
        pytest.skip("../shared/data/formats is not beside the repository")
    path = tmp_path / "case397.tdms"
    path.write_bytes(mutate((_FORMATS / "raw1.tdms").read_bytes(), np.random.default_rng([0, 397])))
    with pytest.raises(InputError, match="cannot scale"):
        with open_capture(path) as reader:
            list(iter_chunks(reader, reader.info.channel_names, 257))


@pytest.mark.serial
def test_ibw_with_a_huge_declared_section_is_refused_before_allocating(tmp_path):
    """Long run, ibw cases 1345, 1380 and 1392: a damaged section size made igor2 ask for
    gigabytes (7.7 GB RSS, and a worker killed as a hang); the header is now checked first."""
    import time

    import numpy as np

    from afmtool.errors import InputError
    from afmtool.io.registry import open_capture
    from tests.fuzz_harness import _FORMATS, mutate

    if not _FORMATS.is_dir():
        pytest.skip("../shared/data/formats is not beside the repository")
    seed = (_FORMATS / "fmt-igor-fd_SiN_FD_plot.ibw").read_bytes()
    for case in (1345, 1380):
        path = tmp_path / f"case{case}.ibw"
        path.write_bytes(mutate(seed, np.random.default_rng([0, case])))
        start = time.monotonic()
        with pytest.raises(InputError, match="declares"):
            open_capture(path)
        assert time.monotonic() - start < 2


def test_jpk_zip_of_an_unknown_version_is_an_input_error(tmp_path):
    """Long run (seed 1), jpk case 1285: zipfile raised NotImplementedError ("zip file version
    11.0") for a central directory that asks for a newer ZIP version than Python reads."""
    import struct
    import zipfile

    from afmtool.errors import InputError
    from afmtool.io.registry import open_capture

    path = tmp_path / "case1285.jpk-force"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("header.properties", "jpk-data-file=spm-forcefile\n")
    data = bytearray(path.read_bytes())
    central = data.index(b"PK\x01\x02")
    struct.pack_into("<H", data, central + 6, 110)  # version needed to extract: 11.0
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="not a readable JPK file"):
        open_capture(path)


@pytest.mark.parametrize("kind", ["datatype", "external", "soft"])
def test_labone_field_that_is_not_a_local_dataset_is_refused(tmp_path, kind):
    """Long run (seed 1), labone-hdf5 cases 3312 and 4314: a demodulator field that was a
    committed datatype raised AttributeError; a field behind an external or soft link must not be
    followed either (issue 20: nothing read from outside the capture)."""
    import h5py
    import numpy as np

    from afmtool.errors import InputError
    from afmtool.io.registry import open_capture

    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.ones(100)
    path = tmp_path / "labone.h5"
    with h5py.File(path, "w") as f:
        sample = f.create_group("000/dev1234/demods/0/sample")
        sample["timestamp"] = np.arange(100, dtype=np.uint64) * 60
        sample["y"] = np.zeros(100)
        sample.attrs["clockbase"] = 60e6
        if kind == "datatype":
            sample["x"] = np.dtype("f8")
        elif kind == "external":
            sample["x"] = h5py.ExternalLink(str(other), "/x")
        else:
            f["elsewhere"] = np.ones(100)
            sample["x"] = h5py.SoftLink("/elsewhere")
    with pytest.raises(InputError, match="x"):
        with open_capture(path) as reader:
            _ = reader.info


def test_mat5_that_crashes_scipy_is_one_line(tmp_path):
    """Long run (seed 0), mat5 cases 486, 1490, 1730, 1778, 3104, 3350, 5022, 6368, 7824, 9674: scipy.io.loadmat
    died with SIGSEGV inside its C reader (the worker 'died').  The variables are read in a child first."""
    import numpy as np

    from tests.conftest import run_cli
    from tests.fuzz_harness import mutate, seed_inputs

    seeds = seed_inputs(tmp_path, "mat5")
    crashed = 0
    for case in (486, 1730, 3350):
        path = tmp_path / f"case{case}.mat"
        path.write_bytes(mutate(seeds[case % len(seeds)].read_bytes(), np.random.default_rng([0, case])))
        result = run_cli("info", path)
        err = result.stderr.decode()
        assert result.returncode == 2 and err.count("\n") == 1 and "Traceback" not in err, err
        crashed += "crashed (signal" in err
    assert crashed == 3
