"""Validation of capture metadata.

The contract is ``schemas/capture-metadata.schema.json``; this module checks
the typed keys of that schema without a runtime dependency on a JSON-schema
engine.  ``tests/test_metadata.py`` keeps the two in step by running the same
good and bad examples through both.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from afmtool.errors import InputError

__all__ = [
    "FORCE_KEYS",
    "MAX_JSON_DEPTH",
    "CantileverMetadata",
    "CaptureMetadata",
    "ControllerMetadata",
    "DriveLineMetadata",
    "DriveMetadata",
    "ElectrostaticMetadata",
    "ForceMetadata",
    "IntervalMetadata",
    "RampMetadata",
    "StepMetadata",
    "ScanMetadata",
    "SweepSegmentMetadata",
    "json_depth",
    "load_json",
    "MAX_JSON_CHARS",
    "parse_metadata_json",
    "validate_metadata",
]

_POSITIVE = "a number > 0"


#: Largest scan image (lines x pixels per line) accepted: 2^26 pixels, 512 MiB as float64.
MAX_SCAN_PIXELS = 1 << 26


def _is_number(value: Any) -> bool:
    """A finite int or float (not a bool), and one a float can hold: JSON's 1 followed by 400 zeros is not."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float range
        return False


def _check_number(where: str, value: Any, *, minimum: float = 0.0, exclusive: bool = True) -> None:
    ok = _is_number(value) and (value > minimum if exclusive else value >= minimum)
    if not ok:
        bound = f"> {minimum:g}" if exclusive else f">= {minimum:g}"
        raise InputError(f"metadata {where}={value!r} must be a number {bound}")


def _check_int(where: str, value: Any) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise InputError(f"metadata {where}={value!r} must be an integer >= 1")


def _check_object(where: str, value: Any) -> Mapping:
    if not isinstance(value, Mapping):
        raise InputError(f"metadata {where} must be an object, got {type(value).__name__}")
    return value


def validate_metadata(metadata: Any) -> dict:
    """Check the typed keys of capture metadata and return it as a dict.

    Raises
    ------
    InputError
        Naming the first offending key and its value.
    """
    meta = dict(_check_object("root", metadata))
    for name, check in _FAMILIES.items():
        if name in meta:
            check(meta[name])
    return meta


def _validate_cantilever(value: Any) -> None:
    cantilever = _check_object("cantilever", value)
    for key in ("f0_hz", "q", "spring_constant_n_per_m", "deflection_sensitivity_nm_per_v"):
        if key in cantilever:
            _check_number(f"cantilever.{key}", cantilever[key])


def _validate_scan(value: Any) -> None:
    scan = _check_object("scan", value)
    for key in ("lines", "pixels_per_line", "scan_size_m", "line_rate_hz"):
        if key not in scan:
            raise InputError(f"metadata scan needs {key}")
    _check_int("scan.lines", scan["lines"])
    _check_int("scan.pixels_per_line", scan["pixels_per_line"])
    if scan["lines"] * scan["pixels_per_line"] > MAX_SCAN_PIXELS:
        raise InputError(
            f"metadata scan of {scan['lines']} x {scan['pixels_per_line']} pixels exceeds {MAX_SCAN_PIXELS:,} "
            "(an image afmtool would have to hold in memory)"
        )
    _check_number("scan.scan_size_m", scan["scan_size_m"])
    _check_number("scan.line_rate_hz", scan["line_rate_hz"])
    if "trace_retrace" in scan and not isinstance(scan["trace_retrace"], bool):
        raise InputError(f"metadata scan.trace_retrace={scan['trace_retrace']!r} must be true or false")
    if "start_s" in scan:
        _check_number("scan.start_s", scan["start_s"], exclusive=False)


