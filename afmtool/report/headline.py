"""The headline of a run: the few numbers a reader looks for first, declared once per command.

Each command's ``results`` hold every number a run produced (77 rows for a
force curve); the headline picks the handful that answer the question the
command was run for, each with its units and, where the analysis gives one,
its uncertainty: f0' and Q' in and after the free-air segment, the
tracking error against the truth, the probe-loss fraction with precision
and recall, the BER with its 95 % bound, the spring constant by each
method, the verdict of a comparison with its worst bins.

:data:`HEADLINES` declares them, once: per command a tuple of
:class:`Item` (label, path in ``results``, units, the path of its standard
deviation, the path of where it occurs).  :func:`headline` reads that
declaration into ``report.json``'s ``headline``; every other reader takes
the report's block and nothing else: the end-of-run lines on the terminal
(:func:`terminal_lines`), ``afmtool batch``'s ``summary.csv``
(:func:`summary_columns`) and the HTML page.  Nothing here is computed
anew: every entry is read from ``results`` at the path it names
(``source``); an analysis that wants a number headlined puts it in its
results first.  Numbers are written by :mod:`afmtool.report.numbers`.

A headline never contradicts the run (issue 28).  Where the results say
that the run's premise failed, the headline opens with that state, a text
entry named ``"warning"`` whose ``source`` is the number that says so
(:data:`STATES`), and the items declared as ``scores`` are left out:

* a free-air phase misfit above 30° (``free_air_route.phase_misfit_deg``):
  the model the observer runs on does not fit the capture; probeloss shows
  no precision, recall or latency;
* probeloss: the switch reading loss more than half the time; a capture
  predicted beyond the detection limit (``detectability``); event precision
  and recall against ``/truth`` that disagree with the time-weighted
  precision (more than 0.1 apart) are left out, with the reason;
* reep: a free-air f0′ more than 5 of its standard deviations from the
  lever's f0 (``free_air_check``) comes first; then, when more than half of
  REEP's rows are flagged, why (``validity.mostly_flagged``); and an
  output-only run (no dither: FM-KPFM, self-oscillation) says that Q′ is not
  identifiable, and shows no Q′ item (``q_identifiable``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from afmtool.report.numbers import format_measurement, format_with_units

__all__ = [
    "HEADLINES", "HEADLINE_FIELDS", "STATES", "STATE_NAME", "Item", "State", "headline", "lookup", "run_subject",
    "summary_columns", "terminal_lines",
]

#: ``name`` of a headline entry that states the run's state instead of a number.
STATE_NAME = "warning"
#: Above this free-air phase misfit (degrees) the headline shows the misfit, not scores.
_PHASE_MISFIT_DEG = 30.0
#: Above this loss fraction probeloss's headline shows the state, not scores.
_MOSTLY_LOSS = 0.5
#: Event and time-weighted precision farther apart than this disagree.
_SCORE_AGREEMENT = 0.1

#: Keys of one headline entry (``schemas/report.schema.json``, ``headline.items``).
HEADLINE_FIELDS = ("name", "value", "std", "units", "source", "std_source", "at", "note", "text")


@dataclass(frozen=True)
class Item:
    """One headline number, as a command declares it.

    Attributes
    ----------
    label : str
        What the number is, for a reader ("f0' in the free-air segment").
    path : str
        Dotted path of the value in ``results`` ("segments.free_air.f0_hz.mean").
    units : str
        Its units ("" when dimensionless); ``"@path"`` reads them from ``results``.
    std : str, optional
        Dotted path of its standard deviation.
    at : str, optional
        Dotted path of where it occurs (the z of a force curve's largest shift).
    at_label : str
        The name of that coordinate ("z", "separation").
    at_units : str
        Its units, or ``"@path"``.
    note : str, optional
        Dotted path of a word on its standing ("identified", "not identifiable").
    text : bool
        The value may be text or a yes/no (a verdict), not only a number.
    scores : bool
        A score that a failed premise undermines: left out when a :class:`State` says so.
    needs : str, optional
        Dotted path of a flag in ``results``: the item is left out when it is False
        (Q′ items need ``q_identifiable``).
    """

    label: str
    path: str
    units: str = ""
    std: str | None = None
    at: str | None = None
    at_label: str = "z"
    at_units: str = ""
    note: str | None = None
    text: bool = False
    scores: bool = False
    needs: str | None = None


def lookup(results: Mapping, path: str) -> Any:
    """The value at the dotted ``path`` of ``results`` (``"truth.index.recall"``), or None."""
    value: Any = results
    for part in path.split("."):
        if isinstance(value, Mapping) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.isdigit() and int(part) < len(value):
            value = value[int(part)]
        else:
            return None
    return value


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _units(results: Mapping, units: str) -> str:
    if units.startswith("@"):
        found = lookup(results, units[1:])
        return found if isinstance(found, str) else ""
    return units


# --------------------------------------------------------------------------- states before numbers


class State(NamedTuple):
    """The run's state where it undermines its own numbers: said first, and maybe the scores left out."""

    text: str
    source: str
    hides_scores: bool = True


def _number_at(results: Mapping, path: str) -> float | None:
    value = lookup(results, path)
    return float(value) if _number(value) else None


def _phase_state(results: Mapping, held: bool) -> State | None:
    """The free-air phase misfit, when it exceeds 30°."""
    misfit = _number_at(results, "free_air_route.phase_misfit_deg")
    if misfit is None or abs(misfit) <= _PHASE_MISFIT_DEG:
        return None
    return State(f"the free-air model misses the capture's phase at the drive by {misfit:+.0f} deg (> 30): "
                 "scores against it are not shown", "free_air_route.phase_misfit_deg")


def _free_air_check_state(results: Mapping, held: bool) -> State | None:
    """reep: a free-air f0' far (in its std) from the lever's or the model's f0."""
    check = results.get("free_air_check") or {}
    if check.get("consistent") is not False:
        return None
    reference = "the lever" if check.get("reference") == "metadata" else "the model"
    return State(f"REEP's free-air f0' {check['f0_hz']:.1f} Hz is {check['deviation_std']:.0f} std from "
                 f"{reference}'s f0 {check['reference_f0_hz']:.1f} Hz: the drive may be far off resonance or the model "
                 "wrong", "free_air_check.deviation_std", hides_scores=False)


def _mostly_flagged_state(results: Mapping, held: bool) -> State | None:
    """reep: more than half of the rows flagged, with the commonest reason (the run's first warning)."""
    text = lookup(results, "validity.mostly_flagged")
    if not isinstance(text, str) or not text:
        return None
    return State(f"{text}: the numbers below are from the remaining rows", "validity.flags.fraction",
                 hides_scores=False)


def _q_identifiable_state(results: Mapping, held: bool) -> State | None:
    """reep without the dither: the damping is the loop's, Q′ is not identifiable (no Q′ item is shown)."""
    if results.get("q_identifiable") is not False:
        return None
    return State("Q' is not identifiable without the dither (output-only: the damping is the loop's, not the "
                 "cantilever's); f0' is the frequency the motion oscillates at", "q_identifiable", hides_scores=False)


def _detectability_state(results: Mapping, held: bool) -> State | None:
    detectability = results.get("detectability") or {}
    if not detectability.get("beyond_limit"):
        return None
    return State(detectability.get("statement") or "beyond the detection limit", "detectability.beyond_limit",
                 hides_scores=False)


def _mostly_loss_state(results: Mapping, held: bool) -> State | None:
    loss = _number_at(results, "loss_fraction")
    if loss is None or loss <= _MOSTLY_LOSS:
        return None
    return State(f"the switch reads probe loss {100 * loss:.0f} % of the time: off the sample that long, or the "
                 "index has no contrast on the sample; scores are not shown", "loss_fraction")


def _scores_disagree_state(results: Mapping, held: bool) -> State | None:
    """Event precision vs /truth against the time-weighted one (asked only while the scores still stand)."""
    event, timed = _number_at(results, "truth.index.precision"), _number_at(results, "truth.index.time_precision")
    if held or event is None or timed is None or abs(event - timed) <= _SCORE_AGREEMENT:
        return None
    return State(f"event precision {event:.2f} disagrees with the time-weighted precision {timed:.2f}: event "
                 "precision and recall are not shown", "truth.index.time_precision")


#: Each command's states, checked in order before its numbers (issue 28).
STATES: Mapping[str, tuple[Callable[[Mapping, bool], State | None], ...]] = {
    "reep": (_phase_state, _free_air_check_state, _mostly_flagged_state, _q_identifiable_state),
    "probeloss": (_phase_state, _detectability_state, _mostly_loss_state, _scores_disagree_state),
    "kalman-bank": (_phase_state,),
}


# --------------------------------------------------------------------------- the declarations


def _free_air_model(prefix: str = "free_air_model") -> tuple[Item, ...]:
    return (
        Item("f0 (free air)", f"{prefix}.f0_hz", "Hz", f"{prefix}.f0_std_hz"),
        Item("Q (free air)", f"{prefix}.q", "", f"{prefix}.q_std"),
    )


def _reep_segments() -> tuple[Item, ...]:
    labels = {"free_air": "in the free-air segment", "after_free_air": "after the free-air segment",
              "settled": "after the warm-up"}
    items = []
    for segment, label in labels.items():
        items.append(Item(f"f0' {label}", f"segments.{segment}.f0_hz.mean", "Hz", f"segments.{segment}.f0_hz.std"))
        items.append(Item(f"Q' {label}", f"segments.{segment}.q.mean", "", f"segments.{segment}.q.std",
                          needs="q_identifiable"))
    return tuple(items)


def _reep_force_curve() -> tuple[Item, ...]:
    """On a force curve: the approach's extremes and where they occur (z in the capture's z units)."""
    leg = "force_curve.approach"
    z_units = f"@{leg}.z_units"
    return (
        Item("largest Δf0' on approach", f"{leg}.largest_df0_hz", "Hz", at=f"{leg}.largest_df0_z", at_units=z_units),
        Item("smallest Q' on approach", f"{leg}.smallest_q", "", at=f"{leg}.smallest_q_z", at_units=z_units,
             needs="q_identifiable"),
        Item("largest energy dissipated per cycle", f"{leg}.largest_energy_per_cycle_ev", "eV",
             at=f"{leg}.largest_energy_per_cycle_z", at_units=z_units, needs="q_identifiable"),
        Item("largest force gradient", f"{leg}.largest_force_gradient_n_per_m", "N/m",
             at=f"{leg}.largest_force_gradient_z", at_units=z_units),
    )


_REEP = (
    *_reep_segments(),
    *_reep_force_curve(),
    Item("|f0' − f0| median vs truth", "truth_tracking.f0_hz.median_abs", "Hz"),
    Item("|f0' − f0| 95th percentile vs truth", "truth_tracking.f0_hz.p95_abs", "Hz"),
    Item("|Q' − Q| median vs truth", "truth_tracking.q.median_abs", "", needs="q_identifiable"),
    Item("|Q' − Q| 95th percentile vs truth", "truth_tracking.q.p95_abs", "", needs="q_identifiable"),
    Item("flagged output samples", "flagged_samples", "samples"),
)

_PROBELOSS = (
    Item("probe-loss fraction (index)", "loss_fraction", "of time"),
    Item("probe-loss fraction (truth)", "truth.loss_fraction", "of time"),
    Item("precision (index)", "truth.index.precision", "", scores=True),
    Item("recall (index)", "truth.index.recall", "", scores=True),
    Item("median latency (index)", "truth.index.median_latency_periods", "drive periods", scores=True),
    Item("probe-loss fraction (amplitude baseline)", "amplitude_baseline.loss_fraction", "of time"),
    Item("precision (amplitude baseline)", "truth.amplitude.precision", ""),
    Item("recall (amplitude baseline)", "truth.amplitude.recall", ""),
    Item("loss events (index)", "events_total", "events"),
)

_DECODE = (
    Item("BER (EKF decoder)", "truth.decoder.ber", ""),
    Item("BER 95 % upper bound (EKF decoder)", "truth.decoder.ber_upper_95", ""),
    Item("BER (lock-in baseline)", "truth.baseline.ber", ""),
    Item("BER estimated from the bit clusters", "bits.estimated_ber_gaussian", ""),
    Item("bits decoded", "bits.count", "bits"),
    Item("bit rate", "clock.rate_hz", "bit/s"),
    Item("ℓ0", "l0.estimate_nm", "nm"),
    # --mode step: the response to a V_phi step (§7.7)
    Item("innovation settling after the V_phi step", "step.innovation.settling_periods", "actuation periods"),
    Item("amplitude settling after the V_phi step", "step.amplitude.settling_periods", "actuation periods"),
    Item("deflection settling after the V_phi step", "step.deflection.settling_periods", "actuation periods"),
    Item("running mean of the innovation: detection delay", "step.innovation_mean.delay_periods",
         "actuation periods"),
)

_KALMAN_BANK = (
    Item("verdict: pass", "verdict.pass", "", text=True),
    Item("adaptive observer has the least RMS", "adaptive.fraction_lowest", "of time"),
    Item("filters in the bank", "design.n_filters", "filters"),
    *_free_air_model(),
)

_FREEAIR = (
    *_free_air_model(),
    Item("gain", "free_air_model.gain", "", "free_air_model.gain_std"),
    Item("k (thermal, equipartition)", "spring_constant.thermal.value_n_per_m", "N/m",
         "spring_constant.thermal.std_n_per_m"),
    Item("k (Sader)", "spring_constant.sader.value_n_per_m", "N/m", "spring_constant.sader.std_n_per_m"),
)

_GAMMA = (
    Item("DC sensitivity Γ_IR,ts", "dc_sensitivity_ua_per_nm", "µA/nm"),
    Item("−3 dB bandwidth", "bandwidth_hz", "Hz"),
    Item("roll-off", "roll_off_db_per_decade", "dB/decade"),
    Item("feed-through capacitance", "feedthrough_fit.capacitance_pf", "pF"),
)

_ELECTROSTATIC = (
    Item("ℓ0", "parameters.l0_m.value", "m", "parameters.l0_m.std"),
    Item("K_esf/k", "parameters.k_esf_over_k_m3_per_v2.value", "m³/V²", "parameters.k_esf_over_k_m3_per_v2.std"),
    Item("α_R", "parameters.alpha_r.value", "", "parameters.alpha_r.std"),
    Item("t_h", "parameters.tip_height_m.value", "m", "parameters.tip_height_m.std"),
    Item("K_esf", "parameters.k_esf_f_m.value", "F·m", "parameters.k_esf_f_m.std"),
    Item("RMS residual", "rms_residual_nm", "nm"),
)

_THERMAL = (
    Item("K_TP (I-V knee)", "iv.k_tp_k_per_mw", "K/mW"),
    Item("knee power", "iv.knee_power_mw", "mW"),
    Item("knee voltage", "iv.knee_voltage_v", "V"),
    Item("K_TP in contact (z curve)", "z_curve.contact_k_tp_k_per_mw", "K/mW"),
    Item("snap-in z", "z_curve.snap_in_z_nm", "nm"),
    Item("C(jω) DC gain", "dynamics.c.dc_gain_k_per_mw", "K/mW"),
    Item("C(jω) −3 dB bandwidth", "dynamics.c.bandwidth_hz", "Hz"),
    Item("H(jω) DC gain", "dynamics.h.dc_gain_k_per_nm", "K/nm"),
    Item("H(jω) −3 dB bandwidth", "dynamics.h.bandwidth_hz", "Hz"),
)

_INVOLS = (
    Item("InvOLS (contact slope)", "invols_nm_per_v", "nm/V", "invols_std_nm_per_v"),
    Item("InvOLS implied by the contact slope", "implied_invols_nm_per_v", "nm/V", "implied_invols_std_nm_per_v"),
    Item("InvOLS of the capture (metadata)", "capture_invols_nm_per_v", "nm/V"),
    Item("contact slope", "contact_slope", "@contact_slope_units", "contact_slope_std"),
    Item("contact point z", "contact_z_nm", "nm"),
)

_COMPARE = (
    Item("verdict", "verdict", "", text=True),
    Item("χ² per degree of freedom", "chi2_per_dof", ""),
    Item("χ² limit per degree of freedom", "chi2_limit_per_dof", ""),
    Item("outlier share of the bins", "outlier_share", ""),
    Item("bins compared", "bins_compared", "bins"),
    Item("bins left out (ill-conditioned)", "bins_ill_conditioned", "bins"),
    Item("worst bin: (f0' − f0e) shift", "worst_bins.0.f0_z", "σ", at="worst_bins.0.separation_nm",
         at_label="separation", at_units="nm"),
    Item("worst bin: (Q' − Qe) shift", "worst_bins.0.q_z", "σ", at="worst_bins.0.separation_nm",
         at_label="separation", at_units="nm"),
    Item("second worst bin: (f0' − f0e) shift", "worst_bins.1.f0_z", "σ", at="worst_bins.1.separation_nm",
         at_label="separation", at_units="nm"),
)


def _fit_parameter(name: str, label: str, units: str) -> Item:
    return Item(label, f"parameters.{name}.value", units, f"parameters.{name}.std", note=f"parameters.{name}.status")


_FIT = (
    _fit_parameter("d_nm", "d", "nm"),
    _fit_parameter("omega_a2", "ω_a²", "1/s²"),
    _fit_parameter("omega_b2", "ω_b²", "1/s²"),
    _fit_parameter("c_a", "c_a", "1/s"),
    _fit_parameter("c_b", "c_b", "1/s"),
    _fit_parameter("contact_z", "contact point z_c", "@parameters.contact_z.units"),
    Item("onset d + s·z_c", "onset_d_plus_s_contact_z_nm.value", "nm", "onset_d_plus_s_contact_z_nm.std"),
    Item("RMS residual of f0'", "rms_residual.f0_hz", "Hz"),
)

_DESIGN = (
    Item("main line", "lines.0.frequency_hz", "Hz"),
    Item("main line amplitude", "lines.0.amplitude_v", "V"),
    Item("lower side line", "lines.1.frequency_hz", "Hz"),
    Item("upper side line", "lines.2.frequency_hz", "Hz"),
    Item("side-line amplitude", "lines.1.amplitude_v", "V"),
    Item("free-air response", "lines.0.response_nm", "nm"),
    Item("envelope beat (R₊ + R₋)/R_d", "envelope_beat", ""),
    Item("amplitude beat", "amplitude_beat", ""),
    Item("loop length", "loop_s", "s"),
)

_AVERAGING = (
    Item("f0e on approach, lowest", "approach.f0_e_range_hz.0", "Hz"),
    Item("f0e on approach, highest", "approach.f0_e_range_hz.1", "Hz"),
    Item("Qe on approach, lowest", "approach.q_e_range.0", ""),
    Item("bistable from separation", "approach.bistable_separation_nm.0", "nm"),
    Item("bistable up to separation", "approach.bistable_separation_nm.1", "nm"),
    Item("drive amplitude", "drive_amplitude_nm", "nm"),
)

_OBSERVER = (
    Item("recommended observer f_k", "recommendation.f_k_hz", "Hz"),
    Item("recommended observer Q_k", "recommendation.q_k", ""),
    Item("recommended window", "recommendation.cycles", "drive periods"),
    Item("observer f_k range mapped, lowest", "maps.f_k_hz_range.0", "Hz"),
    Item("observer f_k range mapped, highest", "maps.f_k_hz_range.1", "Hz"),
    Item("plant f0 (free air)", "plant.f0_hz", "Hz"),
    Item("plant Q (free air)", "plant.q", ""),
)

_CONTROLLERS = (
    Item("verdict: pass", "pass", "", text=True),
    Item("probe-loss area, low gain", "table.0.low.loss_area", "of the image"),
    Item("probe-loss area, high gain", "table.0.high.loss_area", "of the image"),
    Item("probe-loss area, switching gain", "table.0.switching.loss_area", "of the image"),
    Item("peak force, switching gain", "table.0.switching.peak_force_n", "N"),
    Item("at line rate", "table.0.line_rate_hz", "Hz"),
)

_OVERLAY = (
    Item("runs overlaid", "n_runs", "runs"),
    Item("free-air f0' spread across the runs", "free_air_f0_hz_spread", "Hz"),
    Item("free-air Q' spread across the runs", "free_air_q_spread", ""),
    Item("largest Δf0' on approach, first run", "first.largest_df0_hz", "Hz"),
    Item("largest Δf0' on approach, last run", "last.largest_df0_hz", "Hz"),
    Item("spread of the largest Δf0' across the runs", "largest_df0_hz_spread", "Hz"),
)

#: Each command's headline, in reading order (the one declaration every reader uses).
HEADLINES: Mapping[str, tuple[Item, ...]] = {
    "reep": _REEP,
    "probeloss": _PROBELOSS,
    "decode": _DECODE,
    "kalman-bank": _KALMAN_BANK,
    "identify freeair": _FREEAIR,
    "identify gamma": _GAMMA,
    "identify electrostatic": _ELECTROSTATIC,
    "identify thermal": _THERMAL,
    "identify invols": _INVOLS,
    "theory compare": _COMPARE,
    "theory fit": _FIT,
    "theory averaging": _AVERAGING,
    "theory observer": _OBSERVER,
    "theory controllers": _CONTROLLERS,
    "design excitation": _DESIGN,
    "overlay": _OVERLAY,
}


# --------------------------------------------------------------------------- report.json's block

#: Units that count things, and their singular for a count of one.
_SINGULAR = {"samples": "sample", "events": "event", "filters": "filter", "bits": "bit", "runs": "run",
             "drive periods": "drive period"}



def _entry(item: Item, results: Mapping) -> dict | None:
    value = lookup(results, item.path)
    if value is None or (not item.text and not _number(value)):
        return None
    if item.text and not isinstance(value, (str, bool)) and not _number(value):
        return None
    std_source = item.std
    std = lookup(results, std_source) if std_source else None
    if not _number(std):
        std, std_source = None, None
    units = _units(results, item.units)
    if value == 1 and not isinstance(value, bool):
        units = _SINGULAR.get(units, units)  # "1 sample", not "1 samples"
    at = None
    if item.at is not None:
        where = lookup(results, item.at)
        if _number(where):
            at = {"name": item.at_label, "value": where, "units": _units(results, item.at_units), "source": item.at}
    note = lookup(results, item.note) if item.note else None
    note = note if isinstance(note, str) else None
    text = format_with_units(value, std, units)
    if at is not None:
        text += f" at {at['name']} = {format_with_units(at['value'], None, at['units'])}"
    if note:
        text += f" ({note})"
    return {"name": item.label, "value": value, "std": std, "units": units, "source": item.path,
            "std_source": std_source, "at": at, "note": note, "text": text}


def headline(command: str, results: Mapping) -> list[dict]:
    """The headline entries of ``command``'s ``results`` (JSON-ready), in reading order.

    Each entry is ``{"name", "value", "std", "units", "source", "std_source", "at", "note", "text"}``:
    ``value`` is ``results`` at the dotted path ``source`` and ``std`` (its
    standard deviation, or None) at ``std_source``; ``units`` is ``""`` for a
    dimensionless number; ``at`` (or None) says where the value occurs
    (``{"name", "value", "units", "source"}``), ``note`` (or None) its
    standing ("identified"); ``text`` is the entry as the terminal and the
    page write it, by :mod:`afmtool.report.numbers`.  An
    item whose source the run lacks is left out.  Entries named
    :data:`STATE_NAME` (text) come first: the run's state where it undermines
    its own numbers (module docstring), and the scores it undermines are left out.
    """
    states: list[State] = []
    for rule in STATES.get(command, ()):
        state = rule(results, any(s.hides_scores for s in states))
        if state is not None:
            states.append(state)
    hide_scores = any(s.hides_scores for s in states)
    items = [item for item in HEADLINES.get(command, ())
             if not (item.scores and hide_scores) and not (item.needs and lookup(results, item.needs) is False)]
    entries = [entry for entry in (_entry(item, results) for item in items) if entry is not None]
    said = [{"name": STATE_NAME, "value": s.text, "std": None, "units": "", "source": s.source, "std_source": None,
             "at": None, "note": None, "text": s.text} for s in states]
    return said + entries


# --------------------------------------------------------------------------- its readers


def summary_columns(report: Mapping) -> dict[str, Any]:
    """``summary.csv``'s columns of one run: each headline entry by its source path (and std, and where)."""
    columns: dict[str, Any] = {}
    for entry in report.get("headline") or []:
        columns[entry["source"]] = entry["value"]
        if entry.get("std_source"):
            columns[entry["std_source"]] = entry["std"]
        if entry.get("at"):
            columns[entry["at"]["source"]] = entry["at"]["value"]
    return columns


def run_subject(report: Mapping) -> str:
    """What a run was run on, for a title: the first input's file name, or its folder's for afmtool's own files.

    ``theory compare fc`` records ``fc/report.json`` as its input: its subject is ``fc``.
    """
    runs = (report.get("results") or {}).get("runs") if report.get("command") == "overlay" else None
    if isinstance(runs, list) and runs:  # an overlay: its runs, by label
        labels = [str(run.get("label")) for run in runs if isinstance(run, Mapping)]
        return ", ".join(labels) if len(labels) <= 6 else f"{', '.join(labels[:3])} … {labels[-1]} ({len(labels)} runs)"
    inputs = report.get("inputs") or []
    if not inputs or not isinstance(inputs[0], Mapping):
        return ""
    path = str(inputs[0].get("path") or "").rstrip("/")
    parts = path.replace("\\", "/").split("/")
    name = parts[-1]
    if name in _OWN_FILES and len(parts) > 1 and parts[-2] not in ("", "."):
        return parts[-2]
    return name


#: afmtool's own output files that a later command reads: their folder names the run.
_OWN_FILES = frozenset({"report.json", "free_air.json", "reep.h5", "thermal_sensor.json", "gamma.h5", "fit.json",
                        "lines.json", "electrostatic.json"})

#: Warnings printed at the end of a run; the rest are counted (report.json has them all).
TERMINAL_WARNINGS = 6


def terminal_lines(report: Mapping, out: str) -> list[str]:
    """The end-of-run lines on stderr: what ran, the headline aligned, the warnings, where the files went."""
    command = str(report.get("command", ""))
    subject = run_subject(report)
    lines = [f"afmtool {command}" + (f" · {subject}" if subject else "")]
    entries: Sequence[Mapping] = report.get("headline") or []
    width = max((len(str(e["name"])) for e in entries), default=0)
    for entry in entries:
        text = entry.get("text") or format_measurement(entry.get("value"), entry.get("std"))
        lines.append(f"  {str(entry['name']).ljust(width)}  {text}")
    warnings = [str(w) for w in report.get("warnings") or []]
    for warning in warnings[:TERMINAL_WARNINGS]:
        lines.append(f"warning: {warning}")
    if len(warnings) > TERMINAL_WARNINGS:
        more = len(warnings) - TERMINAL_WARNINGS
        lines.append(f"warning: {more} more warning{'s' if more != 1 else ''} in report.json")
    outputs = ", ".join(str(name) for name in report.get("outputs") or [])
    lines.append(f"wrote {outputs} to {out}")
    return lines
