"""The README's "whole experiment, in order", run as written on scope captures afmtool did not make (issue 31 item 2).

The captures come from ``tests/reference_sim.py`` (which shares no code with
afmtool) and are written the way a scope writes them: ``Time (s),CH1 [V],...``,
the deflection in photodiode volts (InvOLS 50 nm/V), z in monitor volts
(10 nm/V), no metadata.  The force curve is recorded with the drive the
design step wrote (its ``lines.json``, played as a generator would).  Each
line of the README's block runs in this process, in a folder holding the
captures, and each step's end-of-run headline is checked against its
report.json and the truth.
"""

from __future__ import annotations

import json
import math
import re
import shlex

import numpy as np
import pytest

from tests import reference_sim as ref
from tests.conftest import REPO

pytestmark = pytest.mark.long  # five commands and three reference captures: about half a minute of CPU

F0_HZ, Q, K_N_PER_M, INVOLS_NM_PER_V, Z_NM_PER_V = 75_000.0, 180.0, 2.0, 50.0, 10.0
FS = 500_000.0


def readme_block() -> list[str]:
    """The command lines of the README's walk-through, exactly as written (comments dropped)."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## The whole experiment, in order", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    lines = []
    for line in block.splitlines():
        command = line.split("   #", 1)[0].split("  #", 1)[0].strip()
        if command and not command.startswith("#"):
            lines.append(command)
    return lines


def _write_scope_csv(path, t, columns: dict) -> None:
    """``Time (s),CH1 [V],...``: what a scope exports."""
    header = ",".join(["Time (s)", *(f"{name} [V]" for name in columns)])
    table = np.column_stack([t, *columns.values()])
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt="%.9g")


def _thermal(folder) -> None:
    record = ref.thermal_record(f0_hz=F0_HZ, q=Q, spring_constant_n_per_m=K_N_PER_M, temperature_k=295.0,
                                sample_rate_hz=FS, duration_s=0.4, noise_nm=0.0005, seed=4)
    _write_scope_csv(folder / "thermal.csv", record.t, {"CH2": record.channels["deflection"] / INVOLS_NM_PER_V})


def _free_air(folder) -> None:
    drive = ref.three_sine(F0_HZ, 6000.0, 20.0 / Q)
    capture = ref.simulate(f0_hz=F0_HZ, q=Q, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=0.03, drive=drive,
                           noise_nm=0.02, seed=5)
    _write_scope_csv(folder / "free_air.csv", capture.t,
                     {"CH1": capture.channels["dither"], "CH2": capture.channels["deflection"] / INVOLS_NM_PER_V})


def _curve(folder) -> None:
    """The force curve, driven by the designed lines (lines.json's sines as the reference's cosines)."""
    design = json.loads((folder / "excitation" / "lines.json").read_text())
    drive = ref.MultiSine(tuple(
        ref.Sine(line["frequency_hz"], line["amplitude_v"], math.radians(line["phase_deg"]) - math.pi / 2)
        for line in design["lines"]
    ))
    duration, free_s = 0.05, 0.01
    ramp = (duration - free_s) / 2

    def separation(t):  # hold 40 nm, approach to 8 nm, retract
        down = np.clip((t - free_s) / ramp, 0.0, 1.0)
        up = np.clip((t - free_s - ramp) / ramp, 0.0, 1.0)
        return 40.0 - 32.0 * down + 32.0 * up

    capture = ref.simulate(f0_hz=F0_HZ, q=Q, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=duration, drive=drive,
                           noise_nm=0.02, seed=6, force=ref.ATTRACTIVE_SET, separation_nm=separation,
                           record_z_piezo=True)
    _write_scope_csv(folder / "curve.csv", capture.t, {
        "CH1": capture.channels["dither"], "CH2": capture.channels["deflection"] / INVOLS_NM_PER_V,
        "CH3": capture.channels["z_piezo"] / Z_NM_PER_V,
    })


def _invoke(line: str) -> tuple[int, str, str]:
    from typer.testing import CliRunner

    from afmtool.cli.main import app

    words = shlex.split(line)
    assert words[0] == "afmtool"
    result = CliRunner().invoke(app, words[1:], catch_exceptions=True)
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        return 2, "", f"{type(result.exception).__name__}: {result.exception}"
    return result.exit_code, result.stdout, result.stderr


def _out(line: str) -> str | None:
    words = shlex.split(line)
    return words[words.index("--out") + 1] if "--out" in words else None


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """Every step of the README's block, in order: [(line, exit, stderr, report)]."""
    folder = tmp_path_factory.mktemp("walkthrough")
    _thermal(folder)
    _free_air(folder)
    steps = []
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        for line in readme_block():
            if line.startswith("afmtool reep") and not (folder / "curve.csv").exists():
                _curve(folder)  # "play excitation/excitation.wav and record the force curve"
            code, _, stderr = _invoke(line)
            out = _out(line)
            report = json.loads((folder / out / "report.json").read_text()) if code == 0 and out else None
            steps.append((line, code, stderr, report))
            if code != 0:
                break
    return folder, steps


def _headline(report: dict) -> dict:
    return {entry["name"]: entry for entry in report["headline"]}


