"""`dt/<cell>/<robot>/correct`: the cell's program asks the twin for a corrected command.

Request-reply over Zenoh (a queryable). The request's payload is JSON:
`{"target_mm": [x, y, z], "speed_mm_s": v, "id": any}` (robot frame, mm and mm/s), optionally
`"temperature_c"` and `"payload_kg"` (the conditions a twin whose maps hold thermal or payload
effects reads; default: the daemon's sensors); the reply is
`{"id", "target_mm", "command_mm", "correction_mm", "U_mm", "inside", "distance_mm"}`: the
corrected command, the expanded uncertainty (95 %) of the position it reaches, whether it lies in
the calibrated volume and its signed distance to it. The bounded-correction rules of
`service.correction.Corrector` apply unchanged; a refused or malformed request gets an error
reply `{"id", "error", "type"}` and the server goes on serving. Corrections are computed in the
zenoh callback (about a tenth of a millisecond) under a lock: the step bound of the Corrector
follows the sequence of requests.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from dt_kernel.errors import DataError, TwinError
from dt_kernel.units import M_PER_MM, MM_PER_M
from dt_runtime.service.bus.config import BusConfig
from dt_runtime.service.bus.session import BusError, close_session, encode, open_session, zenoh_errors
from dt_runtime.service.correction import CorrectionFault, Corrector
from dt_runtime.twin.conditions import Conditions

log = logging.getLogger(__name__)


def _request(raw: bytes) -> tuple[Any, np.ndarray, float, dict[str, float]]:
    """(id, target m, speed m/s, condition overrides) of a request payload; DataError naming
    what is wrong."""
    try:
        req = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"request is not JSON ({exc})") from exc
    if not isinstance(req, dict):
        raise DataError("request must be a JSON object with target_mm and speed_mm_s")
    rid = req.get("id")
    try:
        target = np.asarray(req["target_mm"], dtype=float) * M_PER_MM
        speed = float(req["speed_mm_s"]) * M_PER_MM
    except KeyError as exc:
        raise DataError(f"request has no {exc.args[0]!r} (needs target_mm [x, y, z] and speed_mm_s)") from exc
    except (TypeError, ValueError) as exc:
        raise DataError(f"request: target_mm must be 3 numbers and speed_mm_s a number ({exc})") from exc
    if target.shape != (3,):
        raise DataError(f"request: target_mm must be 3 numbers, got {req['target_mm']!r}")
    over: dict[str, float] = {}
    for key, field in (("temperature_c", "temperature"), ("payload_kg", "payload")):
        if req.get(key) is not None:
            v = req[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise DataError(f"request: {key} must be a finite number, got {v!r}")
            if field == "payload" and v < 0:
                raise DataError(f"request: payload_kg must be >= 0, got {v!r}")
            over[field] = float(v)
    return rid, target, speed, over


class CorrectionServer:
    """Serves `correct` requests with a Corrector, on a session of its own or one it is given
    (the daemon shares its Bus's session: one listen endpoint per process). `conditions`: the
    cell's latest conditions (the daemon's; never a driver call from zenoh's thread), which a
    request's temperature_c / payload_kg override."""

    def __init__(self, corrector: Corrector, config: BusConfig, session: zenoh.Session | None = None,
                 conditions: Callable[[], Conditions | None] | None = None):
        self.corrector, self.config = corrector, config
        self._conditions = conditions
        self.key = config.key("correct")
        self._own = session is None
        self._session = session if session is not None else open_session(config)
        self._lock = threading.Lock()
        self.served = self.refused = 0
        try:
            with zenoh_errors(f"declare queryable {self.key}"):
                self._queryable = self._session.declare_queryable(self.key, self._on_query)
        except BusError:
            if self._own:
                close_session(self._session, config.close_timeout_s)
            raise

    def answer(self, raw: bytes) -> dict[str, Any]:
        """The reply to one request payload (an error reply for a refused or malformed one)."""
        rid = None
        try:
            rid, target, speed, over = _request(raw)
            cond = self._conditions() if self._conditions is not None else None
            if over:
                base = cond or Conditions()
                cond = dataclasses.replace(base, temperature=over.get("temperature", base.temperature),
                                           payload=over.get("payload", base.payload))
            with self._lock:
                c = self.corrector(target, speed, cond)
        except (DataError, CorrectionFault) as exc:
            self.refused += 1
            return {"id": rid, "error": str(exc), "type": type(exc).__name__}
        self.served += 1
        return {"id": rid, "target_mm": (c.target * MM_PER_M).tolist(), "command_mm": (c.command * MM_PER_M).tolist(),
                "correction_mm": (c.correction * MM_PER_M).tolist(), "U_mm": (c.U_tcp * MM_PER_M).tolist(),
                "inside": c.inside, "distance_mm": c.distance_m * MM_PER_M}

    def _on_query(self, query: zenoh.Query) -> None:
        # Never let an exception into zenoh's thread: a reply that cannot be sent is logged.
        try:
            payload = query.payload
            reply = self.answer(payload.to_bytes() if payload is not None else b"")
            with zenoh_errors(f"reply on {self.key}"):
                if "error" in reply:
                    query.reply_err(encode(reply))
                else:
                    query.reply(self.key, encode(reply))
        except TwinError as exc:
            log.warning("correct request not answered: %s", exc)
        except Exception:  # noqa: BLE001 - a defect must not kill the queryable
            log.exception("correct request failed")

    def close(self, timeout: float | None = None) -> bool:
        timeout = self.config.close_timeout_s if timeout is None else timeout
        try:
            with zenoh_errors(f"undeclare {self.key}"):
                self._queryable.undeclare()
        except BusError as exc:
            log.warning("%s", exc)
        return close_session(self._session, timeout) if self._own else True

    def __enter__(self) -> CorrectionServer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def request_correction(session: zenoh.Session, key: str, target_mm, speed_mm_s: float,
                       timeout_s: float = 2.0, request_id: Any = None, temperature_c: float | None = None,
                       payload_kg: float | None = None) -> dict[str, Any]:
    """Ask the twin on `key` (`BusConfig.key("correct")`) for a corrected command; the reply as a
    dict. A refused request raises CorrectionFault with the twin's reason; no reply within
    timeout_s raises BusError."""
    req: dict[str, Any] = {"id": request_id, "target_mm": [float(x) for x in target_mm],
                           "speed_mm_s": float(speed_mm_s)}
    if temperature_c is not None:
        req["temperature_c"] = float(temperature_c)
    if payload_kg is not None:
        req["payload_kg"] = float(payload_kg)
    payload = encode(req)
    with zenoh_errors(f"get {key}"):
        replies = list(session.get(key, payload=payload, timeout=timeout_s))
    if not replies:
        raise BusError(f"{key}: no reply within {timeout_s} s (is the twin daemon serving it?)")
    r = replies[0]
    if r.ok is not None:
        return json.loads(r.ok.payload.to_bytes())
    err = json.loads(r.err.payload.to_bytes()) if r.err is not None else {"error": "empty error reply"}
    raise CorrectionFault(f"{key}: {err.get('error')}")
