"""What each command's headline shows: :class:`Item` declarations, per command, as plain data.

A command's headline (:mod:`afmtool.report.headline`) is declared here, beside the
command's other parts (:mod:`afmtool.config.commands`), so that the one
command table can name it while staying light: nothing here imports beyond the
standard library (and :mod:`afmtool.records.base`, which declares :class:`Item`), and
``afmtool --help`` reads this module.  A command whose results are a typed record declares its
headline on the record instead (:mod:`afmtool.records`); the rest move there one by one.  Every
``Item`` names a dotted path into the run's ``results``; nothing is computed here.
"""

from __future__ import annotations

from afmtool.records.base import Item

__all__ = [
    "Item", "KALMAN_BANK",
]


def _free_air_model(prefix: str = "free_air_model") -> tuple[Item, ...]:
    return (
        Item("f0 (free air)", f"{prefix}.f0_hz", "Hz", f"{prefix}.f0_std_hz"),
        Item("Q (free air)", f"{prefix}.q", "", f"{prefix}.q_std"),
    )


KALMAN_BANK = (
    Item("verdict: pass", "verdict.pass", "", text=True),
    Item("adaptive observer has the least RMS", "adaptive.fraction_lowest", "of time"),
    Item("filters in the bank", "design.n_filters", "filters"),
    *_free_air_model(),
)

COMPARE = (
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


OVERLAY = (
    Item("runs overlaid", "n_runs", "runs"),
    Item("free-air f0' spread across the runs", "free_air_f0_hz_spread", "Hz"),
    Item("free-air Q' spread across the runs", "free_air_q_spread", ""),
    Item("largest Δf0' on approach, first run", "first.largest_df0_hz", "Hz"),
    Item("largest Δf0' on approach, last run", "last.largest_df0_hz", "Hz"),
    Item("spread of the largest Δf0' across the runs", "largest_df0_hz_spread", "Hz"),
)
