"""One Python function per analysis: ``afmtool.reep``, ``afmtool.probeloss``, ... ``afmtool.theory_fit``.

Each takes its inputs (an :class:`~afmtool.Capture`, a path, or for the
folder commands a REEP output folder or ``free_air.json``) and keyword
parameters whose names and defaults are the TOML keys of the one parameter
model (:mod:`afmtool.config.params`), so ``afmtool.reep(cap, lam=0.99)``
means ``afmtool reep --lambda 0.99``.  It runs the command's own code path
(:mod:`afmtool.api.run`, which the CLI calls too) into a private folder and
returns a :class:`~afmtool.api.results.Result`.  The signatures and the
Parameters sections of the docstrings are generated from the parameter
model, so ``help(afmtool.reep)`` lists every parameter with its default,
units and meaning.
"""

from __future__ import annotations

import dataclasses
import inspect
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from afmtool.api.capture import Capture, as_capture
from afmtool.api.results import ChunkQueue, ChunkResult, Result
from afmtool.api.run import (
    RunSettings,
    run_capture_command,
    run_folder_command,
    run_identify_electrostatic,
    run_identify_freeair,
    run_identify_gamma,
    run_identify_invols,
    run_identify_thermal,
    run_stream_rows,
)
from afmtool.config.commands import spec
from afmtool.errors import ConfigError

__all__ = [
    "reep", "probeloss", "kalman_bank", "decode", "identify_freeair", "identify_invols", "identify_gamma",
    "identify_thermal", "identify_electrostatic", "design_excitation", "theory_averaging", "theory_compare",
    "theory_fit",
]

CaptureLike = Capture | str | Path


# ----------------------------------------------------------------------------- shared machinery
def _fields(classes: tuple[type, ...]) -> list[dataclasses.Field]:
    return [f for cls in classes for f in dataclasses.fields(cls)]


def _models(command: str) -> tuple[type, ...]:
    """The parameter models of ``command``'s config sections, its own first (its spec's ``params``)."""
    return tuple(model for _, model in spec(command).sections())


def _function_name(command: str) -> str:
    return command.replace(" ", "_").replace("-", "_")


def _flags(command: str, given: Mapping[str, Any]) -> dict[str, Any]:
    """``{field: value or None}`` for every parameter of ``command``, as the CLI's flags give them."""
    function = _function_name(command)
    names = [f.name for f in _fields(_models(command))]
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ConfigError(f"afmtool.{function}() takes no parameter {unknown[0]!r}; its parameters are "
                          f"{', '.join(names)} (the TOML keys of its section)")
    return {name: given.get(name) for name in names}


def _settings(config: str | Path | None, jobs: int = 1, scheduler: str | None = None,
              max_samples: int | None = None) -> RunSettings:
    split = None
    if jobs != 1 or scheduler:
        from afmtool.pipeline import Split

        if not (isinstance(jobs, int) and jobs >= 1):
            raise ConfigError(f"jobs={jobs!r} must be an integer >= 1")
        split = Split.of(jobs, scheduler)
    return RunSettings(config=Path(config) if config else None, split=split, max_samples=max_samples)


def _in_private_folder(command: str, work: Callable[[Path], dict]) -> Result:
    """Run ``work(out)`` into a folder of its own; the result owns (and in the end removes) it."""
    import shutil

    root = Path(tempfile.mkdtemp(prefix="afmtool-"))
    out = root / command.replace(" ", "_")
    try:
        work(out)
    except BaseException:
        shutil.rmtree(root, ignore_errors=True)
        raise
    return Result.own(command, out, root)


def _stream(command: str, capture: Capture, flags: Mapping, settings: RunSettings) -> Iterator[ChunkResult]:
    units = dict(spec(command).stream_units.load())  # the columns' units, named by the command's spec
    deflection_units = capture.units.get("deflection", "")
    units.update(amplitude=deflection_units, sigma2=f"{deflection_units}^2" if deflection_units else "")
    sink = ChunkQueue(command, units)
    return sink.run(lambda queue: run_stream_rows(command, capture, flags, settings, queue))


