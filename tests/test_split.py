"""One capture split across cores or Dask workers gives the sequential result (issue 19, item 1).

Each command runs in process twice on the same capture, cut into small chunks
so that many chunks start from a fresh state a warm-up early: sequentially,
and split over two local threads or a local two-worker Dask cluster (worker
processes, so the kernels really travel by pickle).  Every float series of
the output file must agree to 1e-9 relative (against the series' own scale
where a value crosses zero), every integer series and every decoded bit exactly.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from afmtool.config import resolve_from
from afmtool.io.registry import open_capture
from afmtool.pipeline import Split, lead_start
from tests.conftest import REPO, run_cli

RTOL = 1e-9
CHUNK = 16384
SAMPLE = REPO / "sample_data"


def _series(path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_run(split_path, sequential_path) -> None:
    split, sequential = _series(split_path), _series(sequential_path)
    assert split.keys() == sequential.keys()
    for name, expected in sequential.items():
        actual = split[name]
        assert actual.shape == expected.shape, name
        if expected.dtype.kind == "f" and expected.size:
            scale = np.nanmax(np.abs(expected)) if np.isfinite(expected).any() else 0.0
            np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=RTOL * scale, equal_nan=True, err_msg=name)
        else:
            np.testing.assert_array_equal(actual, expected, err_msg=name)


def _run(command: str, capture, tmp_path, split: Split | None, **flags):
    """The command's analysis in process into ``tmp_path/<tag>.h5``; returns (result, path)."""
    from afmtool.io.matrix_results import MatrixResultWriter
    from afmtool.io.results import ResultWriter

    tag = "sequential" if split is None else f"split{split.jobs}{'dask' if split.scheduler else ''}"
    path = tmp_path / f"{command}_{tag}.h5"
    with open_capture(capture) as reader:
        if command == "reep":
            from afmtool.analyses.reep import SERIES_UNITS, run_reep
            from afmtool.config.params import ReepParams

            params = resolve_from(ReepParams, "reep", {"reep": {"chunk_samples": CHUNK}}, flags)
            with ResultWriter(path, SERIES_UNITS, {}) as writer:
                return run_reep(reader, params, writer, split=split), path
        if command == "probeloss":
            from afmtool.analyses.probeloss import SERIES_UNITS, run_probeloss
            from afmtool.config.params import ProbeLossParams

            params = resolve_from(ProbeLossParams, "probeloss", {"probeloss": {"chunk_samples": CHUNK}}, flags)
            with ResultWriter(path, SERIES_UNITS, {}) as writer:
                return run_probeloss(reader, params, writer, split=split), path
        if command == "decode":
            from afmtool.analyses.decode import SERIES_UNITS, run_decode
            from afmtool.config.params import DecodeParams

            params = resolve_from(DecodeParams, "decode", {"decode": {"chunk_samples": CHUNK}}, flags)
            with ResultWriter(path, SERIES_UNITS, {}) as writer:
                return run_decode(reader, params, writer, split=split), path
        from afmtool.analyses.kalman_bank import SERIES_UNITS, run_kalman_bank
        from afmtool.config.params import KalmanBankParams

        params = resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"chunk_samples": CHUNK}}, flags)
        with MatrixResultWriter(path, SERIES_UNITS, {}) as writer:
            return run_kalman_bank(reader, params, writer, split=split), path


@pytest.fixture(scope="module")
def long_ltv(tmp_path_factory):
    """0.3 s at 500 kHz (150,000 samples, ten chunks) with an f0/Q step in the middle."""
    path = tmp_path_factory.mktemp("split") / "ltv.h5"
    result = run_cli("simulate", "ltv", "-o", path, "--set", "duration_s=0.3", "--set", "step_time_s=0.15")
    assert result.returncode == 0, result.stderr
    return path


