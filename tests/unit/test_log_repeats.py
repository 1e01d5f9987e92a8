"""Repeated log lines pass once per interval with a count of those held back (a full disk logged
the same store error 87 times a second); the `dt` entry point's handler carries the filter."""
from __future__ import annotations

import logging

from dt_runtime.common.logs import RepeatFilter


def _record(msg: str, *args, level: int = logging.ERROR, name: str = "dt.run") -> logging.LogRecord:
    return logging.LogRecord(name, level, __file__, 1, msg, args, None)


def test_alike_lines_pass_once_per_interval_and_the_next_counts_the_rest(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr("dt_runtime.common.logs.time.monotonic", lambda: clock[0])
    f = RepeatFilter(interval_s=5.0)
    passed = []
    for i in range(87):  # a second of a full disk
        clock[0] = 100.0 + i / 87
        r = _record("store write failed, will retry: %s (row %d)", "database or disk is full", i)
        if f.filter(r):
            passed.append(r.getMessage())
    assert passed == ["store write failed, will retry: database or disk is full (row 0)"]
    clock[0] = 106.0
    r = _record("store write failed, will retry: %s (row %d)", "database or disk is full", 87)
    assert f.filter(r)
    assert r.getMessage().endswith("(row 87) [86 more like it in the last 6 s not shown]")
    assert r.fields == {"repeated": 86}


def test_other_lines_levels_and_loggers_are_not_held():
    f = RepeatFilter(interval_s=5.0)
    assert f.filter(_record("store write failed"))
    assert f.filter(_record("store write failed", level=logging.WARNING))
    assert f.filter(_record("store write failed", name="dt.bus"))
    assert f.filter(_record("escalation nominal -> suspect"))
    assert not f.filter(_record("store write failed"))


def test_the_dt_handler_holds_repeats(monkeypatch, capsys):
    from dt_runtime.cli import main as cli_main

    handlers = []
    monkeypatch.setattr(cli_main.logging, "basicConfig", lambda **kw: handlers.extend(kw["handlers"]))
    assert cli_main.main(["robots"]) == 0  # sets up the handler as every command does
    assert handlers and any(isinstance(x, RepeatFilter) for x in handlers[0].filters)
