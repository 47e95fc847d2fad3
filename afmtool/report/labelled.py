"""Labelled arrays: afmtool's captures and results as ``xarray.Dataset``, and as NetCDF or Zarr files.

One rule turns any result folder into a Dataset (:func:`result_dataset`), so
``result.to_xarray()`` and ``--format netcdf|zarr`` give the same thing:

* every series of the result HDF5 file (``reep.h5``, ``probeloss.h5`` ...)
  becomes a variable; a root-level series on the rows of ``t`` lies on the
  ``time`` coordinate (s), one on the rows of another time column
  (``t_mean``) on that one's; a group's series lie on the group's own
  coordinate when it has one (``z``, ``frequency_hz``: the ``z`` of a force
  curve's approach is the coordinate ``force_curve_approach_z``); images lie
  on ``line`` and ``pixel`` counts; any other array on its own index;
* every headline number (``report.json``'s ``headline``) becomes a scalar
  variable, with its standard deviation as ``<name>_std``;
* every variable and coordinate has ``units`` (CF: ``"1"`` for a
  dimensionless number) and ``long_name``; the Dataset's attrs hold the
  command, the afmtool version, the parameters and the inputs (as JSON
  text, which NetCDF can store) and ``Conventions = "CF-1.8"``.

NetCDF is written with h5netcdf (no compiled netCDF library), Zarr with zarr;
both read back with plain ``xarray.open_dataset`` / ``xarray.open_zarr``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from afmtool.errors import ConfigError

if TYPE_CHECKING:
    import xarray

__all__ = ["DATA_FORMATS", "SUFFIXES", "capture_dataset", "result_dataset", "write_dataset", "convert_result_files",
           "require_xarray"]

#: ``--format`` of the analysis commands, and the suffix each writes.
DATA_FORMATS = ("h5", "netcdf", "zarr")
SUFFIXES = {"h5": ".h5", "netcdf": ".nc", "zarr": ".zarr"}

#: Names of 1-D datasets that are the coordinate of the series beside them in their group.
_COORDINATES = ("z", "frequency_hz", "f_hz", "separation_nm", "z_nm", "t_s", "time_s", "bin_z")

#: Long names of the series a reader meets most (else the name, spaced).
_LONG_NAMES = {
    "t": "time", "f0_hz": "equivalent resonance frequency f0'", "q": "equivalent quality factor Q'",
    "f0_std_hz": "standard deviation of f0'", "q_std": "standard deviation of Q'", "amplitude": "oscillation amplitude",
    "phase_deg": "phase of the deflection against the drive", "sigma2": "noise variance estimate",
    "offset": "static deflection offset", "flag": "validity flags (0 = valid)", "b1": "denominator coefficient b1",
    "b0": "denominator coefficient b0", "index": "reliability index", "switch": "probe-loss switch (1 = lost)",
    "innovation": "EKF innovation", "innovation_mean": "innovation mean over an actuation period",
    "deflection": "cantilever deflection", "dither": "excitation (dither)", "z_piezo": "z-piezo position",
    "thermal_current": "thermal-sensor current", "v_sub": "substrate voltage", "v_r": "sensor voltage",
}


def require_xarray():
    """xarray, or one line saying how to get it."""
    try:
        import xarray
    except ImportError:
        raise ConfigError("labelled arrays need xarray: pip install 'afmtool[xarray]'") from None
    return xarray


def _units(text: str) -> str:
    return text if text else "1"


def _long_name(name: str) -> str:
    return _LONG_NAMES.get(name.split("/")[-1], name.replace("/", " ").replace("_", " "))


def _json_attrs(report: Mapping) -> dict:
    attrs = {"Conventions": "CF-1.8", "source": "afmtool"}
    for key in ("command", "afmtool_version"):
        if isinstance(report.get(key), str):
            attrs[key] = report[key]
    for key in ("parameters", "inputs", "warnings"):
        if key in report:
            attrs[key] = json.dumps(report[key], sort_keys=True)
    return attrs


def capture_dataset(capture, channels: Sequence[str] | None = None) -> xarray.Dataset:
    """A capture's samples on a ``time`` coordinate (s); the metadata as JSON in attrs."""
    xr = require_xarray()
    import numpy as np

    data = capture.read(channels)
    n = len(next(iter(data.values()))) if data else 0
    time = xr.Variable(("time",), np.arange(n) / capture.sample_rate_hz, {"units": "s", "long_name": "time"})
    units = capture.units
    variables = {name: xr.Variable(("time",), values, {"units": _units(units[name]), "long_name": _long_name(name)})
                 for name, values in data.items()}
    attrs = {"Conventions": "CF-1.8", "source": capture.source, "sample_rate_hz": capture.sample_rate_hz,
             "metadata": json.dumps(dict(capture.info.metadata), sort_keys=True, default=str)}
    return xr.Dataset(variables, coords={"time": time}, attrs=attrs)


