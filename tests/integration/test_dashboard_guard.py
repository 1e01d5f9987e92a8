"""The dashboard server's one guard and its route table, in process on loopback (the metrologist's
view of an empty directory, no bus): Host and Origin checks, the operator's token, the body's
size, JSON 404s for what is not routed, the security headers, and HTTPS with --tls-cert/--tls-key."""
from __future__ import annotations

import http.client
import json
import os
import shutil
import ssl
import subprocess

import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.dashboard.app import Dashboard

TOKEN = "alice-token-0123456789abcdef"


@pytest.fixture(scope="module")
def dash(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("guard")
    ops = tmp / "operators"
    fd = os.open(ops, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.write(fd, f"alice {TOKEN}\n".encode())
    os.close(fd)
    (tmp / "results").mkdir()
    with Dashboard(None, None, port=0, results=tmp / "results", token_file=ops) as d:
        yield d


def _ask(dash, method: str, path: str, body: bytes | None = None, headers: dict[str, str] | None = None):
    c = http.client.HTTPConnection("127.0.0.1", dash.server.port, timeout=30)
    try:
        c.request(method, path, body=body, headers=headers or {})
        r = c.getresponse()
        data = r.read()
        return r.status, dict(r.getheaders()), json.loads(data) if r.getheader("content-type") == \
            "application/json" else data
    finally:
        c.close()


def test_a_host_that_is_not_loopback_is_refused_dns_rebinding(dash):
    assert _ask(dash, "GET", "/api/snapshot", headers={"Host": "evil.example:8765"})[:1] == (403,)
    assert _ask(dash, "GET", "/api/snapshot", headers={"Host": "localhost:8765"})[0] == 200
    assert _ask(dash, "GET", "/api/snapshot", headers={"Host": "[::1]:8765"})[0] == 200


def test_actions_need_an_operators_token_and_a_same_origin_small_body(dash):
    post = {"Content-Type": "application/json"}
    status, headers, body = _ask(dash, "POST", "/api/requests/ack", b'{"uid": "x"}', post)
    assert status == 401 and headers["www-authenticate"].startswith("Bearer")
    status, _, body = _ask(dash, "POST", "/api/requests/done", b'{"uid": "x", "note": "n"}',
                           post | {"Authorization": "Bearer not-an-operators-token-123"})
    assert status == 403 and "no operator" in body["error"]
    bearer = post | {"Authorization": f"Bearer {TOKEN}"}
    origin = f"127.0.0.1:{dash.server.port}"
    assert _ask(dash, "POST", "/api/requests/ack", b'{"uid": "x"}', bearer | {"Origin": "http://evil.example"})[0] \
        == 403
    # the operator is known, but this dashboard has no bus: no such request
    status, _, body = _ask(dash, "POST", "/api/requests/ack", b'{"uid": "x"}', bearer | {"Origin": f"http://{origin}"})
    assert status == 404 and "no request" in body["error"]
    assert _ask(dash, "POST", "/api/requests/ack", b"[1, 2", bearer)[0] == 400
    assert _ask(dash, "POST", "/api/requests/done", b'{"uid": "x"}', bearer)[0] == 400  # no note
    big = b'{"uid": "' + b"x" * 5000 + b'"}'
    assert _ask(dash, "POST", "/api/requests/ack", big, bearer)[0] == 413
    chunks = iter([big[:3000], big[3000:]])  # no Content-Length: chunked, counted as it arrives
    assert _ask(dash, "POST", "/api/requests/ack", chunks, bearer)[0] == 413
    assert _ask(dash, "GET", "/api/whoami", headers={"Authorization": f"Bearer {TOKEN}"})[2] == {"operator": "alice"}
    assert _ask(dash, "GET", "/api/whoami")[0] == 401
    assert dash.server.actions == []


def test_what_is_not_routed_is_a_json_404_and_replies_carry_the_security_headers(dash):
    status, headers, body = _ask(dash, "GET", "/api/requests/ack")
    assert status == 404 and body == {"error": "no such page: /api/requests/ack"}
    assert _ask(dash, "POST", "/api/snapshot", b"{}")[2] == {"error": "no such action: /api/snapshot"}
    assert _ask(dash, "GET", "/static/secret.txt")[0] == 404
    assert _ask(dash, "GET", "/api/scene")[0] == 404  # no live cell
    assert _ask(dash, "GET", "/plant")[0] == 404  # no plant
    status, headers, _ = _ask(dash, "GET", "/")
    assert status == 302 and headers["location"] == "/metrology"
    status, headers, page = _ask(dash, "GET", "/static/app.js")
    assert status == 200 and headers["content-type"].startswith("text/javascript") and len(page) > 100
    assert headers["x-content-type-options"] == "nosniff" and "default-src 'self'" in headers["content-security-policy"]
    assert _ask(dash, "GET", "/api/results")[2]["results"] == []


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl makes the test's certificate")
def test_tls_serves_https_and_a_bad_certificate_is_the_command_lines_error(tmp_path):
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
                    "-days", "2", "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
                   check=True, capture_output=True)
    (tmp_path / "r").mkdir()
    with Dashboard(None, None, port=0, results=tmp_path / "r", tls=(str(cert), str(key))) as d:
        assert d.url.startswith("https://127.0.0.1:")
        ctx = ssl.create_default_context(cafile=str(cert))
        c = http.client.HTTPSConnection("127.0.0.1", d.server.port, timeout=30, context=ctx)
        c.request("GET", "/api/snapshot")
        r = c.getresponse()
        assert r.status == 200 and "server_t" in json.loads(r.read())
        c.close()
    with pytest.raises(ConfigError, match="--tls-cert"):
        Dashboard(None, None, port=0, results=tmp_path / "r", tls=(str(key), str(key)))
    with pytest.raises(ConfigError, match="both, or neither"):
        Dashboard(None, None, port=0, results=tmp_path / "r", tls=(str(cert), None))


def test_a_silent_connection_is_closed_but_a_pipelined_stream_is_kept(tmp_path, monkeypatch):
    """The request-head deadline (HEAD_TIMEOUT_S, shortened here) closes a connection that sent
    nothing or half a request line, never one whose request is being answered (a stream asked for
    right behind another request on the same connection)."""
    import socket
    import time

    from dt_runtime.dashboard import server

    monkeypatch.setattr(server, "HEAD_TIMEOUT_S", 0.5)
    (tmp_path / "r").mkdir()
    with Dashboard(None, None, port=0, results=tmp_path / "r") as d:
        port = d.server.port
        silent = socket.create_connection(("127.0.0.1", port), timeout=30)
        half = socket.create_connection(("127.0.0.1", port), timeout=30)
        half.sendall(b"GET /api/snap")
        assert silent.recv(1) == b"" and half.recv(1) == b""  # closed by the server
        ask = f"GET /api/snapshot HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n" \
              f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n"
        with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
            s.sendall(ask.encode())
            got = b""
            while b"event: snapshot" not in got:
                got += s.recv(65536)
            time.sleep(2.0)  # four deadlines
            assert d.server.streams == 1
            s.setblocking(False)
            try:
                assert s.recv(1) != b""  # not closed (a keep-alive or nothing yet)
            except BlockingIOError:
                pass
        silent.close()
        half.close()
