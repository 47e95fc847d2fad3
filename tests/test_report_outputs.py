"""What a scientist reads (issue 18): figures with units and the truth, the headline, the HTML page.

The analyses run once, in this process, with ``Figure.savefig`` wrapped so
that every figure is inspected just before it is saved: every axis that
shows ticks has a label ending in its units in parentheses (a stacked
panel may leave its x label to the shared bottom axis), every colour bar
names its quantity and units.  The same output folders then feed the HTML
tests: the headline against report.json, the numbers the page renders
against report.json, and, in headless Chromium, the headline and the first
figure above the fold of a 1280×800 window.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from tests.conftest import SAMPLE_DATA, SHARED, run_cli, validate_report

#: A label ends in its units: "f0' (Hz)", "Q' (dimensionless)", "PSD (dB re 1 nm²/Hz)".
UNITS_AT_END = re.compile(r"\(([^()]*[^()\s][^()]*)\)\s*$")
_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.tmp-[0-9a-f]+\.png$")

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]

#: Runs made in process: name -> arguments after ``afmtool`` (``{out}`` is the run's folder).
RUNS = {
    # the README's first command, verbatim (run in a folder where sample_data/ links to the bundled data)
    "readme": ["reep", "sample_data/ltv_step.h5", "--out", "results/reep"],
    "reep_scan": ["reep", str(SAMPLE_DATA / "raster_grating.h5"), "--out", "{out}"],
    "probeloss": ["probeloss", str(SAMPLE_DATA / "raster_grating.h5"), "--out", "{out}"],
    "decode": ["decode", str(SAMPLE_DATA / "bits_30khz.h5"), "--bit-rate", "30000", "--out", "{out}"],
    "bank": ["kalman-bank", str(SAMPLE_DATA / "tapping_force_curve.h5"), "--out", "{out}"],
    "gamma": ["identify", "gamma", str(SAMPLE_DATA / "thermal_sweep_near.h5"), "--contact",
              str(SAMPLE_DATA / "thermal_sweep_contact.h5"), "--out", "{out}"],
    "averaging": ["theory", "averaging", "--force-set", "attractive", "--out", "{out}"],
    "observer": ["theory", "observer", "--cycles", "4", "--out", "{out}"],
}
RUNS["sweep"] = ["identify", "freeair", "chirp.h5", "--sweep", "--out", "{out}"]
RUNS["segment"] = ["identify", "freeair", str(SAMPLE_DATA / "ltv_step.h5"), "--out", "{out}"]
RUNS["electrostatic"] = ["identify", "electrostatic", "es.h5", "--out", "{out}"]
# every other command that draws a figure; later runs read earlier runs' folders
RUNS["averaging_q"] = ["theory", "averaging", "--force-set", "attractive", "--q", "50,100,200", "--out", "{out}"]
RUNS["design"] = ["design", "excitation", "--model", "sweep", "--amplitude", "20", "--out", "{out}"]
RUNS["force_curve"] = ["reep", str(SAMPLE_DATA / "tapping_force_curve.h5"), "--out", "{out}"]
RUNS["compare"] = ["theory", "compare", "force_curve", "--out", "{out}"]
RUNS["fit"] = ["theory", "fit", "force_curve", "--out", "{out}"]
RUNS["thermal_sensor"] = ["identify", "thermal", "--iv", "iv.h5", "--z-curve", "z.h5", "--out", "{out}"]
if (SHARED / "data" / "formats" / "fmt-igor-fd_SiN_FD_plot.ibw").is_file():
    RUNS["invols"] = ["identify", "invols", str(SHARED / "data" / "formats" / "fmt-igor-fd_SiN_FD_plot.ibw"),
                      "--out", "{out}"]
#: Made before the runs, in their folder: a chirp sweep of the free-air cantilever.
_CHIRP = ["simulate", "ltv", "-o", "chirp.h5", "--set", "step_time_s=10.0", "--set", "duration_s=0.1",
          "--set", "sweep_span_hz=20000.0", "--set", "drive=chirp"]
if (SHARED / "data" / "thermal_tune_acl_a.csv").is_file():
    RUNS["thermal"] = ["identify", "freeair", "--psd", str(SHARED / "data" / "thermal_tune_acl_a.csv"), "--out", "{out}"]


class FigureRecord(NamedTuple):
    run: str
    name: str
    problems: tuple[str, ...]
    lines: dict  # y label -> {legend label: (x, y)}


def _label_problems(fig, name: str) -> list[str]:
    problems = []
    for ax in fig.axes:
        if not ax.axison:
            continue
        for which in ("x", "y"):
            axis = ax.xaxis if which == "x" else ax.yaxis
            if not axis.get_visible() or len(axis.get_majorticklocs()) == 0:
                continue  # no ticks shown (a colour bar's short side, a twin's hidden x axis)
            label = ax.get_xlabel() if which == "x" else ax.get_ylabel()
            if label:
                if not UNITS_AT_END.search(label):
                    problems.append(f"{name}: {which} label {label!r} has no units in parentheses")
                continue
            shared = (ax.get_shared_x_axes() if which == "x" else ax.get_shared_y_axes()).get_siblings(ax)
            others = [s.get_xlabel() if which == "x" else s.get_ylabel() for s in shared if s is not ax]
            if not any(UNITS_AT_END.search(text) for text in others):
                problems.append(f"{name}: {which} axis of {ax.get_title()!r} has ticks but no label")
    return problems


def _lines(fig) -> dict:
    out = {}
    for ax in fig.axes:
        out.setdefault(ax.get_ylabel(), {}).update(
            {line.get_label(): (np.asarray(line.get_xdata()), np.asarray(line.get_ydata())) for line in ax.get_lines()}
        )
    return out


def _invoke(args: list[str], *, quiet: bool = True) -> str:
    """Run ``afmtool ARGS`` in this process; return what it printed on stderr."""
    from typer.testing import CliRunner

    from afmtool.cli.main import app

    result = CliRunner().invoke(app, [*args, "--quiet"] if quiet else args, catch_exceptions=True)
    assert result.exit_code == 0, f"afmtool {' '.join(args)}: {result.output} {result.exception!r}"
    return result.stderr


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Every run of RUNS in process, each figure inspected as it is saved: (folders, figure records)."""
    from matplotlib.figure import Figure

    from afmtool.report.figure_process import FigureProcess

    base = tmp_path_factory.mktemp("report_outputs")
    (base / "sample_data").symlink_to(SAMPLE_DATA, target_is_directory=True)
    records: list[FigureRecord] = []
    current = {"run": ""}
    original = Figure.savefig

    def inspecting_savefig(self, fname, *args, **kwargs):
        raw = Path(str(fname)).name
        match = _TEMP_NAME.match(raw)
        name = match.group("name") if match else raw
        records.append(FigureRecord(current["run"], name, tuple(_label_problems(self, name)), _lines(self)))
        return original(self, fname, *args, **kwargs)

    folders = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "savefig", inspecting_savefig)
        # the figures are inspected as they are saved, so in this process, not by a figure process
        patch.setattr(FigureProcess, "start", classmethod(lambda cls: cls()))
        patch.chdir(base)
        _invoke(_CHIRP)
        _invoke(["simulate", "es-approach", "-o", "es.h5"])
        _invoke(["simulate", "iv-ramp", "-o", "iv.h5"])
        _invoke(["simulate", "iv-ramp", "-o", "z.h5", "--set", "ramp=z"])
        for run, args in RUNS.items():
            out = base / run
            current["run"] = run
            # not --quiet: the headline each run prints on stderr is checked against its report.json
            STDERR[run] = _invoke([a.format(out=out) for a in args], quiet=False)
            folders[run] = base / "results" / "reep" if run == "readme" else out
    return folders, records


