"""`dt dashboard` in a real headless browser (the OS's Chromium driven by Playwright) against a
daemon on loopback: the page loads and draws the cell, a state change on the bus reaches the DOM
within a second, an unauthenticated acknowledgement is refused with nothing published, and an
operator's acknowledgement and 'done' from the page reach the daemon and are stored by name.

The daemon runs in this process on the simulated cell, paced at 25 Hz, with a joint fault from
its first tick so that it pages within a second or two (its request is what the page acts on).
Set DT_SCREENSHOTS=DIR to keep the browser's screenshots (docs/screenshots/ holds the committed ones).
"""
from __future__ import annotations

import json
import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from dt_runtime.common.paths import CONFIGS
from dt_runtime.dashboard.app import Dashboard
from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.auth import Signer
from dt_runtime.fabric.session import close_session, open_session, put_json
from dt_runtime.service.daemon import Daemon, RuntimeConfig
from tests.support import browser
from tests.support.loopback import free_port, wait_until

TOKEN = "alice-token-0123456789abcdef"


@pytest.fixture(scope="module")
def cell(twin_dir, tmp_path_factory):
    """A paced daemon publishing on tcp/127.0.0.1:<port>, with a 2 mrad joint fault from the start."""
    tmp = tmp_path_factory.mktemp("dashboard")
    port = free_port()
    cfg = RuntimeConfig.model_validate({
        "twin": str(twin_dir), "store": str(tmp / "dt.sqlite"), "realtime": True, "rate_hz": 25,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml"),
                "faults": [{"at_s": 0.0, "joint_offset_rad": [0, 2e-3, 0, 0, 0, 0]}]},
        "bus": {"cell": "c1", "robot": "r1", "listen": [f"tcp/127.0.0.1:{port}"], "republish_period_s": 0.5}})
    d = Daemon(cfg, CONFIGS)
    th = threading.Thread(target=d.run, name="daemon", daemon=True)
    th.start()
    try:
        yield d, cfg, tmp
    finally:
        d.stop()
        th.join(30)
        d.close()


@pytest.fixture(scope="module")
def dash(cell):
    d, cfg, tmp = cell
    ops = tmp / "operators"
    fd = os.open(ops, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.write(fd, f"# the test's operator\nalice {TOKEN}\n".encode())
    os.close(fd)
    with Dashboard(cfg, tmp / "runtime.yaml", port=0, token_file=ops) as dsh:
        yield dsh


@pytest.fixture(scope="module")
def page(dash):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = browser.launch(pw)  # a missing browser fails the test
        # The page's Content-Security-Policy forbids eval; Playwright's string predicates use it.
        pg = b.new_context(viewport={"width": 1400, "height": 1100}, bypass_csp=True).new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(dash.url)
        pg.wait_for_function("window.dtStats && dtStats.messages > 5", timeout=60_000)
        yield pg
        assert not errors, errors
        b.close()


def _shot(page, name: str) -> None:
    out = os.environ.get("DT_SCREENSHOTS")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(out) / name), full_page=True)


@pytest.fixture(scope="module")
def bus_peer(cell):
    """A zenoh session of the test's own on the cell's bus, recording every maintenance ack and
    'done' put on it."""
    _, cfg, _ = cell
    peer_cfg = BusConfig(cell="c1", robot="r1", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=cfg.bus.listen)
    s = open_session(peer_cfg)
    seen: list[str] = []
    sub = s.declare_subscriber("dt/c1/r1/maintenance/*/*", lambda sample: seen.append(str(sample.key_expr)))
    yield s, seen
    sub.undeclare()
    close_session(s, 3.0)


def test_the_page_loads_against_the_daemon_and_draws_the_cell(page, dash):
    assert page.title() == "cobot-dt dashboard"
    assert page.text_content("#prefix") == "dt/c1/r1"
    assert page.text_content("#health-status") in ("running", "degraded")
    prov = page.text_content("#prov")
    assert "cobot_hc20_like, 6 joints" in prov and "t_crit 1.9" in prov
    # the arm: the telemetry carries the controller's joints and the server its FK (8 points, base to TCP)
    last = page.evaluate("S.last")
    assert len(last["arm"]) == 8
    tcp, command = last["arm"][-1], last["command"]
    assert max(abs(a - b) for a, b in zip(tcp, command)) < 0.01  # the arm stands where it was sent (m)
    page.wait_for_function("dtStats.frames > 3")
    ink = browser.canvas_ink(page, "#view3d")
    assert ink["drawn"] > 0.02 * ink["pixels"], ink  # not blank: floor, volume, points, arm
    assert ink["grey"] > 500, ink  # the arm's links and joints
    tplot = browser.canvas_ink(page, "#tplot")
    assert tplot["drawn"] > 500, tplot
    detail = page.text_content("#errors")
    assert "measured − target" in detail and " mm" in detail
    _shot(page, "dashboard_live.png")


