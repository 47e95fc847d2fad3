"""``--stream``: run an analysis with its result rows on stdout as each chunk completes.

The analysis writes to a :class:`afmtool.io.rows.RowWriter` instead of an
HDF5 file; small chunks keep the rows close behind the input.  Whole arrays
(tables, images, bits decided at the end) have no place in a row stream and
are dropped; warnings go to stderr.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from afmtool.config import load_toml, resolve_from
from afmtool.io.rows import RowWriter

__all__ = ["STREAM_CHUNK_SAMPLES", "run_stream", "run_stream_with_model"]

#: Chunk size for --stream: small, so rows follow the input closely.
STREAM_CHUNK_SAMPLES = 4096


class _Selected:
    """Pass on only the columns ``names`` of the blocks that hold them (one row schema per stream)."""

    def __init__(self, rows: RowWriter, names: tuple[str, ...]) -> None:
        self._rows = rows
        self._names = names

    def append(self, columns: Mapping) -> None:
        if all(name in columns for name in self._names):
            self._rows.append({name: columns[name] for name in self._names})

    def put(self, *args, **kwargs) -> None:
        """Whole arrays are dropped, as by :meth:`RowWriter.put`."""


def run_stream(
    analysis: Callable[[Any, Any, Any], Any],
    params_cls: type,
    section: str,
    reader,
    config: Path | None,
    flags: Mapping,
    fmt: str,
    *,
    row_columns: tuple[str, ...] | None = None,
) -> None:
    """Resolve ``[section]`` parameters and run ``analysis(reader, params, writer)`` into stdout rows.

    Parameters
    ----------
    analysis : callable
        ``(reader, params, writer) -> result``; ``result.warnings`` is printed to stderr.
    params_cls, section : type, str
        The parameters dataclass and its config-file section.
    reader, config, flags
        As for the command's file output; ``chunk_samples`` is
        :data:`STREAM_CHUNK_SAMPLES` unless a flag sets it.
    fmt : str or sink
        ``"csv"`` or ``"jsonl"`` rows on stdout; or an object with ``append(columns)``,
        ``put(...)`` and ``finish(warnings)`` (``stream=True`` of the Python API).
    row_columns : tuple of str, optional
        For analyses whose blocks hold columns of more than one length: the
        columns of one length that become rows (others are dropped).
    """
    flags = {"chunk_samples": STREAM_CHUNK_SAMPLES, **{k: v for k, v in flags.items() if v is not None}}
    params = resolve_from(params_cls, section, load_toml(config) if config else None, flags)
    if not isinstance(fmt, str):  # the Python API's sink (afmtool.api.results.ChunkQueue): rows as arrays
        result = analysis(reader, params, fmt if row_columns is None else _Selected(fmt, row_columns))
        fmt.finish(result.warnings)
        return
    with RowWriter(sys.stdout, fmt) as rows:
        result = analysis(reader, params, rows if row_columns is None else _Selected(rows, row_columns))
    for warning in result.warnings:
        print(f"afmtool: warning: {warning}", file=sys.stderr)


def run_stream_with_model(
    run: Callable[..., Any], params_cls: type, section: str, reader, config: Path | None, flags: Mapping, fmt: str
) -> None:
    """:func:`run_stream` for an analysis ``run(reader, params, writer, model=...)`` that takes ``--model``.

    The free-air model file of ``params.model`` (if given) is loaded once the
    parameters are resolved, as the folder outputs do.
    """
    from afmtool.analyses.command_inputs import given_free_air_model

    def analysis(reader, params, writer):
        return run(reader, params, writer, model=given_free_air_model(params.model))

    run_stream(analysis, params_cls, section, reader, config, flags, fmt)
