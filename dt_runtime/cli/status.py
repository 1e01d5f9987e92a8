"""`dt status`: the daemon's current state and last figures, read from its store; or, with
`--bus plant.yaml [SELECTOR]`, every cell of the plant that answers one query on the fabric.

A summary an operator reads at a glance: the escalation state and since when, what the daemon did
(rows, Eq. 17 failures), its last command, correction, MVS measurement and test, in mm with the
frame each is in and times in local time (or on the simulated clock), the open maintenance
requests and the operator's actions. `--json`: the store's figures as they are (SI, epoch times).

`dt status --bus plant.yaml 'dt/*/*'` sends ONE query on `dt/*/*/status` (`--kind`: status,
health, requests, tests, provenance, or * for all) through the plant's router, prints a table of
every cell that answered within `--timeout` and names the cells of the plant config's `cells:`
that did not (docs/plant.md). `--json`: {key, kind, cells: [...], answered, expected, missing}.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from dt_kernel.errors import TwinError
from dt_kernel.units import MM_PER_M


def add_arguments(st: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt status`` (docs/cli.md, ``dt status``).

    Parameters
    ----------
    st : argparse.ArgumentParser
        The subcommand's parser.
    """
    st.add_argument("--store", default="out/run/dt.sqlite", help="the daemon's SQLite store")
    st.add_argument("--bus", default=None, metavar="YAML",
                    help="ask the cells on the bus instead (a plant config, configs/plant/, or a bus config)")
    st.add_argument("selector", nargs="?", default=None,
                    help="with --bus: the cells asked, a key expression (default dt/*/*: every cell)")
    st.add_argument("--kind", default="status", help="with --bus: status, health, requests, tests or provenance")
    st.add_argument("--timeout", type=float, default=3.0, metavar="S",
                    help="with --bus: how long to wait for the cells' answers (default 3 s)")
    st.add_argument("--json", action="store_true",
                    help="print one JSON object (the raw figures: SI units, epoch times)")


def run(args: argparse.Namespace) -> Any:
    """Read the daemon's state and last figures from its store, or (``--bus``) ask every cell of the plant once.

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
    from dt_runtime.service.store import Store

    if args.bus is not None:
        from dt_runtime.plant.config import load_plant_config
        from dt_runtime.plant.status import plant_status

        return plant_status(load_plant_config(args.bus), args.selector or "dt/*/*", args.kind, args.timeout)
    if args.selector is not None:
        raise TwinError(f"a selector ({args.selector!r}) asks the cells on the bus: give --bus plant.yaml")
    if not Path(args.store).exists():
        raise TwinError(f"{args.store}: no such store (start `dt run` first)")
    with Store(args.store) as st:
        return st.last_figures()


def _wall(epoch: float | None) -> str:
    """A wall-clock time (epoch s) in local time, with how long ago."""
    if epoch is None:
        return "never"
    ago = time.time() - epoch
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(epoch))
    return f"{when} ({_ago(ago)} ago)" if ago >= 0 else when


def _ago(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h"


def _mm(d: dict, keys: str) -> str:
    """Three values of a row (m) as 'x 1.234  y ...' in mm; 'none' where not stated."""
    return "  ".join(f"{a} " + ("none" if d.get(k) is None else f"{d[k] * MM_PER_M:.3f}")
                     for a, k in zip("xyz", keys.split()))


def human(r: dict) -> str:
    """The text ``dt status`` prints without ``--json``.

    Parameters
    ----------
    r : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    from dt_runtime.service.rows import shown_time

    if "answered" in r:
        return _plant(r)
    state = r.get("state") or {}
    esc = state.get("data") or {}
    lines = [f"store {r['path']}"]
    if esc:
        lines.append(f"escalation state: {esc.get('state')} (episode {esc.get('episode', 0)})"
                     + (f", halted: {esc['halt_reason']}" if esc.get("halt_reason") else "")
                     + f"; saved {_wall(state.get('updated'))}")
        if esc.get("offer"):  # a rigid shift of the camera set-up: what applying it would do
            o = esc["offer"]
            lines.append(f"re-referencing offered: the failing readings are one shift of the set-up, "
                         f"{', '.join(f'{v:+.3f}' for v in o['translation_mm'])} mm, "
                         f"{', '.join(f'{v:+.3f}' for v in o['rotation_mrad'])} mrad (n {o['n']}, "
                         f"p {o['p_before']:.2g} before, {o['p_after']:.2g} after); apply it: "
                         f"dt ack --store {r['path']} --rereference --by NAME --note TEXT")
    else:
        lines.append("escalation state: none saved yet (a fresh store)")
    c, tt = r["counts"], r["t_tests"]
    failed = f" ({100 * tt['failed'] / tt['n']:.1f} %)" if tt["n"] else ""
    lines.append(f"rows: {c['commands']} commands, {c['measurements']} MVS measurements, {tt['n']} Eq. 17 tests, "
                 f"{tt['failed']} failed{failed}; {c['transitions']} transitions"
                 + (f"; {r['dropped_rows']} rows dropped (store writes failed)" if r.get("dropped_rows") else ""))
    cmd, corr = r.get("last_command"), r.get("last_correction")
    if cmd:
        speed = "" if cmd.get("speed") is None else f" at {cmd['speed'] * MM_PER_M:.0f} mm/s"
        lines.append(f"last command, {shown_time(cmd['t'])}: target (robot frame) {_mm(cmd, 'x y z')} mm{speed}")
    if corr and corr.get("ux") is None:
        lines.append("  sent uncorrected (the correction was not trusted): no uncertainty claimed")
    elif corr:
        lines.append(f"  correction applied (command - target, robot frame) {_mm(corr, 'dx dy dz')} mm; "
                     f"standard uncertainty of the position reached (GL axes) {_mm(corr, 'ux uy uz')} mm")
    m = r.get("last_measurement")
    if m:
        lines.append(f"last MVS measurement, {shown_time(m['t'])}: TCP (MVS frame) {_mm(m, 'x y z')} mm; "
                     f"e_LT_hat - e_MVS (GL) {_mm(m, 'ex ey ez')} mm")
    t = r.get("last_tstat")
    if t:
        lines.append(f"last Eq. 17 test, {shown_time(t['t'])}: t = {t['t_value']:.2f} on the worst axis, "
                     + (f"p = {t['p_value']:.3g}, " if t.get("p_value") is not None else "")
                     + ("passed" if t.get("passed") else "failed"))
    tr = r.get("last_transition")
    if tr:
        lines.append(f"last transition, {shown_time(tr['t'])}: {tr['src']} -> {tr['dst']}"
                     + _evidence(tr.get("evidence") or {}))
    lines.append(f"maintenance requests: {r['outbox_pending']} not acknowledged"
                 + (f", the oldest made {_wall(r['oldest_pending_created'])}" if r.get("oldest_pending_created")
                    else ""))
    for q in r.get("requests") or []:
        lines.append(f"  #{q['id']} to {q.get('group')}, {q.get('kind')}, episode {q.get('episode')}, made "
                     f"{_wall(q.get('created'))}: " + (f"acknowledged {_wall(q['acked_at'])}" if q.get("acked")
                                                       else f"not acknowledged ({q.get('attempts', 0)} attempts)")
                     + (f"; {q['reason']}" if q.get("reason") else ""))
    for a in r.get("operator_actions") or []:
        lines.append(f"  operator: {a['kind']} by {a['by']} ({a['source']}), {_wall(a['created'])}: {a['note']}"
                     + (f"; {_applied(a['result'])}" if a.get("applied_at") else "; not applied yet"))
    return "\n".join(lines)


