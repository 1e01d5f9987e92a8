"""docs/library.md is a session a user can paste: run it as a doctest from the repository root."""
from __future__ import annotations

import doctest
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_library_page_runs_as_written(monkeypatch):
    monkeypatch.chdir(ROOT)  # the page's paths are relative to the repository's root
    res = doctest.testfile(str(ROOT / "docs" / "library.md"), module_relative=False,
                           optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert res.attempted >= 10
    assert res.failed == 0