#: What each run of RUNS printed on stderr (its end-of-run headline).
STDERR: dict[str, str] = {}


def test_readme_first_command_writes_f0_q_against_time_with_the_truth(runs):
    import matplotlib.image

    folders, records = runs
    png = folders["readme"] / "reep_time_series.png"
    assert png.is_file()
    pixels = matplotlib.image.imread(png)
    assert pixels.shape[0] > 600 and pixels.shape[1] > 600
    assert float(np.std(pixels[..., :3])) > 0.05  # not blank
    (figure,) = [r for r in records if r.run == "readme" and r.name == "reep_time_series.png"]
    truth = _truth("ltv_step.h5")
    for label, key in (("f0' (Hz)", "f0_hz"), ("Q' (dimensionless)", "q")):
        lines = figure.lines[label]
        assert {"REEP", "truth"} <= set(lines), lines.keys()
        t, drawn = lines["truth"]
        expected = truth[key][np.rint(t * 500000.0).astype(int)]
        np.testing.assert_array_equal(drawn, expected)  # the truth line is the capture's /truth, sample for sample
        assert np.ptp(drawn) > 0  # ltv_step's step is drawn
    # and the report gives the tracking error after the warm-up: f0' follows the step within a few Hz
    report = json.loads((folders["readme"] / "report.json").read_text())
    tracking = report["results"]["truth_tracking"]
    print("median |f0' - f0| =", tracking["f0_hz"]["median_abs"], "Hz; p95 =", tracking["f0_hz"]["p95_abs"], "Hz")
    assert 0 < tracking["f0_hz"]["median_abs"] < 3.0 and tracking["f0_hz"]["p95_abs"] < 30.0
    assert 0 < tracking["q"]["median_abs"] < 2.0


