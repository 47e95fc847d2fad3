"""The headline, declared once (issue 31 item 1, issue 29 item 2), and the one rule for writing numbers."""

from __future__ import annotations

import math

import pytest

from afmtool.report.headline import HEADLINES, headline, lookup, run_subject, summary_columns, terminal_lines
from afmtool.report.numbers import format_measurement, format_value, format_with_units


@pytest.mark.parametrize(("value", "std", "text"), [
    (80318.41, 1.2957, "80318.4 ± 1.3"),
    (166.63, 0.93, "166.63 ± 0.93"),
    (79692.3, 1285.5, "79700 ± 1300"),  # a deviation of 100 or more: rounded to its second digit
    (1.2431845e-6, 2.0546e-10, "(1.24318 ± 0.00021)e-06"),
    (3.0e7, 2.5e5, "(3.000 ± 0.025)e+07"),
    (0.415082, None, "0.4151"),  # issue 31's examples: four significant digits without a deviation
    (2.19232, None, "2.192"),
    (1.01567, None, "1.016"),
    (80318.41, None, "80318"),  # never fewer digits left of the point
    (9.99996, None, "10.00"),
    (1e-5, None, "1.000e-05"),
    (281, None, "281"),
    (True, None, "yes"),
    (float("nan"), None, "—"),
    (None, None, "—"),
    (5.0, 0.0, "5.000"),  # a zero deviation says nothing: four digits
])
def test_one_rule_for_numbers(value, std, text):
    assert format_measurement(value, std) == text


def test_the_value_is_rounded_where_the_deviation_says():
    # against a naive reading of the rule: the deviation's second significant digit sets the decimal
    for value, std in [(12.345678, 0.0123), (12.345678, 0.123), (12.345678, 1.23), (-4.5e-4, 3.3e-5)]:
        text = format_measurement(value, std)
        body, _, exponent = text.strip("(").partition(")e")
        scale = 10.0 ** int(exponent or 0)
        shown, shown_std = (float(part) * scale for part in body.split(" ± "))
        place = 10.0 ** (math.floor(math.log10(std)) - 1)
        assert abs(shown - value) <= place / 2 + 1e-15 and abs(shown_std - std) <= place / 2 + 1e-15, text


def test_units_follow_the_number():
    assert format_with_units(80318.41, 1.2957, "Hz") == "80318.4 ± 1.3 Hz"
    assert format_with_units(0.5, None, "") == "0.5000"
    assert format_with_units(None, None, "Hz") == "—"
    assert format_value(3) == "3"


def test_a_headline_reads_its_declaration_and_skips_what_a_run_lacks():
    results = {
        "segments": {"free_air": {"f0_hz": {"mean": 80318.41, "std": 1.2957}, "q": {"mean": 166.6, "std": 0.93}}},
        "force_curve": {"approach": {"z_units": "nm", "largest_df0_hz": -9032.8, "largest_df0_z": -26.75,
                                     "smallest_q": 21.52, "smallest_q_z": -26.75}},
        "flagged_samples": 1,
    }
    entries = headline("reep", results)
    names = [e["name"] for e in entries]
    assert names == ["f0' in the free-air segment", "Q' in the free-air segment", "largest Δf0' on approach",
                     "smallest Q' on approach", "flagged output samples"]
    for entry in entries:
        assert lookup(results, entry["source"]) == entry["value"]
    shift = entries[2]
    assert shift["at"] == {"name": "z", "value": -26.75, "units": "nm", "source": "force_curve.approach.largest_df0_z"}
    assert shift["text"] == "-9033 Hz at z = -26.75 nm"
    assert entries[0]["text"] == "80318.4 ± 1.3 Hz"
    assert headline("no such command", results) == []


def _reep(**changes):
    """reep's results on the bundled LTV capture, with ``changes`` and no optional sections besides them."""
    import json

    from afmtool.records.reep import ReepResults
    from tests.golden import GOLDEN_DIR

    golden = ReepResults.from_json(json.loads((GOLDEN_DIR / "reep_ltv_step.json").read_text())["results"])
    bare = dict(free_air_check=None, truth_tracking=None, interaction=None, force_curve=None, flagged_samples=0)
    return golden.replace(**{**bare, **changes})


