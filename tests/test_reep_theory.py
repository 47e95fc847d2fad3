"""REEP against averaging theory on simulated tapping force curves (thesis §3.4.3)."""

from __future__ import annotations

import numpy as np
import pytest

from afmtool import sim
from afmtool.analyses.reep import run_reep
from afmtool.analyses.theory import ReepRows, beat_modulation, compare_binned
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from afmtool.io.memory import ArrayReader
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import THESIS_FORCE_SETS
from tests.memory_sink import MemorySink

FREE_AMPLITUDE_NM = 20.0
SIDEBAND_SCALE = 0.25


@pytest.mark.parametrize("force_set", ["attractive", "attractive-repulsive", "repulsive"])
def test_reep_agrees_with_averaging_theory(force_set):
    # Free air 80,318 Hz, Q 168 (§3.4.3), afmtool's own simulator (the reference simulator's
    # version is tests/test_reep_theory_reference.py): the binned verdict passes with the true
    # force and fails with another thesis set.
    captured = sim.simulate(
        "tapping",
        {
            "duration_s": 0.4,
            "f0_hz": 80318.0,
            "q": 168.0,
            "force_set": force_set,
            "program": "force-curve",
            "separation_nm": 30.0,
            "turn_separation_nm": 2.0,
            "amplitude_nm": FREE_AMPLITUDE_NM,
            "sideband_scale": SIDEBAND_SCALE,
        },
        seed=1,
    )
    reader = ArrayReader(captured.sample_rate_hz, captured.channels, captured.data, captured.metadata)
    params = resolve(ReepParams, {})
    columns = MemorySink()
    result = run_reep(reader, params, columns)
    t = columns["t"]
    index = np.round(t * captured.sample_rate_hz).astype(int)
    cantilever = Cantilever(80318.0, 168.0)
    drive_hz = result.results.drive_frequency_hz
    offset = captured.metadata["drive"]["sideband_offset_hz"]
    beat = beat_modulation([(drive_hz, 1.0), (drive_hz - offset, SIDEBAND_SCALE), (drive_hz + offset, SIDEBAND_SCALE)],
                           drive_hz, cantilever)

    def compare(force):
        return compare_binned(
            t, ReepRows(columns["f0_hz"], columns["q"], columns["f0_std_hz"], columns["q_std"]), columns["amplitude"],
            np.asarray(captured.truth["separation_nm"])[index], drive_frequency_hz=drive_hz, cantilever=cantilever,
            force=force, row_lambda=result.results.forgetting_factor ** result.results.decimate,
            free_amplitude_nm=FREE_AMPLITUDE_NM,
            beat=beat, flag=columns["flag"],
        )

    comparison = compare(THESIS_FORCE_SETS[force_set])
    print(force_set, comparison.verdict, comparison.summary().ill_conditioned_reasons)
    assert comparison.passed, comparison.verdict
    assert comparison.excluded_near_jumps < 0.02 * comparison.mask.sum()
    other = "attractive-repulsive" if force_set == "attractive" else "attractive"
    assert not compare(THESIS_FORCE_SETS[other]).passed


def test_theory_cli_averaging_and_compare(tmp_path):
    import json

    from tests.conftest import run_cli, validate_report

    result = run_cli("theory", "averaging", "--out", tmp_path / "th", "--force-set", "repulsive", "--json")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    # the predominantly repulsive set is bistable: hysteresis between approach and retract
    assert report["results"]["approach"]["bistable_separation_nm"] is not None
    assert (tmp_path / "th" / "averaging.png").stat().st_size > 10_000

    capture = tmp_path / "fc.h5"
    settings = ["duration_s=0.2", "sideband_scale=0.25", "turn_separation_nm=2.0", "amplitude_nm=20.0",
                "separation_nm=30.0"]
    args = [a for s in settings for a in ("--set", s)]
    assert run_cli("simulate", "tapping", "-o", capture, "--seed", "1", *args).returncode == 0
    assert run_cli("reep", capture, "--out", tmp_path / "reep", "-q").returncode == 0
    result = run_cli("theory", "compare", tmp_path / "reep", "--out", tmp_path / "cmp", "--json")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    assert report["results"]["force_set"] == "attractive"
    assert report["results"]["pass"] is True
    # a wrong force model is caught: the comparison fails and says so
    result = run_cli("theory", "compare", tmp_path / "reep", "--out", tmp_path / "cmp2", "--json",
                     "--force-set", "repulsive")
    report = json.loads(result.stdout)
    assert report["results"]["pass"] is False
    assert report["warnings"]
