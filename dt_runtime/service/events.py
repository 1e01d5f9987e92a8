"""What the daemon's parts tell each other, as small typed events on one `Events` hub.

The escalation's transitions (`Transition`, once recorded in the store), requests waiting in the
outbox (`RequestsQueued`), an operator's action stored (`ActionQueued`) and a change of health
(`HealthDue`) are emitted; whoever needs them
subscribes (the bus publishes `.../state` and delivers requests, the health reporter marks
`.../health` due, the housekeeping thread sends it). A subscriber runs on the emitter's thread,
in the order subscribed; none blocks (they queue work or set a flag).
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar


@dataclass(frozen=True)
class Transition:
    """The escalation moved `src` -> `dst` at daemon time `t` (s) on `evidence`; `requests`: the
    outbox ids the transition opened (none unless it entered a paging state)."""

    src: str
    dst: str
    t: float
    evidence: dict[str, Any] = field(default_factory=dict)
    requests: tuple[int, ...] = ()

    def payload(self) -> dict[str, Any]:
        """What `.../state` carries."""
        return {"src": self.src, "dst": self.dst, "t": self.t, "evidence": self.evidence}


@dataclass(frozen=True)
class RequestsQueued:
    """Maintenance requests `ids` are in the outbox (re-created at start-up): deliver them."""

    ids: tuple[int, ...]


@dataclass(frozen=True)
class ActionQueued:
    """An operator action `id` was stored (a 'done' on the bus): the housekeeping thread picks it up now."""

    id: int


@dataclass(frozen=True)
class HealthDue:
    """The health changed (or must be sent now): `.../health` is to be published."""


E = TypeVar("E")


class Events:
    """Subscribers by event type; `emit` calls those of the event's type, in subscription order."""

    def __init__(self) -> None:
        self._subscribers: dict[type, list[Callable[[Any], None]]] = defaultdict(list)

    def subscribe(self, kind: type[E], handler: Callable[[E], None]) -> None:
        """Call `handler(event)` for every event of type `kind` emitted from now on.

        Parameters
        ----------
        kind : type
            The event's class (`Transition`, `RequestsQueued`, `ActionQueued`, `HealthDue`).
        handler : callable
            Called with the event on the emitter's thread; must not block.
        """
        self._subscribers[kind].append(handler)

    def emit(self, event: object) -> None:
        """Deliver `event` to the subscribers of its type (none: nothing happens).

        Parameters
        ----------
        event : object
            One of this module's events.
        """
        for handler in self._subscribers.get(type(event), ()):
            handler(event)
