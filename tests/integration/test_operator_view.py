"""Operators can read the service (issue 22, item 6): `dt run` says every few seconds how it is
doing (ticks, rate, state, last t, U), `dt status` is a summary in mm, local time and named
frames, and the raw figures stay behind `--json`."""
from __future__ import annotations

import argparse
import json
import logging
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dt_runtime.cli import run as run_cli
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS, ROOT
from dt_runtime.service.daemon import Daemon, RuntimeConfig
from dt_runtime.service.rows import shown_time
from tests.support.loopback import free_port

SCENARIO, CELL = CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml"


def _yaml(tmp_path: Path, twin_dir: Path, realtime: bool) -> Path:
    cfg = tmp_path / "runtime.yaml"
    cfg.write_text(f"twin: {twin_dir}\nstore: {tmp_path / 'dt.sqlite'}\nrate_hz: 20\n"
                   f"realtime: {str(realtime).lower()}\npublish: false\n"
                   f"bus: {{listen: [tcp/127.0.0.1:{free_port()}]}}\n"
                   f"sim: {{scenario: {SCENARIO}, cell: {CELL}}}\n")
    return cfg


@pytest.fixture(scope="module")
def ran(twin_dir, tmp_path_factory):
    """A daemon that ran 6 ticks on the simulated cell: (its status line, fields, its store)."""
    tmp = tmp_path_factory.mktemp("operator")
    cfg = RuntimeConfig.model_validate({
        "twin": str(twin_dir), "store": str(tmp / "dt.sqlite"), "realtime": False, "publish": False,
        "sim": {"scenario": str(SCENARIO), "cell": str(CELL)},
        "bus": {"listen": [f"tcp/127.0.0.1:{free_port()}"]}})
    d = Daemon(cfg, CONFIGS)
    try:
        d.run(max_ticks=6)
        text, fields = d.status_line()
        t, corr = d.status_line.last  # type: ignore[misc]
    finally:
        d.close()
    return text, fields, tmp / "dt.sqlite", t, corr


def test_the_status_line_says_ticks_rate_state_last_t_and_U(ran):
    text, f, _, t, corr = ran
    assert f["ticks"] == 6 and f["status"] == "running" and f["escalation"] in ("nominal", "suspect")
    assert f["U95_mm"] == pytest.approx(corr.U_tcp * 1e3, abs=1e-4) and 0 < max(f["U95_mm"]) < 1.0
    assert f["last_t"] == t and f["rate_hz"] > 0
    # the text prints the rate to 0.1/s, the field keeps 0.01: equal to the text's rounding
    m = re.match(r"6 ticks \(([0-9.]+)/s\), running, escalation ", text)
    assert m and float(m.group(1)) == pytest.approx(f["rate_hz"], abs=0.051), text
    assert f"last command t = {t:.1f} s (simulated clock)" in text
    assert "U95 x/y/z " + "/".join(f"{u:.3f}" for u in f["U95_mm"]) + " mm" in text


def test_dt_run_logs_the_line_every_few_seconds_as_json_and_quiet_silences_it(twin_dir, tmp_path, caplog):
    cfg = _yaml(tmp_path, twin_dir, realtime=True)
    p = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "run", "--config", str(cfg), "--duration", "2.5",
                        "--status-every", "0.5", "--json"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = [json.loads(x) for x in p.stderr.splitlines() if x.startswith("{")]
    status = [r for r in lines if r["logger"] == "dt.run.status"]
    assert status, p.stderr[-2000:]  # 2.5 s at one line per 0.5 s: about 5
    last = status[-1]
    assert {"ticks", "rate_hz", "status", "escalation", "last_t", "U95_mm"} <= last.keys()
    assert last["msg"].startswith(f"{last['ticks']} ticks (") and "U95 x/y/z" in last["msg"]
    assert last["ticks"] <= json.loads(p.stdout)["ticks"]
    caplog.set_level(logging.INFO, logger="dt.run.status")
    cfg.write_text(cfg.read_text().replace("realtime: true", "realtime: false"))
    assert main(["run", "--config", str(cfg), "--duration", "30", "--status-every", "0.1", "--quiet", "--json"]) == 0
    assert not [r for r in caplog.records if r.name == "dt.run.status"]


@pytest.mark.parametrize("fmt, tty, as_json", [("auto", False, True), ("auto", True, False), ("json", True, True),
                                               ("text", False, False)])
def test_logs_are_json_lines_for_machines_and_text_at_a_terminal(monkeypatch, fmt, tty, as_json):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty, raising=False)
    assert run_cli.json_logs(argparse.Namespace(log_format=fmt)) is as_json


def test_dt_status_is_a_summary_in_mm_local_time_and_named_frames(ran, capsys):
    _, _, store, _, _ = ran
    assert main(["status", "--store", str(store), "--json"]) == 0
    raw = json.loads(capsys.readouterr().out)
    assert main(["status", "--store", str(store)]) == 0
    out = capsys.readouterr().out
    assert "{" not in out and len(out.splitlines()) <= 12, out
    saved = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(raw["state"]["updated"]))
    assert f"escalation state: {raw['state']['data']['state']} (episode 0); saved {saved} (" in out
    assert f"rows: 6 commands, 6 MVS measurements, 6 Eq. 17 tests, {raw['t_tests']['failed']} failed" in out
    c, m = raw["last_command"], raw["last_measurement"]
    mm = lambda r, k: "  ".join(f"{a} {r[c_] * 1e3:.3f}" for a, c_ in zip("xyz", k.split()))  # noqa: E731
    assert f"last command, {shown_time(c['t'])}: target (robot frame) {mm(c, 'x y z')} mm at " in out
    assert f"standard uncertainty of the position reached (GL axes) {mm(raw['last_correction'], 'ux uy uz')} mm" in out
    assert f"TCP (MVS frame) {mm(m, 'x y z')} mm; e_LT_hat - e_MVS (GL) {mm(m, 'ex ey ez')} mm" in out
    assert "(simulated clock)" in out and np.isfinite(raw["last_tstat"]["t_value"])
    assert "maintenance requests: 0 not acknowledged" in out
