"""``theory averaging --q 50,100,200,400``: force curves for several off-sample Q in one figure.

The thesis's Figs. 4.2-4.5 follow one force and one free amplitude for a
range of off-sample quality factors: f0,e and its topography sensitivity
∂ωe/∂l (eq. 4.17), Qe and ∂δe/∂l (eq. 4.20), the amplitude and ∂a/∂l
(eq. 4.22), and the phase.  Each Q gets its own drive, set so that the free
amplitude is the same (the experiment would re-tune the drive per lever).
Approach legs only, as in the thesis figures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from afmtool.errors import ConfigError
from afmtool.records.theory_averaging import QOverlayRecord

__all__ = ["parse_q_values", "write_q_overlay"]


def parse_q_values(text: str) -> list[float]:
    """``"50,100,200"`` -> [50.0, 100.0, 200.0]; empty -> []."""
    values = []
    for item in str(text or "").split(","):
        if not item.strip():
            continue
        try:
            q = float(item)
        except ValueError:
            raise ConfigError(f"q_values {text!r}: {item.strip()!r} is not a number") from None
        if not (math.isfinite(q) and q > 0.5):
            raise ConfigError(f"q_values {text!r}: Q={item.strip()} must be a finite number > 0.5")
        values.append(q)
    if len(set(values)) != len(values):
        raise ConfigError(f"q_values {text!r}: a Q is repeated")
    return values


def write_q_overlay(staged, q_values: Sequence[float], params, force, force_name: str,
                    approach_path) -> dict[str, QOverlayRecord]:
    """Approach curves for each Q into ``theory_q.h5`` and ``averaging_q.png``/``averaging_q_sensitivity.png``."""
    from afmtool.io.results import ResultWriter
    from afmtool.models.averaging import (
        SinusoidalDrive,
        theoretical_force_curve,
        topography_sensitivities,
    )
    from afmtool.models.cantilever import Cantilever
    from afmtool.report.images import write_multi_panel_png

    curves, summary = {}, {}
    with ResultWriter(staged.path("theory_q.h5"), {}) as writer:
        for q in q_values:
            cantilever = Cantilever(params.f0_hz, q)
            drive = SinusoidalDrive.for_free_amplitude(cantilever, params.free_amplitude_nm,
                                                       params.f0_hz + params.drive_offset_hz)
            curve = theoretical_force_curve(approach_path, drive, cantilever, force)
            sens = topography_sensitivities(curve.amplitude_nm, curve.separation_nm, drive.omega_rad_s,
                                            cantilever, force)
            curves[q] = (curve, sens)
            group = f"q{q:g}/approach"
            for name, values, units in (
                ("separation_nm", curve.separation_nm, "nm"), ("amplitude_nm", curve.amplitude_nm, "nm"),
                ("phase_deg", np.degrees(curve.phase_rad), "deg"), ("f0_e_hz", curve.f0_e_hz, "Hz"),
                ("q_e", curve.q_e, ""), ("da_dl", sens.da_dl, "nm/nm"),
                ("domega_e_dl", sens.domega_e_dl, "rad/s/nm"), ("dq_e_dl", sens.dq_e_dl, "1/nm"),
            ):
                writer.put(f"{group}/{name}", values, units)
            summary[f"{q:g}"] = QOverlayRecord(
                drive_amplitude_nm=drive.amplitude_nm,
                f0_e_change_hz=float(np.nanmax(curve.f0_e_hz) - np.nanmin(curve.f0_e_hz)),
                q_e_range=(float(np.nanmin(curve.q_e)), float(np.nanmax(curve.q_e))),
            )

    def panels(rows):
        return [
            {"y_label": label, "series": [(c.separation_nm, get(c, s), f"Q {q:g}", {"color": f"C{i % 10}"})
                                          for i, (q, (c, s)) in enumerate(curves.items())]}
            for label, get in rows
        ]

    title = f"Averaging theory, {force_name} force, free amplitude {params.free_amplitude_nm:g} nm, several Q"
    write_multi_panel_png(staged.path("averaging_q.png"), panels((
        ("f0e (Hz)", lambda c, s: c.f0_e_hz), ("Qe (dimensionless)", lambda c, s: c.q_e),
        ("amplitude (nm)", lambda c, s: c.amplitude_nm), ("phase (deg)", lambda c, s: np.degrees(c.phase_rad)),
    )), x_label="separation l (nm)", title=title + " (Figs. 4.2a-4.5)")
    write_multi_panel_png(staged.path("averaging_q_sensitivity.png"), panels((
        ("dωe/dl (rad/s/nm)", lambda c, s: s.domega_e_dl), ("dQe/dl (1/nm)", lambda c, s: s.dq_e_dl),
        ("da/dl (nm/nm)", lambda c, s: s.da_dl),
    )), x_label="separation l (nm)", title=title + " (Figs. 4.2b-4.4b)")
    return summary
