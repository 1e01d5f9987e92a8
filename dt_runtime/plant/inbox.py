"""The plant's maintenance inbox: every cell's requests, through the fabric, into one history.

A `MaintenanceConsumer` (fabric: the signed requests of every cell on `dt/**/maintenance/
request`, its consumer group's copies, de-duplicated by (cell, robot, uid), every copy acked)
whose new requests are committed to the plant history (`history`) BEFORE they are acknowledged:
if the commit fails, the request is neither acked nor remembered, and the cell's next
republication brings it again (at least once, end to end). A restarted inbox reads back what its
history holds, so a copy received again is acked, not recorded twice (the history's primary key
makes that true even across two inboxes of the same group writing one PostgreSQL database).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from dt_runtime.fabric.config import BusConfig
from dt_runtime.fabric.consumer import MaintenanceConsumer
from dt_runtime.plant.history import History, open_history


class PlantInbox:
    def __init__(self, bus: BusConfig, history_url: str, *, group: str = "maintenance",
                 key_expr: str = "dt/**/maintenance/request",
                 on_request: Callable[[dict[str, Any]], None] | None = None):
        self.history: History = open_history(history_url)
        self._on_request = on_request
        self.recorded = 0
        try:
            self.consumer = MaintenanceConsumer(bus, key_expr=key_expr, on_request=self._take, group=group,
                                                seen=self.history.seen(group))
        except BaseException:
            self.history.close()
            raise

    def _take(self, req: dict[str, Any]) -> None:
        if self.history.record(req, time.time()):
            self.recorded += 1
        if self._on_request is not None:
            self._on_request(req)

    @property
    def requests(self) -> list[dict[str, Any]]:
        return self.consumer.requests

    def wait_for(self, n: int, timeout: float) -> bool:
        return self.consumer.wait_for(n, timeout)

    def close(self) -> None:
        try:
            self.consumer.close()
        finally:
            self.history.close()

    def __enter__(self) -> PlantInbox:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
