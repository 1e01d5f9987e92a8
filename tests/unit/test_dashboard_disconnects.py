"""A client that goes away mid-reply ends its request quietly: Starlette turns the OSError of a
closed connection into ClientDisconnect, which the stream did not catch, so uvicorn logged
"Exception in ASGI application" with a traceback for every page that went away (hundreds when
pages reload). Driven at the ASGI level, the way uvicorn calls the app."""
from __future__ import annotations

import asyncio
import logging

import pytest
from starlette.requests import ClientDisconnect

from dt_runtime.dashboard.hub import Hub
from dt_runtime.dashboard.server import DashboardServer, Guard, _EventStream


@pytest.fixture
def server():
    srv = DashboardServer(("127.0.0.1", 0), Hub(), None, None, None)
    yield srv
    srv.socket.close()


def _scope(path: str, method: str = "GET") -> dict:
    return {"type": "http", "method": method, "path": path, "headers": [(b"host", b"127.0.0.1")],
            "asgi": {"version": "3.0", "spec_version": "2.4"}, "query_string": b"", "client": ("127.0.0.1", 5)}


async def _receive() -> dict:
    return {"type": "http.disconnect"}


@pytest.mark.parametrize("gone", [ClientDisconnect(), ConnectionResetError(104, "reset"), BrokenPipeError()])
def test_a_request_whose_client_went_away_ends_without_an_error(server, caplog, gone):
    async def app(scope, receive, send):
        raise gone

    caplog.set_level(logging.DEBUG)
    asyncio.run(Guard(app, server)(_scope("/api/scene"), _receive, _send_ok))
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("went away" in r.getMessage() for r in caplog.records)


def test_a_defect_still_reaches_uvicorn(server):
    async def app(scope, receive, send):
        raise ZeroDivisionError

    with pytest.raises(ZeroDivisionError):
        asyncio.run(Guard(app, server)(_scope("/api/scene"), _receive, _send_ok))


async def _send_ok(message) -> None:
    return None


def test_a_stream_written_to_a_closed_connection_ends_quietly_and_gives_its_slot_back(caplog):
    released = []

    async def chunks():
        yield b"data: 1\n\n"
        yield b"data: 2\n\n"

    async def send(message):
        if message["type"] == "http.response.body" and message.get("body"):
            raise OSError(32, "Broken pipe")  # what the transport raises: Starlette makes it ClientDisconnect

    caplog.set_level(logging.DEBUG)
    asyncio.run(_EventStream(chunks(), lambda: released.append(1))(_scope("/api/events"), _receive, send))
    assert released == [1]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
