"""afmtool: model-mismatch analysis of high-rate AFM signals.

The data path is capture -> chunks -> kernel -> result -> writer:
``afmtool.io`` reads captures as aligned chunks, ``afmtool.estimators`` hold the
per-sample kernels, ``afmtool.analyses`` orchestrate one command each, and
``afmtool.report`` writes what they found.
"""

__version__ = "0.1.0"
