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

from afmtool.config.commands import examples

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

#: Example lines closing each command's help, by command path: each command's ``examples``
#: (:class:`~afmtool.config.commands.CommandSpec`).
EXAMPLES: Mapping[str, tuple[str, ...]] = examples()


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
