"""``afmtool batch``: one analysis over many captures, in parallel on Dask.

Each input runs as its own ``afmtool COMMAND INPUT --out SUBDIR`` process on
a Dask worker, so a batch result is exactly the single-file result and a
crash in one file cannot take the others down.  A failing input is recorded
with its reason and the batch goes on; ``summary.csv`` has one row per input.
Inputs whose output folder already holds a ``report.json`` whose recorded
input hash still matches the input, and every output file intact, are
skipped (resume).  A JPK force map or QI data file is one input per curve
(``--curve N``, output folders ``NAME_curveN``).
"""

from __future__ import annotations

import csv
import glob
import json
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from afmtool.errors import ConfigError, InputError, one_line
from afmtool.report.json_report import sha256_file
from afmtool.runtime.atomic import write_text_atomic
from afmtool.runtime.run_options import DEFAULTS, RunOptions, applied

__all__ = ["BatchItem", "BatchOutcome", "child_command", "expand_inputs", "plan_batch", "run_one", "headline",
           "write_summary"]

#: Suffixes of the files a folder given as an input contributes: every format afmtool reads.
_CAPTURE_SUFFIXES = (".h5", ".hdf5", ".hdf", ".csv", ".bag", ".ibw", ".jpk-force", ".jpk-qi-series", ".jpk-force-map",
                     ".jpk-qi-data", ".tdms", ".wav", ".mat", ".npz", ".npy", ".txt", ".zip")
#: Suffixes of files that hold many curves: each curve is an input.
_MAP_SUFFIXES = (".jpk-force-map", ".jpk-qi-data")


@dataclass(frozen=True)
class BatchItem:
    """One input of a batch and the subfolder its outputs go to; ``selection`` picks a map's curve (``--curve N``)."""

    source: str
    out_dir: str
    selection: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """The input as summary.csv and the messages name it: its path, and its curve if it is one of a map's."""
        return " ".join([self.source, *self.selection])


@dataclass(frozen=True)
class BatchOutcome:
    """What happened to one input: ``ok``, ``failed`` or ``skipped`` (already complete)."""

    source: str
    out_dir: str
    status: str
    reason: str
    headline: dict
    #: The exit status of the input's run: 2 for bad input, 1 for an internal error, < 0 killed.
    exit_code: int = 0
    #: The run failed on the environment (a full disk, a read-only one), not on the input.
    fault: bool = False


def expand_inputs(patterns: Sequence[str]) -> list[Path]:
    """Files from globs, paths and folders (captures in a folder, ROS2 bag folders as one input)."""
    found: list[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(pattern)) or [pattern]
        for match in matches:
            path = Path(match)
            if path.is_dir() and not (path / "metadata.yaml").is_file():
                found.extend(
                    p for p in sorted(path.iterdir())
                    if p.name.lower().endswith(_CAPTURE_SUFFIXES) or (p / "metadata.yaml").is_file()
                )
            else:
                found.append(path)
    unique = list(dict.fromkeys(found))
    if not unique:
        raise InputError(f"no inputs match {' '.join(patterns)}")
    return unique


def plan_batch(inputs: Sequence[Path], out: Path) -> list[BatchItem]:
    """A distinct output subfolder per input, named after it.

    Inputs are confined to captures: a file, or a ROS2 bag folder; never the
    batch root or anything inside it (an input of ``.`` would otherwise name
    the root itself as its output folder).
    """
    items, used = [], set()
    root = Path(out).resolve()
    for path in inputs:
        real = path.resolve()
        if not (real.is_file() or (real / "metadata.yaml").is_file()):
            raise InputError(f"{path}: not a capture file or a ROS2 bag folder")
        if real == root or root in real.parents or real in root.parents:
            raise InputError(f"{path}: is, holds or lies inside the batch folder {out}; inputs must be elsewhere")
        base = (real.name or "input").replace(".", "_")
        for selection in _selections(path):
            name = f"{base}_curve{selection[1]}" if selection else base
            candidate, k = name, 2
            while candidate in used:
                candidate, k = f"{name}_{k}", k + 1
            used.add(candidate)
            items.append(BatchItem(str(path), str(out / candidate), selection))
    return items


