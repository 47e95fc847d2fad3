"""Zarr captures (issue 30, item 2): read like any file, and by ranges on a Dask cluster.

A capture is written as Zarr the way a notebook would (``Capture.to_xarray().to_zarr``):
to a local folder and to an fsspec ``memory://`` store.  It must read back
sample for sample, and REEP split over a two-worker local Dask cluster, whose
workers read their own chunks and warm-ups from the store (the tasks carry
sample indices only), must equal the sequential run.  ``memory://`` lives in
one process, so its cluster runs its workers as threads of this process
(``processes=False``); the folder's cluster uses worker processes.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.io.registry import open_capture
from afmtool.pipeline import Split
from tests.conftest import SAMPLE_DATA, run_cli
from tests.test_split import _run, assert_same_run


def _write_zarr(capture_path, store: str) -> None:
    import afmtool

    ds = afmtool.open(capture_path).to_xarray()
    ds.to_zarr(store, mode="w", encoding={name: {"chunks": (8192,)} for name in ds.data_vars})


def _samples(path):
    with open_capture(path) as reader:
        blocks = list(reader.blocks(list(reader.info.channel_names), 5000))
        return reader.info, {c: np.concatenate([b.data[c] for b in blocks]) for c in reader.info.channel_names}


@pytest.mark.parametrize("where", ["folder", "memory"])
def test_a_zarr_capture_reads_back_sample_for_sample(tmp_path, where):
    store = str(tmp_path / "ltv.zarr") if where == "folder" else f"memory://i30/{tmp_path.name}/ltv.zarr"
    _write_zarr(SAMPLE_DATA / "ltv_step.h5", store)
    info, data = _samples(store)
    expected_info, expected = _samples(SAMPLE_DATA / "ltv_step.h5")
    assert info.format == "zarr" and info.sample_rate_hz == expected_info.sample_rate_hz
    assert {c.name: c.units for c in info.channels} == {c.name: c.units for c in expected_info.channels}
    assert info.capture_metadata.free_air == expected_info.capture_metadata.free_air
    for name, values in expected.items():
        np.testing.assert_array_equal(data[name], values)
    with open_capture(store) as reader:
        np.testing.assert_array_equal(reader.ranges().read(["deflection"], 7000, 9000)["deflection"],
                                      expected["deflection"][7000:9000])


def test_a_missing_store_is_one_line(tmp_path):
    from afmtool.errors import InputError

    with pytest.raises(InputError, match="not a readable Zarr store"):
        open_capture(f"memory://i30/{tmp_path.name}/nothing.zarr")


@pytest.fixture(scope="module")
def long_ltv_h5(tmp_path_factory):
    path = tmp_path_factory.mktemp("zarr_split") / "ltv.h5"
    result = run_cli("simulate", "ltv", "-o", path, "--set", "duration_s=0.3", "--set", "step_time_s=0.15")
    assert result.returncode == 0, result.stderr
    return path


@pytest.mark.long
@pytest.mark.parametrize("where", ["folder", "memory"])
def test_split_on_a_dask_cluster_reads_a_zarr_capture_by_ranges(where, long_ltv_h5, tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    import afmtool.pipeline as pipeline

    store = str(tmp_path / "ltv.zarr") if where == "folder" else f"memory://i30/{tmp_path.name}/ltv.zarr"
    _write_zarr(long_ltv_h5, store)
    sent = []
    executor = pipeline._executor

    def spying(split):
        submit, close = executor(split)

        def record(fn, /, *args):
            sent.append((fn.__name__, [a for a in args if isinstance(a, np.ndarray) or hasattr(a, "data")]))
            return submit(fn, *args)

        return record, close

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=(where == "folder"),
                                       protocol="tcp://", dashboard_address=None, host="127.0.0.1")
    try:
        _, sequential = _run("reep", long_ltv_h5, tmp_path, None)
        monkeypatch.setattr(pipeline, "_executor", spying)
        _, split = _run("reep", store, tmp_path, Split(jobs=2, scheduler=cluster.scheduler_address))
    finally:
        cluster.close()
    assert_same_run(split, sequential)
    assert len(sent) > 2
    assert all(name == "_estimate_from_ranges" and not samples for name, samples in sent)