def _validate_drive(value: Any) -> None:
    drive = _check_object("drive", value)
    if "frequency_hz" in drive:
        _check_number("drive.frequency_hz", drive["frequency_hz"])
    if "sideband_offset_hz" in drive:
        _check_number("drive.sideband_offset_hz", drive["sideband_offset_hz"], exclusive=False)
    for key in ("free_amplitude_nm", "amplitude_v"):
        if key in drive:  # 0 is kept as "not known" (the analyses fall back on a measured value)
            _check_number(f"drive.{key}", drive[key], exclusive=False)
    for key in ("hold", "kind"):
        if key in drive:
            _check_string(f"drive.{key}", drive[key])
    if "lines" in drive:
        _validate_drive_lines(drive["lines"])


def _validate_drive_lines(lines: Any) -> None:
    """``drive.lines``: the synthesised dither's lines, for a capture without a dither channel."""
    if not isinstance(lines, list):
        raise InputError("metadata drive.lines must be a list of {frequency_hz, amplitude_v[, phase_deg]}")
    for i, line in enumerate(lines):
        line = _check_object(f"drive.lines[{i}]", line)
        for key in ("frequency_hz", "amplitude_v"):
            if key not in line:
                raise InputError(f"metadata drive.lines[{i}] needs {key}")
            _check_number(f"drive.lines[{i}].{key}", line[key])
        if "phase_deg" in line:
            _check_finite(f"drive.lines[{i}].phase_deg", line["phase_deg"])


def _validate_segments(value: Any) -> None:
    if not isinstance(value, list):
        raise InputError("metadata segments must be a list")
    for i, segment in enumerate(value):
        segment = _check_object(f"segments[{i}]", segment)
        for key in ("start_s", "end_s", "frequency_hz"):
            if key not in segment:
                raise InputError(f"metadata segments[{i}] needs {key}")
        _check_number(f"segments[{i}].start_s", segment["start_s"], exclusive=False)
        _check_number(f"segments[{i}].end_s", segment["end_s"])
        _check_number(f"segments[{i}].frequency_hz", segment["frequency_hz"])


def _validate_scenario(value: Any) -> None:
    if not isinstance(value, str):
        raise InputError("metadata scenario must be a string")


def _check_finite(where: str, value: Any) -> None:
    if not _is_number(value):
        raise InputError(f"metadata {where}={value!r} must be a finite number")


def _check_string(where: str, value: Any) -> None:
    if not isinstance(value, str):
        raise InputError(f"metadata {where}={value!r} must be a string")


def _check_interval(name: str, value: Any) -> None:
    interval = _check_object(name, value)
    for key in ("start_s", "end_s"):
        if key not in interval:
            raise InputError(f"metadata {name} needs {key}")
    _check_number(f"{name}.start_s", interval["start_s"], exclusive=False)
    _check_number(f"{name}.end_s", interval["end_s"])
    if interval["end_s"] <= interval["start_s"]:
        raise InputError(f"metadata {name}.end_s must be after {name}.start_s")


#: Typed keys of the set-up objects: (key, rule) with rule "positive" (> 0), "non-negative" (>= 0),
#: "finite" (any sign) or "string".  Any other key in them is kept as free-form.
_SETUP_KEYS = {
    "controller": (("setpoint_nm", "positive"), ("mode", "string")),
    "electrostatic": (("k_esf_f_m", "positive"), ("alpha_r", "non-negative"), ("l0_m", "positive"),
                      ("tip_height_m", "non-negative")),
    "vphi_step": (("time_s", "non-negative"), ("step_v", "finite")),
    "ramp": (("kind", "string"), ("v_r_v", "finite"), ("v_sub_max_v", "finite")),
    "force": (("d_nm", "non-negative"), ("omega_a2_per_s2", "non-negative"), ("omega_b2_per_s2", "non-negative"),
              ("c_a_per_s", "non-negative"), ("c_b_per_s", "non-negative"), ("set", "string")),
}
#: The force law of eq. 4.1 needs all five of its parameters.
FORCE_KEYS = ("d_nm", "omega_a2_per_s2", "omega_b2_per_s2", "c_a_per_s", "c_b_per_s")


