"""`dt/<cell>/<robot>/correct`: the cell's program asks the twin for a corrected command.

Request-reply over Zenoh (a queryable). The request's payload is JSON:
`{"target_mm": [x, y, z], "speed_mm_s": v, "id": any}` (robot frame, mm and mm/s), optionally
`"temperature_c"` and `"payload_kg"` (the conditions a twin whose maps hold thermal or payload
effects reads; default: the daemon's sensors); the reply is
`{"id", "target_mm", "command_mm", "correction_mm", "U_mm", "inside", "distance_mm"}`: the
corrected command, the expanded uncertainty (95 %) of the position it reaches, whether it lies in
the calibrated volume and its signed distance to it. The bounds of `twin.bounds.Guard`
around the twin's correction law apply unchanged; a refused or malformed request gets an error
reply `{"id", "error", "type"}` and the server goes on serving. Every query gets a reply, an
error reply for a defect too. A request is parsed bounded (`common.safe_json`): at most
MAX_REQUEST_BYTES (checked before the payload is copied), nested at most MAX_REQUEST_DEPTH deep,
integers of at most 20 digits, numbers finite; only the keys above; target_mm 3 numbers and
speed_mm_s a number (a boolean is not a number); temperature_c and payload_kg within the data
checks' plausible ranges (`measurements.checks.RANGES`: -50..150 deg C, 0..1000 kg); speed and
workspace by the Guard. Corrections are computed in the
zenoh callback (about a tenth of a millisecond) under a lock: the step bound of the Guard
follows the sequence of requests.
"""
from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from dt_kernel.errors import DataError, TwinError, brief, cut
from dt_kernel.units import M_PER_MM, MM_PER_M
from dt_runtime.common.safe_json import loads
from dt_runtime.fabric.config import BusConfig
from dt_runtime.fabric.session import BusError, close_session, encode, open_session, zenoh_errors
from dt_runtime.measurements.checks import RANGES
from dt_runtime.twin.bounds import Guard
from dt_runtime.twin.conditions import Conditions

log = logging.getLogger(__name__)


#: A request is about 100 bytes; 4 kB leave room for a long id (it is echoed in the reply).
MAX_REQUEST_BYTES = 4096
#: {"id": {...}, "target_mm": [...]}: three levels; a few more for an id of the caller's own.
MAX_REQUEST_DEPTH = 8
KEYS = ("id", "target_mm", "speed_mm_s", "temperature_c", "payload_kg")


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)  # JSON true is not 1


def _request(raw: bytes) -> tuple[Any, np.ndarray, float, dict[str, float]]:
    """(id, target m, speed m/s, condition overrides) of a request payload; DataError naming
    what is wrong."""
    req = loads(raw, "request", max_bytes=MAX_REQUEST_BYTES, max_depth=MAX_REQUEST_DEPTH)
    if not isinstance(req, dict):
        raise DataError("request must be a JSON object with target_mm and speed_mm_s")
    unknown = sorted(set(req) - set(KEYS))
    if unknown:
        raise DataError(f"request: unknown key(s) {brief(unknown)}; allowed: {', '.join(KEYS)}")
    rid = req.get("id")
    missing = [k for k in ("target_mm", "speed_mm_s") if k not in req]
    if missing:
        raise DataError(f"request has no {missing[0]!r} (needs target_mm [x, y, z] and speed_mm_s)")
    t, v = req["target_mm"], req["speed_mm_s"]
    if not (isinstance(t, list) and len(t) == 3 and all(_number(x) for x in t)):
        raise DataError(f"request: target_mm {brief(t)} is not a finite 3-vector: it must be 3 numbers (x, y, z in mm)")
    if not _number(v):
        raise DataError(f"request: speed_mm_s must be a number (mm/s), got {brief(v)}")
    over: dict[str, float] = {}
    for key, field in (("temperature_c", "temperature"), ("payload_kg", "payload")):
        x = req.get(key)
        if x is None:
            continue
        lo, hi, unit, _ = RANGES[field]
        if not (_number(x) and lo <= x <= hi):
            raise DataError(f"request: {key} must be a number in [{lo:g}, {hi:g}] {unit}, got {brief(x)}")
        over[field] = float(x)
    return rid, np.array(t, dtype=float) * M_PER_MM, float(v) * M_PER_MM, over


