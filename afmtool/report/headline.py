"""The headline of a run: the few numbers a reader looks for first, declared once per command.

Each command's ``results`` hold every number a run produced (77 rows for a
force curve); the headline picks the handful that answer the question the
command was run for, each with its units and, where the analysis gives one,
its uncertainty: f0' and Q' in and after the free-air segment, the
tracking error against the truth, the probe-loss fraction with precision
and recall, the BER with its 95 % bound, the spring constant by each
method, the verdict of a comparison with its worst bins.

:data:`HEADLINES` holds them, declared once per command on its result
record (``HEADLINE``, :mod:`afmtool.records`; the record is the ``result`` of the
command's :class:`~afmtool.config.commands.CommandSpec`): a tuple of :class:`Item`
(label, path in ``results``, units, the path of its standard deviation, the path
of where it occurs).  :func:`headline` reads that
declaration into ``report.json``'s ``headline``; every other reader takes
the report's block and nothing else: the end-of-run lines on the terminal
(:func:`terminal_lines`), ``afmtool batch``'s ``summary.csv``
(:func:`summary_columns`) and the HTML page.  Nothing here is computed
anew: every entry is read from ``results`` at the path it names
(``source``); an analysis that wants a number headlined puts it in its
results first.  Numbers are written by :mod:`afmtool.report.numbers`.

A headline never contradicts the run (issue 28).  Where the results say
that the run's premise failed, the headline opens with that state, a text
entry named ``"warning"`` whose ``source`` is the number that says so
(the ``STATES`` of the command's result record), and the items
declared as ``scores`` are left out:

* a free-air phase misfit above 30° (``free_air_route.phase_misfit_deg``,
  :func:`afmtool.records.common.phase_state`): the model the observer runs on
  does not fit the capture; probeloss shows no precision, recall or latency;
* probeloss (:class:`afmtool.records.probeloss.ProbeLossResults`): the switch
  reading loss more than half the time; a capture predicted beyond the
  detection limit (``detectability``); event precision and recall against
  ``/truth`` that disagree with the time-weighted precision (more than 0.1
  apart) are left out, with the reason;
* reep (:class:`afmtool.records.reep.ReepResults`): a free-air f0′ more than
  5 of its standard deviations from the lever's f0 (``free_air_check``) comes
  first; then, when more than half of REEP's rows are flagged, why
  (``validity.mostly_flagged``); and an output-only run (no dither: FM-KPFM,
  self-oscillation) says that Q′ is not identifiable, and shows no Q′ item
  (``q_identifiable``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from afmtool.config.commands import headlines
from afmtool.records import Item, Record, State
from afmtool.report.numbers import format_measurement, format_with_units

__all__ = [
    "HEADLINES", "HEADLINE_FIELDS", "STATE_NAME", "Item", "State", "headline", "lookup", "run_subject",
    "summary_columns", "terminal_lines",
]

#: ``name`` of a headline entry that states the run's state instead of a number.
STATE_NAME = "warning"

#: Keys of one headline entry (``schemas/report.schema.json``, ``headline.items``).
HEADLINE_FIELDS = ("name", "value", "std", "units", "source", "std_source", "at", "note", "text")


def lookup(results: Mapping, path: str) -> Any:
    """The value at the dotted ``path`` of ``results`` (``"truth.index.recall"``), or None."""
    value: Any = results
    for part in path.split("."):
        if isinstance(value, Mapping) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.isdigit() and int(part) < len(value):
            value = value[int(part)]
        else:
            return None
    return value


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _units(results: Mapping, units: str) -> str:
    if units.startswith("@"):
        found = lookup(results, units[1:])
        return found if isinstance(found, str) else ""
    return units


# --------------------------------------------------------------------------- the declarations

#: Each command's headline, in reading order: the ``HEADLINE`` of its result record.
HEADLINES: Mapping[str, tuple[Item, ...]] = headlines()


# --------------------------------------------------------------------------- report.json's block

#: Units that count things, and their singular for a count of one.
_SINGULAR = {"samples": "sample", "events": "event", "filters": "filter", "bits": "bit", "runs": "run",
             "drive periods": "drive period"}


def _entry(item: Item, results: Mapping) -> dict | None:
    value = lookup(results, item.path)
    if value is None or (not item.text and not _number(value)):
        return None
    if item.text and not isinstance(value, (str, bool)) and not _number(value):
        return None
    std_source = item.std
    std = lookup(results, std_source) if std_source else None
    if not _number(std):
        std, std_source = None, None
    units = _units(results, item.units)
    if value == 1 and not isinstance(value, bool):
        units = _SINGULAR.get(units, units)  # "1 sample", not "1 samples"
    at = None
    if item.at is not None:
        where = lookup(results, item.at)
        if _number(where):
            at = {"name": item.at_label, "value": where, "units": _units(results, item.at_units), "source": item.at}
    note = lookup(results, item.note) if item.note else None
    note = note if isinstance(note, str) else None
    text = format_with_units(value, std, units)
    if at is not None:
        text += f" at {at['name']} = {format_with_units(at['value'], None, at['units'])}"
    if note:
        text += f" ({note})"
    return {"name": item.label, "value": value, "std": std, "units": units, "source": item.path,
            "std_source": std_source, "at": at, "note": note, "text": text}


def headline(command: str, results: Record | Mapping) -> list[dict]:
    """The headline entries of ``command``'s ``results`` (JSON-ready), in reading order.

    ``results`` is the command's root :class:`~afmtool.records.Record`: its
    ``HEADLINE`` items and ``STATES`` rules are the declaration read here.  The
    JSON form of the results (report.json's ``results``, or part of it) is read by
    the same items (:data:`HEADLINES`), without the states, which read the record.
    Each entry is ``{"name", "value", "std", "units", "source", "std_source", "at", "note", "text"}``:
    ``value`` is ``results`` at the dotted path ``source`` and ``std`` (its
    standard deviation, or None) at ``std_source``; ``units`` is ``""`` for a
    dimensionless number; ``at`` (or None) says where the value occurs
    (``{"name", "value", "units", "source"}``), ``note`` (or None) its
    standing ("identified"); ``text`` is the entry as the terminal and the
    page write it, by :mod:`afmtool.report.numbers`.  An
    item whose source the run lacks is left out.  Entries named
    :data:`STATE_NAME` (text) come first: the run's state where it undermines
    its own numbers (module docstring), and the scores it undermines are left out.
    """
    if isinstance(results, Record):
        rules, declared, subject = type(results).STATES, type(results).HEADLINE, results
        results = results.to_json()
    else:
        rules, declared, subject = (), HEADLINES.get(command, ()), results
    states: list[State] = []
    for rule in rules:
        state = rule(subject, any(s.hides_scores for s in states))
        if state is not None:
            states.append(state)
    hide_scores = any(s.hides_scores for s in states)
    items = [item for item in declared
             if not (item.scores and hide_scores) and not (item.needs and lookup(results, item.needs) is False)]
    entries = [entry for entry in (_entry(item, results) for item in items) if entry is not None]
    said = [{"name": STATE_NAME, "value": s.text, "std": None, "units": "", "source": s.source, "std_source": None,
             "at": None, "note": None, "text": s.text} for s in states]
    return said + entries


# --------------------------------------------------------------------------- its readers


def summary_columns(report: Mapping) -> dict[str, Any]:
    """``summary.csv``'s columns of one run: each headline entry by its source path (and std, and where)."""
    columns: dict[str, Any] = {}
    for entry in report.get("headline") or []:
        columns[entry["source"]] = entry["value"]
        if entry.get("std_source"):
            columns[entry["std_source"]] = entry["std"]
        if entry.get("at"):
            columns[entry["at"]["source"]] = entry["at"]["value"]
    return columns


def run_subject(report: Mapping) -> str:
    """What a run was run on, for a title: the first input's file name, or its folder's for afmtool's own files.

    ``theory compare fc`` records ``fc/report.json`` as its input: its subject is ``fc``.
    """
    runs = (report.get("results") or {}).get("runs") if report.get("command") == "overlay" else None
    if isinstance(runs, list) and runs:  # an overlay: its runs, by label
        labels = [str(run.get("label")) for run in runs if isinstance(run, Mapping)]
        return ", ".join(labels) if len(labels) <= 6 else f"{', '.join(labels[:3])} … {labels[-1]} ({len(labels)} runs)"
    inputs = report.get("inputs") or []
    if not inputs or not isinstance(inputs[0], Mapping):
        return ""
    path = str(inputs[0].get("path") or "").rstrip("/")
    parts = path.replace("\\", "/").split("/")
    name = parts[-1]
    if name in _OWN_FILES and len(parts) > 1 and parts[-2] not in ("", "."):
        return parts[-2]
    return name


#: afmtool's own output files that a later command reads: their folder names the run.
_OWN_FILES = frozenset({"report.json", "free_air.json", "reep.h5", "thermal_sensor.json", "gamma.h5", "fit.json",
                        "lines.json", "electrostatic.json"})

#: Warnings printed at the end of a run; the rest are counted (report.json has them all).
TERMINAL_WARNINGS = 6


def terminal_lines(report: Mapping, out: str) -> list[str]:
    """The end-of-run lines on stderr: what ran, the headline aligned, the warnings, where the files went."""
    command = str(report.get("command", ""))
    subject = run_subject(report)
    lines = [f"afmtool {command}" + (f" · {subject}" if subject else "")]
    entries: Sequence[Mapping] = report.get("headline") or []
    width = max((len(str(e["name"])) for e in entries), default=0)
    for entry in entries:
        text = entry.get("text") or format_measurement(entry.get("value"), entry.get("std"))
        lines.append(f"  {str(entry['name']).ljust(width)}  {text}")
    warnings = [str(w) for w in report.get("warnings") or []]
    for warning in warnings[:TERMINAL_WARNINGS]:
        lines.append(f"warning: {warning}")
    if len(warnings) > TERMINAL_WARNINGS:
        more = len(warnings) - TERMINAL_WARNINGS
        lines.append(f"warning: {more} more warning{'s' if more != 1 else ''} in report.json")
    outputs = ", ".join(str(name) for name in report.get("outputs") or [])
    lines.append(f"wrote {outputs} to {out}")
    return lines
