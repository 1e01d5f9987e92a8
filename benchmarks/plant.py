"""A plant of N light cells through one `dt router` on loopback, with the plant's inbox.

Processes: `dt router` (the project's router, its own process), one consumer process (the plant
inbox, `dt_runtime.plant.inbox.PlantInbox`, recording into a SQLite history and acking, plus a
monitor subscribed to every cell's health and telemetry, as a plant view would be), and fleet
processes of light cells. A light cell is one Zenoh client session (its own connection to the
router, as a cell PC's daemon has) that publishes what a daemon publishes at its rates: health at
1 Hz, telemetry (one Eq. 17 test each) at `--rate-hz` (configs/runtime.yaml's 10 Hz), and now and
then a maintenance request (Poisson, one per `--request-period` s on average per cell; cell 0
always sends one at the start), signed with the service's key and republished every 2 s until
the inbox's ack comes back (the outbox's rule). Real daemons are in tests/integration/test_plant.py;
here the cells are light so that 1,000 fit on 2 cores.

Bounded: `--duration` s of load, then at most `--drain` s for the last requests to be acked.
Shared memory between Zenoh sessions is off on the router (its default: on one host Zenoh
negotiates it per session and refuses sessions near 350, docs/plant.md) and on every client.

Keys: `cells`, `duration_s`, `offered_msgs_per_s` (what the fleet was asked to publish),
`published_msgs_per_s`, `msgs_per_s` (received by the consumer process through the router),
`delivered_ratio` (received / published: the baseline is what left the cells), `requests`
{`sent`, `recorded`, `copies`, `unacked`}, `lost` (sent and never recorded), `request_latency_ms`
{`p50`, `p99`, `max`} (the request's creation to its receipt by the inbox), `consumer_rss_mb`,
`consumer_cpu_pct`, `router_rss_mb`, `router_cpu_pct`, `fleet_cpu_pct`, `fleet_late_pct` (the
fleet's publishing slots that started more than a period late), `saturated` and `saturated_by`
(delivered_ratio < 0.95, a request lost, the fleet late in > 5 % of slots, the consumer or the
router above 90 % of a core, p99 latency > 1 s). `--quick`: 5 cells, 3 s (the test's run).

`--netns [--delay-ms 5-20]` (root, `ip`, `tc`): the same workload first on loopback (the
reference), then with the router, the inbox and each fleet process (4 by default) in network
namespaces of their own, joined by links of a seeded latency in that range each way
(tests.support.netns: `tc netem`, or a delay relay where the kernel has no netem). Extra keys:
`netns` {`namespaces`, `links`, `delay_mode`, `link_delay_ms` {`min`, `max`}}, `loopback` (the
reference's delivery, requests, `lost` and latency) and `p99_vs_loopback`.
"""
from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks._common import cli, emit
from tests.support.plant_cells import stop

NO_SHM = {"transport/shared_memory/enabled": False}
ACK_PERIOD_S = 2.0  # the outbox's republish period (bus.republish_period_s default)


