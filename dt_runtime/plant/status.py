"""One question to the whole plant: a single get on `<selector>/<kind>` through the fabric.

`collect(session, "dt/*/*", "status", expected=["c1/r1", ...])` sends ONE query (target ALL: every
matching queryable answers, not only the nearest), gathers every cell's reply until each has
answered or `timeout_s` passes, and names the expected cells that did not answer. A reply is a
cell's answer (service.answers) or an error reply; either way the cell answered.
"""
from __future__ import annotations

import json
import time
from collections.abc import Sequence
from typing import Any

import zenoh

from dt_kernel.errors import DataError
from dt_runtime.fabric.config import MAX_MESSAGE_BYTES, keyexpr_ok
from dt_runtime.fabric.queries import KINDS
from dt_runtime.fabric.session import zenoh_errors


def query_key(selector: str, kind: str) -> str:
    """The key of one query: ``dt/*/*`` + ``status`` -> ``dt/*/*/status``.

    A selector that already ends in a kind is taken as it is.

    Parameters
    ----------
    selector : str
        A key expression of cells (``dt/<cell>/<robot>``, wildcards allowed).
    kind : str
        One of fabric.queries.KINDS.

    Returns
    -------
    str

    Raises
    ------
    DataError
        For an unknown kind or a key expression zenoh refuses.
    """
    if kind not in KINDS:
        raise DataError(f"unknown kind {kind!r}; a cell answers {', '.join(KINDS)}")
    key = selector.rstrip("/")
    if key.rsplit("/", 1)[-1] not in KINDS:
        key = f"{key}/{kind}"
    try:
        return keyexpr_ok(key)
    except ValueError as exc:
        raise DataError(f"selector {selector!r}: {exc}") from exc


def collect(session: zenoh.Session, selector: str = "dt/*/*", kind: str = "status", *,
            expected: Sequence[str] = (), timeout_s: float = 3.0) -> dict[str, Any]:
    """Every cell's answer to one query (target ALL: every matching queryable answers).

    Gathers the replies until each has answered or ``timeout_s`` passes; a reply is a cell's answer
    or an error reply, either way the cell answered.

    Parameters
    ----------
    session : zenoh.Session
    selector : str
        A key expression of cells.
    kind : str
        What to ask (fabric.queries.KINDS).
    expected : sequence of str
        ``cell/robot`` names expected to answer.
    timeout_s : float
        s.

    Returns
    -------
    dict
        ``key``, ``kind``, ``cells`` (one object per answer: ``cell``, ``robot``, ``kind``, the
        answer's keys, ``latency_ms``), ``answered`` (``cell/robot`` names), ``expected`` (those of
        ``expected`` the selector covers), ``missing`` (expected, no answer), ``errors``,
        ``elapsed_ms``.

    Raises
    ------
    DataError
        For a bad selector or kind.
    BusError
        When the query fails.
    """
    key = query_key(selector, kind)
    t0 = time.monotonic()
    cells: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    with zenoh_errors(f"get {key}"):
        replies = session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                              timeout=timeout_s)
        for r in replies:
            ms = round((time.monotonic() - t0) * 1e3, 3)
            sample = r.ok if r.ok is not None else r.err
            raw = sample.payload.to_bytes() if sample is not None else b""
            try:
                body = json.loads(raw[:MAX_MESSAGE_BYTES]) if len(raw) <= MAX_MESSAGE_BYTES else None
            except ValueError:
                body = None
            if not isinstance(body, dict):
                errors.append({"key": str(getattr(sample, "key_expr", key)), "error": "malformed reply"})
                continue
            body.pop("sig", None)
            (cells if r.ok is not None or "cell" in body else errors).append(body | {"latency_ms": ms})
    answered = sorted({f"{c.get('cell')}/{c.get('robot')}" for c in cells})
    asked = zenoh.KeyExpr(key)
    expected = [c for c in expected if asked.intersects(zenoh.KeyExpr(f"dt/{c}/{key.rsplit('/', 1)[-1]}"))]
    missing = [c for c in expected if c not in answered]
    cells.sort(key=lambda c: (str(c.get("cell")), str(c.get("robot")), str(c.get("kind"))))
    return {"key": key, "kind": kind, "cells": cells, "answered": answered, "expected": list(expected),
            "missing": missing, "errors": errors, "elapsed_ms": round((time.monotonic() - t0) * 1e3, 3)}


def plant_status(cfg, selector: str = "dt/*/*", kind: str = "status", timeout_s: float = 3.0) -> dict[str, Any]:
    """``collect`` on a session of the plant config's bus (opened and closed here), expecting its cells.

    Parameters
    ----------
    cfg : PlantConfig
    selector : str
    kind : str
    timeout_s : float
        s.

    Returns
    -------
    dict
        As ``collect``.

    Raises
    ------
    DataError, BusError
        As ``collect``, or when the session cannot open.
    """
    from dt_runtime.fabric.session import close_session, open_session

    session = open_session(cfg.bus)
    try:
        return collect(session, selector, kind, expected=cfg.cells, timeout_s=timeout_s)
    finally:
        close_session(session, cfg.bus.close_timeout_s)
