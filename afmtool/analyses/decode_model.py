"""The plant decode's EKF models (eq. 7.11), without guessing (issue 28, item 5).

Each of the lever's parameters comes, first that gives it, from the
``[decode]`` parameters, from ``--electrostatic`` (the ``electrostatic.json``
of ``identify electrostatic``, eqs. 6.6/6.7), or from the capture metadata
(``cantilever``, ``electrostatic``).  Nothing falls back on the thesis's
experiment (eq. 7.10): its constants fitted to another lever make ℓ0 absorb
the mismatch (1268.6 nm for a lever at 1081.8 nm), silently.  A parameter
none of them gives stops the run, naming it and where to give it; a bit
capture holds no approach curve, so the capture itself cannot supply them.

* k and K_esf: the EKF's force per unit mass needs K_esf/k (an approach
  curve identifies only that ratio); K_esf is K_esf/k times k when the file
  gives only the ratio.  k also sets the thermal force noise.
* α_R ≥ 0 (eq. 6.3): 0 is the lever at ground, V = −V_sub.  Unused with a
  voltage channel.
* t_h: the separation's floor; without one the separation is not clamped
  (it matters only with the lever within t_h of the sample).
* ℓ0: estimated on the nominal segment (§7.4); a value from the file or the
  metadata only centres the search bracket, and without one the bracket is
  1.05·t_h (or 100 nm) to 20 µm on a geometric grid.
"""

from __future__ import annotations

from typing import NamedTuple

from afmtool.config.params import DecodeParams
from afmtool.errors import ConfigError
from afmtool.io.capture import CaptureInfo
from afmtool.io.electrostatic_file import ElectrostaticFile
from afmtool.models.electrostatic import ElectrostaticParams
from afmtool.records.decode import ModelSources

__all__ = ["ModelSetup", "resolve_model", "DEFAULT_L0_BRACKET_M"]

#: The ℓ0 search bracket when nothing gives a guess, m (the low end is raised to 1.05·t_h).
DEFAULT_L0_BRACKET_M = (100e-9, 20e-6)


class ModelSetup(NamedTuple):
    """The plant the EKF models before ℓ0 is estimated, and where each value came from."""

    f0_hz: float
    q: float
    electrostatic: ElectrostaticParams  #: its l0_m is the guess (a placeholder when ``l0_known`` is False)
    sources: ModelSources  #: per parameter: "parameter", "--electrostatic FILE", "metadata" or "none: ..."
    l0_known: bool = True  #: False: nothing gave ℓ0; the default bracket is searched

    def l0_bracket_m(self) -> tuple[float, float, bool]:
        """(low, high, geometric) of the ℓ0 search when no bracket is given (module docstring)."""
        if self.l0_known:
            guess = self.electrostatic.l0_m
            return 0.75 * guess, 1.33 * guess, False
        low = max(DEFAULT_L0_BRACKET_M[0], 1.05 * self.electrostatic.tip_height_m)
        return low, DEFAULT_L0_BRACKET_M[1], True


class _Sources:
    """The first of parameter, file and metadata that gives each value; the names none gives."""

    def __init__(self, params: DecodeParams, file: ElectrostaticFile | None, info: CaptureInfo) -> None:
        self.params, self.file = params, file
        self.cantilever = info.capture_metadata.cantilever
        self.es = info.capture_metadata.electrostatic
        self.sources: dict[str, str] = {}
        self.missing: list[str] = []

    def pick(self, name: str, given, from_file, from_meta, *, scale: float = 1.0, required: bool = True):
        for value, where in ((given, "parameter"), (from_file, f"--electrostatic {self.file.path}" if self.file else ""),
                             (from_meta, "metadata")):
            if value is not None:
                self.sources[name] = where
                return value * scale if where == "parameter" else value
        if required:
            self.missing.append(name)
        return None


def _file(file: ElectrostaticFile | None, name: str):
    return getattr(file, name) if file is not None else None


def resolve_model(info: CaptureInfo, params: DecodeParams, file: ElectrostaticFile | None = None) -> ModelSetup:
    """f0, Q, k, K_esf, α_R, t_h and an ℓ0 guess (module docstring).

    Raises
    ------
    ConfigError
        Naming every parameter that neither the parameters, ``--electrostatic``
        nor the metadata give, and how to give them.
    """
    src = _Sources(params, file, info)
    c, es = src.cantilever, src.es
    f0 = src.pick("f0_hz", params.f0_hz or None, None, c.f0_hz)
    q = src.pick("q", params.q or None, None, c.q)
    k = src.pick("spring_constant_n_per_m", params.spring_constant_n_per_m or None,
                 _file(file, "spring_constant_n_per_m"), c.spring_constant_n_per_m)
    ratio_k_esf = None
    if file is not None and file.k_esf_f_m is None and file.k_esf_over_k_m3_per_v2 is not None and k is not None:
        ratio_k_esf = file.k_esf_over_k_m3_per_v2 * k  # the file knows K_esf/k; k from the parameters or metadata
    k_esf = src.pick("k_esf_f_m", params.k_esf_f_m or None, _file(file, "k_esf_f_m") or ratio_k_esf, es.k_esf_f_m)
    alpha = 0.0
    if params.voltage_channel:
        src.sources["alpha_r"] = "unused (voltage channel)"
    else:
        alpha = src.pick("alpha_r", params.alpha_r if params.alpha_r >= 0 else None, _file(file, "alpha_r"),
                         es.alpha_r)
    tip = src.pick("tip_height_nm", params.tip_height_nm or None, _file(file, "tip_height_m"), es.tip_height_m,
                   scale=1e-9, required=False)
    if tip is None:
        tip, src.sources["tip_height_nm"] = 0.0, "none: the separation is not clamped"
    l0 = src.pick("l0_guess_nm", params.l0_nm or None, _file(file, "l0_m"), es.l0_m, scale=1e-9, required=False)
    if src.missing:
        raise ConfigError(_missing_message(src.missing))
    if l0 is None:  # a placeholder above t_h; the search over the default bracket replaces it
        src.sources["l0_guess_nm"] = "none: the default bracket is searched"
        l0 = 2.0 * max(DEFAULT_L0_BRACKET_M[0], 1.05 * tip)
    sources = ModelSources(**src.sources)
    return ModelSetup(f0, q, ElectrostaticParams(k, k_esf, alpha, l0, tip), sources,
                      sources.l0_guess_nm != "none: the default bracket is searched")


_HOW = {
    "f0_hz": "f0_hz (Hz)",
    "q": "q",
    "spring_constant_n_per_m": "spring_constant_n_per_m (N/m; e.g. from 'identify freeair --psd')",
    "k_esf_f_m": "k_esf_f_m (F*m)",
    "alpha_r": "--alpha-r (0: the lever at ground)",
}


def _missing_message(missing: list[str]) -> str:
    names = ", ".join(_HOW[name] for name in missing)
    return (f"decode needs {names} of eq. 7.11 and neither the parameters, --electrostatic nor the capture "
            "metadata give them (a bit capture holds no approach curve to identify them from): run 'afmtool "
            "identify electrostatic' on an approach curve and pass its folder with --electrostatic, or set them "
            "in the [decode] section of --config")
