"""``afmtool theory``: averaging theory (ch. 4) and its comparison with REEP (§3.4.3).

Averaging theory gives the equivalent ωe and Qe of a cantilever tapping on a
piecewise-linear force (eqs. 4.6-4.8, closed forms in
:mod:`afmtool.models.averaging`).  REEP estimates the same two numbers from
the signals alone, so along a force curve, where the separation is known,
the two can be compared.

The comparison (:func:`compare_binned`)
---------------------------------------
Per REEP row the theory is evaluated at the row's lock-in amplitude a and
separation l and passed through REEP's own exponential window
(1 − λ)/(1 − λz⁻¹), so both describe the same stretch of data.  Rows are then
binned by separation (approach and retract apart), and in each bin the
*shifts* from free air are compared (eq. C.1):

.. math::

    z_f = \\frac{(\\tilde f_0' - f'_{0,\\mathrm{free}}) - (\\tilde f_{0,e} - f_0)}
               {\\sqrt{\\sigma_R^2 + \\sigma_{R,\\mathrm{free}}^2 + \\sigma_T^2 + (\\tau\\,\\Delta f_{0,e})^2}},

with tildes the bin medians, f′₀,free REEP's median in free air (so a small
constant REEP bias cancels), and likewise z_Q for Q′.

* σ_R, REEP's uncertainty of the bin median: 1.2533·median(σ_row)/√n_eff
  (eq. C.2), σ_row REEP's per-row ``f0_std_hz``/``q_std`` (or, in a reep.h5
  without them, the rows' scatter about the theory in the bin), n_eff the
  bin's rows over the correlation length (1 + φ)/(1 − φ) of rows that share
  a window, φ = λ per output row.
* σ_T, the theory's uncertainty from its inputs (:func:`theory_rows`): the
  amplitude REEP measures is the envelope's mean, but a multi-line drive
  makes the envelope beat by ±m·a, m = Σ_side B_i|G(f_i)| / (A|G(f)|) (the
  NOTES' ±2B|G(f0±Δf)|/|G(f0)|): averaging over the beat moves the equivalent
  parameters by ½|f(a + ma) + f(a − ma) − 2f(a)| + ½|f(a + ma) − f(a − ma)|·m
  (curvature, and the a²-weighting of the regression), and an uncertain
  separation by |f(l + σ_l) − f(l − σ_l)|/2.
* τ·Δf0,e, the model floor: averaging theory is first order in the force (one
  harmonic), so agreement is expected to a share τ (``tolerance``, default
  10 %) of the theory's own shift.

*Ill-conditioned bins.*  Where the tip reaches the repulsive wall
(a(1 + m) > l in any row of the bin, or REEP's f0′ above free air by more
than 3σ_R and ``WALL_RISE``·f0: only the wall raises it), averaging theory at the mean
amplitude is ill-conditioned: f0,e moves by hundreds of Hz for sub-nm
changes of the amplitude, and the reference curves show REEP 30-45 % off it
there (docs/conventions.md: treat the repulsive regime qualitatively).  Where σ_T
exceeds both σ_R and a quarter of the theory's shift, the theory cannot say
what REEP should read either: at the onset of the attraction (γ of eq. 4.8
has an unbounded second derivative where the tip just reaches d), and at
low Q, where the side lines beat the envelope by ±17 % (docs/conventions.md).  Such
bins are marked, left out of the verdict, and counted with their reason in
the report; rows next to a branch jump (:func:`jump_neighbourhood`) are left
out too.

*Verdict.*  Over the well-conditioned bins' z_f and z_Q: pass when at most
``MAX_OUTLIER_SHARE`` of them exceed 3 in magnitude and Σz²/ν is below the
χ²_ν quantile of 0.999.  Without a well-conditioned bin where the theory's
shift exceeds three times REEP's uncertainty the comparison is inconclusive,
and does not pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce
from afmtool.records.theory_compare import BinLeg, FreeAirReferenceRecord, TheoryComparisonRecord, WorstBinRecord

__all__ = [
    "ComparisonBins",
    "ReepRows",
    "MAX_OUTLIER_SHARE",
    "TheoryComparison",
    "TheoryRows",
    "beat_modulation",
    "compare_binned",
    "jump_neighbourhood",
    "theory_rows",
]

#: Share of well-conditioned z values allowed beyond ±3 (a calibrated z leaves 0.27 %).
MAX_OUTLIER_SHARE = 0.05
#: z beyond this is an outlier.
Z_OUTLIER = 3.0
#: A bin is ill-conditioned where the theory's uncertainty exceeds this share of its shift (and REEP's σ).
ILL_CONDITIONED_SHARE = 0.25
#: Fewest rows a bin needs.
MIN_BIN_ROWS = 5
#: A bin whose f0′ rises above free air by more than 3 σ_R and this share of f0 shows the wall (below it the
#: force only attracts, which lowers f0′): 8 Hz at 80 kHz, far below any shift the verdict weighs.
WALL_RISE = 1e-4


class TheoryRows(NamedTuple):
    """Averaging theory per REEP row, windowed as REEP is, and its uncertainty from its inputs (Hz, –)."""

    f0_e_hz: np.ndarray
    q_e: np.ndarray
    f0_e_std_hz: np.ndarray
    q_e_std: np.ndarray


@dataclass(frozen=True)
class ComparisonBins:
    """Per separation bin: REEP's and the theory's shifts from free air, their uncertainties and z (eq. C.1).

    ``leg`` is 0 on the approach, 1 on the retract; ``separation_nm`` the
    bin's centre; ``conditioned`` False where the bin is left out, with
    ``reason``.  f0 quantities in Hz, Q quantities dimensionless.
    """

    leg: np.ndarray
    separation_nm: np.ndarray
    rows: np.ndarray
    f0_shift_reep_hz: np.ndarray
    f0_shift_theory_hz: np.ndarray
    f0_reep_std_hz: np.ndarray
    f0_theory_std_hz: np.ndarray
    f0_z: np.ndarray
    q_shift_reep: np.ndarray
    q_shift_theory: np.ndarray
    q_reep_std: np.ndarray
    q_theory_std: np.ndarray
    q_z: np.ndarray
    conditioned: np.ndarray
    reason: tuple[str, ...]

    def table(self) -> dict[str, np.ndarray]:
        """The bins as columns (compare_bins.csv)."""
        names = ("leg", "separation_nm", "rows", "f0_shift_reep_hz", "f0_shift_theory_hz", "f0_reep_std_hz",
                 "f0_theory_std_hz", "f0_z", "q_shift_reep", "q_shift_theory", "q_reep_std", "q_theory_std", "q_z")
        columns = {name: np.asarray(getattr(self, name)) for name in names}
        columns["conditioned"] = self.conditioned.astype(np.uint8)
        return columns


@dataclass(frozen=True)
class TheoryComparison:
    """REEP against averaging theory along a force curve, binned (module docstring).

    ``mask`` selects the rows compared; ``f0_theory_hz``, ``q_theory`` are
    the windowed theory per row.  ``passed`` is the verdict; ``verdict`` says
    it in words.
    """

    mask: np.ndarray
    f0_theory_hz: np.ndarray
    q_theory: np.ndarray
    bins: ComparisonBins
    free_f0_hz: float
    free_q: float
    free_source: str
    uncertainty_source: str
    beat_modulation: float
    tolerance: float
    passed: bool
    verdict: str
    outlier_share: float
    chi2_per_dof: float
    chi2_limit_per_dof: float
    excluded_near_jumps: int

    def worst_bins(self, count: int = 3) -> tuple[WorstBinRecord, ...]:
        """The well-conditioned bins with the largest |z|, worst first."""
        b = self.bins
        worst = np.maximum(np.abs(b.f0_z), np.abs(b.q_z))
        order = [i for i in np.argsort(-np.nan_to_num(worst, nan=-1.0)) if b.conditioned[i]][:count]
        return tuple(WorstBinRecord(
            leg=(BinLeg.APPROACH, BinLeg.RETRACT)[int(b.leg[i])], separation_nm=float(b.separation_nm[i]),
            f0_shift_reep_hz=float(b.f0_shift_reep_hz[i]), f0_shift_theory_hz=float(b.f0_shift_theory_hz[i]),
            f0_z=float(b.f0_z[i]), q_shift_reep=float(b.q_shift_reep[i]), q_shift_theory=float(b.q_shift_theory[i]),
            q_z=float(b.q_z[i])) for i in order)

    def summary(self) -> TheoryComparisonRecord:
        """The report's numbers: verdict, bins compared and left out (with why), the worst bins."""
        b = self.bins
        reasons: dict[str, int] = {}
        for ok, why in zip(b.conditioned, b.reason):
            if not ok:
                reasons[why] = reasons.get(why, 0) + 1
        interaction = b.conditioned & (np.abs(b.f0_shift_theory_hz) > 0)
        return TheoryComparisonRecord(
            verdict=self.verdict,
            compared_rows=int(self.mask.sum()),
            bins=int(b.leg.size),
            bins_compared=int(b.conditioned.sum()),
            bins_ill_conditioned=int((~b.conditioned).sum()),
            ill_conditioned_reasons=reasons,
            excluded_near_jumps=self.excluded_near_jumps,
            outlier_share=self.outlier_share,
            max_outlier_share=MAX_OUTLIER_SHARE,
            chi2_per_dof=self.chi2_per_dof,
            chi2_limit_per_dof=self.chi2_limit_per_dof,
            tolerance=self.tolerance,
            f0_theory_change_hz=float(np.max(np.abs(b.f0_shift_theory_hz[interaction]), initial=0.0)),
            q_theory_change=float(np.max(np.abs(b.q_shift_theory[interaction]), initial=0.0)),
            free_air_reference=FreeAirReferenceRecord(f0_hz=self.free_f0_hz, q=self.free_q, source=self.free_source),
            uncertainty_source=self.uncertainty_source,
            beat_modulation=self.beat_modulation,
            worst_bins=self.worst_bins(),
        )


