"""docs/python.md runs (issue 30, item 3): its code blocks, in order, and the figures they draw carry units.

The blocks are executed in one namespace, as a notebook would, from a folder
that holds ``sample_data/`` (a link to the repository's); afterwards every
matplotlib figure the walk-through left open must label both axes of each
plot, and each label must carry units in parentheses.
"""

from __future__ import annotations

import re

import pytest

from tests.conftest import REPO

DOC = REPO / "docs" / "python.md"


def code_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_the_walkthrough_has_the_thesis_workflow():
    blocks = code_blocks(DOC.read_text())
    joined = "\n".join(blocks)
    for call in ("afmtool.open(", "afmtool.identify_freeair(", "afmtool.reep(", "f0_std_hz", "q_std",
                 "afmtool.theory_compare(", "afmtool.probeloss(", "afmtool.decode(", "Capture.from_arrays("):
        assert call in joined, call


@pytest.mark.long
def test_docs_python_md_runs_and_its_figures_have_units(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (tmp_path / "sample_data").symlink_to(REPO / "sample_data")
    monkeypatch.chdir(tmp_path)
    plt.close("all")
    namespace: dict = {}
    for i, block in enumerate(code_blocks(DOC.read_text())):
        exec(compile(block, f"docs/python.md block {i + 1}", "exec"), namespace)
    figures = [plt.figure(n) for n in plt.get_fignums()]
    assert len(figures) >= 2
    for figure in figures:
        for ax in figure.axes:
            if not ax.has_data():
                continue
            labels = [ax.get_ylabel()] + ([ax.get_xlabel()] if ax.get_xlabel() or ax is figure.axes[-1] else [])
            for label in labels:
                assert re.search(r"\(.+\)", label), f"axis label {label!r} has no units"
    assert (tmp_path / "results" / "freeair" / "free_air.json").is_file()
    plt.close("all")
