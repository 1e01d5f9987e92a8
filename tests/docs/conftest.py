"""The docs commands test prints every command it ran, with its page and line, at the end of the
run (pytest's terminal summary), so a CI log shows what the documentation's commands did."""
from __future__ import annotations

from tests.support import doc_commands


def pytest_terminal_summary(terminalreporter):
    if not doc_commands.RAN and not doc_commands.NOT_RUN:
        return
    tr = terminalreporter
    tr.section("commands of the documentation")
    for where, script, seconds, rc in doc_commands.RAN:
        tr.write_line(f"{'ok' if rc == 0 else f'FAILED (exit {rc})'}  {seconds:.1f} s  {where}")
        for line in script.splitlines():
            tr.write_line(f"    {line}")
    for where, reason in doc_commands.NOT_RUN:
        tr.write_line(f"not run  {where}  ({reason})")
    for where, setup in doc_commands.SKIPPED_SETUP:
        tr.write_line(f"set-up skipped  {where}  {setup}  (the copy reuses the suite's venv)")
