"""The Python API (issue 30): the same code path as the CLI, labelled outputs, a light import.

* Each API function on the sample data: ``.save()`` gives the CLI's datasets
  bit for bit and the same report numbers (the report compared as the golden
  tests compare, paths of inputs and the private folder aside).
* ``afmtool.reep`` on ``Capture.from_arrays`` equals the CLI on the same
  samples written to HDF5.
* ``to_xarray()`` carries units on every variable and coordinate; ``--format
  netcdf`` and ``--format zarr`` open with plain xarray.
* ``import afmtool`` imports no numba, scipy, matplotlib or xarray;
  ``help(afmtool.reep)`` is numpydoc with parameters, units and an example.
"""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from tests.conftest import REPO, SAMPLE_DATA, run_cli
from tests.golden import _compare, _normalise


def _datasets(path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, (obj[()], dict(obj.attrs)))
                     if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_folder(api_dir, cli_dir, *, same_input_path: bool = True) -> None:
    """The same files; every HDF5 dataset bit for bit (values, dtype, attrs); the same report numbers."""
    api_report = json.loads((api_dir / "report.json").read_text())
    cli_report = json.loads((cli_dir / "report.json").read_text())
    if not same_input_path:  # arrays have no path; the samples' hash must still agree
        api_report["inputs"][0]["path"] = cli_report["inputs"][0]["path"]
    assert api_report["outputs"] == cli_report["outputs"]
    for name in cli_report["outputs"]:
        if name.endswith(".h5"):
            api, cli = _datasets(api_dir / name), _datasets(cli_dir / name)
            assert api.keys() == cli.keys(), name
            for key, (values, attrs) in cli.items():
                assert api[key][0].dtype == values.dtype, key
                assert api[key][0].tobytes() == values.tobytes(), f"{name}/{key} differs"
                assert api[key][1].keys() == attrs.keys()
    problems: list[str] = []
    _compare(_normalise(cli_report), _normalise(api_report), "report", problems)
    assert not problems, problems[:10]
    assert api_report["headline"] == cli_report["headline"]


