"""The shell commands the user documentation shows (README.md and docs/*.md), for the docs
commands test (tests/docs/test_doc_commands.py).

The convention, stated in docs/README.md ("Every command shown is run"):

- a fenced block tagged ``bash`` or ``sh`` is commands, and the test runs it, in the page's order,
  in a fresh copy of the repository (the suite's venv reused: ``.venv/bin/dt`` and ``dt`` resolve);
- a block is left out only by a visible marker on the line before it (blank lines between allowed):
  ``<!-- not run: REASON -->`` (a real robot, root, the suite itself); the test lists them;
- ``<!-- run: long -->`` before a block puts its page in the ``docs_long`` run (the demo, campaign
  runs, the plant walkthrough), which CI runs as a second step (.ci/run);
- every other fence carries a language too (``text`` for output, ``yaml``, ``python``...), so a
  block of commands cannot hide as an untagged one;
- a block ends by itself: a server it starts is given ``--duration`` (or stopped by the block), and
  a background job that fails fails the block.

The fresh-machine set-up steps (``python3 -m venv .venv``, ``.venv/bin/pip install ...``) are not
repeated: the copy reuses the venv they made (CI runs them, .ci/run), and the list says so."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

RUN_LANGS = ("bash", "sh")
FENCE = re.compile(r"^```([\w+-]*)\s*$")
MARKER = re.compile(r"^<!--\s*(not run|run):\s*(.*?)\s*-->\s*$")
# The set-up a fresh machine needs and the copy already has (the suite's venv), one `&&` part each.
SETUP = (re.compile(r"^python3? -m venv \.venv$"), re.compile(r"^\.venv/bin/pip install( -q)? -e \S+$"))


@dataclass
class Block:
    """One fenced block of a page: where it starts, its language, its text and its marker."""

    page: str
    line: int  # 1-based line of the opening fence
    lang: str
    text: str
    not_run: str | None = None  # the reason, when marked `<!-- not run: ... -->`
    long: bool = False  # marked `<!-- run: long -->`
    skipped_setup: list[str] = field(default_factory=list)

    @property
    def runs(self) -> bool:
        return self.lang in RUN_LANGS and self.not_run is None

    def where(self) -> str:
        return f"{self.page}:{self.line}"

    def script(self) -> str:
        """The block as run: the set-up parts that the copy already has dropped (recorded in
        ``skipped_setup``), everything else as written."""
        out, self.skipped_setup = [], []
        for line in self.text.splitlines():
            parts = [p.strip() for p in line.split(" && ")] if "&&" in line else [line]
            kept = []
            for p in parts:
                if any(rx.match(p) for rx in SETUP):
                    self.skipped_setup.append(p)
                else:
                    kept.append(p)
            if kept and any(k.strip() for k in kept):
                out.append(" && ".join(kept) if len(parts) > 1 else kept[0])
        return "\n".join(out) + "\n"


def blocks(path: Path, root: Path) -> list[Block]:
    """Every fenced block of a markdown page, with its marker; an unclosed fence is an error."""
    lines = path.read_text(encoding="utf-8").splitlines()
    page = path.relative_to(root).as_posix()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        if j == len(lines):
            raise ValueError(f"{page}:{i + 1}: a fenced block that is never closed")
        b = Block(page, i + 1, m.group(1), "\n".join(lines[i + 1:j]))
        k = i - 1
        while k >= 0 and not lines[k].strip():
            k -= 1
        mk = MARKER.match(lines[k]) if k >= 0 else None
        if mk and mk.group(1) == "not run":
            b.not_run = mk.group(2) or "(no reason given)"
        elif mk and mk.group(2) == "long":
            b.long = True
        found.append(b)
        i = j + 1
    return found


def pages(root: Path) -> list[Path]:
    """The user documentation: the README and every page of docs/."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


# What the test ran, for the terminal summary (tests/docs/conftest.py): (page:line of the block,
# its commands as run, seconds the block took, exit code), the blocks marked not run (page:line,
# reason), and the set-up parts dropped (page:line, command).
RAN: list[tuple[str, str, float, int]] = []
NOT_RUN: list[tuple[str, str]] = []
SKIPPED_SETUP: list[tuple[str, str]] = []
