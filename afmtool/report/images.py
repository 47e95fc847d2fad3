"""Image and plot writers: Gwyddion Simple Field files and PNG figures.

Images are 2-D arrays with rows along y, top row first (row 0 is drawn at
the top, as in Gwyddion), values in ``z_units``; the scan size is given in
metres.  PNG figures use matplotlib, imported inside the writers only, so
that ``import afmtool.report.images`` (and the CLI start-up) stays free of
it.  Every file is written through :func:`afmtool.runtime.atomic.atomic_path`.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, NamedTuple, TypedDict

import numpy as np
from numpy.typing import ArrayLike

from afmtool.errors import InputError
from afmtool.report.figure_process import FigureProcess, NothingToDraw, skipped_when_empty
from afmtool.runtime.atomic import OutputError, atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.colors import Colormap
    from matplotlib.figure import Figure

__all__ = [
    "APPROACH_STYLE",
    "ENVELOPE_BINS",
    "GSF_MAGIC",
    "NAN_COLOUR",
    "PNG_DPI",
    "RETRACT_STYLE",
    "GsfImage",
    "ImageStyle",
    "PanelSpec",
    "Series",
    "read_gsf",
    "start_matplotlib_import",
    "warm_up_figures",
    "write_gsf",
    "write_image_png",
    "write_line_plot_png",
    "write_scan_image_files",
    "write_scan_images",
    "write_multi_panel_png",
    "write_side_by_side_png",
    "line_envelope",
]

GSF_MAGIC = b"Gwyddion Simple Field 1.0\n"

#: Resolution of every PNG, in dots per inch.
PNG_DPI = 150

#: Runs a long line is reduced to (:func:`line_envelope`): about the pixel
#: columns of a 7-inch panel at PNG_DPI, each run drawn as its two extremes.
ENVELOPE_BINS = 1000

#: Colour of NaN (and infinite) pixels: a neutral grey, outside every AFM colour map.
NAN_COLOUR = "#7f7f7f"

#: Line styles for force curves: approach solid, retract dashed, same in every panel.
APPROACH_STYLE: Mapping[str, Any] = MappingProxyType({"color": "C0", "linestyle": "-"})
RETRACT_STYLE: Mapping[str, Any] = MappingProxyType({"color": "C3", "linestyle": "--"})

_STYLE_KEYS = frozenset({"color", "linestyle", "linewidth", "marker", "markersize", "alpha", "zorder", "drawstyle"})
_PANEL_KEYS = frozenset({"series", "y_label", "title", "twin", "y_scale"})

# Units that take an SI prefix on a colour bar; anything else is shown as given.
_PREFIXABLE = frozenset({"m", "V", "A", "N", "Hz", "s", "W", "Pa", "F", "S", "rad"})
_SI_PREFIXES = {-18: "a", -15: "f", -12: "p", -9: "n", -6: "µ", -3: "m", 0: "", 3: "k", 6: "M", 9: "G"}


# --------------------------------------------------------------------------- validation


def _as_image(image: ArrayLike, name: str = "image") -> np.ndarray:
    """``image`` as a 2-D real array (not copied when it already is one)."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a non-empty 2-D array, got shape {arr.shape}")
    if arr.size == 0:
        raise NothingToDraw(f"{name} must be a non-empty 2-D array, got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be real numbers, got dtype {arr.dtype}")
    return arr


def _check_size(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}={value!r} must be a finite length > 0")
    return value


