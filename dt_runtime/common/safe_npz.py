"""Loading a user's NPZ file without trusting it: names, sizes and dtypes checked before reading.

`np.load` on an NPZ decompresses whatever member is asked for, as large as its header says: a
2.9 MB file with an extra compressed member took 2.1 GB to load. `load_npz` opens the archive
with `zipfile`, refuses members that are not expected, reads each member's .npy header (shape,
dtype) from the stream and refuses before allocating anything when the total would exceed
`max_bytes` or a dtype is not a plain number; only then does it read the arrays. No pickle.
"""
from __future__ import annotations

import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError

#: Generous for a twin's models (a GP on 20,000 training rows holds ~4 MB of arrays per axis) and
#: far below what would exhaust a cell PC's memory.
DEFAULT_MAX_BYTES = 512 * 2 ** 20
_NUMERIC = "biuf"  # bool, signed, unsigned, float


def load_npz(path: str | Path, expected: Iterable[str] | None = None,
             max_bytes: int = DEFAULT_MAX_BYTES) -> dict[str, np.ndarray]:
    """The arrays of `path` by name. DataError naming file and member for an unexpected member
    (when `expected` is given: the allowed names, a subset may be present), a non-numeric dtype,
    or a total size over `max_bytes`."""
    path = Path(path)
    allowed = None if expected is None else set(expected)
    out: dict[str, np.ndarray] = {}
    total = 0
    try:
        with zipfile.ZipFile(path) as zf:
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
                    out[name] = arr.reshape(shape, order="F" if fortran else "C").copy()
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise DataError(f"{path}: not a readable NPZ file ({exc})") from exc
    return out