def jump_neighbourhood(amplitude: np.ndarray, sample_rate_hz: float, *, jump_nm: float = 1.0,
                       over_s: float = 2e-4, guard_s: float = 1e-3) -> np.ndarray:
    """Samples within ``guard_s`` of a branch jump (amplitude change > ``jump_nm`` in ``over_s``).

    At a jump between the attractive and repulsive branches the theory
    switches instantly while any estimator needs a window to follow, and
    averaging theory is ill-conditioned there (docs/conventions.md); these samples are
    compared qualitatively only.
    """
    step = max(1, round(over_s * sample_rate_hz))
    jump = np.zeros(len(amplitude), dtype=bool)
    if len(amplitude) > step:
        jump[step:] = np.abs(amplitude[step:] - amplitude[:-step]) > jump_nm
    guard = max(1, round(guard_s * sample_rate_hz))
    return np.convolve(jump.astype(float), np.ones(2 * guard + 1), mode="same") > 0


def beat_modulation(lines: list[tuple[float, float]], drive_hz: float, cantilever: Cantilever) -> float:
    """m = Σ_side B_i|G(f_i)| / (A|G(f)|): the envelope's relative beat of a multi-line drive (module docstring).

    Parameters
    ----------
    lines : list of (frequency Hz, amplitude V)
        The drive's lines; the one nearest ``drive_hz`` is the main line.
    drive_hz : float
        The lock-in (main line) frequency, Hz.
    cantilever : Cantilever
        Free-air f0 and Q of G(jω).
    """
    if len(lines) < 2:
        return 0.0
    main = min(range(len(lines)), key=lambda i: abs(lines[i][0] - drive_hz))
    gain = [abs(complex(cantilever.frequency_response(f))) * abs(a) for f, a in lines]
    return float(sum(g for i, g in enumerate(gain) if i != main) / max(gain[main], 1e-300))


