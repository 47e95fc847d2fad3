"""Text exports: a preamble of parameters, headers with units, any delimiter, decimal commas; AFM Workshop and
NT-MDT files held to afmformats' own reading of them (its tests' numbers where it asserts any)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli

FORMATS = "data/formats"
WORKSHOP_2018 = f"{FORMATS}/fmt-afm-workshop-fd_single_2018-08-01_13.06.09.csv"
WORKSHOP_2021 = f"{FORMATS}/fmt-afm-workshop-fd_single_2021-01-15.csv"
NTMDT = f"{FORMATS}/fmt-ntmdt-txt-fd_2015_01_17_gel4-0,1_mQ_adh_6B_Curve_DFL_Height_51.txt"


def _read(path, **kwargs):
    with open_capture(path, **kwargs) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 333))
        return reader.info, {n: np.concatenate([c.data[n] for c in chunks]) for n in reader.info.channel_names}


@pytest.mark.parametrize("name, rows, k, sensitivity", [(WORKSHOP_2018, 570, 20.0, 0.01e-6), (WORKSHOP_2021, 3369, 1.0, 1e-6)])
def test_afm_workshop_matches_afmformats(shared, name, rows, k, sensitivity):
    """afmformats' test_single_conversion: with k = 20 N/m and 0.01 um/V, force[0] = 0.6861 V x sens x k."""
    afmformats = pytest.importorskip("afmformats")
    curve = afmformats.load_data(str(shared / name), meta_override={"spring constant": k, "sensitivity": sensitivity})[0]
    info, data = _read(shared / name, sample_rate_hz=1000.0)
    assert info.format == "afm-workshop" and info.n_samples == 2 * rows == len(curve["force"])
    assert [(s.name, s.n_samples) for s in info.segments] == [("extend", rows), ("retract", rows)]
    assert [(c.name, c.units) for c in info.channels] == [("z_piezo", "nm"), ("deflection", "V")]
    np.testing.assert_allclose(data["z_piezo"] * -1e-9, curve["height (measured)"], rtol=1e-12)  # afmformats: -Z-Sense
    np.testing.assert_allclose(data["deflection"] * sensitivity * k, curve["force"], rtol=1e-12)
    if name == WORKSHOP_2018:
        assert data["deflection"][0] == 0.6861
    assert int(np.sum(curve["segment"])) == rows


def test_afm_workshop_preamble_becomes_metadata(shared):
    """Light Lever Gain, mV/nm -> the InvOLS (its inverse); Force Constant, nN/nm -> the spring constant."""
    info, _ = _read(shared / WORKSHOP_2021, sample_rate_hz=1000.0)
    assert info.metadata["cantilever"] == {"deflection_sensitivity_nm_per_v": 1000.0, "spring_constant_n_per_m": 1.0}
    assert info.metadata["instrument"]["header"]["Software Version"] == "4.0.0.62"
    refused = run_cli("info", shared / WORKSHOP_2021)  # the export records no rate
    assert refused.returncode == 2 and "give --sample-rate" in refused.stderr.decode()


def test_ntmdt_matches_afmformats(shared):
    """afmformats' test_open_simple: 1644 points, the approach ending where the force peaks."""
    afmformats = pytest.importorskip("afmformats")
    curve = afmformats.load_data(str(shared / NTMDT), meta_override={"spring constant": 0.055, "sensitivity": 61})[0]
    info, data = _read(shared / NTMDT, sample_rate_hz=1000.0)
    assert info.format == "ntmdt" and info.n_samples == 1644 == curve["force"].size
    approach = info.segments[0].n_samples
    assert approach == int(np.sum(~curve["segment"].astype(bool))) == int(np.argmax(curve["force"])) + 1
    np.testing.assert_allclose(data["z_piezo"] * 1e-9, curve["height (measured)"], rtol=1e-12)
    np.testing.assert_allclose(data["deflection"] * 61 * 0.055 * 1e-9, curve["force"], rtol=1e-12)
    assert [(c.name, c.units) for c in info.channels] == [("z_piezo", "nm"), ("deflection", "nA")]


PREAMBLES = {
    "colon": "Sample rate, kHz: 500\nSpring constant (N/m): 2.5\nInvOLS, nm/V: 80\n",
    "equals": "Sample rate (kHz) = 500\nspring constant = 2.5\nsensitivity [nm/V] = 80\n",
    "comment": "# Sample_rate_hz 500000\n# Spring constant 2.5\n# sensitivity 80\n",
    "tab": "Sample rate, kHz\t500\nForce constant, nN/nm\t2.5\nDeflection sensitivity, um/V\t0.08\n",
}


