"""`dt consume`: the maintenance side of the bus, as a maintenance system runs it.

Subscribes to every twin's `dt/**/maintenance/request`, takes its consumer group's copy of each
request (`--group`, one of the twin's `bus.consumer_groups`), acknowledges delivery (so the
twin stops republishing it), and prints each new request once as one JSON line on stdout (and
appends it to `--log FILE.jsonl`), de-duplicated on (cell, robot, uid): a request is re-sent
until acknowledged, so copies arrive. A maintenance system reads those lines (id, uid, cell,
robot, reason, evidence) and, when the work is done, answers with
`dt ack --bus BUS.yaml --request ID --uid UID --by NAME --note TEXT`.
Runs until SIGINT/SIGTERM or `--duration`; `--count N` stops after N new requests.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from dt_runtime.common.jsonsafe import dumps

JSON_LOGS = True


def add_arguments(c: argparse.ArgumentParser) -> None:
    c.add_argument("--bus", required=True, metavar="YAML", help="bus config (configs/bus.yaml: endpoints, TLS)")
    c.add_argument("--group", default="maintenance", help="this consumer's group (default maintenance)")
    c.add_argument("--log", default=None, metavar="FILE.jsonl", help="append each new request to this file")
    c.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    c.add_argument("--count", type=int, default=None, metavar="N", help="stop after N new requests")
    c.add_argument("--json", action="store_true", help="print a summary object at the end")


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.service.bus import MaintenanceConsumer, load_bus_config

    cfg = load_bus_config(args.bus)
    stop = threading.Event()
    log_path = Path(args.log) if args.log else None
    seen = 0

    def on_request(req: dict) -> None:
        nonlocal seen
        line = dumps(req)
        print(line, flush=True)
        if log_path is not None:
            with log_path.open("a", encoding="utf-8") as f:
                f.write(line + "\n")
        seen += 1
        if args.count is not None and seen >= args.count:
            stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with MaintenanceConsumer(cfg, on_request=on_request, group=args.group) as cons:
        print(f"dt consume: group {args.group!r} listening on dt/**/maintenance/request", file=sys.stderr)
        stop.wait(args.duration)
        return {"requests": len(cons.requests), "copies": cons.copies, "group": args.group}


def human(result: dict) -> str:
    return json.dumps(result)
