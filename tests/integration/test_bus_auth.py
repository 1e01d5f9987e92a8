"""Who may ack, clear or raise a maintenance request (issue 22, item 7): signed messages, private files.

The black-box probe: a peer on the default loopback bus read a request's uid off the bus,
published `.../maintenance/done/1`, and the daemon applied `maintenance_requested -> nominal`
"by mallory"; the store and its lock were 0644. Real parts here: Zenoh sessions on loopback (the
daemon's; a consumer holding the service's key; "mallory", a local peer without it, connected to
the daemon's endpoint as the probe was), the SQLite store and the key file on disk; `dt run`,
`dt consume` and `dt ack --bus` as shipped (configs/bus.yaml's settings, the key at its default
place in the suite's own config directory: tests/conftest.py)."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sqlite3
import stat
import subprocess
import sys
import time

import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig, MaintenanceConsumer
from dt_runtime.fabric.auth import AuthConfig, Signer, default_key_file
from dt_runtime.fabric.session import close_session, open_session, put_json
from dt_runtime.service.daemon import Daemon, RuntimeConfig
from dt_runtime.service.store import Store
from tests.support.loopback import free_port, wait_until

ROOT = CONFIGS.parent
BIG_FAULT = {"at_s": 0.0, "joint_offset_rad": [0, 1e-3, 0, 0, 0, 0]}  # every test fails: pages in ~10 tests


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_a_local_peer_without_the_key_cannot_ack_clear_or_forge(twin_dir, tmp_path):
    dport = free_port()
    d = Daemon(RuntimeConfig.model_validate({
        "twin": str(twin_dir), "store": str(tmp_path / "dt.sqlite"), "realtime": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml"),
                "faults": [BIG_FAULT]},
        "bus": {"cell": "c1", "robot": "r1", "listen": [f"tcp/127.0.0.1:{dport}"], "republish_period_s": 0.2,
                "health_period_s": 0.2}}), CONFIGS)
    stack = contextlib.ExitStack()
    stack.callback(d.close)

    def peer(name: str) -> BusConfig:
        return BusConfig(cell="c1", robot=name, listen=[f"tcp/127.0.0.1:{free_port()}"],
                         connect=[f"tcp/127.0.0.1:{dport}"])

    seen: list[dict] = []
    with stack:
        cons = MaintenanceConsumer(peer("maint"), auto_ack=False)
        stack.callback(cons.close)
        mallory = open_session(peer("mallory"))
        stack.callback(close_session, mallory, 3.0)
        sub = mallory.declare_subscriber("dt/**/maintenance/request",
                                         lambda s: seen.append(json.loads(s.payload.to_bytes())))
        stack.callback(sub.undeclare)
        d.run(max_ticks=30)
        assert d.escalator.state == "maintenance_requested"
        assert wait_until(lambda: seen, 20)  # mallory reads the request, uid and all, as the probe did
        oid, uid = seen[0]["id"], seen[0]["uid"]
        prefix = "dt/c1/r1"
        # 1. Acks: unsigned, signed with mallory's own key, and a real signature recorded an hour ago.
        ack_key, done_key = f"{prefix}/maintenance/ack/{oid}", f"{prefix}/maintenance/done/{oid}"
        own = Signer(AuthConfig(key_file=str(tmp_path / "mallory" / "bus.key")))
        put_json(mallory, ack_key, {"id": oid, "uid": uid, "group": "maintenance", "t": time.time()})
        put_json(mallory, ack_key, own.sign(ack_key, {"id": oid, "uid": uid, "group": "maintenance", "t": time.time()}))
        recorded = d.bus.signer.sign(ack_key, {"id": oid, "uid": uid, "group": "maintenance", "t": time.time() - 3600})
        put_json(mallory, ack_key, recorded)
        assert wait_until(lambda: d.bus.refused >= 3, 20), d.bus.last_refused
        assert "signed 3600 s ago" in d.bus.last_refused
        assert [o.id for o in d.store.outbox_pending()] == [oid]  # still not delivered: republished
        # 2. Clear: the probe's 'done' "by mallory".
        put_json(mallory, done_key, {"id": oid, "uid": uid, "by": "mallory", "note": "cleared", "t": time.time()})
        assert wait_until(lambda: d.bus.refused >= 4 and "done" in (d.bus.last_refused or ""), 20)
        d.run(max_ticks=3)
        assert d.escalator.state == "maintenance_requested"
        assert not any(a.by == "mallory" for a in d.store.actions())  # nothing recorded as done
        h = d.health()
        assert h["bus_refused"] == 4 and "not signed" in h["bus_last_refused"] and done_key in h["bus_last_refused"]
        # 3. Forge: a request of mallory's own; the consumer does not take it.
        forged = {"id": 99, "uid": "f" * 32, "group": "maintenance", "episode": 9, "kind": "halt",
                  "reason": "halted: replace the gearbox", "cell": "c1", "robot": "r1", "created": time.time()}
        put_json(mallory, f"{prefix}/maintenance/request", forged)
        assert wait_until(lambda: cons.refused >= 1, 20)
        assert "not signed" in cons.last_refused
        assert cons.wait_for(1, 20) and [r["uid"] for r in cons.requests] == [uid]
        # With the service's key: the consumer acks and confirms, and the daemon applies it.
        cons.ack(prefix, oid, uid)
        assert wait_until(lambda: not d.store.outbox_pending(), 20)
        cons.done(prefix, oid, uid, "ana", "gearbox replaced")
        assert wait_until(lambda: any(a.by == "ana" for a in d.store.actions()), 20)
        assert wait_until(lambda: (d.tick(), d.escalator.state)[1] == "nominal", 20)
        assert d.store.transitions()[-1]["evidence"]["by"] == "ana" and d.bus.refused == 4


def test_dt_run_consume_and_ack_as_shipped_and_without_the_key(twin_dir, tmp_path, monkeypatch, capsys):
    """`dt run` on configs/bus.yaml's settings (another port), `dt consume` and `dt ack --bus` as the
    service's user: the key at its default place is made by the daemon and used by both. The same
    `dt ack` as another user (no key) exits 2 naming the key file."""
    import yaml

    shipped = yaml.safe_load((CONFIGS / "bus.yaml").read_text())
    assert "auth" not in shipped  # the defaults are what is tested
    port = free_port()
    bus = {**shipped, "listen": [f"tcp/127.0.0.1:{port}"], "republish_period_s": 0.2}
    client = tmp_path / "bus.yaml"
    client.write_text(yaml.safe_dump({**shipped, "listen": [f"tcp/127.0.0.1:{free_port()}"],
                                      "connect": [f"tcp/127.0.0.1:{port}"]}))
    runtime = tmp_path / "runtime.yaml"
    runtime.write_text(yaml.safe_dump({
        "twin": str(twin_dir), "store": str(tmp_path / "dt.sqlite"), "rate_hz": 10, "realtime": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml"),
                "faults": [BIG_FAULT]}, "bus": {**bus, "health_period_s": 0.5}}))
    dt = [sys.executable, "-m", "dt_runtime.cli.main"]
    run = subprocess.Popen([*dt, "run", "--config", str(runtime), "--duration", "1e6"], cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        c = subprocess.run([*dt, "consume", "--bus", str(client), "--count", "1", "--duration", "120", "--json"],
                           cwd=ROOT, capture_output=True, text=True, timeout=180)
        assert c.returncode == 0, c.stderr[-2000:]
        req = json.loads(c.stdout.splitlines()[0])
        assert req["robot"] == "r1" and req["sig"].startswith("hmac-sha256:")
        assert _mode(default_key_file()) == 0o600 and _mode(default_key_file().parent) == 0o700
        ack = ["ack", "--bus", str(client), "--request", str(req["id"]), "--uid", req["uid"], "--by", "ana",
               "--note", "joint 2 re-referenced", "--wait", "60", "--json"]
        with monkeypatch.context() as m:  # another user: no key of the service's
            m.setenv("XDG_CONFIG_HOME", str(tmp_path / "another-user"))
            assert main(ack) == 2
        err = capsys.readouterr().err
        assert "bus.key" in err and "missing" in err, err[-2000:]
        assert main(ack) == 0
        assert json.loads(capsys.readouterr().out)["applied"] is True
    finally:
        run.send_signal(signal.SIGTERM)
        _, err = run.communicate(timeout=60)
    assert run.returncode == 0, err[-2000:]
    with Store(tmp_path / "dt.sqlite") as st:
        # the fault goes on, so the machine may page again after the operator's 'done'
        assert any(t["dst"] == "nominal" and t["evidence"].get("by") == "ana" for t in st.transitions(1000))
        assert [a.by for a in st.actions()] == ["ana"]
    for f in ("dt.sqlite", "dt.sqlite.lock"):
        assert _mode(tmp_path / f) == 0o600, f


def test_store_lock_and_key_files_are_created_private_whatever_the_umask(tmp_path, caplog):
    old = os.umask(0)  # what a umask would leave: SQLite's own default is 0644
    try:
        with Store(tmp_path / "new.sqlite", exclusive=True) as st:
            st.outbox_add("dt/c/r/maintenance/request", {"uid": "u"})
            files = ["new.sqlite", "new.sqlite.lock", "new.sqlite-wal", "new.sqlite-shm"]
            assert {f: _mode(tmp_path / f) for f in files} == dict.fromkeys(files, 0o600)
        signer = Signer(AuthConfig(key_file=str(tmp_path / "keys" / "bus.key")))
        assert _mode(signer.path) == 0o600 and _mode(signer.path.parent) == 0o700
        assert len(signer.path.read_text().strip()) == 64
    finally:
        os.umask(old)
    # An existing store that others could read (an older version's, 0644): made 0600, with a warning.
    sqlite3.connect(tmp_path / "old.sqlite").execute("CREATE TABLE x (a)").connection.close()
    os.chmod(tmp_path / "old.sqlite", 0o644)
    with caplog.at_level(logging.WARNING, logger="dt.files"), Store(tmp_path / "old.sqlite"):
        pass
    assert _mode(tmp_path / "old.sqlite") == 0o600
    assert any("was mode 0644" in r.getMessage() and "old.sqlite" in r.getMessage() for r in caplog.records)
    # A key others could read is refused: it may have been copied.
    os.chmod(signer.path, 0o644)
    with pytest.raises(ConfigError, match=r"mode 0644.*may have been copied") as ei:
        Signer(AuthConfig(key_file=str(signer.path)))
    assert ei.value.key == "bus.auth.key_file"
    os.chmod(signer.path, 0o600)
    (tmp_path / "short.key").write_text("abc")
    os.chmod(tmp_path / "short.key", 0o600)
    with pytest.raises(ConfigError, match="at least 16 bytes"):
        Signer(AuthConfig(key_file=str(tmp_path / "short.key")))


def test_a_signature_binds_the_key_expression_and_every_field(tmp_path):
    s = Signer(AuthConfig(key_file=str(tmp_path / "k")))
    key = "dt/c1/r1/maintenance/done/3"
    msg = json.loads(s.sign(key, {"id": 3, "uid": "u", "by": "ana", "note": "ok", "t": time.time()}))
    assert s.check(key, msg, fresh=True) is None
    assert "does not match" in s.check("dt/c1/r2/maintenance/done/3", msg, fresh=True)  # another robot
    assert "does not match" in s.check("dt/c1/r1/maintenance/ack/3", msg, fresh=True)  # an ack is not a done
    assert "does not match" in s.check(key, {**msg, "by": "mallory"}, fresh=True)
    assert "no time" in s.check(key, json.loads(s.sign(key, {"id": 3})), fresh=True)