def _selections(path: Path) -> list[tuple[str, ...]]:
    """``[()]`` for a capture; ``[("--curve", "0"), ...]``, one per curve, for a JPK map or QI data file."""
    if not path.name.lower().endswith(_MAP_SUFFIXES):
        return [()]
    from afmtool.errors import SelectionNeeded
    from afmtool.io.registry import open_capture

    try:
        open_capture(path).close()  # a map of one curve opens as that curve
    except SelectionNeeded as exc:
        return [(exc.option, choice) for choice in exc.choices]
    except InputError:
        return [()]  # the run reports what is wrong with it
    return [()]


#: Beside each finished output folder: the sha256 of every file in it, written by the batch.
MANIFEST_SUFFIX = ".outputs.json"


def _manifest_path(item: BatchItem) -> Path:
    out = Path(item.out_dir)
    return out.with_name(f".{out.name}{MANIFEST_SUFFIX}")


def _output_hashes(folder: Path, names: Sequence[str]) -> dict[str, str]:
    return {name: sha256_file(folder / name) for name in names if (folder / name).is_file()}


#: ``options_of(command, source, extra_args)``: the capture options a run of ``afmtool COMMAND SOURCE
#: EXTRA_ARGS`` reads with, or None (the CLI's own option parsing: :func:`afmtool.cli.batch_cmd.capture_options_of`).
OptionsOf = Callable[[Sequence[str], str, Sequence[str]], Any]


def _complete(item: BatchItem, command: Sequence[str] = (), extra_args: Sequence[str] = (),
              options_of: OptionsOf | None = None) -> dict | None:
    """The existing report if the subfolder holds this input's finished result, every file intact.

    Intact means: report.json is for the same input bytes, and every output
    it lists is there with the sha256 the batch recorded when the run ended
    (a file deleted or changed by hand is redone).
    """
    folder = Path(item.out_dir)
    report_path = folder / "report.json"
    if not report_path.is_file() or not Path(item.source).exists():
        return None
    try:
        report = json.loads(report_path.read_text())
        recorded = report["inputs"][0]["hash"]
        names = [str(name) for name in report["outputs"]]
        manifest = json.loads(_manifest_path(item).read_text())
    except (ValueError, KeyError, IndexError, TypeError, OSError, RecursionError):
        return None
    if not _input_unchanged(item.source, recorded, command, extra_args, options_of):
        return None
    if any(not (folder / name).exists() for name in names):
        return None
    return report if manifest == _output_hashes(folder, names) else None


def _input_unchanged(source: str, recorded, command: Sequence[str] = (), extra_args: Sequence[str] = (),
                     options_of: OptionsOf | None = None) -> bool:
    """Whether ``source`` still has the hash its report recorded, by the report's own algorithm.

    A file hash (sha256) is recomputed over the file; a sample hash (XXH3-128,
    :mod:`afmtool.io.provenance`) over the same channels, read through the one
    reader stack with the run's own capture options (``--arg=--invols=50``...,
    ``options_of``, the CLI's parsing of them).  A run made with ``--no-hash`` cannot be checked
    this way and is redone.
    """
    if not isinstance(recorded, dict):
        return False
    try:
        if recorded.get("over") == "file":
            return recorded.get("algorithm") == "sha256" and recorded.get("value") == sha256_file(Path(source))
        from afmtool.io.provenance import hash_matches
        from afmtool.io.stack import CaptureOptions, open_capture

        options = options_of(command, source, extra_args) if command and options_of else None
        with open_capture(source, options or CaptureOptions()) as reader:
            return hash_matches(recorded, reader)
    except (InputError, ConfigError, OSError, ValueError):
        return False


