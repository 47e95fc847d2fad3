"""``afmtool theory fit``: the piecewise-linear force fitted to a measured force curve (ch. 4, ref. [38]).

Averaging theory (closed form of eq. 4.8, :func:`afmtool.models.averaging.equivalent_parameters_closed_form`)
predicts, at amplitude a and rest separation l,

.. math::

    \\omega_e^2 = \\omega_0^2 - \\frac{\\omega_a^2}{\\pi}\\gamma(x) + \\frac{\\omega_b^2}{\\pi}\\gamma(y),\\qquad
    \\frac{\\omega_e}{Q_e} = \\frac{\\omega_0}{Q} + \\frac{c_a}{\\pi}\\gamma(x) + \\frac{c_b}{\\pi}\\gamma(y),

x = (d − l)/a, y = −l/a, and the amplitude from the first-harmonic balance
a = a_free·√D(ω0, Q)/√D(ωe, Qe), D = (ωe² − ω²)² + ω²(ωe/Qe)² (the drive
that gave the free amplitude a_free at ω).  Along REEP's approach, with
l = s·(z − z_c), the fit finds θ = (d, ω_a², ω_b², c_a, c_b, z_c) that make
REEP's f0′, Q′ and amplitude agree with it, by
``scipy.optimize.least_squares`` (trust-region reflective, θ ≥ 0 except
z_c).  The theory's f0,e and Qe are passed through REEP's own exponential
window, as ``theory compare`` does, so both describe the same data.
Residuals are divided by each series' noise (its scatter on the free-air
start of the approach).

Start: the interaction onset z_on (where the amplitude first falls by
``onset_drop``) fixes z_c = z_on − (a_free + d)/s for a trial d; for fixed
(d, z_c) the model of ωe², ωe/Qe is linear in (ω_a², ω_b², c_a, c_b), solved
by non-negative least squares; the best trial d starts the full fit.

Uncertainties: first-order covariance σ̂²(JᵀJ)⁻¹ of the noise-scaled
residuals, inflated by REEP's window length in output samples (neighbouring
REEP outputs are not independent).  Identifiability is the SVD of the
relative Jacobian (:mod:`afmtool.estimators.identifiability`): a parameter
whose relative standard deviation exceeds ``max_relative_std``, or which lies
in a structural null direction, or sits at its bound 0 with no effect on the
curve, is reported as not determined by this curve, with the reason.

The first-order standard deviation only measures the noise.  Where averaging
theory and REEP differ systematically (a stiff repulsive wall that the tip
barely enters, where a fraction of a nanometre of contact point is worth a
factor in ω_b²), a parameter can have a small standard deviation and still be
wrong by tens of per cent.  So each parameter that passes is also profiled:
it is moved by ±``PROFILE_STEP`` and the others are fitted again; if the
best cost rises by less than a factor ``PROFILE_MIN_RISE`` (geometric mean
of the two sides), the others absorb the change, and the parameter is
reported as poorly identifiable.  On the reference curves of
``tests/test_theory_fit.py`` the rise is 1.3 to 8 for parameters within 4 %
of the truth and 1.04 to 1.21 for those 27 % to 91 % off.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce

__all__ = ["FIT_NAMES", "FIT_UNITS", "ForceFit", "ForceFitData", "fit_force", "run_theory_fit_command"]

FIT_NAMES = ("d_nm", "omega_a2", "omega_b2", "c_a", "c_b", "contact_z")
FIT_UNITS = {"d_nm": "nm", "omega_a2": "1/s^2", "omega_b2": "1/s^2", "c_a": "1/s", "c_b": "1/s",
             "contact_z": "z units"}
#: Trial attractive ranges for the start, nm.
_TRIAL_D_NM = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0)
#: Profile check (module docstring): the relative step, and the least rise of the best cost it must cause.
PROFILE_STEP = 0.3
PROFILE_MIN_RISE = 1.25
#: Scales below which a parameter counts as 0 for least_squares' x_scale.
_PARAMETER_SCALES = (0.1, 1e8, 1e9, 1e2, 1e3, 0.1)
_LOWER = (0.0, 0.0, 0.0, 0.0, 0.0, -math.inf)


@dataclass(frozen=True)
class ForceFitData:
    """One approach: REEP's series per output sample (nm, Hz, –), the model around it."""

    z: np.ndarray
    f0_hz: np.ndarray
    q: np.ndarray
    amplitude_nm: np.ndarray
    fit_mask: np.ndarray
    nm_per_unit: float
    drive_frequency_hz: float
    cantilever: Cantilever
    free_amplitude_nm: float
    window_lambda: float
    sigma: tuple[float, float, float]


