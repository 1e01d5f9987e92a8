"""`dt router --config plant.yaml`: run the plant's Zenoh router (the `router:` section of a plant
config, configs/plant/) until SIGTERM or SIGINT, or `--duration`.

The cells' daemons connect to it (`bus: {mode: client, connect: [tcp/<router>:7447]}`), as do the
plant's tools (`dt status --bus plant.yaml`, `dt consume --bus plant.yaml`); a hall's router
connects to the plant's (`router.connect`). It prints one line on stderr when it listens
(`dt router: listening on ...`), and with `--json` its last state (zid, endpoints, who was
connected) on stdout at the end. docs/plant.md.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import Any

from dt_kernel.errors import ConfigError


def add_arguments(c: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt router`` (docs/cli.md, ``dt router``).

    Parameters
    ----------
    c : argparse.ArgumentParser
        The subcommand's parser.
    """
    c.add_argument("--config", required=True, metavar="YAML", help="plant config with a router: section")
    c.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    c.add_argument("--json", action="store_true", help="print the router's last state as JSON at the end")


def run(args: argparse.Namespace) -> Any:
    """Run the plant config's Zenoh router until SIGTERM/SIGINT or ``--duration``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    dict
        The result; with ``--json`` printed as one object (its keys: docs/cli.md).

    Raises
    ------
    TwinError
        For input the command refuses (``dt`` prints it and exits 2).
    """
    from dt_runtime.plant.config import load_plant_config
    from dt_runtime.plant.router import run_router

    cfg = load_plant_config(args.config)
    if cfg.router is None:
        raise ConfigError(args.config, "router", "<missing>", "a router: section (listen, connect, access_control): "
                          "see configs/plant/plant_router.yaml")
    rc = cfg.router
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def ready(r) -> None:
        print(f"dt router: listening on {', '.join(rc.listen)} (zid {r.zid})"
              + (f", connected to {', '.join(rc.connect)}" if rc.connect else ""),
              file=sys.stderr, flush=True)

    return run_router(rc, stop, args.duration, on_ready=ready)


def human(result: dict) -> str:
    """The text ``dt router`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    return (f"dt router: zid {result.get('zid')}, listened on {', '.join(result.get('listen') or [])}"
            + (f"; {len(result['routers'])} router(s), {len(result['peers'])} peer(s) at the end"
               if "routers" in result else "")
            + (f"; up {result['uptime_s']:.0f} s" if "uptime_s" in result else ""))
