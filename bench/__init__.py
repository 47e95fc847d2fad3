"""afmtool benchmarks: ``python -m bench`` runs them all and writes ``bench.json``.

Speed is measured here, never in the tests.  Each benchmark reports ratios
against a baseline measured in the same run, because the machines are noisy.
"""
