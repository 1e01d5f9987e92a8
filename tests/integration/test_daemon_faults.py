"""Fault injection on the daemon (issue: no maintenance request lost, no silent halt, no hang, an
operator in the loop). Each test reproduces one failure a reliability review found and checks
the invariants: no maintenance request lost, no committed row lost, the state on the bus matches
the store, the process exits or recovers as specified. Real parts throughout: the SQLite file
(a full database is SQLite's own SQLITE_FULL, reached through `PRAGMA max_page_count`), Zenoh
on loopback, PyBullet in DIRECT mode, `dt` in subprocesses for exits and signals. The long
versions run with `-m soak`."""
from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dt_kernel.errors import TwinError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig, MaintenanceConsumer
from dt_runtime.fabric.session import close_session, open_session
from dt_runtime.service.daemon import Daemon, RuntimeConfig
from dt_runtime.service.store import Store, StoreError
from tests.support.loopback import free_port, wait_until

SCENARIO, CELL = CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml"
BIG_FAULT = {"at_s": 0.0, "joint_offset_rad": [0, 1e-3, 0, 0, 0, 0]}  # every test fails: pages in ~10 tests


def cfg_of(twin_dir, tmp_path, *, port=None, faults=(), publish=False, **over) -> RuntimeConfig:
    d = {"twin": str(twin_dir), "store": str(tmp_path / "dt.sqlite"), "realtime": False,
         "sim": {"scenario": str(SCENARIO), "cell": str(CELL), "faults": list(faults)},
         "publish": publish,
         "bus": {"cell": "c1", "robot": "r1", "listen": [f"tcp/127.0.0.1:{free_port()}"],
                 "connect": [f"tcp/127.0.0.1:{port}"] if port else [], "republish_period_s": 0.2,
                 "health_period_s": 0.2}}
    for k, v in over.items():
        d[k] = {**d[k], **v} if isinstance(v, dict) and isinstance(d.get(k), dict) else v
    return RuntimeConfig.model_validate(d)




def consumer(port: int, group: str = "maintenance") -> MaintenanceConsumer:
    return MaintenanceConsumer(BusConfig(cell="c1", robot=f"maint-{group}", listen=[f"tcp/127.0.0.1:{port}"]),
                               group=group)


def paging_consistent(store: Store) -> dict:
    """The invariant a restart must find: a paging state has its episode's requests, one per
    consumer group; the stored statistics match the committed t-tests."""
    state = store.load_state()
    snap = state["data"] if state else {"state": "nominal", "episode": 0, "n_seen": 0}
    if snap["state"] in ("maintenance_requested", "halted"):
        reqs = store.outbox_of_episode(snap["episode"])
        assert reqs, f"state {snap['state']} without its requests"
    n = store.count("t_stats")
    assert snap["n_seen"] <= n <= snap["n_seen"] + 1, (snap["n_seen"], n)  # staged with the rows
    assert store.integrity_ok()
    return snap