@pytest.fixture(scope="module")
def reference_capture(tmp_path_factory):
    """0.1 s from tests/reference_sim.py (continuous three-sine drive, a step in f0 and Q): four chunks of 16,384 samples."""
    from tests import reference_sim as rs

    f0, q = 70e3, 200.0
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=500e3, duration_s=0.1,
                      drive=rs.three_sine(f0, 6000.0, 20.0 / q, 0.5), noise_nm=0.05, seed=5, free_air_s=0.02,
                      f0_of_t=lambda t: np.where(t < 0.05, f0, f0 - 350.0), q_of_t=lambda t: np.where(t < 0.05, q, q - 30.0))
    return rs.write_capture_h5(tmp_path_factory.mktemp("split_ref") / "reference.h5", cap)


CASES = {
    "reep": (lambda ltv: ltv, {}),
    "reep-offset": (lambda ltv: SAMPLE / "force_curve_thesis.h5", {"static_offset": True}),
    "probeloss": (lambda ltv: SAMPLE / "raster_grating.h5", {}),
    "decode": (lambda ltv: SAMPLE / "bits_30khz.h5", {"bit_rate_hz": 30000.0}),
    "kalman-bank": (lambda ltv: SAMPLE / "force_curve_thesis.h5", {}),
}


def test_split_equals_sequential_on_a_reference_capture(reference_capture, tmp_path):
    """The same check on a capture afmtool did not simulate (continuous drive, tests/reference_sim.py)."""
    _, sequential_path = _run("reep", reference_capture, tmp_path, None)
    _, split_path = _run("reep", reference_capture, tmp_path, Split(jobs=2))
    assert_same_run(split_path, sequential_path)
    _, sequential_path = _run("probeloss", reference_capture, tmp_path, None, f0_hz=70e3, q=200.0)
    _, split_path = _run("probeloss", reference_capture, tmp_path, Split(jobs=2), f0_hz=70e3, q=200.0)
    assert_same_run(split_path, sequential_path)
    # the coherent index's phasor is anchored at each chunk's stream position
    coherent = {"f0_hz": 70e3, "q": 200.0, "index": "coherent", "window_periods": 1.5}
    _, sequential_path = _run("probeloss", reference_capture, tmp_path, None, **coherent)
    _, split_path = _run("probeloss", reference_capture, tmp_path, Split(jobs=2), **coherent)
    assert_same_run(split_path, sequential_path)


@pytest.mark.parametrize("case", sorted(CASES))
def test_split_on_two_threads_equals_sequential(case, long_ltv, tmp_path, monkeypatch):
    import afmtool.pipeline as pipeline

    capture_of, flags = CASES[case]
    command = case.removesuffix("-offset")
    capture = capture_of(long_ltv)
    sequential, sequential_path = _run(command, capture, tmp_path, None, **flags)
    passes = []
    run_split = pipeline._run_split
    monkeypatch.setattr(pipeline, "_run_split", lambda *args: passes.append(1) or run_split(*args))
    split, split_path = _run(command, capture, tmp_path, Split(jobs=2), **flags)
    assert len(passes) == (2 if command == "kalman-bank" else 1)  # every pass really ran split
    assert_same_run(split_path, sequential_path)
    if command == "decode":  # the bits themselves are compared exactly in the files
        assert split.results.bits == sequential.results.bits
        assert split.results.ekf.bit_stream_innovation_rms_nm == pytest.approx(
            sequential.results.ekf.bit_stream_innovation_rms_nm, rel=RTOL)
    if command == "kalman-bank":
        for key in ("held_samples", "samples_compared"):
            assert getattr(split.results.adaptive, key) == getattr(sequential.results.adaptive, key)
        assert split.results.adaptive.fraction_lowest == pytest.approx(
            sequential.results.adaptive.fraction_lowest, rel=RTOL)
        assert split.verdict.passed == sequential.verdict.passed


