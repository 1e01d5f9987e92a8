"""The dashboard's plant page in a real headless browser (the OS's Chromium driven by Playwright):
`dt router` and two `dt run` cells as processes on loopback (tests.support.plant_cells), cell c1
with a joint fault (it pages: one open request), c1's own dashboard and the plant page's
dashboard in this process. The facts: /plant lists both cells with their status and escalation,
the third expected cell (c3, never started) is marked silent, and a click on c1 opens c1's live
view (its own dashboard, from the plant config's `dashboards:`). Waits are generous; nothing is timed."""
from __future__ import annotations

import subprocess

import pytest

from dt_runtime.dashboard.app import Dashboard
from dt_runtime.plant.config import PlantConfig
from dt_runtime.service.runtime_config import load_runtime_config
from tests.support import browser
from tests.support.loopback import free_port, wait_until
from tests.support.plant_cells import dt, router, runtime, stop


@pytest.fixture
def fabric(twin_dir, tmp_path):
    """A router and cells c1 (faulty), c2 running; their config paths and the router's port."""
    port = free_port()
    plant_yaml = tmp_path / "plant.yaml"
    plant_yaml.write_text(f"router: {{listen: ['tcp/127.0.0.1:{port}']}}\n")
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["router"] = router(plant_yaml, tmp_path / "router.log")
        cfgs = {c: runtime(tmp_path, twin_dir, c, port, faulty=c == "c1") for c in ("c1", "c2")}
        for c, cfg in cfgs.items():
            procs[c] = dt("run", "--config", str(cfg), log=tmp_path / f"{c}.log")
        yield port, cfgs, procs
    finally:
        for p in procs.values():
            stop(p)


def test_plant_page_lists_the_cells_marks_the_silent_one_and_opens_a_cells_live_view(fabric, tmp_path):
    port, cfgs, procs = fabric
    c1_cfg = load_runtime_config(cfgs["c1"])
    with Dashboard(c1_cfg, cfgs["c1"], port=0) as c1_dash:
        plant = PlantConfig.model_validate({
            "bus": {"cell": "plant", "robot": "view", "mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]},
            "cells": ["c1/r1", "c2/r1", "c3/r1"], "dashboards": {"c1/r1": c1_dash.url}})
        with Dashboard(None, None, plant=plant, plant_period_s=1.0, port=0) as dash:
            def rows() -> dict:
                return {f"{c['cell']}/{c['robot']}": c for c in dash.plant.snapshot()["cells"]} if dash.plant else {}

            def paged() -> bool:
                r = rows()
                return (not r["c1/r1"]["silent"] and r["c1/r1"].get("escalation") == "maintenance_requested"
                        and r["c1/r1"].get("open_requests") == 1 and not r["c2/r1"]["silent"])
            assert wait_until(paged, 120), (rows(), [(tmp_path / f"{c}.log").read_text()[-1500:] for c in cfgs])

            from playwright.sync_api import sync_playwright

            with sync_playwright() as pw:
                b = browser.launch(pw)  # a missing browser fails the test
                try:
                    pg = b.new_context(viewport={"width": 1400, "height": 900}, bypass_csp=True).new_page()
                    errors: list[str] = []
                    pg.on("pageerror", lambda e: errors.append(str(e)))
                    pg.goto(dash.url)  # no live cell of its own: / is the plant page
                    assert pg.url == dash.url + "plant"
                    pg.wait_for_function("window.P && P.rows.length === 3", timeout=60_000)
                    table = {r: [td.strip() for td in pg.locator(f"#cells tr[data-cell='{r}'] td").all_text_contents()]
                             for r in ("c1/r1", "c2/r1", "c3/r1")}
                    # cell/robot, status, escalation, open requests, last contact, live view
                    assert table["c1/r1"][0] == "c1/r1" and table["c1/r1"][1] in ("running", "degraded")
                    assert table["c1/r1"][2:4] == ["maintenance_requested", "1"]
                    assert table["c2/r1"][1:4] == ["running", "nominal", "0"] and table["c2/r1"][5] == "not listed"
                    assert table["c3/r1"][1:5] == ["silent (never heard)", "", "", "never"]
                    assert table["c1/r1"][4].endswith(" s ago") and float(table["c1/r1"][4].split()[0]) < 60
                    assert "silent: c3/r1" in pg.text_content("#summary")
                    assert pg.locator("#cells tr[data-cell='c3/r1']").get_attribute("class") == "silent"

                    # A click on c1 opens its live view: c1's own dashboard, reading dt/c1/r1.
                    pg.locator("#cells tr[data-cell='c1/r1'] td.age").click()
                    pg.wait_for_url(c1_dash.url, timeout=30_000)
                    pg.wait_for_function("window.dtStats && dtStats.messages > 5", timeout=60_000)
                    assert pg.text_content("#prefix") == "dt/c1/r1"
                    assert not errors, errors
                finally:
                    b.close()
    for c in cfgs:
        assert procs[c].poll() is None, (tmp_path / f"{c}.log").read_text()[-2000:]
