"""One reader stack (issue 29, item 5): the CLI, batch and a direct open_capture read the same samples.

A capture whose deflection was recorded in V (no InvOLS in its metadata) is
read with ``--invols``: the CLI's report, a batch run's report and
:func:`afmtool.io.stack.open_capture` with the same :class:`CaptureOptions`
must hash the same converted samples, and those samples must be the
recorded volts times the InvOLS.  A second batch run on the same inputs and
arguments recognises its finished output (its resume check reads through
the same stack, with the run's own ``--invols``).
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from afmtool.io.capture import ChannelSpec
from afmtool.io.registry import create_writer
from afmtool.io.registry import open_capture as open_format
from afmtool.io.stack import CaptureOptions, open_capture
from tests.conftest import SAMPLE_DATA, run_cli

INVOLS = 52.5  # nm/V


@pytest.fixture(scope="module")
def volts_capture(tmp_path_factory):
    """ltv_step.h5 with its deflection written in V (deflection / INVOLS), no InvOLS in its metadata."""
    with open_format(SAMPLE_DATA / "ltv_step.h5") as reader:
        info = reader.info
        data = {c: np.concatenate([b.data[c] for b in reader.blocks(["deflection", "dither"], 1 << 16)])
                for c in ("deflection", "dither")}
    path = tmp_path_factory.mktemp("stack") / "volts.h5"
    channels = [ChannelSpec("dither", "V"), ChannelSpec("deflection", "V")]
    metadata = {k: v for k, v in info.metadata.items()}
    metadata.get("cantilever", {}).pop("deflection_sensitivity_nm_per_v", None)
    writer = create_writer(path, "hdf5", info.sample_rate_hz, channels, metadata)
    writer.write({"dither": data["dither"], "deflection": data["deflection"] / INVOLS})
    writer.close()
    return path


def _read_all(reader, channels=("deflection", "dither")):
    blocks = list(reader.blocks(list(channels), 4096))
    return {c: np.concatenate([b.data[c] for b in blocks]) for c in channels}


def test_direct_open_capture_converts_volts_once(volts_capture):
    with open_format(volts_capture) as raw:
        recorded = _read_all(raw)
        assert raw.info.units("deflection") == "V"
    with open_capture(volts_capture, CaptureOptions(invols_nm_per_v=INVOLS)) as reader:
        assert reader.info.units("deflection") == "nm"
        converted = _read_all(reader)
    np.testing.assert_array_equal(converted["deflection"], recorded["deflection"] * INVOLS)
    np.testing.assert_array_equal(converted["dither"], recorded["dither"])
    # the same path through registry.open_capture(path, options)
    with open_format(volts_capture, CaptureOptions(invols_nm_per_v=INVOLS)) as reader:
        np.testing.assert_array_equal(_read_all(reader)["deflection"], converted["deflection"])


def test_without_invols_a_volts_deflection_is_one_line_that_says_what_to_give(volts_capture):
    from afmtool.errors import InputError

    with pytest.raises(InputError, match="give --invols"):
        open_capture(volts_capture, CaptureOptions())


@pytest.mark.long
def test_cli_batch_and_open_capture_read_the_same_converted_samples(volts_capture, tmp_path):
    cli = run_cli("reep", volts_capture, "--invols", INVOLS, "--out", tmp_path / "cli", "--quiet")
    assert cli.returncode == 0, cli.stderr.decode()
    cli_hash = json.loads((tmp_path / "cli" / "report.json").read_text())["inputs"][0]["hash"]

    batch = run_cli("batch", "reep", volts_capture, f"--arg=--invols={INVOLS}", "--out", tmp_path / "batch",
                    "--workers", "1", "--quiet")
    assert batch.returncode == 0, batch.stderr.decode()
    (sub,) = [p for p in (tmp_path / "batch").iterdir() if p.is_dir()]
    batch_hash = json.loads((sub / "report.json").read_text())["inputs"][0]["hash"]

    with open_capture(volts_capture, CaptureOptions(invols_nm_per_v=INVOLS, accepts_drive=True,
                                                    hash_samples=True)) as reader:
        _read_all(reader, cli_hash["channels"])
        direct_hash = reader.record()
    assert cli_hash == batch_hash == direct_hash

    # batch's resume check reads with the run's own --invols: the finished input is skipped
    again = run_cli("batch", "reep", volts_capture, f"--arg=--invols={INVOLS}", "--out", tmp_path / "batch",
                    "--workers", "1", "--quiet")
    assert again.returncode == 0, again.stderr.decode()
    with open(tmp_path / "batch" / "summary.csv") as handle:
        assert [row["status"] for row in csv.DictReader(handle)] == ["skipped"]