def _windowed(values: np.ndarray, lam: float) -> np.ndarray:
    """(1 − λ)/(1 − λz⁻¹) applied to ``values``, started at its first value (REEP's window)."""
    from scipy.signal import lfilter

    return lfilter([1.0 - lam], [1.0, -lam], values, zi=[lam * values[0]])[0]


def theory_rows(amplitude_nm, separation_nm, *, drive_frequency_hz: float, cantilever: Cantilever,
                force: PiecewiseLinearForce, window_lambda: float, beat: float = 0.0,
                separation_std_nm: float = 0.0) -> TheoryRows:
    """f0,e and Qe per row (closed form of eq. 4.8), windowed as REEP, with σ_T from the beat and σ_l.

    Returns
    -------
    TheoryRows
        Windowed f0,e (Hz), Qe and their input uncertainties (module docstring, σ_T).
    """
    from afmtool.models.averaging import equivalent_parameters_closed_form

    a = np.maximum(np.asarray(amplitude_nm, dtype=np.float64), 1e-6)
    l = np.asarray(separation_nm, dtype=np.float64)
    omega = 2.0 * math.pi * drive_frequency_hz

    def evaluate(aa, ll):
        eq = equivalent_parameters_closed_form(aa, ll, omega, cantilever, force)
        return _windowed(np.nan_to_num(eq.f0_e_hz, nan=0.0), window_lambda), _windowed(
            np.nan_to_num(eq.q_e, nan=0.0), window_lambda)

    f0e, qe = evaluate(a, l)
    f0_var, q_var = np.zeros_like(f0e), np.zeros_like(qe)
    if beat > 0:
        (fu, qu), (fd, qd) = evaluate(a * (1 + beat), l), evaluate(np.maximum(a * (1 - beat), 1e-6), l)
        # curvature: the beat's mean effect; slope·m: the a²-weighted regression's shift of the amplitude
        f0_var += (0.5 * np.abs(fu + fd - 2 * f0e) + 0.5 * np.abs(fu - fd) * beat) ** 2
        q_var += (0.5 * np.abs(qu + qd - 2 * qe) + 0.5 * np.abs(qu - qd) * beat) ** 2
    if separation_std_nm > 0:
        (fu, qu), (fd, qd) = evaluate(a, l + separation_std_nm), evaluate(a, l - separation_std_nm)
        f0_var += (0.5 * (fu - fd)) ** 2
        q_var += (0.5 * (qu - qd)) ** 2
    return TheoryRows(f0e, qe, np.sqrt(f0_var), np.sqrt(q_var))


