"""The provenance hash: computed on the samples in the read pass, checked against an independent digest.

Issue 19, item 2: XXH3-128, no second pass over the file (the reads are
counted), recorded as {algorithm, value}, ``--no-hash``, and batch resume
comparing the same hash.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import xxhash

from afmtool.io.capture import ReaderBase
from afmtool.io.provenance import SampleDigest, capture_hash
from afmtool.io.registry import open_capture
from tests.conftest import REPO, run_cli

LTV = REPO / "sample_data" / "ltv_step.h5"


def independent_digest(path, channels) -> str:
    """The documented fold, computed here from the datasets with h5py and xxhash alone."""
    fold = xxhash.xxh3_128(b"afmtool samples v1\0")
    n = None
    with h5py.File(path, "r") as f:
        for name in sorted(channels):
            values = np.asarray(f["channels"][name][()], dtype="<f8")
            n = len(values)
            fold.update(name.encode() + b"\0" + xxhash.xxh3_128(values.tobytes()).digest())
    fold.update(n.to_bytes(8, "little"))
    return fold.hexdigest()


class CountingReader(ReaderBase):
    """Counts the passes over a capture and the samples each pass yields."""

    def __init__(self, reader) -> None:
        self._reader = reader
        self.info = reader.info
        self.passes: list[int] = []

    def blocks(self, channels, block_samples):
        self.passes.append(0)
        for chunk in self._reader.blocks(channels, block_samples):
            self.passes[-1] += len(chunk)
            yield chunk

    def truth(self):
        return self._reader.truth()

    def close(self) -> None:
        self._reader.close()


def test_reep_hashes_in_its_one_read_pass(tmp_path, monkeypatch):
    import afmtool.report.json_report as json_report
    from afmtool.analyses.command_inputs import CommandRun
    from afmtool.analyses.reep_outputs import run_reep_command

    def no_file_hash(path):
        raise AssertionError(f"the capture {path} was hashed in a second pass")

    monkeypatch.setattr(json_report, "sha256_file", no_file_hash)
    counting = CountingReader(open_capture(LTV))
    with counting:
        report = run_reep_command(CommandRun(counting, str(LTV), tmp_path / "out", None, {}, lambda done: None))
    assert counting.passes == [25_000]  # one pass, every sample once (the free-air segment replayed, not reread)
    record = report["inputs"][0]["hash"]
    assert record == {"algorithm": "xxh3-128", "value": independent_digest(LTV, ["deflection", "dither"]),
                      "over": "samples", "channels": ["deflection", "dither"], "samples": 25_000}
    assert json.loads((tmp_path / "out" / "report.json").read_text())["inputs"][0]["hash"] == record


def test_the_hash_does_not_depend_on_the_chunks():
    with open_capture(LTV) as reader:
        whole = capture_hash(reader, ["dither", "deflection"], chunk_samples=1 << 20)
    with open_capture(LTV) as reader:
        pieces = capture_hash(reader, ["deflection", "dither"], chunk_samples=977)
    assert whole == pieces


def test_a_changed_sample_changes_the_hash(tmp_path):
    copy = tmp_path / "copy.h5"
    copy.write_bytes(LTV.read_bytes())
    with h5py.File(copy, "r+") as f:
        f["channels"]["deflection"][12_345] += 1e-9
    with open_capture(LTV) as a, open_capture(copy) as b:
        assert capture_hash(a, ["deflection"]) != capture_hash(b, ["deflection"])


def test_digest_record_names_what_it_covers():
    digest = SampleDigest(["b", "a"])
    assert digest.record()["channels"] == ["a", "b"] and digest.record()["samples"] == 0


@pytest.mark.parametrize("command, capture, extra", [
    ("reep", "ltv_step.h5", []),
    ("probeloss", "raster_grating.h5", []),
    ("decode", "bits_30khz.h5", ["--bit-rate", "30000"]),
])
def test_cli_records_the_sample_hash_and_no_hash_records_none(command, capture, extra, tmp_path):
    path = REPO / "sample_data" / capture
    hashed = run_cli(command, path, "--out", tmp_path / "hashed", "-q", *extra)
    bare = run_cli(command, path, "--out", tmp_path / "bare", "-q", "--no-hash", *extra)
    assert hashed.returncode == 0 and bare.returncode == 0, (hashed.stderr, bare.stderr)
    record = json.loads((tmp_path / "hashed" / "report.json").read_text())["inputs"][0]["hash"]
    assert record["algorithm"] == "xxh3-128" and record["over"] == "samples"
    assert record["value"] == independent_digest(path, record["channels"])
    bare_report = json.loads((tmp_path / "bare" / "report.json").read_text())
    assert bare_report["inputs"][0]["hash"] is None
    hashed_report = json.loads((tmp_path / "hashed" / "report.json").read_text())
    assert bare_report["results"] == hashed_report["results"]


def _status(out) -> str:
    import csv

    with open(out / "summary.csv") as handle:
        (row,) = csv.DictReader(handle)
    return row["status"]


def test_batch_resume_compares_the_sample_hash(tmp_path):
    pytest.importorskip("dask.distributed")
    capture = tmp_path / "c.h5"
    capture.write_bytes(LTV.read_bytes())
    out = tmp_path / "batch"
    assert run_cli("batch", "reep", capture, "--out", out, "--workers", "1", "-q").returncode == 0
    again = run_cli("batch", "reep", capture, "--out", out, "--workers", "1", "-q")
    assert again.returncode == 0 and _status(out) == "skipped"
    with h5py.File(capture, "r+") as f:  # the samples change, the file's size does not
        f["channels"]["dither"][100] += 1e-6
    third = run_cli("batch", "reep", capture, "--out", out, "--workers", "1", "-q")
    assert third.returncode == 0 and _status(out) == "ok", third.stderr
    record = json.loads((out / "c_h5" / "report.json").read_text())["inputs"][0]["hash"]
    assert record["value"] == independent_digest(capture, record["channels"])
