"""Numeric edges (issue 34): sample counts from flags and TOML, empty figures, channels too small to regress on.

The CLI runs of these shapes are cases of the hostile runner
(``tests/hostile_cases.py``, group ``numeric``); these are the in-process checks.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from afmtool.errors import ConfigError, InputError


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, -1.0, 1e308, 2e15])
def test_a_time_that_is_no_sample_count_is_refused_naming_the_parameter(value):
    from afmtool.config.samples import sample_count

    with pytest.raises(ConfigError, match=r"^warmup_s=.* samples"):
        sample_count(value, 1e6, "warmup_s")


def test_sample_counts_in_range():
    from afmtool.config.samples import MAX_SAMPLES, sample_count

    assert sample_count(0.01, 5e5, "x") == 5000
    assert sample_count(1e-9, 5e5, "x", minimum=1) == 1
    assert sample_count(2.0001, 1.0, "x", ceil=True) == 3
    assert sample_count(MAX_SAMPLES / 1e6, 1e6, "x") == MAX_SAMPLES
    with pytest.raises(ConfigError, match="per drive period"):
        sample_count(1e300, 7.0, "rms_window_periods", per="drive period")


def test_an_interval_past_the_capture_or_past_any_capture():
    from afmtool.config.samples import interval_samples

    assert interval_samples((0.0, 0.01), 5e5, "--free-air", 25_000) == (0, 5000)
    with pytest.raises(InputError, match=r"--free-air 0:1 s ends at sample 500,000, past the capture's 25,000 samples"):
        interval_samples((0.0, 1.0), 5e5, "--free-air", 25_000)
    with pytest.raises(ConfigError, match=r"--free-air 0:1e\+308: END=1e\+308 is inf samples"):
        interval_samples((0.0, 1e308), 5e5, "--free-air", 25_000)
    with pytest.raises(ConfigError, match="START"):
        interval_samples((1e300, 1e301), 5e5, "--free-air")


def test_a_simulation_of_1e308_seconds_is_refused_before_anything_is_allocated():
    from afmtool import sim

    with pytest.raises(ConfigError, match="duration_s=1e\\+308"):
        sim.simulate("ltv", {"duration_s": 1e308}, seed=1)


def test_read_free_air_refuses_an_end_beyond_any_capture():
    from afmtool.analyses.freeair_source import read_free_air
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.chunks import iter_chunks
    from afmtool.io.memory import ArrayReader

    reader = ArrayReader(5e5, [ChannelSpec("deflection"), ChannelSpec("dither")],
                         {"deflection": np.zeros(1000), "dither": np.zeros(1000)})
    chunks = iter_chunks(reader, reader.info.channel_names, 256)
    with pytest.raises(ConfigError, match="END=1e\\+308"):  # was OverflowError: cannot convert float infinity
        read_free_air(reader, chunks, (0.0, 1e308), ("deflection", "dither"))


# -- figures with nothing to draw -----------------------------------------------------------------


@pytest.mark.parametrize("panels", [[], [{"y_label": "f0'", "series": []}],
                                    [{"y_label": "f0'", "series": [(np.zeros(0), np.zeros(0), "none")]}]])
def test_a_figure_with_nothing_to_draw_is_skipped_with_a_warning(tmp_path, panels):
    from afmtool.report.figure_process import FigureSkippedWarning
    from afmtool.report.images import write_multi_panel_png

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        write_multi_panel_png(tmp_path / "f.png", panels, x_label="t (s)")
    assert [w.category for w in seen] == [FigureSkippedWarning]
    assert "f.png not drawn: nothing to draw" in str(seen[0].message)
    assert list(tmp_path.iterdir()) == []


def test_a_figure_that_is_wrong_is_still_an_error(tmp_path):
    from afmtool.report.images import write_multi_panel_png

    with pytest.raises(ValueError, match="unknown keys"):
        write_multi_panel_png(tmp_path / "f.png", [{"series": [([0, 1], [0, 1], "x")], "colour": "red"}], x_label="t")


def test_a_skipped_figure_is_not_listed_among_the_outputs(tmp_path):
    from afmtool.report.figure_process import FigureProcess
    from afmtool.report.images import write_line_plot_png
    from afmtool.runtime.outputs import OutputDir

    with OutputDir(tmp_path / "out") as staged, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        figures = FigureProcess()  # drawn in this process
        figures.draw(write_line_plot_png, staged.path("empty.png"), [], x_label="x", y_label="y", title="")
        staged.path("report.json").write_text("{}")
        assert staged.names == ("report.json",)


# -- channels too small for a regression ----------------------------------------------------------


@pytest.mark.parametrize("scale", [1e-310, 1e-200, 1e-160])
def test_a_channel_whose_squares_underflow_is_refused_with_its_scale(scale):
    from afmtool.estimators.rls import identify_arx

    rng = np.random.default_rng(34)
    dither = np.sin(np.arange(4000) * 0.87) + np.sin(np.arange(4000) * 0.91) + np.sin(np.arange(4000) * 0.95)
    deflection = rng.normal(size=4000) * scale
    with pytest.raises(InputError, match=r"deflection: RMS [0-9.e+-]+ .* below 1e-150: its squares underflow") as refused:
        identify_arx(deflection, dither)
    assert f"{scale:.3g}"[:3] in str(refused.value) or "RMS 0" not in str(refused.value)


def test_channel_rms_does_not_underflow():
    from afmtool.estimators._common import channel_rms

    assert channel_rms(np.full(10, 1e-310)) == pytest.approx(1e-310, rel=1e-6)
    assert channel_rms(np.array([3e200, -4e200])) == pytest.approx(math.sqrt(12.5) * 1e200)
    assert channel_rms(np.zeros(3)) == 0.0