# ----------------------------------------------------------------------------- signatures and docstrings
_KEYWORD = inspect.Parameter.KEYWORD_ONLY
_POSITIONAL = inspect.Parameter.POSITIONAL_OR_KEYWORD

_RUN_PARAMETERS = {
    "config": ("str or Path, optional", "A TOML file whose section sets parameters (``--config``); keywords win."),
    "stream": ("bool", "Return an iterator of :class:`~afmtool.api.results.ChunkResult` (the output series' rows "
                       "of each chunk, as they are computed) instead of a result: for captures larger than memory."),
    "jobs": ("int", "Chunks analysed at once on this machine's threads (``--jobs``)."),
    "scheduler": ("str, optional", "A Dask scheduler address (``--scheduler``): the chunks run on its workers."),
    "max_file_samples": ("int, optional", "Accept HDF5 captures of up to this many samples per dataset whatever their "
                                     "size on disk (``afmtool --max-samples``); by default a file may claim at most "
                                     "1000x its size."),
}


def _type_name(f: dataclasses.Field) -> str:
    return {"float": "float", "int": "int", "bool": "bool", "str": "str"}.get(str(f.type), str(f.type))


def _parameter_doc(f: dataclasses.Field) -> str:
    from afmtool.config import describe_bounds

    meta = f.metadata
    units = f" [{meta['units']}]" if meta.get("units") else ""
    bounds = describe_bounds(meta)
    extra = []
    if meta.get("choices"):
        extra.append("one of " + ", ".join(repr(c) for c in meta["choices"]))
    if bounds:
        extra.append(bounds)
    if meta.get("flag"):
        extra.append(f"CLI {meta['flag']}")
    tail = f" ({'; '.join(extra)})" if extra else ""
    return f"{f.name} : {_type_name(f)}, default {f.default!r}{units}\n    {meta.get('help', '')}{tail}."


def _document(function: Callable, command: str, inputs: list[tuple[str, str, str, Any]],
              run_keywords: tuple[str, ...], example: str) -> Callable:
    """Give ``function`` the signature and numpydoc of ``command``'s parameter models (its spec's sections)."""
    classes, section = _models(command), spec(command).section
    run_keywords = (*run_keywords, "max_file_samples")
    parameters = [inspect.Parameter(name, _POSITIONAL if default is inspect.Parameter.empty else _KEYWORD,
                                    default=default) for name, _, _, default in inputs]
    parameters += [inspect.Parameter(f.name, _KEYWORD, default=f.default, annotation=_type_name(f))
                   for f in _fields(classes)]
    defaults = {"config": None, "stream": False, "jobs": 1, "scheduler": None, "max_file_samples": None}
    parameters += [inspect.Parameter(name, _KEYWORD, default=defaults[name]) for name in run_keywords]
    function.__signature__ = inspect.Signature(parameters, return_annotation="Result")
    summary = inspect.cleandoc(function.__doc__ or "")
    docs = [f"{name} : {kind}\n    {text}" for name, kind, text, _ in inputs]
    docs += [_parameter_doc(f) for f in _fields(classes)]
    docs += [f"{name} : {_RUN_PARAMETERS[name][0]}\n    {_RUN_PARAMETERS[name][1]}" for name in run_keywords]
    returns = ("Result\n    Frozen: ``.summary`` (headline numbers with units), ``.report`` (report.json), "
               "``.to_xarray()``, ``.save(out_dir)`` (the CLI's output folder), shown as cards and the main "
               "figure in a notebook.")
    if "stream" in run_keywords:
        returns += "\n    With ``stream=True``: an iterator of ChunkResult."
    function.__doc__ = (
        f"{summary}\n\nParameters\n----------\n" + "\n".join(docs)
        + f"\n\nThe keywords are the TOML keys of ``[{section}]`` (``afmtool config init``).\n\n"
        f"Returns\n-------\n{returns}\n\nRaises\n------\nafmtool.InputError, afmtool.ConfigError\n"
        f"    With the CLI's one-line message.\n\nExamples\n--------\n{inspect.cleandoc(example)}\n"
    )
    return function


