"""`dt run`: the long-running twin daemon.

Correct every command, test every MVS measurement (Eq. 17), escalate repeated failures to
maintenance over Zenoh; SIGINT/SIGTERM stop cleanly.
"""
from __future__ import annotations

import argparse
import json
from typing import Any

JSON_LOGS = True  # a daemon's stderr is read by machines: one JSON object per log line


def add_arguments(r: argparse.ArgumentParser) -> None:
    r.add_argument("--config", required=True, help="runtime YAML (see configs/runtime.yaml)")
    r.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    r.add_argument("--json", action="store_true", help="print the run summary as one JSON object")


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.service.daemon import run_daemon

    return run_daemon(args.config, args.duration)


def human(result: dict) -> str:
    return json.dumps(result, indent=2)
