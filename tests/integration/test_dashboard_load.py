"""`dt dashboard` under load, as a process of its own on loopback: 200 event-stream clients and
800 half-open connections (connected, then silent or half a request line) at once. Every stream
client is served (200 and its first event) or refused at once (503 with Retry-After); the page's
/api/snapshot still answers; the server's threads and memory stay bounded; the half-open
connections are closed by the server; nothing on its stderr is a traceback; SIGTERM ends it
cleanly. Deadlines are generous (hang detection), nothing is timed; the figures measured are
printed (pytest -s) for docs/dashboard.md."""
from __future__ import annotations

import json
import os
import resource
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dt_runtime.dashboard.server import MAX_STREAMS
from tests.support.loopback import free_port, wait_until

STREAMS = 200
HALF_OPEN = 800
ROOT = Path(__file__).resolve().parents[2]


def _proc(pid: int) -> dict[str, int]:
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return {"threads": int(status["Threads"]), "rss_kb": int(status["VmRSS"].split()[0])}


def _get(port: int, path: str, timeout: float = 30.0) -> tuple[int, bytes]:
    """One GET on a connection of its own (Connection: close): the status and the body."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


@pytest.fixture
def server(tmp_path):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = STREAMS + HALF_OPEN + 200
    if soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(need, hard), hard))
    port = free_port()
    err = tmp_path / "stderr.txt"
    results = tmp_path / "results"
    results.mkdir()
    with err.open("wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "dt_runtime.cli.main", "dashboard", "--results", str(results),
                                 "--port", str(port), "--json"], cwd=ROOT, stdout=subprocess.PIPE, stderr=f,
                                env=os.environ | {"PYTHONUNBUFFERED": "1"})
    try:
        def up() -> bool:
            try:
                return _get(port, "/api/snapshot", 2.0)[0] == 200
            except OSError:
                return False
        assert wait_until(up, 60), err.read_text()
        yield proc, port, err
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)
        if proc.stdout is not None:
            proc.stdout.close()


def test_200_streams_and_800_half_open_connections_are_served_or_refused_and_stay_bounded(server):
    proc, port, err = server
    figures: dict[str, object] = {}
    half: list[socket.socket] = []
    streams: dict[socket.socket, bytes] = {}
    sel = selectors.DefaultSelector()
    try:
        t0 = time.monotonic()
        for i in range(HALF_OPEN):  # connected and silent, or half a request line and silent
            s = socket.create_connection(("127.0.0.1", port), timeout=30)
            if i % 2:
                s.sendall(b"GET /api/snap")
            half.append(s)
        for _ in range(STREAMS):
            s = socket.create_connection(("127.0.0.1", port), timeout=30)
            s.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAccept: text/event-stream\r\n\r\n"
                      .encode())
            s.setblocking(False)
            streams[s] = b""
            sel.register(s, selectors.EVENT_READ)

        # Each stream client's answer: a 200 with its first event (the snapshot), or a 503.
        def answered(data: bytes) -> str | None:
            head, sep, body = data.partition(b"\r\n\r\n")
            if not sep:
                return None
            if head.startswith(b"HTTP/1.1 503"):
                return "refused" if b"\r\nretry-after: " in head.lower() else "refused without Retry-After"
            if head.startswith(b"HTTP/1.1 200") and b"text/event-stream" in head:
                return "served" if b"event: snapshot\r\ndata: {" in body or b"event: snapshot\ndata: {" in body \
                    else None
            return "other: " + head.split(b"\r\n", 1)[0].decode(errors="replace")

        outcome: dict[socket.socket, str] = {}
        deadline = time.monotonic() + 60
        while len(outcome) < STREAMS and time.monotonic() < deadline:
            for key, _ in sel.select(timeout=1.0):
                s = key.fileobj
                assert isinstance(s, socket.socket)
                try:
                    chunk = s.recv(65536)
                except BlockingIOError:
                    continue
                streams[s] += chunk
                got = answered(streams[s]) if chunk else "closed without an answer"
                if got is not None:
                    outcome[s] = got
                    sel.unregister(s)
        figures["answered_s"] = round(time.monotonic() - t0, 2)
        kinds = sorted(outcome.values())
        served, refused = kinds.count("served"), kinds.count("refused")
        figures |= {"served": served, "refused": refused}
        assert served + refused == STREAMS, (kinds, len(outcome))
        assert served == min(STREAMS, MAX_STREAMS)

        # While all of them are open, the page's snapshot answers; the server stays bounded.
        t1 = time.monotonic()
        status, body = _get(port, "/api/snapshot", 30.0)
        figures["snapshot_ms"] = round(1e3 * (time.monotonic() - t1), 1)
        assert status == 200 and "server_t" in json.loads(body)
        load = _proc(proc.pid)
        figures |= {"threads": load["threads"], "rss_mb": round(load["rss_kb"] / 1024, 1)}
        assert load["threads"] < 50 and load["rss_kb"] < 500 * 1024, load

        # The half-open connections are closed by the server (a request head is due within its deadline).
        closing_deadline = time.monotonic() + 60  # for all of them together

        def closed(s: socket.socket) -> bool:
            s.settimeout(max(0.1, closing_deadline - time.monotonic()))
            try:
                return s.recv(1) == b""
            except ConnectionResetError:
                return True
            except TimeoutError:
                return False
        t2 = time.monotonic()
        assert all(closed(s) for s in half)
        figures["half_open_closed_after_s"] = round(time.monotonic() - t2 + (t1 - t0), 1)
    finally:
        sel.close()
        for s in list(streams) + half:
            s.close()
    # the streams' slots come back: a new page is served once the old ones went away
    def served_again() -> bool:
        with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
            s.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
            return s.recv(64).startswith(b"HTTP/1.1 200")
    assert wait_until(served_again, 30)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 0
    log = err.read_text()
    assert "Traceback" not in log and "Exception" not in log, log[-3000:]
    print(f"\ndashboard load: {json.dumps(figures)}")
