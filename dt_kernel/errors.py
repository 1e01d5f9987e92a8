"""The project's one exception hierarchy.

Every layer raises these (the kernel imports nothing of the project); `dt_runtime` exports them
for users. Lower-level errors (serial, socket, zenoh, sqlite, numpy) are converted at the boundary
with `raise ... from exc`.
"""
from __future__ import annotations

import os
from typing import Any


class TwinError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(TwinError):
    """A config, scenario or plan is malformed; names file, key, value and what is allowed."""

    def __init__(self, file: str | os.PathLike[str], key: str, value: Any, allowed: str):
        self.file, self.key, self.value, self.allowed = str(file), key, value, allowed
        super().__init__(f"{file}: key '{key}': value {value!r} is not allowed; {allowed}")


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
