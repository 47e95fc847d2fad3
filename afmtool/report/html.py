"""``afmtool report DIR``: one self-contained HTML page from any output folder.

The page holds the headline numbers, the warnings, the effective parameters,
every PNG of the folder (embedded as data URIs, so the file can be mailed or
archived alone) and the list of files.  It reads only ``report.json`` and the
PNGs; nothing is recomputed.
"""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Iterator, Mapping
from pathlib import Path

from afmtool.errors import InputError

__all__ = ["render_report_html", "headline_rows"]

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 72em; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 1.6em; }
table { border-collapse: collapse; } td, th { border: 1px solid #ddd; padding: .25em .6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.warning { background: #fff4ce; border-left: 4px solid #e0a800; padding: .4em .8em; margin: .3em 0; }
figure { display: inline-block; margin: .5em; vertical-align: top; }
figure img { max-width: 34em; border: 1px solid #eee; }
figcaption { font-size: .9em; color: #555; }
.meta { color: #555; }
"""


def _format(value) -> str:
    if isinstance(value, float):
        if not math.isfinite(value):
            return "—"
        return f"{value:.6g}"
    if value is None:
        return "—"
    return str(value)


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


def render_report_html(folder: Path) -> str:
    """The HTML page for the analysis output ``folder``."""
    report_path = folder / "report.json"
    try:
        report = json.loads(report_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{folder}: no report.json (not an afmtool output folder)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{report_path}: not valid JSON ({exc})") from None
    if not isinstance(report, Mapping) or "command" not in report:
        raise InputError(f"{report_path}: not an afmtool report")
    title = f"afmtool {report['command']}"
    inputs = "".join(
        f"<li><code>{html.escape(str(i.get('path')))}</code> ({html.escape(str(i.get('role')))}; sha256 "
        f"<code>{html.escape(str(i.get('sha256'))[:16])}…</code>)</li>"
        for i in report.get("inputs", [])
    )
    warnings = "".join(f'<div class="warning">{html.escape(w)}</div>' for w in report.get("warnings", []))
    figures = []
    for png in sorted(folder.glob("*.png")):
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        figures.append(
            f'<figure><img alt="{html.escape(png.stem)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(png.name)}</figcaption></figure>"
        )
    files = "".join(f"<li><code>{html.escape(name)}</code></li>" for name in report.get("outputs", []))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>{_STYLE}</style></head>
<body>
<h1>{html.escape(title)}</h1>
<p class="meta">afmtool {html.escape(str(report.get('afmtool_version')))}</p>
<section id="inputs"><h2>Inputs</h2><ul>{inputs or '<li>none</li>'}</ul></section>
<section id="results"><h2>Results</h2>{_table(headline_rows(report.get('results', {})))}</section>
<section id="warnings"><h2>Warnings</h2>{warnings or '<p>none</p>'}</section>
<section id="parameters"><h2>Parameters</h2>{_table(headline_rows(report.get('parameters', {})))}</section>
<section id="figures"><h2>Plots and images</h2>{''.join(figures) or '<p>none</p>'}</section>
<section id="files"><h2>Files</h2><ul>{files}</ul></section>
</body></html>
"""
