"""Gwyddion as a real client of every .gsf file the afmtool CLI writes.

The REEP and probe-loss commands are run once on the bundled raster capture
(it has scan geometry, so both write their per-pixel images); then

* ``gwyddion --check`` loads every file and must say nothing, and
* ``gwyddion-thumbnailer gnome2 256`` renders every file, and the thumbnail
  must have the size Gwyddion's rule gives and show the data: grey levels a
  rising linear map of the values read back with :func:`read_gsf`.

What Gwyddion 2.62 does, found by running it (the tests pin it down):

* ``gwyddion --check FILE...`` prints one ``FILE: message`` line on stderr for
  each file it cannot load (or that fails its data validation) and nothing
  for a good file.  Its exit status is 0 even when a file cannot be loaded,
  so the check is "stdout and stderr empty", not the exit status.  It needs
  no display; HOME points at a temporary directory so that no settings are
  read from or written to the real home, and ``--no-log-to-file`` keeps it
  from writing a log there.
* The thumbnail size counts pixels, not physical size: an image whose larger
  side fits in 256 pixels is drawn 1:1; a larger one is scaled by
  ``s = max(xres, yres)/256`` to ``int(xres/s) x int(yres/s)`` (truncated,
  each side clamped to [2, 256]), nearest-neighbour.
* With a fresh HOME the palette is the grey gradient, and the data are mapped
  linearly onto it (Gwyddion's "auto" range may clip outliers to black or
  white), in 8-bit levels.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from afmtool.models.interaction import InteractionQuantities
from afmtool.report.images import read_gsf, write_gsf
from tests.conftest import REPO, SAMPLE_DATA, run_cli

needs_gwyddion = pytest.mark.skipif(
    shutil.which("gwyddion") is None or shutil.which("gwyddion-thumbnailer") is None,
    reason="gwyddion and gwyddion-thumbnailer are not installed",
)

THUMB_SIZE = 256
DIRECTIONS = ("trace", "retrace")
# Every .gsf the CLI writes, by the command that writes it (see test_every_gsf_writer_is_covered).
GSF_NAMES = sorted(
    # a raster capture with z gets a height image beside REEP's
    [f"reep/{q}_{d}.gsf" for q in ("f0_hz", "q", "amplitude", "phase_deg", "height") for d in DIRECTIONS]
    # the raster capture's metadata has k, so REEP also writes the interaction maps (issue 17 item 1)
    + [f"reep/{q}_{d}.gsf" for q in InteractionQuantities.units() for d in DIRECTIONS]
    + [f"probeloss/{q}_{d}.gsf" for q in ("loss_mask", "index") for d in DIRECTIONS]
)
CAPTURE = SAMPLE_DATA / "raster_grating.h5"  # 3 lines x 32 pixels, trace and retrace

# Largest distance of a grey level from the straight-line fit: 8-bit rounding is
# half a level; measured <= 0.6/255 on the CLI outputs, while the same outputs
# upside down are off by >= 5/255 (their three scan lines are alike, so r alone
# cannot tell).
MAX_GREY_RESIDUAL = 1.5 / 255
# Pearson r between grey level and value.  Measured on the CLI outputs:
# 1 - r <= 1.5e-5 (8-bit quantisation only).  0.99 leaves room for Gwyddion's
# auto range clipping an outlier (a 64x64 Gaussian image with one 100-sigma
# pixel gives r = 0.998) while the outputs mirrored left-right (r <= 0.81) or
# misread bytes fail by far.
MIN_PEARSON_R = 0.99


# --------------------------------------------------------------------------- helpers


def _env(home: Path) -> dict[str, str]:
    env = dict(os.environ, HOME=str(home))  # keep Gwyddion's settings out of the real home
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):  # both tools are console programs
        env.pop(name, None)
    return env


def _gwyddion_check(home: Path, *paths: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["gwyddion", "--check", "--no-log-to-file", "--log-to-console", *map(str, paths)],
        capture_output=True,
        check=False,
        text=True,
        errors="replace",
        timeout=120,
        env=_env(home),
    )


def _render(home: Path, gsf: Path, png: Path) -> tuple[np.ndarray, dict[str, str]]:
    """Gwyddion's thumbnail of ``gsf``: RGB floats in [0, 1] and the PNG's text chunks."""
    from PIL import Image

    proc = subprocess.run(
        ["gwyddion-thumbnailer", "gnome2", str(THUMB_SIZE), str(gsf), str(png)],
        capture_output=True,
        check=False,
        text=True,
        errors="replace",
        timeout=120,
        env=_env(home),
    )
    assert proc.returncode == 0 and not proc.stderr, f"{gsf.name}: {proc.stderr}"
    with Image.open(png) as image:
        info = {k: v for k, v in image.info.items() if isinstance(v, str)}
        rgb = np.asarray(image.convert("RGB"), dtype=float) / 255.0
    return rgb, info


def _thumbnail_shape(yres: int, xres: int, size: int = THUMB_SIZE) -> tuple[int, int]:
    """(height, width) of Gwyddion's thumbnail of a yres x xres image (pixels, not metres)."""
    scale = max(xres / size, yres / size)
    if scale <= 1.0:
        return yres, xres
    return min(max(int(yres / scale), 2), size), min(max(int(xres / scale), 2), size)


