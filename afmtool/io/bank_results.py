"""Reading ``bank.h5`` of ``afmtool kalman-bank`` back: each filter's innovation RMS against time.

Nothing is estimated here.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.io.result_files import MAX_PLOT_POINTS, open_result_file

__all__ = ["BankRms", "read_bank_rms"]


class BankRms(NamedTuple):
    """Thinned rows of bank.h5.

    ``t`` (s); ``rms`` (N, T): each filter's innovation RMS, deflection units;
    ``adaptive_rms`` (T,): the adaptive (REEP) observer's; ``z`` (T,) or None:
    z_piezo, input units.
    """

    t: np.ndarray
    rms: np.ndarray
    adaptive_rms: np.ndarray
    z: np.ndarray | None


def read_bank_rms(path: Path | str, max_points: int = MAX_PLOT_POINTS) -> BankRms:
    """Every ``step``-th row of ``bank.h5`` (or its folder), at most ``max_points`` rows (an HDF5 stride).

    Raises
    ------
    InputError
        If the file is missing, not HDF5, or lacks ``t``, ``rms``, ``adaptive_rms``.
    """
    path = Path(path)
    with open_result_file(path / "bank.h5" if path.is_dir() else path, required=("t", "rms", "adaptive_rms"),
                          what="kalman-bank output") as bank:
        n = len(bank["t"])
        step = max(1, math.ceil(n / max_points))
        return BankRms(bank["t"][::step], bank["rms"][:, ::step], bank["adaptive_rms"][::step],
                       bank["z"][::step] if "z" in bank else None)
