"""Every place a command or set-point is corrected runs through the one correction law
(`twin.corrector.Corrector.correct`): the twin's API, a point program (`dt correct`), a path program
(`dt correct --path`), a streamed path (`path_corrector`), the daemon's tick and the bus correction
server. A spy on the law counts its calls from each."""
import json

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.correction_client import request_correction
from dt_runtime.fabric.session import close_session, open_session
from dt_runtime.service.correction_server import CorrectionServer
from dt_runtime.service.daemon import Daemon
from dt_runtime.service.path_run import path_corrector
from dt_runtime.service.runtime_config import RuntimeConfig
from dt_runtime.twin.bounds import Guard, Limits
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.twin import Twin
from tests.support.loopback import free_port

LINE = """path: 1
start: [900, 0, 550]
speed: 250
acceleration: 2000
segments:
  - line: {to: [950, 0, 550]}
"""


@pytest.fixture
def calls(monkeypatch):
    """The law's calls, counted."""
    n = {"calls": 0}
    law = Corrector.correct

    def spy(self, *a, **kw):
        n["calls"] += 1
        return law(self, *a, **kw)

    monkeypatch.setattr(Corrector, "correct", spy)
    return n


def test_the_twins_api(twin_dir, calls):
    twin = Twin.load(twin_dir)
    twin.correct(np.array([0.9, 0.0, 0.55]), 0.5)
    twin.corrected_command(np.array([0.9, 0.0, 0.55]), 0.5)
    assert calls["calls"] == 2


def test_a_point_program_and_a_path_program(twin_dir, tmp_path, capsys, calls):
    prog = tmp_path / "p.csv"
    prog.write_text("point_id,x,y,z,speed\na,900,0,550,500\nb,880,40,560,250\n")
    assert main(["correct", "--twin", str(twin_dir), "--targets", str(prog), "--out", str(tmp_path / "c.csv")]) == 0
    assert calls["calls"] == 2
    path = tmp_path / "seam.yaml"
    path.write_text(LINE)
    assert main(["correct", "--twin", str(twin_dir), "--path", str(path), "--rate", "125",
                 "--out", str(tmp_path / "sp.csv"), "--json"]) == 0
    n = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["n"]
    assert calls["calls"] == 2 + n


def test_a_streamed_path(twin_dir, calls):
    times = np.linspace(0.0, 0.1, 13)
    correct = path_corrector(str(twin_dir), times, np.full(13, 0.25))
    for k, t in enumerate(times):
        correct(np.array([0.9 + 1e-3 * k, 0.0, 0.55]), float(t))
    assert calls["calls"] == 13


def test_the_daemons_tick(twin_dir, tmp_path, calls):
    cfg = RuntimeConfig.model_validate({
        "twin": str(twin_dir), "store": str(tmp_path / "dt.sqlite"), "realtime": False, "publish": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml")}})
    d = Daemon(cfg, CONFIGS)
    try:
        s = d.run(max_ticks=20)
    finally:
        d.close()
    assert s["ticks"] == 20 and calls["calls"] >= 20 - s["refused_commands"] - s["uncorrected_commands"] > 0


def test_the_bus_correction_server(twin_dir, calls):
    twin = Twin.load(twin_dir)
    port = free_port()
    cfg = BusConfig(cell="c1", robot="r1", listen=[f"tcp/127.0.0.1:{port}"])
    server = CorrectionServer(Guard(twin, Limits(), Corrector(twin)), cfg)
    client = open_session(BusConfig(cell="c1", robot="prog", listen=[f"tcp/127.0.0.1:{free_port()}"],
                                    connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        reply = request_correction(client, cfg.key("correct"), [900.0, 0.0, 550.0], 500.0, timeout_s=10.0)
    finally:
        close_session(client, 3.0)
        assert server.close(3.0)
    assert "command_mm" in reply and calls["calls"] == 1
