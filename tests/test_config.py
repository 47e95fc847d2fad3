"""Parameters: packaged defaults < user TOML < flags, one typed model for all three."""

from __future__ import annotations

import tomllib

import pytest

from afmtool.config import resolve, resolve_from
from afmtool.config.defaults import default_toml, packaged_defaults_text
from afmtool.config.params import ReepParams
from afmtool.errors import ConfigError
from tests.conftest import run_cli


def test_packaged_defaults_are_generated_from_the_models():
    # Regenerate with: python -m afmtool.config.defaults > afmtool/config/defaults.toml
    assert packaged_defaults_text() == default_toml()


def test_precedence_defaults_file_flags():
    user = {"reep": {"lam": 0.99, "decimate": 4}}
    params = resolve_from(ReepParams, "reep", user, {"decimate": 2, "vs": None})
    assert params.lam == 0.99  # from the file
    assert params.decimate == 2  # the flag wins
    assert params.p0 == 1e6  # packaged default
    assert params.vs == "auto"  # an unset flag changes nothing


@pytest.mark.parametrize(
    "layer, message",
    [
        ({"lamda": 0.9}, "unknown parameter 'lamda'"),
        ({"lam": "fast"}, "lam='fast'"),
        ({"lam": 1.5}, "lam=1.5"),
        ({"vs": "sideways"}, "one of"),
        ({"use_input": 1}, "use_input=1"),
        ({"free_air": "0.5"}, "START:END"),
    ],
)
def test_bad_values_are_refused(layer, message):
    with pytest.raises(ConfigError, match=message):
        resolve(ReepParams, layer)


def test_config_init_writes_defaults(tmp_path):
    path = tmp_path / "afmtool.toml"
    result = run_cli("config", "init", path)
    assert result.returncode == 0, result.stderr.decode()
    parsed = tomllib.loads(path.read_text())
    assert parsed["reep"]["window_us"] == 400.0 and parsed["reep"]["lam"] == 0.0  # λ = 0.995 at 500 kHz
    assert "simulate" in parsed and "tapping" in parsed["simulate"]
    again = run_cli("config", "init", path)
    assert again.returncode == 2  # refuses to overwrite without --force


def test_bad_config_file_is_a_clean_error(tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text("[reep\nlam = ")
    capture = tmp_path / "c.csv"
    capture.write_text("# sample_rate_hz: 1000\ndither,deflection\n" + "0,0\n" * 100)
    result = run_cli("reep", capture, "--out", tmp_path / "out", "--config", config)
    assert result.returncode == 2
    assert "not valid TOML" in result.stderr.decode()
    assert not (tmp_path / "out").exists()


def test_kalman_bank_nests_a_reep_block():
    """[kalman-bank.reep] is a ReepParams table over its own defaults; the bank's own fields stay the bank's."""
    from afmtool.config.params import KalmanBankParams, ReepParams

    params = resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"reep": {"window_us": 300.0}}}, {})
    assert params.reep == ReepParams(window_us=300.0)
    assert resolve_from(KalmanBankParams, "kalman-bank", None, {}).reep == ReepParams()
    with pytest.raises(ConfigError, match=r"\[kalman-bank\] reep\.unknown parameter 'lamda'"):
        resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"reep": {"lamda": 0.9}}}, {})
    with pytest.raises(ConfigError, match=r"reep\.window_us=-1\.0 must be > 0"):
        resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"reep": {"window_us": -1.0}}}, {})
    with pytest.raises(ConfigError, match=r"\[kalman-bank.reep\] free_air: kalman-bank sets it"):
        resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"reep": {"free_air": "0:0.01"}}}, {})
    with pytest.raises(ConfigError, match="must be a table"):
        resolve_from(KalmanBankParams, "kalman-bank", {"kalman-bank": {"reep": 0.995}}, {})
    # the config.toml a run writes reads back to the same parameters
    from afmtool.config import section_to_toml

    text = section_to_toml("kalman-bank", params)
    assert "[kalman-bank.reep]" in text
    assert resolve_from(KalmanBankParams, "kalman-bank", tomllib.loads(text), {}) == params
