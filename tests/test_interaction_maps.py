"""Interaction quantities in REEP's force-curve tables and scan images (issue 17 item 1 outputs).

The expected table and image entries are recomputed here from the per-sample
series reep.h5 holds (``/interaction/*``, ``flag``, ``z``, ``t``) by plain
numpy: a sample counts where its fit is not flagged (and, for force curves,
after the warm-up), in the z bin or pixel it falls in.  The same mask must
also reproduce the existing f0' table, so it is REEP's own.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmtool.models.interaction import InteractionQuantities
from afmtool.report.images import read_gsf
from tests.conftest import SAMPLE_DATA, run_cli

NAMES = tuple(InteractionQuantities.units())


def _run(capture: Path, out: Path) -> dict:
    result = run_cli("reep", capture, "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode(errors="replace")
    return json.loads(result.stdout)


def _approach_bins(z: np.ndarray, z_bin: float) -> tuple[np.ndarray, np.ndarray]:
    """(approach mask, bin index): the direction is the sign of the last non-zero z step."""
    step = np.sign(np.diff(z, prepend=np.nan))
    step[~np.isfinite(step)] = 0
    direction = step.copy()
    for i in range(1, len(direction)):  # hold the direction through flat stretches
        if direction[i] == 0:
            direction[i] = direction[i - 1]
    first = direction[np.flatnonzero(direction)[0]]
    return direction == first, np.floor(z / z_bin).astype(np.int64)


def test_force_curve_tables_hold_the_binned_interaction_series(tmp_path):
    report = _run(SAMPLE_DATA / "tapping_force_curve.h5", tmp_path / "reep")  # has k = 2 N/m in its metadata
    results = report["results"]
    assert results["interaction"]["written"] is True
    fs, warmup = results["sample_rate_hz"], results["summary_after_warmup_samples"]
    z_bin = report["parameters"]["z_bin"]
    with h5py.File(tmp_path / "reep" / "reep.h5") as f:
        table = f["force_curve/approach"]
        z, t, flag = f["z"][()], f["t"][()], f["flag"][()]
        approach, index = _approach_bins(z, z_bin)
        use = approach & (flag == 0) & (np.rint(t * fs) >= warmup)
        centres = table["z"][()]
        bins = np.floor(centres / z_bin).astype(np.int64)
        worst = {}
        for name in ("f0_hz", *NAMES):
            series = f["f0_hz"][()] if name == "f0_hz" else f["interaction"][name][()]
            assert table[name].attrs["units"] == ("Hz" if name == "f0_hz" else InteractionQuantities.units()[name])
            ok = use & np.isfinite(series)
            expected = np.array([series[ok & (index == b)].mean() for b in bins])
            got = table[name][()]
            scale = np.nanmax(np.abs(expected))
            worst[name] = float(np.nanmax(np.abs(got - expected)) / scale)
            assert np.isfinite(got).sum() >= 10
            # the table is binned in the stream (float64), the series read back are float32 (issue 33)
            np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7 * scale)
        print("largest relative table error per quantity:", {k: f"{v:.1e}" for k, v in worst.items()})
        # the approach goes into contact: the force gradient changes along it, in N/m
        gradient = table["force_gradient_n_per_m"][()]
        assert np.nanmax(gradient) - np.nanmin(gradient) > 0.01


def _pixel_means(t: np.ndarray, values: np.ndarray, scan: dict, direction: int) -> np.ndarray:
    """Per-pixel means for one direction, from the scan metadata (trace first in each line)."""
    lines, pixels = int(scan["lines"]), int(scan["pixels_per_line"])
    # as ImageAccumulator rounds: elapsed time over the line period (a row at a pixel edge lands alike)
    elapsed = (t - float(scan.get("start_s", 0.0))) / (1.0 / float(scan["line_rate_hz"]))
    line = np.floor(elapsed).astype(np.int64)
    fraction = elapsed - line
    position = np.where(fraction >= 0.5, 2.0 - 2.0 * fraction, 2.0 * fraction)
    pixel = np.minimum((position * pixels).astype(np.int64), pixels - 1)
    keep = (elapsed >= 0) & (line < lines) & ((fraction >= 0.5) == bool(direction)) & np.isfinite(values)
    image = np.full((lines, pixels), np.nan)
    for row in range(lines):
        for col in range(pixels):
            sel = keep & (line == row) & (pixel == col)
            if sel.any():
                image[row, col] = values[sel].mean()
    return image


@pytest.fixture(scope="module")
def raster_outputs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("interaction-raster")
    capture = root / "raster_k.h5"
    shutil.copy(SAMPLE_DATA / "raster_grating.h5", capture)
    with h5py.File(capture, "r+") as f:  # k set explicitly (the bundled capture carries 2 N/m too)
        metadata = json.loads(f.attrs["metadata"])
        metadata["cantilever"]["spring_constant_n_per_m"] = 2.5
        f.attrs["metadata"] = json.dumps(metadata)
    _run(capture, root / "reep")
    return root


def test_raster_images_and_gsf_hold_the_binned_interaction_series(raster_outputs):
    out = raster_outputs / "reep"
    with h5py.File(raster_outputs / "raster_k.h5") as f:
        scan = json.loads(f.attrs["metadata"])["scan"]
    with h5py.File(out / "reep.h5") as f:
        t, flag = f["t"][()], f["flag"][()]
        assert (flag != 0).any(), "the raster capture should have flagged samples to leave out"
        for name in NAMES:
            units = InteractionQuantities.units()[name]
            series = np.where(flag == 0, f["interaction"][name][()], np.nan)
            for direction, label in enumerate(("trace", "retrace")):
                ds = f[f"images/{name}/{label}"]
                assert ds.attrs["units"] == units
                expected = _pixel_means(t, series, scan, direction)
                # pixels binned in the stream (float64) against float32 series read back (issue 33)
                np.testing.assert_allclose(ds[()], expected, rtol=1e-6, atol=1e-7 * np.nanmax(np.abs(expected)))
                gsf = read_gsf(out / f"{name}_{label}.gsf")
                assert gsf.header["ZUnits"] == units and gsf.header["XYUnits"] == "m"
                assert gsf.data.shape == (int(scan["lines"]), int(scan["pixels_per_line"]))
                # top row first in the file: the last line scanned (float32 on disk)
                np.testing.assert_allclose(gsf.data, expected[::-1].astype(np.float32), rtol=1e-6, equal_nan=True)
                assert (out / f"{name}_{label}.png").stat().st_size > 1000
        k_e = f["images/k_e_n_per_m/trace"][()]
        assert np.nanmedian(k_e) == pytest.approx(2.5, rel=0.05)  # k (f0'/f0)^2, with the k given


def test_raster_without_k_writes_no_interaction_images(tmp_path):
    capture = tmp_path / "raster_no_k.h5"
    shutil.copy(SAMPLE_DATA / "raster_grating.h5", capture)
    with h5py.File(capture, "r+") as f:
        metadata = json.loads(f.attrs["metadata"])
        del metadata["cantilever"]["spring_constant_n_per_m"]
        f.attrs["metadata"] = json.dumps(metadata)
    report = _run(capture, tmp_path / "reep")
    assert "spring constant" in report["results"]["interaction"]["reason"]
    assert sorted(p.name for p in (tmp_path / "reep").glob("*.gsf")) == sorted(
        f"{q}_{d}.gsf" for q in ("f0_hz", "q", "amplitude", "phase_deg", "height") for d in ("trace", "retrace"))
    with h5py.File(tmp_path / "reep" / "reep.h5") as f:
        assert "interaction" not in f and "k_e_n_per_m" not in f["images"]


def test_raster_keeps_its_on_sample_pixels(raster_outputs):
    """Issue 27 item 3: ≥ 90 % of the on-sample pixels of the f0' and energy images hold a value (not NaN).

    A pixel is on the sample where the simulator's truth has the probe on it
    (``/truth/switch`` = 0, probe loss 1) for most of the pixel's time; σ̂²
    rising in tapping is no longer a flag, so these pixels keep their numbers.
    """
    with h5py.File(raster_outputs / "raster_k.h5") as f:
        scan = json.loads(f.attrs["metadata"])["scan"]
        fs = float(f.attrs["sample_rate_hz"])
        lost = f["truth/switch"][()].astype(float)
    t_all = np.arange(lost.size) / fs
    with h5py.File(raster_outputs / "reep" / "reep.h5") as f:
        for direction, label in enumerate(("trace", "retrace")):
            on_sample = _pixel_means(t_all, lost, scan, direction) < 0.5
            assert on_sample.sum() >= 10
            for name in ("f0_hz", "energy_per_cycle_ev"):
                image = f[f"images/{name}/{label}"][()]
                kept = float(np.isfinite(image[on_sample]).mean())
                print(f"{name} {label}: {kept:.1%} of {on_sample.sum()} on-sample pixels kept")
                assert kept >= 0.90
    # issue 27 item 1: the report gives the scan's resolution: the distance the tip covers while f0' settles
    settling = json.loads((raster_outputs / "reep" / "report.json").read_text())["results"]["settling"]
    speed = 2.0 * scan["scan_size_m"] * scan["line_rate_hz"]  # trace and retrace in one line period
    assert settling["window_us"] == pytest.approx(400.0)
    assert settling["scan_speed_m_per_s"] == pytest.approx(speed)
    assert settling["spatial_resolution_m"] == pytest.approx(speed * settling["f0_settling_10_90_s"])
    assert settling["spatial_resolution_pixels"] == pytest.approx(
        settling["spatial_resolution_m"] / (scan["scan_size_m"] / scan["pixels_per_line"]))
