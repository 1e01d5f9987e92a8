"""Docstrings for the reader: short module docstrings, every public name documented (with a
Parameters section where it takes any), no work history (issue numbers belong in commits). The
counting is docs/tools/docstring_stats.py's."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]



def _tool():
    spec = importlib.util.spec_from_file_location("docstring_stats", ROOT / "docs" / "tools" / "docstring_stats.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclass looks its module up
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def stats() -> dict:
    tool = _tool()
    return {pkg: tool.scan_package(ROOT / pkg) for pkg in tool.DEFAULT_PACKAGES}


def test_module_docstrings_are_short(stats):
    long = [m for s in stats.values() for m in s.long_modules]
    assert not long, "module docstrings of 20 lines or more (say what the module is, point to docs/): " + \
        ", ".join(long)


def test_public_functions_and_classes_have_docstrings(stats):
    missing = [m for s in stats.values() for m in s.undocumented]
    assert not missing, "public names without a docstring: " + ", ".join(missing)


def test_public_functions_with_parameters_document_them(stats):
    missing = [m for s in stats.values() for m in s.no_parameters]
    assert not missing, "public functions with parameters but no numpydoc 'Parameters' section: " + \
        ", ".join(missing)


def test_docstrings_name_no_issue(stats):
    history = [m for s in stats.values() for m in s.issue_mentions]
    assert not history, "docstrings that mention an issue number (work history belongs in commits): " + \
        ", ".join(history)


def test_the_counter_sees_what_it_should(tmp_path):
    tool = _tool()
    (tmp_path / "m.py").write_text('"""' + "line\n" * 21 + '"""\n\n'
                                   "def f(x):\n    return x\n\n\n"
                                   "def g(x):\n    \"\"\"G, see issue 12.\"\"\"\n    return x\n\n\n"
                                   "def _private(x):\n    return x\n\n\n"
                                   "class C:\n    def m(self):\n        return 1\n")
    s = tool.scan_package(tmp_path)
    assert len(s.long_modules) == 1
    assert sorted(u.rsplit(" ", 1)[1] for u in s.undocumented) == ["C", "C.m", "f"]
    assert [n.rsplit(" ", 1)[1] for n in s.no_parameters] == ["g"]
    assert len(s.issue_mentions) == 1
