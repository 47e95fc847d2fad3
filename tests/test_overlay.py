"""``afmtool overlay``: runs side by side (issue 31 item 5), on the thesis's mica-ageing layout (Fig. 3.17).

Four tapping force curves of one lever whose tip-sample damping grows with
the time the surface has aged (c_a 1e4 to 8e4 1/s), each run through REEP,
then overlaid with the labels 0, 45 min, 2 h and 16 h.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict

import numpy as np
import pytest

from tests.conftest import run_cli, validate_report

pytestmark = pytest.mark.long  # four simulated force curves through REEP, then the overlay

LABELS = ("0", "45 min", "2 h", "16 h")
DAMPING = (1.0e4, 2.0e4, 4.0e4, 8.0e4)


def _invoke(*args: str) -> str:
    from typer.testing import CliRunner

    from afmtool.cli.main import app

    result = CliRunner().invoke(app, [str(a) for a in args], catch_exceptions=True)
    assert result.exit_code == 0, f"afmtool {' '.join(map(str, args))}: {result.output} {result.exception!r}"
    return result.stderr


@pytest.fixture(scope="module")
def ageing(tmp_path_factory):
    base = tmp_path_factory.mktemp("ageing")
    runs = []
    for label, c_a in zip(LABELS, DAMPING):
        name = "mica_" + label.replace(" ", "")
        capture = base / f"{name}.h5"
        _invoke("simulate", "tapping", "-o", capture, "--set", "duration_s=0.02", "--set", "force_set=custom",
                "--set", f"c_a_per_s={c_a}", "--seed", "3")
        _invoke("reep", capture, "--out", base / name, "-q")
        runs.append(base / name)
    out = base / "overlay"
    stderr = _invoke("overlay", *runs, "--labels", ",".join(LABELS), "--out", out)
    return runs, out, stderr


def test_overlay_writes_a_figure_per_quantity_the_csv_and_the_page(ageing):
    runs, out, stderr = ageing
    for quantity in ("f0_hz", "q", "amplitude", "phase_deg", "force_gradient_n_per_m", "energy_per_cycle_ev"):
        assert (out / f"overlay_{quantity}.png").stat().st_size > 5000, quantity
    for quantity in ("f0_hz", "q", "amplitude", "phase_deg"):
        assert (out / f"overlay_time_{quantity}.png").is_file()
    report = json.loads((out / "report.json").read_text())
    validate_report(report)
    assert report["command"] == "overlay" and [r["label"] for r in report["results"]["runs"]] == list(LABELS)
    assert report["headline"] and stderr.startswith("afmtool overlay") and "runs overlaid" in stderr
    page = (out / "report.html").read_text()
    assert "<title>afmtool overlay" in page and page.count("data:image/png;base64,") >= 10
    assert "report.html" in report["outputs"]


def test_the_csv_is_tidy_and_repeats_each_runs_own_numbers(ageing):
    import h5py

    runs, out, _ = ageing
    with open(out / "overlay.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert set(rows[0]) == {"label", "run", "kind", "leg", "x_name", "x", "x_units", "quantity", "value", "units"}
    curves = defaultdict(list)
    for row in rows:
        if row["kind"] == "force_curve" and row["leg"] == "approach" and row["quantity"] == "f0_hz":
            curves[row["label"]].append(float(row["value"]) if row["value"] else np.nan)
    assert list(curves) == list(LABELS)
    for label, run in zip(LABELS, runs):
        with h5py.File(run / "reep.h5", "r") as h5:
            expected = h5["force_curve/approach/f0_hz"][()]
        np.testing.assert_array_equal(np.array(curves[label]), expected)
    assert {row["kind"] for row in rows} == {"force_curve", "time_series"}
    assert all(row["units"] == "Hz" for row in rows if row["quantity"] == "f0_hz")


def test_ageing_shows_in_the_overlaid_damping(ageing):
    # the tip-sample damping c_ts at the turn of the approach grows with c_a, run by run
    import h5py

    runs, _, _ = ageing
    peaks = []
    for run in runs:
        with h5py.File(run / "reep.h5", "r") as h5:
            peaks.append(float(np.nanmax(h5["force_curve/approach/energy_per_cycle_ev"][()])))
    print("largest energy per cycle (eV) by age:", dict(zip(LABELS, np.round(peaks, 2))))
    assert peaks == sorted(peaks)


def test_labels_from_metadata_and_refusals(ageing, tmp_path):
    runs, _, _ = ageing
    _invoke("overlay", *runs[:2], "--label-key", "parameters.c_a_per_s", "--vs", "separation", "--out", tmp_path / "m", "-q")
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    assert [r["label"] for r in report["results"]["runs"]] == ["parameters.c_a_per_s = 10000", "parameters.c_a_per_s = 20000"]
    assert all(r["contact_z"] is not None for r in report["results"]["runs"])
    for args, message in (([runs[0]], "two or more"), ([*runs[:2], "--labels", "a"], "one per run"),
                          ([*runs[:2], "--label-key", "no.such.key"], "no 'no.such.key'")):
        result = run_cli("overlay", *args, "--out", tmp_path / "x")
        assert result.returncode == 2 and message in result.stderr.decode(), (args, result.stderr)
