"""Typed data across module boundaries (issue 15 item 4).

- afmtool's own HDF5 outputs are opened only in ``afmtool/io/``: no module
  elsewhere imports h5py or calls ``h5py.File`` (an AST scan of the package).
- Capture metadata is validated and typed once, when the capture is opened:
  a bad value of any key family is an InputError naming the key and the file.
- Each output reader round-trips what the command wrote.
- ``theory compare`` reads REEP's capture through the reader registry (CSV).
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.metadata import CaptureMetadata
from afmtool.io.registry import open_capture

PACKAGE = Path(__file__).resolve().parents[1] / "afmtool"


def _h5py_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) of every h5py import and ``h5py.File`` / ``File`` from h5py in ``tree``."""
    uses = []
    file_aliases = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            uses += [(node.lineno, f"import {a.name}") for a in node.names if a.name.split(".")[0] == "h5py"]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "h5py":
            uses.append((node.lineno, f"from {node.module} import ..."))
            file_aliases |= {a.asname or a.name for a in node.names if a.name == "File"}
        elif isinstance(node, ast.Attribute) and node.attr == "File" and isinstance(node.value, ast.Name) \
                and node.value.id == "h5py":
            uses.append((node.lineno, "h5py.File"))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in file_aliases:
            uses.append((node.lineno, f"{node.func.id}(...)"))
    return uses


def test_the_scan_finds_what_it_looks_for():
    source = "import h5py\nfrom h5py import File as F\nh5py.File('x')\nF('y')\ndef f(x: h5py.File): ...\n"
    assert [what for _, what in sorted(_h5py_uses(ast.parse(source)))] == [
        "import h5py", "from h5py import ...", "h5py.File", "F(...)", "h5py.File"]
    assert _h5py_uses(ast.parse("import numpy\nsys.modules.get('h5py')\n")) == []


