"""Progress shown on stderr while long work runs (stdout stays clean for --json)."""
from __future__ import annotations

import sys
import time


class Progress:
    """Progress lines on a stream (stderr by default), at most two a second.

    Parameters
    ----------
    enabled : bool, optional
        False writes nothing (``--no-progress``).
    stream : file-like, optional
        Where to write; ``sys.stderr`` when None.
    """
    def __init__(self, enabled: bool = True, stream=None):
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._t0 = time.monotonic()
        self._last = 0.0

    def step(self, label: str, i: int, n: int) -> None:
        """Report item `i` (0-based) of `n`; the last item always ends the line.

        Parameters
        ----------
        label : str
            What is being done.
        i : int
            Index of the item just done.
        n : int
            Number of items.
        """
        if not self.enabled:
            return
        now = time.monotonic()
        if i + 1 < n and now - self._last < 0.5:
            return
        self._last = now
        pct = 100.0 * (i + 1) / max(n, 1)
        end = "\n" if i + 1 >= n else "\r"
        self.stream.write(f"[{now - self._t0:6.1f} s] {label}: {i + 1}/{n} ({pct:5.1f} %){end}")
        self.stream.flush()

    def note(self, text: str) -> None:
        """Write one line of text, with the elapsed time.

        Parameters
        ----------
        text : str
            The line.
        """
        if self.enabled:
            self.stream.write(f"[{time.monotonic() - self._t0:6.1f} s] {text}\n")
            self.stream.flush()
