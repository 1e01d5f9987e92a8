"""`dt consume`: the maintenance side of the bus, as a maintenance system runs it.

Subscribes to every twin's `dt/**/maintenance/request`, takes its consumer group's copy of each
request (`--group`, one of the twin's `bus.consumer_groups`), acknowledges delivery (so the
twin stops republishing it), and prints each new request once as one JSON line on stdout (and
appends it to `--log FILE.jsonl`), de-duplicated on (cell, robot, uid): a request is re-sent
until acknowledged, so copies arrive. A maintenance system reads those lines (id, uid, cell,
robot, reason, evidence) and, when the work is done, answers with
`dt ack --bus BUS.yaml --request ID --uid UID --by NAME --note TEXT`.
Runs until SIGINT/SIGTERM or `--duration`; `--count N` stops after N new requests.

The plant's inbox: `--bus plant.yaml` (a plant config, configs/plant/plant.yaml) joins the plant's
fabric through its router and records every new request in the plant history (its `history:`
section, or `--history FILE.sqlite|postgresql://...`) before acknowledging it; a restarted inbox
does not record a request twice (docs/plant.md). `--key` narrows the cells it serves (a hall's:
`dt/hall-a-$*/*/maintenance/request`).
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from dt_kernel.errors import ConfigError
from dt_runtime.common.jsonsafe import dumps

JSON_LOGS = True


def add_arguments(c: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt consume`` (docs/cli.md, ``dt consume``).

    Parameters
    ----------
    c : argparse.ArgumentParser
        The subcommand's parser.
    """
    c.add_argument("--bus", required=True, metavar="YAML",
                   help="bus config (configs/bus.yaml: endpoints, TLS) or plant config (configs/plant/plant.yaml)")
    c.add_argument("--key", default="dt/**/maintenance/request", metavar="KEYEXPR",
                   help="the requests taken (default dt/**/maintenance/request: every cell)")
    c.add_argument("--history", default=None, metavar="URL",
                   help="record every new request here first (a SQLite file or postgresql://...; "
                        "default: the plant config's history, none for a bus config)")
    c.add_argument("--group", default="maintenance", help="this consumer's group (default maintenance)")
    c.add_argument("--log", default=None, metavar="FILE.jsonl", help="append each new request to this file")
    c.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    c.add_argument("--count", type=int, default=None, metavar="N", help="stop after N new requests")
    c.add_argument("--json", action="store_true", help="print a summary object at the end")


def run(args: argparse.Namespace) -> Any:
    """Take, acknowledge and print the maintenance requests on the bus until stopped.

    With a plant history, each new request is committed to it before it is acknowledged.

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
    from dt_runtime.fabric import MaintenanceConsumer
    from dt_runtime.fabric.config import keyexpr_ok
    from dt_runtime.plant.config import history_url, load_plant_config
    from dt_runtime.plant.inbox import PlantInbox

    cfg = load_plant_config(args.bus)
    try:
        keyexpr_ok(args.key)
    except ValueError as exc:
        raise ConfigError("--key", "--key", args.key, str(exc)) from exc
    history = args.history or (history_url(cfg, Path(args.bus).parent) if "history" in cfg.model_fields_set
                               else None)
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
    if history is None:
        with MaintenanceConsumer(cfg.bus, key_expr=args.key, on_request=on_request, group=args.group) as cons:
            print(f"dt consume: group {args.group!r} listening on {args.key}", file=sys.stderr)
            stop.wait(args.duration)
            return {"requests": len(cons.requests), "copies": cons.copies, "group": args.group}
    with PlantInbox(cfg.bus, history, group=args.group, key_expr=args.key, on_request=on_request) as inbox:
        print(f"dt consume: group {args.group!r} listening on {args.key}, history {inbox.history.where}",
              file=sys.stderr)
        stop.wait(args.duration)
        return {"requests": len(inbox.requests), "copies": inbox.consumer.copies, "group": args.group,
                "recorded": inbox.recorded, "history": inbox.history.where, "history_rows": inbox.history.count()}


def human(result: dict) -> str:
    """The text ``dt consume`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    text = (f"dt consume: {result['requests']} new request(s) ({result['copies']} copies received) for group "
            f"{result['group']!r}")
    if "history" in result:
        text += f"; {result['recorded']} recorded in {result['history']} ({result['history_rows']} rows)"
    return text
