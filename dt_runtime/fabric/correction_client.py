"""The client side of `dt/<cell>/<robot>/correct`: a cell's program asks the twin daemon for a
corrected command over the bus (docs/bus.md). It loads no twin: the daemon corrects.
"""
from __future__ import annotations

import json
from typing import Any

import zenoh

from dt_kernel.errors import CorrectionFault
from dt_runtime.fabric.session import BusError, encode, zenoh_errors


def request_correction(session: zenoh.Session, key: str, target_mm, speed_mm_s: float,
                       timeout_s: float = 2.0, request_id: Any = None, temperature_c: float | None = None,
                       payload_kg: float | None = None) -> dict[str, Any]:
    """Ask the twin daemon for a corrected command.

    Parameters
    ----------
    session : zenoh.Session
        An open session on the cell's bus.
    key : str
        The service's key, `BusConfig.key("correct")`.
    target_mm : sequence of float
        (3,) mm, robot frame.
    speed_mm_s : float
        mm/s.
    timeout_s : float
        How long to wait for the reply, s.
    request_id : any
        Echoed in the reply.
    temperature_c, payload_kg : float or None
        Conditions for a twin whose maps read them (default: the daemon's sensors).

    Returns
    -------
    dict
        The reply (docs/bus.md): `command_mm`, `correction_mm`, `U_mm`, `inside`, `distance_mm`...

    Raises
    ------
    CorrectionFault
        The twin refused the request (its reason).
    BusError
        No reply within timeout_s.
    """
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