def _cli(tmp_path, name, *args):
    out = tmp_path / f"cli_{name}"
    result = run_cli(*args, "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr.decode()
    return out


# --------------------------------------------------------------------------- each function against its command
@pytest.mark.long
def test_capture_commands_equal_the_cli(tmp_path):
    import afmtool

    cases = [
        ("reep", afmtool.reep, ["reep", SAMPLE_DATA / "ltv_step.h5"], {}),
        ("identify freeair", afmtool.identify_freeair, ["identify", "freeair", SAMPLE_DATA / "ltv_step.h5"], {}),
        ("decode", afmtool.decode, ["decode", SAMPLE_DATA / "bits_30khz.h5", "--bit-rate", "30000"],
         {"bit_rate_hz": 30000}),
    ]
    runs = {}
    for name, function, args, params in cases:
        cli = _cli(tmp_path, name.replace(" ", "_"), *args)
        result = runs[name] = function(args[-1] if not params else args[1], **params)
        assert_same_folder(result.save(tmp_path / f"api_{name.replace(' ', '_')}"), cli)
        assert result.summary and all(entry.text for entry in result.summary)
    from afmtool.records.decode import DecodeMode, DecodeResults
    from afmtool.records.freeair import FreeAirResults, FreeAirRoute

    freeair, decoded = runs["identify freeair"].results, runs["decode"].results  # the typed records (issue 29)
    assert isinstance(freeair, FreeAirResults) and freeair.route is FreeAirRoute.SEGMENT
    assert isinstance(decoded, DecodeResults) and decoded.mode is DecodeMode.BITS and decoded.truth.decoder.errors == 0
    for name in ("identify freeair", "decode"):
        assert runs[name].results.to_json() == runs[name].report["results"]
    assert runs["decode"].summary["bits decoded"].value == decoded.bits.count


@pytest.mark.long
def test_probeloss_kalman_bank_and_gamma_equal_the_cli(tmp_path):
    import afmtool

    cli = _cli(tmp_path, "probeloss", "probeloss", SAMPLE_DATA / "raster_grating.h5")
    assert_same_folder(afmtool.probeloss(SAMPLE_DATA / "raster_grating.h5").save(tmp_path / "api_pl"), cli)
    cli = _cli(tmp_path, "bank", "kalman-bank", SAMPLE_DATA / "force_curve_thesis.h5")
    assert_same_folder(afmtool.kalman_bank(SAMPLE_DATA / "force_curve_thesis.h5").save(tmp_path / "api_bank"), cli)
    near, contact = SAMPLE_DATA / "thermal_sweep_near.h5", SAMPLE_DATA / "thermal_sweep_contact.h5"
    cli = _cli(tmp_path, "gamma", "identify", "gamma", near, "--contact", contact)
    gamma = afmtool.identify_gamma(near, contact)
    assert_same_folder(gamma.save(tmp_path / "api_gamma"), cli)
    from afmtool.records.gamma import GammaResults, ResponseMethod

    typed = gamma.results  # the typed record, read back from report.json
    assert isinstance(typed, GammaResults) and typed.method is ResponseMethod.H1
    assert typed.to_json() == gamma.report["results"]
    assert gamma.summary["feed-through capacitance"].value == typed.feedthrough_fit.capacitance_pf


@pytest.mark.slow  # 90 s of CI; the capture commands' API-vs-CLI tests run in CI
def test_theory_design_and_ch6_functions_equal_the_cli(tmp_path):
    import afmtool

    reep_cli = _cli(tmp_path, "reep_fc", "reep", SAMPLE_DATA / "tapping_force_curve.h5")
    run = afmtool.reep(SAMPLE_DATA / "tapping_force_curve.h5")
    assert_same_folder(run.save(tmp_path / "api_reep_fc"), reep_cli)
    assert_same_folder(afmtool.theory_compare(run).save(tmp_path / "api_cmp"),
                       _cli(tmp_path, "cmp", "theory", "compare", reep_cli))
    assert_same_folder(afmtool.theory_fit(run).save(tmp_path / "api_fit"), _cli(tmp_path, "fit", "theory", "fit", reep_cli))
    assert_same_folder(afmtool.theory_averaging(force_set="attractive").save(tmp_path / "api_avg"),
                       _cli(tmp_path, "avg", "theory", "averaging", "--force-set", "attractive"))
    fa = _cli(tmp_path, "fa", "identify", "freeair", SAMPLE_DATA / "ltv_step.h5")
    assert_same_folder(afmtool.design_excitation(fa, amplitude_nm=20).save(tmp_path / "api_ex"),
                       _cli(tmp_path, "ex", "design", "excitation", "--model", fa, "--amplitude", "20"))
    for scenario, command, function, key in (("iv-ramp", ["identify", "thermal", "--iv"], afmtool.identify_thermal, "iv"),
                                             ("es-approach", ["identify", "electrostatic"], afmtool.identify_electrostatic, None)):
        capture = tmp_path / f"{scenario}.h5"
        assert run_cli("simulate", scenario, "-o", capture, "-q").returncode == 0
        cli = _cli(tmp_path, scenario, *command, capture)
        result = function(**{key: capture}) if key else function(capture)
        assert_same_folder(result.save(tmp_path / f"api_{scenario}"), cli)
        assert result.results.to_json() == result.report["results"]  # the typed record (issue 29, item 2)
    from afmtool.records.electrostatic import ParameterStatus, Sensor

    assert result.results.sensor is Sensor.OPTICAL and result.results.parameters.tip_height_m is None
    assert result.results.parameters.l0_m.status is ParameterStatus.IDENTIFIED


def test_identify_invols_equals_the_cli(tmp_path, rng):
    import afmtool
    from tests.test_invols import _hard_contact_curve, _write_curve

    z, volts = _hard_contact_curve(rng)
    curve = tmp_path / "curve.h5"
    _write_curve(curve, z, volts, metadata={"cantilever": {"deflection_sensitivity_nm_per_v": 50.0}})
    cli = _cli(tmp_path, "invols", "identify", "invols", curve)
    result = afmtool.identify_invols(curve)
    assert_same_folder(result.save(tmp_path / "api_invols"), cli)
    from afmtool.records.invols import InvolsResults, Leg

    typed = result.results  # the typed record, read back from report.json
    assert isinstance(typed, InvolsResults) and typed.leg is Leg.APPROACH
    assert typed.to_json() == result.report["results"]
    assert result.summary["InvOLS (contact slope)"].value == typed.invols_nm_per_v
    assert result.summary[0].units == "nm/V"


# --------------------------------------------------------------------------- arrays in, the CLI on the same samples
@pytest.mark.long
def test_reep_on_arrays_equals_the_cli_on_the_same_samples_in_hdf5(tmp_path):
    import afmtool
    from afmtool.io.capture import ChannelSpec
    from afmtool.io.registry import create_writer

    fs, f0, n = 500e3, 70e3, 30000
    rng = np.random.default_rng(3)
    t = np.arange(n) / fs
    dither = 0.1 * np.cos(2 * np.pi * f0 * t) + 0.05 * np.cos(2 * np.pi * (f0 + 6e3) * t)
    # a second-order lever (f0 70 kHz, Q 150) driven by the dither: an exact recursion, plus noise
    w, q = 2 * np.pi * f0 / fs, 150.0
    r = np.exp(-w / (2 * q))
    b1, b0 = -2 * r * np.cos(w * np.sqrt(1 - 1 / (4 * q * q))), r * r
    deflection = np.zeros(n)
    for i in range(2, n):
        deflection[i] = -b1 * deflection[i - 1] - b0 * deflection[i - 2] + 3.0 * dither[i - 1]
    deflection += rng.normal(0, 0.02, n)
    metadata = {"free_air": {"start_s": 0.0, "end_s": 0.02}, "drive": {"frequency_hz": f0}}

    cap = afmtool.Capture.from_arrays(fs, deflection=deflection, dither=dither, metadata=metadata)
    assert cap.channels == ("deflection", "dither") and cap.units == {"deflection": "nm", "dither": "V"}
    run = afmtool.reep(cap)
    api = run.save(tmp_path / "api")
    from afmtool.records.reep import ReepResults

    typed = run.results  # reep's typed record, read back from report.json
    assert isinstance(typed, ReepResults) and typed.to_json() == run.report["results"]
    assert run.summary["f0' in the free-air segment"].value == typed.segments.free_air.f0_hz.mean

    path = tmp_path / "same.h5"
    writer = create_writer(path, "hdf5", fs, [ChannelSpec("deflection", "nm"), ChannelSpec("dither", "V")], metadata)
    writer.write({"deflection": deflection, "dither": dither})
    writer.close()
    assert_same_folder(api, _cli(tmp_path, "arrays", "reep", path), same_input_path=False)


# --------------------------------------------------------------------------- labelled outputs
def _assert_units_everywhere(ds) -> None:
    for name, variable in {**ds.data_vars, **ds.coords}.items():
        assert isinstance(variable.attrs.get("units"), str) and variable.attrs["units"], f"{name} has no units"
        assert variable.attrs.get("long_name"), name


@pytest.mark.long
def test_to_xarray_and_netcdf_zarr_outputs(tmp_path):
    import afmtool

    run = afmtool.reep(SAMPLE_DATA / "tapping_force_curve.h5")
    ds = run.to_xarray()
    _assert_units_everywhere(ds)
    assert ds["f0_hz"].dims == ("time",) and ds["time"].attrs["units"] == "s"
    assert ds["f0_hz"].attrs["units"] == "Hz" and ds["q"].attrs["units"] == "1"
    assert ds["f0_std_hz"].attrs["units"] == "Hz"
    assert any(dim.endswith("_z") for dim in ds["force_curve_approach_f0_hz"].dims)
    assert json.loads(ds.attrs["parameters"])["lam"] == run.parameters["lam"]
    with h5py.File(run.path("reep.h5")) as f:
        np.testing.assert_array_equal(ds["f0_hz"].values, f["f0_hz"][()])

    capture_ds = afmtool.open(SAMPLE_DATA / "ltv_step.h5").to_xarray()
    _assert_units_everywhere(capture_ds)

    # --format netcdf / zarr: plain xarray, in a process that never imports afmtool
    for fmt, opener, name in (("netcdf", "open_dataset", "reep.nc"), ("zarr", "open_zarr", "reep.zarr")):
        out = tmp_path / fmt
        result = run_cli("reep", SAMPLE_DATA / "tapping_force_curve.h5", "--format", fmt, "--out", out, "--quiet")
        assert result.returncode == 0, result.stderr.decode()
        report = json.loads((out / "report.json").read_text())
        assert name in report["outputs"] and "reep.h5" not in report["outputs"]
        script = (
            "import sys, json, xarray\n"
            f"ds = xarray.{opener}(sys.argv[1])\n"
            "assert 'afmtool' not in sys.modules\n"
            "bad = [n for n, v in {**ds.data_vars, **ds.coords}.items() if not v.attrs.get('units')]\n"
            "print(json.dumps({'bad': bad, 'f0': float(ds['f0_hz'].mean()), 'units': ds['f0_hz'].attrs['units']}))\n"
        )
        done = subprocess.run([sys.executable, "-c", script, str(out / name)], capture_output=True, text=True,
                              cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        seen = json.loads(done.stdout)
        assert seen["bad"] == [] and seen["units"] == "Hz"
        assert seen["f0"] == pytest.approx(float(ds["f0_hz"].mean()), rel=1e-12)


# --------------------------------------------------------------------------- light import, help, errors
def test_import_afmtool_loads_no_heavy_module():
    script = ("import sys, afmtool\n"
              "heavy = [m for m in ('numba', 'scipy', 'matplotlib', 'xarray', 'numpy', 'h5py') if m in sys.modules]\n"
              "assert not heavy, heavy\n"
              "afmtool.reep, afmtool.Capture, afmtool.open\n"
              "heavy = [m for m in ('numba', 'scipy', 'matplotlib', 'xarray') if m in sys.modules]\n"
              "assert not heavy, heavy\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr


def test_help_reep_is_numpydoc_with_parameters_units_and_an_example():
    import pydoc

    import afmtool

    text = pydoc.render_doc(afmtool.reep, renderer=pydoc.plaintext)
    for section in ("Parameters\n", "Returns\n", "Examples\n", ">>> "):
        assert section in text, section
    assert "window_us : float, default 400.0 [µs]" in text and "lam : float, default 0.0" in text
    assert "f0_hz : float, default 0.0 [Hz]" in text
    assert "free_air : str, default '' [s]" in text
    import inspect

    assert inspect.signature(afmtool.reep).parameters["window_us"].default == 400.0
    assert set(afmtool.__all__) >= {"reep", "probeloss", "kalman_bank", "decode", "identify_freeair", "identify_invols",
                                    "identify_gamma", "identify_thermal", "identify_electrostatic", "design_excitation",
                                    "theory_averaging", "theory_compare", "theory_fit", "open", "Capture"}


def test_errors_are_afmtools_own_with_the_clis_line(tmp_path):
    import afmtool

    with pytest.raises(afmtool.InputError, match="no such file"):
        afmtool.open(tmp_path / "missing.h5")
    with pytest.raises(afmtool.ConfigError, match="takes no parameter 'lamda'"):
        afmtool.reep(SAMPLE_DATA / "ltv_step.h5", lamda=0.9)
    with pytest.raises(afmtool.ConfigError) as api_error:
        afmtool.reep(SAMPLE_DATA / "ltv_step.h5", lam=1.5)
    cli = run_cli("reep", SAMPLE_DATA / "ltv_step.h5", "--lambda", "1.5", "--out", tmp_path / "x")
    assert cli.returncode == 2 and str(api_error.value) in cli.stderr.decode()


@pytest.mark.long
def test_stream_yields_the_files_rows_chunk_by_chunk():
    import afmtool

    run = afmtool.reep(SAMPLE_DATA / "ltv_step.h5", decimate=10)
    chunks = list(afmtool.reep(SAMPLE_DATA / "ltv_step.h5", decimate=10, stream=True, chunk_samples=4096))
    assert len(chunks) > 3
    with h5py.File(run.path("reep.h5")) as f:
        for name in ("t", "f0_hz", "q"):
            # the stream yields float64; the file stores f0' and Q' as float32 (issue 33), rounded to nearest
            streamed = np.concatenate([c[name] for c in chunks]).astype(f[name].dtype)
            np.testing.assert_array_equal(streamed, f[name][()])
    ds = chunks[0].to_xarray()
    assert ds["f0_hz"].attrs["units"] == "Hz" and ds["time"].attrs["units"] == "s"
    # abandoning the iterator ends the run
    iterator = afmtool.reep(SAMPLE_DATA / "ltv_step.h5", stream=True, chunk_samples=1024)
    next(iterator)
    iterator.close()