@pytest.mark.parametrize("preamble", PREAMBLES)
@pytest.mark.parametrize("delimiter, decimal", [(",", "."), (";", ","), ("\t", ","), ("\t", ".")])
def test_generic_text_export(tmp_path, preamble, delimiter, decimal):
    rng = np.random.default_rng(4)
    z, defl = rng.uniform(-1, 1, 200).round(6), rng.uniform(-1, 1, 200).round(6)
    header = delimiter.join(["Z-Sense (nm)", "T-B(V)", "Force [nN]"])
    rows = [delimiter.join(f"{v:.6f}".replace(".", decimal) for v in (a, b, a * b)) for a, b in zip(z, defl)]
    path = tmp_path / "export.txt"
    path.write_text("Instrument export v2\n" + PREAMBLES[preamble] + "\n" + header + "\n" + "\n".join(rows) + "\n",
                    encoding="latin-1")
    info, data = _read(path)
    assert info.sample_rate_hz == pytest.approx(500000.0) and info.format == "text"
    assert [(c.name, c.units) for c in info.channels] == [("Z-Sense", "nm"), ("T-B", "V"), ("Force", "nN")]
    np.testing.assert_array_equal(data["Z-Sense"], z)
    np.testing.assert_array_equal(data["T-B"], defl)
    assert info.metadata["cantilever"]["spring_constant_n_per_m"] == pytest.approx(2.5)
    assert info.metadata["cantilever"]["deflection_sensitivity_nm_per_v"] == pytest.approx(80.0)


def test_columns_without_units_need_units(tmp_path):
    """Bad input: a text export whose columns have no units and no --units."""
    path = tmp_path / "bare.txt"
    path.write_text("0,1\t2,5\n0,2\t2,6\n0,3\t2,7\n")  # no header: NT-MDT has three columns; this is not one
    result = run_cli("info", path, "--sample-rate", "1000")
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "no units" in err and "--units" in err, err
    result = run_cli("convert", path, tmp_path / "o.h5", "--sample-rate", "1000")
    assert result.returncode == 2 and not (tmp_path / "o.h5").exists()
    ok = run_cli("info", path, "--sample-rate", "1000", "--units", "column1=nm", "--units", "column2=V", "--json")
    assert ok.returncode == 0, ok.stderr.decode()
    info = json.loads(ok.stdout)
    assert [(c["name"], c["units"]) for c in info["channels"]] == [("column1", "nm"), ("column2", "V")]
    assert info["channels"][1]["mean"] == pytest.approx(2.6)
    named = tmp_path / "named.csv"  # a vendor preamble, a column without a unit: the analyses need --units for it
    named.write_text("Device: x\nz (nm),deflection,dither (V)\n1,2,0\n2,3,1\n")
    result = run_cli("reep", named, "--sample-rate", "1000", "--out", tmp_path / "r")
    assert result.returncode == 2 and "deflection" in result.stderr.decode() and "no units" in result.stderr.decode()


@pytest.mark.parametrize("suffix", [".csv", ".txt"])
def test_a_last_line_cut_short_is_refused(tmp_path, suffix):
    """Issue 34: a truncated text file silently lost the last digits of its last value."""
    path = tmp_path / f"cut{suffix}"
    path.write_text("# sample_rate_hz: 1000\nt (s),deflection (nm)\n0,1.25\n0.001,2.5\n0.002,3.14159")
    result = run_cli("info", path)
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "line 5" in err and "cut short" in err, err
    path.write_text(path.read_text() + "265\n")  # complete: read right
    info = json.loads(run_cli("info", path, "--json").stdout)
    assert info["channels"][0]["max"] == 3.14159265


def test_plain_csv_is_read_as_before(tmp_path):
    """A plain CSV (comments, a header) keeps its meaning: units from the header, none assumed internal."""
    path = tmp_path / "plain.csv"
    path.write_text("# sample_rate_hz: 1000\n# units.b: V\nt,a,b\n0,1,2\n0.001,3,4\n")
    info, data = _read(path)
    assert info.units_declared and [(c.name, c.units) for c in info.channels] == [("a", ""), ("b", "V")]
    np.testing.assert_array_equal(data["b"], [2.0, 4.0])


def test_preamble_keys_are_bounded(tmp_path):
    """A preamble of 200,000 lines is read in bounded memory: 1000 keys kept, 200 shown."""
    path = tmp_path / "long.txt"
    lines = [f"key{i}: {i}" for i in range(90_000)]
    path.write_text("\n".join(lines) + "\nx (nm),y (V)\n1,2\n3,4\n")
    info, _ = _read(path, sample_rate_hz=1.0)
    assert len(info.metadata["instrument"]["header"]) == 200


def test_unrecognised_text_layout_is_one_line(tmp_path):
    path = tmp_path / "prose.txt"
    path.write_text("This is a note.\nNothing here is a table.\n")
    with pytest.raises(InputError):
        _read(path, sample_rate_hz=1.0)
