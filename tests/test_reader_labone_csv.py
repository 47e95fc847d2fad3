"""LabOne readers and the generalised CSV reader.

There is no real LabOne file: the LabOne files here are built with h5py and
csv in LabOne's documented layout (demodulator samples with ``timestamp``
in clock ticks, a clockbase, scope shots with ``dt``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli, run_cli_cpu

CLOCKBASE = 60e6
STEP_TICKS = 3000  # 20 kHz


def _read(path, **kwargs):
    with open_capture(path, **kwargs) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 333))
        return reader.info, {n: np.concatenate([c.data[n] for c in chunks]) for n in reader.info.channel_names}


def _labone_h5(path, *, clockbase=True, gap=0, scope=True):
    import h5py

    rng = np.random.default_rng(11)
    fields = {}
    with h5py.File(path, "w") as f:
        for chunk in range(2):
            group = f.create_group(f"{chunk:03d}/dev1234/demods/0/sample")
            first = 10**9 + (1000 * chunk) * STEP_TICKS + (gap if chunk else 0)
            group["timestamp"] = (first + np.arange(1000, dtype=np.uint64) * STEP_TICKS).astype(np.uint64)
            for name in ("x", "y", "r", "theta", "frequency"):
                values = rng.standard_normal(1000)
                group[name] = values
                fields.setdefault(name, []).append(values)
            if clockbase:
                group.attrs["clockbase"] = CLOCKBASE
        if scope:
            wave = f.create_group("000/dev1234/scopes/0/wave")
            wave["wave"] = (rng.standard_normal((2, 4096)) * 1000).astype(np.int16)
            wave.attrs["dt"] = 16 / CLOCKBASE
            wave.attrs["channelscaling"] = [1e-3, 5e-4]
    return {k: np.concatenate(v) for k, v in fields.items()}


def test_labone_hdf5_demodulator_samples(tmp_path):
    expected = _labone_h5(tmp_path / "lab.h5")
    info, data = _read(tmp_path / "lab.h5", segment="demods")
    assert info.format == "labone-hdf5"
    assert info.sample_rate_hz == pytest.approx(CLOCKBASE / STEP_TICKS, rel=1e-12)
    assert info.n_samples == 2000
    assert [(c.name, c.units) for c in info.channels] == [
        ("x", "V"), ("y", "V"), ("r", "V"), ("theta", "deg"), ("frequency", "Hz")
    ]
    for name, values in expected.items():
        np.testing.assert_array_equal(data[name], values)
    assert [s.name for s in info.segments] == ["demods", "scope0"]


def test_labone_hdf5_scope_shot(tmp_path):
    import h5py

    _labone_h5(tmp_path / "lab.h5")
    info, data = _read(tmp_path / "lab.h5", segment="scope0")
    with h5py.File(tmp_path / "lab.h5") as f:
        raw = f["000/dev1234/scopes/0/wave/wave"][()]
    assert info.sample_rate_hz == pytest.approx(CLOCKBASE / 16) and info.n_samples == 4096
    np.testing.assert_array_equal(data["ch2"], raw[1] * 5e-4)


def test_labone_hdf5_refusals(tmp_path):
    _labone_h5(tmp_path / "noclock.h5", clockbase=False, scope=False)
    _labone_h5(tmp_path / "gap.h5", gap=7 * STEP_TICKS, scope=False)
    _labone_h5(tmp_path / "two.h5")
    for name, message in (
        ("noclock.h5", "no clockbase"),
        ("gap.h5", "non-uniform timestamps"),
        ("two.h5", "choose one with --segment"),
    ):
        result = run_cli("info", tmp_path / name)
        assert result.returncode == 2, name
        err = result.stderr.decode()
        assert err.count("\n") == 1 and message in err and str(tmp_path / name) in err, err


def _labone_csv(folder, *, header_file=True, comment=False, n=600):
    rng = np.random.default_rng(2)
    x, y = rng.standard_normal(n), rng.standard_normal(n)
    lines = ["# clockbase: 60000000"] if comment else []
    lines.append("chunk;timestamp;x;y;frequency;phase")
    lines += [f"0;{10**9 + i * STEP_TICKS};{float(x[i])!r};{float(y[i])!r};70000;0.25" for i in range(n)]
    path = folder / "dev1234_demods_0_sample_00000.csv"
    path.write_text("\n".join(lines) + "\n")
    if header_file:
        (folder / "dev1234_demods_0_sample_header_00000.csv").write_text(
            'chunk;history_name;clockbase;createdtimestamp\n0;"sample";60000000;123\n'
        )
    return path, x, y


@pytest.mark.parametrize("source", ["header file", "comment"])
def test_labone_csv(tmp_path, source):
    path, x, y = _labone_csv(tmp_path, header_file=source == "header file", comment=source == "comment")
    info, data = _read(path, channel_map={"deflection": "x"})
    assert info.format == "labone-csv"
    assert info.sample_rate_hz == pytest.approx(20000.0, rel=1e-12)
    assert [(c.name, c.units) for c in info.channels] == [
        ("deflection", "V"), ("y", "V"), ("frequency", "Hz"), ("phase", "rad")
    ]
    np.testing.assert_array_equal(data["deflection"], x)
    np.testing.assert_array_equal(data["y"], y)


def test_labone_csv_without_clockbase_is_refused(tmp_path):
    path, _, _ = _labone_csv(tmp_path, header_file=False)
    result = run_cli("info", path)
    assert result.returncode == 2 and "no clockbase" in result.stderr.decode()
    assert result.stderr.decode().count("\n") == 1


# ------------------------------------------------------------------ generalised CSV


def test_scope_csv_with_time_column_units_row_and_channel_mapping(tmp_path):
    path = tmp_path / "scope.csv"
    rows = "".join(f"{i * 1e-6!r},{float(np.sin(i))!r},{float(np.cos(i))!r}\r\n" for i in range(50))
    path.write_bytes(b"\xef\xbb\xbf" + b'"Time (s)",CH1,CH2\r\nSecond,Volt,Volt\r\n' + rows.encode())
    info = json.loads(run_cli("info", path, "--json", "--channel", "deflection=CH2").stdout)
    assert info["sample_rate_hz"] == pytest.approx(1e6, rel=1e-9) and info["n_samples"] == 50
    assert [(c["name"], c["units"]) for c in info["channels"]] == [("CH1", "V"), ("deflection", "V")]
    assert info["channels"][1]["max"] == pytest.approx(1.0)


def test_latin1_tabs_mixed_endings_units_in_header_and_ms(tmp_path):
    path = tmp_path / "export.csv"
    body = "Time (ms)\tdeflection (µm)\tz_piezo [nm]\r\n0\t1\t2\r0.5\t1.5\t2\n1.0\t2\t2\r\n"
    path.write_bytes(body.encode("latin-1"))
    info, data = _read(path)
    assert info.sample_rate_hz == pytest.approx(2000.0)
    assert [(c.name, c.units) for c in info.channels] == [("deflection", "µm"), ("z_piezo", "nm")]
    np.testing.assert_array_equal(data["deflection"], [1, 1.5, 2])
    # The same text in UTF-8 reads the same.
    path.write_bytes(body.encode("utf-8"))
    assert _read(path)[0].channels[0].units == "µm"


def test_semicolon_csv_and_units_comment_overrides_header(tmp_path):
    path = tmp_path / "semi.csv"
    path.write_text("# units.a: V\n# sample_rate_hz: 10\na (mV);b (nm)\n1;2\n3;4\n")
    info, data = _read(path)
    assert [(c.name, c.units) for c in info.channels] == [("a", "V"), ("b", "nm")]
    np.testing.assert_array_equal(data["b"], [2, 4])


def test_endless_stdin_line_is_refused_quickly():
    start = time.monotonic()
    with open("/dev/zero", "rb") as zero:
        result = subprocess.run(
            [sys.executable, "-m", "afmtool", "info", "-"], stdin=zero, capture_output=True, timeout=30
        )
    elapsed = time.monotonic() - start
    print(f"info - < /dev/zero: exit {result.returncode} in {elapsed:.2f} s")
    assert result.returncode == 2 and "longer than" in result.stderr.decode()
    assert elapsed < 10


def test_forty_thousand_columns_is_linear(tmp_path):
    n = 40_000
    path = tmp_path / "wide.csv"
    path.write_text("# sample_rate_hz: 1000\n" + ",".join(f"c{i}" for i in range(n)) + "\n" + ",".join(["1.5"] * n) + "\n")
    result, cpu_s = run_cli_cpu("info", path, "--json")
    print(f"info on a {n}-column CSV: {cpu_s:.2f} s of CPU")
    assert result.returncode == 0, result.stderr.decode()
    assert len(json.loads(result.stdout)["channels"]) == n
    assert cpu_s < 10
    table, cpu_s = run_cli_cpu("info", path)  # the human-readable table too (rich took 20 s of CPU for it)
    print(f"info (table) on a {n}-column CSV: {cpu_s:.2f} s of CPU")
    assert table.returncode == 0 and table.stdout.decode().count("\n") > n and cpu_s < 10


def test_too_many_columns_is_refused(tmp_path):
    from afmtool.io.csv import MAX_COLUMNS

    path = tmp_path / "huge.csv"
    path.write_text(",".join(f"c{i}" for i in range(MAX_COLUMNS + 1)) + "\n")
    result = run_cli("info", path)
    assert result.returncode == 2 and "columns; at most" in result.stderr.decode()
