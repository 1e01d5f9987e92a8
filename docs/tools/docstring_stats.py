"""Count docstring gaps per package, for reviewing docstrings.

Run from the repository root: ``python docs/tools/docstring_stats.py [package ...]``.
For each package it prints modules whose docstring is 20 lines or longer, public
functions/classes/methods without a docstring, and public functions with parameters
but no ``Parameters`` section. Uses only the standard library (``ast``).
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

# The packages brought to the rules (tests/unit/test_docstrings.py checks these): add one once it complies.
DEFAULT_PACKAGES = (
    "dt_kernel",
    "dt_runtime/common",
    "dt_runtime/metrology",
    "dt_runtime/frames",
    "dt_runtime/measurements",
    "dt_runtime/models",
    "dt_runtime/analysis",
    "dt_runtime/reports",
    "dt_runtime/twin",
    "dt_runtime/programs",
    "dt_runtime/workflows",
    "drivers",
    "sim",
    "emulators",
    "dt_runtime/plant",
    "dt_runtime/dashboard",
    "dt_runtime/cli",
    "dt_runtime/fabric",
    "dt_runtime/service",
)
LONG_MODULE_DOC = 20
ISSUE_RE = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)


@dataclass
class Stats:
    """Docstring findings for one package."""

    long_modules: list[str] = field(default_factory=list)
    undocumented: list[str] = field(default_factory=list)
    no_parameters: list[str] = field(default_factory=list)
    issue_mentions: list[str] = field(default_factory=list)


def _is_public(name: str) -> bool:
    return not name.startswith("_")


def _has_parameters(node: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> bool:
    args = node.args
    names = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
    if method and names and names[0] in ("self", "cls"):
        names = names[1:]
    return bool(names or args.vararg or args.kwarg)


def _is_overload_or_property(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for dec in node.decorator_list:
        target = dec.attr if isinstance(dec, ast.Attribute) else getattr(dec, "id", "")
        if target in ("overload", "setter", "deleter"):
            return True
    return False


def scan_file(path: Path, stats: Stats) -> None:
    """Add the findings for one module to ``stats``.

    Parameters
    ----------
    path : Path
        The Python source file.
    stats : Stats
        Accumulator, updated in place.
    """
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    doc = ast.get_docstring(tree, clean=False)
    if doc is not None and len(doc.splitlines()) >= LONG_MODULE_DOC:
        stats.long_modules.append(str(path))

    def check_doc(node: ast.AST, where: str) -> None:
        text = ast.get_docstring(node, clean=False)  # type: ignore[arg-type]
        if text and ISSUE_RE.search(text):
            stats.issue_mentions.append(where)

    check_doc(tree, str(path))

    def visit(body: list[ast.stmt], prefix: str, in_class: bool) -> None:
        for node in body:
            if isinstance(node, ast.ClassDef):
                where = f"{path}:{node.lineno} {prefix}{node.name}"
                check_doc(node, where)
                if _is_public(node.name):
                    if ast.get_docstring(node) is None:
                        stats.undocumented.append(where)
                    visit(node.body, f"{prefix}{node.name}.", True)
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                where = f"{path}:{node.lineno} {prefix}{node.name}"
                check_doc(node, where)
                if not _is_public(node.name) or _is_overload_or_property(node):
                    continue
                doc = ast.get_docstring(node)
                if doc is None:
                    stats.undocumented.append(where)
                elif _has_parameters(node, in_class) and "Parameters" not in doc:
                    stats.no_parameters.append(where)

    visit(tree.body, "", False)


def scan_package(package: str | Path) -> Stats:
    """Scan every module of a package directory.

    Parameters
    ----------
    package : str or Path
        Package directory, e.g. ``dt_runtime/models``.

    Returns
    -------
    Stats
        The findings over all ``*.py`` files under the directory.
    """
    stats = Stats()
    for path in sorted(Path(package).rglob("*.py")):
        scan_file(path, stats)
    return stats


def main(argv: list[str]) -> int:
    """Print the counts per package; ``-v`` also lists the findings.

    Parameters
    ----------
    argv : list of str
        Package directories and optional ``-v``.

    Returns
    -------
    int
        Process exit status (always 0).
    """
    verbose = "-v" in argv
    packages = [a for a in argv if a != "-v"] or list(DEFAULT_PACKAGES)
    print(f"{'package':28} {'long-mod':>8} {'no-doc':>7} {'no-Params':>9} {'issue#':>6}")
    for package in packages:
        s = scan_package(package)
        print(
            f"{package:28} {len(s.long_modules):8} {len(s.undocumented):7} "
            f"{len(s.no_parameters):9} {len(s.issue_mentions):6}"
        )
        if verbose:
            for label, items in (
                ("long module docstring", s.long_modules),
                ("no docstring", s.undocumented),
                ("no Parameters", s.no_parameters),
                ("mentions an issue", s.issue_mentions),
            ):
                for item in items:
                    print(f"    {label}: {item}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
