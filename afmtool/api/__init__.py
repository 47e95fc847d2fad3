"""afmtool's Python API: :func:`afmtool.open`, :class:`afmtool.Capture` and one function per analysis.

Re-exported at the top level (``afmtool.reep`` ...) and loaded on first use, so
``import afmtool`` stays light.  See ``docs/python.md``.
"""

from afmtool.api.capture import Capture, open
from afmtool.api.commands import (
    decode,
    design_excitation,
    identify_electrostatic,
    identify_freeair,
    identify_gamma,
    identify_invols,
    identify_thermal,
    kalman_bank,
    probeloss,
    reep,
    theory_averaging,
    theory_compare,
    theory_fit,
)
from afmtool.api.results import ChunkResult, Headline, Result, Summary

__all__ = [
    "Capture", "ChunkResult", "Headline", "Result", "Summary", "open", "reep", "probeloss", "kalman_bank", "decode",
    "identify_freeair", "identify_invols", "identify_gamma", "identify_thermal", "identify_electrostatic",
    "design_excitation", "theory_averaging", "theory_compare", "theory_fit",
]
