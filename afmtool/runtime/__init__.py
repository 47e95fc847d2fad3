"""The run's infrastructure, below every floor that writes or reads files (issue 29, item 4).

* :mod:`~afmtool.runtime.atomic` — files and folders written atomically.
* :mod:`~afmtool.runtime.outputs` — the staged output folder of a run
  (:class:`~afmtool.runtime.outputs.OutputDir`), swapped in whole at the end.
* :mod:`~afmtool.runtime.input_guard` — the inputs a run read, so that no
  output overwrites one.
* :mod:`~afmtool.runtime.faults` — faults of the environment (a full disk, a
  lost mount) told from bugs, and HDF5 handles kept past a failed write.
* :mod:`~afmtool.runtime.interrupts` — SIGINT/SIGTERM deferred across the
  swap of a finished output.
* :mod:`~afmtool.runtime.run_options` — ``afmtool --max-samples`` and
  ``--wait`` for the run in progress, read by the HDF5 readers and the
  output folder's lock (a context variable, not ``os.environ``).

It imports nothing of afmtool but :mod:`afmtool.errors`, so that ``io/``,
``models/`` and ``report/`` can all use it (docs/architecture.md, "Floors").
"""