def _setup_validator(name: str):
    """The check of set-up object ``name``: its typed keys by their rules; the force needs all of eq. 4.1's."""

    def check(value: Any) -> None:
        value = _check_object(name, value)
        for key, rule in _SETUP_KEYS[name]:
            if key not in value:
                continue
            where = f"{name}.{key}"
            if rule == "string":
                _check_string(where, value[key])
            elif rule == "finite":
                _check_finite(where, value[key])
            else:
                _check_number(where, value[key], exclusive=rule == "positive")
        missing = [key for key in FORCE_KEYS if key not in value] if name == "force" else []
        if missing:
            raise InputError(f"metadata force needs {', '.join(missing)}")

    return check


#: The validator of each typed top-level key, in the order they are checked.
_FAMILIES = {
    "cantilever": _validate_cantilever,
    "free_air": lambda value: _check_interval("free_air", value),
    "scan": _validate_scan,
    "drive": _validate_drive,
    "segments": _validate_segments,
    "scenario": _validate_scenario,
    **{name: _setup_validator(name) for name in _SETUP_KEYS},
    "nominal": lambda value: _check_interval("nominal", value),
}


def parse_metadata_json(text: str, where: str) -> dict:
    """Parse (bounded: :func:`load_json`) and validate a metadata JSON string found in ``where``."""
    value = load_json(text, where, "metadata")
    try:
        return validate_metadata(value)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


#: Deepest nesting of arrays and objects accepted in metadata JSON (the schema needs 3).
MAX_JSON_DEPTH = 64
#: Longest metadata JSON parsed, characters (afmtool writes a few kB).
MAX_JSON_CHARS = 64 << 20


def load_json(text: str, where: str, what: str = "metadata") -> object:
    """JSON from a file (an HDF5 attribute, a bag's metadata message, a CSV comment), parsed within bounds.

    The depth is measured first, without recursion (:func:`json_depth`): Python's parser
    recurses once per level and ends in RecursionError, or at 10^5 levels a stack
    overflow.  Past :data:`MAX_JSON_DEPTH` levels or :data:`MAX_JSON_CHARS` characters,
    one line and exit 2.

    Raises
    ------
    InputError
        Text that is too deep, too long or not JSON, naming ``where`` and ``what``.
    """
    if len(text) > MAX_JSON_CHARS:
        raise InputError(f"{where}: {what} JSON is {len(text):,} characters, more than {MAX_JSON_CHARS:,}")
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise InputError(f"{where}: {what} JSON is nested {depth} deep, more than {MAX_JSON_DEPTH}")
    try:
        return json.loads(text)
    except (json.JSONDecodeError, TypeError, RecursionError, ValueError) as exc:
        raise InputError(f"{where}: {what} is not valid JSON ({str(exc)[:200]})") from None


def json_depth(text: str) -> int:
    """The deepest nesting of ``[`` and ``{`` in JSON ``text``, outside strings; linear, no recursion.

    Measured before parsing: Python's ``json`` recurses once per level and
    ends in RecursionError (or, at 1e5 levels, a stack overflow).
    """
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


# --------------------------------------------------------------------------- typed records


