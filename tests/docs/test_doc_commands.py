"""Every command the user documentation shows runs as written (tests/support/doc_commands.py
states the convention): each page's ``bash``/``sh`` blocks, in order, in a fresh copy of the
repository (the files git tracks or would track, as a clone of the working tree has them; no out/,
no .venv of its own: the suite's venv is linked in as .venv and first on PATH, not reinstalled).

Pages with a block marked ``<!-- run: long -->`` run under ``-m docs_long`` (CI's second step);
the others in the default suite. A block fails the test when any command of it fails (``set -euo
pipefail``), a background job of it fails, it leaves a process running, or it runs past its
time-out. The documented ports are fixed (7447, 8765, ...): a file lock keeps two copies of the
suite from running pages at the same time. Bus keys go to a temporary XDG_CONFIG_HOME."""
from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.support import doc_commands as dc

ROOT = Path(__file__).resolve().parents[2]
PAGES = dc.pages(ROOT)
BLOCKS = {p.relative_to(ROOT).as_posix(): dc.blocks(p, ROOT) for p in PAGES}
RUN_PAGES = {page: bs for page, bs in BLOCKS.items() if any(b.runs for b in bs)}
# Listed at the end of every run that collects this module (tests/docs/conftest.py).
dc.NOT_RUN[:] = [(b.where(), b.not_run) for bs in BLOCKS.values() for b in bs if b.not_run]
SHORT_TIMEOUT_S = 600  # a block of a default-suite page (generous: two cores shared with another suite)
LONG_TIMEOUT_S = 2400  # a block of a docs_long page (the full demo: ~2 min on a loaded machine)
# Every background job must end well: 0, or 143 when the block itself stopped it (`kill %1`: SIGTERM).
EPILOGUE = """
for _job in $(jobs -p); do
    _rc=0; wait "$_job" || _rc=$?
    if [ "$_rc" != 0 ] && [ "$_rc" != 143 ]; then
        echo "docs test: a background command of this block failed (exit $_rc)" >&2; exit 1
    fi
done
"""


def _params():
    out = []
    for page, bs in sorted(RUN_PAGES.items()):
        marks = [pytest.mark.docs_long] if any(b.long for b in bs) else []
        out.append(pytest.param(page, marks=marks, id=page))
    return out


def _copy_of_the_repository(dest: Path) -> Path:
    """The working tree as a clone of it has it: tracked and not-ignored files, nothing else."""
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    for f in filter(None, files):
        src = ROOT / f
        if src.is_file():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f)
    (dest / ".venv").symlink_to(Path(sys.prefix))
    return dest


def _alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False


def _run_block(block: dc.Block, cwd: Path, env: dict, timeout_s: float) -> tuple[int, str, float]:
    script = "set -euo pipefail\n" + block.script() + EPILOGUE
    t0 = time.monotonic()
    with tempfile.TemporaryFile() as log:
        p = subprocess.Popen(["bash", "-c", script], cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                             start_new_session=True)
        try:
            rc = p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            rc = -1
        left = _alive(p.pid)
        if left:
            os.killpg(p.pid, signal.SIGTERM)
            end = time.monotonic() + 20
            while _alive(p.pid) and time.monotonic() < end:
                time.sleep(0.1)
            if _alive(p.pid):
                os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        log.seek(0)
        out = log.read().decode(errors="replace")
    seconds = time.monotonic() - t0
    if rc == -1:
        out += f"\ndocs test: the block ran past its time-out ({timeout_s:g} s) and was stopped"
    elif left:
        rc = rc or -2
        out += "\ndocs test: the block left a process running (give a server --duration, or stop it)"
    return rc, out, seconds


@pytest.mark.parametrize("page", _params())
def test_the_commands_of_a_page_run_as_written(page, tmp_path):
    bs = RUN_PAGES[page]
    long = any(b.long for b in bs)
    repo = _copy_of_the_repository(tmp_path / "repo")
    venv_bin = Path(sys.prefix) / "bin"
    env = {**os.environ, "PATH": f"{repo / '.venv' / 'bin'}{os.pathsep}{venv_bin}{os.pathsep}{os.environ['PATH']}",
           "VIRTUAL_ENV": sys.prefix, "MPLBACKEND": "Agg", "XDG_CONFIG_HOME": str(tmp_path / "config"),
           "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("PYTHONPATH", None)
    lock_path = Path(tempfile.gettempdir()) / "cobot-dt-doc-commands.lock"
    with lock_path.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # the documented ports are fixed: one page at a time on this host
        for b in bs:
            if not b.runs:
                continue
            rc, out, seconds = _run_block(b, repo, env, LONG_TIMEOUT_S if long else SHORT_TIMEOUT_S)
            dc.SKIPPED_SETUP += [(b.where(), s) for s in b.skipped_setup]
            dc.RAN.append((b.where(), b.script().rstrip(), seconds, rc))
            assert rc == 0, (f"{b.where()}: the block failed (exit {rc}):\n{b.script()}\n"
                             f"--- output (last 4000 chars):\n{out[-4000:]}")


def test_every_fence_names_its_language_and_every_marker_a_block():
    """A block of commands cannot hide as an untagged one; a marker stands right before a block."""
    bad = []
    for bs in BLOCKS.values():
        bad += [f"{b.where()}: a fence without a language (bash, sh, text, yaml, python, ...)"
                for b in bs if not b.lang]
        bad += [f"{b.where()}: marked not run but is {b.lang}, never run anyway" for b in bs
                if b.not_run and b.lang not in dc.RUN_LANGS]
    for path in PAGES:
        lines = path.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            m = dc.MARKER.match(line)
            if not m:
                continue
            rest = [x for x in lines[i + 1:] if x.strip()]
            if not rest or not dc.FENCE.match(rest[0]):
                bad.append(f"{path.name}:{i + 1}: a marker not followed by a fenced block")
            if m.group(1) == "run" and m.group(2) != "long":
                bad.append(f"{path.name}:{i + 1}: '<!-- run: {m.group(2)} -->': the only run marker is 'long'")
            if m.group(1) == "not run" and not m.group(2):
                bad.append(f"{path.name}:{i + 1}: 'not run' without a reason")
    assert not bad, "\n".join(bad)


def test_the_extraction_reads_markers_and_drops_only_the_setup(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# p\n\n<!-- not run: needs a real UR controller -->\n```bash\ndt run --config ur.yaml\n```\n\n"
                    "<!-- run: long -->\n\n```sh\npython3 -m venv .venv && .venv/bin/pip install -e . && dt demo\n```\n"
                    "```text\n$ dt demo\n```\n", encoding="utf-8")
    a, b, c = dc.blocks(page, tmp_path)
    assert (a.runs, a.not_run, a.line) == (False, "needs a real UR controller", 4)
    assert (b.runs, b.long, b.script(), b.skipped_setup) == (True, True, "dt demo\n",
                                                              ["python3 -m venv .venv", ".venv/bin/pip install -e ."])
    assert not c.runs


def test_ci_runs_the_readmes_test_command():
    """The README's test command is what CI runs (.ci/run carries the same line)."""
    cmds = [b for b in BLOCKS["README.md"] if b.lang in dc.RUN_LANGS and "pytest" in b.text]
    assert len(cmds) == 1, "the README shows one test command"
    line = cmds[0].text.strip()
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert line in ci, f".ci/run does not run the README's test command:\n{line}"
    assert "-m docs_long" in ci, ".ci/run does not run the documentation's long commands"
