"""Simulator: named scenarios that synthesise captures together with their ground truth.

A scenario is a frozen dataclass of parameters (every field with a default
and ``metadata={"help": ..., "units": ...}``, built with :func:`param`)
plus a function ``(params, seed) -> SimulatedCapture``.  Scenarios live in
an open registry: a module adds one with :func:`register_scenario`, and the
CLI lists them with :func:`scenario_names`, builds ``--help`` and the
default TOML from :func:`scenario_parameters`, and runs them with
:func:`simulate`, which validates the overrides before any work starts.

Built-in scenarios: ``tapping`` (:mod:`afmtool.sim.tapping`), ``ltv``
(:mod:`afmtool.sim.ltv`), ``raster`` (:mod:`afmtool.sim.raster`, ch. 2),
``thermal-sweep``, ``iv-ramp`` and ``es-approach``
(:mod:`afmtool.sim.thermal_scenarios`, ch. 6), ``bits`` and ``vphi-step``
(:mod:`afmtool.sim.bits`, :mod:`afmtool.sim.vphi`, ch. 7).
"""

from __future__ import annotations

import dataclasses
import numbers
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from afmtool.config import coerce_value, describe_bounds, within_bounds
from afmtool.config import field as declare_parameter
from afmtool.errors import ConfigError
from afmtool.io.capture import CaptureInfo, ChannelSpec

__all__ = [
    "SimulatedCapture",
    "ScenarioInfo",
    "ParameterInfo",
    "param",
    "validate_parameters",
    "parameters_to_dict",
    "register_scenario",
    "scenario_names",
    "scenario_info",
    "scenario_defaults",
    "scenario_parameters",
    "simulate",
]


@dataclass(frozen=True)
class SimulatedCapture:
    """A synthesised capture: channels, metadata and ground truth.

    Parameters
    ----------
    sample_rate_hz : float
        Sample rate shared by every channel and truth array, Hz.
    channels : tuple of ChannelSpec
        Recorded channels, in order, with units.
    data : Mapping[str, numpy.ndarray]
        One 1-D float64 array per channel, all of equal length.
    metadata : Mapping
        Capture metadata (``schemas/capture-metadata.schema.json``), JSON-ready.
    truth : Mapping[str, numpy.ndarray]
        Ground truth arrays (written under ``/truth``), one value per sample.
    """

    sample_rate_hz: float
    channels: tuple[ChannelSpec, ...]
    data: Mapping[str, np.ndarray]
    metadata: Mapping
    truth: Mapping[str, np.ndarray]

    def __post_init__(self) -> None:
        names = [c.name for c in self.channels]
        if sorted(names) != sorted(self.data):
            raise ValueError(f"channels {names} do not match data keys {sorted(self.data)}")
        lengths = {len(v) for v in self.data.values()} | {len(v) for v in self.truth.values()}
        if len(lengths) > 1:
            raise ValueError(f"channel and truth arrays differ in length: {sorted(lengths)}")
        object.__setattr__(self, "channels", tuple(self.channels))
        object.__setattr__(self, "data", MappingProxyType(dict(self.data)))
        object.__setattr__(self, "metadata", MappingProxyType(dict(self.metadata)))
        object.__setattr__(self, "truth", MappingProxyType(dict(self.truth)))

    @property
    def n_samples(self) -> int:
        """Number of samples per channel."""
        return len(next(iter(self.data.values()))) if self.data else 0

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.sample_rate_hz

    def time_s(self) -> np.ndarray:
        """Sample times, s, from 0."""
        return np.arange(self.n_samples) / self.sample_rate_hz

    def info(self, source: str | None = None) -> CaptureInfo:
        """The :class:`CaptureInfo` a writer needs (format ``"sim"``)."""
        scenario = self.metadata.get("scenario", "unknown")
        return CaptureInfo(
            source=source or f"sim:{scenario}",
            format="sim",
            sample_rate_hz=self.sample_rate_hz,
            channels=self.channels,
            n_samples=self.n_samples,
            metadata=self.metadata,
        )


# --------------------------------------------------------------------------- parameters

_SUPPORTED_TYPES = ("float", "int", "bool", "str", "tuple[float, ...]")


def param(
    default: Any,
    help: str,  # named help: the metadata key the CLI reads
    units: str = "",
    *,
    choices: tuple[str, ...] | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
) -> Any:
    """A scenario-parameter field with its help text, units and constraints.

    Use as ``duration_s: float = param(0.05, "capture length", "s", minimum=0,
    exclusive_minimum=True)``.  ``minimum``/``maximum`` apply to numbers and
    to every element of a tuple; ``choices`` to strings.  The declaration is
    :func:`afmtool.config.field`'s, the one the commands' parameters use, so
    ``defaults.toml``, the JSON schemas and the bounds check read both alike.
    """
    return declare_parameter(
        default, help, units, tuple(choices) if choices is not None else None,
        minimum=minimum, maximum=maximum, exclusive_minimum=exclusive_minimum,
    )


