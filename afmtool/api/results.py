"""What the API's analysis functions return: the run's output folder, held, read and saved.

A :class:`Result` is a thin, frozen wrapper over what the command wrote: its
``report.json`` and the files beside it, in a private folder the object owns
(removed when it is garbage-collected).  ``.save(out)`` writes exactly the
CLI's output folder (the same files, copied, committed atomically).  Typed
per-command records (issue 29) are what :attr:`Result.results` gives.
"""

from __future__ import annotations

import json
import queue
import shutil
import threading
import weakref
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    import xarray

__all__ = ["Headline", "Summary", "Result", "ChunkResult", "ChunkQueue"]


@dataclass(frozen=True)
class Headline:
    """One headline number: what it is, its value, standard deviation and units (as ``report.json`` has it)."""

    name: str
    value: Any
    std: float | None
    units: str
    text: str
    source: str | None = None


class Summary(tuple):
    """The run's headline numbers, in reading order; ``summary["f0' in the free-air segment"]`` by name."""

    def __getitem__(self, key):  # type: ignore[override]
        if isinstance(key, str):
            for entry in self:
                if entry.name == key or entry.source == key:
                    return entry
            raise KeyError(key)
        return tuple.__getitem__(self, key)

    def to_dict(self) -> dict[str, Any]:
        """``{name: value}``."""
        return {entry.name: entry.value for entry in self}

    def __repr__(self) -> str:
        return "\n".join(f"{e.name}: {e.text}" for e in self) or "(no headline)"

    def _repr_html_(self) -> str:
        from afmtool.report.html import headline_cards

        return headline_cards([{"name": e.name, "text": e.text, "value": e.value, "std": e.std, "units": e.units}
                               for e in self])


def _remove(folder: str) -> None:
    shutil.rmtree(folder, ignore_errors=True)


@dataclass(frozen=True, repr=False)
class Result:
    """A finished run of one command.

    Attributes
    ----------
    command : str
        The CLI command it is (``"reep"``, ``"identify freeair"``).
    folder : Path
        The private folder holding the outputs (use :meth:`save` to keep them).
    """

    command: str
    folder: Path
    _report_text: str = field(default="", repr=False)

    @classmethod
    def own(cls, command: str, folder: Path, owner_root: Path) -> Result:
        """The result in ``folder``; ``owner_root`` is removed with the object."""
        result = cls(command, Path(folder), (Path(folder) / "report.json").read_text(encoding="utf-8"))
        weakref.finalize(result, _remove, str(owner_root))
        return result

    @property
    def report(self) -> dict:
        """``report.json`` as a dict (a fresh copy)."""
        return json.loads(self._report_text)

    @property
    def results(self) -> Any:
        """``report.json``'s ``results``: the command's typed result record (``afmtool.records``).

        ``inv.results.invols_nm_per_v``, ``run.results.segments.free_air.f0_hz.mean``.
        """
        from afmtool.config.commands import SPECS

        return SPECS[self.command].result.load().from_json(self.report["results"])

    @property
    def parameters(self) -> dict:
        """The effective parameters (defaults < config < keywords), as in ``config.toml``."""
        return self.report["parameters"]

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(self.report["warnings"])

    @property
    def outputs(self) -> tuple[str, ...]:
        """The files of the output folder."""
        return tuple(self.report["outputs"])

    @property
    def summary(self) -> Summary:
        """The headline numbers with their units and uncertainties (the ``HEADLINE`` of the command's record)."""
        return Summary(Headline(e["name"], e["value"], e.get("std"), e.get("units") or "", e.get("text") or "",
                                e.get("source")) for e in self.report.get("headline") or ())

    def path(self, name: str) -> Path:
        """The path of one output file (``"reep.h5"``) in the private folder."""
        if name not in self.outputs:
            from afmtool.errors import InputError

            raise InputError(f"{self.command} wrote no {name!r} (it wrote: {', '.join(self.outputs)})")
        return self.folder / name

    def to_xarray(self) -> xarray.Dataset:
        """The run's arrays and headline as an ``xarray.Dataset`` with units on every variable and coordinate.

        Series on ``time`` (s), force-curve tables on their ``z``, images on ``line``/``pixel``;
        parameters and inputs in ``.attrs`` (:mod:`afmtool.report.labelled`).
        """
        from afmtool.report.labelled import result_dataset

        return result_dataset(self.folder, self.report).load()

    def save(self, out_dir: str | Path, *, wait: bool = False) -> Path:
        """Write the CLI's output folder for this run to ``out_dir`` (atomically; an existing run there is replaced).

        ``wait`` (``afmtool --wait``): wait for another run writing ``out_dir`` instead of failing.
        """
        from afmtool.runtime.outputs import OutputDir
        from afmtool.runtime.run_options import RunOptions, applied

        with applied(RunOptions(wait=wait)), OutputDir(Path(out_dir)) as staged:
            for name in self.outputs:
                source = self.folder / name
                if source.is_dir():
                    shutil.copytree(source, staged.path(name))
                else:
                    shutil.copyfile(source, staged.path(name))
        return Path(out_dir)

    def figures(self) -> dict[str, Path]:
        """The PNG figures, by name, main figure first."""
        from afmtool.report.html import MAIN_FIGURES

        pngs = [n for n in self.outputs if n.endswith(".png")]
        first = [n for n in MAIN_FIGURES.get(self.command, ()) if n in pngs]
        return {n: self.folder / n for n in first + sorted(set(pngs) - set(first))}

    def _repr_html_(self) -> str:
        import base64
        import html

        figures = list(self.figures().values())
        image = ""
        if figures:
            data = base64.b64encode(figures[0].read_bytes()).decode()
            image = f'<img style="max-width:100%" alt="{html.escape(figures[0].name)}" src="data:image/png;base64,{data}">'
        warnings = "".join(f"<li>{html.escape(w)}</li>" for w in self.warnings)
        return (f"<div><h4>afmtool {html.escape(self.command)}</h4>{self.summary._repr_html_()}{image}"
                + (f"<ul>{warnings}</ul>" if warnings else "") + "</div>")

    def __repr__(self) -> str:
        return f"<afmtool result: {self.command}>\n{self.summary!r}"