def test_reep_without_the_dither_shows_no_q_and_says_why():
    """Issue 27 item 3: an output-only run says Q' is not identifiable and shows no Q' item (with it, it does)."""
    from afmtool.records.common import Moments
    from afmtool.records.reep import ForceCurve, ForceCurveLeg, ReepSegments, Segment

    settled = Segment(t_s=(0.002, 0.05), f0_hz=Moments(count=900, mean=60627.8, std=0.7),
                      q=Moments(count=900, mean=1e5, std=1.5e7))
    approach = ForceCurveLeg(bins=3, z_range=(-27.0, 0.0), z_units="nm", f0_hz_range=(6e4, 6.1e4),
                             q_range=(21.5, 1e5), max_abs_df0_dz=None, max_abs_dq_dz=None, max_abs_da_dz=None,
                             smallest_q=21.5, smallest_q_z=-26.75, largest_energy_per_cycle_ev=3.0,
                             largest_energy_per_cycle_z=-20.0)
    results = _reep(segments=ReepSegments(settled=settled), force_curve=ForceCurve(approach=approach),
                    q_identifiable=False)
    entries = headline("reep", results)
    assert entries[0]["name"] == "warning" and "Q' is not identifiable" in entries[0]["text"]
    assert entries[0]["source"] == "q_identifiable"
    names = [e["name"] for e in entries[1:]]
    assert names == ["f0' after the warm-up", "flagged output samples"]
    assert not any("Q'" in n or "energy" in n for n in names)
    shown = [e["name"] for e in headline("reep", results.replace(q_identifiable=True))]
    assert shown == ["f0' after the warm-up", "Q' after the warm-up", "smallest Q' on approach",
                     "largest energy dissipated per cycle", "flagged output samples"]


def test_reep_mostly_flagged_says_why_first():
    """Issue 27 item 3: a run with most rows flagged opens its headline with why; at half or less it does not."""
    why = ("most of REEP's rows are invalid: 80% flagged after the warm-up, mostly (80% of the rows) because "
           "the amplitude is below 1 % of the free amplitude")
    golden = _reep()
    flags = golden.validity.flags.replace(flagged=800, samples=1000, fraction=0.8)
    results = golden.replace(validity=golden.validity.replace(mostly_flagged=why, flags=flags))
    entries = headline("reep", results)
    assert entries[0]["name"] == "warning" and entries[0]["text"].startswith(why)
    assert entries[0]["source"] == "validity.flags.fraction"
    assert [e["name"] for e in entries[1:3]] == ["f0' in the free-air segment", "Q' in the free-air segment"]
    results = golden.replace(validity=golden.validity.replace(mostly_flagged=None))
    assert headline("reep", results)[0]["name"] == "f0' in the free-air segment"


def test_a_fit_parameter_carries_its_standing():
    results = {"parameters": {"omega_a2": {"value": 6.9e10, "std": 2.6e9, "status": "poorly identifiable"}}}
    (entry,) = headline("theory fit", results)
    assert entry["note"] == "poorly identifiable"
    assert entry["text"] == "(6.90 ± 0.26)e+10 1/s² (poorly identifiable)"


@pytest.mark.parametrize("command", ["identify invols", "identify thermal", "theory compare", "theory fit",
                                     "design excitation", "theory averaging", "theory observer", "theory controllers"])
def test_the_commands_issue_31_found_empty_have_a_declaration(command):
    assert HEADLINES[command]


