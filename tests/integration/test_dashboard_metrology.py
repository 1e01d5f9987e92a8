"""The metrologist's view of `dt dashboard` (/metrology) in a real headless browser (the OS's
Chromium driven by Playwright), on real results: `dt diagnose --auto --out` and `dt compare
--report` of a simulated campaign with a hidden backlash, under one `--results` directory, served
without a live cell. The page's numbers are checked against the files the commands wrote.
Set DT_SCREENSHOTS=DIR to keep the screenshot (docs/screenshots/dashboard_metrology.png)."""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from dt_runtime.analysis.points import per_point
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.dashboard.app import Dashboard
from tests.support import browser


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """DIR/model: `dt diagnose --auto --out` (diagnose.json and residuals.csv beside the model); DIR/compare:
    `dt compare --report` of that model on the same data (compare.json, report.html, residuals.csv);
    DIR/older: the diagnose result as written before residuals.csv."""
    root = tmp_path_factory.mktemp("results")
    data = root.parent / f"{root.name}-backlash.csv"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--scenario", str(CONFIGS / "scenarios" / "hidden" / "backlash.yaml"),
                     "--out", str(data), "--json", "--no-progress"]) == 0
        assert main(["diagnose", "--data", str(data), "--auto", "--out", str(root / "model"), "--json",
                     "--no-progress"]) == 0
        assert main(["compare", "--model", str(root / "model"), "--data", str(data), "--report",
                     str(root / "compare"), "--json", "--no-progress"]) == 0
    shutil.copytree(root / "model", root / "older", ignore=shutil.ignore_patterns("residuals.csv"))
    return root


@pytest.fixture(scope="module")
def page(results):
    from playwright.sync_api import sync_playwright

    with Dashboard(None, None, port=0, results=results) as dash, sync_playwright() as pw:
        b = browser.launch(pw)  # a missing browser fails the test
        pg = b.new_context(viewport={"width": 1400, "height": 1100}, bypass_csp=True).new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(dash.url)  # no live cell: / leads to /metrology
        pg.wait_for_function("window.dtMetro && dtMetro.loaded === 'compare'", timeout=60_000)
        yield pg
        assert not errors, errors
        b.close()


def _table(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def test_the_page_opens_the_compare_result_and_draws_its_residual_map_per_point(page, results):
    assert page.url.endswith("/metrology?name=compare")
    t = _table(results / "compare" / "residuals.csv")
    P = np.column_stack([t[a].astype(float) for a in "xyz"])
    r = np.column_stack([t[f"r_{a}:model"].astype(float) for a in "xyz"])
    pts, mean, cnt = per_point(P, r)
    m = page.evaluate("dtMetro")
    assert m["kind"] == "compare" and m["rows"] == len(P) == 372 and m["points"] == len(pts)
    assert page.input_value("#f-model") == "model"  # the primary model (the last compared), as the report's map
    # the largest |mean r| per point, as the page aggregates it, is the one numpy finds
    worst = page.text_content("#worst tbody tr:first-child td:nth-child(2)")
    assert float(worst) == pytest.approx(float(np.linalg.norm(mean, axis=1).max()), abs=1e-4)
    assert int(page.text_content("#worst tbody tr:first-child td:nth-child(3)")) == int(cnt[np.argmax(
        np.linalg.norm(mean, axis=1))])
    ink = browser.canvas_ink(page, "#map3d")
    assert ink["drawn"] > 0.01 * ink["pixels"], ink  # not blank: the points and their box
    # the report's own figures, embedded, as many as report.html holds
    html = (results / "compare" / "report.html").read_text()
    n_fig = len(re.findall(r'<figure><img src="data:image/png;base64,', html))
    assert n_fig >= 3 and page.locator("#figures figure img").count() == n_fig
    cmp = json.loads((results / "compare" / "compare.json").read_text())
    assert page.locator("#models tbody tr td:first-child").all_text_contents() == [mm["name"] for mm in cmp["models"]]
    assert page.text_content("#models tbody tr:last-child td:nth-child(2)").startswith(f"{cmp['rmse_mm']:.4f} ± ")
    _shot(page, "dashboard_metrology.png")


def test_the_colour_scale_starts_at_the_noise_floor_so_noise_is_never_red(page, results):
    # the scale ran 0 ... 95th percentile: a result whose residuals all lie below the noise floor
    # was painted red by its own percentile
    cmp = json.loads((results / "compare" / "compare.json").read_text())
    floor = cmp["noise_floor_mm"]
    assert floor and floor > 0
    blue = page.evaluate("colour(0)")
    assert page.evaluate(f"colour({floor * 0.9})") == blue and page.evaluate(f"colour({floor})") == blue
    vmax = page.evaluate("R.vmax")
    assert vmax >= 3 * floor and page.evaluate(f"colour({vmax})") == "hsl(0 75% 50%)"
    assert f"noise floor {floor:.4f} mm" in page.text_content("#scale-text")


def test_filters_change_the_rows_and_points_shown(page, results):
    t = _table(results / "compare" / "residuals.csv")
    all_points = page.evaluate("dtMetro.points")
    page.select_option("#f-speed", "300")
    assert page.evaluate("dtMetro.rows") == int((t["speed"].astype(float) == 300).sum()) < 372
    page.select_option("#f-speed", "")
    page.select_option("#f-joint", "approach_q1")
    page.select_option("#f-dir", "1")
    rose = t["approach_q1"] == "1"
    P = np.column_stack([t[a].astype(float) for a in "xyz"])[rose]
    m = page.evaluate("dtMetro")
    assert m["rows"] == int(rose.sum()) and m["points"] == len(per_point(P, P)[0]) < all_points
    r = np.column_stack([t[f"r_{a}:model"].astype(float) for a in "xyz"])[rose]
    assert m["rms"] == pytest.approx(float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))), rel=1e-6)
    assert page.text_content("#shown") == f"{m['points']} points ({m['rows']} rows) shown, 3D RMS {m['rms']:.4f} mm"
    page.select_option("#f-joint", "")
    assert page.evaluate("dtMetro.points") == all_points