_CAPTURE_INPUT = [("capture", "Capture or path", "The capture (:func:`afmtool.open`, "
                   ":meth:`afmtool.Capture.from_arrays`) or its path.", inspect.Parameter.empty)]


# ----------------------------------------------------------------------------- the capture commands
def _capture_command(command: str, capture: CaptureLike, stream: bool, config, jobs: int, scheduler,
                     max_file_samples: int | None, params: Mapping) -> Result | Iterator[ChunkResult]:
    flags = _flags(command, params)
    settings = _settings(config, jobs, scheduler, max_file_samples)
    with settings.scope():  # a path opens here, under --max-samples
        capture = as_capture(capture)
    if stream:
        return _stream(command, capture, flags, settings)
    return _in_private_folder(command, lambda out: run_capture_command(command, capture, out, flags, settings))


def reep(capture: CaptureLike, *, stream: bool = False, config=None, jobs: int = 1, scheduler=None,
         max_file_samples=None, **params):
    """REEP: f0′ and Q′ every sample by bias-compensated EW-RLS (thesis ch. 3), as ``afmtool reep``.

    Writes (in the result's folder) reep.h5 with t [s], f0_hz [Hz], q, their standard
    deviations f0_std_hz [Hz] and q_std, amplitude [deflection units], phase_deg [deg],
    b1, b0, sigma2, offset and flag; with z_piezo force-curve tables and figures; with
    scan metadata images.  Samples whose fit cannot be trusted are flagged.
    """
    return _capture_command("reep", capture, stream, config, jobs, scheduler, max_file_samples, params)


def probeloss(capture: CaptureLike, *, stream: bool = False, config=None, jobs: int = 1, scheduler=None,
              max_file_samples=None, **params):
    """Probe loss from the reliability index (thesis ch. 2), beside the amplitude threshold, as ``afmtool probeloss``.

    An observer on the free-air model runs beside the deflection; its innovation RMS over one
    drive period, over its free-air level, is the reliability index (dimensionless), low
    when the tip is off the sample.  probeloss.h5 holds t [s], index, switch, amplitude.
    """
    return _capture_command("probeloss", capture, stream, config, jobs, scheduler, max_file_samples, params)


def decode(capture: CaptureLike, *, stream: bool = False, config=None, jobs: int = 1, scheduler=None,
           max_file_samples=None, **params):
    """Bits read by an electrostatically actuated probe, by an EKF (thesis ch. 7), as ``afmtool decode``.

    Needs deflection [nm] and v_sub, v_r [V].  decode.h5 holds the innovation [nm], its mean
    per actuation period and the bits; the report the BER against ``/truth`` when present.
    """
    return _capture_command("decode", capture, stream, config, jobs, scheduler, max_file_samples, params)


def kalman_bank(capture: CaptureLike, *, config=None, jobs: int = 1, scheduler=None, max_file_samples=None,
                **params) -> Result:
    """REEP's on-sample f0′, Q′ checked by a bank of Kalman filters and an adaptive observer (§3.4.2).

    As ``afmtool kalman-bank``: needs dither, deflection and z_piezo; bank.h5 holds each
    filter's innovation RMS [nm] against time [s].
    """
    return _capture_command("kalman-bank", capture, False, config, jobs, scheduler, max_file_samples, params)