# ----------------------------------------------------------------------------- result folders
def _read_h5(path: Path) -> list[tuple[str, Any, dict]]:
    """Every dataset of an afmtool result file: (path, values, attrs)."""
    from afmtool.io.result_files import read_all_datasets

    return read_all_datasets(path)


def _name(path: str) -> str:
    return re.sub(r"[^0-9A-Za-z_]", "_", path.strip("/").replace("/", "_"))


def _time_dims(items: list[tuple[str, Any, dict]]) -> dict[int, tuple[str, str]]:
    """Row count -> (dimension, source dataset) for root-level time columns (``t`` first)."""
    dims: dict[int, tuple[str, str]] = {}
    candidates = sorted((p for p, v, a in items if "/" not in p and v.ndim == 1 and a.get("units") == "s"
                         and (p == "t" or p.startswith("t_"))), key=lambda p: (p != "t", p))
    values = {p: v for p, v, _ in items}
    for path in candidates:
        dims.setdefault(len(values[path]), ("time" if path == "t" else f"time_{path[2:]}", path))
    return dims


def _variables(items: list[tuple[str, Any, dict]]) -> tuple[dict, dict]:
    """(coordinates, data variables) as xarray Variables from the file's datasets."""
    xr = require_xarray()
    import numpy as np

    time_dims = _time_dims(items)
    coords: dict[str, Any] = {}
    for dim, path in time_dims.values():
        values = next(v for p, v, _ in items if p == path)
        coords[dim] = xr.Variable((dim,), values, {"units": "s", "long_name": "time", "source_path": path})
    group_coords: dict[tuple[str, int], str] = {}
    for path, values, attrs in items:
        group, _, leaf = path.rpartition("/")
        if group and values.ndim == 1 and leaf in _COORDINATES:
            dim = _name(path)
            group_coords[(group, len(values))] = dim
            coords[dim] = xr.Variable((dim,), values, {"units": _units(str(attrs.get("units", ""))),
                                                      "long_name": _long_name(path)})
    data: dict[str, Any] = {}
    used_time = {path for _, path in time_dims.values()}
    for path, values, attrs in items:
        if path in used_time or _name(path) in coords:
            continue
        group = path.rpartition("/")[0]
        name = _name(path)
        if values.ndim == 1 and not group and len(values) in time_dims:
            dims = (time_dims[len(values)][0],)
        elif values.ndim == 1 and (group, len(values)) in group_coords:
            dims = (group_coords[(group, len(values))],)
        elif values.ndim == 2 and path.startswith("images/"):
            dims = (f"{name}_line", f"{name}_pixel")
        else:
            dims = tuple(f"{name}_dim{i}" for i in range(values.ndim))
        var_attrs = {"units": _units(str(attrs.get("units", ""))), "long_name": _long_name(path)}
        var_attrs.update({k: (v if isinstance(v, (str, int, float)) else str(v))
                          for k, v in attrs.items() if k != "units"})
        if values.dtype.kind in "OSU":
            values = np.asarray(values).astype(str)
        data[name] = xr.Variable(dims, values, var_attrs)
    return coords, data


