"""The headline block of a report: the few numbers a reader looks for first.

Each command's ``results`` hold every number a run produced (77 rows for a
force curve); the headline picks the handful that answer the question the
command was run for, each with its units and, where the analysis gives one,
its uncertainty: f0' and Q' in and after the free-air segment, the
tracking error against the truth, the probe-loss fraction with precision
and recall, the BER with its 95 % bound.  ``report.json``, ``--json`` and
the HTML page carry the same block; nothing here is computed anew, every
entry is read from ``results`` at the path it names (``source``).

A headline never contradicts the run (issue 28).  Where the results say
that the run's premise failed, the headline opens with that state, a text
entry named ``"warning"`` whose ``source`` is the number that says so, and
the scores it undermines are left out:

* a free-air phase misfit above 30° (``free_air_route.phase_misfit_deg``):
  the model the observer runs on does not fit the capture; probeloss shows
  no precision, recall or latency;
* probeloss: the switch reading loss more than half the time; a capture
  predicted beyond the detection limit (``detectability``); event precision
  and recall against ``/truth`` that disagree with the time-weighted
  precision (more than 0.1 apart) are left out, with the reason;
* reep: a free-air f0′ more than 5 of its standard deviations from the
  lever's f0 (``free_air_check``) comes first.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["HEADLINE_FIELDS", "STATE_NAME", "headline", "lookup"]

#: Keys of one headline entry (``schemas/report.schema.json``, ``headline.items``).
HEADLINE_FIELDS = ("name", "value", "std", "units", "source", "std_source")

_MISSING = object()

#: ``name`` of a headline entry that states the run's state instead of a number.
STATE_NAME = "warning"
#: Above this free-air phase misfit (degrees) the headline shows the misfit, not scores.
_PHASE_MISFIT_DEG = 30.0
#: Above this loss fraction probeloss's headline shows the state, not scores.
_MOSTLY_LOSS = 0.5
#: Event and time-weighted precision farther apart than this disagree.
_SCORE_AGREEMENT = 0.1


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


class _Block:
    """Entries collected for one report; a missing or non-numeric source is skipped."""

    def __init__(self, results: Mapping) -> None:
        self.results = results
        self.entries: list[dict] = []
        self.states: list[dict] = []

    def add(self, name: str, source: str, units: str, std_source: str | None = None, *, text: bool = False) -> None:
        value = lookup(self.results, source)
        if value is None or (not text and (isinstance(value, bool) or not isinstance(value, (int, float)))):
            return
        std = lookup(self.results, std_source) if std_source else None
        if not isinstance(std, (int, float)) or isinstance(std, bool):
            std, std_source = None, None
        self.entries.append(
            {"name": name, "value": value, "std": std, "units": units, "source": source, "std_source": std_source}
        )

    def state(self, text: str, source: str) -> None:
        """A text entry stating the run's state (issue 28): it goes before every number."""
        self.states.append(
            {"name": STATE_NAME, "value": text, "std": None, "units": "", "source": source, "std_source": None}
        )


def _number(results: Mapping, path: str) -> float | None:
    value = lookup(results, path)
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _phase_state(block: _Block) -> bool:
    """The free-air phase misfit as the run's state when it exceeds 30°; True if it does."""
    misfit = _number(block.results, "free_air_route.phase_misfit_deg")
    if misfit is None or abs(misfit) <= _PHASE_MISFIT_DEG:
        return False
    block.state(f"the free-air model misses the capture's phase at the drive by {misfit:+.0f} deg (> 30): "
                "scores against it are not shown", "free_air_route.phase_misfit_deg")
    return True


def _free_air_model(block: _Block, prefix: str = "free_air_model") -> None:
    block.add("f0 (free air)", f"{prefix}.f0_hz", "Hz", f"{prefix}.f0_std_hz")
    block.add("Q (free air)", f"{prefix}.q", "", f"{prefix}.q_std")


def _reep(block: _Block) -> None:
    _phase_state(block)
    check = block.results.get("free_air_check") or {}
    if check.get("consistent") is False:
        block.state(
            f"REEP's free-air f0' {check['f0_hz']:.1f} Hz is {check['deviation_std']:.0f} std from "
            f"{'the lever' if check['reference'] == 'metadata' else 'the model'}'s f0 {check['reference_f0_hz']:.1f} Hz: "
            "the drive may be far off resonance or the model wrong", "free_air_check.deviation_std")
    segments = block.results.get("segments") or {}
    labels = {"free_air": "in the free-air segment", "after_free_air": "after the free-air segment",
              "settled": "after the warm-up"}
    for segment, label in labels.items():
        if segment in segments:
            block.add(f"f0' {label}", f"segments.{segment}.f0_hz.mean", "Hz", f"segments.{segment}.f0_hz.std")
            block.add(f"Q' {label}", f"segments.{segment}.q.mean", "", f"segments.{segment}.q.std")
    block.add("|f0' − f0| median vs truth", "truth_tracking.f0_hz.median_abs", "Hz")
    block.add("|f0' − f0| 95th percentile vs truth", "truth_tracking.f0_hz.p95_abs", "Hz")
    block.add("|Q' − Q| median vs truth", "truth_tracking.q.median_abs", "")
    block.add("|Q' − Q| 95th percentile vs truth", "truth_tracking.q.p95_abs", "")
    block.add("flagged output samples", "flagged_samples", "samples")


