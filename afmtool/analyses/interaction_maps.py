"""Interaction quantities binned into REEP's force-curve tables and scan images (issue 17 item 1).

:func:`bin_interaction_series` reads the ``/interaction/<quantity>`` series
that :func:`afmtool.analyses.interaction_outputs.add_interaction_series`
wrote into a staged reep.h5 and feeds them, block by block, to the same
accumulators that bin f0′ and Q′ (:class:`ForceCurveAccumulator` against z,
:class:`ImageAccumulator` per pixel), with the same rules: samples whose
REEP fit is flagged (``flag`` != 0) are NaN, and force curves also leave out
the warm-up.  Binning the written per-sample series (rather than the binned
f0′, Q′, a) keeps each table entry the mean of the per-sample quantity,
which is what ``/interaction`` holds; the quantities are nonlinear in
f0′, Q′ and a, so the two differ.

Memory is set by the bins and pixels; the series are read in blocks.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.analyses.accumulators import (
    ForceCurveAccumulator,
    ForceCurveTable,
    ImageAccumulator,
    ScanGeometry,
)
from afmtool.io.result_files import open_result_file

__all__ = ["BinnedInteraction", "bin_interaction_series"]

_BLOCK = 1 << 20


class BinnedInteraction(NamedTuple):
    """Force-curve tables (``{"approach": ForceCurveTable, ...}``), images and units per quantity."""

    force_curves: dict[str, ForceCurveTable]
    images: dict[str, np.ndarray]
    units: dict[str, str]


def bin_interaction_series(
    path: Path,
    *,
    sample_rate_hz: float,
    warmup_samples: int,
    z_bin: float | None,
    geometry: ScanGeometry | None,
) -> BinnedInteraction | None:
    """Bin reep.h5's ``/interaction`` series against z and per pixel; None without them.

    Parameters
    ----------
    path : Path
        A reep.h5 with ``t``, ``flag``, ``/interaction/*`` and, for force
        curves, ``z``.
    sample_rate_hz : float
        Capture sample rate, Hz (``t`` × rate is the raw sample index).
    warmup_samples : int
        Raw samples left out of the force curves (as REEP leaves them out).
    z_bin : float or None
        Force-curve bin width in z units; None: no force curves.
    geometry : ScanGeometry or None
        Raster geometry; None: no images.
    """
    with open_result_file(path, required=("t",), what="reep output") as f:
        names = f.names("interaction")
        if not names:
            return None
        units = {name: f.units(f"interaction/{name}") for name in names}
        curves = ForceCurveAccumulator(z_bin, names) if (z_bin and "z" in f) else None
        images = ImageAccumulator(geometry, names) if geometry is not None else None
        if curves is None and images is None:
            return None
        n = f["t"].shape[0]
        for start in range(0, n, _BLOCK):
            stop = min(n, start + _BLOCK)
            t = f["t"][start:stop]
            trusted = f["flag"][start:stop] == 0
            values = {name: np.where(trusted, f[f"interaction/{name}"][start:stop], np.nan) for name in names}
            if images is not None:
                images.add(t, values)
            if curves is not None:
                settled = np.rint(t * sample_rate_hz) >= warmup_samples
                curves.add(f["z"][start:stop], {k: np.where(settled, v, np.nan) for k, v in values.items()})
    return BinnedInteraction(curves.tables() if curves is not None else {},
                             images.images() if images is not None else {}, units)
