"""Reading ``gamma.h5`` of ``afmtool identify gamma`` back: Γ_IR,ts and the sweep's mean thermal current.

Nothing is estimated here.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError
from afmtool.estimators.frequency_response import FrequencyResponse
from afmtool.io.result_files import open_result_file

__all__ = ["GammaFile", "read_gamma_ir_ts"]


class GammaFile(NamedTuple):
    """Γ_IR,ts (µA/nm) from ``gamma.h5`` and the mean thermal current of its sweep (µA; NaN if not stored)."""

    ir_ts: FrequencyResponse
    thermal_current_mean_ua: float


def read_gamma_ir_ts(path: Path | str) -> GammaFile:
    """Γ_IR,ts from the ``gamma.h5`` of ``identify gamma`` (or its folder).

    Raises
    ------
    InputError
        If the file is missing, not HDF5, or lacks ``frf/frequency_hz``,
        ``frf/ir_ts``, ``frf/coherence_ir_ts`` or ``frf/magnitude_std_ir_ts``.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "gamma.h5"
    if not path.exists():
        raise InputError(f"{path}: no such gamma.h5")
    required = ("frf/frequency_hz", "frf/ir_ts", "frf/coherence_ir_ts", "frf/magnitude_std_ir_ts")
    with open_result_file(path, required=required, what="gamma.h5 from 'identify gamma'") as gamma:
        h = np.asarray(gamma["frf/ir_ts"][()], dtype=np.complex128)
        std = np.asarray(gamma["frf/magnitude_std_ir_ts"][()], dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            response = FrequencyResponse(
                frequency_hz=np.asarray(gamma["frf/frequency_hz"][()], dtype=np.float64),
                response=h,
                coherence=np.asarray(gamma["frf/coherence_ir_ts"][()], dtype=np.float64),
                magnitude_std=std,
                phase_std_rad=std / np.abs(h),
                method="h1",
            )
        return GammaFile(response, float(gamma.attrs.get("thermal_current_mean_ua", np.nan)))
