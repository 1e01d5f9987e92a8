"""A plant spread over network namespaces: the router's namespace holds a bridge, and every other
node (a cell, the inbox, a fleet of light cells) has a namespace of its own joined to it by a veth
pair whose link adds a seeded latency drawn in [lo, hi] ms, each way. Processes run inside with
`ip netns exec`; everything is torn down on leaving `netns_links`, on failure too. Names are unique
per run (parallel runs do not collide). Needs root, `ip` and `tc` (`unavailable()` says why not).

The latency is `tc qdisc ... netem delay` on both ends of each link where the kernel has netem
(`sch_netem`); where it has not, a relay in the node's namespace (`python -m tests.support.netns
relay`) carries its connections to the router and holds every chunk the link's delay, each way,
in order: the same added latency, across the same veth and bridge (`Links.mode` says which).
"""
from __future__ import annotations

import asyncio
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ROUTER_ADDR = "10.77.0.1"
PORT = 7447  # the router's port in its namespace, and each relay's in its node's (namespaces do not share ports)
RELAY = "relay"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


def unavailable() -> str | None:
    """Why namespaces cannot be made on this machine, or None when they can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"`{tool}` is not installed (iproute2)"
    probe = f"dtprobe-{uuid.uuid4().hex[:8]}"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


class Links:
    """The namespaces of one run: `ns(node)`, where a node's clients connect (`endpoint`), the
    router's listen endpoint, each link's delay (`delay_ms`), and `popen` inside a namespace."""

    def __init__(self, prefix: str, nodes: Sequence[str], delay_ms: dict[str, float]):
        self.prefix, self.nodes, self.delay_ms = prefix, list(nodes), delay_ms
        self.mode = "netem"
        self.router_listen = f"tcp/{ROUTER_ADDR}:{PORT}"
        self._procs: list[subprocess.Popen] = []
        self._made: list[str] = []

    def ns(self, node: str) -> str:
        """The namespace of `node` (`router` or one of the nodes)."""
        return f"{self.prefix}-{node}"

    def endpoint(self, node: str) -> str:
        """The router's endpoint as a client in `node`'s namespace connects to it."""
        return f"tcp/127.0.0.1:{PORT}" if self.mode == RELAY else self.router_listen

    def argv(self, node: str, argv: Sequence[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns(node), *argv]

    def popen(self, node: str, argv: Sequence[str], log: Path | None = None, **kw) -> subprocess.Popen:
        """`argv` in `node`'s namespace, its own session, stderr appended to `log`; stopped on teardown."""
        env = dict(kw.pop("env", os.environ))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        kw.setdefault("stdout", subprocess.DEVNULL)
        if log is not None:
            with log.open("ab") as f:
                p = subprocess.Popen(self.argv(node, argv), stderr=f, env=env, start_new_session=True, **kw)
        else:
            p = subprocess.Popen(self.argv(node, argv), env=env, start_new_session=True, **kw)
        self._procs.append(p)
        return p

    # ------------------------------------------------------------------ set-up and teardown
    def _add_ns(self, node: str) -> None:
        _ip("netns", "add", self.ns(node))
        self._made.append(self.ns(node))
        _ip("-n", self.ns(node), "link", "set", "lo", "up")

    def _tc(self, ns: str, dev: str, ms: float) -> bool:
        r = subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "netem", "delay",
                            f"{ms:.3f}ms"], capture_output=True, text=True, timeout=30)
        if r.returncode != 0 and "unknown" not in r.stderr.lower():
            raise RuntimeError(f"tc netem in {ns}: {r.stderr.strip()}")
        return r.returncode == 0

    def build(self) -> None:
        r = self.ns("router")
        self._add_ns("router")
        _ip("-n", r, "link", "add", "br0", "type", "bridge")
        _ip("-n", r, "addr", "add", f"{ROUTER_ADDR}/16", "dev", "br0")
        _ip("-n", r, "link", "set", "br0", "up")
        for k, node in enumerate(self.nodes, start=1):
            n = self.ns(node)
            self._add_ns(node)
            _ip("link", "add", "name", f"v{k}", "netns", r, "type", "veth", "peer", "name", "eth0", "netns", n)
            _ip("-n", r, "link", "set", f"v{k}", "master", "br0", "up")
            _ip("-n", n, "addr", "add", f"10.77.{1 + k // 250}.{1 + k % 250}/16", "dev", "eth0")
            _ip("-n", n, "link", "set", "eth0", "up")
            ms = self.delay_ms[node]
            if self.mode == "netem" and not (self._tc(n, "eth0", ms) and self._tc(r, f"v{k}", ms)):
                self.mode = RELAY  # the kernel has no netem: the first link tells
            if self.mode == RELAY:
                relay = self.popen(node, [sys.executable, "-m", "tests.support.netns", RELAY, str(PORT),
                                          f"{ROUTER_ADDR}:{PORT}", str(ms)], stdout=subprocess.PIPE)
                line = _readline(relay, 60)
                if line.strip() != "ready":
                    raise RuntimeError(f"the delay relay in {n} did not start: {line!r}")

    def close(self) -> None:
        for p in reversed(self._procs):
            _stop(p)
        for ns in reversed(self._made):  # the router's last: its bridge and veth ends go with it
            pids = _ip("netns", "pids", ns, check=False).stdout.split()
            for pid in pids:  # anything still running in a namespace of this run
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", ns, check=False)
        self._made.clear()


