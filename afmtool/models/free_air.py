"""The identified free-air model every observer and REEP runs beside the data.

Whatever route identified it (an off-sample ARX fit, a frequency sweep, a
thermal-noise spectrum), the result is one :class:`FreeAirModel`: the
continuous parameters f0, Q and gain with their uncertainties, and, when the
route was a discrete fit, the discrete numerator (a2, a1, a0) of eq. 3.40 at
the capture's sample rate.  It is saved as ``free_air.json`` and can be
passed back to any command with ``--model``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

from afmtool.errors import InputError
from afmtool.records.common import FreeAirModelRecord

__all__ = ["FreeAirModel", "load_free_air_model"]

_SPRING_FIELDS = ("spring_constant_n_per_m", "spring_constant_std_n_per_m", "spring_constant_source")


@dataclass(frozen=True)
class FreeAirModel:
    """Free-air cantilever model G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²).

    Parameters
    ----------
    f0_hz, q, gain : float
        Resonant frequency (Hz), quality factor, and DC gain (deflection
        units per dither unit, e.g. nm/V).
    f0_std_hz, q_std, gain_std : float or None
        One-standard-deviation uncertainties, where the route gives them.
    source : str
        ``"segment"``, ``"sweep"``, ``"thermal"`` or ``"given"``.
    sample_rate_hz : float or None
        The rate at which ``numerator``/``denominator`` were identified.
    numerator : tuple of 3 floats or None
        (a2, a1, a0) of eq. 3.40, from a discrete fit.
    denominator : tuple of 2 floats or None
        (b1, b0) of eq. 3.40, from a discrete fit.
    delay_s : float
        Pure delay of the drive path, s (sweep route).
    spring_constant_n_per_m, spring_constant_std_n_per_m : float or None
        The cantilever's spring constant k and its one-standard-deviation
        uncertainty, N/m, where the route measured it (the thermal route:
        equipartition, or Sader).  ``reep --model`` uses it for the
        interaction quantities unless ``--spring-constant`` is given.
    spring_constant_source : str or None
        How k was obtained, e.g. ``"thermal (equipartition, optical-lever factor 0.817)"``.
    """

    f0_hz: float
    q: float
    gain: float = 1.0
    f0_std_hz: float | None = None
    q_std: float | None = None
    gain_std: float | None = None
    source: str = "given"
    sample_rate_hz: float | None = None
    numerator: tuple[float, float, float] | None = None
    denominator: tuple[float, float] | None = None
    delay_s: float = 0.0
    spring_constant_n_per_m: float | None = None
    spring_constant_std_n_per_m: float | None = None
    spring_constant_source: str | None = None

    def numerator_at(
        self, sample_rate_hz: float, hold: str = "zoh", match_hz: float | None = None
    ) -> tuple[float, float, float]:
        """(a2, a1, a0) at ``sample_rate_hz``: the identified one, or gain times G sampled for ``hold``.

        ``hold`` is how the drive reached the cantilever
        (:mod:`afmtool.models.discretisation`): ``"zoh"`` (a DAC at the
        sample rate; the zero-order hold already carries the half-sample
        delay T/2 that a sweep fit finds on such data) or ``"continuous"``
        (the line-matched numerator, exact at ``match_hz``, default f0).
        ``delay_s`` is not applied: a longer drive-path delay would need a
        z^-d term, which is not modelled (REEP warns when the model's delay
        exceeds 1.5 samples); the f0/Q route
        (:mod:`afmtool.analyses.freeair_route`) fits it into the numerator.
        """
        if self.numerator is not None and self.sample_rate_hz == sample_rate_hz:
            return tuple(float(a) for a in self.numerator)
        from afmtool.models.discretisation import sampled_numerator

        numerator = sampled_numerator(self.f0_hz, self.q, sample_rate_hz, hold, match_hz=match_hz)
        return (self.gain * numerator.a2, self.gain * numerator.a1, self.gain * numerator.a0)

    def denominator_at(self, sample_rate_hz: float) -> tuple[float, float]:
        """(b1, b0) at ``sample_rate_hz``: the identified one, or the exact pole map of (f0, Q)."""
        if self.denominator is not None and self.sample_rate_hz == sample_rate_hz:
            return tuple(float(b) for b in self.denominator)
        from afmtool.models.discretisation import discrete_denominator

        denominator = discrete_denominator(self.f0_hz, self.q, sample_rate_hz)
        return (float(denominator.b1), float(denominator.b0))

    def to_dict(self) -> dict:
        """The fields as a JSON-ready dict; the spring-constant keys only where k is known."""
        data = dataclasses.asdict(self)
        if self.spring_constant_n_per_m is None:
            for name in _SPRING_FIELDS:
                data.pop(name)
        return data

    def record(self) -> FreeAirModelRecord:
        """The report's copy of the model (:class:`afmtool.records.common.FreeAirModelRecord`)."""
        return FreeAirModelRecord(**self.to_dict())

    @classmethod
    def from_record(cls, record: FreeAirModelRecord, where: str = "model") -> FreeAirModel:
        """The model of a report's :class:`~afmtool.records.common.FreeAirModelRecord` (checked as :meth:`from_dict`)."""
        return cls.from_dict({f.name: getattr(record, f.name) for f in dataclasses.fields(record)}, where)

    def save(self, path: Path) -> None:
        from afmtool.runtime.atomic import write_text_atomic

        write_text_atomic(Path(path), json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, data: dict, where: str = "model") -> FreeAirModel:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise InputError(f"{where}: unknown free-air model keys {sorted(unknown)}")
        try:
            model = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
        except TypeError as exc:
            raise InputError(f"{where}: not a free-air model ({exc})") from None
        for name in ("f0_hz", "q"):
            value = getattr(model, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{where}: {name}={value!r} must be a number > 0")
        k = model.spring_constant_n_per_m
        if k is not None and not (isinstance(k, (int, float)) and not isinstance(k, bool) and math.isfinite(k) and k > 0):
            raise InputError(f"{where}: spring_constant_n_per_m={k!r} must be a number > 0 (N/m)")
        return model


def load_free_air_model(path: Path) -> FreeAirModel:
    """Read ``free_air.json`` (or a ``report.json`` holding ``results.free_air_model``)."""
    path = Path(path)
    if path.is_dir():
        path = path / "free_air.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None
    if isinstance(data, dict) and "results" in data:
        data = data["results"].get("free_air_model", {})
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a free-air model")
    return FreeAirModel.from_dict(data, str(path))
