"""How ``--help`` reads: options in panels, no type after a flag, the terminal's width, examples.

Applied once to the click command tree that typer builds (:func:`arrange_help`),
so every command, including ones added later, gets the same layout without
each option restating it:

* options are grouped into the panels Input, Model, Estimator and Output
  (an option named in none of the tables below is an estimator setting,
  the commands' own tuning knobs), after the arguments;
* a boolean flag shows no ``<bool>`` metavar: it takes no value;
* the help uses the terminal's full width (``COLUMNS`` or the terminal's
  size; 120 columns when the output is not a terminal), not rich's 80;
* each command's help ends with example lines (:data:`EXAMPLES`).

Nothing here imports scipy, numba or matplotlib: ``afmtool --help`` stays fast.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Mapping

__all__ = ["PANELS", "EXAMPLES", "arrange_help", "panel_of"]

#: The option panels, in the order they are shown.
PANELS = ("Input", "Model", "Estimator", "Output")

_INPUT = frozenset({
    "--channel", "--topic", "--sample-rate", "--chunk-samples", "--contact", "--psd", "--iv", "--z-curve",
    "--vr-sweep", "--reep", "--voltage-channel", "--sweep", "--config", "--arg",
    "--segment", "--curve", "--group", "--units", "--invols", "--z-sensitivity", "--z-channel", "--deflection-channel", "--leg",
})
_MODEL = frozenset({
    "--model", "--models", "--free-air", "--thermal-model", "--spring-constant", "--temperature",
    "--room-temperature", "--breakdown-temperature", "--f0", "--q", "--f0-low", "--q-low", "--f0-scale",
    "--force-set", "--sensor", "--l0", "--nominal", "--actuation-hz", "--free-amplitude", "--at-z",
    "--drive-hold", "--drive", "--detection", "--length", "--width", "--fluid", "--contact-z", "--separation",
    "--seed", "--set",  # simulate: the simulated plant and its noise
})
_OUTPUT = frozenset({
    "--out", "--output", "--json", "--quiet", "--stream", "--stream-format", "--format", "--compression",
    "--params", "--help", "--version", "--force", "--no-hash",
})

#: Example lines closing each command's help, by command path.
EXAMPLES: Mapping[str, tuple[str, ...]] = {
    "info": ("afmtool info sample_data/ltv_step.h5", "afmtool info sample_data/ltv_step.csv --json"),
    "convert": ("afmtool convert sample_data/ltv_step.h5 /tmp/ltv_step.bag",),
    "report": ("afmtool report results/reep   # results/reep/report.html",
               "afmtool report results/batch  # one page, a row per input"),
    "simulate": ("afmtool simulate list", "afmtool simulate tapping -o /tmp/tapping.h5 --set duration_s=0.01"),
    "reep": ("afmtool reep sample_data/ltv_step.h5 --out results/reep",
             "afmtool reep sample_data/tapping_force_curve.h5 --lambda 0.99 --out results/force_curve",
             "afmtool reep sample_data/ltv_step.h5 --stream --stream-format jsonl | head -3"),
    "decode": ("afmtool decode sample_data/bits_30khz.h5 --bit-rate 30000 --out results/decode",),
    "batch": ("afmtool batch reep sample_data/ltv_step.h5 sample_data/tapping_force_curve.h5 --out results/batch",),
    "kalman-bank": ("afmtool kalman-bank sample_data/force_curve_thesis.h5 --out results/bank_thesis",
                    "afmtool kalman-bank sample_data/tapping_force_curve.h5 --reep results/force_curve --out results/bank"),
    "probeloss": ("afmtool probeloss sample_data/raster_grating.h5 --out results/probeloss",),
    "identify freeair": ("afmtool identify freeair sample_data/ltv_step.h5 --out results/freeair",
                         "afmtool identify freeair --psd ../shared/data/thermal_tune_acl_a.csv --out results/thermal"),
    "identify gamma": ("afmtool identify gamma sample_data/thermal_sweep_near.h5 "
                       "--contact sample_data/thermal_sweep_contact.h5 --out results/gamma",),
    "identify thermal": ("afmtool identify thermal --iv /tmp/iv.h5 --z-curve /tmp/z.h5 --out results/thermal_sensor",),
    "identify electrostatic": ("afmtool identify electrostatic /tmp/es.h5 --out results/es",),
    "theory averaging": ("afmtool theory averaging --force-set attractive --out results/averaging",),
    "theory compare": ("afmtool theory compare results/force_curve --out results/theory_compare",),
    "theory observer": ("afmtool theory observer --recommend --cycles 2,4,8,16,50 --out results/observer",),
    "theory fit": ("afmtool theory fit results/force_curve --out results/fit",
                   "afmtool theory fit results/scope_curve --z-sensitivity -12.5 --out results/fit_scope"),
    "theory controllers": ("afmtool theory controllers --out results/controllers",
                           "afmtool theory controllers --lines 4 --figure-lines 48 --out results/controllers_small"),
    "identify invols": ("afmtool identify invols curve_on_sapphire.ibw --out results/invols",
                        "afmtool identify invols scope.csv --channel deflection=CH1 --channel z_piezo=CH2 "
                        "--z-sensitivity 12.5 --out results/invols"),
    "design excitation": ("afmtool design excitation --model results/freeair --amplitude 20 --out results/excitation",
                          "afmtool design excitation --model results/freeair --amplitude 20 --dac-rate 2000000 "
                          "--beat-tolerance 0.02 --out results/excitation"),
    "config init": ("afmtool config init afmtool.toml",),
    "overlay": ("afmtool overlay mica_0 mica_45min mica_2h mica_16h --labels '0,45 min,2 h,16 h' --out results/ageing",
                "afmtool overlay results/q50 results/q200 --label-key q --vs separation --out results/multi_q"),
}


def panel_of(param) -> str:
    """The panel of an option: by name, else an estimator setting."""
    names = set(getattr(param, "opts", ())) | set(getattr(param, "secondary_opts", ()))
    for panel, members in (("Input", _INPUT), ("Model", _MODEL), ("Output", _OUTPUT)):
        if names & members:
            return panel
    return "Estimator"


def _options(command, settings: Mapping) -> list:
    """The command's parameters and its help option (created now with the root's names, -h and --help)."""
    # the command's own Context class: typer vendors its click, which need not be the installed one
    ctx = command.context_class(command, info_name=command.name, **{**settings, **(command.context_settings or {})})
    help_option = command.get_help_option(ctx)  # click caches it on the command: what is set here sticks
    return [*command.params, *([help_option] if help_option is not None else [])]


def _unflag(params) -> None:
    for param in params:
        if getattr(param, "is_flag", False) and getattr(param, "param_type_name", "") == "option":
            param.metavar = ""  # a flag takes no value: no "<bool>" after it


def _arrange_command(command, path: str, settings: Mapping) -> None:
    params = _options(command, settings)
    _unflag(params)
    for param in params:
        if getattr(param, "param_type_name", "") == "option" and not getattr(param, "rich_help_panel", None):
            param.rich_help_panel = panel_of(param)
    rank = {panel: i for i, panel in enumerate(PANELS)}
    # stable, arguments first (their own panel) in their order; then the panels in PANELS order
    command.params.sort(key=lambda p: -1 if p.param_type_name == "argument" else rank.get(p.rich_help_panel, len(rank)))
    examples = EXAMPLES.get(path)
    if examples and not command.epilog:
        command.epilog = "Examples:\n" + "\n".join(f"  {line}" for line in examples)


def _walk(command, path: str, settings: Mapping) -> None:
    subcommands = getattr(command, "commands", None)
    if subcommands is None:
        _arrange_command(command, path, settings)
        return
    _unflag(_options(command, settings))  # a group's own flags (--version)
    for name, sub in subcommands.items():
        _walk(sub, f"{path} {name}".strip(), settings)


def arrange_help(root) -> None:
    """Panels, flag metavars, examples on every command under ``root``; the help's width."""
    _set_help_width()
    _walk(root, "", dict(root.context_settings or {}))


def _set_help_width() -> None:
    """Give typer's rich help the terminal's width, without importing it.

    typer reads ``TERMINAL_WIDTH`` once, when its help module is imported,
    which happens only for ``--help`` or a usage error.  Importing that module
    here to set its width cost every command 0.12-0.17 s (rich's markdown,
    traceback and pretty-printing modules).  A ``TERMINAL_WIDTH`` the user
    set still wins; the one set here is inherited by child processes, which
    share the terminal.
    """
    rich_utils = sys.modules.get("typer.rich_utils")
    if rich_utils is not None:  # already imported (a test, an embedding program): set it directly
        if rich_utils.MAX_WIDTH is None:
            rich_utils.MAX_WIDTH = shutil.get_terminal_size(fallback=(120, 24)).columns
        return
    if not os.environ.get("TERMINAL_WIDTH"):
        os.environ["TERMINAL_WIDTH"] = str(shutil.get_terminal_size(fallback=(120, 24)).columns)
