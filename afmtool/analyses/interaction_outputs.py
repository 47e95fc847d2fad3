"""Interaction quantities per REEP output sample, added to reep.h5 (issue 17 item 1).

:func:`add_interaction_series` reads the finished ``f0_hz``, ``q`` and
``amplitude`` series of a staged reep.h5 in blocks and writes
``/interaction/<quantity>`` (each with its ``units`` attribute) by
:func:`afmtool.models.interaction.interaction_quantities`.  It needs the
spring constant (metadata ``cantilever.spring_constant_n_per_m``); without it
nothing is written and the report says why.  The amplitude must be a length:
the deflection units are converted to nm here.

The free-air reference f0, Q is REEP's own median over the settled part of
the free-air segment when the capture has one (a small REEP bias then cancels
from the tip-sample parts), else the free-air model's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmtool.io.metadata import CaptureMetadata
from afmtool.io.result_files import ResultFile, open_result_file
from afmtool.records.reep import FreeReference, Interaction, InteractionSeriesUnits, ReepResults

__all__ = ["add_interaction_series"]

_NM_PER_UNIT = {"pm": 1e-3, "nm": 1.0, "um": 1e3, "µm": 1e3, "μm": 1e3, "mm": 1e6, "m": 1e9}
_BLOCK = 1 << 20


def _free_reference(f: ResultFile, results: ReepResults) -> tuple[float, float, FreeReference]:
    segment = results.free_air_segment_s
    model = results.free_air_model
    if segment:
        t = f["t"][()]
        start, end = segment
        settled = (t >= start + 0.2 * (end - start)) & (t <= end)
        if settled.sum() >= 10:
            f0 = float(np.nanmedian(f["f0_hz"][()][settled]))
            q = float(np.nanmedian(f["q"][()][settled]))
            if np.isfinite(f0) and np.isfinite(q):
                return f0, q, FreeReference.SEGMENT
    if model is not None:
        return float(model.f0_hz), float(model.q), FreeReference.MODEL
    raise ValueError("no free-air reference")


def add_interaction_series(path: Path, results: ReepResults, metadata: CaptureMetadata, amplitude_units: str,
                           spring_constant_n_per_m: float = 0.0,
                           spring_constant_source: str = "--spring-constant") -> Interaction:
    """Write ``/interaction/...`` into the reep.h5 at ``path``; return the report section.

    ``spring_constant_n_per_m`` (``--spring-constant``, or the ``--model``'s
    k, named by ``spring_constant_source``) overrides the metadata's k; 0 uses it.
    """
    from afmtool.models.interaction import InteractionQuantities, interaction_quantities

    k = spring_constant_n_per_m or metadata.cantilever.spring_constant_n_per_m
    k_source = spring_constant_source if spring_constant_n_per_m else "capture metadata cantilever.spring_constant_n_per_m"
    if not k:
        return Interaction(written=False, reason="no spring constant (--spring-constant or metadata "
                                                 "cantilever.spring_constant_n_per_m): k_e, the force gradient, "
                                                 "damping, Phi_c, Phi_d, energy and virial need it")
    scale = _NM_PER_UNIT.get(str(amplitude_units).strip())
    if scale is None:
        return Interaction(written=False,
                           reason=f"the amplitude is in {amplitude_units!r}, not a length (no InvOLS applied)")
    with open_result_file(path, mode="r+", required=("t", "f0_hz", "q", "amplitude"), what="reep output") as f:
        try:
            free_f0, free_q, source = _free_reference(f, results)
        except ValueError:
            return Interaction(written=False, reason="no free-air reference f0, Q")
        n = f["t"].shape[0]
        units = InteractionQuantities.units()
        datasets = f.create_columns("interaction", units, n)
        for start in range(0, n, _BLOCK):
            stop = min(n, start + _BLOCK)
            out = interaction_quantities(
                f["f0_hz"][start:stop], f["q"][start:stop], f["amplitude"][start:stop] * scale,
                free_f0_hz=free_f0, free_q=free_q, spring_constant_n_per_m=float(k),
                drive_frequency_hz=float(results.drive_frequency_hz),
            )
            for name, ds in datasets.items():
                ds[start:stop] = getattr(out, name)
    return Interaction(written=True, spring_constant_n_per_m=float(k), spring_constant_source=k_source,
                       free_f0_hz=free_f0, free_q=free_q, free_reference=source,
                       series=InteractionSeriesUnits(**units))