def _truth(name: str) -> dict:
    import h5py

    with h5py.File(SAMPLE_DATA / name, "r") as h5:
        return {key: ds[()] for key, ds in h5["truth"].items()}


def test_every_figure_has_units_on_every_axis(runs):
    folders, records = runs
    problems = [p for r in records for p in r.problems]
    print(f"{len(records)} figures inspected, {len(problems)} problems")
    assert not problems, "\n".join(problems)
    for run, folder in folders.items():
        saved = {r.name for r in records if r.run == run}
        on_disk = {p.name for p in folder.glob("*.png")}
        assert on_disk and on_disk <= saved, f"{run}: {sorted(on_disk - saved)} not inspected"


def test_the_inspection_can_fail():
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("time t (s)")
    ax.set_ylabel("amplitude")
    problems = _label_problems(fig, "bad.png")
    assert problems == ["bad.png: y label 'amplitude' has no units in parentheses"]
    ax.set_xlabel("")
    assert len(_label_problems(fig, "bad.png")) == 2


def test_probeloss_decode_bank_identify_figures_exist(runs):
    folders, _ = runs
    assert {"probeloss_time_series.png", "probeloss_zoom_1.png", "index_trace.png"} <= _pngs(folders["probeloss"])
    assert {"decode_time_series.png", "eye.png", "psd.png", "l0_search.png"} <= _pngs(folders["decode"])
    assert {"bank_rms_vs_time.png", "bank_rms_vs_z.png"} <= _pngs(folders["bank"])
    assert "feedthrough.png" in _pngs(folders["gamma"])
    assert "sweep_bode.png" in _pngs(folders["sweep"])
    if "thermal" in folders:
        assert "thermal_fit.png" in _pngs(folders["thermal"])


def _pngs(folder: Path) -> set[str]:
    return {p.name for p in folder.glob("*.png")}


def test_fitted_model_band_matches_monte_carlo():
    from afmtool.analyses.freeair_outputs import model_magnitude_std, model_response
    from afmtool.models.free_air import FreeAirModel

    model = FreeAirModel(f0_hz=70_000.0, q=200.0, gain=1.0, f0_std_hz=3.0, q_std=2.0, gain_std=0.002,
                         source="sweep", delay_s=1e-6)
    f = np.linspace(69_000.0, 71_000.0, 81)
    rng = np.random.default_rng(20261201)
    draws = np.array([
        np.abs(model_response(FreeAirModel(f0_hz=70_000.0 + 3.0 * a, q=200.0 + 2.0 * b, gain=1.0 + 0.002 * c,
                                           source="sweep", delay_s=1e-6), f))
        for a, b, c in rng.standard_normal((4000, 3))
    ])
    band = model_magnitude_std(model, f)
    # first-order propagation: right to 15 % where |H| is locally linear in the parameters (off the peak's top)
    flank = np.abs(f - 70_000.0) > 200.0
    ratio = band[flank] / draws.std(axis=0)[flank]
    print(f"band / Monte-Carlo std on the flanks: {ratio.min():.3f} .. {ratio.max():.3f}")
    assert np.all(np.abs(ratio - 1.0) < 0.15)


# --------------------------------------------------------------------------- headline