@dataclass(frozen=True)
class ParameterInfo:
    """One scenario parameter, as the CLI shows it."""

    name: str
    type: str
    default: Any
    help: str
    units: str
    choices: tuple[str, ...] | None
    minimum: float | None
    maximum: float | None


def _type_name(tp: Any) -> str:
    if tp in (float, int, bool, str):
        return tp.__name__
    if typing.get_origin(tp) is tuple and typing.get_args(tp) == (float, ...):
        return "tuple[float, ...]"
    return repr(tp)


def _field_types(params_cls: type) -> dict[str, str]:
    hints = typing.get_type_hints(params_cls)
    return {f.name: _type_name(hints[f.name]) for f in dataclasses.fields(params_cls)}


def _check_bounds(name: str, value: Any, meta: Mapping) -> None:
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"parameter {name}={value!r} must be one of {', '.join(map(repr, meta['choices']))}")
    if not within_bounds(value, meta):
        raise ConfigError(f"parameter {name}={value!r} must be {describe_bounds(meta)}")


def validate_parameters(params: Any) -> None:
    """Type-check, normalise and range-check every field of a parameters dataclass.

    Call it first in the dataclass's ``__post_init__``.  Ints given for
    float fields become floats and lists become tuples (in place, through
    ``object.__setattr__``).

    Raises
    ------
    ConfigError
        Naming the first bad field and its value.
    """
    hints = typing.get_type_hints(type(params))
    for f in dataclasses.fields(params):
        value = coerce_value(f.name, hints[f.name], getattr(params, f.name), "parameter ")
        _check_bounds(f.name, value, f.metadata)
        object.__setattr__(params, f.name, value)


def parameters_to_dict(params: Any) -> dict[str, Any]:
    """The parameters as a JSON-ready dict (tuples become lists)."""
    return {
        f.name: list(v) if isinstance(v := getattr(params, f.name), tuple) else v for f in dataclasses.fields(params)
    }


# --------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class ScenarioInfo:
    """A registered scenario."""

    name: str
    params_cls: type
    run: Callable[[Any, int], SimulatedCapture]

    @property
    def summary(self) -> str:
        """First line of the run function's docstring."""
        doc = (self.run.__doc__ or self.params_cls.__doc__ or "").strip()
        return doc.splitlines()[0] if doc else ""


_REGISTRY: dict[str, ScenarioInfo] = {}


def register_scenario(name: str, params_cls: type, fn: Callable[[Any, int], SimulatedCapture]) -> None:
    """Add a scenario to the registry.

    Parameters
    ----------
    name : str
        Scenario name as typed on the command line (e.g. ``"tapping"``).
    params_cls : type
        Frozen dataclass whose fields all have defaults, ``help``/``units``
        metadata and one of the supported types (float, int, bool, str,
        tuple[float, ...]).
    fn : callable
        ``fn(params, seed) -> SimulatedCapture``; deterministic given ``seed``.

    Raises
    ------
    ValueError
        If the name is taken or ``params_cls`` breaks the rules above (a
        programming error, not a user one).
    """
    if not (isinstance(name, str) and name and name == name.strip()):
        raise ValueError(f"scenario name {name!r} must be a non-empty string")
    if name in _REGISTRY:
        raise ValueError(f"scenario {name!r} is already registered")
    if not (dataclasses.is_dataclass(params_cls) and params_cls.__dataclass_params__.frozen):
        raise ValueError(f"{params_cls!r} must be a frozen dataclass")
    for f in dataclasses.fields(params_cls):
        if f.default is dataclasses.MISSING:
            raise ValueError(f"{params_cls.__name__}.{f.name} needs a default")
        if "help" not in f.metadata or "units" not in f.metadata:
            raise ValueError(f"{params_cls.__name__}.{f.name} needs help and units metadata (use param())")
    for field_name, kind in _field_types(params_cls).items():
        if kind not in _SUPPORTED_TYPES:
            raise ValueError(f"{params_cls.__name__}.{field_name} has unsupported type {kind}")
    params_cls()  # the defaults themselves must validate
    _REGISTRY[name] = ScenarioInfo(name, params_cls, fn)


def scenario_names() -> tuple[str, ...]:
    """Registered scenario names, sorted."""
    return tuple(sorted(_REGISTRY))