_document(reep, "reep", _CAPTURE_INPUT, ("stream", "config", "jobs", "scheduler"), """
    >>> import afmtool
    >>> cap = afmtool.open("sample_data/ltv_step.h5")
    >>> run = afmtool.reep(cap, lam=0.995)          # afmtool reep --lambda 0.995
    >>> run.summary["f0' in the free-air segment"].units
    'Hz'
    >>> ds = run.to_xarray()                         # f0_hz, q, f0_std_hz ... on time [s]
    >>> run.save("results/reep")                     # the CLI's output folder
    PosixPath('results/reep')
""")
_document(probeloss, "probeloss", _CAPTURE_INPUT, ("stream", "config", "jobs", "scheduler"), """
    >>> import afmtool
    >>> run = afmtool.probeloss("sample_data/raster_grating.h5")
    >>> run.to_xarray()["index"].attrs["units"]
    '1'
""")
_document(decode, "decode", _CAPTURE_INPUT, ("stream", "config", "jobs", "scheduler"), """
    >>> import afmtool
    >>> run = afmtool.decode("sample_data/bits_30khz.h5", bit_rate_hz=30000)
    >>> run.summary.to_dict()   # BER and its 95 % bound, bits decoded
""")
_document(kalman_bank, "kalman-bank", _CAPTURE_INPUT, ("config", "jobs", "scheduler"), """
    >>> import afmtool
    >>> run = afmtool.kalman_bank("sample_data/force_curve_thesis.h5")
    >>> run.summary
""")


# ----------------------------------------------------------------------------- identification
def identify_freeair(capture: CaptureLike | None = None, *, psd: str | Path | None = None,
                     thermal: CaptureLike | None = None, invols: float | None = None, config=None,
                     max_file_samples=None, **params) -> Result:
    """The free-air model: f0, Q, gain, the spring constant and their uncertainties, as ``afmtool identify freeair``.

    Routes: an off-sample segment of ``capture`` (ARX fit, bias compensated), a sweep
    (``route="sweep"``), or thermal noise (``psd`` table or ``thermal`` time record).
    free_air.json is what ``model=`` of reep, probeloss and kalman-bank reads.
    """
    flags = _flags("identify freeair", params)
    spring_names = [f.name for f in dataclasses.fields(_models("identify freeair")[1])]
    spring = {name: flags.pop(name) for name in spring_names}
    flags = {**flags, "spring": spring}
    settings = _settings(config, max_samples=max_file_samples)
    with settings.scope():  # a path opens here, under --max-samples
        capture = None if capture is None else as_capture(capture)
        thermal = None if thermal is None else as_capture(thermal, "thermal")
    return _in_private_folder("identify freeair", lambda out: run_identify_freeair(
        capture, out, flags, settings, psd=psd, thermal=thermal, invols=invols))


_document(identify_freeair, "identify freeair", [
    ("capture", "Capture or path, optional", "A capture with dither and deflection (segment or sweep route).", None),
    ("psd", "str or Path, optional", "Thermal route: a spectrum table (CSV), ASD or PSD in m, nm or V.", None),
    ("thermal", "Capture or path, optional", "Thermal route: a thermal-noise time record (deflection).", None),
    ("invols", "float, optional", "InvOLS [nm/V] of a spectrum or record in V (``--invols``).", None),
], ("config",), """
    >>> import afmtool
    >>> fa = afmtool.identify_freeair("sample_data/ltv_step.h5")
    >>> fa.summary.to_dict()                 # f0 [Hz], Q, gain, with uncertainties
    >>> fa.save("results/freeair")            # free_air.json for model="results/freeair"
    PosixPath('results/freeair')
""")


def identify_gamma(sweep: CaptureLike, contact: CaptureLike, *, config=None, max_file_samples=None, **params) -> Result:
    """Γ_IR,ts with the feed-through removed (thesis eq. 6.15), as ``afmtool identify gamma``.

    The DC sensitivity [µA/nm], the −3 dB bandwidth [Hz], the roll-off [dB/decade]; gamma.h5
    holds the frequency responses.
    """
    flags, settings = _flags("identify gamma", params), _settings(config, max_samples=max_file_samples)
    with settings.scope():  # a path opens here, under --max-samples
        sweep, contact = as_capture(sweep, "sweep"), as_capture(contact, "contact")
    return _in_private_folder("identify gamma", lambda out: run_identify_gamma(sweep, contact, out, flags, settings))


