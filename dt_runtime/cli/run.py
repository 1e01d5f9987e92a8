"""`dt run`: the long-running twin daemon.

Correct every command, test every MVS measurement (Eq. 17), escalate repeated failures to
maintenance over Zenoh; SIGINT/SIGTERM stop cleanly. Every few seconds (--status-every) one line
on stderr says how it is doing: ticks and their rate, status and escalation state, the time of
the last command and the expanded uncertainty of the position it reached (--quiet: none).
"""
from __future__ import annotations

import argparse
import sys
from typing import Any

DEFAULT_STATUS_EVERY_S = 5.0


def json_logs(args: argparse.Namespace) -> bool:
    """Logs as one JSON object per line (for journald, a log shipper, a pipe), or as text for a
    person at a terminal: --log-format, by default JSON unless stderr is a terminal."""
    fmt = getattr(args, "log_format", "auto")
    return fmt == "json" or (fmt == "auto" and not sys.stderr.isatty())


def add_arguments(r: argparse.ArgumentParser) -> None:
    r.add_argument("--config", required=True, help="runtime YAML (see configs/runtime.yaml)")
    r.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    r.add_argument("--status-every", type=_period, default=DEFAULT_STATUS_EVERY_S, metavar="S",
                   help=f"the status line on stderr every S seconds (default {DEFAULT_STATUS_EVERY_S:g})")
    r.add_argument("--quiet", action="store_true", help="no status line (warnings and errors are still logged)")
    r.add_argument("--log-format", choices=("auto", "json", "text"), default="auto",
                   help="stderr: one JSON object per line (json), or text (default auto: text on a terminal, "
                        "else JSON)")
    r.add_argument("--json", action="store_true", help="print the run summary as one JSON object")


def _period(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.1 <= v <= 3600:
        raise argparse.ArgumentTypeError(f"{v}: seconds between status lines, 0.1 to 3600")
    return v


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.service.daemon import run_daemon

    return run_daemon(args.config, args.duration, None if args.quiet else args.status_every)


def human(r: dict) -> str:
    lines = [f"{r['ticks']} commands, {r['t_test_failures']} failed Eq. 17, {r['refused_commands']} refused, "
             f"{r['driver_faults']} driver faults, {r['uncorrected_commands']} sent uncorrected, "
             f"{r['stale_measurements']} stale and {r['mvs_refused']} refused MVS readings",
             f"escalation {r['state']}" + (f" ({r['halt_reason']})" if r.get("halt_reason") else "")
             + f"; maintenance requests {r['maintenance_requests']} ({r['requests_delivered']} delivered)"]
    if "true_rms_mm" in r:
        lines.append(f"simulated cell: true 3D RMS error {r['true_rms_mm']:.4f} mm over {r['true_n']} commands")
    lines.append(f"store {r['store']} (dt status --store {r['store']})")
    return "\n".join(lines)
