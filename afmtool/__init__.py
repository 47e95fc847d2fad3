"""afmtool: model-mismatch analysis of high-rate AFM signals.

The data path is capture -> chunks -> kernel -> result -> writer:
``afmtool.io`` reads captures as aligned chunks, ``afmtool.estimators`` hold the
per-sample kernels, ``afmtool.analyses`` orchestrate one command each, and
``afmtool.report`` writes what they found.

The Python API (``docs/python.md``) is at the top level::

    import afmtool
    cap = afmtool.open("sample_data/ltv_step.h5")
    run = afmtool.reep(cap, lam=0.995)      # afmtool reep --lambda 0.995
    run.summary, run.to_xarray(), run.save("results/reep")

Its names load on first use (PEP 562), so ``import afmtool`` imports no numpy,
numba, scipy, matplotlib or xarray.
"""

from afmtool.errors import AfmtoolError, ConfigError, InputError

__version__ = "0.1.0"

#: The public API, loaded from afmtool.api on first use.
_API = (
    "Capture", "ChunkResult", "Headline", "Result", "Summary", "open", "reep", "probeloss", "kalman_bank", "decode",
    "identify_freeair", "identify_invols", "identify_gamma", "identify_thermal", "identify_electrostatic",
    "design_excitation", "theory_averaging", "theory_compare", "theory_fit",
)

__all__ = ["__version__", "AfmtoolError", "ConfigError", "InputError", *_API]


def __getattr__(name: str):
    if name in _API:
        from afmtool import api

        value = getattr(api, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'afmtool' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
