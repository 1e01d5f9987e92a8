"""The compiled hot path's switch: numba's `njit` when numba is installed and not turned off
($DT_NO_JIT set to anything but "" or "0"), else a no-op decorator, so that every kernel is also
plain Python and the callers keep their numpy path (`enabled()` False).

Why numba: the correction law and the IK run per set-point on arrays of 3-200 numbers, where
numpy's per-call overhead (~1 us a call, tens of calls) is the cost, not the arithmetic; a compiled
kernel runs the whole fixed point in one call (docs/streaming.md, "Compiled kernels").
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import Any

log = logging.getLogger("dt.jit")
ENV = "DT_NO_JIT"

_njit: Any = None
try:
    if os.environ.get(ENV, "") not in ("", "0"):
        raise ImportError(f"{ENV} is set")
    from numba import njit as _njit

    _HAVE = True
except Exception:  # noqa: BLE001 - numba missing or broken: the numpy path runs
    _HAVE = False
_failed: list[str] = []


def enabled() -> bool:
    """Whether the compiled kernels run (numba imported, not turned off, none failed).

    Returns
    -------
    bool
    """
    return _HAVE and not _failed


def disable(why: str) -> None:
    """Turn the compiled kernels off for this process (a kernel failed to compile or run): the
    callers' numpy path runs from now on; logged once.

    Parameters
    ----------
    why : str
        What failed.
    """
    if not _failed:
        log.warning("compiled kernels off, the numpy path runs: %s", why)
    _failed.append(why)


def kernel(f: Callable[..., Any]) -> Callable[..., Any]:
    """`numba.njit(cache=True)` when numba is there, else `f` itself. The GIL is kept: a kernel
    runs 5-50 us on the loop's thread, and handing the GIL to another thread (a driver's reader)
    mid-correction would make the loop wait for it back.

    Parameters
    ----------
    f : callable
        The kernel, written in the subset numba compiles (it also runs as plain Python).

    Returns
    -------
    callable
    """
    if not _HAVE or _njit is None:
        return f
    return _njit(cache=True)(f)
