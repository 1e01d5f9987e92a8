"""The user documentation (docs/) tells the same story as the code: links resolve, the
architecture picture is the one the imports give, every documented `dt` command and option
exists (and every command is documented), and the examples in the pages parse as documented.
Fast: no simulation, no model fit."""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = sorted([ROOT / "README.md", *DOCS.glob("*.md")])


def _page_ids(p: Path) -> str:
    return p.relative_to(ROOT).as_posix()


def _without_code(text: str) -> str:
    """Markdown text with fenced code blocks and inline code removed (links there are examples)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lowercase, punctuation dropped, spaces to hyphens."""
    s = heading.strip().lower()
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


def _anchors(md: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", md.read_text(encoding="utf-8"), flags=re.S | re.M)
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.*)$", text, flags=re.M)}


def _links(md: Path) -> list[str]:
    text = _without_code(md.read_text(encoding="utf-8"))
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text)


# --------------------------------------------------------------------------- (a) links

@pytest.mark.parametrize("page", PAGES, ids=_page_ids)
def test_every_relative_link_points_to_an_existing_file(page):
    bad = []
    for target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        dest = page if not path else (page.parent / path).resolve()
        if not dest.exists():
            bad.append(f"{target}: no such file {dest}")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target}: no heading '#{anchor}' in {dest.name}")
    assert not bad, f"{_page_ids(page)}: broken links:\n" + "\n".join(bad)


def test_the_docs_pages_are_all_in_the_index():
    index = (DOCS / "README.md").read_text(encoding="utf-8")
    missing = [p.name for p in DOCS.glob("*.md") if p.name != "README.md" and f"({p.name})" not in index]
    assert not missing, f"docs/README.md does not link {missing}"


# --------------------------------------------------------------------------- (b) architecture