@dataclass(frozen=True)
class ForceFit:
    """The fitted force, its uncertainties and what the curve determines."""

    theta: np.ndarray
    std: np.ndarray
    status: tuple[str, ...]
    reasons: tuple[str, ...]
    cost: float
    rms: tuple[float, float, float]
    null_directions: tuple
    singular_values: np.ndarray
    prediction: tuple[np.ndarray, np.ndarray, np.ndarray]
    repulsive_share: float
    onset_nm: tuple[float, float]

    @property
    def force(self) -> PiecewiseLinearForce:
        return PiecewiseLinearForce(*(max(0.0, float(v)) for v in self.theta[:5]))


def _model(theta: np.ndarray, data: ForceFitData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f0e windowed, Qe windowed, amplitude) along the approach for θ."""
    from scipy.signal import lfilter

    d, wa2, wb2, ca, cb, z_c = theta
    a = np.maximum(data.amplitude_nm, 1e-6)
    l = data.nm_per_unit * (data.z - z_c)
    gx = _gamma((d - l) / a)
    gy = _gamma(-l / a)
    w0 = data.cantilever.omega0_rad_s
    w = w0 * w0 - (wa2 / math.pi) * gx + (wb2 / math.pi) * gy
    b = w0 / data.cantilever.q + (ca / math.pi) * gx + (cb / math.pi) * gy
    omega_e = np.sqrt(np.maximum(w, 1.0))
    f0e, qe = omega_e / (2 * math.pi), omega_e / np.maximum(b, 1e-9)
    om2 = (2 * math.pi * data.drive_frequency_hz) ** 2
    d0 = (w0 * w0 - om2) ** 2 + om2 * (w0 / data.cantilever.q) ** 2
    amplitude = data.free_amplitude_nm * np.sqrt(d0 / ((w - om2) ** 2 + om2 * b * b))
    lam = data.window_lambda
    window = ([1.0 - lam], [1.0, -lam])
    f0e = lfilter(*window, f0e, zi=[lam * f0e[0]])[0]
    qe = lfilter(*window, qe, zi=[lam * qe[0]])[0]
    return f0e, qe, amplitude


def _gamma(u: np.ndarray) -> np.ndarray:
    """γ(u) = π − arccos u + u√(1 − u²), u clipped to [−1, 1] (closed form of eq. 4.8)."""
    u = np.clip(u, -1.0, 1.0)
    return math.pi - np.arccos(u) + u * np.sqrt(1.0 - u * u)


def _residual(theta: np.ndarray, data: ForceFitData) -> np.ndarray:
    f0e, qe, amplitude = _model(theta, data)
    m = data.fit_mask
    sf, sq, sa = data.sigma
    return np.concatenate([(f0e[m] - data.f0_hz[m]) / sf, (qe[m] - data.q[m]) / sq,
                           (amplitude[m] - data.amplitude_nm[m]) / sa])


def _linear_start(d: float, z_c: float, data: ForceFitData) -> np.ndarray:
    """(ω_a², ω_b², c_a, c_b) ≥ 0 by NNLS of the unwindowed ωe², ωe/Qe for fixed (d, z_c)."""
    from scipy.optimize import nnls

    m = data.fit_mask
    a = np.maximum(data.amplitude_nm[m], 1e-6)
    l = data.nm_per_unit * (data.z[m] - z_c)
    gx, gy = _gamma((d - l) / a) / math.pi, _gamma(-l / a) / math.pi
    w0 = data.cantilever.omega0_rad_s
    w_meas = (2 * math.pi * data.f0_hz[m]) ** 2 - w0 * w0
    b_meas = 2 * math.pi * data.f0_hz[m] / data.q[m] - w0 / data.cantilever.q
    sw, sb = max(np.std(w_meas), 1.0), max(np.std(b_meas), 1e-6)
    zeros = np.zeros_like(gx)
    matrix = np.vstack([np.column_stack([-gx, gy, zeros, zeros]) / sw, np.column_stack([zeros, zeros, gx, gy]) / sb])
    solution, _ = nnls(matrix, np.concatenate([w_meas / sw, b_meas / sb]))
    return solution


def _onset_z(data: ForceFitData, drop: float) -> float:
    """First approach z where the amplitude falls below (1 − drop)·a_free."""
    below = np.flatnonzero(data.amplitude_nm < (1.0 - drop) * data.free_amplitude_nm)
    if below.size == 0:
        raise InputError("the approach amplitude never drops: the curve does not reach the interaction")
    return float(data.z[below[0]])


def _best_of_starts(data: ForceFitData, z_on: float, n_starts: int):
    """(least-squares solution, parameter scale) of the lowest cost over the ``n_starts`` best trial starts.

    Each trial d (``_TRIAL_D_NM``) places z_c so that the onset z_on is
    where the tip reaches d; (ω_a², ω_b², c_a, c_b) start at their NNLS
    values for that (d, z_c) (:func:`_linear_start`).
    """
    from scipy.optimize import least_squares

    starts = []
    for d in _TRIAL_D_NM:
        z_c = z_on - (data.free_amplitude_nm + d) / data.nm_per_unit
        theta0 = np.concatenate([[d], _linear_start(d, z_c, data), [z_c]])
        starts.append((float(np.sum(_residual(theta0, data) ** 2)), theta0))
    lower = np.array(_LOWER)
    best = None
    # the curve can have several local minima (a short d with a stiff wall mimics a long soft one):
    # every trial start is run to convergence and the lowest cost wins
    for _, theta0 in sorted(starts, key=lambda item: item[0])[:n_starts]:
        scale = np.maximum(np.abs(theta0), _PARAMETER_SCALES)
        theta0 = np.maximum(theta0, lower + 1e-9 * scale)
        solution = least_squares(_residual, theta0, args=(data,), bounds=(lower, np.full(6, np.inf)),
                                 x_scale=scale, method="trf", max_nfev=400)
        if best is None or solution.cost < best[0].cost:
            best = (solution, scale)
    return best


def _profile_rise(theta: np.ndarray, j: int, data: ForceFitData, best_cost: float) -> float:
    """Geometric mean over ±PROFILE_STEP of (best cost with θ_j moved, the others refitted) / best cost."""
    from scipy.optimize import least_squares

    free = [k for k in range(len(theta)) if k != j]
    lower = np.array(_LOWER)[free]
    scale = np.maximum(np.abs(theta[free]), np.array(_PARAMETER_SCALES)[free])
    rises = []
    for factor in (1.0 - PROFILE_STEP, 1.0 + PROFILE_STEP):
        moved = theta.copy()
        moved[j] = theta[j] * factor

        def residual(x, moved=moved):
            moved[free] = x
            return _residual(moved, data)

        start = np.maximum(theta[free], lower + 1e-9 * scale)
        solution = least_squares(residual, start, bounds=(lower, np.inf), x_scale=scale, method="trf", max_nfev=400)
        rises.append(float(solution.cost) / max(best_cost, 1e-300))
    return math.sqrt(rises[0] * rises[1])


def fit_force(data: ForceFitData, *, max_relative_std: float = 0.1, onset_drop: float = 0.02,
              rank_tolerance: float = 1e-7, n_starts: int = len(_TRIAL_D_NM)) -> ForceFit:
    """Fit θ = (d, ω_a², ω_b², c_a, c_b, z_c) (module docstring)."""
    from afmtool.estimators.identifiability import analyse_identifiability

    solution, scale = _best_of_starts(data, _onset_z(data, onset_drop), n_starts)
    theta, residual = solution.x, solution.fun
    jac = solution.jac * scale  # ∂r per unit of each parameter's scale
    n, p = jac.shape
    window = 1.0 / (1.0 - data.window_lambda)
    sigma2 = float(residual @ residual) / max(1, n - p) * window
    ident = analyse_identifiability(jac, FIT_NAMES, rank_tolerance=rank_tolerance)
    _, s, vt = np.linalg.svd(jac, full_matrices=False)
    s_safe = np.where(s > rank_tolerance * s[0], s, np.inf)
    cov = sigma2 * (vt.T / s_safe**2) @ vt
    std = np.sqrt(np.diag(cov)) * scale
    in_null = {name for nd in ident.null_directions for name in nd.parameters}
    m = data.fit_mask
    reach = float(np.mean(data.nm_per_unit * (data.z[m] - theta[5]) < data.amplitude_nm[m]))
    status, reasons = [], []
    for j, name in enumerate(FIT_NAMES):
        value = theta[j]
        column = float(np.linalg.norm(jac[:, j]))
        relative = std[j] / abs(value) if value else math.inf
        if name in in_null:
            status.append("not identifiable"), reasons.append("in a structural null direction of the Jacobian")
        elif name != "contact_z" and value <= 1e-6 * scale[j] and column < 1e-3 * s[0]:
            status.append("not identifiable"), reasons.append("at its bound 0 and without effect on this curve")
        elif name == "contact_z":
            ok = std[j] * abs(data.nm_per_unit) <= 0.1 * data.free_amplitude_nm
            status.append("identified" if ok else "poorly identifiable")
            reasons.append(f"std {std[j] * abs(data.nm_per_unit):.3g} nm")
        elif relative <= max_relative_std:
            rise = _profile_rise(theta, j, data, float(solution.cost))
            if rise < PROFILE_MIN_RISE:
                status.append("poorly identifiable")
                reasons.append(f"relative std {relative:.3g}, but moved by +-{PROFILE_STEP:.0%} the others absorb it "
                               f"(best cost x{rise:.3g} < {PROFILE_MIN_RISE:g})")
            else:
                status.append("identified"), reasons.append(f"relative std {relative:.3g}")
        else:
            status.append("not identifiable"), reasons.append(f"relative std {relative:.3g} > {max_relative_std:g}")
    # Outside the repulsive zone the model sees d and l only as d − l = d − s(z − z_c): d and z_c
    # trade off exactly.  They separate only through the repulsive terms (y = −l/a), so unless
    # ω_b² or c_b is identified, only the onset d + s·z_c is determined.
    if not any(status[FIT_NAMES.index(n)] == "identified" for n in ("omega_b2", "c_b")):
        for name in ("d_nm", "contact_z"):
            j = FIT_NAMES.index(name)
            status[j] = "not identifiable"
            reasons[j] = ("neither omega_b2 nor c_b is identified, so d and the contact point enter only as the "
                          "onset d + s*contact_z (reported)")
    rms_blocks = np.split(residual, 3)
    rms = tuple(float(np.sqrt(np.mean(r**2)) * sig) for r, sig in zip(rms_blocks, data.sigma))
    onset = float(theta[0] + data.nm_per_unit * theta[5])
    onset_std = float(math.sqrt(max(0.0, cov[0, 0] * scale[0] ** 2 + data.nm_per_unit**2 * cov[5, 5] * scale[5] ** 2
                                    + 2 * data.nm_per_unit * cov[0, 5] * scale[0] * scale[5])))
    return ForceFit(theta, std, tuple(status), tuple(reasons), float(solution.cost), rms,
                    ident.null_directions, s, _model(theta, data), float(reach), (onset, onset_std))


# --------------------------------------------------------------------------- command


def _load(reep_dir: Path, params) -> ForceFitData:
    from afmtool.analyses.theory import jump_neighbourhood
    from afmtool.analyses.theory_outputs import (
        capture_cantilever,
        capture_side,
        open_reep_run,
        reep_capture_path,
        reep_series,
    )
    from afmtool.analyses.theory_separation import z_sensitivity_nm

    with open_reep_run(reep_dir) as reep:
        if "z" not in reep.series:
            raise InputError(f"{reep.path}: no z series (the capture had no z_piezo): not a force curve")
        series = reep_series(reep, ("t", "f0_hz", "q", "amplitude", "z"))
        # samples REEP flagged as invalid (reep.h5 'flag' != 0) are not fitted
        flag = reep.series.get("flag")
        series["trusted"] = flag[()] == 0 if flag is not None else np.ones(len(series["t"]), dtype=bool)
        units, reep_results, capture = reep.z_units, reep.report, reep_capture_path(reep)
        series["trusted"] &= _linear_model_holds(reep, reep_results)
    metadata, _, _ = capture_side(capture, reep_results)
    nm_per_unit = z_sensitivity_nm(units, params.z_sensitivity)
    cantilever = capture_cantilever(metadata, reep_results)
    t = series["t"]
    turn = int(np.argmin(series["z"] * np.sign(nm_per_unit)))
    approach = slice(0, turn + 1)
    s = {k: v[approach] for k, v in series.items()}
    start = max(2, len(s["t"]) // 20)
    early = slice(max(1, start // 4), start)  # free air, after REEP has converged
    free_amplitude = metadata.drive.free_amplitude_nm or float(np.nanmedian(s["amplitude"][early]))
    # each series' scatter in free air, but not below what the model itself is good for: REEP's
    # off-sample accuracy (2 Hz, 2 % of Q) and 1 % of the free amplitude for the averaged amplitude
    # (the three-sine beat and the lock-in are outside averaging theory)
    floors = {"f0_hz": 2.0, "q": 0.02 * cantilever.q, "amplitude": 0.01 * free_amplitude}
    sigma = tuple(max(float(np.nanstd(s[k][early])), floors[k]) for k in ("f0_hz", "q", "amplitude"))
    decimate = reep_results["decimate"]
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    finite = np.isfinite(s["f0_hz"]) & np.isfinite(s["q"]) & np.isfinite(s["amplitude"])
    mask = finite & s["trusted"] & (s["t"] > params.skip_s) & (s["amplitude"] > params.amplitude_fraction * free_amplitude)
    mask &= ~jump_neighbourhood(np.nan_to_num(s["amplitude"]), 1.0 / dt)
    stride = max(1, math.ceil(mask.sum() / params.max_samples))
    thinned = np.zeros_like(mask)
    thinned[np.flatnonzero(mask)[::stride]] = True
    for k in ("f0_hz", "q", "amplitude"):
        s[k] = np.nan_to_num(s[k], nan=float(np.nanmedian(s[k])))
    return ForceFitData(s["z"], s["f0_hz"], s["q"], s["amplitude"], thinned, nm_per_unit,
                        reep_results["drive_frequency_hz"], cantilever, free_amplitude,
                        reep_results["forgetting_factor"] ** decimate, sigma)


#: The fit leaves out rows whose σ̂² exceeds this multiple of its free-air level.
_MAX_SIGMA2_RATIO = 4.0


def _linear_model_holds(reep, reep_results) -> np.ndarray | bool:
    """Rows whose σ̂² is within ``_MAX_SIGMA2_RATIO`` of its free-air level (True where it is unknown).

    REEP's flags mark only invalid rows; a σ̂² far above the free-air level
    (impacts on a stiff wall, where the linear model does not describe the
    window) is a valid row for REEP but not one averaging theory can be
    fitted to: the fit leaves those out, as REEP's flags did before issue 27.
    """
    level = ((reep_results.get("validity") or {}).get("free_air_levels") or {}).get("sigma2")
    sigma2 = reep.series.get("sigma2")
    if not level or sigma2 is None:
        return True
    values = sigma2[()]
    return ~(values > _MAX_SIGMA2_RATIO * level)


def _record(fit: ForceFit, data: ForceFitData) -> dict:
    params = {}
    for j, name in enumerate(FIT_NAMES):
        params[name] = {"value": float(fit.theta[j]), "std": float(fit.std[j]), "units": FIT_UNITS[name],
                        "status": fit.status[j], "reason": fit.reasons[j]}
    return {
        "parameters": params,
        "separation_offset_nm": float(-data.nm_per_unit * fit.theta[5]),
        "onset_d_plus_s_contact_z_nm": {"value": fit.onset_nm[0], "std": fit.onset_nm[1]},
        "repulsive_share": fit.repulsive_share,
        "nm_per_unit": data.nm_per_unit,
        "identified": [n for n, st in zip(FIT_NAMES, fit.status) if st == "identified"],
        "not_identified": [n for n, st in zip(FIT_NAMES, fit.status) if st != "identified"],
        "null_directions": [nd._asdict() for nd in fit.null_directions],
        "singular_values": [float(v) for v in fit.singular_values],
        "rms_residual": {"f0_hz": fit.rms[0], "q": fit.rms[1], "amplitude_nm": fit.rms[2]},
        "noise": {"f0_hz": data.sigma[0], "q": data.sigma[1], "amplitude_nm": data.sigma[2]},
        "fitted_samples": int(data.fit_mask.sum()),
        "free_amplitude_nm": data.free_amplitude_nm,
    }


def run_theory_fit_command(reep_dir: Path, out: Path, config: Path | None, flags: Mapping) -> dict:
    """Fit the force to REEP's approach and write fit.json, fit.h5 and fit.png."""
    from afmtool.config import load_toml, resolve_from
    from afmtool.config.params import TheoryFitParams
    from afmtool.io.results import ResultWriter
    from afmtool.report.images import write_multi_panel_png
    from afmtool.report.json_report import input_record
    from afmtool.report.run import finish_run
    from afmtool.runtime.outputs import OutputDir

    params = resolve_from(TheoryFitParams, "theory.fit", load_toml(config) if config else None, flags)
    data = _load(Path(reep_dir), params)
    fit = fit_force(data, max_relative_std=params.max_relative_std)
    results = _record(fit, data)
    warnings = [f"{name} is not determined by this curve: {reason}" for name, st, reason in
                zip(FIT_NAMES, fit.status, fit.reasons) if st != "identified"]
    separation = data.nm_per_unit * (data.z - fit.theta[5])
    f0e, qe, amplitude = fit.prediction
    m = data.fit_mask
    with OutputDir(out) as staged:
        staged.path("fit.json").write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
        with ResultWriter(staged.path("fit.h5"), {}) as writer:
            for name, values, units in (("separation_nm", separation, "nm"), ("f0_hz", data.f0_hz, "Hz"),
                                        ("q", data.q, ""), ("amplitude_nm", data.amplitude_nm, "nm"),
                                        ("f0_e_fit_hz", f0e, "Hz"), ("q_e_fit", qe, ""),
                                        ("amplitude_fit_nm", amplitude, "nm"), ("fitted", m.astype(np.uint8), "")):
                writer.put(f"approach/{name}", values, units)
        dots = {"linestyle": "none", "marker": ".", "markersize": 2, "color": "C0"}
        line = {"color": "C3"}
        panels = [
            {"y_label": label, "series": [(separation[m], measured[m], "REEP (fitted samples)", dots),
                                          (separation, model, "averaging theory, fitted force", line)]}
            for label, measured, model in (("f0' (Hz)", data.f0_hz, f0e), ("Q' (dimensionless)", data.q, qe),
                                           ("amplitude (nm)", data.amplitude_nm, amplitude))
        ]
        write_multi_panel_png(staged.path("fit.png"), panels, x_label="separation l from the fitted contact point (nm)",
                              title="Force parameters fitted to the approach (averaging theory, eq. 4.8)")
        inputs = [input_record(Path(reep_dir) / "report.json", "reep report"),
                  input_record(Path(reep_dir) / "reep.h5", "reep series")]
        return finish_run(staged, "theory fit", inputs, "theory.fit", params, results, warnings)
