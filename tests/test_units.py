"""Units parsed and converted once where a capture is opened (issue 16, item 2; acceptance 3).

A deflection stored in m, in µm, or in V with ``--invols`` must give the same
REEP and decode results as the nm original; an unknown or wrong-kind unit is
refused naming the channel.
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest

from afmtool.errors import ConfigError, InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk
from afmtool.io.units import Calibration, UnitsReader, calibration_record, parse_unit, plan_conversions
from tests.conftest import SAMPLE_DATA, run_cli, validate_report

LTV = SAMPLE_DATA / "ltv_step.h5"
BITS = SAMPLE_DATA / "bits_30khz.h5"


def _rewrite(src, dst, scale: dict, units: dict, drop_units: tuple = ()) -> None:
    """Copy an afmtool HDF5 capture, scaling some channels and relabelling their units."""
    with h5py.File(src) as f, h5py.File(dst, "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value
        for name, ds in f["channels"].items():
            out = g.create_dataset(f"channels/{name}", data=ds[()] * scale.get(name, 1.0))
            if name not in drop_units:
                out.attrs["units"] = units.get(name, ds.attrs["units"])
        if "truth" in f:
            f.copy("truth", g)


def _report(out) -> dict:
    return json.loads((out / "report.json").read_text())


# --- the table -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "kind", "si"),
    [("nm", "length", 1e-9), ("m", "length", 1.0), ("µm", "length", 1e-6), ("um", "length", 1e-6),
     ("μm", "length", 1e-6), ("mm", "length", 1e-3), ("pm", "length", 1e-12), ("Å", "length", 1e-10),
     ("V", "voltage", 1.0), ("mV", "voltage", 1e-3), ("uA", "current", 1e-6), ("A", "current", 1.0),
     ("nA", "current", 1e-9), ("ms", "time", 1e-3), ("kHz", "frequency", 1e3), ("deg", "angle", 1.0)],
)
def test_parse_unit(text, kind, si):
    unit = parse_unit(text)
    assert unit.kind == kind
    assert math.isclose(unit.si_factor, si, rel_tol=1e-15)


@pytest.mark.parametrize("text", ["furlong", "nmm", "xV", "m/s", "N/m"])
def test_parse_unit_refuses_unknown(text):
    with pytest.raises(ValueError, match="unknown unit"):
        parse_unit(text)


def _info(**units) -> CaptureInfo:
    return CaptureInfo("cap.h5", "hdf5", 1000.0, tuple(ChannelSpec(n, u) for n, u in units.items()), 10)


def test_plan_factors_are_exact_powers_of_ten():
    plan = plan_conversions(_info(deflection="m", z_piezo="um", dither="mV", thermal_current="A", i2="nA"),
                            Calibration())
    assert plan["deflection"].factor == 1e9 and plan["deflection"].internal_units == "nm"
    assert plan["z_piezo"].factor == 1e3
    assert plan["dither"].factor == 1e-3 and plan["dither"].internal_units == "V"
    assert plan["thermal_current"].factor == 1e6 and plan["thermal_current"].internal_units == "uA"
    assert plan["i2"].factor == 1e-3
    assert plan_conversions(_info(thermal_current="uA"), Calibration())["thermal_current"].factor == 1.0


def test_plan_keeps_an_unparsed_unit_of_a_channel_no_analysis_reads():
    plan = plan_conversions(_info(deflection="nm", lockin_r="Vrms"), Calibration())
    assert plan["lockin_r"] == ("Vrms", "Vrms", 1.0, "unparsed")
    with pytest.raises(InputError, match="channel 'deflection' has units 'Vrms'"):
        plan_conversions(_info(deflection="Vrms"), Calibration())
    assert parse_unit("Volts").kind == "voltage" and parse_unit("METERS").kind == "length"


def test_plan_refuses_wrong_kind_naming_the_channel():
    with pytest.raises(InputError, match=r"channel 'deflection' has units 'uA' \(current\)"):
        plan_conversions(_info(deflection="uA"), Calibration())
    with pytest.raises(InputError, match="channel 'dither' has units 'nm'"):
        plan_conversions(_info(dither="nm"), Calibration())


def test_plan_volts_need_a_sensitivity():
    with pytest.raises(InputError, match="channel 'deflection' is in 'V'.*--invols"):
        plan_conversions(_info(deflection="V"), Calibration())
    with pytest.raises(InputError, match="channel 'z_piezo' is in 'mV'.*--z-sensitivity"):
        plan_conversions(_info(z_piezo="mV"), Calibration())
    plan = plan_conversions(_info(deflection="mV", z_piezo="V"), Calibration(invols_nm_per_v=50.0,
                                                                         z_sensitivity_nm_per_v=2000.0))
    assert math.isclose(plan["deflection"].factor, 0.05) and plan["deflection"].via == "invols (--invols)"
    assert plan["z_piezo"].factor == 2000.0


def test_metadata_invols_is_used():
    info = CaptureInfo("c.h5", "hdf5", 1e3, (ChannelSpec("deflection", "V"),), 3,
                       {"cantilever": {"deflection_sensitivity_nm_per_v": 80.0}})
    reader = UnitsReader(_ArrayReader(info, {"deflection": np.array([1.0, -0.5, 0.25])}), Calibration())
    assert reader.info.units("deflection") == "nm"
    (chunk,) = reader.blocks(["deflection"], 10)
    np.testing.assert_array_equal(chunk.data["deflection"], [80.0, -40.0, 20.0])
    assert calibration_record(reader)["calibration"] == {"invols_nm_per_v": 80.0}


def test_bad_calibration_values():
    with pytest.raises(ConfigError, match="--invols"):
        Calibration(invols_nm_per_v=-1.0)
    with pytest.raises(ConfigError, match="--units deflection=parsec"):
        Calibration(units={"deflection": "parsec"})


class _ArrayReader:
    def __init__(self, info, data):
        self.info, self._data = info, data

    def blocks(self, channels, block_samples):
        yield Chunk(0, {n: self._data[n] for n in channels})

    def truth(self):
        return {}

    def close(self):
        pass


def test_internal_units_pass_through_untouched():
    info = _info(deflection="nm", dither="V")
    data = {"deflection": np.arange(3.0), "dither": np.ones(3)}
    reader = UnitsReader(_ArrayReader(info, data), Calibration())
    (chunk,) = reader.blocks(["deflection", "dither"], 10)
    assert chunk.data["deflection"] is data["deflection"]  # no copy on the common path
    assert calibration_record(reader) == {}


# --- end to end (acceptance 3) -------------------------------------------------------------------


def _reep_numbers(report: dict) -> tuple[float, float, float]:
    s = report["results"]["summary"]
    return s["f0_hz"]["mean"], s["q"]["mean"], s["amplitude"]["mean"]


@pytest.fixture(scope="module")
def reep_nm(tmp_path_factory):
    out = tmp_path_factory.mktemp("nm") / "out"
    assert run_cli("reep", LTV, "--out", out, "-q").returncode == 0
    return _report(out)


@pytest.mark.parametrize(
    ("label", "scale", "unit", "extra"),
    [("m", 1e-9, "m", ()), ("um", 1e-3, "µm", ()), ("volts", 1 / 42.5, "V", ("--invols", "42.5"))],
)
def test_reep_same_in_m_um_and_volts(tmp_path, reep_nm, label, scale, unit, extra):
    capture = tmp_path / f"ltv_{label}.h5"
    _rewrite(LTV, capture, {"deflection": scale}, {"deflection": unit})
    out = tmp_path / "out"
    result = run_cli("reep", capture, "--out", out, "-q", *extra)
    assert result.returncode == 0, result.stderr.decode()
    report = _report(out)
    expected, actual = _reep_numbers(reep_nm), _reep_numbers(report)
    print(label, "f0', Q', amplitude:", actual, "nm:", expected)
    for a, e in zip(actual, expected):
        assert math.isclose(a, e, rel_tol=1e-9)
    validate_report(report)
    conversion = report["inputs"][0]["unit_conversions"]["deflection"]
    assert conversion["recorded_units"] == unit and conversion["internal_units"] == "nm"
    assert math.isclose(conversion["factor"], 1 / scale, rel_tol=1e-12)
    with h5py.File(out / "reep.h5") as h5:
        assert h5["amplitude"].attrs["units"] == "nm"


def test_reep_volts_without_invols_is_refused(tmp_path):
    capture = tmp_path / "ltv_v.h5"
    _rewrite(LTV, capture, {"deflection": 0.01}, {"deflection": "V"})
    result = run_cli("reep", capture, "--out", tmp_path / "out")
    assert result.returncode == 2
    assert "channel 'deflection' is in 'V'" in result.stderr.decode() and "--invols" in result.stderr.decode()
    assert not (tmp_path / "out").exists()


def test_unknown_unit_exits_2_naming_the_channel(tmp_path):
    capture = tmp_path / "ltv_bad.h5"
    _rewrite(LTV, capture, {}, {"deflection": "furlong"})
    result = run_cli("reep", capture, "--out", tmp_path / "out")
    assert result.returncode == 2
    stderr = result.stderr.decode()
    assert "channel 'deflection'" in stderr and "'furlong'" in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_units_option_gives_units_to_a_foreign_hdf5(tmp_path, reep_nm):
    """A dataset without a units attribute, stored in m: --units deflection=m reads it right."""
    capture = tmp_path / "foreign.h5"
    _rewrite(LTV, capture, {"deflection": 1e-9}, {}, drop_units=("deflection",))
    out = tmp_path / "out"
    result = run_cli("reep", capture, "--units", "deflection=m", "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    assert math.isclose(_reep_numbers(_report(out))[0], _reep_numbers(reep_nm)[0], rel_tol=1e-9)
    assert _report(out)["inputs"][0]["unit_conversions"]["deflection"]["via"] == "override"
    info = run_cli("info", capture, "--units", "deflection=m", "--json")
    assert info.returncode == 0
    channels = {c["name"]: c["units"] for c in json.loads(info.stdout)["channels"]}
    assert channels["deflection"] == "m"  # info shows the file's own scale, with the given units


def test_units_option_on_csv(tmp_path):
    csv = tmp_path / "c.csv"
    csv.write_text("# sample_rate_hz: 1000\ndeflection\n1e-9\n2e-9\n")
    info = run_cli("info", csv, "--units", "deflection=m", "--json")
    assert info.returncode == 0, info.stderr.decode()
    assert json.loads(info.stdout)["channels"][0]["units"] == "m"
    bad = run_cli("info", csv, "--units", "deflectoin=m")
    assert bad.returncode == 2 and "no channel 'deflectoin'" in bad.stderr.decode()


@pytest.fixture(scope="module")
def decode_nm(tmp_path_factory):
    out = tmp_path_factory.mktemp("decode_nm") / "out"
    result = run_cli("decode", BITS, "--bit-rate", "30000", "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    return _report(out)["results"]


@pytest.mark.parametrize(
    ("label", "scale", "unit", "extra"),
    [("m", 1e-9, "m", ()), ("um", 1e-3, "um", ()), ("volts", 1 / 38.0, "V", ("--invols", "38"))],
)
def test_decode_same_in_m_um_and_volts(tmp_path, decode_nm, label, scale, unit, extra):
    """decode on a deflection in m used to run l0 to the bracket edge; now it is converted."""
    capture = tmp_path / f"bits_{label}.h5"
    _rewrite(BITS, capture, {"deflection": scale}, {"deflection": unit})
    out = tmp_path / label
    result = run_cli("decode", capture, "--bit-rate", "30000", "--out", out, "-q", *extra)
    assert result.returncode == 0, result.stderr.decode()
    nm, got = decode_nm, _report(out)["results"]
    print(label, "l0:", got["l0"]["estimate_nm"], "nm run:", nm["l0"]["estimate_nm"], "bits", got["bits"]["count"])
    assert math.isclose(got["l0"]["estimate_nm"], nm["l0"]["estimate_nm"], rel_tol=1e-9)
    assert math.isclose(got["noise"]["measurement_noise_nm"], nm["noise"]["measurement_noise_nm"], rel_tol=1e-9)
    assert got["bits"]["count"] == nm["bits"]["count"] and got["bits"]["ones"] == nm["bits"]["ones"]
    for who in ("decoder", "baseline"):
        assert got["truth"][who]["errors"] == nm["truth"][who]["errors"]
        assert got["truth"][who]["confusion"] == nm["truth"][who]["confusion"]
    print("BER decoder", got["truth"]["decoder"]["ber"], "baseline", got["truth"]["baseline"]["ber"])
