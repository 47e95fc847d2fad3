"""Custom piecewise-linear force parameters from the command line.

``d=3,wa2=1.5e9,wb2=4e10,ca=2000,cb=40000`` gives a
:class:`afmtool.models.forces.PiecewiseLinearForce` (eq. 4.1 in the
docs/conventions.md sign convention): d in nm, ω_a² and ω_b² in 1/s², c_a and c_b in
1/s, all per unit mass.  Omitted keys are 0; ``d`` is required.
"""

from __future__ import annotations

import math

from afmtool.errors import ConfigError
from afmtool.models.forces import PiecewiseLinearForce

__all__ = ["FORCE_KEYS", "format_force_spec", "parse_force_spec"]

#: Accepted keys -> PiecewiseLinearForce field, with units.
FORCE_KEYS = {"d": ("d_nm", "nm"), "wa2": ("omega_a2", "1/s^2"), "wb2": ("omega_b2", "1/s^2"),
              "ca": ("c_a", "1/s"), "cb": ("c_b", "1/s")}


def parse_force_spec(text: str, where: str = "--force") -> PiecewiseLinearForce:
    """``"d=…,wa2=…,wb2=…,ca=…,cb=…"`` -> PiecewiseLinearForce; a bad spec raises ConfigError."""
    values: dict[str, float] = {}
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        key, sep, raw = item.partition("=")
        key = key.strip().lower()
        if not sep or key not in FORCE_KEYS:
            raise ConfigError(f"{where} {text!r}: {item!r} is not one of {', '.join(k + '=' for k in FORCE_KEYS)}")
        if key in values:
            raise ConfigError(f"{where} {text!r}: {key} given twice")
        try:
            value = float(raw)
        except ValueError:
            raise ConfigError(f"{where} {text!r}: {key}={raw!r} is not a number") from None
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{where} {text!r}: {key}={raw!r} must be a finite number >= 0")
        values[key] = value
    if "d" not in values:
        raise ConfigError(f"{where} {text!r}: needs d= (the attractive range, nm)")
    return PiecewiseLinearForce(**{FORCE_KEYS[k][0]: values.get(k, 0.0) for k in FORCE_KEYS})


def format_force_spec(force: PiecewiseLinearForce) -> str:
    """The inverse of :func:`parse_force_spec`."""
    return ",".join(f"{k}={getattr(force, name):.9g}" for k, (name, _) in FORCE_KEYS.items())
