"""Registers the chapter-6 scenarios: ``thermal-sweep``, ``iv-ramp`` and ``es-approach``.

Imported once from :mod:`afmtool.sim`, after the registry exists.
"""

from __future__ import annotations

from afmtool.sim import register_scenario
from afmtool.sim.es_approach import EsApproachParams, simulate_es_approach
from afmtool.sim.iv_ramp import IvRampParams, simulate_iv_ramp
from afmtool.sim.thermal_sweep import ThermalSweepParams, simulate_thermal_sweep

__all__: list[str] = []

register_scenario("thermal-sweep", ThermalSweepParams, simulate_thermal_sweep)
register_scenario("iv-ramp", IvRampParams, simulate_iv_ramp)
register_scenario("es-approach", EsApproachParams, simulate_es_approach)
