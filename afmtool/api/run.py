"""What a command does between its inputs and its output folder, once, for the CLI and the Python API.

Each ``run_*`` here takes the command's inputs (:class:`~afmtool.api.capture.Capture`
objects or paths), the output folder, the parameter values as the CLI's
flags give them (``{field: value or None}``, the TOML keys) and the
:class:`RunSettings` of how it runs; it returns the ``report.json`` dict.
The CLI commands (``afmtool/cli``) call them with ``--out``; the API
functions (``afmtool.reep`` ...) with a private folder that the result object
owns and ``.save()`` copies.  So the numbers and files are the same by
construction: one code path.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from afmtool.api.capture import Capture, as_capture
from afmtool.config.commands import capture_commands, spec
from afmtool.errors import ConfigError

if TYPE_CHECKING:
    from afmtool.pipeline import Split

__all__ = ["RunSettings", "CAPTURE_COMMANDS", "run_capture_command", "run_identify_freeair", "run_identify_gamma",
           "run_identify_thermal", "run_identify_electrostatic", "run_identify_invols", "run_folder_command",
           "capture_options_for", "drive_response_from_flags"]


def _no_progress(name: str, total: int | None) -> AbstractContextManager[Callable[[int], None]]:
    return nullcontext(lambda done: None)


@dataclass(frozen=True)
class RunSettings:
    """How a run is carried out, not what it computes.

    ``max_samples`` and ``wait`` reach the HDF5 readers and the output folder's lock
    through :mod:`afmtool.runtime.run_options`, in force during :meth:`scope`, which
    every ``run_*`` here enters for the whole run (and :meth:`writing` too).

    Attributes
    ----------
    config : Path or None
        ``--config``: a TOML file whose sections set parameters (flags still win).
    split : Split or None
        ``--jobs`` / ``--scheduler``: chunks at once on threads or a Dask cluster; None is sequential.
    hash_input : bool
        Record the hash of the samples read (``--no-hash`` turns it off).
    figures : FigureProcess or None
        Where the figures are drawn (the CLI forks a helper; None draws them in this process).
    progress : callable
        ``progress(name, total_samples)`` -> a context manager yielding ``update(samples_done)``.
    data_format : str
        ``--format``: ``h5`` (afmtool's HDF5), ``netcdf`` or ``zarr`` for the result arrays.
    own_warnings : bool
        Record the run's Python warnings into its report as a fresh ``afmtool`` process does
        (Python's default filters, each first occurrence), restoring the caller's warning state after.
        The CLI records them for the whole process itself (False there).
    max_samples : int or None
        ``afmtool --max-samples N``: accept HDF5 captures of up to N samples per dataset whatever
        their size on disk (None: a file may claim at most 1000x its size).
    wait : bool
        ``afmtool --wait``: wait for another run writing the same output folder instead of failing.
    """

    config: Path | None = None
    split: Split | None = None
    hash_input: bool = True
    figures: Any = None
    progress: Callable[[str, int | None], AbstractContextManager] = field(default=_no_progress)
    data_format: str = "h5"
    own_warnings: bool = True
    max_samples: int | None = None
    wait: bool = False

    def __post_init__(self) -> None:
        self.run_options()  # a bad --max-samples is refused as the settings are made

    def run_options(self):
        """``max_samples`` and ``wait`` as the :class:`~afmtool.runtime.run_options.RunOptions` the floors read."""
        from afmtool.runtime.run_options import RunOptions

        return RunOptions(self.max_samples, self.wait)

    def scope(self) -> AbstractContextManager:
        """Within the block, the readers and output folders of this run see :attr:`max_samples` and :attr:`wait`."""
        from afmtool.runtime.run_options import applied

        return applied(self.run_options())

    def figure_process(self):
        from afmtool.report.figure_process import FigureProcess

        return self.figures if self.figures is not None else FigureProcess()

    @contextmanager
    def writing(self):
        """The run's result arrays are written in :attr:`data_format` (``report.run.finish_run`` converts them).

        Within :meth:`scope`, so a runner called without a ``run_*`` here still sees ``max_samples`` and ``wait``.
        """
        import warnings

        from afmtool.report.run import result_format

        if not self.own_warnings:
            with self.scope(), result_format(self.data_format):
                yield
            return
        from afmtool.report.captured_warnings import record, take

        with warnings.catch_warnings():
            warnings.resetwarnings()  # Python's own defaults, as in a fresh afmtool process
            warnings.simplefilter("default")
            for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
                warnings.simplefilter("ignore", category)
            warnings.showwarning = record
            take()  # nothing recorded before this run belongs to its report
            with self.scope(), result_format(self.data_format):
                yield


#: The capture commands: the channels each needs, and whether a dither may be synthesised for it
#: (their specs' ``channels`` and ``synthesised_drive``, :mod:`afmtool.config.commands`).
CAPTURE_COMMANDS: Mapping[str, tuple[tuple[str, ...], bool]] = capture_commands()


def _in_scope(run: Callable) -> Callable:
    """``run`` within its ``settings``' :meth:`RunSettings.scope` from its first line on.

    From the first line: a path given as the capture is opened by ``as_capture`` already, and
    ``--max-samples`` must be in force there.
    """
    import functools
    import inspect

    signature = inspect.signature(run)

    @functools.wraps(run)
    def scoped(*args, **kwargs):
        with signature.bind(*args, **kwargs).arguments["settings"].scope():
            return run(*args, **kwargs)

    return scoped


def _runner(command: str) -> Callable:
    """The analysis that runs ``command``, bound from its spec (imported now, with what it needs)."""
    return spec(command).runner.load()


def capture_options_for(command: str, capture: Capture, flags: Mapping, *, hash_input: bool = False):
    """The capture's options with what ``command`` needs of it (checked as it opens) and may synthesise."""
    from afmtool.analyses.capture_check import needs_from_flags

    channels, accepts_drive = CAPTURE_COMMANDS[command]
    if command == "reep" and flags.get("use_input") is False:
        channels = ("deflection",)
    return capture.options.replace(
        free_air=(flags.get("free_air") or capture.options.free_air) if accepts_drive else capture.options.free_air,
        drive_response=(drive_response_from_flags(flags) or capture.options.drive_response) if accepts_drive
        else capture.options.drive_response,
        accepts_drive=accepts_drive or capture.options.accepts_drive,
        needs=needs_from_flags(command, flags, channels), hash_samples=hash_input,
    )


def drive_response_from_flags(flags: Mapping):
    """The free-air f0 and Q a synthesised drive is fitted against: ``--model``, else ``--f0``/``--q``; None without.

    The same resonance the command itself then uses (:class:`~afmtool.estimators.drive_lines.DriveResponse`).
    """
    from afmtool.estimators.drive_lines import DriveResponse

    if flags.get("model"):
        from afmtool.models.free_air import load_free_air_model

        model = load_free_air_model(Path(flags["model"]))
        return DriveResponse(model.f0_hz, model.q, model.f0_std_hz or 0.0, model.q_std or 0.0, f"--model {flags['model']}")
    if flags.get("f0_hz") and flags.get("q"):
        return DriveResponse(float(flags["f0_hz"]), float(flags["q"]), 0.0, 0.0, "--f0/--q")
    return None


@_in_scope
def run_capture_command(command: str, capture: Capture | str | Path, out: Path, flags: Mapping,
                        settings: RunSettings) -> dict:
    """reep, probeloss, decode or kalman-bank on ``capture`` into ``out``; the report."""
    from afmtool.analyses.command_inputs import CommandRun

    capture = as_capture(capture)
    options = capture_options_for(command, capture, flags, hash_input=settings.hash_input)
    runner = _runner(command)
    with capture.open_reader(options) as reader, settings.progress(command, reader.info.n_samples) as update:
        run = CommandRun(reader, capture.source, out, settings.config, flags, update,
                         hash_input=settings.hash_input, split=settings.split, figures=settings.figure_process())
        with settings.writing():
            return runner(run)


@_in_scope
def run_stream_rows(command: str, capture: Capture | str | Path, flags: Mapping, settings: RunSettings, sink) -> None:
    """reep, probeloss or decode with its rows going to ``sink`` (``append(columns)``) as each chunk completes."""
    capture = as_capture(capture)
    options = capture_options_for(command, capture, flags)
    stream = spec(command).stream
    if stream is None:
        raise ConfigError(f"{command} has no --stream")
    runner = stream.load()
    with capture.open_reader(options) as reader:
        runner(reader, settings.config, flags, sink)


@_in_scope
def run_identify_freeair(capture: Capture | str | Path | None, out: Path, flags: Mapping, settings: RunSettings,
                         *, psd: Path | str | None = None, thermal: Capture | str | Path | None = None,
                         invols: float | None = None) -> dict:
    """``identify freeair``: the segment or sweep route on ``capture``, or the thermal route (``psd``, ``thermal``)."""
    from afmtool.analyses.capture_check import needs_from_flags

    run_freeair_command = _runner("identify freeair")
    if psd and thermal:
        raise ConfigError("give one thermal input: --psd FILE.csv or --thermal CAPTURE")
    route = flags.get("route") or ("thermal" if (psd or thermal) else "segment")
    if thermal and capture is not None:
        raise ConfigError("--thermal CAPTURE takes the record itself: give no other CAPTURE")
    if route != "thermal" and capture is None:
        raise ConfigError("give a CAPTURE (segment or --sweep route), --psd FILE.csv or --thermal CAPTURE (thermal)")
    flags = {**flags, "route": route, "invols_nm_per_v": invols}
    with settings.writing():
        if psd:
            return run_freeair_command(None, psd, out, settings.config, flags, lambda done: None)
        source = as_capture(thermal or capture)
        needs = needs_from_flags("identify freeair", flags, ("deflection",) if thermal else ("deflection", "dither"))
        options = source.options.replace(free_air=flags.get("free_air") or None, accepts_drive=not thermal,
                                         needs=needs)
        with source.open_reader(options) as reader, settings.progress("identify", reader.info.n_samples) as update:
            return run_freeair_command(reader, source.source, out, settings.config, flags, update)


@_in_scope
def run_identify_gamma(sweep: Capture | str | Path, contact: Capture | str | Path, out: Path, flags: Mapping,
                       settings: RunSettings) -> dict:
    """``identify gamma``: Γ from the sweep near the sample and the sweep in contact."""
    run_gamma_command = _runner("identify gamma")
    sweep, contact = as_capture(sweep, "sweep"), as_capture(contact, "contact")
    with sweep.open_reader() as near, contact.open_reader() as far, settings.writing():
        total = (near.info.n_samples or 0) + (far.info.n_samples or 0)
        with settings.progress("identify gamma", total or None) as update:
            return run_gamma_command(near, far, (sweep.source, contact.source), out, settings.config, flags, update)


@_in_scope
def run_identify_thermal(inputs: Mapping[str, Any], out: Path, flags: Mapping, settings: RunSettings) -> dict:
    """``identify thermal`` from its optional inputs: ``iv``, ``z``, ``vr`` (captures), ``gamma``, ``model`` (paths)."""
    from contextlib import ExitStack

    run_thermal_command = _runner("identify thermal")
    captures = {key: as_capture(inputs[key], f"--{key}") if inputs.get(key) is not None else None
                for key in ("iv", "z", "vr")}
    sources = {key: (value.source if value is not None else None) for key, value in captures.items()}
    sources.update(gamma=inputs.get("gamma"), model=inputs.get("model"))
    with ExitStack() as stack:
        readers = {key: stack.enter_context(capture.open_reader()) if capture is not None else None
                   for key, capture in captures.items()}
        total = sum((r.info.n_samples or 0) for r in readers.values() if r is not None)
        with settings.progress("identify thermal", total or None) as update, settings.writing():
            return run_thermal_command(readers, sources, out, settings.config, flags, update)


@_in_scope
def run_identify_electrostatic(capture: Capture | str | Path, out: Path, flags: Mapping, settings: RunSettings,
                               thermal_model: Path | str | None = None) -> dict:
    """``identify electrostatic`` on a quasi-static approach curve."""
    run_electrostatic_command = _runner("identify electrostatic")
    capture = as_capture(capture)
    with capture.open_reader() as reader, settings.writing():
        return run_electrostatic_command(reader, capture.source, out, settings.config, flags,
                                         Path(thermal_model) if thermal_model else None)


@_in_scope
def run_identify_invols(curve: Capture | str | Path, out: Path, flags: Mapping, settings: RunSettings) -> dict:
    """``identify invols``: the deflection is left in V (the InvOLS is what is measured)."""
    run_invols_command = _runner("identify invols")
    curve = as_capture(curve, "curve")
    with curve.open_reader(curve.options.replace(raw_deflection=True)) as reader, settings.writing():
        return run_invols_command(reader, curve.source, out, settings.config, flags)


@_in_scope
def run_folder_command(command: str, source: Path | str | None, out: Path, flags: Mapping,
                       settings: RunSettings) -> dict:
    """theory averaging (no input), theory compare / fit (a reep folder), design excitation (a free_air.json)."""
    runner = _runner(command)
    with settings.writing():
        if source is None:
            return runner(out, settings.config, flags)
        return runner(Path(source), out, settings.config, flags)
