"""Log lines that repeat are let through once per interval, with a count of those held back: a
failing disk made the daemon log the same store error 87 times a second.

`RepeatFilter` is installed on the `dt` entry point's one handler (`cli.main`), so every command,
the daemon above all, logs through it.
"""
from __future__ import annotations

import collections
import logging
import re
import threading
import time

_DIGITS = re.compile(r"\d+(\.\d+)?")


class RepeatFilter(logging.Filter):
    """Pass a log record unless one like it (same logger, level and message with its numbers
    masked: 't=12.5 s' and 't=12.6 s' are alike) passed less than `interval_s` ago; the next one
    like it that passes says how many were held back and over how long.

    Parameters
    ----------
    interval_s : float
        Least time between two alike records that pass.
    max_kinds : int
        Most kinds of record remembered (the oldest is forgotten first).
    """

    def __init__(self, interval_s: float = 5.0, max_kinds: int = 512):
        super().__init__()
        self.interval_s, self.max_kinds = interval_s, max_kinds
        # kind -> [time the last one passed, alike records held back since]
        self._seen: collections.OrderedDict[tuple[str, int, str], list[float]] = collections.OrderedDict()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        """True to let `record` through (its message then counts those held back), False to hold it.

        Parameters
        ----------
        record : logging.LogRecord

        Returns
        -------
        bool
        """
        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 - a bad format is logging's to report, not ours to hide
            return True
        kind = (record.name, record.levelno, _DIGITS.sub("#", text))
        now = time.monotonic()
        with self._lock:
            seen = self._seen.get(kind)
            if seen is not None and now - seen[0] < self.interval_s:
                seen[1] += 1
                return False
            held = int(seen[1]) if seen is not None else 0
            since = now - seen[0] if seen is not None else 0.0
            self._seen[kind] = [now, 0]
            self._seen.move_to_end(kind)
            while len(self._seen) > self.max_kinds:
                self._seen.popitem(last=False)
        if held:
            record.msg, record.args = f"{text} [{held} more like it in the last {since:.0f} s not shown]", None
            fields = getattr(record, "fields", None)
            record.fields = {**(fields or {}), "repeated": held}
        return True
