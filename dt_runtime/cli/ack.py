"""`dt ack`: the operator's path out of `maintenance_requested` (or `halted`).

Maintenance was done (default), or only the delivery of a request is confirmed
(`--delivered-only`: the bus stops republishing it, the state stays). Who (`--by`) and why
(`--note`) are stored with the action and, once the daemon applies it, with the transition back to
nominal. Two ways to reach the daemon: `--store FILE` at the cell (the action is written to its
store; `--wait S` waits until it is applied), or `--bus FILE --request ID --uid UID` from a
maintenance system elsewhere (published signed with the service's key, `bus.auth.key_file`).
`--request ID` names the request answered (default, with --store: the newest one).
`--rereference` (with --store) applies an open re-referencing offer instead: the escalation is in
`rereference_offered` because the failures are one rigid shift of the camera set-up
(docs/service.md, "Re-referencing instead of paging").

Who can act, and the bus's rules: docs/cli.md ("dt ack") and docs/bus.md."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from dt_kernel.errors import TwinError


def add_arguments(a: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt ack`` (docs/cli.md, ``dt ack``).

    Parameters
    ----------
    a : argparse.ArgumentParser
        The subcommand's parser.
    """
    where = a.add_mutually_exclusive_group(required=True)
    where.add_argument("--store", metavar="FILE", help="the daemon's SQLite store (the runtime YAML's `store:`)")
    where.add_argument("--bus", metavar="YAML", help="a bus config (configs/bus.yaml) to publish the action on")
    a.add_argument("--by", required=True, help="who confirms (a name or badge id)")
    a.add_argument("--note", required=True, help="why: what was done")
    a.add_argument("--request", type=int, default=None, metavar="ID", help="the request's id (default: newest)")
    a.add_argument("--uid", default=None, help="the request's uid (with --bus; as `dt consume` printed it)")
    a.add_argument("--cell", default=None, help="with --bus: the twin's cell (default: the bus config's)")
    a.add_argument("--robot", default=None, help="with --bus: the twin's robot (default: the bus config's)")
    a.add_argument("--rereference", action="store_true",
                   help="apply the offered re-referencing of the camera frame (escalation rereference_offered; "
                        "with --store)")
    a.add_argument("--delivered-only", action="store_true",
                   help="only confirm that the request was delivered (the state stays)")
    a.add_argument("--wait", type=float, default=0.0, metavar="S",
                   help="with --store: wait up to S seconds for the daemon to apply it")
    a.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> Any:
    """Record (``--store``) or publish (``--bus``) the operator's action: maintenance done, or a request delivered.

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
    if not args.by.strip() or not args.note.strip():
        raise TwinError("--by and --note must not be empty: the record says who confirmed what")
    return _via_bus(args) if args.bus else _via_store(args)


def _via_store(args: argparse.Namespace) -> dict[str, Any]:
    from dt_runtime.service.store import Store

    if not Path(args.store).exists():
        raise TwinError(f"{args.store}: no such store (the runtime YAML's `store:`)")
    if args.rereference:
        return _rereference(args)
    with Store(args.store) as st:
        requests = st.requests(limit=1000)
        if not requests:
            raise TwinError(f"{args.store}: no maintenance request was ever made; nothing to acknowledge")
        rid = requests[0]["id"] if args.request is None else args.request
        req = next((r for r in requests if r["id"] == rid), None)
        if req is None:
            raise TwinError(f"{args.store}: no request {rid}; the newest are "
                            + ", ".join(str(r["id"]) for r in requests[:10]))
        if args.delivered_only:
            same = [r["id"] for r in requests if r.get("episode") == req.get("episode") and not r["acked"]]
            for i in same if req.get("episode") is not None else [rid]:
                st.outbox_ack(i)
            aid = st.add_action("delivered", args.by, args.note, request_id=rid, source="cli",
                                applied=f"delivery of {len(same)} copies confirmed")
            return {"action": aid, "kind": "delivered", "request": rid, "applied": True,
                    "result": f"delivery of {len(same)} copies confirmed"}
        aid = st.add_action("done", args.by, args.note, request_id=rid, source="cli")
        return {"action": aid, "kind": "done", "request": rid, **_wait_applied(st, aid, args.wait)}


def _wait_applied(st: Any, aid: int, wait_s: float) -> dict[str, Any]:
    """Whether the daemon applied action `aid` within `wait_s`, and its result."""
    deadline = time.monotonic() + max(0.0, wait_s)
    while True:
        act = next((a for a in st.actions(limit=1000) if a.id == aid), None)
        if (act is not None and act.applied_at is not None) or time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    applied = act is not None and act.applied_at is not None
    return {"applied": applied, "result": act.result if applied and act else
            "recorded: the daemon applies it at its next tick (or its next start)"}


def _rereference(args: argparse.Namespace) -> dict[str, Any]:
    """Store a 'rereference' action; the daemon applies it if it offers re-referencing."""
    from dt_runtime.service.store import Store

    if args.delivered_only or args.request is not None:
        raise TwinError("--rereference answers the open re-referencing offer: no --request, no --delivered-only")
    with Store(args.store) as st:
        saved = st.load_state() or {}
        data = saved.get("data", {})
        state = data.get("state")
        if data.get("offer") is None or (state != "rereference_offered"
                                         and (state, data.get("halted_from")) != ("halted", "rereference_offered")):
            raise TwinError(f"{args.store}: no re-referencing is offered (the escalation is {state or 'unknown'}); "
                            "`dt status` shows the state")
        aid = st.add_action("rereference", args.by, args.note, source="cli")
        return {"action": aid, "kind": "rereference", "offer": saved["data"].get("offer"),
                **_wait_applied(st, aid, args.wait)}


def _via_bus(args: argparse.Namespace) -> dict[str, Any]:
    import threading

    from dt_runtime.fabric import load_bus_config
    from dt_runtime.fabric.auth import Signer
    from dt_runtime.fabric.consumer import publish_done
    from dt_runtime.fabric.session import close_session, open_session, zenoh_errors

    if args.rereference:
        raise TwinError("--rereference is applied at the cell: use --store FILE")
    if args.request is None or not args.uid:
        raise TwinError("--bus needs --request ID and --uid UID of the request (as `dt consume` printed them)")
    if args.delivered_only:
        raise TwinError("--delivered-only over the bus is what a consumer's ack does: `dt consume` sends it")
    cfg = load_bus_config(args.bus)
    signer = Signer(cfg.auth, create=False)  # only the service makes a key: a new one here could not be right
    prefix = f"dt/{args.cell or cfg.cell}/{args.robot or cfg.robot}"
    key = f"{prefix}/maintenance/done/{args.request}"
    applied = threading.Event()

    def done() -> None:  # signed afresh for every copy: its time must stay within bus.auth.max_age_s
        publish_done(session, signer, prefix, args.request, args.uid, args.by, args.note)

    def on_state(sample: Any) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            if signer.check(str(sample.key_expr), msg, fresh=False):
                return  # not the daemon's: anyone can publish a 'state'
            ev = msg.get("evidence", {})
            if msg.get("dst") == "nominal" and ev.get("by") == args.by and ev.get("note") == args.note:
                applied.set()
        except (ValueError, AttributeError):
            pass

    session = open_session(cfg)
    try:
        with zenoh_errors(f"cannot subscribe to {prefix}/state"):
            sub = session.declare_subscriber(f"{prefix}/state", on_state)
        # Re-sent until the twin's state shows it applied (or --wait ends): a put made before
        # the peers have met is lost, and the twin ignores copies once it is back to nominal.
        deadline = time.monotonic() + max(0.0, args.wait)
        done()
        while not applied.wait(1.0) and time.monotonic() < deadline:
            done()
        sub.undeclare()
    finally:
        close_session(session, cfg.close_timeout_s)
    return {"kind": "done", "request": args.request, "published": key,
            "applied": applied.is_set() if args.wait else None}


def human(result: dict) -> str:
    """The text ``dt ack`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    if "published" in result:  # over the bus
        state = {True: "applied: the twin is back to nominal", False: "not applied within --wait",
                 None: "not waited for (--wait S to see it applied)"}[result.get("applied")]
        return f"'done' for request {result['request']} published on {result['published']}; {state}"
    what = "delivery confirmed" if result["kind"] == "delivered" else "maintenance done recorded"
    return f"request {result['request']}: {what} (action {result['action']}); {result['result']}"
