"""Escalation, paging and the operator's actions of one daemon.

Every transition of the machine (`service.escalation`) is one store transaction with the
machine's new snapshot and, on entering `maintenance_requested` or `halted`, that episode's
maintenance requests (one per consumer group) in the outbox; only then is it published
(`.../state`, `.../health`) and the bus woken to deliver the requests, which it republishes
until each group acknowledges. If the store cannot commit, the machine stays where it was and
the next test fires the transition again. A recorded transition is emitted as a
`service.events.Transition` (the bus publishes it, the health reporter marks `.../health` due);
requests re-created at start-up as `RequestsQueued`. At start-up a paging state that has no requests gets
them (`reconcile`), and the machine resumes from the store's snapshot.

Operator: `dt ack` (or a maintenance system's `.../maintenance/done/<id>` on the bus, signed with
the service's key: bus.auth) stores an operator action (who, why); the housekeeping thread
queues it (`take_actions`) and the loop applies it (`apply_actions`): `maintenance_requested` or
`halted` -> `nominal`, statistics reset, in the transition's transaction. A 'done' that names a
request of an earlier episode is stored as ignored. A 'rereference' applies an open offer
(`rereference_offered`) and returns to `nominal` (docs/service.md, "Re-referencing instead of paging").
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from dt_runtime.fabric import BusConfig
from dt_runtime.service.escalation import PAGING, EscalationConfig, Escalator, Jacobian
from dt_runtime.service.events import Events, HealthDue, RequestsQueued, Transition
from dt_runtime.service.publisher import new_requests
from dt_runtime.service.store import OperatorAction, Store

log = logging.getLogger("dt.run")


class Paging:
    """The escalation machine with its store records, maintenance requests and operator actions;
    every recorded transition is emitted on `events`. The machine resumes from the store's resume
    row when there is one.

    Parameters
    ----------
    escalation : EscalationConfig
        The machine's thresholds.
    bus_cfg : BusConfig
        Names the requests' keys and consumer groups.
    store : Store
        Where transitions, requests and actions are recorded.
    events : Events
        Where `Transition` and `RequestsQueued` are emitted.
    resume_extra : callable
        What else resumes with the machine, added to the resume row (a path program's state
        under `path`, the camera frame's re-referencing under `mvs_rereferenced`, the stated U's
        adaptive scale under `stated_u`, read back as `saved_extra`).
    on_rereference : callable
        `on_rereference(offer)` applies an offer's fitted shift (`Escalator.shift`) before the
        transition to nominal is recorded; `undo()` of what it returns puts it back if that
        record fails. Default: nothing to apply.
    jacobian : callable, optional
        The arm's position Jacobian in GL axes (`escalation.Jacobian`); without it no
        re-referencing is offered (`Escalator`).

    Raises
    ------
    StateError
        The stored snapshot cannot be restored.
    StoreError
        The store could not be read.

    Threads: the loop moves the machine and applies actions; the housekeeping thread queues
    actions (`take_actions`); the bus worker calls `on_ack`.
    """

    def __init__(self, escalation: EscalationConfig, bus_cfg: BusConfig, store: Store, events: Events,
                 resume_extra: Callable[[], dict[str, Any]] = dict,
                 on_rereference: Callable[[dict[str, Any]], Callable[[], None]] | None = None,
                 jacobian: Jacobian | None = None):
        self.bus_cfg, self.store, self.events = bus_cfg, store, events
        self.requests: list[dict] = []  # the requests this daemon opened (the first group's, with all ids)
        self.delivered: list[int] = []  # outbox ids a consumer acknowledged
        self.actions: collections.deque[OperatorAction] = collections.deque()  # queued for the loop
        self._actions_seen: set[int] = set()
        self._actions_lock = threading.Lock()
        self._applying: OperatorAction | None = None  # the 'done' whose transition is being recorded
        self.escalator = Escalator(escalation, on_transition=self._on_transition, jacobian=jacobian)
        # What else resumes from the store's one resume row beside the machine (the daemon's path
        # program: its resume point): a key of that row, read back by `saved_extra`.
        self.resume_extra = resume_extra
        self.on_rereference = on_rereference
        saved = store.load_state()
        self.saved_extra: dict[str, Any] = {}
        if saved and saved.get("name") == "escalation":
            self.escalator.restore(saved["data"])
            self.saved_extra = {k: v for k, v in saved["data"].items() if k in ("path", "mvs_rereferenced", "stated_u")}
            log.info("resumed escalation state %s (episode %d) from %s", self.escalator.state,
                     self.escalator.episode, store.path)

    def resume_row(self) -> tuple[str, dict[str, Any]]:
        """The store's resume row: the machine's snapshot and what `resume_extra` adds."""
        return "escalation", self.escalator.snapshot() | self.resume_extra()

    # --- transitions and requests (callbacks never block on the bus) ---------------------------
    def _request_body(self, dst: str, evidence: dict, t: float, reconciled: bool = False) -> dict:
        esc = self.escalator
        halt = dst == "halted"
        return {"t": t, "state": dst, "episode": esc.episode, "kind": "halt" if halt else "t_test",
                "reason": (f"halted: {esc.halt_reason}" if halt
                           else evidence.get("reason", "repeated Eq. 17 t-test failures")),
                "evidence": evidence, **({"reconciled": True} if reconciled else {})}

    def _on_transition(self, src: str, dst: str, evidence: dict, t: float) -> None:
        """Record first (one transaction; raises StoreError and the machine stays), then act."""
        opens = dst in PAGING and src not in PAGING
        reqs = new_requests(self.bus_cfg, self._request_body(dst, evidence, t)) if opens else []
        applying = self._applying
        applied = (applying.id, f"applied: {src} -> {dst}") if applying is not None and dst == "nominal" else None
        _, ids = self.store.record_transition(src, dst, evidence, t, state=self.resume_row(),
                                              requests=reqs, applied=applied)
        log.warning("escalation %s -> %s at t=%.1f s: %s", src, dst, t, evidence)
        if reqs:
            self.requests.append(reqs[0][1] | {"ids": ids})
        self.events.emit(Transition(src, dst, t, evidence, tuple(ids) if reqs else ()))

    def reconcile(self, now: float) -> None:
        """A paging state without its requests (a store written by an older version, or edited)
        gets them now, emitted as `RequestsQueued`.

        Parameters
        ----------
        now : float
            Daemon time, s: the requests' time when no transition into the state is stored.

        Raises
        ------
        StoreError
            The store could not be read or the requests not committed.
        """
        esc = self.escalator
        if esc.state in PAGING and not self.store.outbox_of_episode(esc.episode):
            last = next((tr for tr in reversed(self.store.transitions(50)) if tr["dst"] == esc.state), None)
            evidence = last["evidence"] if last else esc.evidence()
            body = self._request_body(esc.state, evidence, last["t"] if last else now, reconciled=True)
            ids = self.store.outbox_add_many(new_requests(self.bus_cfg, body))
            self.requests.append(body | {"ids": ids})
            log.warning("state %s (episode %d) had no maintenance request in %s: re-created %s",
                        esc.state, esc.episode, self.store.path, ids)
            self.events.emit(RequestsQueued(tuple(ids)))

    def on_ack(self, oid: int, payload: dict) -> None:
        """A consumer acknowledged delivery of outbox entry `oid` (the bus worker's thread): noted
        in `delivered`. The machine stays in maintenance_requested until maintenance is confirmed
        done, or the same fault would page again at once.

        Parameters
        ----------
        oid : int
            The outbox id.
        payload : dict
            The acknowledgement (not used).
        """
        self.delivered.append(oid)

    # --- operator actions -----------------------------------------------------------------------
    def acknowledge(self, note: str, by: str) -> int:
        """Operator confirmation, as `dt ack` does it: stored as an action (who, why), applied by
        the loop at its next tick.

        Parameters
        ----------
        note : str
            Why.
        by : str
            Who.

        Returns
        -------
        int
            The action's id.

        Raises
        ------
        StoreError
            A blank `note` or `by`, or the action could not be stored.
        """
        with self._actions_lock:  # the housekeeper must not queue it a second time
            aid = self.store.add_action("done", by, note, source="api")
            self._actions_seen.add(aid)
            self.actions.append(OperatorAction(aid, time.time(), "done", None, by, note, "api"))
        return aid

    def rereference(self, note: str, by: str) -> int:
        """Operator: apply the offered re-referencing, as `dt ack --rereference` does it: stored as
        an action (who, why), applied by the loop at its next tick.

        Parameters
        ----------
        note : str
            Why.
        by : str
            Who.

        Returns
        -------
        int
            The action's id.

        Raises
        ------
        StoreError
            A blank `note` or `by`, or the action could not be stored.
        """
        with self._actions_lock:
            aid = self.store.add_action("rereference", by, note, source="api")
            self._actions_seen.add(aid)
            self.actions.append(OperatorAction(aid, time.time(), "rereference", None, by, note, "api"))
        return aid

    def take_actions(self) -> None:
        """Housekeeping: queue the operator actions the loop has not seen (never blocks the loop)."""
        with self._actions_lock:
            for a in self.store.actions(pending_only=True):
                if a.kind in ("done", "rereference") and a.id not in self._actions_seen:
                    self._actions_seen.add(a.id)
                    self.actions.append(a)

    def apply_actions(self, t: float) -> None:
        """Apply the queued 'done' actions (the loop's thread: transitions are the loop's alone).
        One applied returns maintenance_requested or halted to nominal and marks the episode's
        requests delivered; one for another state or an earlier episode is stored as ignored.

        Parameters
        ----------
        t : float
            Daemon time, s.

        Raises
        ------
        StoreError
            A record could not be committed; the action stays queued unless its transition was
            already recorded.
        """
        while self.actions:
            a = self.actions[0]
            esc = self.escalator
            if a.kind == "rereference":
                result = self._apply_rereference(a, t)
                if result is None:
                    continue
            elif esc.state not in PAGING:
                result = f"ignored: the escalation was {esc.state}"
            elif a.request_id is not None and self._episode_of(a.request_id) != esc.episode:
                result = f"ignored: request {a.request_id} is not of the open episode {esc.episode}"
            else:
                episode = esc.episode
                self._applying = a
                try:
                    esc.acknowledge(t, note=a.note, by=a.by)  # records the action as applied, same transaction
                finally:
                    self._applying = None
                self.actions.popleft()  # applied: a failing write below must not judge it again
                self.store.outbox_ack_episode(episode)  # done implies delivered: stop republishing
                # the transition's health went out before these acks: without a fresh one, .../health
                # (the dashboard, dt status --bus) kept counting the done request as not acknowledged
                self.events.emit(HealthDue())
                continue
            self.store.apply_action(a.id, result)
            log.info("operator action %d (%s by %s) %s", a.id, a.kind, a.by, result)
            self.actions.popleft()

    def _apply_rereference(self, a: OperatorAction, t: float) -> str | None:
        """A 'rereference' action: the offer applied and the transition to nominal recorded (None:
        done, the action applied in its transaction), or why it was ignored."""
        esc = self.escalator
        if not esc.offer_open or esc.offer is None:
            return f"ignored: no re-referencing is offered (the escalation is {esc.state})"
        undo = self.on_rereference(esc.offer) if self.on_rereference is not None else None
        halted, episode = esc.state == "halted", esc.episode
        self._applying = a
        try:
            esc.rereference(t, note=a.note, by=a.by)  # records the action as applied, same transaction
        except BaseException:
            if undo is not None:
                undo()
            raise
        finally:
            self._applying = None
        self.actions.popleft()
        if halted:  # the offer had halted the arm (and paged): its requests are answered
            self.store.outbox_ack_episode(episode)
        return None

    def _episode_of(self, request_id: int) -> int | None:
        item = self.store.outbox_get(request_id)
        return None if item is None else item.payload.get("episode")