_document(identify_gamma, "identify gamma", [
    ("sweep", "Capture or path", "Sweep near the sample: v_sub, thermal_current and deflection.", inspect.Parameter.empty),
    ("contact", "Capture or path", "The same sweep in contact: v_sub and thermal_current.", inspect.Parameter.empty),
], ("config",), """
    >>> import afmtool
    >>> g = afmtool.identify_gamma("sample_data/thermal_sweep_near.h5", "sample_data/thermal_sweep_contact.h5")
    >>> g.summary
""")


def identify_thermal(*, iv: CaptureLike | None = None, z_curve: CaptureLike | None = None,
                     vr_sweep: CaptureLike | None = None, gamma: str | Path | None = None,
                     model: str | Path | None = None, config=None, max_file_samples=None, **params) -> Result:
    """The thermal sensor from its current alone: g(T), K_TP, C(jω), H(jω) (thesis 6.5.2, 6.6.2).

    As ``afmtool identify thermal``; writes thermal_sensor.json (for identify_electrostatic).
    """
    flags = _flags("identify thermal", params)
    inputs = {"iv": iv, "z": z_curve, "vr": vr_sweep, "gamma": gamma, "model": model}
    settings = _settings(config, max_samples=max_file_samples)
    return _in_private_folder("identify thermal", lambda out: run_identify_thermal(inputs, out, flags, settings))


_document(identify_thermal, "identify thermal", [
    ("iv", "Capture or path, optional", "I-V ramp: v_r [V] and thermal_current [µA] past breakdown.", None),
    ("z_curve", "Capture or path, optional", "Thermal z force curve: z_piezo, v_r, thermal_current.", None),
    ("vr_sweep", "Capture or path, optional", "V_R perturbation sweep: v_r, thermal_current.", None),
    ("gamma", "str or Path, optional", "gamma.h5 (or its folder) from identify_gamma, for H(jω).", None),
    ("model", "str or Path, optional", "thermal_sensor.json supplying g(T) without ``iv``.", None),
], ("config",), """
    >>> import afmtool
    >>> th = afmtool.identify_thermal(iv="iv.h5")
    >>> th.summary
""")


def identify_electrostatic(capture: CaptureLike, *, thermal_model: str | Path | None = None, config=None,
                           max_file_samples=None, **params) -> Result:
    """Electrostatic parameters from an approach curve before snap-in (thesis eqs. 6.6, 6.7).

    As ``afmtool identify electrostatic``: l0 [nm], K_esf/k, α_R with uncertainties.
    """
    flags, settings = _flags("identify electrostatic", params), _settings(config, max_samples=max_file_samples)
    with settings.scope():  # a path opens here, under --max-samples
        capture = as_capture(capture)
    return _in_private_folder("identify electrostatic", lambda out: run_identify_electrostatic(
        capture, out, flags, settings, thermal_model))


_document(identify_electrostatic, "identify electrostatic", _CAPTURE_INPUT + [
    ("thermal_model", "str or Path, optional", "thermal_sensor.json from identify_thermal.", None),
], ("config",), """
    >>> import afmtool
    >>> es = afmtool.identify_electrostatic("es.h5")
    >>> es.summary
""")


def identify_invols(curve: CaptureLike, *, config=None, max_file_samples=None, **params) -> Result:
    """InvOLS [nm/V] from the contact part of a force curve on a hard sample, as ``afmtool identify invols``."""
    flags, settings = _flags("identify invols", params), _settings(config, max_samples=max_file_samples)
    with settings.scope():  # a path opens here, under --max-samples
        curve = as_capture(curve, "curve")
    return _in_private_folder("identify invols", lambda out: run_identify_invols(curve, out, flags, settings))


