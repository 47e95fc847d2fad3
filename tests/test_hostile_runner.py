"""The hostile-case runner in CI (issue 34): its quick subset here, every case under ``-m slow``.

The counts of the whole run are in the notes of issue 34 and in docs/fuzzing.md;
rerun them with ``python -m tests.hostile_runner``.
"""

from __future__ import annotations

import pytest

from tests.hostile_cases import all_cases
from tests.hostile_runner import FORBIDDEN, counts, make_fixtures, run_cases, table


def _run(tmp_path, cases):
    fixtures = make_fixtures(tmp_path / "fixtures")
    outcomes = run_cases(cases, tmp_path / "cases", fixtures, jobs=2)
    print(table(outcomes))
    bad = [o for o in outcomes if o.outcome in FORBIDDEN]
    assert not bad, "\n".join(f"{o.outcome}: {o.case}: {o.detail}" for o in bad)
    return counts(outcomes)


def test_every_case_has_a_unique_name_and_a_known_group():
    cases = all_cases()
    assert len({c.name for c in cases}) == len(cases)
    groups = {c.group for c in cases}
    assert groups >= {"lock", "overlap", "rate", "numeric", "scheduler", "diskfull", "stdin", "batch", "files"}
    assert all(group in {c.group for c in cases if c.quick} for group in groups - {"batch"})  # CI sees every class


@pytest.mark.long
def test_the_quick_hostile_cases(tmp_path):
    tally = _run(tmp_path, [c for c in all_cases() if c.quick])
    assert tally["clean_error"] > 0 and tally["success"] > 0


@pytest.mark.slow
def test_every_hostile_case(tmp_path):
    _run(tmp_path, all_cases())