def _step(walk, key):
    """The first step whose command line contains ``key``."""
    _, steps = walk
    for step in steps:
        if key in step[0]:
            return step
    pytest.fail(f"the walk-through stopped before '{key}': {[(s[0][:60], s[1], s[2][-300:]) for s in steps]}")


def _check_printed(stderr: str, report: dict) -> None:
    """The stderr headline is the report's, line by line, with units."""
    for entry in report["headline"]:
        assert f"{entry['name']}  " in stderr and entry["text"] in stderr, (entry, stderr)
    assert any(entry["units"] for entry in report["headline"])


def test_the_walkthrough_is_the_readmes_and_reads_scope_csvs_without_metadata():
    lines = readme_block()
    assert [shlex.split(line)[1:3] for line in lines][:3] == [["identify", "freeair"], ["identify", "freeair"],
                                                             ["design", "excitation"]]
    assert all("--channel" in line for line in lines if line.split()[1] in ("reep",))
    assert any(" --fit " in line for line in lines)


def test_thermal_spring_constant(walk):
    line, code, stderr, report = _step(walk, "--thermal")
    assert code == 0, stderr
    _check_printed(stderr, report)
    k = _headline(report)["k (thermal, equipartition)"]
    print("k =", k["text"], "truth", K_N_PER_M)
    # a displacement record (no optical-lever factor): within 3 std and 5 % of the truth
    assert abs(k["value"] - K_N_PER_M) < max(3 * (k["std"] or 0), 0.05 * K_N_PER_M) or \
        abs(k["value"] / report["results"]["spring_constant"]["thermal"]["factor"] - K_N_PER_M) < 0.05 * K_N_PER_M


def test_free_air_model(walk):
    line, code, stderr, report = _step(walk, "identify freeair free_air.csv")
    assert code == 0, stderr
    _check_printed(stderr, report)
    entries = _headline(report)
    print(entries["f0 (free air)"]["text"], entries["Q (free air)"]["text"])
    assert entries["f0 (free air)"]["value"] == pytest.approx(F0_HZ, abs=5.0)
    assert entries["Q (free air)"]["value"] == pytest.approx(Q, rel=0.03)


def test_design_and_reep_on_the_recorded_curve(walk):
    _, code, stderr, report = _step(walk, "afmtool design excitation")
    assert code == 0, stderr
    _check_printed(stderr, report)
    line, code, stderr, report = _step(walk, "afmtool reep curve.csv")
    assert code == 0, stderr
    _check_printed(stderr, report)
    entries = _headline(report)
    print("\n".join(e["text"] for e in report["headline"]))
    assert entries["f0' in the free-air segment"]["value"] == pytest.approx(F0_HZ, abs=20.0)
    shift = entries["largest Δf0' on approach"]
    assert shift["value"] < -100.0 and shift["at"]["units"] == "nm"  # attraction lowers f0'
    assert "largest energy dissipated per cycle" in entries and "largest force gradient" in entries


def test_fit_then_compare_then_report(walk):
    _, code, stderr, report = _step(walk, "afmtool theory fit")
    assert code == 0, stderr
    _check_printed(stderr, report)
    line, code, stderr, report = _step(walk, "afmtool theory compare")
    assert code == 0, stderr
    _check_printed(stderr, report)
    verdict = _headline(report)["verdict"]
    print("compare:", verdict["text"], "|", [e["text"] for e in report["headline"]][1:])
    # the fitted force reproduces the curve it was fitted to, off the wall (the bins on it are left out)
    assert report["results"]["pass"] is True and verdict["value"].startswith("agree"), verdict["text"]
    assert any(e["at"] and e["at"]["name"] == "separation" for e in report["headline"])  # the worst bins, located
    _, code, stderr, _ = _step(walk, "afmtool report reep_fc")
    assert code == 0


def test_the_same_curve_from_an_instrument_file_without_metadata(walk):
    """The recorded curve as a multichannel float WAV (unitless channels, no metadata): the same answers."""
    from scipy.io import wavfile

    folder, _ = walk
    _, code, _, from_csv = _step(walk, "afmtool reep curve.csv")
    assert code == 0
    table = np.loadtxt(folder / "curve.csv", delimiter=",", skiprows=1)
    wavfile.write(folder / "curve.wav", int(FS), table[:, 1:].astype(np.float32))
    line = ("afmtool reep curve.wav --channel dither=ch1 --channel deflection=ch2 --channel z_piezo=ch3 "
            "--units dither=V --units deflection=V --units z_piezo=V --invols 50 --z-sensitivity 10 "
            "--free-air 0:0.01 --model lever --spring-constant 2 --out reep_wav")
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        code, _, stderr = _invoke(line)
    assert code == 0, stderr
    report = json.loads((folder / "reep_wav" / "report.json").read_text())
    _check_printed(stderr, report)
    wav, csv_ = _headline(report), _headline(from_csv)
    for name in ("f0' in the free-air segment", "largest Δf0' on approach", "smallest Q' on approach"):
        print(name, "csv", csv_[name]["text"], "wav", wav[name]["text"])
        assert wav[name]["value"] == pytest.approx(csv_[name]["value"], rel=0.02, abs=0.5)
