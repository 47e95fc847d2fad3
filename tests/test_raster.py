"""Scenario ``raster``: the closed-loop scan simulator and the ch. 2 reproduction (issue 4).

The in-loop instrument is checked against afmtool's own estimators run
offline on the recorded channels (lock-in, observer window RMS), the
topographies against their definitions, and the three controllers against
the thesis's claims (§2.5): the acceptance table over the grating line rates.
Simulations are cached in module-scoped fixtures.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from afmtool import sim
from afmtool.analyses.controllers import ch2_table, height_image, write_controller_png
from afmtool.errors import ConfigError
from afmtool.estimators.lockin import LockIn
from afmtool.estimators.observer import ObserverState, observer_update
from afmtool.io.metadata import validate_metadata
from afmtool.sim.raster import CONTROLLERS, RasterParams, run_raster, topography_nm
from tests.raster_cache import TABLE_RATES_HZ
from tests.raster_cache import table_runs as _table_runs


@pytest.fixture(scope="module")
def short_run():
    """One switching-gain line at 12 Hz: the in-loop signals beside their offline twins."""
    return run_raster(RasterParams(line_rate_hz=12.0, lines=1, pixels_per_line=32), seed=5)


@pytest.fixture(scope="module")
def table_runs():
    """The three controllers at 4, 8, 12 and 30 Hz on the grating, two lines each (shared with test_probeloss)."""
    return _table_runs()


def test_in_loop_amplitude_is_afmtools_lockin(short_run):
    """The controller's amplitude is LockIn.process applied to the recorded deflection."""
    params = short_run.params
    lockin = LockIn(params.f0_hz, params.sample_rate_hz, params.lowpass_hz(), params.lockin_order)
    blocks, _ = lockin.process(short_run.deflection_nm, lockin.initial_state(1))
    np.testing.assert_allclose(short_run.amplitude_nm, blocks[0].amplitude, rtol=0, atol=1e-12)


def test_in_loop_index_is_the_observer_window_rms(short_run):
    """The switching signal's RMS equals observer_update on the recorded channels, bit for bit."""
    state = ObserverState.initial(short_run.design, short_run.window_samples)
    step = observer_update(state, short_run.deflection_nm, short_run.dither_v)
    np.testing.assert_array_equal(short_run.rms_nm, step.block.rms)


def test_closest_approach_is_the_contact_truth(short_run):
    """closest_nm is t_s at the step boundaries where contact is read: contact iff t_s < d somewhere."""
    d = short_run.params.force().d_nm
    np.testing.assert_array_equal(short_run.contact, (short_run.closest_nm < d).astype(np.uint8))
    # and it is the tip's lowest point: about l − A on the free-air hold (sample retracted 30 nm beyond A0)
    params = short_run.params
    free = slice(int(0.5 * params.free_air_s * params.sample_rate_hz), int(params.free_air_s * params.sample_rate_hz))
    assert np.min(short_run.closest_nm[free]) == pytest.approx(params.retract_nm, abs=0.5)


def test_chunk_size_does_not_change_the_run(short_run):
    other = run_raster(short_run.params, seed=5, chunk_samples=4099)
    for name in ("deflection_nm", "z_piezo_nm", "amplitude_nm", "force_n", "switch", "contact", "closest_nm"):
        np.testing.assert_array_equal(getattr(other, name), getattr(short_run, name), err_msg=name)


