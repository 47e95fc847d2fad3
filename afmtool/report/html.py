"""``afmtool report DIR``: one self-contained HTML page from any output folder.

The page is laid out for a reader, not as a dump of ``report.json``: first
the headline block (the few numbers that matter, with units and
uncertainties: ``report.json``'s ``headline``), then the figures (the
command's main figure first and full width), then the warnings, made
prominent, and last, collapsed in ``<details>``, the inputs (path, hash),
the parameters, every result and the list of files.  Every PNG is embedded
as a data URI, so the file can be mailed or archived alone.  Nothing is
recomputed.

A batch folder (``summary.csv`` and one subfolder per input) gives one page
with a row per input: its status, its headline numbers, a thumbnail of its
main figure and a link to its own page (written beside it).

Only regular files directly inside the folder are read: never through a
symbolic link (a link could pull any file of the machine into a page that
is then mailed), never a FIFO or device (reading one would block or never
end).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
import os
import stat
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from afmtool.config.commands import main_figures
from afmtool.errors import InputError
from afmtool.report.numbers import format_measurement as _measurement
from afmtool.report.numbers import format_value

__all__ = [
    "BATCH_COLUMNS",
    "BATCH_SUMMARY",
    "MAIN_FIGURES",
    "format_measurement",
    "headline_cards",
    "headline_rows",
    "read_regular_file",
    "render_batch_html",
    "render_report_html",
    "report_pages",
]

#: The file a batch folder holds (``afmtool batch``).
BATCH_SUMMARY = "summary.csv"

#: Each command's figures in reading order; figures not named follow, sorted.  Each command's
#: ``main_figures`` (:class:`~afmtool.config.commands.CommandSpec`).
MAIN_FIGURES: Mapping[str, tuple[str, ...]] = main_figures()

#: Headline numbers shown per row of a batch page (each run's own page has all of them).
BATCH_COLUMNS = 4

#: Largest file embedded (bytes): a page stays mailable.
_MAX_EMBED_BYTES = 64 << 20

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 0 auto; padding: 0 1.5em 2em; max-width: 76em; color: #222; }
header { display: flex; align-items: baseline; gap: 1em; flex-wrap: wrap; margin: .8em 0 .4em; }
h1 { font-size: 1.45em; margin: 0; } h2 { font-size: 1.15em; border-bottom: 1px solid #ccc; padding-bottom: .15em; margin: 1.2em 0 .5em; }
.meta { color: #555; font-size: .9em; }
.warning-flag { background: #b00020; color: #fff; border-radius: .3em; padding: .1em .6em; font-size: .9em; text-decoration: none; }
.warning-flag.minor { background: #e8eaed; color: #333; } .warning-flag.moderate { background: #b26a00; }
#headline { display: grid; grid-template-columns: repeat(auto-fill, minmax(14.5em, 1fr)); gap: .4em; margin: .3em 0 .8em; }
.card { border: 1px solid #d6dde6; border-radius: .35em; padding: .3em .6em; background: #f7f9fc; }
.card .name { font-size: .8em; color: #445; } .card .value { font-size: 1.15em; font-variant-numeric: tabular-nums; }
.card .units { color: #445; }
figure { display: inline-block; margin: .4em; vertical-align: top; max-width: 100%; }
figure.main { display: block; margin: .3em 0; } figure.main img { width: 100%; max-width: 100%; height: auto; }
figure img { max-width: min(34em, 100%); height: auto; border: 1px solid #eee; }
figcaption { font-size: .85em; color: #555; }
.warning { background: #fde7e9; border-left: 6px solid #b00020; padding: .5em .9em; margin: .35em 0; font-weight: 500; }
.warning.moderate { background: #fff4e0; border-left-color: #b26a00; } .warning.minor { background: #f3f4f6; border-left-color: #9aa0a6; font-weight: normal; }
.share { color: #555; font-size: .85em; }
table { border-collapse: collapse; } td, th { border: 1px solid #ddd; padding: .2em .55em; text-align: left; vertical-align: top; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
details { margin: .4em 0; } summary { cursor: pointer; font-weight: 600; }
img.thumb { max-height: 7em; max-width: 100%; width: auto; height: auto; border: 1px solid #eee; }
.table-wrap { overflow-x: auto; max-width: 100%; }
table.runs { table-layout: fixed; width: 100%; } table.runs td, table.runs th { overflow-wrap: anywhere; }
table.runs col.input { width: 16%; } table.runs col.status { width: 12%; } table.runs col.link { width: 11%; } table.runs col.figure { width: 17%; }
@media (max-width: 40em) { body { padding: 0 .6em 1em; } #headline { grid-template-columns: 1fr 1fr; } table.runs col.figure { width: 0; } table.runs .fig { display: none; } }
td.num { white-space: nowrap; }
.status-failed { color: #b00020; font-weight: 600; } .status-ok, .status-skipped { color: #1b6e20; }
"""