def scenario_info(name: str) -> ScenarioInfo:
    """The registered scenario ``name``; ConfigError if unknown."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown scenario {name!r}; known: {', '.join(scenario_names())}") from None


def scenario_defaults(name: str) -> Any:
    """The default parameters of scenario ``name`` (a frozen dataclass instance)."""
    return scenario_info(name).params_cls()


def scenario_parameters(name: str) -> tuple[ParameterInfo, ...]:
    """Name, type, default, help, units and constraints of each parameter, in field order."""
    cls = scenario_info(name).params_cls
    kinds = _field_types(cls)
    return tuple(
        ParameterInfo(
            name=f.name,
            type=kinds[f.name],
            default=f.default,
            help=f.metadata["help"],
            units=f.metadata["units"],
            choices=f.metadata.get("choices"),
            minimum=f.metadata.get("minimum"),
            maximum=f.metadata.get("maximum"),
        )
        for f in dataclasses.fields(cls)
    )


def simulate(name: str, overrides: Mapping[str, Any] | None = None, seed: int = 0) -> SimulatedCapture:
    """Run scenario ``name`` with its defaults replaced by ``overrides``.

    Parameters
    ----------
    name : str
        A registered scenario (:func:`scenario_names`).
    overrides : Mapping[str, Any], optional
        Parameter values by field name; ints are accepted for floats and
        lists for tuples.
    seed : int, optional
        Seed of ``numpy.random.default_rng``; the result is a deterministic
        function of ``(name, overrides, seed)``.

    Returns
    -------
    SimulatedCapture
        With ``metadata["scenario"]``, ``metadata["seed"]`` and the
        effective ``metadata["parameters"]`` set.

    Raises
    ------
    ConfigError
        For an unknown scenario or parameter, a value of the wrong type or
        out of range (the message names the key and the value), or a bad seed.
    """
    info = scenario_info(name)
    if not (isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and seed >= 0):
        raise ConfigError(f"seed={seed!r} must be an integer >= 0")
    overrides = {} if overrides is None else overrides
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"overrides must be a mapping of parameter names to values, got {type(overrides).__name__}")
    fields = {f.name: f for f in dataclasses.fields(info.params_cls)}
    hints = typing.get_type_hints(info.params_cls)
    checked: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in fields:
            raise ConfigError(
                f"unknown parameter {key!r}={value!r} for scenario {name!r}; known: {', '.join(sorted(fields))}"
            )
        checked[key] = coerce_value(key, hints[key], value, "parameter ")
        _check_bounds(key, checked[key], fields[key].metadata)
    _check_size(name, {f: checked.get(f, fields[f].default) for f in ("sample_rate_hz", "duration_s", "capture_s") if f in fields})
    try:
        params = dataclasses.replace(info.params_cls(), **checked)
    except TypeError as exc:  # a params class refusing a value in its own __post_init__
        raise ConfigError(f"scenario {name!r}: {exc}") from None
    capture = info.run(params, int(seed))
    metadata = dict(capture.metadata)
    metadata["scenario"] = name
    metadata["seed"] = int(seed)
    metadata["parameters"] = parameters_to_dict(params)
    return dataclasses.replace(capture, metadata=metadata)


#: A simulated capture is held in memory, every channel and its truth: at most this many samples.
MAX_SIMULATED_SAMPLES = 1 << 25
#: The simulators discretise continuous models at the sample rate; past this their matrices are singular.
MAX_SIMULATED_RATE_HZ = 1e10


def _check_size(name: str, values: Mapping[str, Any]) -> None:
    """Refuse a scenario whose sample rate or length no simulation can hold, before its parameters are
    even built (their own checks discretise the model at that rate)."""
    rate = values.get("sample_rate_hz")
    if not isinstance(rate, (int, float)):
        return
    if not rate <= MAX_SIMULATED_RATE_HZ:
        raise ConfigError(f"scenario {name!r}: sample_rate_hz={rate!r} must be at most {MAX_SIMULATED_RATE_HZ:g}")
    for key in ("duration_s", "capture_s"):
        duration = values.get(key)
        if isinstance(duration, (int, float)) and not duration * rate <= MAX_SIMULATED_SAMPLES:
            raise ConfigError(
                f"scenario {name!r}: {key}={duration!r} at {rate:g} Hz is {duration * rate:.4g} samples; a simulation "
                f"is held in memory, at most {MAX_SIMULATED_SAMPLES:,} samples (simulate shorter captures)"
            )


# --------------------------------------------------------------------------- built-in scenarios
# Imported last: the scenario modules import SimulatedCapture, param and
# validate_parameters from this package.
from afmtool.sim import ltv as _ltv  # noqa: E402 - imports SimulatedCapture and param from above
from afmtool.sim import tapping as _tapping  # noqa: E402 - imports SimulatedCapture and param from above

register_scenario("tapping", _tapping.TappingParams, _tapping.simulate_tapping)
register_scenario("ltv", _ltv.LtvParams, _ltv.simulate_ltv)

# These modules register themselves on import.
from afmtool.sim import bits as _bits  # noqa: E402, F401 - registers its scenarios on import
from afmtool.sim import raster as _raster  # noqa: E402, F401 - registers its scenarios on import
from afmtool.sim import thermal_scenarios as _thermal_scenarios  # noqa: E402, F401 - registers its scenarios on import
from afmtool.sim import vphi as _vphi  # noqa: E402, F401 - registers its scenarios on import
