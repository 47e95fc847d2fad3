"""What the command runners (``*_outputs.py``) receive and read before they run.

The runners of reep, probeloss, decode and kalman-bank each began with the
same lines: the same seven arguments, the parameters resolved from the
packaged defaults, ``--config`` and the flags, the capture's hash, the
``--model`` file loaded and recorded as an input, the units of a channel
the capture may lack.  They live here once: :class:`CommandRun` is the
request, the functions below the shared first steps.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from afmtool.config import load_toml, resolve_from
from afmtool.io.capture import CaptureReader
from afmtool.io.provenance import HashedReader
from afmtool.models.free_air import FreeAirModel, load_free_air_model
from afmtool.report.figure_process import FigureProcess

if TYPE_CHECKING:
    from afmtool.pipeline import Split
    from afmtool.report.json_report import SampleInputRecord

__all__ = ["CommandRun", "channel_units", "given_free_air_model", "model_input_records"]

P = TypeVar("P")


@dataclass(frozen=True)
class CommandRun:
    """One run of a capture command into ``--out``, as the CLI hands it to the command's runner.

    Attributes
    ----------
    reader : CaptureReader
        The open capture (units converted, metadata validated).  With
        ``hash_input`` it is wrapped in a :class:`~afmtool.io.provenance.HashedReader`,
        so that the capture's hash is computed in the analysis's own read pass.
    capture : str
        Its path as given (``-`` for stdin), for the input record.
    out : Path
        The output folder, written atomically.
    config : Path or None
        ``--config`` TOML.
    flags : mapping
        ``{field: value or None}`` from the command's generated flags.
    progress : callable
        Called with the samples done so far.
    hash_input : bool
        Record the hash of the samples read (``--no-hash`` turns it off, for live pipelines).
    split : Split, optional
        ``--jobs`` and ``--scheduler``: the kernels of several chunks at once; None runs sequentially.
    figures : FigureProcess
        Draws the figures: a helper process the CLI forked as the command started, or by
        default this process.
    """

    reader: CaptureReader
    capture: str
    out: Path
    config: Path | None
    flags: Mapping
    progress: Callable[[int], None]
    hash_input: bool = True
    split: Split | None = None
    figures: FigureProcess = field(default_factory=FigureProcess)

    def __post_init__(self) -> None:
        if self.hash_input and not isinstance(self.reader, HashedReader):
            object.__setattr__(self, "reader", HashedReader(self.reader))

    def params(self, cls: type[P], section: str) -> P:
        """The effective parameters: packaged defaults, then ``[section]`` of ``--config``, then flags."""
        return resolve_from(cls, section, load_toml(self.config) if self.config else None, self.flags)

    def input_record(self) -> SampleInputRecord:
        """The capture's input record (path, role, hash); ``result()`` once the capture has been read."""
        from afmtool.report.json_report import SampleInputRecord

        return SampleInputRecord(self.capture, self.reader if self.hash_input else None)


def given_free_air_model(model: str) -> FreeAirModel | None:
    """The free-air model of ``--model`` (a ``free_air.json``, its folder or a ``report.json``); None if not given."""
    return load_free_air_model(Path(model)) if model else None


def model_input_records(model: str) -> list[dict]:
    """The input record (path, role, sha256) of the ``--model`` file, as a list: empty if not given."""
    from afmtool.report.json_report import input_record

    if not model:
        return []
    path = Path(model)
    return [input_record(path / "free_air.json" if path.is_dir() else path, "model")]


def channel_units(reader: CaptureReader, name: str) -> str:
    """Units of channel ``name``; "" when the capture has no such channel."""
    return reader.info.units(name) if name in reader.info.channel_names else ""
