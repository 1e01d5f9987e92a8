"""A user's file opened without trusting it: a regular file no larger than a cap, or DataError.

A model member that is a symlink to /dev/zero (or a FIFO, a socket) has no end: `dt run` read it
for ever (10 GB RSS in 20 s). Only regular files are read, their size checked before the first
byte, and the read itself bounded (a file may grow after the check).
"""
from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from dt_kernel.errors import DataError

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"))


def open_regular(path: str | Path, max_bytes: int, what: str) -> BinaryIO:
    """`path` opened for binary reading, if it is a regular file of at most `max_bytes`.

    Parameters
    ----------
    path : str or Path
        The file (symlinks followed).
    max_bytes : int
        Largest size accepted.
    what : str
        What the file should be, for the error.

    Returns
    -------
    BinaryIO

    Raises
    ------
    DataError
        Naming the file and `what` it should be when it cannot be opened, is not a regular file
        or holds more than `max_bytes`.
    """
    path = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer; it is refused below
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise DataError(f"{path}: cannot read {what} ({exc.strerror})") from exc
    f = os.fdopen(fd, "rb")
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        f.close()
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
        raise DataError(f"{path}: {kind}, not a regular file; {what} must be a file")
    if st.st_size > max_bytes:
        f.close()
        raise DataError(f"{path}: {st.st_size} bytes, more than the {max_bytes} allowed for {what}")
    return f


def read_regular(path: str | Path, max_bytes: int, what: str) -> bytes:
    """The bytes of `path` (`open_regular`'s checks), at most `max_bytes` of them.

    Parameters
    ----------
    path : str or Path
        The file.
    max_bytes : int
        Largest size accepted.
    what : str
        What the file should be, for the error.

    Returns
    -------
    bytes
    """
    with open_regular(path, max_bytes, what) as f:
        try:
            raw = f.read(max_bytes + 1)
        except OSError as exc:
            raise DataError(f"{path}: cannot read {what} ({exc.strerror})") from exc
    if len(raw) > max_bytes:  # it grew since the check
        raise DataError(f"{path}: more than the {max_bytes} bytes allowed for {what}")
    return raw
