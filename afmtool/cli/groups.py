"""Option groups declared once and added to each command's signature.

A command lists the groups it takes::

    @with_options(param_flags(ReepParams), output_options(stream=True), capture_options())
    def reep(capture: CaptureArg, *, flags: dict, output: CommandOutput, source: CaptureSource) -> None:

:func:`with_options` replaces the keyword parameters ``flags``, ``output`` and
``source`` in the signature typer reads (``__signature__``) by the options of
each group, and hands the command one value per group: the flag -> field
mapping of a parameter model (:mod:`afmtool.cli.param_flags`), the output
options as a :class:`CommandOutput`, the capture options as a
:class:`CaptureSource`.  Flag names, short options, defaults and help stay
those of :mod:`afmtool.cli.options` and :mod:`afmtool.cli.calibration_options`.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from afmtool.cli.calibration_options import (
    CaptureCalibration,
    DriveOpt,
    DrivePhasesOpt,
    InvolsOpt,
    UnitsOpt,
    ZSensitivityOpt,
)
from afmtool.cli.options import (
    ChannelOpt,
    ConfigOpt,
    CurveOpt,
    DataFormatOpt,
    GroupOpt,
    JobsOpt,
    JsonOpt,
    NoHashOpt,
    OutOpt,
    QuietOpt,
    SampleRateOpt,
    SchedulerOpt,
    SchedulerTimeoutOpt,
    SegmentOpt,
    StdinTimeoutOpt,
    StreamFormatOpt,
    StreamOpt,
    StreamOutOpt,
    TopicOpt,
)

__all__ = [
    "OptionGroup",
    "option",
    "with_options",
    "CaptureSource",
    "capture_options",
    "CommandOutput",
    "output_options",
]


class OptionGroup(NamedTuple):
    """Options added to a command, and how their values become the one value it receives.

    ``keyword`` is the command's keyword parameter that receives
    ``collect({option name: value})``.
    """

    keyword: str
    parameters: tuple[inspect.Parameter, ...]
    collect: Callable[[dict], Any]


def option(name: str, annotation: Any, default: Any = None) -> inspect.Parameter:
    """A keyword-only parameter of a generated signature (typer reads its ``Annotated`` option)."""
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)


def _resolved(fn: Callable) -> list[inspect.Parameter]:
    """The function's parameters with their annotations evaluated (``from __future__ import annotations``)."""
    hints = typing.get_type_hints(fn, include_extras=True)
    return [p.replace(annotation=hints.get(p.name, p.annotation)) for p in inspect.signature(fn).parameters.values()]


def with_options(*groups: OptionGroup) -> Callable[[Callable], Callable]:
    """Decorate a command: each group's options join its signature, collected into the group's keyword."""

    def decorate(fn: Callable) -> Callable:
        keywords = {g.keyword for g in groups}
        own = [p for p in _resolved(fn) if p.name not in keywords]
        missing = keywords - {p.name for p in inspect.signature(fn).parameters.values()}
        if missing:
            raise TypeError(f"{fn.__name__} takes no parameter {', '.join(sorted(missing))} for its option groups")
        added = [p for g in groups for p in g.parameters]
        names = [p.name for p in own + added]
        if len(names) != len(set(names)):
            raise TypeError(f"{fn.__name__}: option names repeat: {sorted({n for n in names if names.count(n) > 1})}")
        positional = [p for p in own if p.kind is not inspect.Parameter.KEYWORD_ONLY]
        keyword_only = [p for p in own if p.kind is inspect.Parameter.KEYWORD_ONLY]

        @functools.wraps(fn)
        def command(*args, **kwargs):
            for group in groups:
                kwargs[group.keyword] = group.collect({p.name: kwargs.pop(p.name, p.default) for p in group.parameters})
            return fn(*args, **kwargs)

        parameters = positional + keyword_only + added
        command.__signature__ = inspect.Signature(parameters, return_annotation=None)
        command.__annotations__ = {p.name: p.annotation for p in parameters}
        return command

    return decorate


class CaptureSource(NamedTuple):
    """How to open a capture: ``--channel``, ``--topic``, ``--sample-rate``, ``--segment``, ``--curve``,
    ``--group`` and calibration."""

    channel: list[str] | None = None
    topic: list[str] | None = None
    sample_rate: float | None = None
    units: list[str] | None = None
    invols: float | None = None
    z_sensitivity: float | None = None
    drive: str | None = None
    drive_phases: str | None = None
    segment: str | None = None
    stdin_timeout: float | None = None
    curve: str | None = None
    group: str | None = None

    @property
    def selection(self):
        """``--segment``, ``--curve`` and ``--group`` as one :class:`afmtool.io.registry.Selection`."""
        from afmtool.io.registry import Selection

        return Selection(self.segment, self.curve, self.group)

    def calibration(
        self, free_air: str | None = None, *, accepts_drive: bool = False, raw_deflection: bool = False,
        needs=None,
    ) -> CaptureCalibration:
        """The :class:`CaptureCalibration` of these options (``free_air`` places a synthesised drive's phases).

        ``needs`` (:class:`afmtool.analyses.capture_check.CaptureNeeds`) is checked as the capture opens.
        """
        return CaptureCalibration(
            self.units, self.invols, self.z_sensitivity, self.drive, self.drive_phases, free_air,
            accepts_drive=accepts_drive, raw_deflection=raw_deflection, needs=needs,
        )

    def args(self, calibration: CaptureCalibration | None = None) -> tuple:
        """``(channel, topic, sample_rate, calibration, selection)``, as open_input and run_capture_analysis take them."""
        return self.channel, self.topic, self.sample_rate, calibration or self.calibration(), self.selection

    def open(self, path: str, calibration: CaptureCalibration | None = None, **kwargs):
        """:func:`afmtool.cli.common.open_input` on ``path`` with these options (a context manager)."""
        from afmtool.cli.common import open_input

        channel, topic, sample_rate, calibration, selection = self.args(calibration)
        return open_input(path, channel, topic, sample_rate, calibration, selection, **kwargs)


