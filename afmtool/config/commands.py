"""What a command is, declared once: one :class:`CommandSpec` per ``afmtool`` command (issue 29, item 3).

A command's parts used to be spread over six tables and a string import
(the config sections, the help's examples, the headlines, the HTML page's
main figures, batch's command list, the capture commands' channels, and
``api/run``'s runner names).  Each is now derived from :data:`SPECS`:

========================================  ==========================================
table                                     derived by
========================================  ==========================================
``config.params.SECTIONS``                :func:`sections`
``cli.help.EXAMPLES``                     :func:`examples`
``report.headline.HEADLINES``             :func:`headlines`
``report.html.MAIN_FIGURES``              :func:`main_figures`
``cli.batch_cmd._COMMANDS``               :func:`batch_commands`
``api.run.CAPTURE_COMMANDS``              :func:`capture_commands`
runners (``api/run``, the CLI)            ``SPECS[name].runner.load()``
========================================  ==========================================

The module sits on the config floor (``docs/architecture.md``, "Floors") so that
every floor that keeps one of those tables can read it, and it is light:
``afmtool --help`` imports it.  A command's runner lives in ``afmtool.analyses``,
above this floor, so it is named here, not imported: :class:`Lazy` holds its
module and name, and :meth:`Lazy.load` is the one place a command's code is
imported by name; only the api and cli floors call it.

A spec that lacks a part its kind needs fails as it is built
(:func:`missing_parts`); ``tests/test_command_specs.py`` checks that every command
of the CLI has a spec and every spec a command.  docs/development.md,
"Adding a command", lists the files a new command touches.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from afmtool.config import params as P
from afmtool.records.base import Item

__all__ = [
    "Kind", "Lazy", "Section", "CommandSpec", "SPECS", "REQUIRED", "missing_parts", "check_specs", "spec",
    "sections", "examples", "headlines", "results", "main_figures", "batch_commands", "capture_commands",
]


class Kind(enum.Enum):
    """What a command reads, which decides the parts it must declare (:data:`REQUIRED`)."""

    #: One capture, streamed chunk by chunk (reep, probeloss, decode, kalman-bank).
    CAPTURE = "capture"
    #: Any other analysis that writes report.json (identify, theory, design, overlay).
    ANALYSIS = "analysis"
    #: A utility that writes no report.json (info, convert, report, simulate, batch, config init).
    TOOL = "tool"


@dataclass(frozen=True)
class Lazy:
    """A function named by its module and name, imported only when a command runs.

    Attributes
    ----------
    module : str
        ``"afmtool.analyses.reep_outputs"``.
    name : str
        ``"run_reep_command"``.
    """

    module: str
    name: str

    def load(self) -> Callable:
        """The object named (a function, a table): its module is imported now, with numpy, numba ..."""
        import importlib

        return getattr(importlib.import_module(self.module), self.name)


@dataclass(frozen=True)
class Section:
    """A config-file section a command reads: its parameter model and, when not the command's own, its name.

    Attributes
    ----------
    model : type
        The frozen parameter dataclass (:mod:`afmtool.config.params`).
    name : str
        The section's name; ``""`` is the command's own (``identify freeair`` -> ``identify.freeair``).
    """

    model: type
    name: str = ""


@dataclass(frozen=True)
class CommandSpec:
    """Every part of one command.  A part left ``None`` is missing; ``()`` declares it empty.

    Attributes
    ----------
    name : str
        The command's words on the command line: ``"reep"``, ``"identify freeair"``.
    kind : Kind
        What it reads; decides which parts are required (:data:`REQUIRED`).
    params : tuple of Section
        The config sections it reads, its own first; ``()`` for a command without parameters.
    runner : Lazy
        The analysis that writes its output folder and returns the report.
    stream : Lazy or None
        ``--stream``'s row writer, where the command has one.
    stream_units : Lazy or None
        The units of the streamed columns (a mapping), with ``stream``: ``afmtool.reep(stream=True)`` labels its chunks by it.
    examples : tuple of str
        The example lines closing its ``--help``.
    main_figures : tuple of str
        Its figures a reader sees first on the HTML page, in order; ``()`` puts none first
        (the page shows the figures by name).
    result : Lazy
        Its root result record (:mod:`afmtool.records`): the ``results`` of its report.json, whose
        ``HEADLINE`` is its headline and ``STATES`` the states said before it.
    batch : str or None
        Its name under ``afmtool batch`` (``"freeair"``); None when batch does not run it.
    channels : tuple of str
        A capture command's channels, checked as the capture opens.
    synthesised_drive : bool
        A capture command may synthesise a dither the capture lacks (``--drive``).
    """

    name: str
    kind: Kind
    params: tuple[Section, ...] | None = None
    runner: Lazy | None = None
    stream: Lazy | None = None
    stream_units: Lazy | None = None
    examples: tuple[str, ...] | None = None
    main_figures: tuple[str, ...] | None = None
    result: Lazy | None = None
    batch: str | None = None
    channels: tuple[str, ...] | None = None
    synthesised_drive: bool = False

    def __post_init__(self) -> None:
        problems = missing_parts(self)
        if problems:
            raise ValueError(f"command {self.name!r} lacks {', '.join(problems)}")

    @property
    def section(self) -> str:
        """Its own config section: the words joined by dots (``identify.freeair``)."""
        return self.name.replace(" ", ".")

    def sections(self) -> tuple[tuple[str, type], ...]:
        """``(section name, parameter model)`` of every section it reads, its own first."""
        return tuple((s.name or self.section, s.model) for s in self.params or ())


#: The parts each kind must declare (a part declared empty, ``()``, is declared).
REQUIRED: Mapping[Kind, tuple[str, ...]] = {
    Kind.CAPTURE: ("params", "runner", "examples", "main_figures", "result", "channels"),
    Kind.ANALYSIS: ("params", "runner", "examples", "main_figures", "result"),
    Kind.TOOL: ("examples",),
}
#: Parts only a capture command may have: the stream and its capture's channels and drive.
_CAPTURE_ONLY = ("stream", "stream_units", "channels")


def missing_parts(spec: CommandSpec) -> list[str]:
    """The parts ``spec`` lacks for its kind, and those it has but must not; empty when it is whole."""
    problems = [part for part in REQUIRED[spec.kind] if getattr(spec, part) is None]
    if spec.kind is not Kind.CAPTURE:
        problems += [f"no {part} (capture commands only)" for part in _CAPTURE_ONLY if getattr(spec, part) is not None]
        if spec.synthesised_drive:
            problems.append("no synthesised_drive (capture commands only)")
    if spec.kind is Kind.TOOL and spec.result is not None:
        problems.append("no result (a tool writes no report.json)")
    if (spec.stream is None) != (spec.stream_units is None):
        problems.append("stream and stream_units (both or neither)")
    if spec.examples == ():
        problems.append("examples (at least one)")
    return problems


def check_specs(specs: Mapping[str, CommandSpec], cli_commands: Iterable[str]) -> list[str]:
    """Every way ``specs`` and the CLI's commands (their words) disagree, and every spec's missing parts."""
    cli = set(cli_commands)
    problems = [f"{name}: a command without a spec" for name in sorted(cli - set(specs))]
    problems += [f"{name}: a spec without a command" for name in sorted(set(specs) - cli)]
    problems += [f"{key}: its spec is named {s.name!r}" for key, s in specs.items() if key != s.name]
    problems += [f"{s.name}: lacks {part}" for s in specs.values() for part in missing_parts(s)]
    batch = [s.batch for s in specs.values() if s.batch is not None]
    problems += [f"batch name {b!r} given twice" for b in sorted(set(batch)) if batch.count(b) > 1]
    return problems


def _own(model: type, *more: Section) -> tuple[Section, ...]:
    return (Section(model), *more)


def _analysis(module: str, name: str) -> Lazy:
    """``name`` in ``afmtool.analyses.<module>``, imported when loaded."""
    return Lazy(f"afmtool.analyses.{module}", name)


_REEP = CommandSpec(
    "reep", Kind.CAPTURE, _own(P.ReepParams), _analysis("reep_outputs", "run_reep_command"),
    stream=_analysis("reep_outputs", "run_reep_stream"), stream_units=_analysis("reep", "SERIES_UNITS"),
    examples=("afmtool reep sample_data/ltv_step.h5 --out results/reep",
              "afmtool reep sample_data/tapping_force_curve.h5 --lambda 0.99 --out results/force_curve",
              "afmtool reep sample_data/ltv_step.h5 --stream --stream-format jsonl | head -3"),
    main_figures=("reep_time_series.png", "force_curve.png", "force_curve_sensitivity.png"),
    result=Lazy("afmtool.records.reep", "ReepResults"), batch="reep", channels=("deflection", "dither"),
    synthesised_drive=True,
)
_PROBELOSS = CommandSpec(
    "probeloss", Kind.CAPTURE, _own(P.ProbeLossParams), _analysis("probeloss_outputs", "run_probeloss_command"),
    stream=_analysis("probeloss_outputs", "run_probeloss_stream"), stream_units=_analysis("probeloss", "SERIES_UNITS"),
    examples=("afmtool probeloss sample_data/raster_grating.h5 --out results/probeloss",),
    main_figures=("probeloss_time_series.png",), result=Lazy("afmtool.records.probeloss", "ProbeLossResults"),
    batch="probeloss",
    channels=("deflection", "dither"), synthesised_drive=True,
)
_DECODE = CommandSpec(
    "decode", Kind.CAPTURE, _own(P.DecodeParams), _analysis("decode_outputs", "run_decode_command"),
    stream=_analysis("decode_outputs", "run_decode_stream"), stream_units=_analysis("decode", "SERIES_UNITS"),
    examples=("afmtool decode sample_data/bits_30khz.h5 --bit-rate 30000 --out results/decode",),
    main_figures=("decode_time_series.png", "eye.png", "psd.png", "l0_search.png"),
    result=Lazy("afmtool.records.decode", "DecodeResults"), batch="decode", channels=("deflection",),
)
_KALMAN_BANK = CommandSpec(
    "kalman-bank", Kind.CAPTURE, _own(P.KalmanBankParams), _analysis("kalman_bank_outputs", "run_kalman_bank_command"),
    examples=("afmtool kalman-bank sample_data/force_curve_thesis.h5 --out results/bank_thesis",
              "afmtool kalman-bank sample_data/tapping_force_curve.h5 --reep results/force_curve --out results/bank"),
    main_figures=("bank_rms_vs_time.png", "bank_rms_vs_z.png"),
    result=Lazy("afmtool.records.kalman_bank", "KalmanBankResults"), batch="kalman-bank",
    channels=("deflection", "dither", "z_piezo"), synthesised_drive=True,
)

_IDENTIFY = (
    CommandSpec(
        "identify freeair", Kind.ANALYSIS,
        _own(P.FreeAirParams, Section(P.SpringConstantParams, "identify.spring_constant")),
        _analysis("freeair_outputs", "run_freeair_command"),
        examples=("afmtool identify freeair sample_data/ltv_step.h5 --out results/freeair",
                  "afmtool identify freeair --psd ../shared/data/thermal_tune_acl_a.csv --out results/thermal"),
        main_figures=("thermal_fit.png", "sweep_bode.png", "segment_bode.png"),
        result=Lazy("afmtool.records.freeair", "FreeAirResults"), batch="freeair",
    ),
    CommandSpec(
        "identify gamma", Kind.ANALYSIS, _own(P.GammaParams), _analysis("gamma_outputs", "run_gamma_command"),
        examples=("afmtool identify gamma sample_data/thermal_sweep_near.h5 "
                  "--contact sample_data/thermal_sweep_contact.h5 --out results/gamma",),
        main_figures=("gamma_ir_ts.png",), result=Lazy("afmtool.records.gamma", "GammaResults"),
    ),
    CommandSpec(
        "identify thermal", Kind.ANALYSIS, _own(P.ThermalParams), _analysis("thermal_outputs", "run_thermal_command"),
        examples=("afmtool identify thermal --iv /tmp/iv.h5 --z-curve /tmp/z.h5 --out results/thermal_sensor",),
        main_figures=(), result=Lazy("afmtool.records.thermal", "ThermalResults"),
    ),
    CommandSpec(
        "identify electrostatic", Kind.ANALYSIS, _own(P.ElectrostaticFitParams),
        _analysis("electrostatic_outputs", "run_electrostatic_command"),
        examples=("afmtool identify electrostatic /tmp/es.h5 --out results/es",), main_figures=(),
        result=Lazy("afmtool.records.electrostatic", "ElectrostaticResults"),
    ),
)


def _theory(word: str, params: type, runner: Lazy, examples: tuple[str, ...], result: Lazy) -> CommandSpec:
    """A ``theory`` subcommand: its figures read in name order (none put first)."""
    return CommandSpec(f"theory {word}", Kind.ANALYSIS, _own(params), runner, examples=examples, main_figures=(),
                       result=result)


_THEORY_AVERAGING = _theory(
    "averaging", P.AveragingParams, _analysis("theory_outputs", "run_averaging_command"),
    ("afmtool theory averaging --force-set attractive --out results/averaging",),
    Lazy("afmtool.records.theory_averaging", "AveragingResults"))
_THEORY_COMPARE = _theory(
    "compare", P.TheoryCompareParams, _analysis("theory_outputs", "run_compare_command"),
    ("afmtool theory compare results/force_curve --out results/theory_compare",),
    Lazy("afmtool.records.theory_compare", "TheoryCompareResults"))
_THEORY_CONTROLLERS = _theory(
    "controllers", P.TheoryControllersParams, _analysis("controllers", "run_controllers_command"),
    ("afmtool theory controllers --out results/controllers",
     "afmtool theory controllers --lines 4 --figure-lines 48 --out results/controllers_small"),
    Lazy("afmtool.records.theory_controllers", "ControllersResults"))
_THEORY_OBSERVER = _theory(
    "observer", P.ObserverTheoryParams, _analysis("observer_theory_outputs", "run_observer_theory_command"),
    ("afmtool theory observer --recommend --cycles 2,4,8,16,50 --out results/observer",),
    Lazy("afmtool.records.theory_observer", "ObserverResults"))
_THEORY_FIT = _theory(
    "fit", P.TheoryFitParams, _analysis("theory_fit", "run_theory_fit_command"),
    ("afmtool theory fit results/force_curve --out results/fit",
     "afmtool theory fit results/scope_curve --z-sensitivity -12.5 --out results/fit_scope"),
    Lazy("afmtool.records.theory_fit", "TheoryFitResults"))
_IDENTIFY_INVOLS = CommandSpec(
    "identify invols", Kind.ANALYSIS, _own(P.InvolsParams), _analysis("invols", "run_invols_command"),
    examples=("afmtool identify invols curve_on_sapphire.ibw --out results/invols",
              "afmtool identify invols scope.csv --channel deflection=CH1 --channel z_piezo=CH2 "
              "--z-sensitivity 12.5 --out results/invols"),
    main_figures=(), result=Lazy("afmtool.records.invols", "InvolsResults"), batch="invols",
)
_DESIGN_EXCITATION = CommandSpec(
    "design excitation", Kind.ANALYSIS, _own(P.DesignExcitationParams),
    _analysis("design_excitation", "run_design_excitation_command"),
    examples=("afmtool design excitation --model results/freeair --amplitude 20 --out results/excitation",
              "afmtool design excitation --model results/freeair --amplitude 20 --dac-rate 2000000 "
              "--beat-tolerance 0.02 --out results/excitation"),
    main_figures=(), result=Lazy("afmtool.records.design", "DesignResults"),
)
_OVERLAY = CommandSpec(
    "overlay", Kind.ANALYSIS, (), _analysis("overlay", "run_overlay_command"),
    examples=("afmtool overlay mica_0 mica_45min mica_2h mica_16h --labels '0,45 min,2 h,16 h' --out results/ageing",
              "afmtool overlay results/q50 results/q200 --label-key q --vs separation --out results/multi_q"),
    main_figures=("overlay_f0_hz.png", "overlay_q.png", "overlay_amplitude.png", "overlay_phase_deg.png"),
    result=Lazy("afmtool.records.overlay", "OverlayResults"),
)

#: The utilities: they write no report.json; their work is in their CLI module.
_TOOLS = (
    CommandSpec("info", Kind.TOOL, examples=(
        "afmtool info sample_data/ltv_step.h5", "afmtool info sample_data/ltv_step.csv --json")),
    CommandSpec("convert", Kind.TOOL, examples=("afmtool convert sample_data/ltv_step.h5 /tmp/ltv_step.bag",)),
    CommandSpec("report", Kind.TOOL, examples=("afmtool report results/reep   # results/reep/report.html",
                                               "afmtool report results/batch  # one page, a row per input")),
    CommandSpec("simulate", Kind.TOOL, examples=(
        "afmtool simulate list", "afmtool simulate tapping -o /tmp/tapping.h5 --set duration_s=0.01")),
    CommandSpec("batch", Kind.TOOL, examples=(
        "afmtool batch reep sample_data/ltv_step.h5 sample_data/tapping_force_curve.h5 --out results/batch",)),
    CommandSpec("config init", Kind.TOOL, examples=("afmtool config init afmtool.toml",)),
)

#: Every command, by its words.  The order is the config file's section order (``afmtool config init``).
SPECS: Mapping[str, CommandSpec] = {s.name: s for s in (
    *_IDENTIFY, _REEP, _PROBELOSS, _DECODE, _THEORY_AVERAGING, _THEORY_COMPARE, _THEORY_CONTROLLERS, _KALMAN_BANK,
    _THEORY_OBSERVER, _IDENTIFY_INVOLS, _DESIGN_EXCITATION, _THEORY_FIT, _OVERLAY, *_TOOLS,
)}


def spec(name: str) -> CommandSpec:
    """The spec of the command ``name`` (its words); KeyError names the commands there are."""
    try:
        return SPECS[name]
    except KeyError:
        raise KeyError(f"no command {name!r}; the commands: {', '.join(SPECS)}") from None


# ----------------------------------------------------------------------------- the derived tables
def sections() -> dict[str, type]:
    """Config-file section -> parameter model (``config.params.SECTIONS``)."""
    return {name: model for s in SPECS.values() for name, model in s.sections()}


def examples() -> dict[str, tuple[str, ...]]:
    """Command -> the example lines closing its ``--help`` (``cli.help.EXAMPLES``)."""
    return {s.name: s.examples for s in SPECS.values() if s.examples is not None}


def headlines() -> dict[str, tuple[Item, ...]]:
    """Command -> its headline items, for the commands that write report.json (``report.headline.HEADLINES``).

    A command with a result record declares them on it (its ``HEADLINE``); the records are light
    (standard library only).
    """
    return {s.name: s.result.load().HEADLINE for s in SPECS.values() if s.result is not None}


def results() -> dict[str, type]:
    """Command -> its root result record, for the commands that have one."""
    return {s.name: s.result.load() for s in SPECS.values() if s.result is not None}


def main_figures() -> dict[str, tuple[str, ...]]:
    """Command -> its figures shown first (``report.html.MAIN_FIGURES``)."""
    return {s.name: s.main_figures for s in SPECS.values() if s.main_figures is not None}


def batch_commands() -> dict[str, tuple[str, ...]]:
    """batch's name -> the command's words (``cli.batch_cmd._COMMANDS``)."""
    return {s.batch: tuple(s.name.split()) for s in SPECS.values() if s.batch is not None}


def capture_commands() -> dict[str, tuple[tuple[str, ...], bool]]:
    """Capture command -> (channels it needs, may a drive be synthesised) (``api.run.CAPTURE_COMMANDS``)."""
    return {s.name: (s.channels, s.synthesised_drive) for s in SPECS.values() if s.kind is Kind.CAPTURE}
