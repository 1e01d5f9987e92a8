"""Output directories written whole or not at all.

A command that writes a directory (`dt demo --out`, `dt fit --out`, ...) writes it under a
temporary sibling and swaps it in when everything is written (`staged`); an interrupted run
leaves the previous output as it was. `final_path` names a staged file where it will end up.
See docs/cli.md ("Rules every command follows").
"""
from __future__ import annotations

import glob
import os
import shutil
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dt_kernel.errors import DataError

# Why whole or not at all: a re-run must never leave the new run's campaign beside the old run's
# summary, model and report (a traceability record that would be false). A run killed with
# SIGKILL leaves its `.NAME.partial-PID`, removed by the next run into the same place; killed
# between the two renames, it leaves the previous output as `.NAME.previous-PID`, which the next
# run puts back (`_leftovers`).
PARTIAL, PREVIOUS = "partial", "previous"

# Staged work directory (resolved) -> the directory it becomes (as the caller named it).
_STAGED: dict[Path, Path] = {}


def final_path(path: str | Path) -> Path:
    """Where `path` will be once its staged directory is swapped in.

    While a run is staged, the traceability record (`provenance.shown_path`) and every path a
    command writes into its summary go through this: ``m/hybrid.json``, not
    ``.m.partial-PID/hybrid.json``.

    Parameters
    ----------
    path : str or Path
        A path, possibly inside a staged directory.

    Returns
    -------
    Path
        The path where it will be; `path` itself when not staged.
    """
    p = Path(path)
    resolved = p.resolve()
    for work, target in _STAGED.items():
        if resolved == work or work in resolved.parents:
            return target / resolved.relative_to(work)
    return p


def _sibling(target: Path, kind: str, pid: int) -> Path:
    return target.parent / f".{target.name}.{kind}-{pid}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _leftovers(target: Path, command: str) -> None:
    """Clean up after a run into `target` that was killed (SIGKILL, power loss): its partial
    directory is removed; a previous output it had moved aside mid-swap is put back."""
    for kind in (PREVIOUS, PARTIAL):
        for p in sorted(target.parent.glob(f".{glob.escape(target.name)}.{kind}-*")):
            try:
                pid = int(p.name.rsplit("-", 1)[1])
            except ValueError:
                continue
            if pid == os.getpid() or _alive(pid):
                continue
            if kind == PREVIOUS and not target.exists():
                p.rename(target)
                _say(f"{command}: {target}: put back the previous output that a killed run (pid {pid}) had moved "
                     "aside")
            else:
                shutil.rmtree(p, ignore_errors=True)


def _check_target(target: Path, command: str, marks: tuple[str, ...], inputs: Iterable[str | Path]) -> None:
    if target.exists() and not target.is_dir():
        raise DataError(f"{target}: a file, not a directory (the output of {command} is a directory)")
    resolved, cwd = target.resolve(), Path.cwd().resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise DataError(f"{target}: holds the working directory, and an output directory is replaced whole: name a "
                        "directory of its own")
    for f in inputs:
        r = Path(f).resolve()
        if r == resolved or resolved in r.parents:
            raise DataError(f"{target}: holds the input {f}, and an output directory is replaced whole: write to "
                            "another directory")
    if target.is_dir() and any(target.iterdir()) and not any((target / m).exists() for m in marks):
        raise DataError(f"{target}: exists and is not a previous output of {command} (it has none of "
                        f"{', '.join(marks)}), and an output directory is replaced whole: name a new or empty one")


class _Held:
    """SIGINT and SIGTERM held off while the output is swapped in: recorded, and raised again once
    the block is done (Python runs signal handlers in the main thread only; elsewhere nothing
    needs holding)."""

    def __enter__(self) -> None:
        self.got: list[int] = []
        self.old: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            self.old = {s: signal.signal(s, lambda n, _f: self.got.append(n)) for s in (signal.SIGINT, signal.SIGTERM)}

    def __exit__(self, *exc: Any) -> None:
        for s, h in self.old.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)
        if self.got:
            signal.raise_signal(self.got[0])


def _swap_in(work: Path, target: Path) -> None:
    """`work` becomes `target`; the previous `target` (if any) is removed. A signal that arrives
    during the two renames is delivered after them (then the new output is in place)."""
    previous = _sibling(target, PREVIOUS, os.getpid())
    try:
        with _Held():
            if target.exists():
                target.rename(previous)
            work.rename(target)
    finally:
        shutil.rmtree(previous, ignore_errors=True)


def _on_sigterm(signum: int, _frame: Any) -> None:
    raise SystemExit(128 + signum)  # unwinds like Ctrl-C: the staged directory is removed


@contextmanager
def staged(target: str | Path, command: str, marks: tuple[str, ...] = (),
           inputs: Iterable[str | Path] = ()) -> Iterator[Path]:
    """Stage an output directory: write into a temporary sibling, swap it in at the end.

    Yields the sibling ``.NAME.partial-PID``; when the block ends normally it replaces `target`
    (two renames, SIGINT and SIGTERM held off between them). On an exception, Ctrl-C or SIGTERM
    (then exit status 143) the sibling is removed and stderr says that `target` was left as it
    was. Leftovers of a run killed by SIGKILL are cleaned up first (see `_leftovers`)::

        with staged(args.out, "dt fit", marks=("hybrid.json",)) as out:
            model.save(out)   # writes .m.partial-PID/...; m appears at the end

    Parameters
    ----------
    target : str or Path
        The output directory.
    command : str
        The command's name, for messages (e.g. "dt fit").
    marks : tuple of str, optional
        Files of which one marks a previous output of `command` (e.g. "twin.json").
    inputs : iterable of str or Path, optional
        The run's inputs, which `target` must not hold.

    Yields
    ------
    Path
        The staged directory to write into.

    Raises
    ------
    DataError
        Before anything is written, when `target` is a file, holds the working directory or one
        of `inputs`, or is a non-empty directory without any of `marks`.
    """
    target = Path(target)
    _check_target(target, command, marks, inputs)
    target.parent.mkdir(parents=True, exist_ok=True)
    _leftovers(target, command)
    work = _sibling(target, PARTIAL, os.getpid())
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    key = work.resolve()
    _STAGED[key] = target
    # SIGTERM (a service manager, `kill`) unwinds like Ctrl-C while the output is staged, unless
    # the process was told to ignore it or someone else handles it.
    term = threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    if term:
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        try:
            yield work
        except BaseException as exc:
            shutil.rmtree(work, ignore_errors=True)
            why = "interrupted" if isinstance(exc, (KeyboardInterrupt, SystemExit)) else "failed"
            _say(f"{command}: {why}: {target} " + ("left as it was (the new output was not kept)" if target.exists()
                                                    else "not written"))
            raise
        _swap_in(work, target)
    finally:
        _STAGED.pop(key, None)
        if term:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