def _legs(separation: np.ndarray) -> np.ndarray:
    """0 up to the closest approach (the turn), 1 after it."""
    leg = np.zeros(separation.size, dtype=np.int8)
    if separation.size:
        leg[int(np.argmin(separation)) + 1 :] = 1
    return leg


def _effective_rows(selected: np.ndarray, row_lambda: float) -> float:
    """Independent rows among ``selected``: each contiguous run's length over (1 + φ)/(1 − φ), at least 1 per run."""
    correlation = (1.0 + row_lambda) / max(1.0 - row_lambda, 1e-12)
    edges = np.diff(np.concatenate(([0], selected.astype(np.int8), [0])))
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    return float(np.sum(np.maximum(1.0, runs / correlation)))


class ReepRows(NamedTuple):
    """REEP's series per row, as compared: f0′ (Hz), Q′, and their per-row std (None: not in reep.h5)."""

    f0_hz: np.ndarray
    q: np.ndarray
    f0_std_hz: np.ndarray | None
    q_std: np.ndarray | None


def _free_reference(reep: ReepRows, theory: TheoryRows, usable: np.ndarray, cantilever: Cantilever, row_lambda: float):
    """REEP's free-air f0′, Q′ (rows with no interaction in their window), their std, and where they came from."""
    free = usable & (theory.f0_e_hz == cantilever.f0_hz) & (theory.q_e == cantilever.q)
    if free.sum() < 4 * MIN_BIN_ROWS:
        free = usable & (np.abs(theory.f0_e_hz - cantilever.f0_hz) < 1e-6 * cantilever.f0_hz)
    if free.sum() < 4 * MIN_BIN_ROWS:
        return cantilever.f0_hz, cantilever.q, 0.0, 0.0, "the cantilever's f0, Q (too few free-air rows)"
    n_eff = _effective_rows(free, row_lambda)
    f0_std = _median_std(reep.f0_hz[free], reep.f0_std_hz, free, n_eff)
    q_std = _median_std(reep.q[free], reep.q_std, free, n_eff)
    return (float(np.median(reep.f0_hz[free])), float(np.median(reep.q[free])), f0_std, q_std,
            f"REEP's median over {int(free.sum())} rows without interaction in their window")


def _median_std(values: np.ndarray, row_std: np.ndarray | None, selected: np.ndarray, n_eff: float) -> float:
    """Std of a median of correlated rows, eq. C.2: from REEP's per-row std, else from the scatter (MAD)."""
    if row_std is not None:
        scale = float(np.median(row_std[selected]))
    else:
        scale = 1.4826 * float(np.median(np.abs(values - np.median(values))))
    return 1.2533 * scale / math.sqrt(max(n_eff, 1.0))


