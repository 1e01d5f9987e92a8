"""systemd's service notification protocol (sd_notify), without a dependency.

When `dt run` is started by systemd with `Type=notify` it finds `NOTIFY_SOCKET` in its environment
and sends datagrams there: `READY=1` once started, `WATCHDOG=1` while its loop ticks (with
`WatchdogSec=` set, systemd exports `WATCHDOG_USEC` and restarts a daemon that stops sending),
`STOPPING=1` on the way out. The protocol is a line `KEY=VALUE` per datagram on a Unix socket
(an abstract one when the path starts with '@'); see sd_notify(3). Outside systemd every call
is a no-op.
"""
from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger("dt.sdnotify")


def notify(message: str) -> bool:
    """Send `message` to systemd (one datagram on `NOTIFY_SOCKET`); never raises.

    Parameters
    ----------
    message : str
        E.g. "READY=1", "WATCHDOG=1", "STOPPING=1".

    Returns
    -------
    bool
        True if sent; False if not run under systemd (or the socket is gone: logged at DEBUG).
    """
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(message.encode())
        return True
    except OSError as exc:
        log.debug("sd_notify %s failed: %s", message, exc)
        return False


def watchdog_period() -> float | None:
    """Seconds within which systemd wants WATCHDOG=1 (WATCHDOG_USEC), or None when no watchdog
    is set for this process (WATCHDOG_PID names another)."""
    usec, pid = os.environ.get("WATCHDOG_USEC"), os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return int(usec) / 1e6
    except ValueError:
        return None