@contextmanager
def netns_links(nodes: Sequence[str], delay_ms: tuple[float, float] = (5.0, 20.0), seed: int = 0) -> Iterator[Links]:
    """Namespaces `router` and one per node, each node linked to the router with a latency drawn
    (seeded) in `delay_ms`; removed on exit, whatever happened.

    Parameters
    ----------
    nodes : sequence of str
        The nodes besides the router (short names: `c1`, `inbox`, `fleet0`).
    delay_ms : (float, float)
        The range of a link's added latency, each way, in ms.
    seed : int
        Seeds the links' latencies.

    Returns
    -------
    Links
        The namespaces (yielded).
    """
    rng = random.Random(seed)
    delays = {node: round(rng.uniform(*delay_ms), 3) for node in nodes}
    links = Links(f"dt{uuid.uuid4().hex[:8]}", nodes, delays)
    try:
        links.build()
        yield links
    finally:
        links.close()


def _readline(p: subprocess.Popen, timeout: float) -> str:
    out: list[bytes] = []
    th = threading.Thread(target=lambda: out.append(p.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    th.start()
    th.join(timeout)
    return out[0].decode(errors="replace") if out else ""


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


# --------------------------------------------------------------------------- the delay relay

async def _carry(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    """Every chunk from `reader` to `writer`, each sent `delay_s` after it arrived, in order."""
    loop = asyncio.get_running_loop()
    q: asyncio.Queue = asyncio.Queue()

    async def send() -> None:
        while True:
            due, data = await q.get()
            wait = due - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            if not data:
                break
            writer.write(data)
            await writer.drain()

    sender = asyncio.create_task(send())
    try:
        while True:
            try:
                data = await reader.read(65536)
            except (ConnectionError, OSError):
                data = b""
            q.put_nowait((loop.time() + delay_s, data))
            if not data:
                break
        await sender
    except (ConnectionError, OSError):
        pass
    finally:
        sender.cancel()
        writer.close()


async def _relay(port: int, upstream: str, delay_s: float) -> None:
    host, _, up_port = upstream.rpartition(":")

    async def handle(cr: asyncio.StreamReader, cw: asyncio.StreamWriter) -> None:
        try:
            ur, uw = await asyncio.open_connection(host, int(up_port))
        except OSError:  # the router is down: the client retries
            cw.close()
            return
        await asyncio.gather(_carry(cr, uw, delay_s), _carry(ur, cw, delay_s), return_exceptions=True)

    server = await asyncio.start_server(handle, "127.0.0.1", port)
    print("ready", flush=True)
    async with server:
        await server.serve_forever()


def main(argv: list[str]) -> int:
    """`relay PORT HOST:PORT DELAY_MS`: listen on 127.0.0.1:PORT, carry to HOST:PORT with the delay."""
    if len(argv) != 4 or argv[0] != RELAY:
        print("usage: python -m tests.support.netns relay PORT HOST:PORT DELAY_MS", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    asyncio.run(_relay(int(argv[1]), argv[2], float(argv[3]) / 1e3))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