def _architecture_tool():
    spec = importlib.util.spec_from_file_location("docs_architecture", DOCS / "tools" / "architecture.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_architecture_picture_is_up_to_date_with_the_imports():
    tool = _architecture_tool()
    committed = tool.committed_block((DOCS / "architecture.md").read_text(encoding="utf-8"))
    assert committed, "docs/architecture.md lost its GENERATED markers"
    fresh = tool.generated_block()
    assert committed == fresh, ("docs/architecture.md is out of date with the code's imports: "
                                "run .venv/bin/python docs/tools/architecture.py and commit the result")
    nodes, edges = tool.graph()
    svg = (DOCS / "architecture.svg").read_text(encoding="utf-8")
    assert f"edge-set fingerprint {tool.fingerprint(edges)}" in svg, (
        "docs/architecture.svg is out of date: run .venv/bin/python docs/tools/architecture.py")


def test_the_architecture_graph_reads_the_imports():
    tool = _architecture_tool()
    nodes, edges = tool.graph()
    assert {"dt_kernel", "sim", "drivers", "dt_runtime.cli", "dt_runtime.common"} <= set(nodes)
    assert not tool.cycles(nodes, edges)
    assert not [e for e in edges if e[0] == "dt_kernel"], "dt_kernel imports nothing of the project"
    assert ("sim", "dt_kernel") in edges and ("drivers.simulated", "sim") in edges
    # the resolver itself: relative, lazy and `from pkg import module` imports all count
    src = "from ..frames import registration\ndef f():\n    from dt_runtime.cli import main\n"
    got = tool.imports_of(src, "dt_runtime.models.hybrid", False)
    assert {"dt_runtime.frames", "dt_runtime.frames.registration", "dt_runtime.cli.main"} <= got
    assert tool.node_of("dt_runtime.models.hybrid") == "dt_runtime.models"
    assert tool.node_of("drivers.registry") == "drivers" and tool.node_of("numpy") is None


# --------------------------------------------------------------------------- (c) commands

def _documented_commands() -> list[str]:
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    return re.findall(r"^## `dt (\w+)`", text, flags=re.M)


def _dt_help(*args: str) -> str:
    out = subprocess.run([sys.executable, "-m", "dt_runtime.cli", *args, "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_every_command_in_cli_md_exists_in_dt_help_and_back():
    documented = _documented_commands()
    assert len(documented) >= 7
    help_text = _dt_help()
    real = set(re.findall(r"^    (\w+)\s", help_text, flags=re.M))
    assert not set(documented) - real, f"docs/cli.md documents commands dt lacks: {set(documented) - real}"
    assert not real - set(documented), f"dt commands missing from docs/cli.md: {real - set(documented)}"
    assert "--version" in help_text


def test_every_option_documented_for_a_command_exists():
    from dt_runtime.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    sections = re.split(r"^## ", text, flags=re.M)
    bad = []
    for sec in sections:
        m = re.match(r"`dt (\w+)`", sec)
        if not m:
            continue
        name = m.group(1)
        usage = re.search(r"```text\n(dt .*?)```", sec, flags=re.S)
        assert usage, f"docs/cli.md: `dt {name}` has no usage block"
        documented = set(re.findall(r"(--[a-z][a-z-]*)", usage.group(1) + "\n".join(
            line for line in sec.splitlines() if line.startswith("| `--"))))
        real = {o for a in sub.choices[name]._actions for o in a.option_strings}
        bad += [f"dt {name} {o}" for o in sorted(documented - real)]
        bad += [f"dt {name} {o} (undocumented)" for o in sorted(real - documented - {"--help", "-h"})]
    assert not bad, "docs/cli.md and the parser disagree:\n" + "\n".join(bad)


# --------------------------------------------------------------------------- (d) examples

def _blocks(page: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", (DOCS / page).read_text(encoding="utf-8"),
                      flags=re.S | re.M)


def test_measurement_table_examples_read_as_documented(tmp_path):
    from dt_runtime import import_file, read_table

    with_error, with_measured = _blocks("measurement-table.md", "csv")[:2]
    (tmp_path / "e.csv").write_text(with_error, encoding="utf-8")
    (tmp_path / "m.csv").write_text(with_measured, encoding="utf-8")
    a, b = read_table(tmp_path / "e.csv"), read_table(tmp_path / "m.csv")
    np.testing.assert_allclose(a.error, b.error, atol=1e-12)  # e = commanded - measured
    np.testing.assert_allclose(a.error[0] * 1e3, [0.050, -0.012, 0.031], atol=1e-12)
    assert a.speed[0] == pytest.approx(0.3)  # mm/s in the file, m/s in the code

    foreign = _blocks("measurement-table.md", "text")[0]
    mapping = _blocks("measurement-table.md", "yaml")[0]
    (tmp_path / "cell7.csv").write_text(foreign, encoding="utf-8")
    (tmp_path / "cell7.yaml").write_text(mapping, encoding="utf-8")
    ds, _ = import_file(tmp_path / "cell7.csv", tmp_path / "cell7.yaml")
    np.testing.assert_allclose(ds.commanded, a.commanded[:2], atol=1e-12)
    np.testing.assert_allclose(ds.error, a.error[:2], atol=1e-12)  # sign flipped by the mapping
    np.testing.assert_allclose(ds.t, [0.0, 6.2])


def test_the_worked_ur10_mapping_is_the_shipped_one(tmp_path):
    from dt_runtime import load_mapping

    (tmp_path / "ur10.yaml").write_text(_blocks("measurement-table.md", "yaml")[1], encoding="utf-8")
    doc = load_mapping(tmp_path / "ur10.yaml").model_dump()
    shipped = load_mapping(ROOT / "configs" / "import" / "ur10.yaml").model_dump()
    doc["description"] = shipped["description"]
    assert doc == shipped


def test_the_tls_acl_example_in_bus_md_is_the_shipped_one(tmp_path):
    from dt_runtime.fabric import load_bus_config

    (tmp_path / "bus.yaml").write_text(_blocks("bus.md", "yaml")[0], encoding="utf-8")
    assert load_bus_config(tmp_path / "bus.yaml") == load_bus_config(ROOT / "configs" / "bus_tls_acl_example.yaml")


def test_effects_md_covers_every_effect_and_its_diagnosis_factor():
    from dt_runtime.models import effects as fx

    registry = getattr(fx, "REGISTRY", None)
    names = tuple(registry) if registry is not None else tuple(fx.EFFECT_NAMES)
    assert names == ("geometric", "compliance", "gear", "backlash", "thermal", "dynamic", "drift")
    if registry is not None:
        factors = {n: e.factor for n, e in registry.items()}
    else:
        from dt_runtime.analysis.diagnose import FACTOR as factors
    text = (DOCS / "effects.md").read_text(encoding="utf-8")
    assert set(re.findall(r"^## `(\w+)`", text, flags=re.M)) == set(names)
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `(\w+)` \|.*$", text, flags=re.M)}
    missing = [n for n in names if n not in rows or factors[n] not in rows[n]]
    assert not missing, f"docs/effects.md table lacks the effect or its diagnosis factor: {missing}"


def test_nothing_points_to_a_design_file_a_clone_does_not_have():
    """The design's contracts are carried by docs/ (a fresh clone has no ../shared design file)."""
    name = "DESIGN" + ".md"  # spelled apart so this test does not find itself
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    bad = [f for f in files if f.endswith((".py", ".md", ".yaml", ".toml"))
           and name in (ROOT / f).read_text(encoding="utf-8", errors="replace")]
    assert not bad, f"files naming {name}, which the repository lacks: {bad}"