class CorrectionServer:
    """Serves `correct` requests with a Guard (give it its own Corrector: zenoh's thread shares no
    state with another), on a session of its own or one it is given (the daemon shares its Bus's
    session: one listen endpoint per process). `conditions`: the cell's latest conditions (the
    daemon's; never a driver call from zenoh's thread), which a request's temperature_c /
    payload_kg override.

    Parameters
    ----------
    corrector : Guard
        The bounded correction law (with a Corrector of its own).
    config : BusConfig
        The bus config (the key `.../correct`, the session, the close time-out).
    session : zenoh.Session, optional
        A session to serve on (left open by `close`); None opens one of its own.
    conditions : callable, optional
        The cell's latest conditions, or None.

    Raises
    ------
    BusError
        The session could not be opened or the queryable declared (a session of its own is
        closed again).
    """

    def __init__(self, corrector: Guard, config: BusConfig, session: zenoh.Session | None = None,
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
        """The reply to one request payload (an error reply for a refused or malformed one, and
        for a defect: a request is never left without a reply). Runs on zenoh's thread; the
        correction itself under a lock.

        Parameters
        ----------
        raw : bytes
            The request's JSON payload.

        Returns
        -------
        dict
            `id`, `target_mm`, `command_mm`, `correction_mm`, `U_mm`, `inside`, `distance_mm`; or
            `id`, `error`, `type` for a refused request. Never raises.
        """
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
        except TwinError as exc:  # DataError, CorrectionFault, a ModelError of the twin
            return self._refuse(rid, exc)
        except Exception as exc:  # noqa: BLE001 - a defect: logged, and still a reply
            log.exception("correct request failed")
            return self._refuse(rid, exc, internal=True)
        self.served += 1
        return {"id": rid, "target_mm": (c.target * MM_PER_M).tolist(), "command_mm": (c.command * MM_PER_M).tolist(),
                "correction_mm": (c.correction * MM_PER_M).tolist(), "U_mm": (c.U_tcp * MM_PER_M).tolist(),
                "inside": c.inside, "distance_mm": c.distance_m * MM_PER_M}

    def _refuse(self, rid: Any, exc: BaseException, internal: bool = False) -> dict[str, Any]:
        self.refused += 1
        return {"id": rid, "error": cut(f"internal error: {exc}") if internal else str(exc),
                "type": type(exc).__name__}

    def _on_query(self, query: zenoh.Query) -> None:
        # Never let an exception into zenoh's thread: a reply that cannot be sent is logged.
        try:
            payload = query.payload
            size = len(payload) if payload is not None else 0
            if size > MAX_REQUEST_BYTES:  # refused before the payload is copied out of zenoh
                reply = self._refuse(None, DataError(f"request: {size} bytes, more than the {MAX_REQUEST_BYTES} "
                                                     "allowed"))
            else:
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
        finally:
            # The requester sees the end of the replies now, not at its timeout: a logged
            # traceback (answer's defect) keeps this frame, and so the query, alive.
            drop = getattr(query, "drop", None)  # zenoh-python >= 1.0 has it; without, garbage collection
            if drop is not None:
                drop()

    def close(self, timeout: float | None = None) -> bool:
        """Undeclare the queryable and close the session if it is its own.

        Parameters
        ----------
        timeout : float, optional
            Bound of the session's close, s (the bus config's `close_timeout_s` if None).

        Returns
        -------
        bool
            True if the session closed in time (always True on a shared session).
        """
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