def test_batch_summary_and_terminal_read_the_reports_block():
    report = {
        "command": "reep",
        "inputs": [{"path": "runs/c3.h5"}],
        "headline": headline("reep", {"segments": {"free_air": {"f0_hz": {"mean": 70000.2, "std": 0.2}}},
                                      "flagged_samples": 3}),
        "warnings": [f"w{i}" for i in range(8)],
        "outputs": ["reep.h5", "report.json"],
    }
    assert summary_columns(report) == {"segments.free_air.f0_hz.mean": 70000.2, "segments.free_air.f0_hz.std": 0.2,
                                       "flagged_samples": 3}
    lines = terminal_lines(report, "out/c3")
    assert lines[0] == "afmtool reep · c3.h5"
    assert lines[1] == "  f0' in the free-air segment  70000.20 ± 0.20 Hz"
    assert lines[2] == "  flagged output samples       3 samples"
    assert lines[3:9] == [f"warning: w{i}" for i in range(6)] and lines[9] == "warning: 2 more warnings in report.json"
    assert lines[-1] == "wrote reep.h5, report.json to out/c3"


def test_the_subject_of_a_run_on_a_run_is_its_folder():
    assert run_subject({"inputs": [{"path": "results/fc/report.json"}]}) == "fc"
    assert run_subject({"inputs": [{"path": "lever/free_air.json"}]}) == "lever"
    assert run_subject({"inputs": [{"path": "data/curve.h5"}]}) == "curve.h5"
    assert run_subject({"inputs": []}) == ""


def test_the_page_sets_warning_severity_by_the_share_of_samples(tmp_path):
    import json

    from afmtool.errors import SampleShareWarning
    from afmtool.report.html import render_report_html, warning_severity
    from afmtool.report.json_report import build_report

    one_in_many = SampleShareWarning("1 of 14777 output samples after the warm-up flagged: ...", 1, 14777)
    report = build_report("reep", [{"path": "c.h5", "role": "capture", "hash": None}], {},
                          {"flagged_samples": 1}, ["report.json"], [one_in_many])
    assert report["warning_shares"] == [1 / 14777]
    (entry,) = report["headline"]
    assert entry["units"] == "sample" and entry["text"] == "1 sample"  # not "1 samples"
    (tmp_path / "report.json").write_text(json.dumps(report))
    page = render_report_html(tmp_path)
    assert 'class="warning-flag minor"' in page and 'class="warning minor"' in page  # no red badge
    assert "0.006767 % of the samples" in page
    assert [warning_severity(s) for s in (1 / 14777, 0.05, 0.5, None)] == ["minor", "moderate", "serious", "serious"]
    report = build_report("reep", [], {}, {"flagged_samples": 4000}, ["report.json"],
                          [SampleShareWarning("4000 of 5000 flagged", 4000, 5000), "the drive is off resonance"])
    (tmp_path / "report.json").write_text(json.dumps(report))
    page = render_report_html(tmp_path)
    assert 'class="warning-flag" href' in page and page.count('class="warning serious"') == 2


def test_an_overlay_is_titled_by_its_runs():
    runs = [{"label": label} for label in ("0", "45 min", "2 h", "16 h")]
    assert run_subject({"command": "overlay", "results": {"runs": runs}, "inputs": [{"path": "r/report.json"}]}) == \
        "0, 45 min, 2 h, 16 h"


def test_controllers_and_design_headlines_read_their_results():
    controllers = {"pass": True, "table": [{"line_rate_hz": 4.0, "low": {"loss_area": 0.0658}, "high": {"loss_area": 0.0348},
                                            "switching": {"loss_area": 0.0348, "peak_force_n": 5.07e-8}}]}
    names = [e["name"] for e in headline("theory controllers", controllers)]
    assert names[0] == "verdict: pass" and "peak force, switching gain" in names and "at line rate" in names
    design = {"lines": [{"frequency_hz": 70000.07, "amplitude_v": 0.1, "response_nm": 20.0},
                        {"frequency_hz": 63007.06, "amplitude_v": 0.05}, {"frequency_hz": 76993.08, "amplitude_v": 0.05}],
              "envelope_beat": 0.025, "amplitude_beat": 0.00125, "loop_s": 0.2857}
    texts = {e["name"]: e["text"] for e in headline("design excitation", design)}
    assert texts["main line"] == "70000 Hz" and texts["free-air response"] == "20.00 nm" and texts["loop length"] == "0.2857 s"
