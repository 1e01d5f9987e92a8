"""The README is a guide a newcomer reads in ten minutes, and the user documentation speaks of the
software, not of its work history: the README stays short, its layout and docs/architecture.md name
every package there is, and no page of README.md or docs/ speaks of issues or shortfall histories."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")
MAX_README_LINES = 250


def _packages() -> tuple[list[str], list[str]]:
    top = sorted(p.parent.name for p in ROOT.glob("*/__init__.py") if p.parent.name not in ("tests",))
    sub = sorted(p.parent.name for p in (ROOT / "dt_runtime").glob("*/__init__.py"))
    return top, sub


def test_the_readme_is_short():
    n = len(README.splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}: move detail to docs/)"


def test_the_readme_layout_names_every_package():
    layout = re.search(r"^## Layout\n(.*?)(?=^## |\Z)", README, flags=re.S | re.M)
    assert layout, "README.md has no '## Layout' section"
    top, sub = _packages()
    text = layout.group(1)
    missing = [f"{t}/" for t in top if f"{t}/" not in text] + [f"dt_runtime/{s}" for s in sub
                                                                if not re.search(rf"\b{s}\b", text)]
    assert not missing, f"README.md's layout does not name {missing}"


def test_architecture_md_says_what_every_package_holds():
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    table = re.search(r"^## What each package holds\n(.*?)(?=^## )", text, flags=re.S | re.M).group(1)
    top, sub = _packages()
    missing = [t for t in top if t != "dt_runtime" and f"`{t}/`" not in table]  # dt_runtime: by its layers
    missing += [s for s in sub if f"| `dt_runtime/{s}/` |" not in table]
    assert not missing, f"docs/architecture.md's package table lacks {missing}"


def test_no_user_document_speaks_of_issues_or_shortfall_histories():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    bad = []
    for p in pages:
        for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"\bissues?\b|shortfall|before issue", line, flags=re.I):
                bad.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()[:120]}")
    assert not bad, "user documents speak of the work's history (say what the software does):\n" + "\n".join(bad)