def _bin_rows(separation: np.ndarray, usable: np.ndarray, bin_nm: float):
    """(leg, bin index, selection) of every bin with at least MIN_BIN_ROWS usable rows."""
    leg = _legs(separation)
    key = np.floor(separation / bin_nm).astype(np.int64)
    for side in (0, 1):
        on_leg = usable & (leg == side)
        for k in np.unique(key[on_leg]):
            selected = on_leg & (key == k)
            if selected.sum() >= MIN_BIN_ROWS:
                yield side, int(k), selected


def _bin_condition(record, touching: bool) -> str:
    """Why a bin is left out of the verdict ("" if it is not): the repulsive wall, or a theory REEP cannot test."""
    if touching:
        return ("the tip reaches the repulsive wall: averaging theory at the mean amplitude is ill-conditioned "
                "there (docs/conventions.md)")
    if record[0][5] or record[1][5]:
        return ("the theory changes by more than REEP resolves within the amplitude's beat or the separation's "
                "uncertainty (attraction onset, low Q)")
    return ""


def _bin_record(reep: ReepRows, theory: TheoryRows, selected: np.ndarray, free, cantilever, row_lambda, tolerance):
    """One bin's numbers: (shift, REEP std, theory shift, theory std, z) for f0 and Q, and its condition."""
    free_f0, free_q, free_f0_std, free_q_std = free
    n_eff = _effective_rows(selected, row_lambda)
    record = []
    for values, row_std, model, model_std, model_free, reep_free, reep_free_std in (
        (reep.f0_hz, reep.f0_std_hz, theory.f0_e_hz, theory.f0_e_std_hz, cantilever.f0_hz, free_f0, free_f0_std),
        (reep.q, reep.q_std, theory.q_e, theory.q_e_std, cantilever.q, free_q, free_q_std),
    ):
        shift_reep = float(np.median(values[selected])) - reep_free
        shift_theory = float(np.median(model[selected])) - model_free
        std_reep = _median_std(values[selected] - model[selected], row_std, selected, n_eff)
        std_theory = float(np.median(model_std[selected]))
        # eq. C.1
        total = math.sqrt(std_reep**2 + reep_free_std**2 + std_theory**2 + (tolerance * shift_theory) ** 2)
        z = (shift_reep - shift_theory) / total if total > 0 else 0.0
        ill = std_theory > max(std_reep, ILL_CONDITIONED_SHARE * abs(shift_theory))
        record.append((shift_reep, std_reep, shift_theory, std_theory, z, ill))
    return record


def _verdict(bins: ComparisonBins) -> tuple[bool, str, float, float, float]:
    """(passed, in words, outlier share, Σz²/ν, its limit) over the well-conditioned bins (module docstring)."""
    from scipy.stats import chi2

    ok = bins.conditioned
    z = np.concatenate([bins.f0_z[ok], bins.q_z[ok]])
    probing = ok & ((np.abs(bins.f0_shift_theory_hz) > 3 * bins.f0_reep_std_hz)
                    | (np.abs(bins.q_shift_theory) > 3 * bins.q_reep_std))
    if z.size == 0 or not probing.any():
        return False, ("inconclusive: no well-conditioned bin where the theory's shift exceeds three times REEP's "
                       "uncertainty"), math.nan, math.nan, math.nan
    share = float(np.mean(np.abs(z) > Z_OUTLIER))
    chi2_dof = float(np.mean(z * z))
    limit = float(chi2.ppf(0.999, z.size) / z.size)
    passed = share <= MAX_OUTLIER_SHARE and chi2_dof <= limit
    words = (f"{'agree' if passed else 'disagree'}: {share:.0%} of {z.size} z values (f0 and Q in {int(ok.sum())} "
             f"well-conditioned bins) beyond +-{Z_OUTLIER:g} (allowed {MAX_OUTLIER_SHARE:.0%}), sum z^2/nu "
             f"{chi2_dof:.3g} (limit {limit:.3g})")
    return passed, words, share, chi2_dof, limit


