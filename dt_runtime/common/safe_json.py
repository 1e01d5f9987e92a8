"""JSON from a file or a message without trusting it: the one reader of model and twin files
(hybrid.json, gp.json, twin.json) and of request payloads on the bus.

Size, encoding, integer length, nesting and finite numbers are checked (`loads`, `read_json`);
every refusal is a DataError naming the source and, for a value, its key path. See docs/cli.md
("Bounded parsing").
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from dt_kernel.errors import DataError
from dt_runtime.common.safe_files import read_regular

#: Model and twin metadata are kilobytes (a hybrid model's hybrid.json with its identifiability
#: analysis: ~100 kB); the arrays are in the NPZ.
MAX_FILE_BYTES = 16 * 2 ** 20
#: Twin files nest about 6 levels (provenance -> inputs -> file -> ...).
MAX_DEPTH = 32
#: An integer in these files is a count, an index or a seed: 64 bits are 20 digits.
MAX_INT_DIGITS = 20


class _HugeInt(Exception):
    def __init__(self, digits: int):
        super().__init__(digits)
        self.digits = digits


def _int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise _HugeInt(digits)  # before int(): Python refuses 4,300 digits with a bare ValueError
    return int(text)


def loads(raw: bytes | str, where: str, *, max_bytes: int, max_depth: int = MAX_DEPTH,
          infinite_ok: tuple[str, ...] = ()) -> Any:
    """The JSON value of `raw`, bounded and checked.

    Parameters
    ----------
    raw : bytes or str
        The JSON text.
    where : str
        What the error names (a file).
    max_bytes : int
        Most bytes accepted.
    max_depth : int, optional
        Deepest nesting accepted.
    infinite_ok : tuple of str, optional
        +infinity is allowed under a key whose name ends with one of these.

    Returns
    -------
    Any

    Raises
    ------
    DataError
        Naming `where` for more than `max_bytes`, text that is not UTF-8 or not JSON, an integer of
        more than MAX_INT_DIGITS digits, nesting deeper than `max_depth`, or a NaN or infinite
        number.

    Notes
    -----
    `json.loads` takes anything: deep nesting ends in RecursionError (a traceback), a
    thousands-digit integer in a ValueError that is not a JSONDecodeError, NaN and Infinity are
    accepted, and the size is whatever was sent. Here the size is checked before parsing, the text
    must be UTF-8, integers have at most MAX_INT_DIGITS digits, nesting is at most `max_depth`
    deep, and every number is finite, except infinity where the caller allows it by key (degrees
    of freedom: GUM's infinite dof).
    """
    if len(raw) > max_bytes:
        raise DataError(f"{where}: {len(raw)} bytes, more than the {max_bytes} allowed")
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
    except UnicodeDecodeError as exc:
        raise DataError(f"{where}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from exc
    try:
        value = json.loads(text, parse_int=_int)
    except _HugeInt as exc:
        raise DataError(f"{where}: an integer of {exc.digits} digits (at most {MAX_INT_DIGITS})") from None
    except RecursionError:  # the C scanner's guard, at about a thousand levels
        raise DataError(f"{where}: nested deeper than {max_depth} levels") from None
    except ValueError as exc:  # JSONDecodeError, and any value the decoder refuses
        raise DataError(f"{where}: not JSON ({exc})") from exc
    _check(value, where, max_depth, infinite_ok)
    return value


def _check(value: Any, where: str, max_depth: int, infinite_ok: tuple[str, ...]) -> None:
    """Depth and finite numbers, walked without recursion; the first offence with its key path."""
    stack: list[tuple[Any, int, tuple[str, ...]]] = [(value, 0, ())]
    while stack:
        v, depth, path = stack.pop()
        if isinstance(v, (dict, list)):
            if depth >= max_depth:
                raise DataError(f"{where}: nested deeper than {max_depth} levels (at {'.'.join(path) or 'the top'})")
            items = v.items() if isinstance(v, dict) else enumerate(v)
            stack.extend((child, depth + 1, (*path, str(k))) for k, child in items)
        elif isinstance(v, float) and not math.isfinite(v):
            key = next((p for p in reversed(path) if not p.isdigit()), "")
            if not (v > 0 and key.endswith(infinite_ok)):  # NaN and -inf never
                raise DataError(f"{where}: {'.'.join(path) or 'the value'} is {v} (numbers must be finite)")


def read_json(path: str | Path, what: str, *, max_bytes: int = MAX_FILE_BYTES, max_depth: int = MAX_DEPTH,
              infinite_ok: tuple[str, ...] = ()) -> Any:
    """The JSON value of a regular file, with `loads`' checks.

    The file is read by `safe_files.read_regular` (not a device or a FIFO, size checked before
    reading).

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file should be, for the error.
    max_bytes : int, optional
        Most bytes accepted.
    max_depth : int, optional
        Deepest nesting accepted.
    infinite_ok : tuple of str, optional
        As for `loads`.

    Returns
    -------
    Any

    Raises
    ------
    DataError
        Naming the file.
    """
    return loads(read_regular(path, max_bytes, what), str(path), max_bytes=max_bytes, max_depth=max_depth,
                 infinite_ok=infinite_ok)