def test_free_air_hold_is_free_and_identifies_the_model(short_run):
    """No contact during the free-air hold; the ARX fit of it finds the true cantilever."""
    from afmtool.estimators.free_air_fit import free_air_from_segment

    params = short_run.params
    n_free = round(params.free_air_s * params.sample_rate_hz)
    assert not short_run.contact[:n_free].any()
    model = free_air_from_segment(short_run.deflection_nm[:n_free], short_run.dither_v[:n_free],
                                  params.sample_rate_hz)
    print(f"identified f0 {model.f0_hz:.1f} Hz (true {params.f0_hz}), Q {model.q:.1f} (true {params.q}), "
          f"gain {model.gain:.4f}")
    assert model.f0_hz == pytest.approx(params.f0_hz, abs=2.0)
    assert model.q == pytest.approx(params.q, rel=0.03)
    # free amplitude at the drive: amplitude_nm (the held dither's sinc is compensated)
    settled = short_run.amplitude_nm[n_free // 2:n_free]
    assert np.mean(settled) == pytest.approx(params.amplitude_nm, rel=0.01)


def test_scenario_metadata_builds_images():
    captured = sim.simulate("raster", {"lines": 1, "line_rate_hz": 30.0, "pixels_per_line": 16}, seed=2)
    meta = validate_metadata(dict(captured.metadata))
    scan = meta["scan"]
    assert (scan["lines"], scan["pixels_per_line"], scan["scan_size_m"], scan["line_rate_hz"]) == (1, 16, 10e-6, 30.0)
    assert scan["trace_retrace"] is True and scan["start_s"] == pytest.approx(0.022)
    assert meta["free_air"] == {"start_s": 0.0, "end_s": 0.01}
    assert meta["controller"]["setpoint_nm"] == pytest.approx(21.0)
    assert set(captured.truth) == {"contact", "force_n", "topography_nm", "separation_nm", "switch"}
    assert captured.channel_names == ("dither", "deflection", "z_piezo", "amplitude")
    assert captured.n_samples == round((0.022 + 1 / 30.0) * 500e3)


def test_grating_topography():
    params = RasterParams(grating_wall_m=0.0)
    pitch = params.grating_pitch_m
    y_pit, y_flat = 0.5 * pitch, 0.1 * pitch
    x = np.array([0.1, 0.3, 0.5, 0.7, 0.8, 1.5]) * pitch
    np.testing.assert_array_equal(topography_nm(params, x, y_pit), [0.0, -20.0, -20.0, -20.0, 0.0, -20.0])
    np.testing.assert_array_equal(topography_nm(params, x, y_flat), np.zeros(6))
    sloped = RasterParams()  # 100 nm walls: half depth 50 nm inside the edge
    edge = 0.25 * pitch + 0.5 * sloped.grating_wall_m
    assert topography_nm(sloped, edge, y_pit) == pytest.approx(-10.0)


def test_dna_strands_are_1p4_nm_ridges():
    from afmtool.sim.raster import _dna_strands

    params = RasterParams(topography="dna", scan_size_m=1e-6, line_rate_hz=30.0, lines=8, pixels_per_line=8,
                          y_offset_m=0.0)
    strands = _dna_strands(params, seed=3)
    assert strands.shape == (params.dna_strands, 3)
    x0, y0, angle = strands[0]
    along = np.array([-50e-9, 0.0, 50e-9])
    heights = topography_nm(params, x0 + along * np.cos(angle), y0 + along * np.sin(angle), strands)
    np.testing.assert_allclose(heights, 1.4, rtol=1e-12)
    # FWHM: half height at ± dna_width_m / 2 across the strand (another strand may not be nearer)
    half = topography_nm(params, x0 + 0.5 * params.dna_width_m * np.sin(angle),
                         y0 - 0.5 * params.dna_width_m * np.cos(angle), strands)
    assert half == pytest.approx(0.7, rel=1e-6)


def test_dna_scan_at_30_hz_runs_and_shows_strands():
    """A 30 Hz DNA scan: the strands raise the truth topography under the tip; the loop stays engaged."""
    params = RasterParams(topography="dna", scan_size_m=1e-6, line_rate_hz=30.0, lines=4, pixels_per_line=32,
                          y_offset_m=0.0)
    run = run_raster(params, seed=3)
    start = round(params.scan_start_s * params.sample_rate_hz)
    assert run.topography_nm[start:].max() == pytest.approx(1.4, abs=0.05)
    assert 0.02 < np.mean(run.topography_nm[start:] > 0.1) < 0.5
    assert run.contact[start:].mean() > 0.1  # tapping, not parachuting


def test_validation():
    with pytest.raises(ConfigError, match="index_on"):
        RasterParams(index_on=1.0)
    with pytest.raises(ConfigError, match="controller"):
        sim.simulate("raster", {"controller": "medium"})
    with pytest.raises(ConfigError, match="engage"):
        run_raster(RasterParams(engage_s=0.001, lines=1, line_rate_hz=30.0), seed=0)


def test_ch2_table_switching_gain(table_runs, tmp_path):
    """Thesis §2.5 at 4, 8, 12 (grating) and 30 Hz: switching loses like the high gain, presses like the low."""
    rows = ch2_table(TABLE_RATES_HZ, runs=table_runs)
    print("\nline rate | probe-loss area low / high / switching | lift-off area low / high / switching"
          " | peak force (nN) low / high / switching | ratios")
    for row in rows:
        print(f"{row.line_rate_hz:5g} Hz | {row.low.loss_area:.4f} / {row.high.loss_area:.4f} / "
              f"{row.switching.loss_area:.4f} | {row.low.lift_off_area:.4f} / {row.high.lift_off_area:.4f} / "
              f"{row.switching.lift_off_area:.4f} | {row.low.peak_force_n * 1e9:.1f} / {row.high.peak_force_n * 1e9:.1f}"
              f" / {row.switching.peak_force_n * 1e9:.1f} | loss S/H {row.loss_ratio_to_high:.4f}, "
              f"force S/L {row.force_ratio_to_low:.3f}")
    (tmp_path / "ch2_table.json").write_text(json.dumps([r.record().to_json() for r in rows], indent=2))
    for row in rows:
        assert row.high.loss_area < row.low.loss_area, row  # the high gain loses contact less (issue 14, item 8)
        assert row.switching.loss_area <= 1.2 * row.high.loss_area, row
        assert row.switching.peak_force_n <= 1.2 * row.low.peak_force_n, row
        if row.line_rate_hz >= 8.0:
            # the high gain has the least probe-loss area: while lost the switching gain runs the high gain
            # too, and loses one drive period or so per pit to the index's delay and the early switch back
            assert row.high.loss_area < row.switching.loss_area, row
        else:
            # 4 Hz: the two tie within seed-to-seed noise (0.3 %); §2.5 calls them "comparable" there
            assert row.loss_ratio_to_high == pytest.approx(1.0, abs=0.01), row
        # and it is a real improvement on the low gain, the thesis's point: by 30 % at the grating rates
        # of §2.5 (4-12 Hz) and at 30 Hz (the thesis's DNA rate, here on the 20 nm grating at 600 um/s)
        assert row.switching.loss_area < 0.7 * row.low.loss_area, row
        # what the high gain has instead (§2.5, "on sample ringing"): after each rising edge it overshoots
        # and pulls the sample off the tip, which the switching gain's on-sample low gain does not
        if row.line_rate_hz >= 8.0:
            assert row.high.lift_off_area > 1.3 * max(row.switching.lift_off_area, row.low.lift_off_area, 1e-3), row


def test_ch2_table_can_fail(table_runs):
    """The same table with the switching run replaced by the low gain's breaks the loss criterion."""
    swapped = {rate: {**runs, "switching": runs["low"]} for rate, runs in table_runs.items()}
    rows = ch2_table(TABLE_RATES_HZ, runs=swapped)
    assert any(row.switching.loss_area > 1.2 * row.high.loss_area for row in rows)


def test_side_by_side_png_of_the_three_controllers(table_runs, tmp_path):
    runs = table_runs[8.0]
    path = tmp_path / "controllers.png"
    write_controller_png(path, runs)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    images = {c: height_image(runs[c]) for c in CONTROLLERS}
    assert all(img.shape == (2, runs["low"].params.pixels_per_line) for img in images.values())
    # pits read about 20 nm below the terraces with every controller (the high gain overshoots the edges)
    for img in images.values():
        assert np.nanpercentile(img, 95) - np.nanpercentile(img, 5) == pytest.approx(20.0, abs=3.0)


def test_shipped_ch2_figure_exists():
    """The figure of docs/ is the one ``afmtool theory controllers --lines 4 --figure-lines 48`` writes."""
    from tests.conftest import REPO

    png = REPO / "docs" / "ch2_controllers.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = json.loads((REPO / "docs" / "ch2_table.json").read_text())
    assert [row["line_rate_hz"] for row in table] == list(TABLE_RATES_HZ)


def test_raster_params_replace_keeps_validation():
    with pytest.raises(ConfigError):
        dataclasses.replace(RasterParams(), sample_rate_hz=100e3)
