"""The bus's one boundary with zenoh: its errors become BusError here and only here
(`zenoh_errors`), chained with `from`; session open and bounded close; JSON payloads.
`SessionOpener` opens a client's session in the background while its router is not up yet
(`state`: connecting, then connected; docs/bus.md).
"""
from __future__ import annotations

import json
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

    Parameters
    ----------
    what : str
        What was being done, the start of the BusError's message.

    Raises
    ------
    BusError
        `what: <the error>`, with the original as `__cause__`; a TwinError (the project's own)
        passes unchanged.
    """
    try:
        yield
    except TwinError:
        raise
    except Exception as exc:  # noqa: BLE001 - see the docstring: zenoh has no single root
        raise BusError(f"{what}: {exc}") from exc


def open_session(cfg: BusConfig) -> zenoh.Session:
    """Open the zenoh session of `cfg` now (a client whose router is down fails: `SessionOpener`).

    Parameters
    ----------
    cfg : BusConfig
        The node's bus config (mode, endpoints, TLS, access control).

    Returns
    -------
    zenoh.Session
        Open; the caller closes it (`close_session`).

    Raises
    ------
    BusError
        Zenoh rejects the config or cannot open the session (naming mode and endpoints).
    """
    config = cfg.zenoh_config()
    with zenoh_errors(f"cannot open zenoh session ({cfg.mode}, listen={cfg.listen}, connect={cfg.connect})"):
        return zenoh.open(config)


#: Waits between a client's attempts to reach its router: doubling from the first to the last.
RETRY_FIRST_S, RETRY_MAX_S = 0.25, 2.0


class SessionOpener:
    """A bus config's zenoh session, open now or as soon as it can be.

    The first attempt is made in the constructor: a session that opens is `connected` at once
    (the caller's hooks run before the constructor returns, as with `open_session`). A client
    whose routers are all down cannot open (zenoh refuses a client session with no router): it
    is `connecting` and a background thread retries, waiting `RETRY_FIRST_S` doubling to
    `RETRY_MAX_S` between attempts, until it opens (then `on_connected(session)` runs in that
    thread) or `close()`. A peer whose session cannot open raises BusError, as `open_session`.

    Once open, zenoh itself reconnects a client to its router; `state` says `connecting` while a
    client session has no router (the router restarting) and `connected` when it has one again.
    `attempts` counts the attempts to open, `last_error` holds the last one's failure.

    Parameters
    ----------
    cfg : BusConfig
        The node's bus config (mode, endpoints, TLS, access control).
    on_connected : callable, optional
        Called once with the open session (the declarations of its user); if it raises, the
        session is closed and the error raised (first attempt) or logged and retried (background).
    """

    def __init__(self, cfg: BusConfig, on_connected: Callable[[zenoh.Session], None] | None = None):
        self.cfg = cfg
        self._on_connected = on_connected
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._opened = threading.Event()
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None
        self.attempts = 1
        self.last_error: str | None = None
        try:
            session = open_session(cfg)
        except BusError as exc:
            if cfg.mode != "client":
                raise
            self.last_error = str(exc)
            log.warning("bus: no router reachable at %s yet; connecting in the background (%s)", cfg.connect, exc)
            self._thread = threading.Thread(target=self._retry, name=f"bus-connect-{cfg.robot}", daemon=True)
            self._thread.start()
            return
        try:
            self._connected(session)
        except BaseException:
            close_session(session, cfg.close_timeout_s)
            raise

    @property
    def state(self) -> str:
        """`connecting` (no session yet, or a client session without a router), `connected`, or
        `closed`."""
        if self._stop.is_set():
            return "closed"
        session = self._session
        if session is None:
            return "connecting"
        if self.cfg.mode == "client":
            try:
                with zenoh_errors("session info"):
                    if not any(True for _ in session.info.routers_zid()):
                        return "connecting"
            except BusError:
                return "connecting"
        return "connected"

    @property
    def session(self) -> zenoh.Session | None:
        """The open session, or None while connecting (or once closed)."""
        return self._session

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the session is open; True if it is.

        Parameters
        ----------
        timeout : float or None
            s; None waits until it opens.

        Returns
        -------
        bool
            True once the session has opened (also if it has been closed since), False on time-out.
        """
        return self._opened.wait(timeout)

    def _connected(self, session: zenoh.Session) -> None:
        if self._on_connected is not None:
            self._on_connected(session)
        with self._lock:
            self._session = session
        self._opened.set()

    def _retry(self) -> None:
        wait = RETRY_FIRST_S
        while not self._stop.wait(wait):
            wait = min(2 * wait, RETRY_MAX_S)
            self.attempts += 1
            try:
                session = open_session(self.cfg)
            except BusError as exc:
                self.last_error = str(exc)
                log.debug("bus: attempt %d: %s", self.attempts, exc)
                continue
            if self._stop.is_set():  # closed while this attempt was under way
                close_session(session, self.cfg.close_timeout_s)
                return
            try:
                self._connected(session)
            except Exception as exc:  # noqa: BLE001 - a failed declaration: log it, close, try again
                log.exception("bus: the session opened but could not be set up; retrying")
                self.last_error = str(exc)
                close_session(session, self.cfg.close_timeout_s)
                continue
            log.warning("bus: connected to %s after %d attempt(s)", self.cfg.connect, self.attempts)
            return

    def close(self, timeout: float | None = None) -> bool:
        """Stop connecting and close the session, within `timeout` s (the config's close
        time-out by default); True if all is down.

        Parameters
        ----------
        timeout : float or None
            s, for both the background attempts and the close; None: `cfg.close_timeout_s`.

        Returns
        -------
        bool
            True if the background attempts ended and the session (if any) closed in time.
        """
        timeout = self.cfg.close_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        done = self.cancel(timeout)
        with self._lock:
            session, self._session = self._session, None
        if session is not None:
            done = close_session(session, max(0.1, deadline - time.monotonic())) and done
        return done

    def cancel(self, timeout: float) -> bool:
        """Stop connecting (a session already open stays open until `close`); True if the
        background attempts have ended within `timeout` s.

        Parameters
        ----------
        timeout : float
            s to wait for the background thread, if there is one.

        Returns
        -------
        bool
            True if no background attempt is under way any more.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        return self._thread is None or not self._thread.is_alive()


def close_session(session: zenoh.Session, timeout: float) -> bool:
    """Close in a helper thread so a wedged close cannot hang the daemon; True if it finished.

    A failing close is logged, not raised (closing is best effort); a close still running after
    `timeout` is abandoned (the helper is a daemon thread) with a warning.

    Parameters
    ----------
    session : zenoh.Session
        The session to close.
    timeout : float
        s to wait for the close.

    Returns
    -------
    bool
        True if the close finished within `timeout`.
    """
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
    """One message: compact UTF-8 JSON (numpy as lists, NaN as null, other objects as text).

    Parameters
    ----------
    payload : mapping of str to any
        The message.

    Returns
    -------
    bytes
        UTF-8 JSON without spaces.
    """
    try:  # plain str keys, lists and finite floats (a tick's telemetry): json alone, the same text
        return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
    except (TypeError, ValueError):  # numpy, NaN, objects: made strict JSON first
        return dumps(payload, separators=(",", ":"), default=str).encode()


def put_json(session: zenoh.Session, key: str, payload: Mapping[str, Any] | bytes) -> None:
    """A reliable, high-priority JSON put on any key (acks, requests of another robot name).

    Congestion control BLOCK, priority INTERACTIVE_HIGH, encoding application/json: the put may
    block while the network is congested, so a control loop does not call it.

    Parameters
    ----------
    session : zenoh.Session
        An open session.
    key : str
        The key expression put on.
    payload : mapping or bytes
        The message; a mapping is `encode`d, bytes (e.g. `Signer.sign`'s) are sent as they are.

    Raises
    ------
    BusError
        Zenoh refuses the put.
    """
    data = payload if isinstance(payload, bytes) else encode(payload)
    with zenoh_errors(f"put on {key}"):
        session.put(key, data, encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_HIGH)


def shut_down(session: zenoh.Session, worker: threading.Thread, wake: Callable[[], None], timeout: float) -> bool:
    """Wake `worker` (its stop signal), join it and close `session`, all within `timeout` s; True
    when both are down.

    Parameters
    ----------
    session : zenoh.Session
        The session to close once the worker has stopped (or its share of `timeout` has passed).
    worker : threading.Thread
        The bus worker thread.
    wake : callable
        Tells the worker to stop, e.g. puts None on its queue.
    timeout : float
        s for the whole (the close gets at least 0.1 s).

    Returns
    -------
    bool
        True if the worker ended and the session closed in time.
    """
    deadline = time.monotonic() + timeout
    wake()
    worker.join(max(0.0, deadline - time.monotonic()))
    return close_session(session, max(0.1, deadline - time.monotonic())) and not worker.is_alive()


def serve_tasks(tasks: queue.Queue, handle: Callable[[Any], None], failed: Callable[[Any], str],
                logger: logging.Logger = log) -> None:
    """A bus worker thread's loop (zenoh's callbacks only enqueue): `handle` each task until a None
    comes; a task that raises is logged with `failed(task)` and the worker goes on (one bad
    message must not stop it).

    Parameters
    ----------
    tasks : queue.Queue
        The tasks, in order; None ends the loop.
    handle : callable
        Called with each task, in this thread.
    failed : callable
        The log message for a task whose `handle` raised an Exception.
    logger : logging.Logger
        Where failures are logged (default: the bus's log channel).
    """
    while True:
        task = tasks.get()
        if task is None:
            return
        try:
            handle(task)
        except Exception:  # noqa: BLE001 - the worker must survive any single failure
            logger.exception("%s", failed(task))