def test_headline_repeats_results(runs):
    from afmtool.report.headline import lookup

    folders, _ = runs
    for run, folder in folders.items():
        report = json.loads((folder / "report.json").read_text())
        validate_report(report)
        for entry in report["headline"]:
            assert lookup(report["results"], entry["source"]) == entry["value"], (run, entry)
            if entry["std_source"]:
                assert lookup(report["results"], entry["std_source"]) == entry["std"], (run, entry)
    names = {run: [e["name"] for e in json.loads((f / "report.json").read_text())["headline"]] for run, f in folders.items()}
    assert "f0' in the free-air segment" in names["readme"] and "Q' after the free-air segment" in names["readme"]
    assert {"probe-loss fraction (index)", "precision (index)", "recall (index)"} <= set(names["probeloss"])
    assert {"BER (EKF decoder)", "BER 95 % upper bound (EKF decoder)"} <= set(names["decode"])


#: A unit is a word such as Hz, nm, N/m, eV, samples, "of time" or "drive periods" after the number.
_UNITS = re.compile(r"\s(?:[A-Za-zµΩ°][\w/·²³^%-]*|of \w+|drive periods|bit/s)")


@pytest.mark.parametrize("run", sorted(RUNS))
def test_every_command_prints_its_headline_on_stderr(runs, run):
    """Issue 31 acceptance: the stderr headline is non-empty, has units and matches report.json, line by line."""
    folders, _ = runs
    report = json.loads((folders[run] / "report.json").read_text())
    printed = [line for line in STDERR[run].splitlines() if line.strip()]
    assert printed[0].startswith(f"afmtool {report['command']}"), printed
    assert printed[-1].startswith("wrote ") and "report.json" in printed[-1], printed
    entries = report["headline"]
    assert entries, f"{run}: empty headline"
    rows = [line for line in printed[1:] if line.startswith("  ")]
    assert len(rows) == len(entries), (rows, entries)
    for row, entry in zip(rows, entries, strict=True):
        name, _, text = row.strip().partition("  ")
        assert name == entry["name"] and text.strip() == entry["text"], (row, entry)
        from afmtool.report.numbers import format_with_units

        assert entry["text"].startswith(format_with_units(entry["value"], entry["std"], entry["units"])), entry
    with_units = [e for e in entries if e["units"]]
    assert with_units and all(_UNITS.search(e["text"]) for e in with_units), entries
    warnings = [line for line in printed if line.startswith("warning: ")]
    shown = len(report["warnings"])
    assert len(warnings) == (shown if shown <= 6 else 7)  # six, then "N more warnings in report.json"


def test_quiet_silences_the_headline_and_json_keeps_stdout(tmp_path):
    quiet = run_cli("identify", "freeair", SAMPLE_DATA / "ltv_step.h5", "--out", tmp_path / "q", "-q")
    assert quiet.returncode == 0 and quiet.stderr == b""
    loud = run_cli("identify", "freeair", SAMPLE_DATA / "ltv_step.h5", "--out", tmp_path / "l")
    text = loud.stderr.decode()
    assert loud.stdout == b"" and "f0 (free air)" in text and " Hz" in text and text.rstrip().endswith(str(tmp_path / "l"))