def test_validity_now_shows_the_worse_state_and_the_views_say_mm(page, dash):
    # "validity: OK" (the calibration's) stood beside an active maintenance request; the live view
    # said "robot frame, m" while every figure is in mm; the t chart had no axis scale
    page.wait_for_function("currentState() === 'maintenance_requested'", timeout=90_000)
    page.wait_for_function("document.getElementById('validity-now').textContent.startsWith('NOT VALID now')",
                           timeout=10_000)
    prov = page.text_content("#prov")
    assert "validity at calibration" in prov and prov.index("validity now") < prov.index("validity at calibration")
    assert "robot frame, mm" in page.text_content("#cell h2")
    assert page.evaluate("[niceStep(9.6), niceStep(4.2), niceStep(0.4)]") == [5, 2, 0.1]
    assert page.evaluate("T_MARGIN.left") >= 30  # the t axis's labels sit left of the traces


ARROWS = (0x00, 0x89, 0x7B)  # the error map's colour (app.js drawErrorMap)


def test_the_error_map_is_drawn_as_arrows_at_the_campaigns_points_and_toggles(page, dash, twin_dir):
    em = page.evaluate("S.scene.error_map")
    # the quick demo's DOE: its points, every row of the campaign's doe.csv counted once
    doe_rows = sum(1 for _ in open(twin_dir.parent / "campaign" / "doe.csv")) - 1
    assert sum(em["count"]) == em["rows"] == doe_rows and len(em["points"]) == len(em["e_hat"]) > 20
    # the twin's own prediction at a point (its map at rest there: no previous command to approach from)
    twin = dash.scene.twin
    e0 = twin.e_lt_hat(em["points"][0], 0.3)[0]
    assert 0.05e-3 < float(np.linalg.norm(e0)) < 5e-3  # the demo arm's error: about a millimetre
    assert float(np.linalg.norm(np.array(em["e_hat"][0]) - e0)) < 0.3 * float(np.linalg.norm(e0))
    # drawn at a stated scale: the longest arrow about a tenth of the ~1 m campaign
    assert em["scale"] in (20, 50, 100) and 0.04 < em["scale"] * em["max_m"] < 0.15
    assert f"× {em['scale']:g}" in page.text_content("#arrows-key")
    page.wait_for_function("dtStats.frames > 3")
    on = browser.canvas_colour(page, "#view3d", ARROWS)
    page.uncheck("#arrows")
    frames = page.evaluate("dtStats.frames")
    page.wait_for_function(f"dtStats.frames > {frames + 1}")
    off = browser.canvas_colour(page, "#view3d", ARROWS)
    page.check("#arrows")
    frames = page.evaluate("dtStats.frames")
    page.wait_for_function(f"dtStats.frames > {frames + 1}")
    assert on > 4 * len(em["points"]) and off < 0.02 * on, (on, off)  # 531 and 0 when written
    assert browser.canvas_colour(page, "#view3d", ARROWS) > 0.5 * on


def test_a_state_change_on_the_bus_appears_in_the_dom_within_a_second(page, dash, bus_peer, cell):
    session, _ = bus_peer
    signer = Signer(cell[1].bus.auth, create=False)  # the daemon's key: the dashboard refuses unsigned states
    key = "dt/c1/r1/state"

    def publish(rule: str) -> None:
        put_json(session, key, signer.sign(key, {"src": "nominal", "dst": "suspect", "t": time.time(),
                                                 "evidence": {"rule": rule}}))

    before = dash.hub.received["state"]
    # the test's peer and the dashboard must have met (a put before that is lost): warm up until one arrives
    assert wait_until(lambda: (publish("warm-up") or True) and dash.hub.received["state"] > before, 30)
    marker = f"test-{uuid.uuid4().hex[:8]}"
    t0 = time.monotonic()
    publish(marker)
    shown = f"[...document.querySelectorAll('#timeline li')].some(li => li.textContent.includes('{marker}'))"
    page.wait_for_function(shown, timeout=1000)
    assert time.monotonic() - t0 < 1.0
    assert page.get_attribute("#timeline li:first-child", "data-dst") in ("suspect", "nominal", "out_of_control",
                                                                          "maintenance_requested")


def _request_row(page, cell):
    d = cell[0]
    assert wait_until(lambda: d.escalator.state == "maintenance_requested", 60), d.escalator.state
    page.wait_for_selector("#requests tr[data-uid]", timeout=30_000)
    return page.get_attribute("#requests tr[data-uid]", "data-uid")


