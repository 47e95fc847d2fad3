"""``decode`` without guessing (issue 28, item 5).

* Without electrostatic parameters in the metadata, decode no longer falls
  back on the thesis's experiment (eq. 7.10): it exits 2 and names what to
  give and how.
* ``--electrostatic DIR`` takes ``identify electrostatic``'s result, fitted on
  an approach curve of the same lever (K_esf/k and α_R from eq. 6.6; k from
  the capture's cantilever metadata), and the bits decode with ℓ0 within 1 %.
* α_R = 0 (the lever at ground, V = −V_sub in eq. 6.3) is accepted and decodes.
* ``simulate vphi-step`` has an analysis path (``--mode step``, chosen by the
  metadata): the settling of the deflection, its amplitude and the EKF
  innovation across Q = 1, 100, 1000 as in Figs. 7.9-7.12, and neither
  ``decode`` nor ``decode --stream`` exits 2 on it.
"""

from __future__ import annotations

import json

import pytest

from afmtool import sim
from afmtool.analyses.decode import run_decode
from afmtool.config import resolve
from afmtool.config.params import DecodeParams
from afmtool.errors import ConfigError
from afmtool.io.hdf5 import Hdf5Writer
from afmtool.io.memory import ArrayReader
from afmtool.records.decode import DecodeMode
from tests.conftest import run_cli
from tests.memory_sink import MemorySink

#: The bits lever (eq. 7.10) that the approach curve below shares.
LEVER = {"f0_hz": 57185.0, "q": 1.0148, "spring_constant_n_per_m": 0.1404, "k_esf_f_m": 1.66e-21,
         "alpha_r": 0.2549, "tip_height_nm": 768.3, "l0_nm": 1081.8}


def _reader(captured, metadata=None):
    return ArrayReader(captured.sample_rate_hz, captured.channels, captured.data,
                       captured.metadata if metadata is None else metadata, captured.truth, "bits")


def _write(path, captured, metadata=None):
    writer = Hdf5Writer(path, captured.sample_rate_hz, captured.channels,
                        captured.metadata if metadata is None else metadata)
    writer.write(captured.data)
    writer.close()
    return path


@pytest.fixture(scope="module")
def bits():
    return sim.simulate("bits", {"duration_s": 0.006, "bit_rate_hz": 30e3}, seed=3)


def test_missing_electrostatic_parameters_are_named_not_guessed(bits, tmp_path):
    bare = {k: v for k, v in bits.metadata.items() if k != "electrostatic"}
    with pytest.raises(ConfigError, match="k_esf_f_m.*--alpha-r.*--electrostatic"):
        run_decode(_reader(bits, bare), resolve(DecodeParams, {"bit_rate_hz": 30e3}), MemorySink())
    path = _write(tmp_path / "bare.h5", bits, bare)
    result = run_cli("decode", path, "--out", tmp_path / "out", "--bit-rate", "30000", "--quiet")
    message = result.stderr.decode()
    assert result.returncode == 2 and "identify electrostatic" in message and "--electrostatic" in message
    assert not (tmp_path / "out").exists() and "Traceback" not in message


def test_electrostatic_from_identify_electrostatic(bits, tmp_path):
    """An approach curve of the same lever, through identify electrostatic, then decode --electrostatic."""
    approach = sim.simulate("es-approach", {
        "f0_hz": LEVER["f0_hz"], "spring_constant_n_per_m": LEVER["spring_constant_n_per_m"],
        "k_esf_f_m": LEVER["k_esf_f_m"], "alpha_r": LEVER["alpha_r"], "l0_nm": LEVER["l0_nm"],
        "tip_height_nm": LEVER["tip_height_nm"], "v_r_v": 4.0}, seed=2)
    curve = _write(tmp_path / "approach.h5", approach)
    identified = run_cli("identify", "electrostatic", curve, "--out", tmp_path / "es", "--quiet")
    assert identified.returncode == 0, identified.stderr.decode()
    fit = json.loads((tmp_path / "es" / "electrostatic.json").read_text())["parameters"]
    print(f"identified: K_esf/k {fit['k_esf_over_k_m3_per_v2']['value']:.4g} m^3/V^2, "
          f"alpha_R {fit['alpha_r']['value']:.4f}, l0 {fit['l0_m']['value'] * 1e9:.1f} nm")
    bare = {k: v for k, v in bits.metadata.items() if k != "electrostatic"}
    columns = MemorySink()
    result = run_decode(_reader(bits, bare), resolve(DecodeParams, {"bit_rate_hz": 30e3,
                                                                    "electrostatic": str(tmp_path / "es")}), columns)
    model, l0 = result.results.model, result.results.l0
    print(f"decode --electrostatic: l0 {l0.estimate_nm:.1f} nm (truth {LEVER['l0_nm']}), sources {model.sources}")
    assert model.sources.k_esf_f_m.startswith("--electrostatic")
    assert model.sources.alpha_r.startswith("--electrostatic")
    assert model.sources.spring_constant_n_per_m == "metadata"  # the curve knows only K_esf/k
    assert model.alpha_r == pytest.approx(LEVER["alpha_r"], rel=0.01)
    assert l0.estimate_nm == pytest.approx(LEVER["l0_nm"], rel=0.01)
    assert result.results.truth.decoder.errors == 0