def test_json_output_carries_the_headline(tmp_path):
    result = run_cli("identify", "freeair", SAMPLE_DATA / "ltv_step.h5", "--out", tmp_path / "fa", "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    printed = json.loads(result.stdout)
    assert printed["headline"] == json.loads((tmp_path / "fa" / "report.json").read_text())["headline"]
    assert [e["name"] for e in printed["headline"]] == ["f0 (free air)", "Q (free air)", "gain"]
    assert all(e["std"] is not None and e["std"] > 0 for e in printed["headline"])


# --------------------------------------------------------------------------- the page


class _Cards(HTMLParser):
    """(data-source, rendered number, rendered units) of every headline card."""

    def __init__(self) -> None:
        super().__init__()
        self.cards: list[list[str]] = []
        self._field: str | None = None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if attrs.get("class") == "card":
            self.cards.append([attrs.get("data-source", ""), "", ""])
        elif attrs.get("class") in ("number", "units") and self.cards:
            self._field = attrs["class"]

    def handle_endtag(self, tag):
        self._field = None

    def handle_data(self, data):
        if self._field and self.cards:
            self.cards[-1][1 if self._field == "number" else 2] += data


def _page(folder: Path) -> str:
    _invoke(["report", str(folder)])
    return (folder / "report.html").read_text(encoding="utf-8")


@pytest.mark.parametrize("run", ["readme", "probeloss", "decode", "bank", "gamma", "sweep", "electrostatic"])
def test_rendered_numbers_match_report_json(runs, run):
    folders, _ = runs
    report = json.loads((folders[run] / "report.json").read_text())
    parser = _Cards()
    parser.feed(_page(folders[run]))
    assert len(parser.cards) == len(report["headline"]) > 0
    for (source, number, units), entry in zip(parser.cards, report["headline"], strict=True):
        assert source == entry["source"] and units == entry["units"]
        value = entry["value"]
        if isinstance(value, bool):
            assert number == ("yes" if value else "no")
            continue
        assert number + (f" {units}" if units else "") == entry["text"].split(" at ")[0].split(" (")[0], (entry, number)
        if entry["std"] is None:
            assert " ± " not in number
            # four significant digits (afmtool.report.numbers), never fewer left of the point
            assert math.isclose(float(number), value, rel_tol=5e-4, abs_tol=1e-300), (entry, number)
        else:
            match = re.fullmatch(r"\(?(-?[\d.]+) ± ([\d.]+)\)?(?:e([-+]\d+))?", number)
            assert match, number
            shown, shown_std, exponent = match.group(1), match.group(2), int(match.group(3) or 0)
            scale = 10.0**exponent
            # rounded to the second significant digit of the deviation, value to the same decimal
            decimals = len(shown.partition(".")[2]) or -(len(shown_std) - 2)
            assert abs(float(shown) * scale - value) <= (0.5 * 10.0**-decimals + 1e-12) * scale, (entry, number)
            assert abs(float(shown_std) * scale - entry["std"]) <= (0.5 * 10.0**-decimals + 1e-12) * scale, (entry, number)
            assert 10 <= round(float(shown_std) * 10.0**decimals) < 100 or float(shown_std) == 0, (entry, number)


def test_page_order_headline_figures_warnings_details(runs):
    folders, _ = runs
    page = _page(folders["bank"])  # the bundled force curve fails the bank's verdict: a warning
    order = [page.index(marker) for marker in (
        'id="headline"', 'id="figures"', 'id="warnings"', '<details id="inputs">', '<details id="parameters">')]
    assert order == sorted(order)
    assert re.search(r'class="warning-flag[^"]*" href="#warnings"', page) and 'class="warning ' in page
    main = re.search(r'<figure class="main"><img alt="([^"]+)"', page)
    assert main and main.group(1) == "bank_rms_vs_time"
    digest = json.loads((folders["bank"] / "report.json").read_text())["inputs"][0]["hash"]
    assert digest["algorithm"] == "xxh3-128" and digest["value"] in page  # the full hash, in the collapsed inputs
    assert "src=\"http" not in page and "href=\"http" not in page


def test_a_symlinked_png_is_not_embedded_and_a_fifo_is_not_read(runs, tmp_path):
    folders, _ = runs
    folder = tmp_path / "run"
    folder.mkdir()
    for name in ("report.json", "decode_time_series.png"):
        shutil.copy(folders["decode"] / name, folder / name)
    outside = tmp_path / "private.png"
    shutil.copy(folders["decode"] / "eye.png", outside)
    (folder / "linked.png").symlink_to(outside)
    os.mkfifo(folder / "fifo.png")  # nobody writes it: reading it would block forever
    result = run_cli("report", folder, "-q")  # a hang would hit run_cli's timeout
    assert result.returncode == 0, result.stderr.decode()
    page = (folder / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 1
    assert 'alt="linked"' not in page and 'alt="fifo"' not in page
    # a report.json that is a link is refused as a whole
    (folder / "report.json").rename(tmp_path / "report.json")
    (folder / "report.json").symlink_to(tmp_path / "report.json")
    refused = run_cli("report", folder)
    assert refused.returncode == 2 and "not a regular file" in refused.stderr.decode()


@pytest.fixture(scope="module")
def batch_folder(tmp_path_factory):
    pytest.importorskip("dask.distributed")
    out = tmp_path_factory.mktemp("batch") / "batch"
    result = run_cli("batch", "reep", SAMPLE_DATA / "ltv_step.h5", SAMPLE_DATA / "ltv_step.csv", "--out", out,
                     "--workers", "1", "-q")
    assert result.returncode == 0, result.stderr.decode()
    assert run_cli("report", out, "-q").returncode == 0
    return out


def test_batch_page_has_a_row_per_input_with_links(batch_folder):
    page = (batch_folder / "report.html").read_text()
    links = re.findall(r'<a href="([^"]+)/report.html">', page)
    assert sorted(links) == ["ltv_step_csv", "ltv_step_h5"]
    for link in links:
        assert (batch_folder / link / "report.html").is_file()
    assert page.count('<tr><td title="') == 2 and "ltv_step.h5</code>" in page  # file names, the path as title
    assert page.count('class="thumb"') == 2
    assert "f0&#x27; in the free-air segment" in page or "f0' in the free-air segment" in page


def _chromium() -> str:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("headless Chromium is not installed (Debian package chromium)")
    return chromium


_LAYOUT_SCRIPT = """<script>addEventListener("load", () => {
  const box = (sel) => { const e = document.querySelector(sel); if (!e) return null;
    const r = e.getBoundingClientRect(); return {top: r.top, bottom: r.bottom, height: r.height, width: r.width,
      left: r.left, right: r.right}; };
  const body = getComputedStyle(document.body);
  const content = document.body.clientWidth - parseFloat(body.paddingLeft) - parseFloat(body.paddingRight);
  document.body.setAttribute("data-layout", JSON.stringify({headline: box("#headline"),
    figure: box("#figures figure img, #runs img.thumb"), table: box("#runs table"), viewport: innerHeight,
    viewport_width: innerWidth,
    content: content, scroll_width: document.documentElement.scrollWidth, title: document.title,
    h1: document.querySelector("h1").textContent}));
});</script>"""

#: The windows the page is checked in (issue 31): a laptop and a phone.
WINDOWS = {"desktop": (1280, 900), "phone": (390, 844)}


#: Headless Chromium will not make a window narrower than this, so a phone is a frame of its width inside one.
_NARROWEST_WINDOW = 500

_FRAME_PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"></head><body style="margin:0">
<iframe id="phone" src="{src}" width="{width}" height="{height}" style="border:0"></iframe>
<script>document.getElementById("phone").addEventListener("load", (e) => {{
  const inner = e.target.contentDocument.body;
  const copy = () => {{ const d = inner.getAttribute("data-layout");
    if (d) document.body.setAttribute("data-layout", d); else setTimeout(copy, 20); }};
  copy();
}});</script></body></html>"""


def _layout(chromium: str, folder: Path, html_text: str, size: tuple[int, int], profile: Path) -> dict:
    """The page's layout in a window of ``size``; a phone's width is a frame of that width (see above)."""
    probe = folder / "layout_probe.html"  # beside the page, so that the batch page's thumbnails resolve alike
    probe.write_text(html_text.replace("</body>", _LAYOUT_SCRIPT + "</body>"))
    target = probe
    window = size
    if size[0] < _NARROWEST_WINDOW:
        target = folder / "layout_phone.html"
        target.write_text(_FRAME_PAGE.format(src=probe.name, width=size[0], height=size[1]))
        window = (_NARROWEST_WINDOW, size[1])
    common = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={window[0]},{window[1]}",
              "--allow-file-access-from-files"]
    try:
        dom = subprocess.run([*common, "--dump-dom", target.as_uri()], capture_output=True, text=True, timeout=120).stdout
    finally:
        probe.unlink()
        if target != probe:
            target.unlink()
    match = re.search(r'data-layout="([^"]+)"', dom)
    assert match, "the page did not load"
    import html as html_module

    return json.loads(html_module.unescape(match.group(1)))


@pytest.mark.parametrize("window", sorted(WINDOWS))
@pytest.mark.parametrize("run", ["readme", "probeloss", "compare", "batch"])
def test_page_in_chromium_title_headline_and_a_full_width_figure(runs, batch_folder, run, window, tmp_path):
    """Issue 31: the main figure fills the content width, the title names the command and the input."""
    chromium = _chromium()
    folders, _ = runs
    folder = batch_folder if run == "batch" else folders[run]
    page = (folder / "report.html") if run == "batch" else None
    html_text = page.read_text() if page else _page(folder)
    size = WINDOWS[window]
    layout = _layout(chromium, folder, html_text, size, tmp_path / "profile")
    print(run, window, layout)
    report = None if run == "batch" else json.loads((folder / "report.json").read_text())
    if report is not None:
        from afmtool.report.headline import run_subject

        assert layout["title"] == f"afmtool {report['command']} — {run_subject(report)}" == layout["h1"]
        assert "report.json" not in layout["title"]
        if report["command"].startswith("theory"):
            assert layout["title"].endswith(" — force_curve")  # the REEP run compared, not its report.json
    fold = min(size[1], layout["viewport"])
    assert layout["headline"]["height"] > 0 and layout["headline"]["top"] < fold
    assert layout["scroll_width"] <= size[0] + 1, "the page scrolls sideways"
    if run == "batch":
        assert layout["table"]["right"] <= size[0]
        assert layout["figure"]["height"] > 20 or window == "phone"  # a phone's table drops the thumbnails
    else:
        assert layout["figure"]["width"] >= 0.97 * layout["content"], layout  # fills the content width
        assert layout["figure"]["top"] < fold  # and starts above the fold
    assert layout["viewport_width"] == size[0]
    shot = tmp_path / "shot.png"
    width = max(size[0], _NARROWEST_WINDOW)
    common = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", f"--window-size={width},{size[1]}"]
    subprocess.run([*common, f"--screenshot={shot}", (folder / "report.html").as_uri()], capture_output=True, timeout=120)
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (size[1], width)
    assert float(np.std(pixels[..., :3])) > 0.05  # not a blank page


def test_reep_rows_flagged_in_reep_h5_are_left_out_and_marked(tmp_path):
    import h5py

    from afmtool.analyses.reep_timeseries import read_thinned, segment_statistics, tracking_error

    fs, n = 500_000.0, 4000
    t = (np.arange(n) * 7 + 6) / fs
    f0 = np.full(n, 70_000.0)
    q = np.full(n, 200.0)
    flag = np.zeros(n, dtype=np.uint8)
    flag[1000:1100] = 4  # a validity check failed there: the fitted values are kept but not trusted
    f0[1000:1100], q[1000:1100] = 90_000.0, 5.0
    path = tmp_path / "reep.h5"
    with h5py.File(path, "w") as h5:
        for name, values in {"t": t, "f0_hz": f0, "q": q, "amplitude": np.ones(n), "phase_deg": np.zeros(n),
                             "flag": flag}.items():
            h5[name] = values
    stats = segment_statistics(path, 0.0, None).settled
    assert stats.f0_hz.mean == 70_000.0 and stats.f0_hz.count == n - 100
    truth = {"f0_hz": np.full(n * 7 + 7, 70_000.0), "q": np.full(n * 7 + 7, 200.0)}
    error = tracking_error(path, truth, fs, 0.0)
    assert error.f0_hz.p95_abs == 0.0 and error.rows_compared == n - 100
    marked = read_thinned(path, ("f0_hz",))
    np.testing.assert_array_equal(marked.flagged_t, t[1000:1100])


@pytest.mark.parametrize("expected_rows", [None, 10_000, 50_001])
def test_thinned_rows_in_the_stream_are_every_kth_row_and_the_flagged_rows(rng, expected_rows):
    from afmtool.analyses import reep_timeseries
    from afmtool.analyses.reep_timeseries import ThinnedRows

    n = 50_001
    t = np.arange(n) / 1e3
    f0 = 7e4 + rng.standard_normal(n)
    flag = (rng.random(n) < 0.3).astype(np.uint8)
    f0[::1000] = np.nan  # not finite: marked even with flag 0
    flag[::1000] = 0
    thinned = ThinnedRows(("f0_hz", "q"), expected_rows)
    cuts = np.unique(np.r_[0, rng.integers(0, n, 40), n])
    for a, b in zip(cuts[:-1], cuts[1:]):
        thinned.add(t[a:b], {"f0_hz": f0[a:b], "q": 2 * f0[a:b]}, flag[a:b])
    got = thinned.result()
    rows = np.rint(got.t * 1e3).astype(int)
    step = rows[1]
    assert got.t.size <= 2 * reep_timeseries.MAX_PLOT_POINTS and (expected_rows is None or step >= 2)
    np.testing.assert_array_equal(rows, np.arange(0, n, step))  # as reep.h5[::step]
    np.testing.assert_array_equal(got.columns["q"], 2 * f0[::step])
    bad = np.flatnonzero((flag != 0) | ~np.isfinite(f0))
    marks = np.rint(got.flagged_t * 1e3).astype(int)
    flag_step = int(np.searchsorted(bad, marks[1]))
    assert marks.size <= 2 * reep_timeseries._MAX_FLAG_MARKS
    np.testing.assert_array_equal(marks, bad[::flag_step])
    np.testing.assert_array_equal(got.flagged["f0_hz"], f0[bad[::flag_step]])