def _float(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class CantileverMetadata:
    """``cantilever``: free-air f0 (Hz), Q, k (N/m), InvOLS (nm/V); None where not given."""

    f0_hz: float | None = None
    q: float | None = None
    spring_constant_n_per_m: float | None = None
    deflection_sensitivity_nm_per_v: float | None = None

    @classmethod
    def from_mapping(cls, value: Mapping) -> CantileverMetadata:
        return cls(*(_float(value.get(k)) for k in ("f0_hz", "q", "spring_constant_n_per_m",
                                                      "deflection_sensitivity_nm_per_v")))


@dataclass(frozen=True)
class DriveLineMetadata:
    """One line of ``drive.lines``: frequency (Hz), amplitude (V), cosine phase at the first sample (deg; None: fit it)."""

    frequency_hz: float
    amplitude_v: float
    phase_deg: float | None = None


@dataclass(frozen=True)
class DriveMetadata:
    """``drive``: the dither excitation.

    ``frequency_hz`` and ``sideband_offset_hz`` (Hz), ``free_amplitude_nm``
    (nm; 0 or None: not known), ``amplitude_v`` (V), ``hold`` (how the
    drive was generated; see :attr:`held`), ``kind`` and the ``lines`` for a
    capture without a dither channel.
    """

    frequency_hz: float | None = None
    sideband_offset_hz: float | None = None
    free_amplitude_nm: float | None = None
    amplitude_v: float | None = None
    hold: str = ""
    kind: str = ""
    lines: tuple[DriveLineMetadata, ...] = ()

    @property
    def held(self) -> bool:
        """Whether a DAC held the drive between samples: ``"zero-order..."`` (afmtool's simulators) or ``"zoh"``."""
        return self.hold.startswith("zero-order") or self.hold == "zoh"

    @classmethod
    def from_mapping(cls, value: Mapping) -> DriveMetadata:
        lines = tuple(DriveLineMetadata(float(x["frequency_hz"]), float(x["amplitude_v"]), _float(x.get("phase_deg")))
                      for x in value.get("lines", ()))
        return cls(*(_float(value.get(k)) for k in ("frequency_hz", "sideband_offset_hz", "free_amplitude_nm",
                                                      "amplitude_v")),
                   value.get("hold", ""), value.get("kind", ""), lines)


@dataclass(frozen=True)
class ControllerMetadata:
    """``controller``: the z feedback the capture was recorded under; ``setpoint_nm`` is the amplitude set-point (nm)."""

    setpoint_nm: float | None = None
    mode: str = ""

    @classmethod
    def from_mapping(cls, value: Mapping) -> ControllerMetadata:
        return cls(_float(value.get("setpoint_nm")), value.get("mode", ""))


@dataclass(frozen=True)
class ElectrostaticMetadata:
    """``electrostatic`` (SI): K_esf (F·m), α_R, the rest gap ℓ0 (m) and the tip height (m) of eq. 6.3."""

    k_esf_f_m: float | None = None
    alpha_r: float | None = None
    l0_m: float | None = None
    tip_height_m: float | None = None

    @classmethod
    def from_mapping(cls, value: Mapping) -> ElectrostaticMetadata:
        return cls(*(_float(value.get(k)) for k in ("k_esf_f_m", "alpha_r", "l0_m", "tip_height_m")))


@dataclass(frozen=True)
class StepMetadata:
    """``vphi_step``: a step in the sample's surface potential V_φ at ``time_s`` (s) of ``step_v`` (V) (§7.7)."""

    time_s: float | None = None
    step_v: float | None = None

    @classmethod
    def from_mapping(cls, value: Mapping) -> StepMetadata:
        return cls(_float(value.get("time_s")), _float(value.get("step_v")))


@dataclass(frozen=True)
class IntervalMetadata:
    """A segment of the capture, in seconds from its first sample (``free_air``, ``nominal``)."""

    start_s: float
    end_s: float

    @classmethod
    def from_mapping(cls, value: Mapping) -> IntervalMetadata:
        return cls(float(value["start_s"]), float(value["end_s"]))


@dataclass(frozen=True)
class RampMetadata:
    """``ramp``: a quasi-static ramp's ``kind``, the fixed V_R (V) and the largest V_sub (V)."""

    kind: str = ""
    v_r_v: float | None = None
    v_sub_max_v: float | None = None

    @classmethod
    def from_mapping(cls, value: Mapping) -> RampMetadata:
        return cls(value.get("kind", ""), _float(value.get("v_r_v")), _float(value.get("v_sub_max_v")))


@dataclass(frozen=True)
class ForceMetadata:
    """``force``: the piecewise-linear tip-sample force of eq. 4.1 (F/m; d in nm, ω² in 1/s², c in 1/s) and its set's name."""

    d_nm: float
    omega_a2_per_s2: float
    omega_b2_per_s2: float
    c_a_per_s: float
    c_b_per_s: float
    set: str = ""

    @classmethod
    def from_mapping(cls, value: Mapping) -> ForceMetadata:
        return cls(*(float(value[k]) for k in FORCE_KEYS), value.get("set", ""))


@dataclass(frozen=True)
class ScanMetadata:
    """``scan``: ``lines`` lines of ``pixels_per_line`` over ``scan_size_m`` (m) at ``line_rate_hz``, from ``start_s`` (s)."""

    lines: int
    pixels_per_line: int
    scan_size_m: float
    line_rate_hz: float
    trace_retrace: bool = True
    start_s: float = 0.0

    @classmethod
    def from_mapping(cls, value: Mapping) -> ScanMetadata:
        return cls(int(value["lines"]), int(value["pixels_per_line"]), float(value["scan_size_m"]),
                   float(value["line_rate_hz"]), bool(value.get("trace_retrace", True)),
                   float(value.get("start_s", 0.0)))


@dataclass(frozen=True)
class SweepSegmentMetadata:
    """One stepped-sine segment of ``segments``: from ``start_s`` to ``end_s`` (s) at ``frequency_hz``."""

    start_s: float
    end_s: float
    frequency_hz: float


@dataclass(frozen=True)
class CaptureMetadata:
    """A capture's metadata, parsed and validated once where the capture is opened.

    Every key the analyses read has a typed field.  An absent object whose
    keys are all optional is a record of Nones (``cantilever``, ``drive``,
    ``controller``, ``electrostatic``, ``ramp``); one with required keys is
    None (``force``, ``free_air``, ``nominal``, ``scan``).  ``raw`` is the metadata mapping itself, read-only, for
    free-form keys (``instrument``, ``parameters``, ...).
    """

    cantilever: CantileverMetadata = CantileverMetadata()
    drive: DriveMetadata = DriveMetadata()
    controller: ControllerMetadata = ControllerMetadata()
    electrostatic: ElectrostaticMetadata = ElectrostaticMetadata()
    ramp: RampMetadata = RampMetadata()
    vphi_step: StepMetadata = StepMetadata()
    force: ForceMetadata | None = None
    free_air: IntervalMetadata | None = None
    nominal: IntervalMetadata | None = None
    scan: ScanMetadata | None = None
    segments: tuple[SweepSegmentMetadata, ...] = ()
    scenario: str | None = None
    raw: Mapping = field(default_factory=lambda: MappingProxyType({}), repr=False, compare=False)

    @classmethod
    def from_mapping(cls, metadata: Mapping, source: str = "") -> CaptureMetadata:
        """Validate ``metadata`` (:func:`validate_metadata`) and type it.

        Raises
        ------
        InputError
            Naming ``source`` (the capture), the offending key and its value.
        """
        try:
            meta = validate_metadata(metadata)
        except InputError as exc:
            message = str(exc)
            raise InputError(message if not source or message.startswith(source) else f"{source}: {message}") from None

        def typed(name: str, record):
            return record.from_mapping(meta[name]) if name in meta else None

        return cls(
            cantilever=typed("cantilever", CantileverMetadata) or CantileverMetadata(),
            drive=typed("drive", DriveMetadata) or DriveMetadata(),
            controller=typed("controller", ControllerMetadata) or ControllerMetadata(),
            electrostatic=typed("electrostatic", ElectrostaticMetadata) or ElectrostaticMetadata(),
            ramp=typed("ramp", RampMetadata) or RampMetadata(),
            vphi_step=typed("vphi_step", StepMetadata) or StepMetadata(),
            force=typed("force", ForceMetadata),
            free_air=typed("free_air", IntervalMetadata),
            nominal=typed("nominal", IntervalMetadata),
            scan=typed("scan", ScanMetadata),
            segments=tuple(SweepSegmentMetadata(float(x["start_s"]), float(x["end_s"]), float(x["frequency_hz"]))
                           for x in meta.get("segments", ())),
            scenario=meta.get("scenario"),
            raw=MappingProxyType(meta),
        )