def test_alpha_r_zero_decodes(tmp_path):
    """α_R = 0: the lever at ground, V = −V_sub (eq. 6.3); the substrate carries the DC."""
    captured = sim.simulate("bits", {"duration_s": 0.006, "bit_rate_hz": 30e3, "alpha_r": 0.0,
                                     "substrate_dc_v": -2.8}, seed=4)
    assert captured.metadata["electrostatic"]["alpha_r"] == 0.0
    result = run_decode(_reader(captured), resolve(DecodeParams, {"bit_rate_hz": 30e3}), MemorySink())
    truth = result.results.truth
    print(f"alpha_R = 0: l0 error {truth.l0_error_percent:+.3f} %, BER {truth.decoder.ber}")
    assert result.results.model.alpha_r == 0.0 and result.results.model.sources.alpha_r == "metadata"
    assert truth.decoder.errors == 0 and abs(truth.l0_error_percent) < 1
    # and as a parameter: --alpha-r 0 is a value, not "automatic"
    assert resolve(DecodeParams, {"alpha_r": 0.0}).alpha_r == 0.0


def _step_capture(q: float):
    # noise-free, as the thesis's simulation; 10 ms before the step, 20 ms after (3.6 lever time constants at Q 1000)
    return sim.simulate("vphi-step", {"q": q, "duration_s": 0.03, "step_time_s": 0.01}, seed=0)


@pytest.mark.long
def test_vphi_step_across_q_as_figs_7_9_to_7_12():
    """§7.7 through decode: the amplitude's settling grows with Q, the innovation's does not."""
    settling = {}
    for q in (1.0148, 100.0148, 1000.0148):
        result = run_decode(_reader(_step_capture(q)), resolve(DecodeParams, {}), MemorySink())
        step = result.results.step
        assert result.results.mode is DecodeMode.STEP and result.step is not None
        settling[q] = {name: getattr(step, name).settling_periods for name in ("deflection", "amplitude", "innovation")}
        print(f"Q {q:g}: " + ", ".join(f"{k} {v:.2f}" for k, v in settling[q].items())
              + f" actuation periods; running-mean detection after {step.innovation_mean.delay_periods:.2f}")
    innovation = [s["innovation"] for s in settling.values()]
    amplitude = [s["amplitude"] for s in settling.values()]
    assert max(innovation) <= 5.0 and max(innovation) / max(min(innovation), 0.5) < 2.0
    assert amplitude[2] / amplitude[0] > 100.0 and amplitude[1] / amplitude[0] > 10.0
    assert settling[1000.0148]["deflection"] > 100.0 * settling[1.0148]["deflection"]


def test_decode_and_stream_run_on_a_vphi_step(tmp_path):
    path = _write(tmp_path / "vphi.h5", _step_capture(100.0148))
    out = tmp_path / "out"
    result = run_cli("decode", path, "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    assert report["results"]["mode"] == "step" and "decode_step.png" in report["outputs"]
    names = [entry["name"] for entry in report["headline"]]
    assert "innovation settling after the V_phi step" in names
    stream = run_cli("decode", path, "--stream")
    assert stream.returncode == 0, stream.stderr.decode()
    lines = stream.stdout.decode().splitlines()
    assert lines[0] == "t_mean,innovation_mean" and len(lines) > 100
