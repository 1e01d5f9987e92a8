"""`dt run`: the long-running twin daemon.

Correct every command, test every MVS measurement (Eq. 17), escalate repeated failures to
maintenance over Zenoh; SIGINT/SIGTERM stop cleanly. Every few seconds (--status-every) one line
on stderr says how it is doing: ticks and their rate, status and escalation state, the time of
the last command and the expanded uncertainty of the position it reached (--quiet: none).
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Any

DEFAULT_STATUS_EVERY_S = 5.0


def json_logs(args: argparse.Namespace) -> bool:
    """Logs as one JSON object per line (for journald, a log shipper, a pipe), or as text for a
    person at a terminal: --log-format, by default JSON unless stderr is a terminal.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    bool
    """
    fmt = getattr(args, "log_format", "auto")
    return fmt == "json" or (fmt == "auto" and not sys.stderr.isatty())


def add_arguments(r: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt run`` (docs/cli.md, ``dt run``).

    Parameters
    ----------
    r : argparse.ArgumentParser
        The subcommand's parser.
    """
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
    """Run the twin daemon of the runtime YAML until SIGINT/SIGTERM or ``--duration``.

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
    from dt_runtime.service.daemon import run_daemon

    return run_daemon(args.config, args.duration, None if args.quiet else args.status_every)


def human(r: dict) -> str:
    """The text ``dt run`` prints without ``--json``.

    Parameters
    ----------
    r : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    lines = [f"{r['ticks']} commands, {r['t_test_failures']} failed Eq. 17, {r['refused_commands']} refused, "
             f"{r['driver_faults']} driver faults, {r['uncorrected_commands']} sent uncorrected, "
             f"{r['stale_measurements']} stale and {r['mvs_refused']} refused MVS readings",
             f"escalation {r['state']}" + (f" ({r['halt_reason']})" if r.get("halt_reason") else "")
             + f"; maintenance requests {r['maintenance_requests']} ({r['requests_delivered']} delivered)"]
    if "true_rms_mm" in r:
        lines.append(f"simulated cell: true 3D RMS error {r['true_rms_mm']:.4f} mm over {r['true_n']} commands")
    if "path" in r:
        lines += path_lines(r["path"], r["t_test_failures"])
    lines.append(f"store {r['store']} (dt status --store {r['store']})")
    return "\n".join(lines)


def path_lines(p: dict, failed: int) -> list[str]:
    """A streamed path's summary in words: passes, the lag and on which data the moving arm was
    tested, and what to do when something needs doing.

    Parameters
    ----------
    p : dict
        The result's ``path`` block.
    failed : int
        Readings of the moving arm that failed Eq. 17.

    Returns
    -------
    list of str
    """
    last = p["last"]
    jitter = last.get("jitter_p99_ms")
    if not last:
        rate = ""
    elif jitter is None or not math.isfinite(jitter):  # NaN in process, null in the JSON: not paced
        rate = f", last pass on the simulated clock ({last['target_hz']:g} Hz of simulated time, not paced)"
    else:
        rate = f", last pass {last['rate_hz']:.1f} Hz of {last['target_hz']:g} Hz, p99 jitter {jitter:.3f} ms"
    out = [f"path {p['file']}: {p['passes']} passes completed ({p['pass_started']} started), {p['sent']} set-points "
           f"sent ({p['rerun']} again after a stop){rate}"]
    lag = p.get("lag")
    if lag:
        out.append(f"servo lag {lag['tau_ms']:.2f} +- {lag['u_tau_ms']:.2f} ms, learnt from {lag['n']} readings of the "
                   f"learning pass (RMS {lag['rms_before_mm']:.3f} -> {lag['rms_after_mm']:.3f} mm)")
    if p["tested"]:
        where = "in the passes after the learning pass (readings the lag fit did not see)" if lag else "as streamed"
        out.append(f"moving arm: {p['tested']} readings tested by Eq. 17 {where}, {failed} failed "
                   f"({100 * failed / p['tested']:.1f} %); refused: {p['transient_refused']} in servo transients, "
                   f"{p['timing_refused']} timing-dominated, {p['outside_refused']} outside a pass")
    else:
        out.append("moving arm: no reading tested (a learning pass only, or the camera gave none): "
                   "run more passes to test the twin on the path")
    if lag and lag.get("warning"):
        out.append(f"WARNING: {lag['warning']}")
    if p["state"] == "stopped":
        out.append(f"the path is stopped: {p['stopped']}; it resumes at set-point {p['next'] + 1} of {p['n']} "
                   "at the next start (or after dt ack while running)")
    return out
