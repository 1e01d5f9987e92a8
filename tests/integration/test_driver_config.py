"""Every driver is configured one way from the runtime YAML: `drivers.<kind>: {kind: NAME, option:
value, ...}`, checked per driver (its `config_model`) when the file is read, errors naming the
file and the key path; an unknown or broken driver ends `dt run` with exit 2 and never hangs."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.serial.tracker import SerialTracker
from dt_kernel.errors import ConfigError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.service.daemon import Daemon
from dt_runtime.service.runtime_config import load_runtime_config
from emulators.serial import TrackerEmulator
from tests.support.loopback import free_port

SCENARIO, CELL = CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml"


def _yaml(tmp_path: Path, twin: Path | str, drivers: str, name: str = "runtime.yaml") -> Path:
    cfg = tmp_path / name
    cfg.write_text(f"twin: {twin}\nstore: {tmp_path / 'dt.sqlite'}\nrealtime: false\npublish: false\n"
                   f"bus: {{listen: [tcp/127.0.0.1:{free_port()}]}}\n"
                   f"sim: {{scenario: {SCENARIO}, cell: {CELL}}}\ndrivers: {drivers}\n")
    return cfg


def test_the_serial_tracker_is_configured_from_the_runtime_yaml_and_the_daemon_runs_with_it(twin_dir, tmp_path):
    """The issue: `tracker: serial` could not be given its url. Now it is an option like any other."""
    with TrackerEmulator(lambda: (2.0, 0.3, -0.1, "ok")) as emu:
        cfg = _yaml(tmp_path, twin_dir, f"{{tracker: {{kind: serial, url: {emu.port}, timeout_s: 1.0, retries: 1}}}}")
        rc = load_runtime_config(cfg)
        assert rc.drivers.tracker.kind == "serial" and rc.drivers.tracker.options["url"] == emu.port
        d = Daemon(rc, cfg.parent, source=str(cfg))
        try:
            assert isinstance(d.inst.tracker, SerialTracker) and d.inst.tracker.state == "active"
            assert d.inst.tracker.cfg.retries == 1
            r = d.inst.tracker.measure()
            assert r.ok and np.isclose(np.linalg.norm(r.point), 2.0)
            assert d.run(max_ticks=3)["ticks"] == 3
        finally:
            d.close()
        assert d.inst.tracker.state == "closed"


def test_the_earlier_form_still_reads_the_same(tmp_path):
    new = load_runtime_config(_yaml(tmp_path, "x", "{robot: {kind: serial, url: /dev/ttyUSB0}, camera: sim_point}"))
    old = load_runtime_config(_yaml(tmp_path, "x", "{robot: serial, robot_config: {url: /dev/ttyUSB0}, "
                                                   "camera: sim_point}", "old.yaml"))
    assert new.drivers == old.drivers
    assert new.drivers.chosen() == [("robot", "serial", {"url": "/dev/ttyUSB0"}), ("tracker", "sim", {}),
                                    ("camera", "sim_point", {})]
    with pytest.raises(ConfigError, match="robot_config"):  # both forms at once: which one is meant?
        load_runtime_config(_yaml(tmp_path, "x", "{robot: {kind: serial, url: a}, robot_config: {url: b}}"))


@pytest.mark.parametrize("drivers, key, value", [
    ("{tracker: {kind: serial}}", "drivers.tracker.url", "<missing>"),
    ("{tracker: {kind: serial, url: /dev/x, timeout_s: -1}}", "drivers.tracker.timeout_s", -1),
    ("{robot: {kind: sim, url: /dev/ttyUSB0}}", "drivers.robot.url", "/dev/ttyUSB0"),
    ("{camera: {kind: sim_images, bogus: 1}}", "drivers.camera.bogus", 1),
    ("{robot: {url: /dev/ttyUSB0}}", "drivers.robot.kind", "<missing>"),
    ("{robot: {kind: ur_rtde_typo}}", "drivers.robot.kind", "ur_rtde_typo"),
])
def test_a_bad_driver_option_names_the_file_and_the_key_path(tmp_path, drivers, key, value):
    cfg = _yaml(tmp_path, "x", drivers)
    with pytest.raises(ConfigError) as ei:
        load_runtime_config(cfg)
    e = ei.value
    assert (e.file, e.key) == (str(cfg), key) and e.value == value, e


def _dt_run(cfg: Path, env: dict | None = None) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "run", "--config", str(cfg), "--duration", "30"],
                       capture_output=True, text=True, timeout=60, env=env)  # a hang fails here
    return p, time.monotonic() - t0


def test_an_unknown_driver_exits_2_listing_the_known_ones_and_never_hangs(twin_dir, tmp_path):
    p, elapsed = _dt_run(_yaml(tmp_path, twin_dir, "{robot: {kind: ur_rtde_typo, host: 10.0.0.2}}"))
    print(f"unknown driver: exit {p.returncode} after {elapsed:.2f} s")
    assert p.returncode == 2, p.stderr[-2000:]
    err = p.stderr
    assert "runtime.yaml" in err and "drivers.robot.kind" in err and "ur_rtde_typo" in err
    assert "serial, sim" in err and "cobot_dt.drivers.robot" in err and "Traceback" not in err


def test_a_plugin_that_does_not_import_exits_2_naming_itself(twin_dir, tmp_path):
    """A package whose entry point names a module that is not there (a broken install)."""
    import os

    site = tmp_path / "site"
    info = site / "dt_broken_driver-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dt-broken-driver\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[cobot_dt.drivers.robot]\nbroken = dt_broken_driver.robot:Robot\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}
    p, _ = _dt_run(_yaml(tmp_path, twin_dir, "{robot: {kind: broken}}"), env)
    assert p.returncode == 2, p.stderr[-2000:]
    assert "dt-broken-driver" in p.stderr and "dt_broken_driver.robot" in p.stderr and "ModuleNotFoundError" in p.stderr


def test_a_stale_measurement_is_refused_counted_and_not_tested(twin_dir, tmp_path):
    """The MVS reading must match the command's arrival: one received (host clock) longer than
    max_measurement_age_s before the move returned is refused, counted and reported."""
    import dataclasses

    cfg = load_runtime_config(_yaml(tmp_path, twin_dir, "{camera: sim_images}"))
    cfg = cfg.model_copy(update={"max_measurement_age_s": 0.5})
    d = Daemon(cfg, CONFIGS)
    try:
        read = d.inst.camera.read
        d.latencies = []
        s = d.run(max_ticks=3)
        assert s["stale_measurements"] == 0 and len(d.latencies) == 3  # polled: read after the arrival
        assert all(lat >= 0 for lat in d.latencies)
        # a stream's frame from 2 s before (the clock's offset is what matters, not how long we wait)
        d.inst.camera.read = lambda: dataclasses.replace(read(), host_time=time.monotonic() - 2.0)
        d.store.flush()
        n_tests = d.store._query("SELECT COUNT(*) FROM t_stats")[0][0]
        s = d.run(max_ticks=4)
        assert s["stale_measurements"] == 4 and s["ticks"] == 7
        assert d.health()["stale_measurements"] == 4 and "stale measurement" in d.counters.last_problem
        d.store.flush()
        assert d.store._query("SELECT COUNT(*) FROM t_stats")[0][0] == n_tests == 3  # none tested
    finally:
        d.close()


def test_max_measurement_age_is_validated(tmp_path):
    for bad in ("0", "-1", ".inf", "3600"):
        cfg = tmp_path / "runtime.yaml"
        cfg.write_text(f"twin: x\nmax_measurement_age_s: {bad}\n")
        with pytest.raises(ConfigError) as ei:
            load_runtime_config(cfg)
        assert ei.value.key == "max_measurement_age_s"
