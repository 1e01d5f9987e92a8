"""Files only the service's user may read or write (mode 0600): the store, its lock, the bus key.

Created 0600 from the start (no moment when another user could open them); an existing file that
others may access is tightened (the store, its lock) or refused (a key): docs/bus.md, "Files".
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
    """The permission bits of `path`.

    Parameters
    ----------
    path : Path
        An existing file.

    Returns
    -------
    int
        Its mode's permission bits (e.g. 0o600); OSError as `stat` raises it.
    """
    return stat.S_IMODE(path.stat().st_mode)


def create_private(path: Path) -> bool:
    """Create `path` empty with mode 0600 unless it exists.

    Parameters
    ----------
    path : Path
        The file to create.

    Returns
    -------
    bool
        True if this call created it; OSError as the file system raises it.
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def open_private(path: Path, what: str = "file", flags: int = os.O_RDWR | os.O_CREAT) -> int:
    """`os.open` of `path`, creating it 0600, then `tighten`ed.

    Parameters
    ----------
    path : Path
        The file.
    what : str
        What it is, for the warning (`tighten`).
    flags : int
        `os.open` flags.

    Returns
    -------
    int
        The file descriptor.
    """
    fd = os.open(path, flags, PRIVATE)
    try:
        tighten(path, what)
    except OSError:
        os.close(fd)
        raise
    return fd


def tighten(path: Path, what: str = "file") -> bool:
    """Make an existing `path` 0600 if the group or others have any access, warning with its old mode.

    A record, not a secret: from now on only the service's user can write it, and refusing to start
    would stop a running cell over a file mode.

    Parameters
    ----------
    path : Path
        The file; a missing one is left alone.
    what : str
        What it is, for the warning.

    Returns
    -------
    bool
        True if its mode was changed; OSError if it cannot be (the file belongs to another user).
    """
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
    """The mode of `path` if the group or others have any access to it, else None.

    A key is refused rather than tightened (dt_runtime.fabric.auth): one others could read may
    have been copied, and tightening it would hide that.

    Parameters
    ----------
    path : Path
        An existing file.

    Returns
    -------
    int or None
        Its permission bits when too open, else None.
    """
    mode = mode_of(path)
    return mode if mode & _OTHERS else None