def _check_header_value(name: str, value: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{name}={value!r} must be a string")
    if any(c in value for c in "\n\r\0"):
        raise ValueError(f"{name}={value!r} must be one line without NUL characters")
    if value != value.strip():
        raise ValueError(f"{name}={value!r} must not start or end with whitespace (Gwyddion strips it)")
    return value


def _check_png_path(path: Path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise OutputError(f"{path}: a PNG figure needs a .png suffix")
    return path


def _check_z_range(z_range: tuple[float, float] | None) -> tuple[float, float] | None:
    if z_range is None:
        return None
    lo, hi = (float(v) for v in z_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"z_range={z_range!r} must be two finite numbers, low < high")
    return lo, hi


# --------------------------------------------------------------------------- GSF


@dataclass(frozen=True)
class GsfImage:
    """A Gwyddion Simple Field file as read: header fields and data.

    ``header`` maps every field name to its text value (whitespace around
    both stripped); ``data`` is float32 with shape ``(YRes, XRes)``, top row
    first, read-only.
    """

    header: Mapping[str, str]
    data: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "header", MappingProxyType(dict(self.header)))


def _gsf_header(
    xres: int, yres: int, x_real: float, y_real: float, xy_units: str, z_units: str, title: str
) -> bytes:
    """Magic line, ``name = value`` lines, then 1-4 NULs so that len % 4 == 0."""
    lines = [f"XRes = {xres}", f"YRes = {yres}", f"XReal = {x_real!r}", f"YReal = {y_real!r}"]
    # Empty values are left out, as Gwyddion's own exporter does; the reader then
    # uses its defaults (no units, a fallback channel title).
    for key, value in (("XYUnits", xy_units), ("ZUnits", z_units), ("Title", title)):
        if value:
            lines.append(f"{key} = {value}")
    text = GSF_MAGIC + "".join(line + "\n" for line in lines).encode("utf-8")
    # Always at least one NUL: it terminates the header.
    return text + b"\0" * (4 - len(text) % 4)


def write_gsf(
    path: Path,
    image: ArrayLike,
    x_real_m: float,
    y_real_m: float,
    *,
    xy_units: str = "m",
    z_units: str = "m",
    title: str = "",
) -> None:
    """Write a 2-D image as a Gwyddion Simple Field (.gsf) file.

    Parameters
    ----------
    path : Path
        The output file (conventionally ``*.gsf``; Gwyddion detects the
        format by its first line).
    image : array_like, shape (ny, nx)
        Values in ``z_units``; row 0 is the top row of the scan.
    x_real_m, y_real_m : float
        Physical width and height of the scan, in ``xy_units`` (metres by
        default); positive and finite.
    xy_units, z_units : str, optional
        Units as Gwyddion spells them (``"m"``, ``"V"``, ``"Hz"``, ``"deg"``).
        Empty strings are left out of the header.
    title : str, optional
        Channel title (UTF-8); left out when empty.

    Raises
    ------
    ValueError
        A bad argument, or a finite value too large for float32.
    OutputError
        The file cannot be written.

    Notes
    -----
    Layout (Gwyddion user guide, "Simple Field Files"): the line
    ``Gwyddion Simple Field 1.0``, then ``XRes``, ``YRes``, ``XReal``,
    ``YReal``, ``XYUnits``, ``ZUnits``, ``Title`` as ``name = value`` lines,
    each ending in LF; then 1 to 4 NUL bytes so the data start at a multiple
    of 4; then ``XRes*YRes`` little-endian float32 values, row by row, top
    row first.  Lengths are written with ``repr`` so they read back exactly.

    NaN is stored as float32 NaN; the format has no other way to mark
    missing pixels.  Gwyddion 2.62 (checked with ``gwyddion-thumbnailer``)
    replaces NaN pixels on import by values interpolated from their
    neighbours and puts a mask over them (drawn in red), so holes show as
    masked, not as data.  Other readers see the raw NaN.
    """
    arr = _as_image(image)
    x_real = _check_size("x_real_m", x_real_m)
    y_real = _check_size("y_real_m", y_real_m)
    for name, value in (("xy_units", xy_units), ("z_units", z_units), ("title", title)):
        _check_header_value(name, value)
    with np.errstate(over="ignore", invalid="ignore"):
        data = np.ascontiguousarray(arr, dtype="<f4")
    overflow = np.isinf(data) & np.isfinite(arr)
    if overflow.any():
        row, col = np.argwhere(overflow)[0]
        raise ValueError(f"image[{row}, {col}]={arr[row, col]!r} does not fit in float32")
    yres, xres = arr.shape
    header = _gsf_header(xres, yres, x_real, y_real, xy_units, z_units, title)
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        fh.write(data.tobytes())


def _parse_gsf_header(path: Path, text: bytes) -> dict[str, str]:
    try:
        decoded = text.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: GSF header is not UTF-8") from None
    header = {}
    for number, line in enumerate(decoded.split("\n"), start=2):
        if not line.strip():
            continue
        name, sep, value = line.partition("=")
        if not sep:
            raise InputError(f"{path}: GSF header line {number} is not 'name = value': {line!r}")
        header[name.strip()] = value.strip()
    return header


def _pixel_count(path: Path, header: Mapping[str, str], key: str) -> int:
    value = header.get(key)
    if value is None:
        raise InputError(f"{path}: GSF header has no {key}")
    try:
        count = int(value)
    except ValueError:
        raise InputError(f"{path}: GSF {key}={value!r} is not an integer") from None
    if count < 1:
        raise InputError(f"{path}: GSF {key}={count} must be positive")
    return count


def read_gsf(path: Path) -> GsfImage:
    """Read a Gwyddion Simple Field file strictly (used to check :func:`write_gsf`).

    Raises
    ------
    InputError
        The file is missing, not GSF, or its size does not match its header.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror})") from None
    if not raw.startswith(GSF_MAGIC):
        raise InputError(f"{path}: not a Gwyddion Simple Field file (bad first line)")
    nul = raw.find(b"\0", len(GSF_MAGIC))
    if nul < 0:
        raise InputError(f"{path}: GSF header is not terminated by a NUL byte")
    offset = nul + 4 - nul % 4
    if raw[nul:offset] != b"\0" * (offset - nul):
        raise InputError(f"{path}: GSF header padding is not 1-4 NUL bytes")
    header = _parse_gsf_header(path, raw[len(GSF_MAGIC) : nul])
    xres = _pixel_count(path, header, "XRes")
    yres = _pixel_count(path, header, "YRes")
    expected = offset + 4 * xres * yres
    if len(raw) != expected:
        raise InputError(f"{path}: {len(raw)} bytes, but the header ({xres}x{yres}) implies {expected}")
    data = np.frombuffer(raw, dtype="<f4", count=xres * yres, offset=offset).reshape(yres, xres)
    return GsfImage(header=header, data=data)


# --------------------------------------------------------------------------- matplotlib


def _figure_class() -> type[Figure]:
    """Import matplotlib (only now) and return its ``Figure`` class.

    Figures are built from ``Figure`` directly, never through pyplot, so
    nothing is registered globally and nothing needs closing.  The Agg
    backend is selected only if pyplot has not been imported: switching
    backends under a running pyplot (a notebook) would close its figures.
    """
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    from matplotlib.figure import Figure

    return Figure


def start_matplotlib_import() -> None:
    """Import matplotlib and its Agg backend in a daemon thread, now.

    A command that will draw figures at its end calls this at its start:
    the import (about 0.3 s, with the font cache) then overlaps the stream,
    whose kernels leave the GIL free, instead of adding to the run.  A
    figure drawn before the import is done waits for it (the import lock);
    a failed import is left to fail again, and be reported, there.
    """
    import threading

    def run() -> None:
        try:
            _figure_class()
            import matplotlib.backends.backend_agg
            import matplotlib.style  # noqa: F401 - loaded here, off the main thread, for the first figure
            from matplotlib.font_manager import fontManager

            fontManager.findfont("DejaVu Sans")
        except Exception:  # noqa: BLE001 - the figure's own import reports it
            pass

    threading.Thread(target=run, name="afmtool-matplotlib", daemon=True).start()


def warm_up_figures() -> None:
    """Import matplotlib and draw a small figure into memory, discarded.

    The first figure of a process pays for loading the fonts and for the
    first pass through matplotlib's drawing code (0.1-0.2 s more than the
    next one); the figure process (:mod:`afmtool.report.figure_process`)
    pays it while the command is still analysing.
    """
    import io

    import matplotlib.style

    figure_class = _figure_class()
    with matplotlib.style.context("default"):
        fig = figure_class(figsize=(2.0, 1.5), dpi=PNG_DPI)
        axes = fig.add_subplot()
        axes.plot([0.0, 1.0], [0.0, 1.0])
        axes.set(xlabel="time t (s)", ylabel="f0' (Hz)", title="warm-up")
        fig.savefig(io.BytesIO(), format="png", dpi=PNG_DPI)


@contextmanager
def _png_figure(path: Path, width_in: float, height_in: float, layout: str | None = "constrained") -> Iterator[Figure]:
    """Yield a new figure, then save it to ``path`` as PNG if the block succeeds.

    The figure is built and saved under matplotlib's default style, not the
    user's matplotlibrc, so the output does not depend on who runs it.
    ``layout=None``: the caller places the axes (:func:`_stacked_margins`).
    """
    import matplotlib.style

    figure_class = _figure_class()
    with matplotlib.style.context("default"):
        fig = figure_class(figsize=(width_in, height_in), dpi=PNG_DPI, layout=layout)
        yield fig
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=PNG_DPI)


def _colormap(name: str) -> Colormap:
    import matplotlib

    try:
        base = matplotlib.colormaps[name]
    except KeyError:
        raise ValueError(f"cmap={name!r} is not a matplotlib colour map (e.g. 'afmhot', 'gray')") from None
    return base.with_extremes(bad=NAN_COLOUR)


def _si_scale(max_abs: float, units: str) -> tuple[float, str]:
    """Factor and prefixed units that bring ``max_abs`` into [1, 1000): (1e9, "nm") for 3e-9 m."""
    if units not in _PREFIXABLE or not (math.isfinite(max_abs) and max_abs > 0):
        return 1.0, units
    exponent = min(max(3 * math.floor(math.log10(max_abs) / 3), -18), 9)
    return 10.0**-exponent, _SI_PREFIXES[exponent] + units


def _lateral_scale(x_real_m: float, y_real_m: float) -> tuple[float, str]:
    """Micrometres for scans of 1 µm or more, nanometres below."""
    return (1e6, "µm") if max(x_real_m, y_real_m) >= 1e-6 else (1e9, "nm")


class _ZScale(NamedTuple):
    factor: float  # displayed = value * factor
    units: str  # prefixed units of the displayed values
    vmin: float  # displayed colour limits
    vmax: float
    extend: str  # colour bar arrows for values clipped by z_range


def _z_scale(images: Sequence[np.ndarray], z_units: str, z_range: tuple[float, float] | None) -> _ZScale:
    """One colour scale for all ``images``: SI prefix, limits, and clipping arrows."""
    finite = [a[np.isfinite(a)] for a in images]
    values = np.concatenate([f.ravel().astype(float) for f in finite])
    lo, hi = (float(values.min()), float(values.max())) if values.size else (0.0, 1.0)
    extend = "neither"
    if z_range is not None:
        clipped = (values.size > 0 and lo < z_range[0], values.size > 0 and hi > z_range[1])
        extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get(clipped, "neither")
        lo, hi = z_range
    elif lo == hi:  # a flat image: centre it in a small range rather than divide by zero
        pad = abs(lo) * 1e-3 or 1.0
        lo, hi = lo - pad, hi + pad
    factor, units = _si_scale(max(abs(lo), abs(hi)), z_units)
    return _ZScale(factor, units, lo * factor, hi * factor, extend)


def _colorbar_label(z_label: str, units: str) -> str:
    """``"height (nm)"``: every colour bar names a quantity and its units, ``dimensionless`` for none."""
    return f"{z_label or 'value'} ({units or 'dimensionless'})"


def _draw_image(
    ax: Axes,
    image: np.ndarray,
    extent: tuple[float, float, float, float],
    cmap: Colormap,
    zs: _ZScale,
) -> Any:
    """Draw one image, top row at the top, y increasing downwards as in Gwyddion."""
    shown = np.ma.masked_invalid(image.astype(float) * zs.factor)
    im = ax.imshow(
        shown,
        cmap=cmap,
        vmin=zs.vmin,
        vmax=zs.vmax,
        origin="upper",
        extent=extent,
        interpolation="antialiased",
    )
    ax.set_aspect("equal")
    return im


def _draw_colorbar(fig: Figure, ax: Axes, im: Any, label: str, extend: str) -> None:
    """A colour bar just right of ``ax``, exactly as tall as the image."""
    cax = ax.inset_axes((1.04, 0.0, 0.05, 1.0))
    fig.colorbar(im, cax=cax, label=label, extend=extend)


def _image_figure_size(x_real_m: float, y_real_m: float, n: int, colorbar_label: str) -> tuple[float, float]:
    """(width, height) in inches: the image at its true aspect, plus room for the title and the x axis.

    A scan of a few lines is a thin strip; the figure is cut to it (no band
    of white above and below), with a floor that keeps the colour bar's
    label (set vertically beside it) inside the figure: a label taller than
    the figure collapsed the constrained layout of a 3-line scan's
    probe-loss index.
    """
    aspect = min(max(y_real_m / x_real_m, 0.02), 4.0)
    panel = 4.8 if n == 1 else 3.6
    label_in = _LABEL_CHAR_IN * max(len(line) for line in colorbar_label.split("\n"))
    height = min(max(panel * aspect, 0.6, label_in - 1.0), 9.0) + 1.1
    return panel * n + 1.6, height


#: Width of a 10 pt DejaVu Sans character, with margin (inches).
_LABEL_CHAR_IN = 0.085


def _short_colorbar_label(label: str, x_real_m: float, y_real_m: float) -> str:
    """The label on two lines, quantity over units, when the image is too thin for it on one."""
    if 4.8 * y_real_m / x_real_m < _LABEL_CHAR_IN * len(label) and " (" in label:
        quantity, _, units = label.rpartition(" (")
        return f"{quantity}\n({units}"
    return label


@dataclass(frozen=True)
class ImageStyle:
    """How one scan-image quantity is written: its title and units, the file stem, colour map and range."""

    title: str
    units: str
    stem: str | None = None  #: file stem before ``_trace``/``_retrace``; the quantity's name by default
    cmap: str = "afmhot"
    z_range: tuple[float, float] | None = None


def write_scan_images(
    path_of: Callable[[str], Path],
    images: Mapping[str, np.ndarray],
    geometry,
    style_of: Callable[[str], ImageStyle],
    put: Callable[..., None] | None = None,
    figures: FigureProcess | None = None,
) -> None:
    """Every ``quantity/direction`` image of a scan as PNG + .gsf (:func:`write_scan_image_files`).

    Parameters
    ----------
    path_of : callable
        Output file name -> path.
    images : mapping of str to ndarray
        ``"f0_hz/trace"`` and the like -> (lines, pixels) image, row 0 the first line scanned.
    geometry
        The scan's geometry (``scan_size_m``, ``lines``, ``pixels_per_line``).
    style_of : callable
        Quantity -> :class:`ImageStyle`.
    put : callable, optional
        ``put(name, values, units, attrs)`` of the command's result file: each image is
        stored there as ``images/<key>`` too.
    figures : FigureProcess, optional
        Draws the PNGs (the command's figure process); by default this process.
    """
    for key, image in sorted(images.items()):
        quantity, direction = key.split("/")
        style = style_of(quantity)
        if put is not None:
            put(f"images/{key}", image, style.units, {"row0": "first line scanned"})
        write_scan_image_files(path_of, f"{style.stem or quantity}_{direction}", image, geometry.scan_size_m,
                               geometry.lines / geometry.pixels_per_line, title=style.title, direction=direction,
                               units=style.units, cmap=style.cmap, z_range=style.z_range, figures=figures)


def write_scan_image_files(
    path_of: Callable[[str], Path],
    stem: str,
    image: ArrayLike,
    scan_size_m: float,
    aspect: float,
    *,
    title: str,
    direction: str,
    units: str,
    cmap: str = "afmhot",
    z_range: tuple[float, float] | None = None,
    figures: FigureProcess | None = None,
) -> None:
    """``{stem}.png`` and ``{stem}.gsf`` of one per-pixel scan image.

    Parameters
    ----------
    path_of : callable
        Output file name -> path (e.g. ``OutputDir.path``).
    stem : str
        File name without suffix.
    image : array_like, shape (lines, pixels)
        Row 0 is the first line scanned; the files show the last line at
        the top, as AFM viewers do.
    scan_size_m : float
        Fast-axis scan size, m.
    aspect : float
        lines / pixels_per_line: the slow-axis size is ``scan_size_m * aspect``.
    title, direction, units : str
        The quantity's title, the scan direction (trace, retrace) and its units.
    cmap, z_range
        As for :func:`write_image_png`.
    figures : FigureProcess, optional
        Draws the PNG (the command's figure process); by default this process.
    """
    top_first = np.asarray(image)[::-1]
    y_size = scan_size_m * aspect
    (figures or FigureProcess()).draw(write_image_png, path_of(f"{stem}.png"), top_first, scan_size_m, y_size,
                                      z_units=units, title=f"{title} ({direction})", cmap=cmap, z_range=z_range,
                                      z_label=title)
    write_gsf(path_of(f"{stem}.gsf"), top_first, scan_size_m, y_size, xy_units="m", z_units=units,
              title=f"{title} {direction}")


@skipped_when_empty
def write_image_png(
    path: Path,
    image: ArrayLike,
    x_real_m: float,
    y_real_m: float,
    *,
    z_units: str,
    title: str,
    cmap: str = "afmhot",
    z_label: str = "",
    z_range: tuple[float, float] | None = None,
) -> None:
    """Render a 2-D scan as a PNG with physical axes and a labelled colour bar.

    Parameters
    ----------
    path : Path
        The output file; must end in ``.png``.
    image : array_like, shape (ny, nx)
        Values in ``z_units``; row 0 is drawn at the top.
    x_real_m, y_real_m : float
        Scan width and height in metres.  The axes are in µm for scans of
        1 µm or more, in nm below; y increases downwards, as in Gwyddion.
    z_units : str
        Units of the values.  SI units (``m``, ``V``, ``Hz``, ...) get a
        prefix on the colour bar (heights of a few 1e-9 m show as nm).
    title : str
        Figure title.
    cmap : str, optional
        Matplotlib colour map; ``afmhot`` by default.  NaN and infinite
        pixels are drawn in neutral grey (:data:`NAN_COLOUR`).
    z_label : str, optional
        Quantity on the colour bar, e.g. ``"height"``; the units follow in
        parentheses.
    z_range : (float, float), optional
        Colour limits in ``z_units``; by default the finite minimum and
        maximum.  Clipped values are marked by arrows on the colour bar.
    """
    path = _check_png_path(path)
    arr = _as_image(image)
    x_real = _check_size("x_real_m", x_real_m)
    y_real = _check_size("y_real_m", y_real_m)
    zr = _check_z_range(z_range)
    colormap = _colormap(cmap)

    factor, unit = _lateral_scale(x_real, y_real)
    zs = _z_scale([arr], z_units, zr)
    label = _short_colorbar_label(_colorbar_label(z_label, zs.units), x_real, y_real)
    with _png_figure(path, *_image_figure_size(x_real, y_real, 1, label)) as fig:
        ax = fig.add_subplot()
        im = _draw_image(ax, arr, (0.0, x_real * factor, y_real * factor, 0.0), colormap, zs)
        ax.set_xlabel(f"x ({unit})")
        ax.set_ylabel(f"y ({unit})")
        ax.set_title(title)
        _draw_colorbar(fig, ax, im, label, zs.extend)


@skipped_when_empty
def write_side_by_side_png(
    path: Path,
    images: Sequence[tuple[ArrayLike, str]],
    x_real_m: float,
    y_real_m: float,
    *,
    z_units: str,
    suptitle: str,
    cmap: str = "afmhot",
    z_label: str = "",
    z_range: tuple[float, float] | None = None,
) -> None:
    """Render several scans of the same area in one row with one shared colour scale.

    Parameters
    ----------
    path : Path
        The output file; must end in ``.png``.
    images : sequence of (array_like, str)
        Each image (rows along y, top row first) and its panel title.  All
        cover the same ``x_real_m`` by ``y_real_m`` area; pixel counts may
        differ.
    x_real_m, y_real_m, z_units, cmap, z_label, z_range
        As for :func:`write_image_png`; the colour limits span every image.
    suptitle : str
        Title over the whole row.
    """
    path = _check_png_path(path)
    if len(images) == 0:
        raise NothingToDraw("images must hold at least one (array, title) pair")
    arrays, titles = [], []
    for i, item in enumerate(images):
        arr, panel_title = item
        arrays.append(_as_image(arr, f"images[{i}]"))
        titles.append(str(panel_title))
    x_real = _check_size("x_real_m", x_real_m)
    y_real = _check_size("y_real_m", y_real_m)
    zr = _check_z_range(z_range)
    colormap = _colormap(cmap)

    factor, unit = _lateral_scale(x_real, y_real)
    zs = _z_scale(arrays, z_units, zr)
    extent = (0.0, x_real * factor, y_real * factor, 0.0)
    label = _short_colorbar_label(_colorbar_label(z_label, zs.units), x_real, y_real)
    with _png_figure(path, *_image_figure_size(x_real, y_real, len(arrays), label)) as fig:
        axes = fig.subplots(1, len(arrays), sharex=True, sharey=True, squeeze=False)[0]
        for ax, arr, panel_title in zip(axes, arrays, titles, strict=True):
            im = _draw_image(ax, arr, extent, colormap, zs)
            ax.set_title(panel_title)
            ax.set_xlabel(f"x ({unit})")
        axes[0].set_ylabel(f"y ({unit})")
        fig.suptitle(suptitle)
        _draw_colorbar(fig, axes[-1], im, label, zs.extend)


# --------------------------------------------------------------------------- line plots


class Series(NamedTuple):
    """One line: ``x`` and ``y`` (1-D, same length), a legend label, and a style.

    ``style`` holds matplotlib line properties (``color``, ``linestyle``,
    ``linewidth``, ``marker``, ``markersize``, ``alpha``, ``zorder``,
    ``drawstyle``), e.g. :data:`APPROACH_STYLE`.  Plain ``(x, y, label)``
    tuples are accepted wherever a ``Series`` is.  NaN in ``y`` breaks the line.
    """

    x: ArrayLike
    y: ArrayLike
    label: str
    style: Mapping[str, Any] | None = None


class PanelSpec(TypedDict, total=False):
    """One panel of :func:`write_multi_panel_png`; only ``series`` is required."""

    series: Sequence[Series | tuple]
    y_label: str
    title: str
    #: ``{"series": [...], "y_label": "z (nm)"}``: lines on a second y axis at the right
    twin: Mapping[str, Any]
    #: ``"linear"`` (default) or ``"log"``
    y_scale: str


def _as_series(item: Series | tuple, name: str) -> tuple[np.ndarray, np.ndarray, str, dict[str, Any]]:
    if not 3 <= len(item) <= 4:
        raise ValueError(f"{name} must be (x, y, label) or (x, y, label, style), got {len(item)} items")
    s = Series(*item)
    x, y = np.asarray(s.x), np.asarray(s.y)
    if x.ndim != 1 or y.ndim != 1 or len(x) != len(y):
        raise ValueError(f"{name}: x and y must be non-empty 1-D arrays of one length, got {x.shape} and {y.shape}")
    if len(x) == 0:
        raise NothingToDraw(f"{name}: no points")
    for axis, arr in (("x", x), ("y", y)):
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"{name}: {axis} must be real numbers, got dtype {arr.dtype}")
    style = dict(s.style or {})
    unknown = sorted(set(style) - _STYLE_KEYS)
    if unknown:
        raise ValueError(f"{name}: unknown style keys {unknown}; allowed: {sorted(_STYLE_KEYS)}")
    return x, y, str(s.label), style


def _check_markers(markers: Sequence[tuple[float, str]] | None) -> list[tuple[float, str]]:
    checked = []
    for i, item in enumerate(markers or ()):
        x, label = item
        x = float(x)
        if not math.isfinite(x):
            raise ValueError(f"markers[{i}]: x={x!r} must be finite")
        checked.append((x, str(label)))
    return checked


def line_envelope(x: np.ndarray, y: np.ndarray, bins: int = ENVELOPE_BINS) -> tuple[np.ndarray, np.ndarray]:
    """A long line over ascending x as the extremes of ``bins`` runs of consecutive points.

    Each run keeps its lowest and its highest point, in their order, so the
    line drawn covers the same pixels as the full one at the figure's width
    (and shows a spike that taking every k-th point would miss), while
    matplotlib lays out and draws 2·``bins`` points instead of all of them.
    A run with no finite y is NaN: a gap, as in the full line.  Lines of at
    most 4·``bins`` points, or over x that is not ascending (an approach
    and its retract), are returned as they are.
    """
    n = len(y)
    if n <= 4 * bins or not np.all(np.diff(x) >= 0):
        return x, y
    per_run = -(-n // bins)
    runs = -(-n // per_run)
    padded = np.full(runs * per_run, np.nan)
    padded[:n] = y
    padded = padded.reshape(runs, per_run)
    finite = np.isfinite(padded)
    lowest = np.where(finite, padded, np.inf).argmin(axis=1)
    highest = np.where(finite, padded, -np.inf).argmax(axis=1)
    starts = np.arange(runs) * per_run
    index = np.stack([starts + np.minimum(lowest, highest), starts + np.maximum(lowest, highest)], axis=1).ravel()
    values = np.where(np.repeat(finite.any(axis=1), 2), y[index], np.nan)
    return x[index], values


def _plot(ax: Axes, x: np.ndarray, y: np.ndarray, label: str, style: Mapping[str, Any]) -> None:
    """``ax.plot``; a long line over ascending x is drawn as its envelope (:func:`line_envelope`)."""
    if style.get("linestyle", "-") not in ("none", "None", "") and "marker" not in style:
        x, y = line_envelope(x, y)
    ax.plot(x, y, label=label or None, **style)


def _draw_series(ax: Axes, series: Sequence[tuple[np.ndarray, np.ndarray, str, dict[str, Any]]]) -> None:
    for x, y, label, style in series:
        _plot(ax, x, y, label, style)
    if any(label for _, _, label, _ in series):
        ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3)


def _draw_markers(ax: Axes, markers: Sequence[tuple[float, str]], *, labelled: bool) -> None:
    """Dotted vertical lines at ``markers`` x positions, labelled at the top of the axes."""
    for x, label in markers:
        ax.axvline(x, color="0.35", linestyle=":", linewidth=1.0)
        if labelled and label:
            ax.annotate(
                label,
                xy=(x, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(-2, -4),
                textcoords="offset points",
                rotation=90,
                ha="right",
                va="top",
                fontsize="small",
                color="0.35",
            )


def _check_spans(spans: Sequence[tuple[float, float, str]] | None) -> list[tuple[float, float, str]]:
    checked = []
    for i, (x0, x1, label) in enumerate(spans or ()):
        x0, x1 = float(x0), float(x1)
        if not (math.isfinite(x0) and math.isfinite(x1) and x0 < x1):
            raise ValueError(f"spans[{i}]: ({x0!r}, {x1!r}) must be finite with start < end")
        checked.append((x0, x1, str(label)))
    return checked


def _draw_spans(ax: Axes, spans: Sequence[tuple[float, float, str]], *, labelled: bool) -> None:
    """Shaded x intervals (a free-air segment), labelled once in the legend of the top panel."""
    for x0, x1, label in spans:
        ax.axvspan(x0, x1, color="0.85", alpha=0.6, zorder=0, label=label if labelled and label else None)


def _check_panels(panels: Sequence[PanelSpec]) -> list[tuple[list, str, str]]:
    """``(series, y label, title)`` of each panel of :func:`write_multi_panel_png`, checked."""
    if len(panels) == 0:
        raise NothingToDraw("panels must hold at least one panel")
    checked = []
    for p, panel in enumerate(panels):
        unknown = sorted(set(panel) - _PANEL_KEYS)
        if unknown:
            raise ValueError(f"panels[{p}]: unknown keys {unknown}; allowed: {sorted(_PANEL_KEYS)}")
        if not panel.get("series"):
            raise NothingToDraw(f"panels[{p}] must hold a non-empty 'series'")
        lines = [_as_series(item, f"panels[{p}]['series'][{i}]") for i, item in enumerate(panel["series"])]
        if panel.get("y_scale", "linear") not in ("linear", "log"):
            raise ValueError(f"panels[{p}]['y_scale']={panel['y_scale']!r} must be 'linear' or 'log'")
        checked.append((lines, str(panel.get("y_label", "")), str(panel.get("title", ""))))
    return checked


def _stacked_margins(fig: Figure, width_in: float, height_in: float, *, twin: bool, panel_titles: bool,
                     title: bool) -> None:
    """Fixed margins (inches) for panels stacked on one x axis (or one), room made for a right axis and titles.

    Constrained layout measured every tick label of every panel before the
    draw measured them again: half of such a figure's time (0.7 of 1.3 s for
    probeloss's two).  The stacked panels need no search: tick labels of up
    to about eight characters fit the left margin, and matplotlib sets each
    y label beside its tick labels.
    """
    fig.subplots_adjust(
        left=1.0 / width_in,
        right=1.0 - (0.95 if twin else 0.25) / width_in,
        bottom=0.6 / height_in,
        top=1.0 - (0.6 if title else 0.25) / height_in,
        hspace=0.3 if panel_titles else 0.12,
    )
    fig.align_ylabels()


def _draw_twin(ax: Axes, twin: Mapping[str, Any], p: int) -> None:
    """Lines of ``twin`` on a second y axis at the right of ``ax``, greyed so that the panel's own lines lead."""
    lines = [_as_series(item, f"panels[{p}]['twin']['series'][{i}]") for i, item in enumerate(twin.get("series", ()))]
    if not lines:
        raise NothingToDraw(f"panels[{p}]['twin'] must hold a non-empty 'series'")
    right = ax.twinx()
    for x, y, label, style in lines:
        _plot(right, x, y, label, {"color": "0.45", "linewidth": 1.0, **style})
    right.set_ylabel(str(twin.get("y_label", "")))
    if any(label for _, _, label, _ in lines):
        right.legend(fontsize="small", loc="lower right")


@skipped_when_empty
def write_line_plot_png(
    path: Path,
    series: Sequence[Series | tuple],
    *,
    x_label: str,
    y_label: str,
    title: str,
    markers: Sequence[tuple[float, str]] | None = None,
) -> None:
    """Plot one or more lines on one pair of axes.

    Parameters
    ----------
    path : Path
        The output file; must end in ``.png``.
    series : sequence of Series or (x, y, label[, style]) tuples
        The lines, drawn in order; labelled lines get a legend.
    x_label, y_label : str
        Axis labels with their units, e.g. ``"z (nm)"``; values are plotted
        as given.
    title : str
        Figure title.
    markers : sequence of (float, str), optional
        ``(x, label)`` pairs drawn as labelled dotted vertical lines (a
        contact point, a set point).
    """
    path = _check_png_path(path)
    if len(series) == 0:
        raise NothingToDraw("series must hold at least one line")
    lines = [_as_series(item, f"series[{i}]") for i, item in enumerate(series)]
    marks = _check_markers(markers)

    with _png_figure(path, 7.0, 4.2, layout=None) as fig:
        ax = fig.add_subplot()
        _stacked_margins(fig, 7.0, 4.2, twin=False, panel_titles=False, title=True)
        _draw_series(ax, lines)
        _draw_markers(ax, marks, labelled=True)
        ax.set_xlabel(x_label)
        ax.set_ylabel(y_label)
        ax.set_title(title)


@skipped_when_empty
def write_multi_panel_png(
    path: Path,
    panels: Sequence[PanelSpec],
    *,
    x_label: str = "",
    title: str = "",
    markers: Sequence[tuple[float, str]] | None = None,
    spans: Sequence[tuple[float, float, str]] | None = None,
    x_limits: tuple[float, float] | None = None,
) -> None:
    """Stack panels that share one x axis: force-curve and time-series plots.

    Parameters
    ----------
    path : Path
        The output file; must end in ``.png``.
    panels : sequence of dict
        Top to bottom.  Each holds ``series`` (as for
        :func:`write_line_plot_png`), and optionally ``y_label`` and
        ``title``, ``y_scale`` (``"linear"`` or ``"log"``) and ``twin``
        (``{"series": ..., "y_label": ...}``, lines on a right-hand y axis,
        e.g. z over an RMS).  Give approach and retract the same style in
        every panel (:data:`APPROACH_STYLE`, :data:`RETRACT_STYLE`).
    x_label : str, optional
        Shared x label, under the bottom panel, e.g. ``"z (nm)"``.
    title : str, optional
        Title over all panels.
    markers : sequence of (float, str), optional
        ``(x, label)`` dotted vertical lines through every panel, labelled
        in the top one.
    spans : sequence of (float, float, str), optional
        ``(x0, x1, label)`` shaded intervals through every panel (a
        free-air segment), in the top panel's legend.
    x_limits : (float, float), optional
        The x range shown (a zoomed segment); default: the data's.

    Examples
    --------
    >>> panels = [  # doctest: +SKIP
    ...     {"y_label": "f0' (kHz)", "series": [(z, f_app, "approach", APPROACH_STYLE),
    ...                                        (z, f_ret, "retract", RETRACT_STYLE)]},
    ...     {"y_label": "Q'", "series": [(z, q_app, "approach", APPROACH_STYLE)]},
    ... ]
    >>> write_multi_panel_png(Path("curve.png"), panels, x_label="z (nm)")  # doctest: +SKIP
    """
    path = _check_png_path(path)
    checked = _check_panels(panels)
    marks = _check_markers(markers)
    shaded = _check_spans(spans)

    width_in, height_in = 7.0, 1.9 * len(checked) + 1.1
    with _png_figure(path, width_in, height_in, layout=None) as fig:
        axes = fig.subplots(len(checked), 1, sharex=True, squeeze=False)[:, 0]
        _stacked_margins(
            fig, width_in, height_in, twin=any(panel.get("twin") for panel in panels),
            panel_titles=any(panel_title for _, _, panel_title in checked), title=bool(title),
        )
        for i, (ax, (lines, y_label, panel_title)) in enumerate(zip(axes, checked, strict=True)):
            _draw_spans(ax, shaded, labelled=i == 0)
            _draw_series(ax, lines)
            _draw_markers(ax, marks, labelled=i == 0)
            ax.set_ylabel(y_label)
            ax.set_yscale(panels[i].get("y_scale", "linear"))
            if panel_title:
                ax.set_title(panel_title, fontsize="medium")
            if panels[i].get("twin"):
                _draw_twin(ax, panels[i]["twin"], i)
        axes[-1].set_xlabel(x_label)
        if x_limits is not None:
            axes[-1].set_xlim(*(float(v) for v in x_limits))
        if title:
            fig.suptitle(title)
