"""What a new user meets first (issue 31 item 7, and the designed drive of item 2)."""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from tests.conftest import REPO, run_cli


def test_readme_names_the_thesis_and_nothing_points_outside_the_repository():
    readme = (REPO / "README.md").read_text()
    for part in ("Pranav Agarwal", "Model Mismatch Paradigm for Probe based Nanoscale Imaging", "University of Minnesota",
                 "2010"):
        assert part in readme
    conventions = (REPO / "docs" / "conventions.md").read_text()
    for erratum in ("Eq. 2.8", "Eq. 3.43 is garbled", "Eq. 4.1 and eq. 6.2 use opposite signs", "eq. 6.14",
                    "eq. 5.13", "with a ½ in eqs. 7.5 and 7.7"):
        assert erratum in conventions, erratum
    offenders = []
    for path in [*REPO.joinpath("afmtool").rglob("*.py"), *REPO.joinpath("docs").glob("*.md"), REPO / "README.md"]:
        text = path.read_text(encoding="utf-8")
        if "NOTES.md" in text or "shared/reference" in text:
            offenders.append(str(path.relative_to(REPO)))
    assert not offenders, offenders


def test_quick_start_says_which_tests_need_chromium_and_gwyddion():
    quick = (REPO / "README.md").read_text().split("## Commands")[0]
    assert "Chromium" in quick and "gwyddion" in quick.lower() and ".ci/run" in quick and "apt-get install" in quick


def test_coverage_data_is_not_tracked():
    tracked = subprocess.run(["git", "ls-files", ".coverage"], cwd=REPO, capture_output=True, text=True).stdout
    assert tracked.strip() == ""
    assert ".coverage" in (REPO / ".gitignore").read_text().split()


def test_every_command_has_examples():
    from typer.main import get_command

    from afmtool.cli.help import EXAMPLES
    from afmtool.cli.main import app

    def paths(command, prefix=""):
        subcommands = getattr(command, "commands", None)
        if not subcommands:
            yield prefix
            return
        for name, sub in subcommands.items():
            yield from paths(sub, f"{prefix} {name}".strip())

    missing = [path for path in paths(get_command(app)) if not EXAMPLES.get(path)]
    assert not missing, f"commands without examples in cli/help.EXAMPLES: {missing}"


def test_simulate_list_describes_each_scenario():
    from afmtool import sim
    from afmtool.cli.simulate_cmd import SCENARIO_USES, scenario_list

    text = scenario_list()
    for name in sim.scenario_names():
        line = next(line for line in text.splitlines() if line.startswith(name + " "))
        assert len(line.split(None, 1)[1]) > 20, line  # a sentence, not a bare name
        assert name in SCENARIO_USES


def test_batch_exit_codes_match_the_readme():
    readme = (REPO / "README.md").read_text()
    assert "`afmtool batch` follows the same rule" in readme and "2 when an input failed on bad input" in readme
    from afmtool.cli.batch_cmd import batch

    assert "Exit status 2 when any input failed" in batch.__doc__  # tests/test_batch.py runs it


def test_info_never_cuts_values_when_piped(tmp_path):
    capture = tmp_path / "long.csv"
    long_name = "deflection_with_a_very_long_descriptive_channel_name_from_the_instrument_software"
    rows = [f"{i * 1e-3},{np.sin(i) * 1e5:.9f},{i * 1.234567e-4:.9g}" for i in range(50)]
    capture.write_text(f"t,{long_name} [nm],z_piezo_sensor_output_as_recorded [nm]\n" + "\n".join(rows) + "\n")
    result = run_cli("info", capture)
    text = result.stdout.decode()
    assert result.returncode == 0 and "…" not in text and long_name in text


def test_simulate_quiet_works_and_steps_write_z(tmp_path):
    quiet = run_cli("simulate", "tapping", "-o", tmp_path / "q.h5", "--set", "duration_s=0.002", "-q")
    assert quiet.returncode == 0 and quiet.stderr == b""
    loud = run_cli("simulate", "tapping", "-o", tmp_path / "s.h5", "--set", "duration_s=0.004", "--set", "program=steps")
    text = loud.stderr.decode()
    assert loud.returncode == 0 and "z_piezo (nm)" in text and "1,999 samples" not in text and "2,000 samples" in text
    import h5py

    with h5py.File(tmp_path / "s.h5", "r") as h5:
        z = h5["channels/z_piezo"][()]
        separation = h5["truth/separation_nm"][()]
    np.testing.assert_allclose(z, separation - separation[0])
    assert len(np.unique(z)) == 4  # the four default step levels


@pytest.fixture(scope="module")
def design(tmp_path_factory):
    base = tmp_path_factory.mktemp("design")
    model = base / "free_air.json"
    model.write_text('{"f0_hz": 70000.0, "q": 200.0, "gain": 1.0, "source": "sweep"}')
    result = run_cli("design", "excitation", "--model", model, "--amplitude", "20", "--out", base / "excitation", "-q")
    assert result.returncode == 0, result.stderr.decode()
    return base / "excitation"


def test_simulate_plays_the_designed_drive_from_lines_json_or_the_wav(design, tmp_path):
    import h5py

    from afmtool.sim.excitation import load_designed_drive

    from_json, from_wav = load_designed_drive(str(design / "lines.json")), load_designed_drive(str(design / "excitation.wav"))
    order = np.argsort(from_json.frequencies_hz)  # the WAV's lines come in frequency order
    np.testing.assert_allclose(from_wav.frequencies_hz, np.array(from_json.frequencies_hz)[order], rtol=1e-9)
    np.testing.assert_allclose(from_wav.amplitudes, np.array(from_json.amplitudes)[order], rtol=1e-5)  # float32
    captures = {}
    for name in ("lines.json", "excitation.wav"):
        out = tmp_path / f"{name}.h5"
        result = run_cli("simulate", "tapping", "-o", out, "--drive", design / name, "--set", "duration_s=0.004",
                         "--set", "f0_hz=70000", "--set", "q=200", "--set", "force_set=none")
        assert result.returncode == 0 and "3 designed lines" in result.stderr.decode(), result.stderr
        with h5py.File(out, "r") as h5:
            captures[name] = (h5["channels/dither"][()], h5["channels/deflection"][()])
    np.testing.assert_allclose(captures["lines.json"][0], captures["excitation.wav"][0], atol=1e-6)
    # the design's promise: 20 nm of free-air response (± the side lines' small beat and the noise)
    deflection = captures["lines.json"][1]
    amplitude = np.sqrt(2.0) * np.std(deflection)
    assert amplitude == pytest.approx(20.0, rel=0.03)
    assert re.search(r"designed", result.stderr.decode())