def test_no_h5py_outside_io():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if relative.parts[0] == "io":
            continue
        for line, what in _h5py_uses(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            offenders.append(f"afmtool/{relative}:{line}: {what}")
    assert not offenders, "h5py outside afmtool/io/ (open afmtool outputs through the io/ readers):\n" + "\n".join(offenders)


# --------------------------------------------------------------------------- CaptureMetadata at open time

NAN = float("nan")
_FORCE = {"d_nm": 4.0, "omega_a2_per_s2": 9.6e10, "omega_b2_per_s2": 9.2e12, "c_a_per_s": 4.2e4, "c_b_per_s": 0.0}

#: (key family, bad metadata, the key the message must name)
BAD_BY_FAMILY = [
    ("cantilever", {"cantilever": {"q": -3.0}}, "cantilever.q"),
    ("cantilever huge", {"cantilever": {"f0_hz": 10**400}}, "cantilever.f0_hz"),  # was an OverflowError
    ("drive", {"drive": {"free_amplitude_nm": NAN}}, "drive.free_amplitude_nm"),
    ("drive lines", {"drive": {"lines": [{"frequency_hz": 7e4, "amplitude_v": "1"}]}}, "drive.lines[0].amplitude_v"),
    ("drive hold", {"drive": {"hold": 1}}, "drive.hold"),
    ("controller", {"controller": {"setpoint_nm": NAN}}, "controller.setpoint_nm"),
    ("controller object", {"controller": [1, 2]}, "controller"),
    ("electrostatic", {"electrostatic": {"k_esf_f_m": -1e-19}}, "electrostatic.k_esf_f_m"),
    ("electrostatic tip", {"electrostatic": {"tip_height_m": "tall"}}, "electrostatic.tip_height_m"),
    ("nominal", {"nominal": {"start_s": 0.1, "end_s": 0.05}}, "nominal.end_s"),
    ("nominal missing", {"nominal": {"start_s": 0.0}}, "nominal needs end_s"),
    ("ramp", {"ramp": {"v_r_v": float("inf")}}, "ramp.v_r_v"),
    ("ramp kind", {"ramp": {"kind": 3}}, "ramp.kind"),
    ("force", {"force": {**_FORCE, "d_nm": -4.0}}, "force.d_nm"),
    ("force incomplete", {"force": {"d_nm": 4.0}}, "force needs omega_a2_per_s2"),
    ("free_air", {"free_air": {"start_s": -1.0, "end_s": 1.0}}, "free_air.start_s"),
    ("scan", {"scan": {"lines": 0, "pixels_per_line": 4, "scan_size_m": 1e-6, "line_rate_hz": 1.0}}, "scan.lines"),
    ("segments", {"segments": [{"start_s": 0.0, "end_s": 1.0, "frequency_hz": 0.0}]}, "segments[0].frequency_hz"),
]


def _h5_capture(path: Path, metadata: dict) -> Path:
    with h5py.File(path, "w") as h5:
        h5.attrs["sample_rate_hz"] = 1000.0
        # allow_nan: Python's json writes NaN and inf, and reads them back; the validator must catch them
        h5.attrs["metadata"] = json.dumps(metadata, allow_nan=True)
        h5.create_dataset("channels/deflection", data=np.zeros(16)).attrs["units"] = "nm"
    return path


@pytest.mark.parametrize(("family", "metadata", "key"), BAD_BY_FAMILY, ids=[b[0] for b in BAD_BY_FAMILY])
def test_a_bad_metadata_value_fails_at_open_naming_key_and_file(tmp_path, family, metadata, key):
    path = _h5_capture(tmp_path / "bad.h5", metadata)
    with pytest.raises(InputError) as error:
        open_capture(path)
    message = str(error.value)
    assert str(path) in message and key in message, message
    assert "\n" not in message
    # the same check runs on metadata that did not come from JSON (an instrument reader's, a view's)
    with pytest.raises(InputError, match=key.replace("[", r"\[").replace("]", r"\]")):
        CaptureMetadata.from_mapping(metadata, "capture.x")


def test_csv_metadata_is_validated_at_open_too(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text('# sample_rate_hz: 1000\n# metadata: {"controller": {"setpoint_nm": -2}}\nt,deflection\n0,0\n0.001,1\n')
    with pytest.raises(InputError, match=r"bad\.csv.*controller\.setpoint_nm"):
        open_capture(path).info  # noqa: B018 - opening is the test


def test_good_metadata_is_typed(tmp_path):
    metadata = {
        "cantilever": {"f0_hz": 70_000, "q": 200, "spring_constant_n_per_m": 2.0},
        "drive": {"frequency_hz": 70_000.0, "sideband_offset_hz": 6000, "free_amplitude_nm": 20.0, "hold": "zoh",
                  "lines": [{"frequency_hz": 70_000.0, "amplitude_v": 0.1, "phase_deg": 30.0}]},
        "controller": {"setpoint_nm": 14.0, "mode": "switching", "kp_low": 0.1},
        "electrostatic": {"k_esf_f_m": 1.5e-19, "alpha_r": 0.3, "l0_m": 2e-7, "tip_height_m": 0.0},
        "nominal": {"start_s": 0.0, "end_s": 0.004},
        "ramp": {"kind": "v_sub triangle", "v_r_v": -3.0, "v_sub_max_v": 8.0},
        "force": {**_FORCE, "set": "attractive"},
        "free_air": {"start_s": 0.0, "end_s": 0.002},
        "scan": {"lines": 4, "pixels_per_line": 8, "scan_size_m": 1e-6, "line_rate_hz": 2.0, "trace_retrace": False},
        "segments": [{"start_s": 0.0, "end_s": 0.01, "frequency_hz": 1000}],
        "scenario": "hand-written",
        "operator": "free-form",
    }
    with open_capture(_h5_capture(tmp_path / "good.h5", metadata)) as reader:
        meta = reader.info.capture_metadata
    assert meta.cantilever.f0_hz == 70_000.0 and meta.cantilever.deflection_sensitivity_nm_per_v is None
    assert meta.drive.sideband_offset_hz == 6000.0 and meta.drive.held and meta.drive.lines[0].phase_deg == 30.0
    assert meta.controller.setpoint_nm == 14.0 and meta.controller.mode == "switching"
    assert meta.electrostatic.l0_m == 2e-7 and meta.electrostatic.tip_height_m == 0.0
    assert (meta.nominal.start_s, meta.nominal.end_s) == (0.0, 0.004)
    assert meta.ramp.v_r_v == -3.0 and meta.ramp.kind == "v_sub triangle"
    assert meta.force.d_nm == 4.0 and meta.force.set == "attractive"
    assert meta.scan.lines == 4 and meta.scan.trace_retrace is False and meta.scan.start_s == 0.0
    assert meta.segments[0].frequency_hz == 1000.0 and meta.scenario == "hand-written"
    assert meta.raw["operator"] == "free-form"
    empty = CaptureMetadata.from_mapping({})
    assert empty.controller.setpoint_nm is None and empty.force is None and empty.scan is None


def test_every_simulator_writes_metadata_the_typed_parser_accepts():
    from afmtool import sim

    for name in sim.scenario_names():
        captured = sim.simulate(name, {"duration_s": 0.002}, seed=0)
        CaptureMetadata.from_mapping(captured.metadata, name)


def test_bad_metadata_is_exit_2_one_line_before_any_output(tmp_path):
    from tests.conftest import run_cli

    path = _h5_capture(tmp_path / "bad.h5", {"ramp": {"v_r_v": NAN}})
    result = run_cli("reep", path, "--out", tmp_path / "out")
    lines = result.stderr.decode().strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and "ramp.v_r_v" in lines[0] and "bad.h5" in lines[0]
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- theory compare through the registry


@pytest.mark.long
def test_theory_compare_reads_a_csv_capture_through_the_registry(tmp_path):
    """REEP on a CSV (converted from a reference-simulator force curve) compares with theory like on HDF5.

    CSV carries no /truth, so the separation comes from z_piezo; the force law
    and cantilever come from the CSV's metadata, which only the registry's CSV
    reader can open.
    """
    from afmtool.analyses.convert import convert_capture
    from tests import reference_sim as rs
    from tests.conftest import run_cli, validate_report
    from tests.test_kalman_bank_reference import _force_curve

    f0, q, fs, start_nm = 80318.0, 168.0, 500e3, 30.0
    capture = rs.simulate(
        f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.2,
        drive=rs.three_sine(f0, 6000.0, 20.0 / q, 0.25), noise_nm=0.05, seed=5,
        force=rs.PiecewiseLinearForce(4.0, 0.31e6**2, 3.03e6**2, 0.042e6, 0.0),
        separation_nm=_force_curve(0.2, start_nm=start_nm), record_z_piezo=True,
    )
    h5_path = rs.write_capture_h5(tmp_path / "curve.h5", capture)
    csv_path = tmp_path / "curve.csv"
    with open_capture(h5_path) as reader:
        convert_capture(reader, csv_path, "csv")
    h5_path.unlink()  # only the CSV is left to read
    assert run_cli("reep", csv_path, "--out", tmp_path / "reep", "-q").returncode == 0
    result = run_cli("theory", "compare", tmp_path / "reep", "--out", tmp_path / "cmp", "--json")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    results = report["results"]
    contact_error = results["separation"]["contact_z"] + start_nm
    print(f"CSV capture: contact point error {contact_error:+.3f} nm (tol 1); {results['verdict']}")
    assert results["force_set"] == "metadata"  # the force law of the CSV's metadata
    assert results["separation"]["source"] == "z-piezo"
    assert abs(contact_error) <= 1.0
    assert results["pass"] is True
    assert {"path": str(csv_path), "role": "capture"}.items() <= report["inputs"][-1].items()


# --------------------------------------------------------------------------- output readers


def test_result_file_reads_back_what_the_result_writer_wrote(tmp_path):
    from afmtool.io.result_files import open_result_file
    from afmtool.io.results import ResultWriter

    n = 50_000
    t = np.arange(n) / 1000.0
    flag = (np.arange(n) % 7 == 0).astype(np.uint8)
    with ResultWriter(tmp_path / "r.h5", {"t": "s", "x": "nm"}, {"afmtool_command": "test"}) as writer:
        for start in range(0, n, 12_345):
            writer.append({"t": t[start:start + 12_345], "x": 2 * t[start:start + 12_345], "flag": flag[start:start + 12_345]})
    with open_result_file(tmp_path / "r.h5", required=("t", "x")) as result:
        assert result.attrs["afmtool_command"] == "test" and result.units("x") == "nm"
        rows = result.read_rows(("x", "absent"), max_points=1000)
        assert len(rows["t"]) <= 1000 and "absent" not in rows
        np.testing.assert_array_equal(rows["x"], 2 * t[rows["_rows"]])
        window = result.read_rows(("x",), t_range=(10.0, 10.5))
        np.testing.assert_array_equal(window["t"], t[(t >= 10.0) & (t < 10.5)])
        trusted = result.trusted("x", slice(None))
        np.testing.assert_array_equal(np.isnan(trusted), flag != 0)
        blocks = list(result.blocks("x", block_rows=20_000))
        assert [b[0] for b in blocks] == [0, 20_000, 40_000]
        np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), 2 * t)
    with open_result_file(tmp_path / "r.h5", mode="r+") as result:
        result.put("tables/x", [1.0, 2.0], "nm", {"row0": "first"})
        columns = result.create_columns("derived", {"y": "N"}, n)
        columns["y"][:] = 3.0
    with open_result_file(tmp_path / "r.h5", required=("tables/x", "derived/y")) as result:
        assert result.units("tables/x") == "nm" and result["tables/x"].attrs["row0"] == "first"
        assert result.names("derived") == ("y",) and result.units("derived/y") == "N"
    with pytest.raises(InputError, match="no nope"):
        open_result_file(tmp_path / "r.h5", required=("nope",))
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(InputError, match="not an HDF5 file"):
        open_result_file(tmp_path / "text.h5")
    with pytest.raises(InputError, match="no such"):
        open_result_file(tmp_path / "missing.h5")