def _resample_nearest(data: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixel centres of ``shape`` mapped onto ``data``; the identity when the shapes match."""
    rows = np.minimum(((np.arange(shape[0]) + 0.5) * data.shape[0] / shape[0]).astype(int), data.shape[0] - 1)
    cols = np.minimum(((np.arange(shape[1]) + 0.5) * data.shape[1] / shape[1]).astype(int), data.shape[1] - 1)
    return data[np.ix_(rows, cols)]


_SI_PREFIX = {"k": 1e3, "": 1.0, "m": 1e-3, "µ": 1e-6, "n": 1e-9, "p": 1e-12}


def _check_real_size(text: str, x_real: float, y_real: float) -> None:
    """``Thumb::X-Gwyddion::RealSize`` (e.g. ``10.00×0.94 µm``) matches the header's lengths in metres."""
    match = re.fullmatch(r"([0-9.]+)×([0-9.]+) ?(k|m|µ|n|p|)m", text)
    assert match, f"unexpected real size {text!r}"
    unit = _SI_PREFIX[match[3]]
    for shown, real in ((match[1], x_real), (match[2], y_real)):
        decimals = len(shown.partition(".")[2])
        assert abs(float(shown) - real / unit) <= 0.5 * 10.0**-decimals * (1 + 1e-9), (text, x_real, y_real)


def _assert_shows(grey: np.ndarray, data: np.ndarray) -> float:
    """The grey levels are a rising linear map of ``data`` (NaN left out); returns Pearson r."""
    finite = np.isfinite(data)
    assert finite.sum() >= 3
    g, d = grey[finite], data[finite].astype(float)
    r = float(np.corrcoef(g, d)[0, 1])
    assert r > MIN_PEARSON_R, f"Pearson r = {r:.5f}"
    # Pixels inside the rendered range fit one straight line to within 8-bit rounding ...
    inside = (g > 0.0) & (g < 1.0)
    slope, offset = np.polyfit(d[inside], g[inside], 1)
    assert slope > 0
    residual = np.abs(slope * d[inside] + offset - g[inside]).max()
    assert residual <= MAX_GREY_RESIDUAL, f"grey levels off the linear map by {residual * 255:.2f}/255"
    # ... and pixels drawn black or white are the extreme values (clipped by the auto range).
    if (g == 0.0).any():
        assert d[g == 0.0].max() <= d[inside].min()
    if (g == 1.0).any():
        assert d[g == 1.0].min() >= d[inside].max()
    return r


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def gwy_home(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("gwyddion-home")


@pytest.fixture(scope="module")
def cli_outputs(tmp_path_factory) -> Path:
    """REEP and probe-loss outputs of the raster capture, each command run once."""
    root = tmp_path_factory.mktemp("gsf-outputs")
    for command in ("reep", "probeloss"):
        result = run_cli(command, CAPTURE, "--out", root / command)
        assert result.returncode == 0, result.stderr.decode(errors="replace")
    return root


@pytest.fixture(scope="module")
def thumbnails(cli_outputs, gwy_home, tmp_path_factory) -> dict[str, tuple[np.ndarray, dict[str, str]]]:
    thumbs = tmp_path_factory.mktemp("thumbnails")
    return {
        name: _render(gwy_home, cli_outputs / name, thumbs / name.replace("/", "_").replace(".gsf", ".png"))
        for name in GSF_NAMES
    }


# --------------------------------------------------------------------------- coverage


def test_every_gsf_writer_is_covered():
    """Only the REEP and probe-loss image writers write .gsf files; a new caller needs adding to GSF_NAMES."""
    callers = sorted(
        path.relative_to(REPO / "afmtool").as_posix()
        for path in (REPO / "afmtool").rglob("*.py")
        if re.search(r"\b(write_gsf|write_scan_image_files|write_scan_images)\(", path.read_text(encoding="utf-8"))
    )
    assert callers == ["analyses/probeloss_outputs.py", "analyses/reep_outputs.py", "report/images.py"]


@needs_gwyddion
def test_cli_writes_the_expected_gsf_files(cli_outputs):
    assert sorted(p.relative_to(cli_outputs).as_posix() for p in cli_outputs.rglob("*.gsf")) == GSF_NAMES


# --------------------------------------------------------------------------- gwyddion --check


@needs_gwyddion
def test_gwyddion_check_accepts_every_output(cli_outputs, gwy_home):
    proc = _gwyddion_check(gwy_home, *(cli_outputs / name for name in GSF_NAMES))
    assert proc.returncode == 0
    assert proc.stderr == "" and proc.stdout == ""


@needs_gwyddion
def test_gwyddion_check_reports_corrupt_files(cli_outputs, gwy_home, tmp_path):
    """Negative control: the check above can fail.  Gwyddion still exits 0; the problems are on stderr."""
    good = cli_outputs / "reep/f0_hz_trace.gsf"
    raw = good.read_bytes()
    corrupt = {
        "truncated.gsf": (raw[:-8], "Expected data size"),
        "too_long.gsf": (raw + b"\0" * 4, "Expected data size"),
        "no_xres.gsf": (raw.replace(b"XRes = ", b"Xres = ", 1), "XRes"),
        "zero_size.gsf": (raw.replace(b"YRes = 3\n", b"YRes = 0\n", 1), "Invalid field dimension"),
        "no_data.gsf": (raw[: raw.index(b"\0")], "truncated"),
    }
    for name, (data, _) in corrupt.items():
        (tmp_path / name).write_bytes(data)
    proc = _gwyddion_check(gwy_home, good, *(tmp_path / name for name in corrupt))
    assert proc.returncode == 0  # Gwyddion 2.62: load failures do not change the exit status
    lines = proc.stderr.splitlines()
    assert len(lines) == len(corrupt), proc.stderr
    for line, (name, (_, message)) in zip(lines, corrupt.items()):
        assert line.startswith(f"{tmp_path / name}: ") and message in line, line
    assert good.name not in proc.stderr


# --------------------------------------------------------------------------- thumbnails


@needs_gwyddion
@pytest.mark.parametrize("name", GSF_NAMES)
def test_thumbnail_shows_the_data(cli_outputs, thumbnails, name):
    gsf = read_gsf(cli_outputs / name)
    rgb, info = thumbnails[name]
    yres, xres = gsf.data.shape
    # Gwyddion read the header as written ...
    assert (info["Thumb::Image::Width"], info["Thumb::Image::Height"]) == (str(xres), str(yres))
    _check_real_size(info["Thumb::X-Gwyddion::RealSize"], float(gsf.header["XReal"]), float(gsf.header["YReal"]))
    # ... drew it at the size its rule gives ...
    assert rgb.shape[:2] == _thumbnail_shape(yres, xres)
    # ... in grey, showing the values.
    data = _resample_nearest(gsf.data, rgb.shape[:2])
    finite = np.isfinite(data)
    assert np.ptp(rgb[finite], axis=-1).max() == 0.0, "not the grey gradient"
    _assert_shows(rgb[..., 0], data)


@needs_gwyddion
@pytest.mark.parametrize(
    "shape",
    [(3, 32), (4, 8), (256, 256), (96, 128), (257, 100), (300, 500), (500, 300), (200, 1000), (1000, 3)],
)
def test_thumbnail_size_rule(tmp_path, shape):
    """Small images are drawn 1:1, large ones scaled to fit 256 pixels; pixels count, not metres."""
    ny, nx = shape
    y, x = np.mgrid[0:ny, 0:nx]
    image = np.sin(2 * np.pi * x / max(nx, 8)) + 0.5 * np.cos(2 * np.pi * y / max(ny, 8)) + x / nx
    path = tmp_path / "shape.gsf"
    write_gsf(path, image, 1e-6, 1e-6)  # square scan, non-square pixels: the thumbnail ignores XReal/YReal
    rgb, info = _render(tmp_path, path, tmp_path / "shape.png")
    assert rgb.shape[:2] == _thumbnail_shape(ny, nx)
    assert (info["Thumb::Image::Width"], info["Thumb::Image::Height"]) == (str(nx), str(ny))
    if max(shape) <= THUMB_SIZE:
        _assert_shows(rgb.mean(axis=-1), image)
    else:  # nearest-neighbour sampling may pick neighbouring pixels; compare loosely
        r = np.corrcoef(rgb.mean(axis=-1).ravel(), _resample_nearest(image, rgb.shape[:2]).ravel())[0, 1]
        assert r > MIN_PEARSON_R


def test_thumbnail_shape_rule_examples():
    """The rule as observed with Gwyddion 2.62 (see the module docstring)."""
    assert _thumbnail_shape(3, 32) == (3, 32)
    assert _thumbnail_shape(256, 256) == (256, 256)
    assert _thumbnail_shape(300, 500) == (153, 256)
    assert _thumbnail_shape(257, 100) == (256, 99)
    assert _thumbnail_shape(1000, 3) == (256, 2)


@needs_gwyddion
def test_thumbnail_top_row_first(tmp_path):
    """The first row in the file is the top of Gwyddion's image (the x ramp is in test_images.py)."""
    image = np.tile(np.linspace(0.0, 1e-8, 40)[:, None], (1, 50))  # rising downwards
    path = tmp_path / "down.gsf"
    write_gsf(path, image, 1e-6, 0.8e-6)
    rgb, _ = _render(tmp_path, path, tmp_path / "down.png")
    brightness = rgb.mean(axis=(1, 2))  # per row
    assert np.all(np.diff(brightness) >= 0.0)
    assert brightness[0] < 0.01 and brightness[-1] > 0.99
