"""``electrostatic.json`` from ``afmtool identify electrostatic``, read back for ``decode --electrostatic``.

The file holds, per parameter of eq. 6.6 (optical) or 6.7 (thermal),
``{"value", "std", "relative_std", "status"}``; a status of ``"not
identifiable"`` comes with a null value.  From an approach curve alone k and
K_esf are identified only as their ratio ``k_esf_over_k_m3_per_v2`` (what
the electrostatic force per unit stiffness needs); either of them is known
only when the fit had ``--spring-constant``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

from afmtool.errors import InputError

__all__ = ["ElectrostaticFile", "read_electrostatic_file"]

_NAME = "electrostatic.json"
#: The largest electrostatic.json read (a fit's file is a few kB).
_MAX_BYTES = 1 << 20


class ElectrostaticFile(NamedTuple):
    """The identified values of an ``electrostatic.json`` (None where the fit could not identify them), SI.

    Attributes
    ----------
    path : str
    sensor : str
        ``"optical"`` or ``"thermal"``.
    k_esf_over_k_m3_per_v2 : float or None
    spring_constant_n_per_m, k_esf_f_m, alpha_r, l0_m, tip_height_m : float or None
    """

    path: str
    sensor: str
    k_esf_over_k_m3_per_v2: float | None
    spring_constant_n_per_m: float | None
    k_esf_f_m: float | None
    alpha_r: float | None
    l0_m: float | None
    tip_height_m: float | None


def _value(parameters: dict, name: str, path: Path) -> float | None:
    entry = parameters.get(name)
    if entry is None:
        return None
    if not isinstance(entry, dict):
        raise InputError(f"{path}: parameters.{name} must be an object with a value")
    value = entry.get("value")
    if value is None or entry.get("status") == "not identifiable":
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{path}: parameters.{name}.value must be a finite number, got {value!r}")
    return float(value)


def read_electrostatic_file(path: str | Path) -> ElectrostaticFile:
    """Read ``electrostatic.json`` (or the folder that holds it).

    Raises
    ------
    InputError
        If the file is missing, unreadable, not an identify-electrostatic
        result, or a value is not a finite number (α_R ≥ 0, the others > 0).
    """
    path = Path(path)
    if path.is_dir():
        path = path / _NAME
    try:
        if path.stat().st_size > _MAX_BYTES:
            raise InputError(f"{path}: larger than {_MAX_BYTES} bytes; not an electrostatic.json")
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (give the folder or electrostatic.json of 'identify electrostatic')") \
            from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read it as JSON ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("parameters"), dict):
        raise InputError(f"{path}: not an electrostatic.json of 'identify electrostatic' (no parameters object)")
    parameters = data["parameters"]
    values = {name: _value(parameters, name, path) for name in (
        "k_esf_over_k_m3_per_v2", "spring_constant_n_per_m", "k_esf_f_m", "alpha_r", "l0_m", "tip_height_m")}
    for name, value in values.items():
        if value is not None and not (value >= 0 if name in ("alpha_r", "tip_height_m") else value > 0):
            raise InputError(f"{path}: parameters.{name}.value = {value!r} is out of range")
    ratio = values["k_esf_over_k_m3_per_v2"]
    if ratio is None and values["k_esf_f_m"] and values["spring_constant_n_per_m"]:
        ratio = values["k_esf_f_m"] / values["spring_constant_n_per_m"]
    return ElectrostaticFile(str(path), str(data.get("sensor", "")), ratio, values["spring_constant_n_per_m"],
                             values["k_esf_f_m"], values["alpha_r"], values["l0_m"], values["tip_height_m"])
