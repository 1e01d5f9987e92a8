"""`dt dashboard`: the live cell in a browser, beside a running `dt run`.

Joins the cell's bus with the runtime YAML's `bus` section, reads the twin the YAML names, and
serves one page on http://127.0.0.1:8765/ (`--host`, `--port`): health, the escalation state and
its timeline, the t statistic against its thresholds, maintenance requests, the twin's provenance
and the cell in 3D. Acting on a request needs an operator (`--token-file F`) and the bus key;
without a token file the page is read-only. `--results DIR` adds the metrologist's view
(/metrology; alone, only that page), `--plant plant.yaml` the plant page (/plant). Beyond loopback
the page is served only over TLS (`--tls-cert`, `--tls-key`). Runs until SIGINT/SIGTERM or
`--duration`.

The options and the page: docs/cli.md ("dt dashboard") and docs/dashboard.md."""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any


def add_arguments(d: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt dashboard`` (docs/cli.md, ``dt dashboard``).

    Parameters
    ----------
    d : argparse.ArgumentParser
        The subcommand's parser.
    """
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
    """Serve the dashboard until SIGINT/SIGTERM or ``--duration``.

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
    from dt_kernel.errors import ConfigError, TwinError

    if not (args.config or args.results or args.plant):  # said before the web server's imports (seconds)
        raise TwinError("nothing to show: give --config runtime.yaml (the live cell beside its `dt run`), "
                        "--results DIR (the metrologist's view of dt compare / dt diagnose / twin results), "
                        "--plant plant.yaml (the plant page), or several; `dt dashboard --help` for the rest")
    from dt_runtime.dashboard.app import Dashboard
    from dt_runtime.dashboard.plant import check_links
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
    if plant is not None:
        check_links(plant, args.plant, args.host, args.port)
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
    """The text ``dt dashboard`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    got = result.get("received") or {}
    actions = result.get("actions") or []
    return (f"dt dashboard: served {result['url']}"
            + (f" (bus {result['bus']})" if result.get("bus") else "")
            + f"; received {sum(got.values())} messages" + (f" ({', '.join(f'{k} {v}' for k, v in got.items())})"
                                                            if got else "")
            + (f", {result['bus_refused']} refused" if result.get("bus_refused") else "")
            + (f", {result['dropped']} dropped" if result.get("dropped") else "")
            + f"; {len(actions)} operator action(s)")
