"""`dt dashboard`: the live cell in a browser, beside a running `dt run`.

Joins the cell's bus with the runtime YAML's `bus` section (as `dt run` and `dt consume` do: the
same cell, robot, TLS and access control; it connects to the daemon's listen endpoints), reads
the twin the YAML names (its kinematics, calibrated volume, Eq. 17 thresholds and provenance),
and serves one page on http://127.0.0.1:8765/ (`--host`, `--port`): health, the escalation state
and its timeline, the t statistic against its thresholds, maintenance requests, the twin's
provenance and the cell in 3D. Viewing needs nothing more than the bus allows.

Acknowledging a request or confirming maintenance done needs an operator: `--token-file F`
(one `<name> <token>` a line, mode 0600, docs/dashboard.md), and the bus key
(`bus.auth.key_file`, as for `dt ack --bus`: run as the service's user). The server signs the
action with the key under the operator's name; the daemon stores it by that name. Without a
token file the page is read-only.

The metrologist's view (/metrology, `--results DIR`): the results in DIR and below (`dt compare
--report`, `dt diagnose --auto --out`, twins), one chosen on the page: the residual map per point in
3D with filters by session, speed and direction of approach, the diagnose steps, the report's
figures. With `--results` alone no bus is joined and only that page is served.

The plant page (/plant, `--plant plant.yaml`, a plant config as `dt status --bus` takes): every
cell on the fabric with its status, escalation, open requests and the age of its last contact,
the expected cells that are silent marked; a click on a cell opens its own dashboard (the plant
config's `dashboards:`). The plant is asked every `--plant-period` s (one query on dt/*/*/status).

Beyond loopback (`--host` another address) the page is served only over TLS (`--tls-cert`,
`--tls-key`): the operators' tokens travel in its requests. Runs until SIGINT/SIGTERM or
`--duration`.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any


def add_arguments(d: argparse.ArgumentParser) -> None:
    d.add_argument("--config", default=None, metavar="YAML",
                   help="the runtime YAML of the `dt run` to watch (the live view)")
    d.add_argument("--results", default=None, metavar="DIR",
                   help="results of dt compare --report, dt diagnose --auto --out or twins, in DIR or below it: the "
                        "metrologist's view at /metrology (with --results alone, only that page, no bus)")
    d.add_argument("--plant", default=None, metavar="YAML",
                   help="a plant config (as dt status --bus): the plant page at /plant, every cell on the fabric")
    d.add_argument("--plant-period", type=float, default=3.0, metavar="S",
                   help="ask the plant every S seconds (default 3)")
    d.add_argument("--bus", default=None, metavar="YAML",
                   help="a bus config of its own (another machine, a router) instead of joining the runtime "
                        "YAML's daemon")
    d.add_argument("--host", default="127.0.0.1", help="address to serve the page on (default 127.0.0.1)")
    d.add_argument("--port", type=_port, default=8765, help="port (default 8765; 0: any free one)")
    d.add_argument("--token-file", default=None, metavar="FILE",
                   help="operators' tokens, '<name> <token>' a line, mode 0600 (without: read-only)")
    d.add_argument("--group", default="maintenance",
                   help="the consumer group whose copy 'acknowledge' confirms (default maintenance)")
    d.add_argument("--tls-cert", default=None, metavar="PEM", help="certificate chain to serve HTTPS")
    d.add_argument("--tls-key", default=None, metavar="PEM", help="its private key")
    d.add_argument("--max-rate", type=float, default=50.0, metavar="HZ",
                   help="at most this many updates a second to each page (default 50)")
    d.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    d.add_argument("--json", action="store_true", help="print a summary object at the end")


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{v}: a port is 0 to 65535")
    return v


def run(args: argparse.Namespace) -> Any:
    from dt_kernel.errors import ConfigError
    from dt_runtime.dashboard.app import Dashboard
    from dt_runtime.fabric import load_bus_config
    from dt_runtime.plant.config import load_plant_config
    from dt_runtime.service.runtime_config import load_runtime_config

    if not 0.2 <= args.plant_period <= 600:
        raise ConfigError("<command line>", "--plant-period", args.plant_period, "0.2 to 600 seconds")
    if not 1 <= args.max_rate <= 200:
        raise ConfigError("<command line>", "--max-rate", args.max_rate, "1 to 200 updates a second")
    config = Path(args.config) if args.config else None
    cfg = load_runtime_config(config) if config else None
    bus = load_bus_config(args.bus) if args.bus else None
    plant = load_plant_config(args.plant) if args.plant else None
    stop = threading.Event()
    with Dashboard(cfg, config, bus=bus, host=args.host, port=args.port, token_file=args.token_file,
                   group=args.group, tls=(args.tls_cert, args.tls_key), max_rate_hz=args.max_rate,
                   results=args.results, plant=plant, plant_period_s=args.plant_period) as dash:
        # installed once it runs, and the caller's put back after (a test calling main in process)
        before = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            if dash.feed is not None:
                print(f"dt dashboard: {dash.url} (bus {dash.feed.prefix}; "
                      f"{'operators ' + ', '.join(dash.operators.names) if dash.operators else 'read-only'})",
                      file=sys.stderr, flush=True)
            if args.results:
                print(f"dt dashboard: the metrologist's view {dash.url}metrology (results in {args.results})",
                      file=sys.stderr, flush=True)
            if dash.plant is not None:
                print(f"dt dashboard: the plant {dash.url}plant ({len(plant.cells) if plant else 0} cell(s) expected)",
                      file=sys.stderr, flush=True)
            stop.wait(args.duration)
        finally:
            for s, handler in before.items():
                signal.signal(s, signal.SIG_DFL if handler is None else handler)
        return dash.summary()


def human(result: dict) -> str:
    return json.dumps(result)
