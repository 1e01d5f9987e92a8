"""Loading a user's NPZ file without trusting it: names, sizes and dtypes checked before reading
(`load_npz`; no pickle). See docs/cli.md ("Bounded parsing").
"""
from __future__ import annotations

import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.common.safe_files import open_regular

#: Generous for a twin's models (a GP on 20,000 training rows holds ~4 MB of arrays per axis) and
#: far below what would exhaust a cell PC's memory.
DEFAULT_MAX_BYTES = 512 * 2 ** 20
_NUMERIC = "biuf"  # bool, signed, unsigned, float
_ZIP_SLACK = 2 ** 20  # zip and .npy headers around the arrays


def load_npz(path: str | Path, expected: Iterable[str] | None = None,
             max_bytes: int = DEFAULT_MAX_BYTES) -> dict[str, np.ndarray]:
    """The arrays of an NPZ file by name, sizes and values checked before they are trusted.

    Parameters
    ----------
    path : str or Path
        The NPZ file.
    expected : iterable of str, optional
        The allowed member names (a subset may be present).
    max_bytes : int, optional
        Most bytes of arrays accepted.

    Returns
    -------
    dict of str to ndarray

    Raises
    ------
    DataError
        Naming file and member for an unexpected member, a non-numeric dtype, a total size over
        `max_bytes`, a member that is truncated or unreadable, or a NaN or infinite value; naming
        the file when it is not a regular file or larger than `max_bytes`.

    Notes
    -----
    `np.load` on an NPZ decompresses whatever member is asked for, as large as its header says: a
    small file with an extra compressed member can take gigabytes to load. This opens the archive
    with `zipfile`, refuses members that are not expected, reads each member's .npy header (shape,
    dtype) from the stream and refuses before allocating anything when the total would exceed
    `max_bytes` or a dtype is not a plain number; only then does it read the arrays. The archive
    itself must be a regular file no larger than `max_bytes` plus its headers (a member symlinked
    to /dev/zero would be read for ever), and every float array must be finite (a model holding
    inf must not load as if it were sound).
    """
    path = Path(path)
    allowed = None if expected is None else set(expected)
    out: dict[str, np.ndarray] = {}
    total = 0
    try:
        with open_regular(path, max_bytes + _ZIP_SLACK, "an NPZ archive of arrays") as f, zipfile.ZipFile(f) as zf:
            infos = zf.infolist()
            for info in infos:
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                if allowed is not None and name not in allowed:
                    raise DataError(f"{path}: unexpected member {info.filename!r} "
                                    f"(allowed: {', '.join(sorted(allowed))})")
                if info.file_size > max_bytes:
                    raise DataError(f"{path}: member {info.filename!r} declares {info.file_size} bytes, more than the "
                                    f"{max_bytes} allowed")
            for info in infos:
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                with zf.open(info) as fp:
                    version = np.lib.format.read_magic(fp)
                    shape, fortran, dtype = (np.lib.format.read_array_header_1_0(fp) if version == (1, 0)
                                             else np.lib.format.read_array_header_2_0(fp))
                    if dtype.kind not in _NUMERIC or dtype.hasobject:
                        raise DataError(f"{path}: member {info.filename!r} has dtype {dtype}, not a plain number")
                    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
                    total += nbytes
                    if total > max_bytes:
                        raise DataError(f"{path}: member {info.filename!r} holds {shape} {dtype} ({nbytes} bytes): the "
                                        f"arrays exceed the {max_bytes} bytes allowed for this file")
                    data = fp.read(nbytes + 1)
                    if len(data) != nbytes:
                        raise DataError(f"{path}: member {info.filename!r} is truncated or longer than its header "
                                        f"({len(data)} bytes for {nbytes})")
                    arr = np.frombuffer(data, dtype=dtype)
                    if dtype.kind == "f" and not np.all(np.isfinite(arr)):
                        bad = int(np.count_nonzero(~np.isfinite(arr)))
                        raise DataError(f"{path}: member {info.filename!r} holds {bad} NaN or infinite value(s) "
                                        "(a model's numbers must be finite: refit it)")
                    out[name] = arr.reshape(shape, order="F" if fortran else "C").copy()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error) as exc:  # EOF, zlib: a cut member
        raise DataError(f"{path}: not a readable NPZ file ({exc})") from exc
    return out
