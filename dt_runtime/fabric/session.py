"""The bus's one boundary with zenoh: its errors become BusError here and only here
(`zenoh_errors`), chained with `from`; session open and bounded close; JSON payloads.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import zenoh

from dt_kernel.errors import DriverError, TwinError
from dt_runtime.common.jsonsafe import dumps

if TYPE_CHECKING:
    from dt_runtime.fabric.config import BusConfig

log = logging.getLogger("dt_runtime.service.bus")  # the log channel keeps its name (filters name it)


class BusError(DriverError):
    """The Zenoh bus failed (session, declaration, put); the zenoh error is the __cause__."""


@contextmanager
def zenoh_errors(what: str) -> Iterator[None]:
    """Convert whatever zenoh raises inside the block into BusError naming `what`.

    zenoh-python raises ZError, and its Rust bindings TypeError/ValueError/RuntimeError for
    values they refuse, so everything but the project's own errors is converted.
    """
    try:
        yield
    except TwinError:
        raise
    except Exception as exc:  # noqa: BLE001 - see the docstring: zenoh has no single root
        raise BusError(f"{what}: {exc}") from exc


def open_session(cfg: BusConfig) -> zenoh.Session:
    config = cfg.zenoh_config()
    with zenoh_errors(f"cannot open zenoh session ({cfg.mode}, listen={cfg.listen}, connect={cfg.connect})"):
        return zenoh.open(config)


def close_session(session: zenoh.Session, timeout: float) -> bool:
    """Close in a helper thread so a wedged close cannot hang the daemon; True if it finished."""
    def run() -> None:
        try:
            with zenoh_errors("zenoh close failed"):
                session.close()
        except BusError as exc:  # closing is best effort
            log.warning("%s", exc)

    th = threading.Thread(target=run, name="zenoh-close", daemon=True)
    th.start()
    th.join(timeout)
    if th.is_alive():
        log.warning("zenoh session did not close within %.1f s; abandoned", timeout)
        return False
    return True


def encode(payload: Mapping[str, Any]) -> bytes:
    """One message: compact UTF-8 JSON (numpy as lists, NaN as null, other objects as text)."""
    return dumps(payload, separators=(",", ":"), default=str).encode()


def put_json(session: zenoh.Session, key: str, payload: Mapping[str, Any] | bytes) -> None:
    """A reliable, high-priority JSON put on any key (acks, requests of another robot name)."""
    data = payload if isinstance(payload, bytes) else encode(payload)
    with zenoh_errors(f"put on {key}"):
        session.put(key, data, encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_HIGH)


def shut_down(session: zenoh.Session, worker: threading.Thread, wake: Callable[[], None], timeout: float) -> bool:
    """Wake `worker` (its stop signal), join it and close `session`, all within `timeout` s; True
    when both are down."""
    deadline = time.monotonic() + timeout
    wake()
    worker.join(max(0.0, deadline - time.monotonic()))
    return close_session(session, max(0.1, deadline - time.monotonic())) and not worker.is_alive()


def serve_tasks(tasks: queue.Queue, handle: Callable[[Any], None], failed: Callable[[Any], str],
                logger: logging.Logger = log) -> None:
    """A bus worker thread's loop (zenoh's callbacks only enqueue): `handle` each task until a None
    comes; a task that raises is logged with `failed(task)` and the worker goes on (one bad
    message must not stop it)."""
    while True:
        task = tasks.get()
        if task is None:
            return
        try:
            handle(task)
        except Exception:  # noqa: BLE001 - the worker must survive any single failure
            logger.exception("%s", failed(task))