def test_a_split_run_really_splits(long_ltv, tmp_path, monkeypatch):
    """The chunks' kernels run on worker threads, each with a warm-up before it (not the carried state)."""
    import threading

    from afmtool.analyses.reep import ReepKernels

    calls = []
    original = ReepKernels.estimate

    def spy(self, lead, chunk):
        calls.append((threading.current_thread().name, None if lead is None else (lead.start, len(lead)), chunk.start))
        return original(self, lead, chunk)

    monkeypatch.setattr(ReepKernels, "estimate", spy)
    _run("reep", long_ltv, tmp_path, Split(jobs=2))
    assert len(calls) == -(-150_000 // CHUNK)
    assert all(name.startswith("afmtool-split") for name, _, _ in calls)
    assert calls[0][1] is None and calls[0][2] == 0  # the first chunk starts the stream, as sequentially
    for _, (lead_first, lead_n), start in calls[1:]:
        assert lead_first + lead_n == start and lead_n > 0


def test_lead_start_sits_on_the_decimation_grid():
    assert lead_start(0, 5000, 7) == 0
    assert lead_start(3000, 5000, 7) == 0  # a chunk near the start is warmed from sample 0: exact
    first = lead_start(100_000, 5000, 7)
    assert first % 7 == 0 and 100_000 - 5000 - 7 < first <= 100_000 - 5000


@pytest.fixture(scope="module")
def dask_cluster():
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                       host="127.0.0.1")
    yield cluster.scheduler_address
    cluster.close()


@pytest.mark.long
@pytest.mark.parametrize("case", ["reep", "probeloss", "decode", "kalman-bank"])
def test_split_on_a_two_worker_dask_cluster_equals_sequential(case, long_ltv, tmp_path, dask_cluster):
    capture_of, flags = CASES[case]
    capture = capture_of(long_ltv)
    sequential, sequential_path = _run(case, capture, tmp_path, None, **flags)
    split, split_path = _run(case, capture, tmp_path, Split(jobs=2, scheduler=dask_cluster), **flags)
    assert_same_run(split_path, sequential_path)
    if case == "decode":
        assert split.results.bits == sequential.results.bits


def test_cli_jobs_and_scheduler(long_ltv, tmp_path):
    """--jobs 1 and the default (all cores) write the same numbers; an unreachable scheduler is one line, exit 2."""
    one = run_cli("reep", long_ltv, "--out", tmp_path / "one", "--jobs", "1", "-q")
    every = run_cli("reep", long_ltv, "--out", tmp_path / "all", "-q")
    assert one.returncode == 0 and every.returncode == 0, (one.stderr, every.stderr)
    assert_same_run(tmp_path / "all" / "reep.h5", tmp_path / "one" / "reep.h5")
    bad = run_cli("reep", long_ltv, "--out", tmp_path / "bad", "--scheduler", "tcp://127.0.0.1:9", "-q")
    assert bad.returncode == 2
    assert len(bad.stderr.decode().strip().splitlines()) == 1 and "Dask scheduler" in bad.stderr.decode()
    assert not (tmp_path / "bad").exists()


@pytest.mark.long
def test_dask_workers_read_their_own_samples(long_ltv, tmp_path, dask_cluster, monkeypatch):
    """On a cluster the tasks carry sample indices only, and the run still equals the sequential one."""
    import afmtool.pipeline as pipeline

    sent = []
    executor = pipeline._executor

    def spying(split):
        submit, close = executor(split)

        def record(fn, /, *args):
            sent.append((fn.__name__, [a for a in args if isinstance(a, np.ndarray) or hasattr(a, "data")]))
            return submit(fn, *args)

        return record, close

    monkeypatch.setattr(pipeline, "_executor", spying)
    capture_of, flags = CASES["reep"]
    _, sequential_path = _run("reep", capture_of(long_ltv), tmp_path, None, **flags)
    _, split_path = _run("reep", capture_of(long_ltv), tmp_path, Split(jobs=2, scheduler=dask_cluster), **flags)
    assert_same_run(split_path, sequential_path)
    assert len(sent) > 2
    assert all(name == "_estimate_from_ranges" and not samples for name, samples in sent)
