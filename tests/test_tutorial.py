"""docs/tutorial.md is run as written, so the docs cannot rot.

Every ```bash block of the tutorial runs, in order, in one temporary folder
holding a link to sample_data/; a failing command fails the test.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from tests.conftest import REPO, SAMPLE_DATA

TUTORIAL = REPO / "docs" / "tutorial.md"


def tutorial_blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", TUTORIAL.read_text(), flags=re.S)


def test_tutorial_commands_run(tmp_path):
    blocks = tutorial_blocks()
    assert len(blocks) >= 5
    (tmp_path / "sample_data").symlink_to(SAMPLE_DATA)
    env = dict(os.environ)
    # the tests run from the source tree; make `afmtool` the same package and interpreter
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    launcher = bin_dir / "afmtool"
    launcher.write_text(f"#!/bin/sh\nexec {sys.executable} -m afmtool \"$@\"\n")
    launcher.chmod(0o755)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    env["PYTHONPATH"] = str(REPO)
    for number, block in enumerate(blocks, start=1):
        result = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=env,
                                capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, f"tutorial block {number} failed:\n{block}\n{result.stderr[-2000:]}"