def _index_coords(variables: Mapping[str, Any], coords: dict) -> None:
    """A dimensionless index coordinate (units "1") for every dimension without one."""
    xr = require_xarray()
    import numpy as np

    for variable in variables.values():
        for dim, size in zip(variable.dims, variable.shape):
            if dim not in coords:
                coords[dim] = xr.Variable((dim,), np.arange(size), {"units": "1", "long_name": f"{dim} index"})


def _headline_variables(report: Mapping) -> dict:
    """Each headline number as a scalar variable (units, long name), its std beside it."""
    xr = require_xarray()

    out: dict[str, Any] = {}
    for entry in report.get("headline") or ():
        value = entry.get("value")
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        name = "headline_" + _name(str(entry.get("source") or entry.get("name")))
        attrs = {"units": _units(str(entry.get("units") or "")), "long_name": str(entry.get("name")),
                 "headline_text": str(entry.get("text") or "")}
        out[name] = xr.Variable((), float(value), attrs)
        if isinstance(entry.get("std"), (int, float)):
            out[name + "_std"] = xr.Variable((), float(entry["std"]), {**attrs, "long_name": f"standard deviation of {entry.get('name')}"})
    return out


def result_dataset(folder: Path, report: Mapping, h5_names: Sequence[str] | None = None) -> xarray.Dataset:
    """The run in ``folder`` as one Dataset: its result file(s) and its headline (module docstring)."""
    xr = require_xarray()

    folder = Path(folder)
    names = list(h5_names) if h5_names is not None else sorted(
        n for n in report.get("outputs", ()) if str(n).endswith(".h5"))
    coords: dict[str, Any] = {}
    data: dict[str, Any] = {}
    for name in names:
        items = _read_h5(folder / name)
        file_coords, file_data = _variables(items)
        prefix = "" if len(names) == 1 else Path(name).stem + "_"
        coords.update(file_coords)
        data.update({prefix + k: v for k, v in file_data.items() if prefix + k not in coords})
    data.update(_headline_variables(report))
    _index_coords(data, coords)
    return xr.Dataset(data, coords=coords, attrs=_json_attrs(report))


def write_dataset(dataset: xarray.Dataset, path: Path | str, data_format: str) -> None:
    """``dataset`` as NetCDF (h5netcdf) or a Zarr store (a folder, or an fsspec URL)."""
    if data_format == "netcdf":
        try:
            import h5netcdf  # noqa: F401 - the engine, checked here so that the message says what is missing
        except ImportError:
            raise ConfigError("--format netcdf needs h5netcdf: pip install 'afmtool[xarray]'") from None
        dataset.to_netcdf(path, engine="h5netcdf", invalid_netcdf=False)
    elif data_format == "zarr":
        try:
            import zarr  # noqa: F401 - checked here, so that the message says what is missing
        except ImportError:
            raise ConfigError("--format zarr needs zarr: pip install 'afmtool[xarray]'") from None
        dataset.to_zarr(path, mode="w", consolidated=True)
    else:
        raise ConfigError(f"--format {data_format!r} must be one of {', '.join(DATA_FORMATS)}")


def convert_result_files(staged, report_stub: Mapping, data_format: str) -> None:
    """In a staged output folder, replace the result HDF5 files by one ``<stem>.nc`` or ``<stem>.zarr`` each.

    ``staged`` is the run's :class:`~afmtool.runtime.outputs.OutputDir`; ``report_stub``
    the report so far (command, parameters, inputs) for the attrs.
    """
    import shutil

    for name in [n for n in staged.names if n.endswith(".h5")]:
        source = staged.path(name)
        dataset = result_dataset(source.parent, report_stub, [name])
        target = staged.path(Path(name).stem + SUFFIXES[data_format])
        write_dataset(dataset, target, data_format)
        dataset.close()
        if source.is_dir():
            shutil.rmtree(source)
        else:
            source.unlink()