# --------------------------------------------------------------------------- reading files safely


def read_regular_file(path: Path, limit: int = _MAX_EMBED_BYTES) -> bytes | None:
    """The bytes of ``path`` if it is a regular file reached without a symbolic link, else None.

    ``O_NOFOLLOW`` refuses a link at the last component and ``O_NONBLOCK``
    keeps a FIFO from blocking the open; the type is checked on the open
    descriptor, so a file swapped after a check cannot slip in.
    """
    try:
        if stat.S_ISLNK(os.lstat(path).st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_size > limit:
            return None
        with os.fdopen(fd, "rb", closefd=False) as handle:
            return handle.read(limit + 1)[:limit]
    except OSError:
        return None
    finally:
        os.close(fd)


def _pngs(folder: Path) -> list[tuple[str, bytes]]:
    """(name, bytes) of the regular PNG files directly in ``folder``, by name."""
    found = []
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        if entry.name.lower().endswith(".png") and not entry.name.startswith("."):
            data = read_regular_file(Path(entry.path))
            if data is not None and data.startswith(b"\x89PNG\r\n\x1a\n"):
                found.append((entry.name, data))
    return found


def _png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels from the IHDR chunk, so the page lays out before the images decode."""
    if len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def _load_report(folder: Path) -> dict:
    report_path = folder / "report.json"
    if not os.path.lexists(report_path):
        raise InputError(f"{folder}: no report.json (not an afmtool output folder)")
    data = read_regular_file(report_path)
    if data is None:
        raise InputError(f"{report_path}: not a regular file (a symbolic link, FIFO or device is not read)")
    try:
        report = json.loads(data.decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{report_path}: not valid JSON ({exc})") from None
    if not isinstance(report, Mapping) or "command" not in report:
        raise InputError(f"{report_path}: not an afmtool report")
    return dict(report)


# --------------------------------------------------------------------------- numbers


def _format(value) -> str:
    return format_value(value)


def format_measurement(value, std=None, units: str = "") -> tuple[str, str]:
    """``(number, units)`` as the page shows them: ``("70000.2 ± 1.0", "Hz")``.

    The number is written by :func:`afmtool.report.numbers.format_measurement`,
    the one rule of the terminal, ``report.json``'s headline and the page.
    """
    return _measurement(value, std), units


def headline_rows(results: Mapping, prefix: str = "", depth: int = 0) -> Iterator[tuple[str, str]]:
    """Flatten scalar results (two levels of nesting) into (name, value) rows."""
    for key, value in results.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and depth < 2:
            yield from headline_rows(value, f"{name}.", depth + 1)
        elif isinstance(value, (int, float, str, bool)) or value is None:
            yield name, _format(value)
        elif isinstance(value, list) and len(value) <= 6 and all(isinstance(v, (int, float)) for v in value):
            yield name, ", ".join(_format(v) for v in value)


def _table(rows: Iterator[tuple[str, str]], numeric: bool = True) -> str:
    cells = []
    for name, value in rows:
        css = ' class="num"' if numeric and value[:1] in "-0123456789" else ""
        cells.append(f"<tr><th>{html.escape(name)}</th><td{css}>{html.escape(value)}</td></tr>")
    return "<table>" + "".join(cells) + "</table>" if cells else "<p>none</p>"


def _headline_cards(entries: Sequence[Mapping]) -> str:
    cards = []
    for entry in entries:
        number, units = format_measurement(entry.get("value"), entry.get("std"), str(entry.get("units", "")))
        source = html.escape(str(entry.get("source", "")))
        cards.append(
            f'<div class="card" data-source="{source}"><div class="name">{html.escape(str(entry.get("name")))}</div>'
            f'<div class="value"><span class="number">{html.escape(number)}</span>'
            f'{" " if units else ""}<span class="units">{html.escape(units)}</span></div></div>'
        )
    return "".join(cards)


_NOTEBOOK_CARD_STYLE = (
    "<style>.afmtool-cards{display:flex;flex-wrap:wrap;gap:.5em}.afmtool-cards .card{border:1px solid #ccc;"
    "border-radius:4px;padding:.4em .7em}.afmtool-cards .name{font-size:85%;color:#555}"
    ".afmtool-cards .number{font-size:130%;font-weight:600}</style>"
)


def headline_cards(entries: Sequence[Mapping]) -> str:
    """The headline as cards in a block of its own (a notebook's result display): the page's cards, styled inline."""
    return f'{_NOTEBOOK_CARD_STYLE}<div class="afmtool-cards">{_headline_cards(entries)}</div>'


# --------------------------------------------------------------------------- one run


def _ordered_figures(command: str, pngs: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    preferred = MAIN_FIGURES.get(command, ())
    rank = {name: i for i, name in enumerate(preferred)}
    return sorted(pngs, key=lambda item: (rank.get(item[0], len(rank)), item[0]))


def _img(name: str, data: bytes, css: str = "") -> str:
    size = _png_size(data)
    dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
    encoded = base64.b64encode(data).decode("ascii")
    cls = f' class="{css}"' if css else ""
    return f'<img{cls} alt="{html.escape(Path(name).stem)}"{dims} src="data:image/png;base64,{encoded}">'


def _figures(command: str, folder: Path) -> str:
    figures = []
    for i, (name, data) in enumerate(_ordered_figures(command, _pngs(folder))):
        css = ' class="main"' if i == 0 else ""
        figures.append(f"<figure{css}>{_img(name, data)}<figcaption>{html.escape(name)}</figcaption></figure>")
    return "".join(figures)


def _hash_text(record) -> str:
    """``xxh3-128 of the samples (deflection, dither): 3f…`` or ``sha256 of the file: 9a…``; "none" if not recorded."""
    if not isinstance(record, Mapping):
        return "none"
    over = record.get("over")
    what = f"the samples ({', '.join(map(str, record.get('channels') or []))})" if over == "samples" else "the file"
    return f"{record.get('algorithm')} of {what}: {record.get('value')}"


def _inputs(report: Mapping) -> str:
    rows = []
    for item in report.get("inputs", []):
        rows.append(
            f"<tr><td><code>{html.escape(str(item.get('path')))}</code></td><td>{html.escape(str(item.get('role')))}</td>"
            f"<td><code>{html.escape(_hash_text(item.get('hash')))}</code></td></tr>"
        )
    if not rows:
        return "<p>none</p>"
    return "<table><tr><th>path</th><th>role</th><th>hash</th></tr>" + "".join(rows) + "</table>"


#: A warning about at most this share of the samples is minor (grey); up to MODERATE_SHARE, moderate (amber).
MINOR_SHARE = 0.01
MODERATE_SHARE = 0.1
_SEVERITY_RANK = {"minor": 0, "moderate": 1, "serious": 2}


def warning_severity(share) -> str:
    """``minor``, ``moderate`` or ``serious`` by the share of samples a warning concerns (None: serious)."""
    if not isinstance(share, (int, float)) or isinstance(share, bool) or not math.isfinite(share):
        return "serious"
    return "minor" if share <= MINOR_SHARE else ("moderate" if share <= MODERATE_SHARE else "serious")


def _warnings(report: Mapping) -> tuple[str, str]:
    """(the header's badge, the warning boxes): each warning's colour follows the share of samples it concerns."""
    warnings = [str(w) for w in report.get("warnings", [])]
    shares = list(report.get("warning_shares") or [])
    shares += [None] * (len(warnings) - len(shares))
    if not warnings:
        return "", "<p>none</p>"
    levels = [warning_severity(share) for share in shares[:len(warnings)]]
    worst = max(levels, key=_SEVERITY_RANK.get)
    css = "" if worst == "serious" else f" {worst}"
    badge = f'<a class="warning-flag{css}" href="#warnings">{len(warnings)} warning{"s" if len(warnings) != 1 else ""}</a>'
    boxes = []
    for text, share, level in zip(warnings, shares, levels):
        note = f' <span class="share">({_measurement(100.0 * share)} % of the samples)</span>' if level != "serious" else ""
        boxes.append(f'<div class="warning {level}">{html.escape(text)}{note}</div>')
    return badge, "".join(boxes)


def page_title(report: Mapping) -> str:
    """``afmtool COMMAND — SUBJECT``: the command and what it ran on (a run folder's name for a run on a run)."""
    from afmtool.report.headline import run_subject

    subject = run_subject(report)
    return f"afmtool {report.get('command')}" + (f" — {subject}" if subject else "")


def render_report_html(folder: Path) -> str:
    """The HTML page for the analysis output ``folder``."""
    folder = Path(folder)
    report = _load_report(folder)
    command = str(report["command"])
    title = page_title(report)
    warning_flag, warning_boxes = _warnings(report)
    headline = report.get("headline") or []
    cards = _headline_cards(headline) or '<p class="meta">no headline numbers for this command; see Details.</p>'
    figures = _figures(command, folder) or "<p>none</p>"
    files = "".join(f"<li><code>{html.escape(str(name))}</code></li>" for name in report.get("outputs", []))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>{_STYLE}</style></head>
<body>
<header><h1>{html.escape(title)}</h1><span class="meta">afmtool {html.escape(str(report.get('afmtool_version')))}</span>{warning_flag}</header>
<section id="headline-block" aria-label="headline"><div id="headline">{cards}</div></section>
<section id="figures"><h2>Figures</h2>{figures}</section>
<section id="warnings"><h2>Warnings</h2>{warning_boxes}</section>
<section id="details"><h2>Details</h2>
<details id="inputs"><summary>Inputs</summary>{_inputs(report)}</details>
<details id="parameters"><summary>Parameters</summary>{_table(headline_rows(report.get('parameters', {})))}</details>
<details id="results"><summary>All results</summary>{_table(headline_rows(report.get('results', {})))}</details>
<details id="files"><summary>Files</summary><ul>{files}</ul></details>
</section>
</body></html>
"""


# --------------------------------------------------------------------------- a batch


def _batch_rows(folder: Path) -> list[dict]:
    data = read_regular_file(folder / BATCH_SUMMARY)
    if data is None:
        raise InputError(f"{folder / BATCH_SUMMARY}: not a regular file")
    try:
        return list(csv.DictReader(io.StringIO(data.decode("utf-8"))))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{folder / BATCH_SUMMARY}: not a batch summary ({exc})") from None


def _subfolder(folder: Path, output: str) -> Path | None:
    """The run's subfolder if it lies directly inside ``folder`` and is a real directory (no link)."""
    candidate = folder / Path(output).name
    try:
        if stat.S_ISDIR(os.lstat(candidate).st_mode):
            return candidate
    except OSError:
        pass
    return None


def _short_name(path: str) -> str:
    """An input as a batch table shows it: its file name (the whole path is the cell's title)."""
    name = Path(path).name
    return name or path


def _batch_cell(folder: Path, row: dict, names: list[str]) -> tuple[dict | None, str, str, dict]:
    """One run of a batch page: its report (None if unreadable), link, main figure and headline values.

    Headline names not yet in ``names`` are appended (the page's columns, in order of appearance).
    """
    sub = _subfolder(folder, row.get("output", ""))
    report, figure = None, ""
    if sub is not None and os.path.lexists(sub / "report.json"):
        try:
            report = _load_report(sub)
        except InputError:
            report = None
    if report is not None:
        ordered = _ordered_figures(str(report["command"]), _pngs(sub))
        if ordered:
            figure = _img(*ordered[0], css="thumb")
    values = {}
    for entry in ((report or {}).get("headline") or [])[:BATCH_COLUMNS]:
        name = str(entry.get("name"))
        if name not in names:
            names.append(name)
        number, units = format_measurement(entry.get("value"), entry.get("std"), str(entry.get("units", "")))
        values[name] = f"{number} {units}".strip()
    link = (
        f'<a href="{html.escape(sub.name)}/report.html">{html.escape(sub.name)}</a>' if report is not None
        else html.escape(row.get("output", ""))
    )
    return report, link, figure, values


def render_batch_html(folder: Path) -> str:
    """The page of a batch folder: a row per input, with its headline, main figure and a link."""
    folder = Path(folder)
    rows = _batch_rows(folder)
    names: list[str] = []
    cells = []
    counts = {"ok": 0, "skipped": 0, "failed": 0}
    command = ""
    for row in rows:
        status = row.get("status", "")
        counts[status] = counts.get(status, 0) + 1
        report, link, figure, values = _batch_cell(folder, row, names)
        if report is not None:
            command = command or str(report["command"])
        cells.append((row, status, link, figure, values))
    head = "".join(f"<th>{html.escape(n)}</th>" for n in names)
    body = []
    for row, status, link, figure, values in cells:
        reason = html.escape(row.get("reason", ""))
        numbers = "".join(f'<td class="num">{html.escape(values.get(n, ""))}</td>' for n in names)
        source = row.get("input", "")
        body.append(
            f'<tr><td title="{html.escape(source)}"><code>{html.escape(_short_name(source))}</code></td>'
            f'<td class="status-{html.escape(status)}">{html.escape(status)}{(": " + reason) if reason else ""}</td>'
            f'<td>{link}</td><td class="fig">{figure}</td>{numbers}</tr>'
        )
    done = counts.get("ok", 0) + counts.get("skipped", 0)
    summary_cards = _headline_cards([
        {"name": "inputs", "value": len(rows), "units": "run" if len(rows) == 1 else "runs"},
        {"name": "done", "value": done, "units": "run" if done == 1 else "runs"},
        {"name": "failed", "value": counts.get("failed", 0), "units": "run" if counts.get("failed", 0) == 1 else "runs"},
    ])
    title = f"afmtool batch {command}".rstrip() + f" — {folder.name}"
    failed = counts.get("failed", 0)
    flag = f'<a class="warning-flag" href="#runs">{failed} failed</a>' if failed else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>{_STYLE}</style></head>
<body>
<header><h1>{html.escape(title)}</h1>{flag}</header>
<section id="headline-block" aria-label="headline"><div id="headline">{summary_cards}</div></section>
<section id="runs"><h2>Runs</h2>
<div class="table-wrap"><table class="runs"><colgroup><col class="input"><col class="status"><col class="link"><col class="figure">{"<col>" * len(names)}</colgroup>
<tr><th>input</th><th>status</th><th>report</th><th class="fig">main figure</th>{head}</tr>{''.join(body)}</table></div></section>
</body></html>
"""


def report_pages(folder: Path, output: Path | None = None) -> list[tuple[Path, str]]:
    """Every page ``afmtool report FOLDER`` writes: ``(path, html)``, the folder's own page last.

    An analysis folder gives one page; a batch folder (``summary.csv``, no
    ``report.json``) gives a page per finished run, in its subfolder, and
    the batch page that links to them.
    """
    folder = Path(folder)
    target = Path(output) if output is not None else folder / "report.html"
    if not os.path.lexists(folder / "report.json") and os.path.lexists(folder / BATCH_SUMMARY):
        pages = []
        for row in _batch_rows(folder):
            sub = _subfolder(folder, row.get("output", ""))
            if sub is not None and os.path.lexists(sub / "report.json"):
                try:
                    pages.append((sub / "report.html", render_report_html(sub)))
                except InputError:
                    continue
        pages.append((target, render_batch_html(folder)))
        return pages
    return [(target, render_report_html(folder))]