def headline(report: dict) -> dict:
    """summary.csv's headline columns of one run: report.json's headline (:func:`afmtool.report.headline.summary_columns`)."""
    from afmtool.report.headline import summary_columns

    return summary_columns(report)


FAILURE_FILE = "failure.json"


def _known_failure(item: BatchItem) -> tuple[str, int] | None:
    """The recorded reason and exit status if this exact input already failed in an earlier run."""
    path = Path(item.out_dir) / FAILURE_FILE
    if not path.is_file() or not Path(item.source).exists():
        return None
    try:
        record = json.loads(path.read_text())
        if record.get("sha256") != _sha_or_none(item.source):
            return None
        return one_line(str(record["reason"])), int(record.get("exit_code", 2))
    except (ValueError, OSError, KeyError, TypeError, AttributeError, RecursionError):
        return None


def _sha_or_none(source: str) -> str | None:
    try:
        return sha256_file(Path(source))
    except OSError:
        return None


def child_command(command: Sequence[str], item: BatchItem, extra_args: Sequence[str],
                  options: RunOptions = DEFAULTS) -> list[str]:
    """The command line of one input's run: ``afmtool [--max-samples N] [--wait] COMMAND INPUT --out SUBDIR ...``.

    ``options`` are the batch's own ``afmtool --max-samples`` and ``--wait``, given to each run
    explicitly (a Dask worker's environment is not the batch's).
    """
    return [sys.executable, "-m", "afmtool", *options.args(), *command, item.source, "--out", item.out_dir,
            "--quiet", *extra_args]


def run_one(command: Sequence[str], item: BatchItem, extra_args: Sequence[str], retry_failed: bool = False,
            options: RunOptions = DEFAULTS, options_of: OptionsOf | None = None) -> BatchOutcome:
    """Run one input as a separate afmtool process (on whichever worker Dask chose).

    Completed inputs are skipped; an input that failed before with the same
    bytes is reported failed again without rerunning unless ``retry_failed``.
    ``options`` (``afmtool --max-samples``, ``--wait``) apply to the resume check here and to the run;
    ``options_of`` reads the run's own capture options for that check (None: the capture's defaults).
    """
    extra_args = [*item.selection, *extra_args]  # a map's curve: --curve N, for the run and its resume check
    with applied(options):  # the resume check reads the input as the run would
        existing = _complete(item, command, extra_args, options_of)
    if existing is not None:
        return BatchOutcome(item.label, item.out_dir, "skipped", "outputs complete", headline(existing))
    known = None if retry_failed else _known_failure(item)
    if known is not None:
        # the same line as the run that found it: a rerun reports the same result for the same input
        return BatchOutcome(item.label, item.out_dir, "failed", known[0], {}, known[1])
    args = child_command(command, item, extra_args, options)
    _manifest_path(item).unlink(missing_ok=True)
    proc = subprocess.run(args, capture_output=True, text=True)
    if _killed(proc.returncode):
        proc = subprocess.run(args, capture_output=True, text=True)  # once more: OOM killer, a stray signal
    if proc.returncode != 0:
        return _failed(item, proc)
    folder = Path(item.out_dir)
    (folder / FAILURE_FILE).unlink(missing_ok=True)
    report = json.loads((folder / "report.json").read_text())
    write_text_atomic(_manifest_path(item), json.dumps(_output_hashes(folder, report["outputs"])) + "\n")
    return BatchOutcome(item.label, item.out_dir, "ok", "", headline(report))