def test_an_unauthenticated_acknowledgement_is_refused_and_nothing_is_published(page, dash, bus_peer, cell):
    uid = _request_row(page, cell)
    assert page.is_disabled("#requests tr[data-uid] button.ack")  # not signed in: no buttons
    _, seen = bus_peer
    before = list(seen)
    post = """async ([action, uid, auth]) => {
        const headers = {"Content-Type": "application/json"};
        if (auth) headers.Authorization = auth;
        const r = await fetch(`/api/requests/${action}`, {method: "POST", headers,
                                                          body: JSON.stringify({uid, note: "forged"})});
        return [r.status, (await r.json()).error];
    }"""
    assert page.evaluate(post, ["ack", uid, None])[0] == 401
    assert page.evaluate(post, ["done", uid, None])[0] == 401
    status, why = page.evaluate(post, ["done", uid, "Bearer not-an-operators-token-123"])
    assert status == 403 and "no operator" in why
    assert page.evaluate(post, ["ack", uid, "Basic " + TOKEN])[0] == 401
    time.sleep(0.5)  # what was published would have arrived by now on loopback
    assert seen == before and dash.server.actions == []
    assert not [a for a in cell[0].store.actions(limit=100) if a.kind == "done"]
    assert cell[0].escalator.state == "maintenance_requested"
    _shot(page, "dashboard_degraded.png")


def test_an_operators_acknowledgement_from_the_page_reaches_the_daemon_by_name(page, dash, cell):
    d = cell[0]
    uid = _request_row(page, cell)
    page.fill("#token", TOKEN)
    page.click("#signin")
    page.wait_for_function("document.getElementById('operator').textContent === 'operator alice'")
    row = f"#requests tr[data-uid='{uid}']"
    page.click(f"{row} button.ack")
    page.wait_for_function("document.getElementById('act-status').textContent.startsWith('ack by alice')")
    assert wait_until(lambda: len(d.paging.delivered) >= 1, 10)  # the daemon took the ack: the copy left the outbox
    page.fill(f"{row} input.note", "joint 2 re-referenced")
    page.click(f"{row} button.done")
    page.wait_for_function("document.getElementById('act-status').textContent.startsWith('done by alice')")
    assert wait_until(lambda: any(a.kind == "done" and a.by == "alice" and a.note == "joint 2 re-referenced"
                                  and a.applied_at is not None for a in d.store.actions(limit=100)), 20)
    # the daemon's transition back to nominal, published with who and why, shows on the page's timeline
    page.wait_for_function("[...document.querySelectorAll('#timeline li')]"
                           ".some(li => li.textContent.includes('by alice: joint 2 re-referenced'))", timeout=20_000)
    assert [a["by"] for a in dash.server.actions] == ["alice", "alice"]
    _shot(page, "dashboard_operator.png")


def test_the_token_file_must_be_private(cell, tmp_path):
    from dt_kernel.errors import ConfigError

    ops = tmp_path / "operators"
    ops.write_text(f"alice {TOKEN}\n")
    ops.chmod(0o644)
    with pytest.raises(ConfigError, match="mode 0644"):
        Dashboard(cell[1], tmp_path / "runtime.yaml", port=0, token_file=ops)


def test_dt_dashboard_refuses_plain_http_beyond_loopback(cell, tmp_path, capsys):
    from dt_runtime.cli.main import main

    cfg = tmp_path / "runtime.yaml"
    cfg.write_text(json.dumps(cell[1].model_dump(mode="json")))  # JSON is YAML
    assert main(["dashboard", "--config", str(cfg), "--host", "0.0.0.0", "--port", "0", "--json"]) == 2
    assert "--tls-cert" in json.loads(capsys.readouterr().out)["error"]


def test_a_page_refused_when_too_many_are_open_tries_again_and_goes_live(dash, page):
    """With every event stream taken (503 + Retry-After), a new page shows 'reconnecting', then
    goes live by itself once a slot is free (its EventSource gives up on a 503; the page retries)."""
    import socket

    from dt_runtime.dashboard.server import MAX_STREAMS

    port = dash.server.port
    held = []
    try:
        assert wait_until(lambda: dash.server.streams >= 1, 10)  # the module's page
        for _ in range(MAX_STREAMS - dash.server.streams):
            s = socket.create_connection(("127.0.0.1", port), timeout=30)
            s.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
            assert s.recv(64).startswith(b"HTTP/1.1 200")
            held.append(s)
        ctx = page.context.browser.new_context(bypass_csp=True)  # the module's browser: a second page
        try:
            pg = ctx.new_page()
            pg.goto(dash.url)
            pg.wait_for_function("document.getElementById('link').textContent === 'reconnecting'", timeout=30_000)
            assert dash.server.refused_streams >= 1
            for s in held:
                s.close()
            held.clear()
            pg.wait_for_function("window.dtStats && dtStats.connected && dtStats.messages > 0", timeout=60_000)
            assert pg.text_content("#link") == "live"
        finally:
            ctx.close()
    finally:
        for s in held:
            s.close()