def _applied(result: str | None) -> str:
    """An applied action's result as a clause: the store's text says 'applied: ...' or 'ignored: ...'
    itself (service.paging), a delivery confirmation does not."""
    text = result or ""
    return text if text.startswith(("applied", "ignored")) else f"applied: {text}"


def _evidence(e: dict) -> str:
    """The evidence an operator reads first (the rest: `dt status --json`): the rule that fired,
    the failures in the window and the CUSUM, a halt's reason, who acknowledged and why."""
    parts = []
    if e.get("rule"):
        parts.append(f"rule {e['rule']}")
    if e.get("window_len"):
        parts.append(f"{e.get('window_failures')} of the last {e['window_len']} tests failed, CUSUM "
                     f"{e.get('cusum', 0):.2f} (limit {e.get('cusum_h')})")
    parts += [f"halted: {e['halt_reason']}"] if e.get("halt_reason") else []
    parts += [str(e["reason"])] if e.get("reason") else []
    parts += [f"by {e['by']}: {e.get('note', '')}"] if e.get("by") else []
    return (" (" + "; ".join(parts) + ")") if parts else ""


def _plant(r: dict) -> str:
    """The plant's table: one line per answer (status: state, escalation, open requests, last
    tick, twin), then the expected cells that did not answer."""
    lines = [f"{len(r['answered'])} cell(s) answered {r['key']} in {r['elapsed_ms'] / 1e3:.2f} s"
             + (f" ({len(r['expected'])} expected)" if r["expected"] else "")]
    head = f"{'cell/robot':<24} {'kind':<10} {'status':<9} {'escalation':<22} {'open':>4}  last tick / answer"
    lines.append(head)
    for c in r["cells"]:
        name = f"{c.get('cell')}/{c.get('robot')}"
        if "error" in c:
            lines.append(f"{name:<24} {c.get('kind', '?'):<10} error: {c['error']}")
            continue
        opened = c.get("open_requests", len(c["open"]) if isinstance(c.get("open"), list) else "")
        when = c.get("last_tick") or c.get("t")
        lines.append(f"{name:<24} {c.get('kind', ''):<10} {c.get('status', '') or '':<9} "
                     f"{c.get('escalation', '') or '':<22} {opened!s:>4}  {_wall(when)}"
                     + (f"; {c['reason']}" if c.get("reason") else ""))
    if r["missing"]:
        lines.append(f"did not answer: {', '.join(r['missing'])}")
    for e in r.get("errors") or []:
        lines.append(f"unreadable reply: {e}")
    return "\n".join(lines)
