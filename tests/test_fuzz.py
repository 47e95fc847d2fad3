"""Bounded fuzzing of every reader in CI (the long run: python -m tests.fuzz_harness --cases 10000)."""

from __future__ import annotations

import json

import pytest

import time

from tests.fuzz_harness import _FORMATS, READERS, VENDOR_READERS, fuzz_reader

#: Mutated inputs per reader in CI; the documented long run uses 10,000.
CI_CASES = 120


@pytest.mark.parametrize("reader", READERS)
def test_reader_survives_mutations(reader):
    if reader in VENDOR_READERS and not _FORMATS.is_dir():
        pytest.skip("../shared/data/formats (the vendor seeds) is not beside the repository")
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