def _probeloss_states(block: _Block) -> bool:
    """The states that replace probeloss's scores; True if any holds."""
    results = block.results
    held = _phase_state(block)
    detectability = results.get("detectability") or {}
    if detectability.get("beyond_limit"):
        block.state(detectability.get("statement") or "beyond the detection limit", "detectability.beyond_limit")
    loss = _number(results, "loss_fraction")
    if loss is not None and loss > _MOSTLY_LOSS:
        block.state(f"the switch reads probe loss {100 * loss:.0f} % of the time: off the sample that long, or the "
                    "index has no contrast on the sample; scores are not shown", "loss_fraction")
        held = True
    return held


def _scores_agree(block: _Block) -> bool:
    """Event precision vs /truth agrees with the time-weighted one (else a state says why)."""
    event, timed = _number(block.results, "truth.index.precision"), _number(block.results, "truth.index.time_precision")
    if event is None or timed is None or abs(event - timed) <= _SCORE_AGREEMENT:
        return True
    block.state(f"event precision {event:.2f} disagrees with the time-weighted precision {timed:.2f}: event "
                "precision and recall are not shown", "truth.index.time_precision")
    return False


def _probeloss(block: _Block) -> None:
    scores = not _probeloss_states(block) and _scores_agree(block)
    block.add("probe-loss fraction (index)", "loss_fraction", "of time")
    block.add("probe-loss fraction (truth)", "truth.loss_fraction", "of time")
    if scores:
        block.add("precision (index)", "truth.index.precision", "")
        block.add("recall (index)", "truth.index.recall", "")
        block.add("median latency (index)", "truth.index.median_latency_periods", "drive periods")
    block.add("probe-loss fraction (amplitude baseline)", "amplitude_baseline.loss_fraction", "of time")
    block.add("precision (amplitude baseline)", "truth.amplitude.precision", "")
    block.add("recall (amplitude baseline)", "truth.amplitude.recall", "")
    block.add("loss events (index)", "events_total", "events")


def _decode(block: _Block) -> None:
    block.add("BER (EKF decoder)", "truth.decoder.ber", "")
    block.add("BER 95 % upper bound (EKF decoder)", "truth.decoder.ber_upper_95", "")
    block.add("BER (lock-in baseline)", "truth.baseline.ber", "")
    block.add("BER estimated from the bit clusters", "bits.estimated_ber_gaussian", "")
    block.add("bits decoded", "bits.count", "bits")
    block.add("bit rate", "clock.rate_hz", "bit/s")
    block.add("ℓ0", "l0.estimate_nm", "nm")


def _kalman_bank(block: _Block) -> None:
    _phase_state(block)
    block.add("verdict: pass", "verdict.pass", "", text=True)
    block.add("adaptive observer has the least RMS", "adaptive.fraction_lowest", "of time")
    block.add("filters in the bank", "design.n_filters", "filters")
    _free_air_model(block)


def _freeair(block: _Block) -> None:
    _free_air_model(block)
    block.add("gain", "free_air_model.gain", "", "free_air_model.gain_std")


def _gamma(block: _Block) -> None:
    block.add("DC sensitivity Γ_IR,ts", "dc_sensitivity_ua_per_nm", "µA/nm")
    block.add("−3 dB bandwidth", "bandwidth_hz", "Hz")
    block.add("roll-off", "roll_off_db_per_decade", "dB/decade")
    block.add("feed-through capacitance", "feedthrough_fit.capacitance_pf", "pF")


def _electrostatic(block: _Block) -> None:
    block.add("ℓ0", "parameters.l0_m.value", "m", "parameters.l0_m.std")
    block.add("K_esf/k", "parameters.k_esf_over_k_m3_per_v2.value", "m³/V²", "parameters.k_esf_over_k_m3_per_v2.std")
    block.add("α_R", "parameters.alpha_r.value", "", "parameters.alpha_r.std")
    block.add("t_h", "parameters.tip_height_m.value", "m", "parameters.tip_height_m.std")
    block.add("K_esf", "parameters.k_esf_f_m.value", "F·m", "parameters.k_esf_f_m.std")
    block.add("RMS residual", "rms_residual_nm", "nm")


def _thermal(block: _Block) -> None:
    block.add("K_TP (I-V knee)", "iv.k_tp_k_per_mw", "K/mW")
    block.add("knee power", "iv.knee_power_mw", "mW")
    block.add("knee voltage", "iv.knee_voltage_v", "V")


_BY_COMMAND: Mapping[str, Callable[[_Block], None]] = {
    "identify electrostatic": _electrostatic,
    "identify thermal": _thermal,
    "reep": _reep,
    "probeloss": _probeloss,
    "decode": _decode,
    "kalman-bank": _kalman_bank,
    "identify freeair": _freeair,
    "identify gamma": _gamma,
}


def headline(command: str, results: Mapping) -> list[dict]:
    """The headline entries of ``command``'s ``results`` (JSON-ready), in reading order.

    Each entry is ``{"name", "value", "std", "units", "source", "std_source"}``:
    ``value`` is ``results`` at the dotted path ``source`` and ``std`` (its
    standard deviation, or None) at ``std_source``; ``units`` is ``""`` for a
    dimensionless number.  A command without a headline of its own gets an
    empty list, and so does a run whose results lack every source.  Entries
    named ``STATE_NAME`` (text) come first: the run's state where it
    undermines its own numbers (module docstring).
    """
    block = _Block(results)
    fill = _BY_COMMAND.get(command)
    if fill is not None:
        fill(block)
    return block.states + block.entries