_CAPTURE_OPTIONS = (
    ("channel", ChannelOpt),
    ("topic", TopicOpt),
    ("sample_rate", SampleRateOpt),
    ("units", UnitsOpt),
    ("invols", InvolsOpt),
    ("z_sensitivity", ZSensitivityOpt),
    ("drive", DriveOpt),
    ("drive_phases", DrivePhasesOpt),
    ("segment", SegmentOpt),
    ("stdin_timeout", StdinTimeoutOpt),
    ("curve", CurveOpt),
    ("group", GroupOpt),
)


def capture_options(
    *,
    invols: bool = True,
    z_sensitivity: bool = True,
    drive: bool = True,
    segment: bool = True,
    keyword: str = "source",
) -> OptionGroup:
    """The capture options (channel, topic, sample-rate, units, invols, z-sensitivity, drive, segment, curve, group).

    ``segment=False`` leaves out the selections (``--segment``, ``--curve``, ``--group``) together.
    """
    left_out = {name for name, wanted in
                (("invols", invols), ("z_sensitivity", z_sensitivity), ("drive", drive), ("drive_phases", drive),
                 ("segment", segment),
                 ("curve", segment), ("group", segment))
                if not wanted}
    parameters = tuple(option(name, annotation) for name, annotation in _CAPTURE_OPTIONS if name not in left_out)
    return OptionGroup(keyword, parameters, _capture_source)


def _capture_source(values: dict) -> CaptureSource:
    """The options as a :class:`CaptureSource`; ``--stdin-timeout`` is set for the reading of ``-``."""
    if values.get("stdin_timeout") is not None:
        from afmtool.io.stdin_watch import set_stdin_timeout

        set_stdin_timeout(values["stdin_timeout"])
    return CaptureSource(**values)


class CommandOutput(NamedTuple):
    """``--out``, ``--json``, ``--config``, ``--quiet`` (and ``--stream``, ``--stream-format``).

    The capture commands also take ``--no-hash``, ``--jobs`` and ``--scheduler``: how the run
    is carried out, not what it computes.
    """

    out: Path | None
    json_output: bool = False
    config: Path | None = None
    quiet: bool = False
    stream: bool = False
    stream_format: str = "csv"
    no_hash: bool = False
    jobs: int | None = None
    scheduler: str | None = None
    scheduler_timeout: float = 10.0
    data_format: str = "h5"

    def split(self):
        """The :class:`afmtool.pipeline.Split` of ``--jobs`` and ``--scheduler``; a scheduler is probed now.

        A scheduler that refuses, stays silent or answers garbage is refused
        here, within ``--scheduler-timeout``, before any output is staged.
        """
        from afmtool.errors import ConfigError
        from afmtool.pipeline import Split

        if self.jobs is not None and self.jobs < 1:
            raise ConfigError(f"--jobs {self.jobs} must be at least 1")
        if self.scheduler:
            from afmtool.io.scheduler import probe_scheduler

            probe_scheduler(self.scheduler, self.scheduler_timeout)
        return Split.of(self.jobs, self.scheduler, self.scheduler_timeout)

    def settings(self, figures=None, *, split: bool = False):
        """The :class:`afmtool.api.run.RunSettings` of these options (``split``: probe ``--jobs``/``--scheduler``),
        with the root's ``--max-samples`` and ``--wait``."""
        from afmtool.api.run import RunSettings
        from afmtool.cli.options import root_run_options
        from afmtool.cli.progress import progress_bar

        quiet, root = self.quiet, root_run_options()  # afmtool --max-samples / --wait
        return RunSettings(config=self.config, split=self.split() if split else None, hash_input=not self.no_hash,
                           figures=figures, progress=lambda name, total: progress_bar(name, total, quiet),
                           data_format=self.data_format, own_warnings=False, max_samples=root.max_samples,
                           wait=root.wait)

    @property
    def stream_mode(self) -> tuple[bool, str]:
        """``(--stream, --stream-format)``, as run_capture_analysis takes them."""
        return self.stream, self.stream_format


def output_options(
    default_out: Path | None = None, *, stream: bool = False, json: bool = True, keyword: str = "output",
    capture_run: bool = False,
) -> OptionGroup:
    """The output options; with ``stream``, ``--out`` is optional and ``--stream``/``--stream-format`` join.

    ``capture_run`` adds ``--no-hash``, ``--jobs`` and ``--scheduler`` (the streaming capture commands).
    """
    parameters = [option("out", StreamOutOpt, None) if stream else option("out", OutOpt, default_out)]
    if stream:
        parameters += [option("stream", StreamOpt, False), option("stream_format", StreamFormatOpt, "csv")]
    if capture_run:
        parameters += [option("no_hash", NoHashOpt, False), option("jobs", JobsOpt, None),
                       option("scheduler", SchedulerOpt, None), option("scheduler_timeout", SchedulerTimeoutOpt, 10.0)]
    if json:
        parameters.append(option("json_output", JsonOpt, False))
    parameters += [option("config", ConfigOpt, None), option("quiet", QuietOpt, False),
                   option("data_format", DataFormatOpt, "h5")]
    return OptionGroup(keyword, tuple(parameters), lambda values: CommandOutput(**values))
