"""``afmtool --max-samples N`` and ``--wait`` travel as run settings, not through ``os.environ`` (issue 29, item 4).

The CLI keeps them on its click context and in force for the command
(:mod:`afmtool.runtime.run_options`), the Python API in its
:class:`~afmtool.api.run.RunSettings`, and ``afmtool batch`` puts them on
each run's command line.  Every test here runs in this process, in well
under a second or two.
"""

from __future__ import annotations

import fcntl
import os
import signal
import sys
import threading
import time

import h5py
import pytest

from afmtool.errors import ConfigError, InputError
from afmtool.runtime.run_options import DEFAULTS, RunOptions, applied, current

FS = 100_000.0


@pytest.fixture
def sparse(tmp_path):
    """1e7 samples of fill value: the file claims 80 MB in a few kB, refused without --max-samples."""
    path = tmp_path / "sparse.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = FS
        f.create_dataset("channels/deflection", shape=(10**7,), dtype="f8", chunks=(1 << 16,)).attrs["units"] = "nm"
    return path


@pytest.fixture
def in_process(monkeypatch, capsys):
    """``afmtool.cli.main.main(argv)`` in this process, with no ``AFMTOOL_`` variable set: (status, stderr)."""
    from afmtool.cli import main as cli_main

    for name in [name for name in os.environ if name.startswith("AFMTOOL_")]:
        monkeypatch.delenv(name)
    # main() ends a failed run without interpreter teardown while a helper thread lives; pytest has some
    monkeypatch.setattr("afmtool.runtime.process.exit_now_if_teardown_unsafe", lambda code: None)
    saved = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM), sys.unraisablehook)

    def run(*argv) -> tuple[int, str]:
        capsys.readouterr()
        with pytest.raises(SystemExit) as done:
            cli_main.main([str(a) for a in argv])
        return done.value.code, capsys.readouterr().err

    yield run
    signal.signal(signal.SIGINT, saved[0])
    signal.signal(signal.SIGTERM, saved[1])
    sys.unraisablehook = saved[2]


def test_cli_max_samples_reaches_the_reader_without_the_environment(in_process, sparse, tmp_path):
    status, err = in_process("info", sparse)
    assert status == 2 and "give afmtool --max-samples N" in err
    assert in_process("--max-samples", 10**7, "info", sparse)[0] == 0
    status, err = in_process("--max-samples", 1000, "info", sparse)
    assert status == 2 and "more than --max-samples 1,000" in err
    # through the RunSettings the command builds (its scope would otherwise put the defaults back)
    status, err = in_process("--max-samples", 1000, "reep", sparse, "--out", tmp_path / "out", "--no-input", "-q")
    assert status == 2 and "more than --max-samples 1,000" in err, err
    assert not [name for name in os.environ if name.startswith("AFMTOOL_")]
    assert current() == DEFAULTS  # the run's options ended with it ...
    assert in_process("info", sparse)[0] == 2  # ... so the next run in this process checks the ratio again


def test_python_path_takes_max_samples_from_its_run_settings(sparse, tmp_path, monkeypatch):
    from afmtool.api.run import RunSettings, run_capture_command
    from afmtool.io.registry import open_capture

    monkeypatch.delenv("AFMTOOL_MAX_SAMPLES", raising=False)
    with pytest.raises(InputError, match="more than --max-samples 1,000"):
        run_capture_command("reep", sparse, tmp_path / "out", {"use_input": False}, RunSettings(max_samples=1000))
    with pytest.raises(InputError, match="give afmtool --max-samples N"):
        run_capture_command("reep", sparse, tmp_path / "out", {"use_input": False}, RunSettings())
    with RunSettings(max_samples=10**7).scope():
        open_capture(sparse).close()
    assert current() == DEFAULTS
    with pytest.raises(ConfigError, match="--max-samples 0 must be at least 1"):
        RunSettings(max_samples=0)


def test_folder_lock_waits_with_the_runs_wait_option(tmp_path):
    from afmtool.runtime.atomic import OutputError
    from afmtool.runtime.outputs import FolderLock

    out = tmp_path / "out"
    held = open(tmp_path / ".out.lock", "wb")  # noqa: SIM115 - closed by the thread below, to let the waiter in
    fcntl.flock(held, fcntl.LOCK_EX)
    with pytest.raises(OutputError, match="give afmtool --wait"):
        FolderLock(out, out).acquire()
    with applied(RunOptions(wait=True)), pytest.raises(OutputError, match="give afmtool --wait"):
        FolderLock(out, out, wait=False).acquire()  # batch's own lock is told explicitly
    threading.Timer(0.3, held.close).start()
    started = time.monotonic()
    with applied(RunOptions(wait=True)), FolderLock(out, out):
        assert time.monotonic() - started >= 0.2


def test_batch_gives_each_run_the_options_on_its_command_line():
    from afmtool.analyses.batch import BatchItem, child_command

    item = BatchItem("in.h5", "out/in")
    args = child_command(["identify", "freeair"], item, ["--no-input"], RunOptions(max_samples=5, wait=True))
    assert args[1:] == ["-m", "afmtool", "--max-samples", "5", "--wait", "identify", "freeair", "in.h5",
                        "--out", "out/in", "--quiet", "--no-input"]
    assert "--max-samples" not in child_command(["reep"], item, []) and "--wait" not in child_command(["reep"], item, [])
    assert RunOptions(wait=True).args() == ["--wait"]


def test_every_python_function_takes_max_file_samples_and_passes_it_to_its_reader(sparse):
    import inspect

    import afmtool
    from afmtool.api import commands

    for name in commands.__all__:
        parameter = inspect.signature(getattr(afmtool, name)).parameters.get("max_file_samples")
        assert parameter is not None and parameter.default is None, name
        assert "max_file_samples : int, optional" in getattr(afmtool, name).__doc__, name
    with pytest.raises(InputError, match="give afmtool --max-samples N"):
        afmtool.reep(sparse, use_input=False)
    with pytest.raises(InputError, match="more than --max-samples 1,000"):
        afmtool.reep(sparse, use_input=False, max_file_samples=1000)
    with pytest.raises(InputError, match="more than --max-samples 1,000"):  # stream=True runs in a thread of its own
        next(iter(afmtool.reep(sparse, use_input=False, stream=True, max_file_samples=1000)))
    with pytest.raises(InputError, match="more than --max-samples 1,000"):
        afmtool.identify_invols(sparse, max_file_samples=1000)
    assert current() == DEFAULTS


def test_result_save_waits_for_the_folder_with_wait(tmp_path):
    import afmtool
    from afmtool.runtime.atomic import OutputError

    result = afmtool.theory_averaging(force_set="attractive", points=40)
    out = tmp_path / "out"
    held = open(tmp_path / ".out.lock", "wb")  # noqa: SIM115 - closed by the timer, to let the waiter in
    fcntl.flock(held, fcntl.LOCK_EX)
    with pytest.raises(OutputError, match="give afmtool --wait"):
        result.save(out)
    threading.Timer(0.3, held.close).start()
    assert result.save(out, wait=True) == out and (out / "report.json").is_file()