_document(identify_invols, "identify invols", [
    ("curve", "Capture or path", "Force curve on a hard sample: deflection [V] and z_piezo.", inspect.Parameter.empty),
], ("config",), """
    >>> import afmtool
    >>> inv = afmtool.identify_invols("curve_on_sapphire.ibw")
    >>> inv.summary
""")


# ----------------------------------------------------------------------------- design and theory
def design_excitation(model: str | Path, *, config=None, max_file_samples=None, **params) -> Result:
    """The three-sine REEP dither of §3.3.2 for an identified cantilever, as ``afmtool design excitation``."""
    flags, settings = _flags("design excitation", params), _settings(config, max_samples=max_file_samples)
    return _in_private_folder("design excitation",
                              lambda out: run_folder_command("design excitation", model, out, flags, settings))


_document(design_excitation, "design excitation", [
    ("model", "str or Path", "free_air.json (or its folder) from identify_freeair.", inspect.Parameter.empty),
], ("config",), """
    >>> import afmtool
    >>> ex = afmtool.design_excitation("results/freeair", amplitude_nm=20)
    >>> ex.summary
""")


def theory_averaging(*, config=None, max_file_samples=None, **params) -> Result:
    """Averaging theory (eqs. 4.6-4.8): f0e, Qe and the steady state along a force curve, as ``afmtool theory averaging``."""
    flags, settings = _flags("theory averaging", params), _settings(config, max_samples=max_file_samples)
    return _in_private_folder("theory averaging",
                              lambda out: run_folder_command("theory averaging", None, out, flags, settings))


_document(theory_averaging, "theory averaging", [], ("config",), """
    >>> import afmtool
    >>> th = afmtool.theory_averaging(force_set="attractive")
    >>> th.to_xarray()
""")


def _reep_folder(reep_run: Result | str | Path) -> Path:
    return reep_run.folder if isinstance(reep_run, Result) else Path(reep_run)


def theory_compare(reep_run: Result | str | Path, *, config=None, max_file_samples=None, **params) -> Result:
    """REEP's f0′ and Q′ beside averaging theory along a force curve (§3.4.3), with a verdict.

    As ``afmtool theory compare``; ``reep_run`` is a REEP result or its saved folder.
    """
    flags = _flags("theory compare", params)
    if isinstance(flags.get("fit"), Result):
        flags["fit"] = str(flags["fit"].folder)
    folder, settings = _reep_folder(reep_run), _settings(config, max_samples=max_file_samples)
    return _in_private_folder("theory compare",
                              lambda out: run_folder_command("theory compare", folder, out, flags, settings))


_document(theory_compare, "theory compare", [
    ("reep_run", "Result or path", "A REEP result on a force curve (``afmtool.reep``) or its output folder.",
     inspect.Parameter.empty),
], ("config",), """
    >>> import afmtool
    >>> run = afmtool.reep("sample_data/tapping_force_curve.h5")
    >>> cmp = afmtool.theory_compare(run)
    >>> cmp.summary
""")


def theory_fit(reep_run: Result | str | Path, *, config=None, max_file_samples=None, **params) -> Result:
    """Fit d, ωa², ωb², ca, cb and the contact point so averaging theory reproduces the approach, as ``afmtool theory fit``."""
    flags = _flags("theory fit", params)
    folder, settings = _reep_folder(reep_run), _settings(config, max_samples=max_file_samples)
    return _in_private_folder("theory fit", lambda out: run_folder_command("theory fit", folder, out, flags, settings))


_document(theory_fit, "theory fit", [
    ("reep_run", "Result or path", "A REEP result on a force curve, or its output folder.", inspect.Parameter.empty),
], ("config",), """
    >>> import afmtool
    >>> fit = afmtool.theory_fit(afmtool.reep("sample_data/tapping_force_curve.h5"))
    >>> fit.summary
""")