# --- 1. a full disk during escalation ------------------------------------------------------------
@contextlib.contextmanager
def disk_full(store: Store):
    """No file of this process may grow (RLIMIT_FSIZE at the store's current WAL size, SIGXFSZ
    ignored): every write past it fails with EFBIG, which SQLite reports as a full disk or an
    I/O error, as on a full file system. Lifted on exit (the disk is freed)."""
    store.flush()
    wal = store.path.with_name(store.path.name + "-wal")
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (wal.stat().st_size, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def test_a_full_database_during_escalation_loses_no_request(twin_dir, tmp_path):
    port = free_port()
    cons = consumer(port)
    try:
        d = Daemon(cfg_of(twin_dir, tmp_path, port=port, faults=[BIG_FAULT], publish=True), CONFIGS)
        try:
            with disk_full(d.store):
                d.run(max_ticks=40)
                # checked while the disk is still full: the writer thread succeeds as soon as it is freed
                errors, h = d.store.write_errors_in_row, d.health()
                state, requests = d.escalator.state, list(d.paging.requests)
            assert errors > 0
            assert h["status"] == "degraded" and "store" in h["reason"]
            # every transition was refused by the store, so the machine did not move without it
            assert state == "nominal" and requests == []
            d.run(max_ticks=40)  # the disk was freed
            assert d.escalator.state == "maintenance_requested"
            assert cons.wait_for(1, timeout=20)
            snap = paging_consistent(d.store)
            assert [r["dst"] for r in d.store.transitions()] == ["suspect", "out_of_control", "maintenance_requested"]
            assert cons.requests[0]["episode"] == snap["episode"] == 1
            assert wait_until(lambda: not d.store.outbox_pending(), 20)  # acked by the consumer
        finally:
            d.close()
    finally:
        cons.close()


# --- 2. SIGKILL at every step of a transition -----------------------------------------------------
KILLER = r"""
import os, signal, sys
from pathlib import Path
from dt_runtime.common.paths import CONFIGS
from dt_runtime.service.daemon import Daemon, RuntimeConfig

cfg = RuntimeConfig.model_validate_json(Path(sys.argv[1]).read_text())
step = int(sys.argv[2])
d = Daemon(cfg, CONFIGS)

class Killer:
    '''The store's connection, killed (SIGKILL) before statement `step` of the transaction that
    enters maintenance_requested; `step` past its COMMIT kills right after the commit.'''
    def __init__(self, db):
        self.db, self.armed, self.n = db, False, 0
    def execute(self, sql, *a):
        if sql.startswith("INSERT INTO transitions") and "maintenance_requested" in a[0]:
            self.armed = True
        if self.armed:
            if self.n == step:
                os.kill(os.getpid(), signal.SIGKILL)
            self.n += 1
        return self.db.execute(sql, *a)
    def __getattr__(self, name):
        return getattr(self.db, name)

d.store._db = Killer(d.store._db)
d.run(max_ticks=200)
if d.store._db.armed and d.store._db.n <= step:  # past the commit: die before anything else
    os.kill(os.getpid(), signal.SIGKILL)
print("not killed", d.escalator.state)
"""

#: statements of the paging transaction, each killed before it runs: 0 the transition row, 1 the
#: state row, 2 and 3 the outbox rows of the two consumer groups, 4 COMMIT, 5 the first statement after it
KILL_STEPS = range(0, 6)


@pytest.mark.parametrize("step", KILL_STEPS)
def test_sigkill_at_every_step_of_a_paging_transition(twin_dir, tmp_path, step):
    cfg = cfg_of(twin_dir, tmp_path, faults=[BIG_FAULT],
                 bus={"consumer_groups": ["maintenance", "mes"]})
    (tmp_path / "cfg.json").write_text(cfg.model_dump_json())
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    p = subprocess.run([sys.executable, str(script), str(tmp_path / "cfg.json"), str(step)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == -signal.SIGKILL, p.stdout + p.stderr[-3000:]
    committed = step >= 5
    with Store(tmp_path / "dt.sqlite") as st:
        snap = st.load_state()["data"]
        dsts = [r["dst"] for r in st.transitions()]
        outbox = st.outbox_pending()
    assert ("maintenance_requested" in dsts) == committed
    assert (snap["state"] == "maintenance_requested") == committed
    assert len(outbox) == (2 if committed else 0)  # both groups' copies, or none
    # The restarted daemon finds a consistent store and pages (again or for the first time).
    d = Daemon(cfg, CONFIGS)
    try:
        paging_consistent(d.store)
        d.run(max_ticks=30)
        assert d.escalator.state == "maintenance_requested"
        reqs = d.store.outbox_of_episode(d.escalator.episode)
        assert sorted(r.payload["group"] for r in reqs) == ["maintenance", "mes"]
        assert len({r.payload["uid"] for r in reqs}) == 1
    finally:
        d.close()


def test_a_paging_state_without_its_request_is_reconciled_at_start_up(twin_dir, tmp_path):
    """A store written by the old three-commit code and killed between save_state and outbox_add."""
    cfg = cfg_of(twin_dir, tmp_path)
    d = Daemon(cfg, CONFIGS)
    snap = d.escalator.snapshot() | {"state": "maintenance_requested", "version": 1}
    snap.pop("episode")
    d.close()
    with Store(tmp_path / "dt.sqlite") as st:
        st.save_state("escalation", snap)
        assert st.outbox_pending() == []
    for _ in range(2):  # the second start finds the request and adds none
        d = Daemon(cfg, CONFIGS)
        d.close()
        with Store(tmp_path / "dt.sqlite") as st:
            pending = st.outbox_pending()
            assert len(pending) == 1 and pending[0].payload["reconciled"] is True
            assert pending[0].payload["episode"] == 0


# --- 3. consumers: absent then present, two groups ------------------------------------------------
def test_every_consumer_group_receives_the_request_and_a_late_one_still_does(twin_dir, tmp_path):
    port = free_port()
    maint = consumer(port, "maintenance")
    d = Daemon(cfg_of(twin_dir, tmp_path, port=port, faults=[BIG_FAULT], publish=True,
                      bus={"consumer_groups": ["maintenance", "mes"]}), CONFIGS)
    mes = None
    try:
        d.run(max_ticks=30)
        assert d.escalator.state == "maintenance_requested"
        assert maint.wait_for(1, timeout=20)
        assert wait_until(lambda: len(d.store.outbox_pending()) == 1, 20)  # the absent group's copy waits
        assert d.store.outbox_pending()[0].payload["group"] == "mes"
        mes = MaintenanceConsumer(BusConfig(cell="c1", robot="mes", connect=[f"tcp/127.0.0.1:{port}"],
                                            listen=[f"tcp/127.0.0.1:{free_port()}"]), group="mes")
        assert mes.wait_for(1, timeout=20)
        assert wait_until(lambda: not d.store.outbox_pending(), 20)
        assert maint.requests[0]["uid"] == mes.requests[0]["uid"] and len(maint.requests) == 1
    finally:
        d.close()
        maint.close()
        if mes:
            mes.close()


# --- 4. the operator: dt ack, then a second fault pages again -------------------------------------
def test_operator_ack_returns_to_nominal_and_a_second_fault_pages_again(twin_dir, tmp_path, capsys):
    second = {"at_s": 400.0, "joint_offset_rad": [0, 0, 1e-3, 0, 0, 0]}
    d = Daemon(cfg_of(twin_dir, tmp_path, faults=[BIG_FAULT, second]), CONFIGS)
    store = str(tmp_path / "dt.sqlite")
    try:
        d.run(max_ticks=30)
        assert d.escalator.state == "maintenance_requested" and d.escalator.episode == 1
        # a delivery confirmation changes nothing of the state
        assert main(["ack", "--store", store, "--by", "ana", "--note", "seen", "--delivered-only", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["applied"] is True
        assert main(["ack", "--store", store, "--by", "ana", "--note", "joint 2 re-referenced", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["kind"] == "done"
        assert wait_until(lambda: len(d.paging.actions) == 1, 10)  # the housekeeper picked it up
        d.tick()
        assert d.escalator.state == "nominal"
        last = d.store.transitions()[-1]
        assert last["dst"] == "nominal" and last["evidence"]["by"] == "ana"
        assert last["evidence"]["note"] == "joint 2 re-referenced"
        act = d.store.actions()[-1]
        assert act.applied_at is not None and act.result == "applied: maintenance_requested -> nominal"
        d.world.inject_joint_offset([-v for v in BIG_FAULT["joint_offset_rad"]])  # what the maintenance did
        while d.world.t < 400.0 and d.escalator.state == "nominal":  # no page before the second fault
            d.tick()
        d.run(max_ticks=40)
        assert d.escalator.state == "maintenance_requested" and d.escalator.episode == 2
        assert len(d.store.outbox_of_episode(2)) == 1
        # a 'done' naming the first episode's request does not clear the second
        first = d.store.outbox_of_episode(1)[0].id
        assert main(["ack", "--store", store, "--by", "bo", "--note", "old", "--request", str(first)]) == 0
        assert wait_until(lambda: len(d.paging.actions) == 1, 10)
        d.tick()
        assert d.escalator.state == "maintenance_requested"
        assert "not of the open episode" in d.store.actions()[-1].result
    finally:
        d.close()


def test_done_over_the_bus_is_checked_against_the_outbox(twin_dir, tmp_path):
    port = free_port()
    cons = consumer(port)
    d = Daemon(cfg_of(twin_dir, tmp_path, port=port, faults=[BIG_FAULT], publish=True), CONFIGS)
    try:
        d.run(max_ticks=30)
        assert cons.wait_for(1, timeout=20)
        req = cons.requests[0]
        prefix = "dt/c1/r1"
        cons.done(prefix, req["id"], "not-the-uid", "eve", "forged")  # wrong uid: ignored
        cons.done(prefix, req["id"], req["uid"], "ana", "gearbox replaced")
        assert wait_until(lambda: any(a.by == "ana" for a in d.store.actions()), 20)
        assert not any(a.by == "eve" for a in d.store.actions())
        assert wait_until(lambda: len(d.paging.actions) >= 1, 10)
        d.tick()
        assert d.escalator.state == "nominal"
        assert d.store.transitions()[-1]["evidence"]["note"] == "gearbox replaced"
    finally:
        d.close()
        cons.close()


# --- 5. halts: a model asking for 50 mm, a NaN model ----------------------------------------------
def test_a_model_refused_on_every_command_halts_on_the_bus_and_the_run_ends(twin_dir, tmp_path):
    port = free_port()
    seen: list[dict] = []
    listener = open_session(BusConfig(cell="c1", robot="watch", listen=[f"tcp/127.0.0.1:{port}"]))
    sub = listener.declare_subscriber("dt/**/health", lambda s: seen.append(json.loads(s.payload.to_bytes())))
    # A limit of 1 um: every correction of this twin (tens of um) is "too big", as 50 mm would be
    # under the default bound. Simulated time: the run must still end at its duration.
    d = Daemon(cfg_of(twin_dir, tmp_path, port=port, publish=True, limits={"max_correction_m": 1e-6}), CONFIGS)
    try:
        s = d.run(duration_s=30.0)
        assert s["ticks"] == 0 and s["refused_commands"] >= 10
        assert s["state"] == "halted" and "every command refused" in s["halt_reason"]
        assert wait_until(lambda: any(h["status"] == "halted" for h in seen), 20)
        h = next(h for h in seen if h["status"] == "halted")
        assert "exceeds the bound" in h["reason"] and h["escalation"] == "halted"
        stored = d.store.load_state()["data"]
        assert stored["state"] == "halted" and stored["halt_reason"] == s["halt_reason"]
        reqs = d.store.outbox_of_episode(stored["episode"])
        assert len(reqs) == 1 and reqs[0].payload["kind"] == "halt"
    finally:
        d.close()
        sub.undeclare()
        close_session(listener, 3.0)


def test_a_halt_from_refusals_resumes_when_commands_go_through(twin_dir, tmp_path):
    d = Daemon(cfg_of(twin_dir, tmp_path, halt={"after_refused": 3}), CONFIGS)
    try:
        real = d.corrector.__call__
        d.corrector = _Refusing(real, n=5)
        d.run(max_ticks=5)
        assert d.escalator.state == "halted"
        d.run(max_ticks=3)
        assert d.escalator.state == "nominal"
        assert [r["dst"] for r in d.store.transitions()] == ["halted", "nominal"]
    finally:
        d.close()


class _Refusing:
    """The daemon's corrector, refusing its first n commands."""

    def __init__(self, real, n):
        self.real, self.n = real, n
        self.uncorrected = real.__self__.uncorrected

    def __call__(self, *a):
        from dt_runtime.twin.bounds import CorrectionFault

        if self.n > 0:
            self.n -= 1
            raise CorrectionFault("correction 50.000 mm exceeds the bound 2.000 mm")
        return self.real(*a)


class _BlindCamera:
    """The daemon's camera, refusing every reading while `blind` (the rigid body out of view)."""

    def __init__(self, real):
        self.real, self.blind, self.reads = real, True, 0

    def read(self):
        from drivers.base import RigReading

        self.reads += 1
        if self.blind:
            return RigReading(None, 0.0, refused="rigid body 'tool' (id 1) not tracked (tracking-valid flag off)")
        return self.real.read()

    def __getattr__(self, name):
        return getattr(self.real, name)


def test_a_camera_refused_for_longer_than_the_limit_halts_pages_and_resumes(twin_dir, tmp_path):
    """The probe's finding: a blind camera left the daemon `degraded` for good, escalation
    nominal, no page. Now: refused readings for `halt.after_camera_refused_s` (simulated
    seconds here) halt and page; the arm does not move while halted (it would move unmonitored);
    the first accepted reading resumes."""
    d = Daemon(cfg_of(twin_dir, tmp_path, halt={"after_camera_refused_s": 20.0}), CONFIGS)
    try:
        cam = d.inst.camera = _BlindCamera(d.inst.camera)
        d.run(max_ticks=2)  # a short blindness (a person in the view; a move is a few seconds) is not a halt
        h = d.health()
        assert d.escalator.state == "nominal" and h["status"] == "degraded" and 0 < h["camera_untested_s"] < 20
        d.run(max_ticks=200)
        s = d.summary()
        assert s["state"] == "halted" and "no MVS reading tested for" in s["halt_reason"]
        assert "after_camera_refused_s 20 s" in s["halt_reason"] and "not tracked" in s["halt_reason"]
        halted_for = float(s["halt_reason"].split("tested for ")[1].split(" s")[0])
        assert 20.0 <= halted_for < 30.0  # the limit plus at most one move
        stored = d.store.load_state()["data"]
        reqs = d.store.outbox_of_episode(stored["episode"])  # paged: the halt's request is in the outbox
        assert stored["state"] == "halted" and len(reqs) == 1 and reqs[0].payload["kind"] == "halt"
        assert d.health()["status"] == "halted"
        ticks, reads = d.counters.ticks, cam.reads
        d.run(max_ticks=20)  # halted: the camera is read once a tick, the arm is not moved
        assert d.counters.ticks == ticks and cam.reads == reads + 20 and d.escalator.state == "halted"
        cam.blind = False
        d.run(max_ticks=5)
        assert d.escalator.state == "nominal" and d.counters.ticks > ticks and d.health()["camera_untested_s"] is None
        assert [t["dst"] for t in d.store.transitions()] == ["halted", "nominal"]
    finally:
        d.close()


def _nan_twin(twin_dir: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(twin_dir, dst)
    for npz in dst.rglob("*.npz"):
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: (np.full_like(v, np.nan) if v.dtype.kind == "f" else v) for k, v in z.items()}
        np.savez(npz, **arrays)
    return dst


def test_a_nan_model_stops_the_start_with_a_config_error(twin_dir, tmp_path):
    bad = _nan_twin(twin_dir, tmp_path / "nan_twin")
    with pytest.raises(TwinError, match="NaN|nan|finite"):
        Daemon(cfg_of(bad, tmp_path), CONFIGS)
    # nothing left open: the same store can be taken at once
    with Store(tmp_path / "dt.sqlite", exclusive=True):
        pass


def test_a_part_that_fails_to_open_closes_the_parts_opened_before_newest_first(twin_dir, tmp_path, monkeypatch):
    """The daemon's parts are registered on one stack as they open: the drivers failing to open
    close the bus (and the services on its session) and the store, in that order (newest first)."""
    from dt_kernel.errors import DriverError
    from dt_runtime.service import daemon as daemon_mod

    closed: list[str] = []

    def recording(cls, name):
        class Recorded(cls):
            def close(self, *a, **k):
                closed.append(name)
                return super().close(*a, **k)
        return Recorded

    for attr, name in (("Store", "store"), ("Bus", "bus")):
        monkeypatch.setattr(daemon_mod, attr, recording(getattr(daemon_mod, attr), name))

    def failing_cell(*args):
        args[-1].callback(closed.append, "world")  # what the cell opened before a driver failed
        raise DriverError("the camera does not answer")

    monkeypatch.setattr(daemon_mod, "open_cell", failing_cell)
    with pytest.raises(DriverError, match="does not answer"):
        Daemon(cfg_of(twin_dir, tmp_path, publish=True), CONFIGS)
    assert closed == ["world", "bus", "store"]
    with Store(tmp_path / "dt.sqlite", exclusive=True):  # released
        pass


def test_out_of_control_commands_uncorrected_or_halts_by_policy(twin_dir, tmp_path):
    d = Daemon(cfg_of(twin_dir, tmp_path, faults=[BIG_FAULT]), CONFIGS)
    try:
        d.run(max_ticks=30)
        assert d.escalator.state == "maintenance_requested" and d.counters.uncorrected > 0
        rows = d.store._query("SELECT dx, dy, dz FROM corrections ORDER BY id DESC LIMIT 3")
        assert all(r == (0.0, 0.0, 0.0) for r in rows)  # the untrusted correction is not applied
    finally:
        d.close()
    d = Daemon(cfg_of(twin_dir, tmp_path / "h", faults=[BIG_FAULT], halt={"on_untrusted": "halt"}), CONFIGS)
    try:
        d.run(max_ticks=30)
        assert d.escalator.state == "halted" and d.escalator.halt_sticky
        n = d.counters.ticks
        d.run(max_ticks=5)
        assert d.counters.ticks == n  # it does not move until the operator confirms
        d.acknowledge_maintenance("fixed", by="ana")
        d.tick()
        assert d.escalator.state == "nominal" and d.counters.ticks == n + 1
    finally:
        d.close()


# --- 6. bounds in the config ----------------------------------------------------------------------
@pytest.mark.parametrize("yaml_text, key", [
    ("limits: {max_correction_m: .inf}", "max_correction_m"),
    ("limits: {max_correction_m: 2.0}", "max_correction_m"),
    ("limits: {workspace_min_m: [1.7, -0.8, 0.05]}", "limits"),
    ("path: {box_min_m: [1.0, 0, 0.5], box_max_m: [0.7, 0.3, 0.8]}", "path"),
    ("path: {speeds: []}", "speeds"),
    ("path: {speeds: [5.0]}", "speeds"),
    ("path: {box_min_m: [0.65, -0.3, 0.25], box_max_m: [1.9, 0.3, 0.85]}", "workspace"),
    ("escalation: {confirm_n: 1000000000}", "confirm_n"),
    ("drivers: {robot: kuka}", "kuka"),
])
def test_config_bounds_are_refused_with_the_key_named(tmp_path, capsys, yaml_text, key):
    cfg = tmp_path / "runtime.yaml"
    cfg.write_text(f"twin: x\n{yaml_text}\n")
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "runtime.yaml" in err and key in err and "Traceback" not in err


# --- 7. start-up failure and SIGTERM: exits within seconds ----------------------------------------
def _dt(*args: str) -> list[str]:
    return [sys.executable, "-m", "dt_runtime.cli.main", *args]


def _runtime_yaml(tmp_path: Path, twin_dir: Path, extra: str = "") -> Path:
    cfg = tmp_path / "runtime.yaml"
    cfg.write_text(f"twin: {twin_dir}\nstore: {tmp_path / 'dt.sqlite'}\nrate_hz: 20\n"
                   f"bus: {{listen: [tcp/127.0.0.1:{free_port()}]}}\n"
                   f"sim: {{scenario: {SCENARIO}, cell: {CELL}}}\n{extra}")
    return cfg


def test_a_missing_serial_port_exits_non_zero_within_seconds(twin_dir, tmp_path):
    cfg = _runtime_yaml(tmp_path, twin_dir, "drivers: {robot: {kind: serial, url: /dev/dt-no-such-port}}\n")
    t0 = time.monotonic()
    p = subprocess.run(_dt("run", "--config", str(cfg)), capture_output=True, text=True, timeout=60)
    elapsed = time.monotonic() - t0
    assert p.returncode == 2, p.stderr[-2000:]
    assert "dt-no-such-port" in p.stderr
    print(f"start-up failure: exit {p.returncode} after {elapsed:.2f} s")
    with Store(tmp_path / "dt.sqlite", exclusive=True):  # the store was released
        pass


def test_one_daemon_per_store(twin_dir, tmp_path):
    cfg = cfg_of(twin_dir, tmp_path)
    d = Daemon(cfg, CONFIGS)
    try:
        with pytest.raises(StoreError, match="in use by pid"):
            Daemon(cfg, CONFIGS)
    finally:
        d.close()
    Daemon(cfg, CONFIGS).close()  # released on close


def test_sigterm_with_a_silent_device_stops_within_the_bound(twin_dir, tmp_path):
    from drivers.simulated.devices import SimWorld
    from emulators.serial import ControllerEmulator

    world = SimWorld(SCENARIO, CELL)
    emu = ControllerEmulator(world.cell.plant)
    serial = f"{{kind: serial, url: {emu.port}, timeout_s: 2.0, move_timeout_s: 30.0, retries: 3}}"
    cfg = _runtime_yaml(tmp_path, twin_dir, f"drivers: {{robot: {serial}}}\npublish: false\n")
    proc = subprocess.Popen(_dt("run", "--config", str(cfg), "--json"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        moved = wait_until(lambda: proc.poll() is not None or _count(tmp_path / "dt.sqlite", "commands") >= 3, 120)
        # a daemon that stopped on its own says why (rather than a 120 s wait in vain)
        assert moved and proc.poll() is None, ("the daemon never moved" if not moved else
                                               f"the daemon exited {proc.returncode}: {proc.communicate()[1][-3000:]}")
        emu.pause(600)  # deaf and mute: the next MOVL gets no reply for 10 minutes
        time.sleep(1.0)  # a move is in flight (20 Hz ticks)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
        emu.stop()
    print(f"SIGTERM with a silent device: exit {proc.returncode} after {elapsed:.2f} s")
    assert elapsed < 10.0, err[-3000:]  # the default stop_timeout_s is 8 s; the old code took 120 s
    assert proc.returncode == 0  # a clean stop: the move was aborted, not the hard exit (75)
    with Store(tmp_path / "dt.sqlite") as st:
        assert st.integrity_ok()


def _count(path: Path, table: str) -> int:
    if not path.exists():
        return 0
    try:
        with Store(path) as st:
            return st.count(table)
    except StoreError:
        return 0


# --- 8. the systemd watchdog ----------------------------------------------------------------------
def test_sd_notify_ready_watchdog_and_stopping(twin_dir, tmp_path, monkeypatch):
    sock_path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(sock_path)
    srv.settimeout(0.1)
    monkeypatch.setenv("NOTIFY_SOCKET", sock_path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    got: list[str] = []
    stop = threading.Event()

    def read():
        while not stop.is_set():
            try:
                got.append(srv.recv(256).decode())
            except TimeoutError:
                pass

    th = threading.Thread(target=read, daemon=True)
    th.start()
    d = Daemon(cfg_of(twin_dir, tmp_path, rate_hz=20.0, realtime=True), CONFIGS)
    try:
        d.run(duration_s=1.5)
    finally:
        d.close()
        time.sleep(0.3)
        stop.set()
        th.join()
        srv.close()
    assert got[0] == "READY=1" and "WATCHDOG=1" in got and got[-1] == "STOPPING=1"


# --- 9. retention -------------------------------------------------------------------------------
def test_retention_prunes_high_rate_rows_and_keeps_transitions_and_requests(twin_dir, tmp_path):
    d = Daemon(cfg_of(twin_dir, tmp_path, faults=[BIG_FAULT], retention={"max_age_s": 30.0}), CONFIGS)
    try:
        d.run(max_ticks=40)
        d.store.flush()
        n_before = d.store.count("t_stats")
        deleted = d.prune()
        d.store.flush()
        t_min = d.store._query("SELECT MIN(t) FROM t_stats")[0][0]
        assert deleted > 0 and d.store.count("t_stats") < n_before
        assert t_min >= d.world.t - 30.0
        assert len(d.store.transitions()) == 3 and d.store.outbox_of_episode(1)
    finally:
        d.close()


# --- 10. kill -9 at random moments, over and over ---------------------------------------------------
def _kill_cycles(twin_dir: Path, tmp_path: Path, cycles: int, seed: int) -> list[str]:
    """`dt run` on the simulated clock with a fault that pages, killed (SIGKILL) at a random
    moment of each run; after every kill the store must be consistent (a paging state has its
    requests, the statistics match the committed t-tests, the transitions form one path)."""
    rng = np.random.default_rng(seed)
    fault = "[{at_s: 120, joint_offset_rad: [0, 1.0e-3, 0, 0, 0, 0]}]"
    cfg = tmp_path / "runtime.yaml"
    cfg.write_text(f"twin: {twin_dir}\nstore: {tmp_path / 'dt.sqlite'}\nrealtime: false\npublish: false\n"
                   f"sim: {{scenario: {SCENARIO}, cell: {CELL}, faults: {fault}}}\n"
                   "bus: {consumer_groups: [maintenance, mes]}\n")
    db = tmp_path / "dt.sqlite"
    for _ in range(cycles):
        proc = subprocess.Popen(_dt("run", "--config", str(cfg)), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        assert wait_until(lambda p=proc: _count(db, "commands") > 0 or p.poll() is not None, 120)
        time.sleep(float(rng.uniform(0.0, 1.5)))
        proc.kill()
        proc.wait(timeout=30)
        with Store(db) as st:
            paging_consistent(st)
            tr = st.transitions(1000)
            for a, b in zip(tr, tr[1:]):
                assert a["dst"] == b["src"], (a, b)
    with Store(db) as st:
        snap = st.load_state()["data"]
        assert st.count("t_stats") > 0
        if snap["state"] in ("maintenance_requested", "halted"):
            groups = sorted(r.payload["group"] for r in st.outbox_of_episode(snap["episode"]))
            assert groups == ["maintenance", "mes"]
        return [t["dst"] for t in st.transitions(1000)]


def test_kill_9_at_random_moments_keeps_the_store_consistent(twin_dir, tmp_path):
    _kill_cycles(twin_dir, tmp_path, cycles=3, seed=1)


@pytest.mark.soak
def test_kill_9_at_random_moments_many_times(twin_dir, tmp_path):
    dsts = _kill_cycles(twin_dir, tmp_path, cycles=30, seed=2)
    assert "maintenance_requested" in dsts  # the kills fell before, during and after paging


# --- the paced loop's scheduling -----------------------------------------------------------------
@pytest.mark.parametrize("priority", [0, 10])
def test_the_paced_loop_runs_fifo_when_allowed_and_gives_the_policy_back(twin_dir, tmp_path, priority):
    """`rt_priority`: the paced loop's thread SCHED_FIFO while it runs (when the user may have it),
    its own policy after; 0 never."""
    import os

    try:  # may this user have SCHED_FIFO here? (root in the test container; a user may not)
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, *old)
        allowed = True
    except (AttributeError, PermissionError, OSError):
        allowed = False
    seen: list[int] = []
    d = Daemon(cfg_of(twin_dir, tmp_path, rate_hz=50.0, realtime=True, rt_priority=priority), CONFIGS)
    before = os.sched_getscheduler(0)
    tick = d.tick

    def spy() -> None:
        seen.append(os.sched_getscheduler(0))
        tick()

    d.tick = spy
    try:
        d.run(duration_s=0.3)
    finally:
        d.close()
    assert seen and d.realtime_thread == (allowed and priority > 0)
    assert set(seen) == {os.SCHED_FIFO if d.realtime_thread else before}
    assert os.sched_getscheduler(0) == before
