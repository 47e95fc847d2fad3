"""The hostile-case runner (issue 34): every shape of bad input, environment and peer, counted.

Each case runs ``afmtool`` in a child process, in a folder of its own, and
is classified by what the contract allows:

- ``clean_error``: exit 2, exactly one line on stderr (a ``waiting for input
  on stdin`` notice aside), no traceback;
- ``success``: exit 0;

and what it forbids:

- ``internal``: exit 1 (an internal error on bad input);
- ``hang``: the child outlived the case's time-out (it is killed);
- ``crash``: a signal or any other exit status;
- ``multiline``: exit 2 with more or fewer lines than one, or a traceback;
- ``left_behind``: a failed run left anything in its folder (an output, a
  staging folder, a lock, a temporary file), or a run left a hidden
  temporary entry beside its outputs;
- ``input_modified``: a file that existed before the run changed;
- ``unexpected``: a case that must be refused succeeded, or one that must
  succeed was refused (``expect``).

Run it by hand (the lead's rerun of the counts in the notes)::

    python -m tests.hostile_runner                 # every case, 2 at a time
    python -m tests.hostile_runner --quick         # the CI subset
    python -m tests.hostile_runner --group scheduler --json findings.json

``tests/test_hostile_runner.py`` runs the quick subset in CI and the whole
set under ``-m slow``.  Disk-full cases mount tmpfs (root only; skipped with
the reason elsewhere); scheduler cases listen on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data"
SHARED = REPO.parent / "shared"

FORBIDDEN = ("internal", "hang", "crash", "multiline", "left_behind", "input_modified", "unexpected")
OUTCOMES = ("clean_error", "success", *FORBIDDEN, "skipped")
NOTICE = "afmtool: waiting for input on stdin"


@dataclass
class Case:
    """One hostile case.

    ``argv(folder, ctx)`` gives the arguments after ``afmtool`` (``folder`` is
    the case's own folder; ``ctx`` holds the fixtures, a peer's address, a
    tmpfs mount).  ``prepare(folder, ctx)`` puts inputs into the folder
    before the run, so that a change to them is seen.  ``expect`` is
    ``"error"``, ``"ok"`` or ``"either"``.
    """

    name: str
    group: str
    argv: Callable[[Path, dict], list]
    expect: str = "either"
    prepare: Callable[[Path, dict], None] | None = None
    stdin: Sequence[tuple[float, bytes]] | None = None
    timeout_s: float = 120.0
    quick: bool = False
    tmpfs_bytes: int | None = None
    peer: str | None = None
    hold_lock: str | None = None  # a lock file (relative to the folder) held while the case runs
    check: Callable[[Path, subprocess.CompletedProcess], str | None] | None = None
    env: dict = field(default_factory=dict)
    #: A refusal that keeps outputs by design (a batch with a failed input keeps the others' folders).
    keeps_outputs: bool = False


@dataclass
class Outcome:
    case: str
    group: str
    outcome: str
    returncode: object
    seconds: float
    detail: str = ""


# ------------------------------------------------------------------------------------------ fixtures


def _copy(src: Path, dst: Path) -> Path:
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copyfile(src, dst)
    return dst


def _scaled_capture(path: Path, *, scale: dict[str, float] | None = None, rate: float | None = None) -> Path:
    import h5py

    with h5py.File(SAMPLE / "ltv_step.h5") as src, h5py.File(path, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        if rate is not None:
            dst.attrs["sample_rate_hz"] = rate
        for name in src["channels"]:
            data = src["channels"][name][()] * (scale or {}).get(name, 1.0)
            ds = dst.create_dataset(f"channels/{name}", data=data)
            for key, value in src["channels"][name].attrs.items():
                ds.attrs[key] = value
    return path


def _labone_export(folder: Path) -> list[Path]:
    import numpy as np

    folder.mkdir()
    rows = "\n".join(f"0;{10**9 + i * 3000};{np.sin(i / 5.0):.17g};{np.cos(i / 5.0):.17g}" for i in range(300))
    files = []
    for n in range(2):
        sample = folder / f"dev1234_demods_0_sample_{n:05d}.csv"
        sample.write_text("chunk;timestamp;x;y\n" + rows + "\n")
        header = folder / f"dev1234_demods_0_sample_header_{n:05d}.csv"
        header.write_text('chunk;history_name;clockbase;createdtimestamp\n0;"sample";60000000;123\n')
        files += [sample, header]
    return files


def make_fixtures(folder: Path) -> dict:
    """Inputs shared by the cases (read-only: cases that may write near an input copy it first)."""
    import h5py
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    fx = {"cap": SAMPLE / "ltv_step.h5", "fc": SAMPLE / "tapping_force_curve.h5", "raster": SAMPLE / "raster_grating.h5",
          "bits": SAMPLE / "bits_30khz.h5"}
    for label, scale in (("tiny_all_310", 1e-310), ("tiny_all_170", 1e-170), ("tiny_all_100", 1e-100)):
        fx[label] = _scaled_capture(folder / f"{label}.h5", scale={"deflection": scale, "dither": scale})
    fx["tiny_defl_300"] = _scaled_capture(folder / "tiny_defl_300.h5", scale={"deflection": 1e-300})
    fx["tiny_dither_300"] = _scaled_capture(folder / "tiny_dither_300.h5", scale={"dither": 1e-300})
    fx["huge_values"] = _scaled_capture(folder / "huge_values.h5", scale={"deflection": 1e300, "dither": 1e300})
    fx["rate_1e12"] = _scaled_capture(folder / "rate_1e12.h5", rate=1e12)
    fx["rate_1e-3"] = _scaled_capture(folder / "rate_1e-3.h5", rate=1e-3)
    for label, rate in (("rate_subnormal", 5e-324), ("rate_1e-310", 1e-310), ("rate_1e308", 1e308), ("rate_1e-300", 1e-300)):
        path = folder / f"{label}.h5"
        with h5py.File(path, "w") as f:
            f.attrs["sample_rate_hz"] = rate
            f.create_dataset("channels/deflection", data=np.sin(np.arange(5000) / 7.0)).attrs["units"] = "nm"
        fx[label] = path
    no_meta = folder / "no_free_air.h5"
    with h5py.File(SAMPLE / "ltv_step.h5") as src, h5py.File(no_meta, "w") as dst:
        dst.attrs["sample_rate_hz"] = src.attrs["sample_rate_hz"]
        for name in src["channels"]:
            dst.create_dataset(f"channels/{name}", data=src["channels"][name][()]).attrs["units"] = src["channels"][name].attrs.get("units", "")
    fx["no_free_air"] = no_meta
    deep = folder / "deep_meta.h5"
    _copy(SAMPLE / "ltv_step.h5", deep)
    with h5py.File(deep, "a") as f:
        f.attrs["metadata"] = "[" * 100_000 + "]" * 100_000
    fx["deep_meta"] = deep
    claim = folder / "huge_claim.h5"
    with h5py.File(claim, "w") as f:
        f.attrs["sample_rate_hz"] = 1e6
        f.create_dataset("channels/deflection", shape=(10**15,), dtype="f8", chunks=(4096,)).attrs["units"] = "nm"
    fx["huge_claim"] = claim
    if (SHARED / "fixtures" / "capture_v1_ros2_mcap").is_dir():
        fx["mcap_bag"] = SHARED / "fixtures" / "capture_v1_ros2_mcap"
    formats = SHARED / "data" / "formats"
    if formats.is_dir():
        fx["jpk"] = formats / "fmt-jpk-fd_spot3-0192.jpk-force"
        fx["tdms"] = formats / "raw1.tdms"
    bad = folder / "corrupt.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    fx["corrupt"] = bad
    return _Fixtures(folder, fx)


class _Fixtures(dict):
    """The fixtures; the output folders some cases read (``free_air_dir``, ``reep_fc``) are made when first asked for."""

    _MADE = {
        "free_air_dir": ("fa", "free_air.json", ["identify", "freeair", str(SAMPLE / "ltv_step.h5")]),
        "reep_fc": ("reep_fc", "report.json", ["reep", str(SAMPLE / "tapping_force_curve.h5")]),
    }

    def __init__(self, folder: Path, items: dict) -> None:
        super().__init__(items)
        self._folder = folder
        self._lock = threading.Lock()

    def for_case(self) -> _Fixtures:
        """A copy a case may add to (its tmpfs, its peer), sharing the lock that makes the folders once."""
        copy = _Fixtures(self._folder, self)
        copy._lock = self._lock
        return copy

    def __missing__(self, key: str) -> Path:
        if key not in self._MADE:
            raise KeyError(key)
        name, marker, args = self._MADE[key]
        with self._lock:
            out = self._folder / name
            if not (out / marker).is_file():
                _afmtool([*args, "--out", str(out), "-q"], timeout=600)
            self[key] = out
        return out


def _afmtool(args: list[str], **kwargs) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "afmtool", *args], capture_output=True, env=env, cwd=REPO, **kwargs)


# ------------------------------------------------------------------------------------------ running


def _tree(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 (files) or "dir"/"link", of everything under ``folder``."""
    found = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = Path(root, name)
            rel = str(path.relative_to(folder))
            if path.is_symlink():
                found[rel] = "link:" + os.readlink(path)
            elif path.is_dir():
                found[rel] = "dir"
            else:
                try:
                    found[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
                except OSError:
                    found[rel] = "unreadable"
    return found


def _hidden_leftovers(tree: dict[str, str]) -> list[str]:
    return [p for p in tree if any(part.startswith(".") and (".tmp-" in part or ".staging-" in part or ".old-" in part
                                                              or part.endswith(".lock")) for part in Path(p).parts)]


def _feed(fd: int, parts: Sequence[tuple[float, bytes]]) -> threading.Thread:
    def run() -> None:
        try:
            for delay, data in parts:
                time.sleep(delay)
                os.write(fd, data)
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                os.close(fd)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def _mount(where: Path, size: int) -> str | None:
    where.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={max(size, 4096)}", "tmpfs", str(where)], capture_output=True)
    return None if done.returncode == 0 else f"cannot mount a tmpfs ({done.stderr.decode().strip()})"


def _classify(result: subprocess.CompletedProcess | None, expect: str) -> tuple[str, str]:
    if result is None:
        return "hang", ""
    stderr = result.stderr.decode(errors="replace")
    lines = [line for line in stderr.splitlines() if line.strip() and line.strip() != NOTICE]
    code = result.returncode
    last = lines[-1][:300] if lines else ""
    if code == 1:
        return "internal", last
    if code not in (0, 2):
        return "crash", f"exit {code}: {last}"
    if code == 2 and (len(lines) != 1 or "Traceback" in stderr):
        return "multiline", " | ".join(line[:150] for line in lines[:4])
    if code == 0 and "Traceback" in stderr:
        return "multiline", "traceback on a success"
    if expect == "error" and code == 0:
        return "unexpected", "succeeded; must be refused"
    if expect == "ok" and code != 0:
        return "unexpected", f"refused; must succeed: {last}"
    return ("success" if code == 0 else "clean_error"), last


def run_case(case: Case, root: Path, fixtures: dict) -> Outcome:
    folder = root / case.name.replace("/", "_").replace(" ", "_")
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    ctx = fixtures.for_case() if isinstance(fixtures, _Fixtures) else dict(fixtures)
    with contextlib.ExitStack() as stack:
        if case.tmpfs_bytes is not None:
            mnt = folder / "mnt"
            reason = _mount(mnt, case.tmpfs_bytes)
            if reason is not None:
                return Outcome(case.name, case.group, "skipped", None, 0.0, reason)
            stack.callback(subprocess.run, ["umount", "-l", str(mnt)], capture_output=True)
            ctx["mnt"] = mnt
        if case.peer is not None:
            from tests.hostile_peers import HostilePeer

            peer = stack.enter_context(HostilePeer(case.peer, lifetime_s=case.timeout_s + 30))
            ctx["scheduler"] = peer.address
        if case.prepare is not None:
            case.prepare(folder, ctx)
        if case.hold_lock is not None:
            handle = stack.enter_context(open(folder / case.hold_lock, "wb"))
            fcntl.flock(handle, fcntl.LOCK_EX)
        before = _tree(folder)
        argv = [str(a) for a in case.argv(folder, ctx)]
        start = time.monotonic()
        result = _run(argv, case, folder)
        took = time.monotonic() - start
        if case.hold_lock is not None:
            before.pop(case.hold_lock, None)
        after = _tree(folder)
        if case.hold_lock is not None:
            after.pop(case.hold_lock, None)
    outcome, detail = _classify(result, case.expect)
    if outcome in ("success", "clean_error"):
        extra = _post_checks(case, result, before, after, folder)
        if extra is not None:
            outcome, detail = extra
    return Outcome(case.name, case.group, outcome, None if result is None else result.returncode, round(took, 2), detail)


def _post_checks(case, result, before, after, folder) -> tuple[str, str] | None:
    changed = [p for p, digest in before.items() if after.get(p) != digest and digest != "dir"]
    if changed:
        return "input_modified", ", ".join(changed[:4])
    if result.returncode != 0 and not case.keeps_outputs:
        created = sorted(set(after) - set(before))
        if created:
            return "left_behind", ", ".join(created[:4])
    else:
        hidden = _hidden_leftovers({p: d for p, d in after.items() if p not in before})
        if hidden:
            return "left_behind", ", ".join(hidden[:4])
    if case.check is not None:
        problem = case.check(folder, result)
        if problem:
            return "unexpected", problem
    return None


def _run(argv: list[str], case: Case, folder: Path) -> subprocess.CompletedProcess | None:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), **case.env)
    env.pop("AFMTOOL_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "afmtool", *argv], cwd=folder, env=env,
                            stdin=subprocess.PIPE if case.stdin is not None else subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    feeder = None
    if case.stdin is not None:
        feeder = _feed(os.dup(proc.stdin.fileno()), case.stdin)
        proc.stdin.close()
        proc.stdin = None
    try:
        out, err = proc.communicate(timeout=case.timeout_s)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, 9)
        proc.communicate()
        return None
    finally:
        if feeder is not None:
            feeder.join(timeout=1)
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def run_cases(cases: Sequence[Case], root: Path, fixtures: dict, jobs: int = 2,
              progress: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Every case (``jobs`` at a time, in their own folders under ``root``); outcomes in case order."""
    def one(case: Case) -> Outcome:
        try:
            outcome = run_case(case, root, fixtures)
        except Exception as exc:  # noqa: BLE001 - a runner fault is reported as the case's, not lost
            outcome = Outcome(case.name, case.group, "crash", None, 0.0, f"runner: {type(exc).__name__}: {exc}")
        if progress is not None:
            progress(outcome)
        return outcome

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        return list(pool.map(one, cases))


def counts(outcomes: Sequence[Outcome]) -> dict[str, int]:
    tally = Counter(o.outcome for o in outcomes)
    return {name: tally.get(name, 0) for name in OUTCOMES}


def table(outcomes: Sequence[Outcome]) -> str:
    groups = sorted({o.group for o in outcomes}, key=[o.group for o in outcomes].index)
    head = ["group", *OUTCOMES]
    rows = [[g, *(str(counts([o for o in outcomes if o.group == g])[k]) for k in OUTCOMES)] for g in groups]
    rows.append(["all", *(str(counts(outcomes)[k]) for k in OUTCOMES)])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from tests.hostile_cases import all_cases

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the CI subset")
    parser.add_argument("--group", action="append", help="only these groups (repeatable)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--json", type=Path, help="write every outcome here")
    parser.add_argument("--keep", type=Path, help="run in this folder and keep it")
    args = parser.parse_args(argv)
    cases = [c for c in all_cases() if (not args.quick or c.quick) and (not args.group or c.group in args.group)]
    root = args.keep or Path(tempfile.mkdtemp(prefix="afmtool-hostile-"))
    start = time.monotonic()
    try:
        fixtures = make_fixtures(root / "_fixtures")

        def show(o: Outcome) -> None:
            mark = "!!" if o.outcome in FORBIDDEN else "  "
            print(f"{mark} {o.outcome:14s} {o.seconds:6.1f}s  {o.group:10s} {o.case}  {o.detail[:140]}", flush=True)

        outcomes = run_cases(cases, root / "cases", fixtures, args.jobs, show)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    print(f"\n{len(outcomes)} cases in {time.monotonic() - start:.0f} s\n")
    print(table(outcomes))
    if args.json:
        args.json.write_text(json.dumps([o.__dict__ for o in outcomes], indent=1, default=str) + "\n")
    return 1 if any(o.outcome in FORBIDDEN for o in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