def _proc_stats(pid: int) -> tuple[float, float]:
    """(CPU seconds, RSS MB) of a running process, from /proc."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    rss = 0.0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
    return cpu, rss


def _self_rss_mb() -> float:
    return _proc_stats(os.getpid())[1]


def _raise_fd_limit() -> None:
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def _client(endpoint: str, cell: str, robot: str):
    from dt_runtime.fabric import BusConfig

    return BusConfig(cell=cell, robot=robot, mode="client", connect=[endpoint], extra=NO_SHM)


# --------------------------------------------------------------------------- the consumer process

def consumer(endpoint: str, out: str, history: str) -> None:
    """The plant's inbox and a monitor of health and telemetry until a line arrives on stdin; its
    figures to `out`."""
    import zenoh

    from dt_runtime.fabric.session import close_session, open_session
    from dt_runtime.plant.inbox import PlantInbox

    latencies: list[float] = []
    counts = {"health": 0, "telemetry": 0}
    lock = threading.Lock()

    def on_request(req: dict) -> None:
        latencies.append(time.time() - float(req["created"]))

    def count(kind: str):
        def cb(sample: zenoh.Sample) -> None:
            with lock:
                counts[kind] += 1
        return cb

    monitor = open_session(_client(endpoint, "plant", "monitor"))
    subs = [monitor.declare_subscriber(f"dt/*/*/{k}", count(k)) for k in counts]
    inbox = PlantInbox(_client(endpoint, "plant", "inbox"), history, on_request=on_request)
    print("ready", flush=True)
    c0, t0 = time.process_time(), time.monotonic()
    sys.stdin.readline()
    cpu, wall = time.process_time() - c0, time.monotonic() - t0
    res = {"received": dict(counts), "wall_s": wall, "cpu_s": cpu, "rss_mb": _self_rss_mb(),
           "latencies": latencies, "recorded": inbox.history.count(), "copies": inbox.consumer.copies,
           "uids": sorted(r["uid"] for r in inbox.requests)}
    for s in subs:
        s.undeclare()
    inbox.close()
    close_session(monitor, 3.0)
    Path(out).write_text(json.dumps(res))


# --------------------------------------------------------------------------- the fleet process

def fleet(endpoint: str, out: str, first: int, count: int, seconds: float, drain: float, rate_hz: float,
          request_period: float, seed: int) -> None:
    """`count` light cells from index `first` (module docstring); figures to `out`."""
    import zenoh

    from dt_runtime.fabric.auth import Signer
    from dt_runtime.fabric.session import close_session, encode, open_session

    _raise_fd_limit()
    rng = random.Random(seed + first)
    cells = [f"cell{first + i:04d}" for i in range(count)]
    signer = Signer(_client(endpoint, cells[0], "r1").auth, create=True)
    sessions, pubs, subs = [], [], []
    pending: dict[tuple[str, str], dict] = {}  # (cell, uid) -> request body (with id, attempt)
    lock = threading.Lock()
    acked = 0

    def on_ack(sample: zenoh.Sample) -> None:
        nonlocal acked
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        cell = str(sample.key_expr).split("/")[1]
        with lock:
            if pending.pop((cell, str(msg.get("uid"))), None) is not None:
                acked += 1

    for c in cells:
        s = open_session(_client(endpoint, c, "r1"))
        sessions.append(s)
        pubs.append({k: s.declare_publisher(f"dt/{c}/r1/{k}", encoding=zenoh.Encoding.APPLICATION_JSON,
                                            congestion_control=cc, priority=prio)
                     for k, cc, prio in (("telemetry", zenoh.CongestionControl.DROP, zenoh.Priority.DATA_LOW),
                                         ("health", zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_HIGH),
                                         ("maintenance/request", zenoh.CongestionControl.BLOCK,
                                          zenoh.Priority.INTERACTIVE_HIGH))})
        subs.append(s.declare_subscriber(f"dt/{c}/r1/maintenance/ack/*", on_ack))
    # when each cell sends its next request (cell 0: at once)
    next_req = [rng.expovariate(1.0 / request_period) for _ in cells]
    if first == 0:
        next_req[0] = 0.0
    sent, published, slots, late, n_req = 0, 0, 0, 0, 0
    period = 1.0 / rate_hz
    print("ready", flush=True)
    c0 = time.process_time()
    t0 = time.monotonic()
    last_republish = t0
    while True:
        now = time.monotonic()
        t = now - t0
        if t >= seconds:
            break
        slots += 1
        tick = int(t * rate_hz)
        for i, c in enumerate(cells):
            p = pubs[i]
            p["telemetry"].put(encode({"t": time.time(), "target": [0.9, 0.0, 0.55], "command": [0.9, 0.0, 0.55],
                                       "t_stat": [0.3, -0.8, 1.1], "passed": True, "state": "nominal"}))
            published += 1
            if (tick + i) % int(rate_hz) == 0:  # health at 1 Hz, the cells spread over the second
                p["health"].put(signer.sign(f"dt/{c}/r1/health", {"status": "running", "escalation": "nominal",
                                                                  "ticks": tick, "t": time.time()}))
                published += 1
            if t >= next_req[i]:
                next_req[i] = t + rng.expovariate(1.0 / request_period)
                n_req += 1
                body = {"id": n_req, "uid": f"{c}-{n_req}-{seed}", "group": "maintenance", "cell": c, "robot": "r1",
                        "kind": "t_test", "episode": n_req, "created": time.time(), "attempt": 1, "t": time.time(),
                        "state": "maintenance_requested", "reason": "benchmark", "evidence": {}}
                with lock:
                    pending[(c, body["uid"])] = body
                p["maintenance/request"].put(signer.sign(f"dt/{c}/r1/maintenance/request", body))
                sent += 1
                published += 1
        if time.monotonic() - last_republish >= ACK_PERIOD_S:
            last_republish = time.monotonic()
            _republish(pending, lock, pubs, cells, signer)
        next_slot = t0 + slots * period
        delay = next_slot - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -period:
            late += 1
    cpu_load = time.process_time() - c0
    wall = time.monotonic() - t0
    end = time.monotonic() + drain
    while time.monotonic() < end:  # the outbox's rule: republish until acked, within the drain
        with lock:
            if not pending:
                break
        time.sleep(0.2)
        if time.monotonic() - last_republish >= ACK_PERIOD_S:
            last_republish = time.monotonic()
            _republish(pending, lock, pubs, cells, signer)
    res = {"cells": count, "sent": sent, "acked": acked, "unacked": len(pending), "published": published,
           "slots": slots, "late": late, "wall_s": wall, "cpu_s": cpu_load, "rss_mb": _self_rss_mb()}
    for s in sessions:
        close_session(s, 3.0)
    Path(out).write_text(json.dumps(res))


def _republish(pending, lock, pubs, cells, signer) -> None:
    index = {c: i for i, c in enumerate(cells)}
    with lock:
        items = list(pending.items())
    for (c, _uid), body in items:
        body["attempt"] += 1
        pubs[index[c]]["maintenance/request"].put(signer.sign(f"dt/{c}/r1/maintenance/request", body))


# --------------------------------------------------------------------------- the run

def _spawn(args: list[str], log: Path, env: dict, stdin: bool = False) -> subprocess.Popen:
    with log.open("wb") as f:
        return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=f, env=env,
                                stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, start_new_session=True)


def _ready(p: subprocess.Popen, log: Path, timeout: float = 300.0) -> None:
    """Wait for the child's 'ready' line (bounded by a thread-joined read)."""
    line: list[bytes] = []
    th = threading.Thread(target=lambda: line.append(p.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    th.start()
    th.join(timeout)
    if not line or line[0].strip() != b"ready":
        raise RuntimeError(f"{p.args}: not ready: {log.read_text()[-2000:]}")


def _pct(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]


def _free_port() -> int:
    import socket

    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return so.getsockname()[1]


def run(cells: int = 10, duration: float = 20.0, rate_hz: float = 10.0, request_period: float = 30.0,
        drain: float = 20.0, fleet_procs: int = 0, seed: int = 0, netns: bool = False,
        delay_ms: str = "5-20") -> dict[str, Any]:
    """The plant on loopback; with `netns`, across network namespaces (module docstring), after the
    same workload on loopback as the reference."""
    if not netns:
        return _run(cells, duration, rate_hz, request_period, drain, fleet_procs or max(1, math.ceil(cells / 500)),
                    seed)
    from tests.support.netns import netns_links, unavailable

    why = unavailable()
    if why:
        raise RuntimeError(f"--netns: {why}")
    lo, _, hi = delay_ms.partition("-")
    span = (float(lo), float(hi or lo))
    n_fleet = min(cells, fleet_procs or 4)
    ref = _run(cells, duration, rate_hz, request_period, drain, n_fleet, seed)
    with netns_links(["inbox", *(f"fleet{k}" for k in range(n_fleet))], span, seed) as links:
        res = _run(cells, duration, rate_hz, request_period, drain, n_fleet, seed, links)
        delays = list(links.delay_ms.values())
        res["netns"] = {"namespaces": len(delays) + 1, "links": len(delays), "delay_mode": links.mode,
                        "link_delay_ms": {"min": min(delays), "max": max(delays)}}
    p99, ref_p99 = res["request_latency_ms"]["p99"], ref["request_latency_ms"]["p99"]
    res["loopback"] = {k: ref[k] for k in ("msgs_per_s", "delivered_ratio", "requests", "lost", "request_latency_ms",
                                           "saturated")}
    res["p99_vs_loopback"] = round(p99 / ref_p99, 2) if p99 and ref_p99 else None
    return res


def _run(cells: int, duration: float, rate_hz: float, request_period: float, drain: float, fleet_procs: int,
         seed: int, links=None) -> dict[str, Any]:
    """One run; `links` (tests.support.netns.Links): the router, the inbox and each fleet process in
    namespaces of their own (nodes `router`, `inbox`, `fleet<k>`)."""
    from dt_runtime.common.paths import ROOT

    n_fleet = min(cells, fleet_procs)
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="dt-plant-bench-") as tmp_s:
        tmp = Path(tmp_s)
        env = dict(os.environ, XDG_CONFIG_HOME=str(tmp / "config"))  # the service's key, shared by all
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        loopback = f"tcp/127.0.0.1:{_free_port()}"

        def spawn(node: str, args: list[str], log: Path, stdin: bool = False) -> subprocess.Popen:
            if links is None:
                return _spawn(args, log, env, stdin)
            return links.popen(node, [sys.executable, *args], log, env=env, stdout=subprocess.PIPE,
                               stdin=subprocess.PIPE if stdin else subprocess.DEVNULL)

        def endpoint(node: str) -> str:
            return loopback if links is None else links.endpoint(node)

        cfg = tmp / "plant.yaml"
        # the router's defaults: max_sessions 10000, shared memory off (dt_runtime.plant.config)
        cfg.write_text(json.dumps({"router": {"listen": [loopback if links is None else links.router_listen]}}))
        try:
            rlog = tmp / "router.log"
            router = spawn("router", ["-m", "dt_runtime.cli.main", "router", "--config", str(cfg)], rlog)
            procs.append(router)
            end = time.monotonic() + 120
            while "dt router: listening" not in rlog.read_text() and router.poll() is None and time.monotonic() < end:
                time.sleep(0.05)
            if router.poll() is not None or "dt router: listening" not in rlog.read_text():
                raise RuntimeError(f"the router did not start: {rlog.read_text()[-2000:]}")
            clog = tmp / "consumer.log"
            cons = spawn("inbox", ["-m", "benchmarks.plant", "consumer", json.dumps(
                {"endpoint": endpoint("inbox"), "out": str(tmp / "consumer.json"),
                 "history": str(tmp / "history.sqlite")})], clog, stdin=True)
            procs.append(cons)
            _ready(cons, clog)
            fleets = []
            for k in range(n_fleet):
                first = k * cells // n_fleet  # the cells split evenly over the fleet processes
                count = (k + 1) * cells // n_fleet - first
                log = tmp / f"fleet{k}.log"
                f = spawn(f"fleet{k}", ["-m", "benchmarks.plant", "fleet", json.dumps(
                    {"endpoint": endpoint(f"fleet{k}"), "out": str(tmp / f"fleet{k}.json"), "first": first,
                     "count": count, "seconds": duration, "drain": drain, "rate_hz": rate_hz,
                     "request_period": request_period, "seed": seed})], log)
                procs.append(f)
                fleets.append((f, log))
            for f, log in fleets:
                _ready(f, log)
            r0, c0 = _proc_stats(router.pid)[0], _proc_stats(cons.pid)[0]
            f0 = [_proc_stats(f.pid)[0] for f, _ in fleets]
            t0 = time.monotonic()
            time.sleep(duration)
            (r1, router_rss), (c1, cons_rss) = _proc_stats(router.pid), _proc_stats(cons.pid)
            f1 = [_proc_stats(f.pid)[0] for f, _ in fleets]
            load_s = time.monotonic() - t0
            for f, log in fleets:
                if f.wait(duration + drain + 120) != 0:
                    raise RuntimeError(f"a fleet failed: {log.read_text()[-2000:]}")
            time.sleep(0.5)  # the last acks' records
            assert cons.stdin is not None
            cons.stdin.write(b"stop\n")
            cons.stdin.flush()
            if cons.wait(120) != 0:
                raise RuntimeError(f"the consumer failed: {clog.read_text()[-2000:]}")
            figs = [json.loads((tmp / f"fleet{k}.json").read_text()) for k in range(n_fleet)]
            c = json.loads((tmp / "consumer.json").read_text())
        finally:
            for p in reversed(procs):
                stop(p)
    sent = sum(f["sent"] for f in figs)
    published = sum(f["published"] for f in figs)
    wall = max(f["wall_s"] for f in figs)
    received = sum(c["received"].values())
    lat = [x * 1e3 for x in c["latencies"]]
    slots = sum(f["slots"] for f in figs)
    late_pct = 100.0 * sum(f["late"] for f in figs) / max(1, slots)
    res: dict[str, Any] = {
        "cells": cells, "duration_s": round(wall, 3), "fleet_processes": n_fleet,
        "offered_msgs_per_s": round(cells * (rate_hz + 1.0) + cells / request_period, 1),
        "published_msgs_per_s": round(published / wall, 1), "msgs_per_s": round(received / wall, 1),
        "delivered_ratio": round(received / max(1, published - sent), 4),
        "requests": {"sent": sent, "recorded": c["recorded"], "copies": c["copies"],
                     "unacked": sum(f["unacked"] for f in figs)},
        "lost": sent - c["recorded"],
        "request_latency_ms": {"p50": _round(_pct(lat, 50)), "p99": _round(_pct(lat, 99)),
                               "max": _round(max(lat, default=None))},
        "consumer_rss_mb": round(cons_rss, 1), "consumer_cpu_pct": round(100 * (c1 - c0) / load_s, 1),
        "router_rss_mb": round(router_rss, 1), "router_cpu_pct": round(100 * (r1 - r0) / load_s, 1),
        "fleet_cpu_pct": round(100 * sum(b - a for a, b in zip(f0, f1)) / load_s, 1),
        "fleet_rss_mb": round(sum(f["rss_mb"] for f in figs), 1), "fleet_late_pct": round(late_pct, 2),
    }
    why = []
    if res["delivered_ratio"] < 0.95:
        why.append("delivered_ratio < 0.95")
    if res["lost"]:
        why.append("requests lost")
    if late_pct > 5:
        why.append("the fleet fell behind its schedule (publishers saturated)")
    if res["consumer_cpu_pct"] > 90:
        why.append("the consumer above 90 % of a core")
    if res["router_cpu_pct"] > 90:
        why.append("the router above 90 % of a core")
    if (res["request_latency_ms"]["p99"] or 0) > 1000:
        why.append("request p99 latency > 1 s")
    res["saturated"], res["saturated_by"] = bool(why), why
    return res


def _round(x: float | None) -> float | None:
    return None if x is None else round(x, 3)


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] in ("consumer", "fleet"):  # a child of `run`
        role, params = argv[0], json.loads(argv[1])
        (consumer if role == "consumer" else fleet)(**params)
        return 0
    a = cli(__doc__.splitlines()[0], argv, cells=10, duration=20.0, rate_hz=10.0, request_period=30.0,
            drain=20.0, fleet_procs=0, seed=0, quick=False, netns=False, delay_ms="5-20")
    if a.quick:
        a.cells, a.duration, a.drain = 5, 3.0, 15.0
    where = f"across network namespaces, links of {a.delay_ms} ms" if a.netns else "on loopback"
    emit(run(a.cells, a.duration, a.rate_hz, a.request_period, a.drain, a.fleet_procs, a.seed, a.netns, a.delay_ms),
         a.json, f"plant: {a.cells} light cells through a router {where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