def _failed(item: BatchItem, proc: subprocess.CompletedProcess) -> BatchOutcome:
    """The outcome of a child that did not succeed; a verdict on the input is recorded for reruns."""
    reason = _reason(proc.stderr, proc.returncode)
    if _is_fault(reason):
        # a full disk is not a verdict on the input: nothing is recorded, the batch stops
        return BatchOutcome(item.label, item.out_dir, "failed", reason, {}, proc.returncode, fault=True)
    if _killed(proc.returncode):
        # not a verdict on the input: the next batch run tries it again
        return BatchOutcome(item.label, item.out_dir, "failed", f"killed by a signal ({reason})", {}, proc.returncode)
    Path(item.out_dir).mkdir(parents=True, exist_ok=True)
    record = {"input": item.source, "sha256": _sha_or_none(item.source), "reason": reason, "exit_code": proc.returncode}
    write_text_atomic(Path(item.out_dir) / FAILURE_FILE, json.dumps(record) + "\n")
    return BatchOutcome(item.label, item.out_dir, "failed", reason, {}, proc.returncode)


def _is_fault(reason: str) -> bool:
    """Whether a child's error line is a fault of the environment (its cause in the words of strerror)."""
    import errno
    import os

    codes = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EROFS, errno.EIO)
    return any(f"({os.strerror(code)})" in reason or reason.endswith(os.strerror(code)) for code in codes)


def _reason(stderr: str, returncode: int) -> str:
    """The child's one error line (its ``afmtool: error:`` line, else its last line), on one line."""
    lines = [line.strip() for line in (stderr or "").splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("afmtool: error: ")]
    reason = (errors or lines or [f"exit status {returncode}"])[-1].removeprefix("afmtool: error: ")
    return one_line(reason)


def _outcome(future, item: BatchItem) -> BatchOutcome:
    """The future's outcome; a task Dask lost (its worker killed, again and again) is a failure of this run only."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001 - whatever ended the task, the batch goes on and reports it
        from afmtool.runtime.faults import environment_fault

        reason = one_line(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)
        fault = environment_fault(exc) is not None  # the worker could not write (a full disk)
        return BatchOutcome(item.label, item.out_dir, "failed", f"worker lost ({reason})", {}, -1, fault=fault)


def _killed(returncode: int) -> bool:
    """A child that a signal ended (negative status) or that was interrupted (130)."""
    return returncode < 0 or returncode == 130


def write_summary(path: Path, outcomes: Sequence[BatchOutcome]) -> None:
    """summary.csv: input, status, reason, output folder, then the headline columns."""
    keys = list(dict.fromkeys(k for o in outcomes for k in o.headline))
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["input", "status", "reason", "output", *keys])
        for o in outcomes:
            writer.writerow([o.source, o.status, one_line(o.reason), o.out_dir, *(o.headline.get(k, "") for k in keys)])


def run_batch(
    command: Sequence[str],
    items: Sequence[BatchItem],
    extra_args: Sequence[str],
    *,
    workers: int,
    scheduler: str | None,
    on_done: Callable[[BatchOutcome], None],
    retry_failed: bool = False,
    scheduler_timeout_s: float = 10.0,
    options: RunOptions = DEFAULTS,
    options_of: OptionsOf | None = None,
) -> list[BatchOutcome]:
    """Submit every item to Dask (a local cluster, or ``scheduler``) and gather outcomes in input order.

    ``options`` (``afmtool --max-samples``, ``--wait``) go to every run on its command line; ``options_of``
    (a module-level function, sent to the workers by reference) to each run's resume check.
    """
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ConfigError("afmtool batch needs Dask: pip install 'afmtool[cluster]'") from None
    cluster = None
    if scheduler:
        from afmtool.io.scheduler import connect_client

        client = connect_client(scheduler, scheduler_timeout_s)
    else:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=50
        )
        client = Client(cluster)
    try:
        futures = {
            client.submit(run_one, list(command), item, list(extra_args), retry_failed, options, options_of,
                          key=f"afmtool-{i}-{item.out_dir}", pure=False): i
            for i, item in enumerate(items)
        }
        outcomes: list[BatchOutcome | None] = [None] * len(items)
        for future in as_completed(futures):
            outcome = _outcome(future, items[futures[future]])
            outcomes[futures[future]] = outcome
            on_done(outcome)
        return [o for o in outcomes if o is not None]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
