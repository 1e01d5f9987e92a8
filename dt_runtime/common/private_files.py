"""Files only the service's user may read or write (mode 0600): the store, its lock, the bus key.

Created 0600 from the start (`os.open` with the mode, not a chmod afterwards: there is no moment
when another user could open it). An existing file that others may read or write is treated by
kind (docs/bus.md, "Files"):
- the store and its lock (`tighten`): made 0600 with a warning naming the file and its old mode.
  Their content is a record, not a secret; what matters is that from now on only the service's
  user can write it, and refusing to start would stop a running cell over a file mode.
- a key (`looser_than_private`, checked by dt_runtime.fabric.auth): refused. A key others
  could read may have been copied; tightening it would hide that. The operator makes a new one
  (or, knowing nobody read it, chmods it).
"""
from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

log = logging.getLogger("dt.files")

PRIVATE = 0o600
_OTHERS = stat.S_IRWXG | stat.S_IRWXO  # any bit for the group or others


def mode_of(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def create_private(path: Path) -> bool:
    """Create `path` empty with mode 0600 unless it exists; True if this call created it.
    OSError as the file system raises it."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def open_private(path: Path, what: str = "file", flags: int = os.O_RDWR | os.O_CREAT) -> int:
    """`os.open` of `path` creating it 0600, then `tighten`ed: a file descriptor."""
    fd = os.open(path, flags, PRIVATE)
    try:
        tighten(path, what)
    except OSError:
        os.close(fd)
        raise
    return fd


def tighten(path: Path, what: str = "file") -> bool:
    """Make an existing `path` 0600 if the group or others have any access, warning with its old
    mode; True if it was changed. A missing file is left alone; OSError if the mode cannot be
    changed (the file belongs to another user)."""
    try:
        mode = mode_of(path)
    except FileNotFoundError:
        return False
    if not mode & _OTHERS:
        return False
    os.chmod(path, PRIVATE)
    log.warning("%s %s was mode %04o (other users could read or write it): made 0600", what, path, mode)
    return True


def looser_than_private(path: Path) -> int | None:
    """The mode of `path` if the group or others have any access to it, else None."""
    mode = mode_of(path)
    return mode if mode & _OTHERS else None