def test_the_diagnose_steps_are_the_results(page, results):
    page.select_option("#result", "model")
    page.wait_for_function("dtMetro.loaded === 'model'", timeout=30_000)
    d = json.loads((results / "model" / "diagnose.json").read_text())
    rows = page.locator("#steps tbody tr")
    assert rows.count() == len(d["steps"]) >= 2  # the hidden backlash is found: at least one change and the stop
    changes = [rows.nth(i).get_attribute("data-change") for i in range(rows.count())]
    assert changes == [s["change"] or "" for s in d["steps"]] and "+backlash" in changes
    first = rows.nth(0).locator("td").nth(3).text_content()
    assert first == f"{d['steps'][0]['rmse_mm']:.4f} → {d['steps'][1]['rmse_mm']:.4f}"
    assert page.text_content("#verdict") == d["verdict"]
    page.select_option("#result", "compare")
    page.wait_for_function("dtMetro.loaded === 'compare'", timeout=30_000)


def test_a_diagnose_result_maps_the_held_out_residuals_of_its_first_and_final_model(page, results):
    """residuals.csv of dt diagnose --auto --out: the map as for a compare result, the model selector
    the first and the final model; the final one's held-out error is the smaller (the hidden backlash
    found), and a filter changes what is shown."""
    page.select_option("#result", "model")
    page.wait_for_function("dtMetro.loaded === 'model'", timeout=30_000)
    d = json.loads((results / "model" / "diagnose.json").read_text())
    t = _table(results / "model" / "residuals.csv")
    names = [k[4:] for k in t if k.startswith("r_x:")]
    first, final = f"first: {d['steps'][0]['model']}", f"final: {d['steps'][-1]['model']}"
    assert names == [first, final]
    assert page.locator("#f-model option").all_text_contents() == names
    assert page.input_value("#f-model") == final and page.text_content("#map-why") == ""
    P = np.column_stack([t[a].astype(float) for a in "xyz"])
    m = page.evaluate("dtMetro")
    assert m["rows"] == len(P) == d["n"] and m["points"] == len(per_point(P, P)[0])
    ink = browser.canvas_ink(page, "#map3d")
    assert ink["drawn"] > 0.01 * ink["pixels"], ink
    final_rms, all_points, scale = m["rms"], m["points"], page.text_content("#scale-text")
    _shot(page, "dashboard_metrology_diagnose.png")
    page.select_option("#f-model", first)
    first_rms = page.evaluate("dtMetro.rms")
    assert page.text_content("#scale-text") == scale  # one colour scale for both: the error removed shows
    # the map's RMS over its rows is the steps' held-out figure of each model, and the diagnosis lowered it
    assert first_rms == pytest.approx(d["steps"][0]["rmse_mm"], rel=1e-5)
    assert final_rms == pytest.approx(d["final_rmse_mm"], rel=1e-5)
    assert final_rms < 0.5 * first_rms
    page.select_option("#f-model", final)
    page.select_option("#f-joint", "approach_q1")
    page.select_option("#f-dir", "-1")
    fell = t["approach_q1"] == "-1"
    m = page.evaluate("dtMetro")
    assert m["rows"] == int(fell.sum()) < len(P) and m["points"] == len(per_point(P[fell], P[fell])[0]) < all_points
    page.select_option("#f-joint", "")
    page.select_option("#result", "compare")
    page.wait_for_function("dtMetro.loaded === 'compare'", timeout=30_000)


def test_an_older_diagnose_result_without_residuals_says_how_to_get_its_map(page):
    page.select_option("#result", "older")
    page.wait_for_function("dtMetro.loaded === 'older'", timeout=30_000)
    assert page.evaluate("dtMetro.points") == 0 and page.locator("#steps tbody tr").count() >= 2
    why = page.text_content("#map-why")
    assert "no residuals.csv" in why and "dt compare --model DIR --data FILE --report OUT" in why
    page.select_option("#result", "compare")
    page.wait_for_function("dtMetro.loaded === 'compare'", timeout=30_000)


def test_a_twin_is_a_result_too(twin_dir):
    from dt_runtime.dashboard.results import find_results, load

    found = find_results(twin_dir.parent)
    assert [(r.kind, r.name) for r in found] == [("twin", "model")]
    t = load(found[0])
    assert t["error_map"]["rows"] == sum(t["error_map"]["count"]) > 0
    assert len(t["figures"]) >= 5  # dt demo's report beside the twin


def test_dt_dashboard_needs_a_cell_or_results(tmp_path, capsys):
    assert main(["dashboard", "--port", "0", "--json"]) == 2
    assert "--results" in json.loads(capsys.readouterr().out)["error"]
    assert main(["dashboard", "--results", str(tmp_path / "none"), "--port", "0", "--json"]) == 2
    assert "none" in json.loads(capsys.readouterr().out)["error"]


def _shot(page, name: str) -> None:
    out = os.environ.get("DT_SCREENSHOTS")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(out) / name), full_page=True)
