"""The thermal sensor model that ``identify thermal`` learns, and its file ``thermal_sensor.json``.

g(T), K_TP from an I-V knee and K_TP(t_s) from a z force curve (thesis
§6.5.2); :mod:`afmtool.estimators.thermal_sensor` identifies them and
``identify electrostatic --sensor thermal`` uses them.  Units as in
:mod:`afmtool.models.thermal_sensor`: K/W, W, V, m.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

from afmtool.errors import InputError
from afmtool.models.thermal_sensor import ResistanceFit
from afmtool.records.thermal import KtpTableRecord, ThermalSensorRecord

__all__ = ["THERMAL_MODEL_FILE", "ThermalModel", "load_thermal_model"]

#: The file name of the model in an ``identify thermal`` output folder.
THERMAL_MODEL_FILE = "thermal_sensor.json"
_K_TP_DEFINITION = "DC gain of Gamma_TP, (T - T_r)/P, K/W"


class ThermalModel(NamedTuple):
    """What ``identify thermal`` learns, as saved in ``thermal_sensor.json``.

    g_fit : ResistanceFit or None
    breakdown_temperature_c : float
    k_tp_k_per_w : float or None
        From the I-V knee, at the ramp's separation.
    knee_power_w, knee_voltage_v : float or None
    k_tp_separation_m, k_tp_table_k_per_w : tuple of float or None
        K_TP(t_s) from a z force curve (t_s from the snap-in).
    contact_k_tp_k_per_w : float or None
    """

    g_fit: ResistanceFit | None
    breakdown_temperature_c: float
    k_tp_k_per_w: float | None = None
    knee_power_w: float | None = None
    knee_voltage_v: float | None = None
    k_tp_separation_m: tuple[float, ...] | None = None
    k_tp_table_k_per_w: tuple[float, ...] | None = None
    contact_k_tp_k_per_w: float | None = None

    def record(self) -> ThermalSensorRecord:
        """The model as a result record (``identify thermal``'s ``thermal_sensor``); its JSON is :meth:`to_dict`'s."""
        table = None
        if self.k_tp_separation_m is not None:
            table = KtpTableRecord(separation_m=self.k_tp_separation_m, k_tp_k_per_w=self.k_tp_table_k_per_w)
        return ThermalSensorRecord(
            g=None if self.g_fit is None else self.g_fit.record(),
            breakdown_temperature_c=self.breakdown_temperature_c,
            k_tp_k_per_w=self.k_tp_k_per_w,
            knee_power_w=self.knee_power_w,
            knee_voltage_v=self.knee_voltage_v,
            k_tp_table=table,
            contact_k_tp_k_per_w=self.contact_k_tp_k_per_w,
            k_tp_definition=_K_TP_DEFINITION,
        )

    def to_dict(self) -> dict:
        """``thermal_sensor.json``'s content (a non-finite number stays NaN here; :meth:`record` writes null)."""
        return {
            "g": None if self.g_fit is None else self.g_fit.to_dict(),
            "breakdown_temperature_c": self.breakdown_temperature_c,
            "k_tp_k_per_w": self.k_tp_k_per_w,
            "knee_power_w": self.knee_power_w,
            "knee_voltage_v": self.knee_voltage_v,
            "k_tp_table": None
            if self.k_tp_separation_m is None
            else {"separation_m": list(self.k_tp_separation_m), "k_tp_k_per_w": list(self.k_tp_table_k_per_w)},
            "contact_k_tp_k_per_w": self.contact_k_tp_k_per_w,
            "k_tp_definition": _K_TP_DEFINITION,
        }

    @classmethod
    def from_dict(cls, data) -> ThermalModel:
        try:
            table = data.get("k_tp_table")
            return cls(
                g_fit=None if data.get("g") is None else ResistanceFit.from_dict(data["g"]),
                breakdown_temperature_c=float(data["breakdown_temperature_c"]),
                k_tp_k_per_w=data.get("k_tp_k_per_w"),
                knee_power_w=data.get("knee_power_w"),
                knee_voltage_v=data.get("knee_voltage_v"),
                k_tp_separation_m=None if table is None else tuple(float(x) for x in table["separation_m"]),
                k_tp_table_k_per_w=None if table is None else tuple(float(x) for x in table["k_tp_k_per_w"]),
                contact_k_tp_k_per_w=data.get("contact_k_tp_k_per_w"),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"not a thermal sensor model: {exc}") from None


def load_thermal_model(path: Path) -> ThermalModel:
    """``thermal_sensor.json`` (or the ``identify thermal`` folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / THERMAL_MODEL_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such thermal sensor model") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read the thermal sensor model ({exc})") from None
    return ThermalModel.from_dict(data.get("thermal_sensor", data))