def compare_binned(
    t_s: np.ndarray, reep: ReepRows, amplitude_nm: np.ndarray, separation_nm: np.ndarray, *,
    drive_frequency_hz: float, cantilever: Cantilever, force: PiecewiseLinearForce, row_lambda: float,
    free_amplitude_nm: float, beat: float = 0.0, separation_std_nm: float = 0.0, amplitude_fraction: float = 0.3,
    skip_s: float = 5e-3, bin_nm: float = 1.0, tolerance: float = 0.1, flag: np.ndarray | None = None,
) -> TheoryComparison:
    """Compare REEP's f0′, Q′ with averaging theory in separation bins (module docstring, eq. C.1).

    Parameters
    ----------
    t_s : numpy.ndarray
        REEP's row times, s.
    reep : ReepRows
        f0′ (Hz), Q′ and their per-row std (None where reep.h5 has none).
    amplitude_nm, separation_nm : numpy.ndarray
        Lock-in amplitude and rest separation per row, nm.
    drive_frequency_hz, cantilever, force
        The averaging-theory model.
    row_lambda : float
        REEP's forgetting factor per output row, λ^decimate.
    free_amplitude_nm : float
        A0, nm: rows below ``amplitude_fraction``·A0 are not compared.
    beat, separation_std_nm : float
        m of :func:`beat_modulation` and σ_l (nm), for σ_T.
    skip_s, bin_nm, tolerance : float
        REEP's start-up left out (s), the bin width (nm) and τ of eq. C.1.
    flag : numpy.ndarray, optional
        REEP's validity flags; flagged rows are not compared.

    Returns
    -------
    TheoryComparison
    """
    theory = theory_rows(amplitude_nm, separation_nm, drive_frequency_hz=drive_frequency_hz, cantilever=cantilever,
                         force=force, window_lambda=row_lambda, beat=beat, separation_std_nm=separation_std_nm)
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    near_jump = jump_neighbourhood(np.nan_to_num(amplitude_nm), 1.0 / dt)
    candidates = (amplitude_nm > amplitude_fraction * free_amplitude_nm) & (t_s > skip_s)
    candidates &= np.isfinite(reep.f0_hz) & np.isfinite(reep.q) & (flag == 0 if flag is not None else True)
    mask = candidates & ~near_jump
    if not mask.any():
        raise ValueError("no rows to compare: the amplitude never stays above the threshold")
    *free, free_source = _free_reference(reep, theory, mask, cantilever, row_lambda)
    columns: dict[str, list] = {name: [] for name in ComparisonBins.__dataclass_fields__}
    # the tip reaches t_s < 0 at the top of the beating envelope (where the force has a wall at all)
    touching = (amplitude_nm * (1.0 + beat) > separation_nm) & (force.omega_b2 > 0 or force.c_b > 0)
    for side, k, selected in _bin_rows(separation_nm, mask, bin_nm):
        record = _bin_record(reep, theory, selected, free, cantilever, row_lambda, tolerance)
        (f_r, f_rs, f_t, f_ts, f_z, _), (q_r, q_rs, q_t, q_ts, q_z, _) = record
        # REEP's own f0′ above free air: the tip reaches the wall whatever the mean amplitude says (at low Q
        # the side lines and the tapping's harmonics carry the tip 25-45 % past it, more than the lines' beat)
        rises = f_r > max(Z_OUTLIER * f_rs, WALL_RISE * free[0])
        reason = _bin_condition(record, bool(touching[selected].any()) or rises)
        for name, value in zip(columns, (side, (k + 0.5) * bin_nm, int(selected.sum()), f_r, f_t, f_rs, f_ts, f_z,
                                         q_r, q_t, q_rs, q_ts, q_z, not reason, reason)):
            columns[name].append(value)
    bins = ComparisonBins(**{name: (tuple(v) if name == "reason" else np.array(v)) for name, v in columns.items()})
    if bins.leg.size == 0:
        raise ValueError(f"no separation bin of {bin_nm:g} nm holds {MIN_BIN_ROWS} rows to compare")
    passed, words, share, chi2_dof, limit = _verdict(bins)
    return TheoryComparison(mask, theory.f0_e_hz, theory.q_e, bins, free[0], free[1], free_source,
                            "REEP's per-row f0_std_hz, q_std" if reep.f0_std_hz is not None
                            else "the rows' scatter about the theory in each bin (reep.h5 has no f0_std_hz)",
                            beat, tolerance, passed, words, share, chi2_dof, limit, int((candidates & near_jump).sum()))
