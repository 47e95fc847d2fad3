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
