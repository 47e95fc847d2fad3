"""Image and plot writers, and atomic output: GSF bytes, Gwyddion, PNG, failure cleanup."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.report.images import (
    APPROACH_STYLE,
    NAN_COLOUR,
    PNG_DPI,
    RETRACT_STYLE,
    _lateral_scale,
    _si_scale,
    _z_scale,
    read_gsf,
    write_gsf,
    write_image_png,
    write_line_plot_png,
    write_multi_panel_png,
    write_side_by_side_png,
)
from afmtool.runtime.atomic import (
    OutputError,
    PendingPath,
    atomic_path,
    write_bytes_atomic,
    write_text_atomic,
)

MAGIC = b"Gwyddion Simple Field 1.0\n"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _split_gsf(raw: bytes, n_values: int) -> tuple[bytes, bytes, bytes]:
    """(header text after the magic line, padding, data), the data start found from the file size."""
    data_start = len(raw) - 4 * n_values
    text_end = raw.index(b"\0")
    return raw[len(MAGIC) : text_end], raw[text_end:data_start], raw[data_start:]


def _ramp(ny: int = 96, nx: int = 128) -> np.ndarray:
    """Heights rising along x from 0 to 10 nm, the same in every row."""
    return np.tile(np.linspace(0.0, 1e-8, nx), (ny, 1))


def _listing(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


# --------------------------------------------------------------------------- GSF


@pytest.mark.parametrize("title", ["", "a", "ab", "abc", "abcd"])
def test_gsf_bytes_exact(tmp_path, rng, title):
    image = rng.standard_normal((3, 5)) * 1e-9
    image[1, 2] = np.nan
    path = tmp_path / "s.gsf"
    write_gsf(path, image, 2.5e-6, 1.5e-6, z_units="m", title=title)
    raw = path.read_bytes()

    assert raw.startswith(MAGIC)
    text, padding, data = _split_gsf(raw, image.size)
    expected_lines = ["XRes = 5", "YRes = 3", "XReal = 2.5e-06", "YReal = 1.5e-06", "XYUnits = m", "ZUnits = m"]
    if title:
        expected_lines.append(f"Title = {title}")
    assert text.decode("utf-8") == "".join(line + "\n" for line in expected_lines)
    assert 1 <= len(padding) <= 4 and padding == b"\0" * len(padding)
    assert (len(MAGIC) + len(text) + len(padding)) % 4 == 0
    assert data == image.astype("<f4").tobytes()


def test_gsf_padding_takes_every_length(tmp_path):
    seen = set()
    for n in range(1, 5):
        path = tmp_path / f"{n}.gsf"
        write_gsf(path, np.ones((2, 2)), 1e-6, 1e-6, title="t" * n)
        seen.add(len(_split_gsf(path.read_bytes(), 4)[1]))
    assert seen == {1, 2, 3, 4}


def test_gsf_round_trip(tmp_path, rng):
    image = rng.standard_normal((7, 11))
    image[0, 0] = np.nan
    x_real = 1e-6 / 3  # needs all 17 digits to read back exactly
    path = tmp_path / "r.gsf"
    write_gsf(path, image, x_real, 2e-7, xy_units="m", z_units="V", title="Δf₀ map, µV")
    gsf = read_gsf(path)
    assert float(gsf.header["XReal"]) == x_real
    assert gsf.header["ZUnits"] == "V"
    assert gsf.header["Title"] == "Δf₀ map, µV"
    assert gsf.data.dtype == np.float32 and gsf.data.shape == (7, 11)
    np.testing.assert_array_equal(gsf.data, image.astype(np.float32))
    assert gsf.data[0, 1] == np.float32(image[0, 1])  # top row first, row-major


def test_gsf_leaves_input_alone(tmp_path, rng):
    image = rng.standard_normal((4, 4))
    before = image.copy()
    image.setflags(write=False)
    write_gsf(tmp_path / "p.gsf", image, 1e-6, 1e-6)
    np.testing.assert_array_equal(image, before)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"image": np.zeros(4)}, "2-D"),
        ({"image": np.zeros((0, 3))}, "2-D"),
        ({"image": np.zeros((2, 2), complex)}, "real"),
        ({"x_real_m": 0.0}, "x_real_m"),
        ({"y_real_m": np.nan}, "y_real_m"),
        ({"title": "two\nlines"}, "title"),
        ({"z_units": " m"}, "z_units"),
        ({"image": np.array([[1e39, 0.0]])}, "float32"),
    ],
)
def test_gsf_rejects_bad_arguments(tmp_path, kwargs, message):
    args = {"image": np.zeros((2, 2)), "x_real_m": 1e-6, "y_real_m": 1e-6, "title": "", "z_units": "m"}
    args.update(kwargs)
    path = tmp_path / "bad.gsf"
    with pytest.raises(ValueError, match=message):
        write_gsf(path, args.pop("image"), args.pop("x_real_m"), args.pop("y_real_m"), **args)
    assert _listing(tmp_path) == []


def test_read_gsf_rejects_bad_files(tmp_path):
    good = tmp_path / "g.gsf"
    write_gsf(good, np.zeros((2, 3)), 1e-6, 1e-6)
    raw = good.read_bytes()
    cases = {"magic": b"Gwyddion Simple Field 2.0\n" + raw[len(MAGIC) :], "short": raw[:-1], "long": raw + b"\0"}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError):
            read_gsf(tmp_path / name)
    with pytest.raises(InputError, match="no such file"):
        read_gsf(tmp_path / "missing.gsf")


# --------------------------------------------------------------------------- Gwyddion

needs_gwyddion = pytest.mark.skipif(
    shutil.which("gwyddion-thumbnailer") is None, reason="gwyddion-thumbnailer is not installed"
)


def _thumbnail(tmp_path: Path, gsf: Path) -> np.ndarray:
    """Render ``gsf`` with Gwyddion's own loader; RGB floats in [0, 1]."""
    import matplotlib.image

    png = gsf.with_suffix(".thumb.png")
    env = dict(os.environ, HOME=str(tmp_path))  # keep Gwyddion's settings out of the real home
    proc = subprocess.run(
        ["gwyddion-thumbnailer", "gnome2", "256", str(gsf), str(png)],
        capture_output=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    assert png.is_file() and png.stat().st_size > 0
    return matplotlib.image.imread(png)[..., :3]


@needs_gwyddion
def test_gwyddion_reads_ramp(tmp_path):
    path = tmp_path / "ramp.gsf"
    write_gsf(path, _ramp(), 1e-6, 0.75e-6, title="ramp")
    rgb = _thumbnail(tmp_path, path)
    brightness = rgb.mean(axis=(0, 2))  # per column, along the ramp
    assert np.all(np.diff(brightness) >= -1e-6)
    assert brightness[-1] - brightness[0] > 0.5


@needs_gwyddion
def test_gwyddion_masks_nan(tmp_path):
    # Gwyddion 2.62 replaces NaN pixels on import and masks them; the
    # thumbnailer draws the mask in red over grey data.
    image = _ramp()
    image[30:60, 40:80] = np.nan
    path = tmp_path / "holes.gsf"
    write_gsf(path, image, 1e-6, 0.75e-6)
    rgb = _thumbnail(tmp_path, path)
    if rgb.shape[:2] != image.shape:
        pytest.skip(f"thumbnail resized to {rgb.shape[:2]}; pixel check needs 1:1")
    red_excess = rgb[..., 0] - rgb[..., 1]
    assert np.all(red_excess[35:55, 45:75] > 0.2)
    assert np.all(np.abs(red_excess[:25]) < 0.02)


# --------------------------------------------------------------------------- PNG


def _read_png(path: Path) -> np.ndarray:
    import matplotlib.image

    assert path.read_bytes()[:8] == PNG_SIGNATURE
    return matplotlib.image.imread(path)


def _count_colour(rgba: np.ndarray, hex_colour: str) -> int:
    target = np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255
    return int(np.all(np.abs(rgba[..., :3] - target) < 1 / 512, axis=-1).sum())


def test_image_png(tmp_path, rng):
    image = 1e-9 * rng.standard_normal((64, 80))
    path = tmp_path / "topo.png"
    write_image_png(path, image, 5e-6, 4e-6, z_units="m", title="Topography", z_label="height")
    rgba = _read_png(path)
    height, width = rgba.shape[:2]
    assert 600 <= width <= 1500 and 400 <= height <= 1200
    assert _listing(tmp_path) == ["topo.png"]


def test_image_png_top_row_at_top(tmp_path):
    image = np.zeros((40, 40))
    image[:20] = 1.0  # top half high: yellow in viridis, bottom half purple
    path = tmp_path / "o.png"
    write_image_png(path, image, 1e-6, 1e-6, z_units="V", title="", cmap="viridis")
    rgba = _read_png(path)
    yellow = np.argwhere((rgba[..., 0] > 0.95) & (rgba[..., 2] < 0.2))[:, 0]
    purple = np.argwhere((rgba[..., 1] < 0.05) & (rgba[..., 2] > 0.3))[:, 0]
    assert yellow.size > 1000 and purple.size > 1000
    assert np.median(yellow) < np.median(purple)


def test_image_png_shows_nan_in_grey(tmp_path, rng):
    image = rng.standard_normal((50, 50))
    holes = image.copy()
    holes[10:40, 10:40] = np.nan
    for name, data in (("full.png", image), ("holes.png", holes)):
        write_image_png(tmp_path / name, data, 1e-6, 1e-6, z_units="m", title="t")
    grey_full = _count_colour(_read_png(tmp_path / "full.png"), NAN_COLOUR)
    grey_holes = _count_colour(_read_png(tmp_path / "holes.png"), NAN_COLOUR)
    assert grey_holes - grey_full > 20_000


@pytest.mark.parametrize("fill", [np.nan, 3.0])
def test_image_png_degenerate_images(tmp_path, fill):
    path = tmp_path / "d.png"
    write_image_png(path, np.full((8, 8), fill), 1e-6, 1e-6, z_units="m", title="flat")
    _read_png(path)


def test_side_by_side_png(tmp_path, rng):
    images = [(rng.standard_normal((32, 32)) * 1e-9, name) for name in ("PI", "Kalman", "LMS")]
    images.append((rng.standard_normal((16, 16)) * 1e-9, "coarse"))
    path = tmp_path / "cmp.png"
    write_side_by_side_png(path, images, 2e-6, 2e-6, z_units="m", suptitle="Controllers", z_label="height")
    rgba = _read_png(path)
    assert rgba.shape[1] > 2 * rgba.shape[0]  # a row of panels


def test_line_plot_png(tmp_path):
    z = np.linspace(0, 50, 200)
    path = tmp_path / "line.png"
    series = [(z, np.exp(-z / 5), "approach", APPROACH_STYLE), (z, np.exp(-z / 6), "retract", RETRACT_STYLE)]
    write_line_plot_png(path, series, x_label="z (nm)", y_label="A (nm)", title="t", markers=[(5.0, "contact")])
    assert _read_png(path).shape[:2] == (round(4.2 * PNG_DPI), round(7.0 * PNG_DPI))


def test_multi_panel_png(tmp_path):
    z = np.linspace(0, 50, 200)
    panels = [
        {"y_label": "f0' (Hz)", "series": [(z, z, "approach", APPROACH_STYLE), (z, z + 1, "retract", RETRACT_STYLE)]},
        {"y_label": "Q'", "series": [(z, np.sqrt(z), "approach", APPROACH_STYLE)], "title": "quality factor"},
        {"y_label": "A (nm)", "series": [(z, np.full_like(z, np.nan), "")]},
        {"y_label": "phase (deg)", "series": [(z, -z, "")]},
    ]
    path = tmp_path / "curve.png"
    write_multi_panel_png(path, panels, x_label="z (nm)", title="Force curve", markers=[(4.0, "contact")])
    assert _read_png(path).shape[:2] == (round((1.9 * 4 + 1.1) * PNG_DPI), round(7.0 * PNG_DPI))


def test_plot_arguments_are_checked(tmp_path):
    z = np.arange(3.0)
    with pytest.raises(ValueError, match="unknown keys"):
        write_multi_panel_png(tmp_path / "p.png", [{"series": [(z, z, "")], "ylabel": "typo"}])
    with pytest.raises(ValueError, match="one length"):
        write_line_plot_png(tmp_path / "p.png", [(z, z[:2], "")], x_label="", y_label="", title="")
    with pytest.raises(ValueError, match="style keys"):
        write_line_plot_png(tmp_path / "p.png", [(z, z, "", {"colour": "r"})], x_label="", y_label="", title="")
    with pytest.raises(ValueError, match="cmap"):
        write_image_png(tmp_path / "p.png", np.eye(3), 1e-6, 1e-6, z_units="m", title="", cmap="nope")
    with pytest.raises(ValueError, match="z_range"):
        write_image_png(tmp_path / "p.png", np.eye(3), 1e-6, 1e-6, z_units="m", title="", z_range=(1, 0))
    with pytest.raises(OutputError, match=".png suffix"):
        write_image_png(tmp_path / "p.jpg", np.eye(3), 1e-6, 1e-6, z_units="m", title="")
    assert _listing(tmp_path) == []


def test_png_writer_failure_leaves_nothing(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    def broken_savefig(self, fname, **kwargs):
        Path(fname).write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", broken_savefig)
    with pytest.raises(KeyboardInterrupt):
        write_image_png(tmp_path / "i.png", np.eye(3), 1e-6, 1e-6, z_units="m", title="")
    assert _listing(tmp_path) == []


@pytest.mark.parametrize(
    ("max_abs", "units", "expected"),
    [
        (3e-9, "m", (1e9, "nm")),
        (2.5e-6, "m", (1e6, "µm")),
        (999e-12, "m", (1e12, "pm")),
        (1.0, "V", (1.0, "V")),
        (1.2e3, "Hz", (1e-3, "kHz")),
        (0.05, "deg", (1.0, "deg")),
        (0.0, "m", (1.0, "m")),
    ],
)
def test_si_scale(max_abs, units, expected):
    factor, prefixed = _si_scale(max_abs, units)
    assert prefixed == expected[1]
    assert factor == pytest.approx(expected[0], rel=1e-12)


def test_lateral_units_follow_scan_size():
    assert _lateral_scale(5e-6, 5e-6) == (1e6, "µm")
    assert _lateral_scale(1e-6, 2e-7) == (1e6, "µm")
    assert _lateral_scale(500e-9, 500e-9) == (1e9, "nm")


def test_shared_colour_scale_spans_all_images():
    zs = _z_scale([np.array([[0.0, 1e-9]]), np.array([[np.nan, -2e-9]]), np.array([[3e-9]])], "m", None)
    assert (zs.units, zs.extend) == ("nm", "neither")
    assert (zs.vmin, zs.vmax) == pytest.approx((-2.0, 3.0))
    clipped = _z_scale([np.array([[-5e-9, 5e-9]])], "m", (-1e-9, 1e-9))
    assert clipped.extend == "both"


def test_import_does_not_load_matplotlib():
    code = (
        "import sys, afmtool.report.images, afmtool.runtime.atomic\n"
        "loaded = sorted(m for m in sys.modules if m == 'matplotlib' or m.startswith('matplotlib.'))\n"
        "assert not loaded, loaded\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr.decode()


def test_writers_do_not_load_pyplot(tmp_path):
    code = (
        "import sys, numpy as np\n"
        "from pathlib import Path\n"
        "from afmtool.report.images import write_image_png\n"
        f"write_image_png(Path({str(tmp_path / 'x.png')!r}), np.eye(4), 1e-6, 1e-6, z_units='m', title='t')\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr.decode()


# --------------------------------------------------------------------------- atomic_path


def test_atomic_file_success(tmp_path):
    final = tmp_path / "out.csv"
    with atomic_path(final) as tmp:
        assert tmp.parent == tmp_path
        assert tmp.name.startswith(".out.csv.tmp-") and tmp.suffix == ".csv"
        assert tmp.is_file() and not final.exists()
        tmp.write_text("a,b\n")
    assert final.read_text() == "a,b\n"
    assert _listing(tmp_path) == ["out.csv"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_atomic_file_failure_leaves_nothing(tmp_path, error):
    final = tmp_path / "out.bin"
    with pytest.raises(error), atomic_path(final) as tmp:
        tmp.write_bytes(b"partial")
        raise error
    assert _listing(tmp_path) == []


def test_atomic_file_failure_keeps_old_file(tmp_path):
    final = tmp_path / "out.txt"
    final.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(final) as tmp:
        tmp.write_text("new, partial")
        raise RuntimeError
    assert final.read_text() == "old"
    assert _listing(tmp_path) == ["out.txt"]


@pytest.mark.skipif(os.name != "posix", reason="umask is POSIX")
def test_atomic_file_permissions_follow_umask(tmp_path):
    umask = os.umask(0o022)
    try:
        write_bytes_atomic(tmp_path / "m", b"x")
    finally:
        os.umask(umask)
    assert (tmp_path / "m").stat().st_mode & 0o777 == 0o644


def test_write_text_and_bytes_atomic(tmp_path):
    path = tmp_path / "t.txt"
    write_text_atomic(path, "µm\r\nline\n")
    assert path.read_bytes() == "µm\r\nline\n".encode()
    write_bytes_atomic(path, b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"
    assert _listing(tmp_path) == ["t.txt"]


def test_atomic_refuses_bad_targets(tmp_path):
    with pytest.raises(OutputError, match="does not exist"), atomic_path(tmp_path / "no" / "f.txt"):
        pass
    (tmp_path / "d").mkdir()
    with pytest.raises(OutputError, match="is a directory"), atomic_path(tmp_path / "d"):
        pass
    assert _listing(tmp_path) == ["d"]


def test_atomic_directory_success(tmp_path):
    final = tmp_path / "bag"
    with atomic_path(final, directory=True) as tmp:
        assert not tmp.exists() and tmp.name == "bag"
        assert tmp.parent.parent == tmp_path and tmp.parent.name.startswith(".bag.tmp-")
        tmp.mkdir()
        (tmp / "bag_0.mcap").write_bytes(b"data")
        (tmp / "metadata.yaml").write_text("x: 1\n")
    assert _listing(final) == ["bag_0.mcap", "metadata.yaml"]
    assert _listing(tmp_path) == ["bag"]


def test_atomic_directory_replaces_existing(tmp_path):
    final = tmp_path / "bag"
    final.mkdir()
    (final / "old.db3").write_bytes(b"old")
    with atomic_path(final, directory=True) as tmp:
        tmp.mkdir()
        (tmp / "new.mcap").write_bytes(b"new")
    assert _listing(final) == ["new.mcap"]
    assert _listing(tmp_path) == ["bag"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_atomic_directory_failure_leaves_old(tmp_path, error):
    final = tmp_path / "bag"
    final.mkdir()
    (final / "old.db3").write_bytes(b"old")
    with pytest.raises(error), atomic_path(final, directory=True) as tmp:
        tmp.mkdir()
        (tmp / "half.mcap").write_bytes(b"half")
        raise error
    assert _listing(final) == ["old.db3"]
    assert _listing(tmp_path) == ["bag"]


def test_atomic_directory_not_created_is_an_error(tmp_path):
    with pytest.raises(OutputError, match="did not create"), atomic_path(tmp_path / "bag", directory=True):
        pass
    assert _listing(tmp_path) == []


def test_pending_path_for_open_close_writers(tmp_path):
    pending = PendingPath(tmp_path / "c.h5")
    pending.tmp.write_bytes(b"capture")
    pending.commit()
    assert (tmp_path / "c.h5").read_bytes() == b"capture"
    aborted = PendingPath(tmp_path / "d.h5")
    aborted.tmp.write_bytes(b"half")
    aborted.abort()
    aborted.abort()
    assert _listing(tmp_path) == ["c.h5"]


@pytest.mark.filterwarnings("ignore:All-NaN slice")
def test_line_envelope_keeps_each_runs_extremes_in_order(rng):
    from afmtool.report.images import line_envelope

    n, bins = 100_000, 1000
    x = np.arange(n) / 1e3
    y = rng.standard_normal(n)
    y[54_321] = 40.0  # a spike one sample wide: every-k-th thinning would drop it
    y[10_000:10_500] = np.nan  # five whole runs flagged: a gap
    ex, ey = line_envelope(x, y, bins)
    assert ex.size == 2 * bins and np.all(np.diff(ex) >= 0)
    runs = y.reshape(bins, n // bins)
    np.testing.assert_array_equal(ey.reshape(bins, 2).min(axis=1), np.nanmin(runs, axis=1))
    np.testing.assert_array_equal(ey.reshape(bins, 2).max(axis=1), np.nanmax(runs, axis=1))
    assert 40.0 in ey and np.isnan(ey[200:210]).all()
    # the values are the line's own points, at their x
    finite = np.isfinite(ey)
    np.testing.assert_array_equal(y[np.rint(ex[finite] * 1e3).astype(int)], ey[finite])
    # short lines, and lines whose x turns back (approach then retract), are drawn whole
    assert line_envelope(x[:4000], y[:4000], bins)[0].size == 4000
    back = np.r_[x, x[::-1]]
    assert line_envelope(back, np.r_[y, y], bins)[0].size == 2 * n