def test_reep_results_round_trip(tmp_path):
    from afmtool.io.reep_results import open_reep_results
    from afmtool.io.results import ResultWriter

    n = 100
    with ResultWriter(tmp_path / "reep.h5", {"t": "s", "z": ""}) as writer:
        writer.append({name: np.arange(n, dtype=float) for name in ("t", "b1", "b0", "f0_hz", "q", "amplitude", "z")}
                      | {"flag": np.zeros(n, dtype=np.uint8)})
        writer.put("force_curve/approach/z", np.arange(3.0), "V")
    report = {"inputs": [{"path": "capture.csv", "role": "capture"}], "results": {"drive_frequency_hz": 7e4}}
    (tmp_path / "report.json").write_text(json.dumps(report))
    with open_reep_results(tmp_path) as reep:
        assert set(reep.series) == {"t", "b1", "b0", "f0_hz", "q", "amplitude", "z", "flag"}
        assert reep.z_units == "V"  # the series has none: the force-curve table's
        assert reep.report == report["results"] and reep.inputs == tuple(report["inputs"])
        assert reep.free_air_model is None
        np.testing.assert_array_equal(reep.file.trusted("q", slice(None)), np.arange(n))
    with pytest.raises(InputError, match="--reep .*no reep.h5 there"):
        open_reep_results(tmp_path / "nowhere")
    (tmp_path / "report.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="not an afmtool report"):
        open_reep_results(tmp_path)


def test_bank_gamma_probeloss_decode_readers_round_trip(tmp_path):
    from afmtool.io.bank_results import read_bank_rms
    from afmtool.io.gamma_results import read_gamma_ir_ts
    from afmtool.io.matrix_results import MatrixResultWriter
    from afmtool.io.result_files import open_decode_results, open_probeloss_results
    from afmtool.io.results import ResultWriter

    n = 45_000
    rms = np.vstack([np.arange(n), 2 * np.arange(n)]).astype(float)
    with MatrixResultWriter(tmp_path / "bank.h5", {}) as writer:
        writer.append({"t": np.arange(n) / 1e3, "rms": rms, "adaptive_rms": np.ones(n)})
    bank = read_bank_rms(tmp_path, max_points=10_000)
    assert bank.z is None and bank.rms.shape == (2, len(bank.t)) and len(bank.t) == 9000
    np.testing.assert_array_equal(bank.rms[1], 2 * rms[0, ::5])

    f = np.linspace(100.0, 1000.0, 8)
    h = (1 + 1j) * f
    with ResultWriter(tmp_path / "gamma.h5", {}, {"thermal_current_mean_ua": 12.5}) as writer:
        for name, values in (("frequency_hz", f), ("ir_ts", h), ("coherence_ir_ts", np.ones(8)),
                             ("magnitude_std_ir_ts", 0.1 * np.abs(h))):
            writer.put(f"frf/{name}", values)
    gamma = read_gamma_ir_ts(tmp_path)
    np.testing.assert_array_equal(gamma.ir_ts.response, h)
    np.testing.assert_allclose(gamma.ir_ts.phase_std_rad, 0.1)
    assert gamma.thermal_current_mean_ua == 12.5
    with ResultWriter(tmp_path / "other.h5", {}) as writer:
        writer.put("frf/frequency_hz", f)
    with pytest.raises(InputError, match="not a gamma.h5 .*no frf/ir_ts"):
        read_gamma_ir_ts(tmp_path / "other.h5")

    with ResultWriter(tmp_path / "probeloss.h5", {"index": ""}) as writer:
        writer.append({"t": np.arange(10.0), "index": np.arange(10.0)})
    with open_probeloss_results(tmp_path) as probeloss:
        assert probeloss.read_rows(("index",))["index"].tolist() == list(range(10))
    with ResultWriter(tmp_path / "decode.h5", {}) as writer:
        writer.put("bit_times_s", np.arange(4.0))
        writer.put("bits", np.array([0, 1, 1, 0]))
    with open_decode_results(tmp_path) as decoded:
        assert decoded.read_rows(("bits",), time="bit_times_s")["bits"].tolist() == [0, 1, 1, 0]


# --------------------------------------------------------------------------- result records


def test_result_records_are_frozen_and_write_their_report_section():
    """reep's, probeloss's and kalman-bank's results are typed records: each result's report section is its record's."""
    import dataclasses

    from afmtool.analyses.kalman_bank import KalmanBankResult
    from afmtool.analyses.probeloss import ProbeLossResult
    from afmtool.analyses.reep import ReepResult
    from afmtool.records.kalman_bank import KalmanBankResults
    from afmtool.records.probeloss import ProbeLossResults
    from afmtool.records.reep import ReepResults
    from tests.golden import GOLDEN_DIR

    bank_fields = {f.name for f in dataclasses.fields(KalmanBankResult)} - {"results", "warnings"}
    for golden, record, result in (
        ("reep_ltv_step", ReepResults, lambda r: ReepResult(r, ())),
        ("probeloss_raster_grating", ProbeLossResults, lambda r: ProbeLossResult(r, ())),
        ("kalman_bank_force_curve_thesis", KalmanBankResults,
         lambda r: KalmanBankResult(r, (), **dict.fromkeys(bank_fields))),
    ):
        section = json.loads((GOLDEN_DIR / f"{golden}.json").read_text())["results"]
        made = result(record.from_json(section))
        assert made.to_json() == section, golden
        json.dumps(made.to_json(), allow_nan=False)
        with pytest.raises(dataclasses.FrozenInstanceError):
            made.results = {}  # type: ignore[misc]


def test_theory_compare_result_is_the_report_section():
    import dataclasses

    from afmtool.analyses.theory import ComparisonBins, TheoryComparison
    from afmtool.analyses.theory_outputs import compare_results
    from afmtool.records.theory_compare import BeatRecord, CompareForceRecord, SeparationRecord, SeparationSource

    one = np.ones(1)
    bins = ComparisonBins(np.zeros(1, dtype=int), 10.5 * one, 40 * one, -98.0 * one, -100.0 * one, 1.0 * one,
                          0.5 * one, 0.2 * one, -3.0 * one, -3.1 * one, 0.1 * one, 0.05 * one, 0.1 * one,
                          np.ones(1, dtype=bool), ("",))
    comparison = TheoryComparison(np.array([True, False, True]), np.zeros(3), np.zeros(3), bins, 7e4, 200.0,
                                  "REEP's median", "REEP's per-row f0_std_hz, q_std", 0.03, 0.1, True, "agree",
                                  0.0, 0.025, 6.9, 1)
    result = compare_results(CompareForceRecord(source="attractive", spec="d=4"), 20.0,
                             SeparationRecord(source=SeparationSource.TRUTH), comparison,
                             BeatRecord(modulation=0.03, lines=((7e4, 1.0),), lines_from="metadata"))
    section = result.to_json()
    assert section["force_set"] == "attractive" and section["separation"] == {"source": "truth"}
    assert section["force"] == {"source": "attractive", "spec": "d=4"}
    assert section["pass"] is True and section["verdict"] == "agree" and section["compared_rows"] == 2
    assert section["bins"] == 1 and section["bins_compared"] == 1 and section["excluded_near_jumps"] == 1
    assert section["worst_bins"] == [{"leg": "approach", "separation_nm": 10.5, "f0_shift_reep_hz": -98.0,
                                      "f0_shift_theory_hz": -100.0, "f0_z": 0.2, "q_shift_reep": -3.0,
                                      "q_shift_theory": -3.1, "q_z": 0.1}]
    json.dumps(section, allow_nan=False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.pass_ = False  # type: ignore[misc]


def test_theory_compare_refuses_a_folder_that_is_not_a_reep_run(tmp_path):
    from afmtool.analyses.theory_outputs import open_reep_run
    from afmtool.io.results import ResultWriter

    with pytest.raises(InputError, match="not a reep output folder"):
        open_reep_run(tmp_path)
    with ResultWriter(tmp_path / "reep.h5", {}) as writer:
        writer.append({name: np.zeros(4) for name in ("t", "b1", "b0")})
    (tmp_path / "report.json").write_text(json.dumps({"results": {"drive_frequency_hz": 7e4, "decimate": 7}}))
    with pytest.raises(InputError, match="not the report of a reep run .*results: no '"):
        open_reep_run(tmp_path)
