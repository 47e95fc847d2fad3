"""Errors that name the real reason first (issue 31 item 4): Nyquist, then channels, before any model.

On the real Asylum force curve (2 kHz, a 23 kHz lever) every oscillation
command used to fail on whatever it looked for first ("no free-air model",
"no channel 'dither'", "the f0/Q route ...") and named the sample rate
fourth.  The check now runs as the capture opens.
"""

from __future__ import annotations

import csv

import pytest

from afmtool.analyses.capture_check import CaptureNeeds, check_capture
from afmtool.errors import InputError
from tests.conftest import SAMPLE_DATA, SHARED, run_cli

IBW = SHARED / "data" / "formats" / "fmt-igor-fd_SiN_FD_plot.ibw"


def _ibw():
    if not IBW.is_file():
        pytest.skip("../shared/data/formats is not beside the repository")
    return IBW


@pytest.mark.parametrize("command", [["reep"], ["probeloss"], ["kalman-bank"], ["decode"], ["identify", "freeair"]])
def test_a_low_rate_instrument_curve_is_refused_for_its_sample_rate_first(command, tmp_path):
    result = run_cli(*command, _ibw(), "--out", tmp_path / "out")
    lines = result.stderr.decode().strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, lines
    line = lines[0]
    assert line.startswith("afmtool: error: ") and "sampled at 2000 Hz" in line and "1000 Hz (Nyquist)" in line
    assert "23251 Hz" in line and "at least 5.81e+04 Hz" in line  # what to do: record faster
    for misleading in ("free-air model", "no channel", "f0/Q route"):
        assert misleading not in line
    assert not (tmp_path / "out").exists()


def test_then_the_missing_channel_with_what_to_give(tmp_path):
    # the same file claimed to be at 200 kHz passes the Nyquist check and meets the channel check next
    result = run_cli("reep", _ibw(), "--sample-rate", "200000", "--out", tmp_path / "out")
    line = result.stderr.decode().strip()
    assert result.returncode == 2 and "\n" not in line
    assert "reads channel 'dither'" in line and "--channel dither=NAME" in line and "--drive" in line


def test_the_frequency_given_on_the_command_line_counts(tmp_path):
    result = run_cli("reep", SAMPLE_DATA / "ltv_step.h5", "--f0", "300000", "--q", "200", "--out", tmp_path / "o")
    line = result.stderr.decode().strip()
    assert result.returncode == 2 and "resonance is 300000 Hz (given)" in line and "250000 Hz (Nyquist)" in line


class _Info:
    def __init__(self, fs, channels, f0=None, drive=None):
        from afmtool.io.metadata import CantileverMetadata, CaptureMetadata, DriveMetadata

        self.source, self.sample_rate_hz, self.channel_names = "c.h5", fs, tuple(channels)
        self.capture_metadata = CaptureMetadata(cantilever=CantileverMetadata(f0_hz=f0),
                                                drive=DriveMetadata(frequency_hz=drive))


def test_check_passes_a_capture_that_can_carry_the_command_and_fails_one_that_cannot():
    good = _Info(500_000.0, ("deflection", "dither"), f0=70_000.0, drive=70_000.0)
    check_capture(good, CaptureNeeds("reep"))
    check_capture(_Info(500_000.0, ("deflection",), f0=70_000.0), CaptureNeeds("reep"), synthesisable=True)
    with pytest.raises(InputError, match="drive frequency is 260000 Hz"):
        check_capture(_Info(500_000.0, ("deflection", "dither"), drive=260_000.0), CaptureNeeds("reep"))
    with pytest.raises(InputError, match="lacks"):
        check_capture(_Info(500_000.0, ("deflection",)), CaptureNeeds("reep"))
    # no frequency known anywhere: nothing to refuse on (the analysis asks for a model later)
    check_capture(_Info(2_000.0, ("deflection", "dither")), CaptureNeeds("reep"))


def test_batch_summary_keeps_the_one_line(tmp_path):
    pytest.importorskip("dask.distributed")
    out = tmp_path / "batch"
    result = run_cli("batch", "reep", _ibw(), "--out", out, "--workers", "1", "-q")
    assert result.returncode == 2  # bad input (README)
    with open(out / "summary.csv") as handle:
        (row,) = list(csv.DictReader(handle))
    assert row["status"] == "failed" and row["reason"].startswith(f"{IBW}: sampled at 2000 Hz")
