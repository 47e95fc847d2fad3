"""The figure process: the same PNG as drawn here, errors and warnings brought back, no helper left behind.

Each case runs in a fresh interpreter: the helper is forked only from a
process with no other thread, which a pytest worker is not.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

_PRELUDE = """
import os, sys, time, warnings
from pathlib import Path
import numpy as np
from afmtool.report.captured_warnings import capture_warnings, drain
from afmtool.report.figure_process import FigureProcess
from afmtool.report.images import write_multi_panel_png
capture_warnings()
out = Path(sys.argv[1])
t = np.linspace(0.0, 1e-3, 500)
panels = [{"y_label": "f0' (Hz)", "series": [(t, 3e5 + np.sin(4e3 * t), "REEP", {"color": "C0"})]}]

def warn_and_draw(path):
    warnings.warn("a warning from the figure", UserWarning)
    write_multi_panel_png(path, panels, x_label="time t (s)", title="with a warning")
"""


def _run(tmp_path, body: str) -> subprocess.CompletedProcess:
    script = _PRELUDE + textwrap.dedent(body)
    return subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=120)


def test_the_helper_draws_the_same_png_as_this_process(tmp_path):
    result = _run(tmp_path, """
        with FigureProcess.start() as figures:
            assert figures.forked
            figures.draw(write_multi_panel_png, out / "helper.png", panels, x_label="time t (s)", title="t")
            figures.wait()
        FigureProcess().draw(write_multi_panel_png, out / "here.png", panels, x_label="time t (s)", title="t")
    """)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "helper.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_an_error_in_the_helper_is_raised_here_with_its_type(tmp_path):
    result = _run(tmp_path, """
        from afmtool.runtime.atomic import OutputError
        with FigureProcess.start() as figures:
            figures.draw(write_multi_panel_png, out / "no-such-folder" / "f.png", panels, x_label="t (s)")
            try:
                figures.wait()
            except OutputError as exc:
                print("RAISED", exc)
    """)
    assert result.returncode == 0, result.stderr
    assert "RAISED" in result.stdout and "no-such-folder" in result.stdout


def test_a_warning_in_the_helper_is_recorded_here(tmp_path):
    result = _run(tmp_path, """
        with FigureProcess.start() as figures:
            figures.draw(warn_and_draw, out / "w.png")
            figures.wait()
        print("WARNINGS", drain())
    """)
    assert result.returncode == 0, result.stderr
    assert "UserWarning: a warning from the figure" in result.stdout
    assert (tmp_path / "w.png").is_file()


def test_a_failed_command_kills_the_helper_at_once(tmp_path):
    result = _run(tmp_path, """
        started = time.monotonic()
        try:
            with FigureProcess.start() as figures:
                figures.draw(time.sleep, 60)
                pid = figures._pid
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            pass
        assert time.monotonic() - started < 10
        try:
            os.kill(pid, 0)
            print("ALIVE")
        except ProcessLookupError:
            print("GONE")
    """)
    assert result.returncode == 0, result.stderr
    assert "GONE" in result.stdout


def test_the_helper_leaves_when_the_command_dies(tmp_path):
    result = _run(tmp_path, """
        figures = FigureProcess.start()
        print(figures._pid, flush=True)
        os._exit(0)  # no close: the helper sees its pipe end
    """)
    pid = int(result.stdout.split()[0])
    check = _run(tmp_path, f"""
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                state = Path("/proc/{pid}/stat").read_text().split(") ")[1][0]
            except (FileNotFoundError, IndexError):
                state = "gone"
            if state in ("gone", "Z", "X"):
                break
            time.sleep(0.05)
        print("STATE", state)
    """)
    assert "STATE gone" in check.stdout or "STATE Z" in check.stdout or "STATE X" in check.stdout, check.stdout


def test_with_another_thread_running_figures_are_drawn_here(tmp_path):
    result = _run(tmp_path, """
        import threading
        stop = threading.Event()
        threading.Thread(target=stop.wait).start()
        with FigureProcess.start() as figures:
            print("FORKED", figures.forked)
            figures.draw(write_multi_panel_png, out / "here.png", panels, x_label="t (s)")
            assert (out / "here.png").is_file()  # drawn at once, in this process
        stop.set()
    """)
    assert result.returncode == 0, result.stderr
    assert "FORKED False" in result.stdout


def test_a_failed_run_stops_the_helper_before_its_folder_is_removed(tmp_path):
    # the helper keeps writing into the staging folder; the run fails at once: nothing may be left
    result = _run(tmp_path, """
        from afmtool.runtime.outputs import OutputDir

        def keep_writing(folder, seconds):
            end = time.monotonic() + seconds
            k = 0
            while time.monotonic() < end:
                (folder / f"partial-{k}.png").write_bytes(b"x")
                k += 1

        with FigureProcess.start() as figures:
            try:
                with OutputDir(out / "run") as staged, figures.stopped_on_failure():
                    folder = staged.path("f.png").parent
                    figures.draw(keep_writing, folder, 20.0)
                    deadline = time.monotonic() + 20
                    # until the helper (done with its warm-up) has written enough that removing the
                    # folder takes a while: without the guard it then writes into it meanwhile
                    while len(list(folder.iterdir())) < 2000 and time.monotonic() < deadline:
                        time.sleep(0.01)
                    raise KeyboardInterrupt
            except KeyboardInterrupt:
                pass
        print("LEFT", sorted(p.name for p in out.iterdir()))
    """)
    assert result.returncode == 0, result.stderr
    assert "LEFT []" in result.stdout, result.stdout