@dataclass(frozen=True)
class ChunkResult:
    """The rows one chunk of a streamed run produced: the same columns as the output file's series."""

    command: str
    columns: Mapping[str, np.ndarray]
    units: Mapping[str, str]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def to_xarray(self) -> xarray.Dataset:
        """The rows on their ``time`` coordinate (s), with units."""
        from afmtool.report.labelled import require_xarray

        xr = require_xarray()
        time_name = "t" if "t" in self.columns else next((n for n in self.columns if n.startswith("t_")), None)
        dims = ("time",)
        coords = {}
        if time_name is not None:
            coords["time"] = xr.Variable(dims, self.columns[time_name], {"units": "s", "long_name": "time"})
        data = {name: xr.Variable(dims, values, {"units": self.units.get(name) or "1", "long_name": name})
                for name, values in self.columns.items() if name != time_name}
        return xr.Dataset(data, coords=coords, attrs={"command": self.command})


_DONE = object()


class ChunkQueue:
    """The sink a streamed analysis writes to in its own thread; iterating it yields :class:`ChunkResult`.

    At most ``depth`` chunks wait, so a notebook that reads slowly holds the analysis back
    instead of filling memory.  Stopping the iteration early ends the analysis at its next chunk.
    """

    def __init__(self, command: str, units: Mapping[str, str], depth: int = 4) -> None:
        self.command, self.units = command, dict(units)
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stopped = threading.Event()
        self.warnings: tuple[str, ...] = ()

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        if self._stopped.is_set():
            raise _Stopped
        self._put(ChunkResult(self.command, {k: v.copy() for k, v in columns.items()}, self.units))

    def put(self, *args, **kwargs) -> None:
        """Whole arrays (tables, images) are not rows; they come with the file output only."""

    def finish(self, warnings) -> None:
        self.warnings = tuple(warnings)

    def _put(self, item) -> None:
        while True:
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                if self._stopped.is_set():
                    raise _Stopped from None

    def run(self, work) -> Iterator[ChunkResult]:
        """Run ``work(self)`` in a thread and yield the chunks it appends; its exception is raised here."""
        failure: list[BaseException] = []

        def target() -> None:
            try:
                work(self)
            except _Stopped:
                pass
            except BaseException as exc:  # noqa: BLE001 - handed to the iterating thread, raised there
                failure.append(exc)
            finally:
                try:
                    self._put(_DONE)
                except _Stopped:
                    pass

        thread = threading.Thread(target=target, name=f"afmtool-{self.command}-stream", daemon=True)
        thread.start()
        try:
            while True:
                item = self._queue.get()
                if item is _DONE:
                    break
                yield item
        finally:
            self._stopped.set()
            thread.join()
        if failure:
            raise failure[0]


class _Stopped(Exception):
    """The iteration of a streamed run was abandoned."""
