"""``afmtool theory controllers`` and the tuning of the raster simulator's gains (issue 14, item 8).

Acceptance at three line rates (8, 12 and 30 Hz; §2.5): the high gain has the least probe-loss area
(§2.2's parachuting, :func:`afmtool.analyses.controllers.classify_loss`), the switching gain's is
within 1.2× of the high gain's, and its peak on-sample force within 1.2× of the low gain's.  At
4 Hz the high and switching gains tie (tests/test_raster.py checks all four rates on shared runs).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from afmtool.sim.raster import RasterParams, run_raster
from tests.conftest import run_cli, validate_report

#: Acceptance tolerance on the two ratios.
TOLERANCE = 1.2


def test_theory_controllers_command(tmp_path):
    out = tmp_path / "controllers"
    result = run_cli("theory", "controllers", "--out", out, "--line-rates", "8,12,30", "--lines", "2",
                     "--figure-lines", "4", "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    results = report["results"]
    print("\nline rate | loss area low / high / switching | peak force (nN) low / high / switching | ratios")
    for row in results["table"]:
        low, high, switching = row["low"], row["high"], row["switching"]
        print(f"{row['line_rate_hz']:5g} Hz | {low['loss_area']:.4f} / {high['loss_area']:.4f} / "
              f"{switching['loss_area']:.4f} | {low['peak_force_n'] * 1e9:.1f} / {high['peak_force_n'] * 1e9:.1f} / "
              f"{switching['peak_force_n'] * 1e9:.1f} | loss S/H {row['loss_ratio_switching_to_high']:.3f}, "
              f"force S/L {row['force_ratio_switching_to_low']:.3f} (tolerance {TOLERANCE})")
        assert high["loss_area"] < min(low["loss_area"], switching["loss_area"])  # the least of the three
        assert switching["loss_area"] <= TOLERANCE * high["loss_area"]
        assert switching["peak_force_n"] <= TOLERANCE * low["peak_force_n"]
        assert switching["loss_area"] < 0.7 * low["loss_area"]  # the switching gain is a real improvement
    assert [row["line_rate_hz"] for row in results["table"]] == [8.0, 12.0, 30.0]
    assert results["pass"] is True and report["warnings"] == []
    assert all(all(c.values()) for c in results["criteria"].values())
    assert results["gains"]["high"] == {"ki_per_s": 1500.0, "kp": 0.5}
    for name in ("ch2_controllers.png", "ch2_loss_force.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out / "ch2_table.json").read_text()) == results["table"]
    assert (out / "config.toml").is_file()


def test_theory_controllers_bad_rates(tmp_path):
    result = run_cli("theory", "controllers", "--out", tmp_path / "x", "--line-rates", "4,fast")
    assert result.returncode == 2
    assert "line_rates_hz" in result.stderr.decode() and "Traceback" not in result.stderr.decode()
    assert not (tmp_path / "x").exists()


def _flat_z_rms(scale: float) -> float:
    """z rms on a flat sample with the high pair scaled by ``scale`` (the loop's own ringing, nm)."""
    base = RasterParams()
    params = dataclasses.replace(base, controller="high", topography="flat", line_rate_hz=30.0, lines=1,
                                 ki_high_per_s=scale * base.ki_high_per_s, kp_high=scale * base.kp_high)
    run = run_raster(params, seed=1)
    start = round(params.scan_start_s * params.sample_rate_hz) + 2000
    return float(np.std(run.z_piezo_nm[start:]))


def test_high_gain_is_tuned_from_the_stability_limit():
    # The default high pair sits at 0.43 of the on-sample stability limit (Ziegler-Nichols, PI 0.45):
    # the loop is quiet at 1x, still stable at 2x and oscillates in a limit cycle at 2.6x.
    quiet, near, beyond = (_flat_z_rms(s) for s in (1.0, 2.0, 2.6))
    print(f"flat-sample z rms: {quiet:.3f} nm at 1x, {near:.3f} nm at 2x, {beyond:.3f} nm at 2.6x the high pair")
    assert quiet < 0.05 and near < 0.1
    assert beyond > 0.3


def test_classify_loss_splits_parachuting_from_lift_off():
    """Loss where the surface fell away (a pit) is probe loss; loss on a level surface is lift-off."""
    import pytest

    from afmtool.analyses.controllers import classify_loss
    from afmtool.errors import ConfigError

    period = 7.07
    n = 400
    contact = np.ones(n, dtype=np.uint8)
    height = np.zeros(n)
    height[100:] = -20.0  # a falling edge at sample 100 ...
    contact[101:140] = 0  # ... and the tip parachutes into the pit for 39 samples
    height[250:] = 0.0  # a rising edge at 250 ...
    contact[260:290] = 0  # ... then the controller pulls the sample off the tip on the level terrace
    contact[330:335] = 0  # a skipped tap (< 1.5 periods) is not loss
    loss = classify_loss(contact, height, period, fall_nm=1.65)
    assert loss.probe_loss.start.tolist() == [101] and loss.probe_loss.end.tolist() == [140]
    assert loss.lift_off.start.tolist() == [260] and loss.lift_off.end.tolist() == [290]
    # a surface that falls by less than the force range does not make it probe loss
    shallow = np.where(height < 0, -1.0, 0.0)
    assert len(classify_loss(contact, shallow, period, fall_nm=1.65).probe_loss) == 0
    with pytest.raises(ConfigError):
        classify_loss(contact, height[:-1], period, fall_nm=1.65)
    with pytest.raises(ConfigError):
        classify_loss(contact, height, period, fall_nm=-1.0)


def test_high_gain_least_probe_loss_over_seeds():
    """Not one seed's luck: at 8 and 12 Hz the high gain's probe-loss area is below the switching gain's
    for other seeds too (by the index's delay and the early switch back, about a drive period per pit)."""
    from afmtool.analyses.controllers import controller_row

    for seed in (2, 3):
        for rate in (8.0, 12.0):
            rows = {c: controller_row(run_raster(RasterParams(controller=c, line_rate_hz=rate, lines=2), seed=seed))
                    for c in ("high", "switching")}
            ratio = rows["switching"].loss_area / rows["high"].loss_area
            print(f"seed {seed}, {rate:g} Hz: probe-loss area high {rows['high'].loss_area:.4f}, "
                  f"switching {rows['switching'].loss_area:.4f} (S/H {ratio:.4f}, tolerance {TOLERANCE})")
            assert 1.0 < ratio <= TOLERANCE
