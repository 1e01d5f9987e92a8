"""The project's one exception hierarchy.

Every layer raises these (the kernel imports nothing of the project); `dt_runtime` exports them
for users. Lower-level errors (serial, socket, zenoh, sqlite, numpy) are converted at the boundary
with `raise ... from exc`.
"""
from __future__ import annotations

import os
import reprlib
from typing import Any

#: The longest message a user is shown (about a screen): a message quoting what it refuses (a
#: config value, a request, a header) must not become the 312 MB that an alias bomb's value was.
MAX_MESSAGE_CHARS = 2000

class _Brief(reprlib.Repr):
    """The quoted value of a message: nested containers and long strings abbreviated with "...",
    built without ever making the whole repr (reprlib stops at its limits), and an integer too
    long to print (Python refuses over 4300 digits) by its size."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 2, 6, 6, 6
        self.maxset = self.maxfrozenset = self.maxdeque = self.maxarray = 6
        self.maxstring, self.maxlong, self.maxother = 200, 40, 200

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:
            return f"<an integer of {int(x.bit_length() * 0.30103) + 1} digits>"
        return super().repr_int(x, level)


_brief = _Brief()


def brief(value: Any) -> str:
    """repr(value) for a message, bounded in length whatever the value holds.

    Parameters
    ----------
    value : Any
        The value to show.

    Returns
    -------
    str
    """
    return _brief.repr(value)


def cut(message: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """`message` at most `limit` characters: the head, and how much was left out.

    Parameters
    ----------
    message : str
        The text.
    limit : int, optional
        Most characters kept.

    Returns
    -------
    str
    """
    if len(message) <= limit:
        return message
    return f"{message[:limit]} ... [{len(message) - limit} more characters not shown]"


class TwinError(Exception):
    """Root of every error this project raises on purpose. Its text (what `dt` prints, an
    error reply on the bus, a log line) is cut to MAX_MESSAGE_CHARS: this is the one place
    where the length of an error message shown to a user is bounded."""

    def __str__(self) -> str:
        return cut(super().__str__())


class ConfigError(TwinError):
    """A config, scenario or plan is malformed; names file, key, value and what is allowed."""

    def __init__(self, file: str | os.PathLike[str], key: str, value: Any, allowed: str):
        self.file, self.key, self.value, self.allowed = str(file), key, value, allowed
        super().__init__(f"{file}: key '{key}': value {brief(value)} is not allowed; {allowed}")


class DataError(TwinError):
    """A measurement file or row is unusable; names file, line, column and value."""


class StateError(TwinError):
    """A driver or component was called in the wrong lifecycle state."""


class DriverError(TwinError):
    """A device (real or simulated) failed; lower-level errors are chained with `from`."""


class UnreachableError(TwinError):
    """A target lies outside the robot's reach or joint limits."""


class ModelError(TwinError):
    """An error model cannot be fitted, loaded or evaluated."""


class StoreError(TwinError):
    """The store could not read or write (disk full, I/O error, corrupt or locked file)."""


class CorrectionFault(TwinError):
    """The correction asked for is out of bounds, or an input is invalid; nothing was moved."""
