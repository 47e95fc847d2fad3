"""afmtool report: a self-contained HTML page, rendered by headless Chromium."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from tests.conftest import SAMPLE_DATA, run_cli

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


@pytest.fixture(scope="module")
def reep_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("html") / "reep"
    result = run_cli("reep", SAMPLE_DATA / "tapping_force_curve.h5", "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    return out


def test_report_is_self_contained(reep_folder):
    result = run_cli("report", reep_folder, "-q")
    assert result.returncode == 0, result.stderr.decode()
    page = (reep_folder / "report.html").read_text()
    for section in ("headline-block", "figures", "warnings", "details"):
        assert f'<section id="{section}"' in page
    for collapsed in ("inputs", "parameters", "results", "files"):
        assert f'<details id="{collapsed}">' in page
    assert page.count("data:image/png;base64,") == len(list(reep_folder.glob("*.png"))) >= 2
    assert "src=\"http" not in page and "href=\"http" not in page  # nothing fetched from elsewhere
    assert "summary.f0_hz.mean" in page  # every result, in the collapsed table


def test_report_of_a_non_output_folder(tmp_path):
    result = run_cli("report", tmp_path)
    assert result.returncode == 2
    assert "report.json" in result.stderr.decode()


def test_report_renders_in_headless_chromium(reep_folder, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("headless Chromium is not installed (Debian package chromium)")
    assert run_cli("report", reep_folder, "-o", tmp_path / "page.html", "-q").returncode == 0
    url = (tmp_path / "page.html").as_uri()
    common = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run([*common, "--dump-dom", url], capture_output=True, text=True, timeout=120).stdout
    for heading in ("Figures", "Warnings", "Details"):
        assert f"<h2>{heading}</h2>" in dom
    for summary in ("Inputs", "Parameters", "All results", "Files"):
        assert f"<summary>{summary}</summary>" in dom
    shot = tmp_path / "shot.png"
    subprocess.run([*common, f"--screenshot={shot}", "--window-size=1200,1600", url],
                   capture_output=True, timeout=120)
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (1600, 1200)
    assert float(np.std(pixels[..., :3])) > 0.05  # not a blank page
