"""Closed-loop raster runs shared by test_raster.py and test_probeloss.py (simulated once per session)."""

from __future__ import annotations

from functools import lru_cache

from afmtool.analyses.controllers import TABLE_LINE_RATES_HZ as TABLE_RATES_HZ
from afmtool.sim.raster import CONTROLLERS, RasterParams, RasterRun, run_raster


@lru_cache(maxsize=1)
def table_runs() -> dict[float, dict[str, RasterRun]]:
    """The three controllers at 4, 8, 12 and 30 Hz on the grating, two lines each, seed 1."""
    return {
        rate: {c: run_raster(RasterParams(controller=c, line_rate_hz=rate, lines=2), seed=1) for c in CONTROLLERS}
        for rate in TABLE_RATES_HZ
    }
