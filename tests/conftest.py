"""The suite's common setup: the longest test files first, and no progress lines by default.

``make test`` runs the suite on pytest-xdist workers with ``--dist loadfile``: each file on
one worker (its module fixtures and caches built once), files handed out in collection
order as workers come free. Handed out alphabetically, a file of several minutes can start
last and run alone while the other worker idles; longest first (the greedy order that
keeps the makespan within a third of the ideal, Graham 1969) lets the short files fill in
around them. The order of the tests inside a file is unchanged, and so is the set of tests.

Without a terminal a command prints a line per stage once it has run for
``pipeline.core.progress.LOG_AFTER_S``: what a test reads on stderr would then depend on the
machine's speed. Every test runs with ``MAGALIGN_PROGRESS=never`` (inherited by the commands
it starts) unless it sets the mode itself, as the tests of the progress display do.
"""

from __future__ import annotations

import pytest

#: The files whose tests take more than about a minute together on 2 cores (measured with
#: ``pytest --durations``, docs/testing.md, "Running time"), longest first.
LONGEST_FIRST = (
    "test_local_source_indep.py",
    "test_stability.py",
    "test_regress.py",
    "test_kill_rerun.py",
    "test_bad_input_cli.py",
    "test_honest.py",
    "test_one_runner.py",
    "test_campaign.py",
    "test_semireal.py",
    "test_diagnose_real.py",
    "test_fuzz.py",
    "test_field_map.py",
)


def _rank(item: pytest.Item) -> int:
    name = item.path.name
    return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the longest files first, keeping the order within each file (a stable sort)."""
    items.sort(key=_rank)


@pytest.fixture(autouse=True)
def _no_progress_lines(monkeypatch: pytest.MonkeyPatch) -> None:
    """Run each test with the progress display off unless the test sets its mode."""
    monkeypatch.setenv("MAGALIGN_PROGRESS", "never")


@pytest.fixture(scope="session")
def real_outputs(tmp_path_factory: pytest.TempPathFactory):
    """``process`` of the shared real recordings, run once for the whole suite
    (tests/real_campaign.py); skips when they are absent."""
    from real_campaign import real_run

    return real_run(tmp_path_factory)
