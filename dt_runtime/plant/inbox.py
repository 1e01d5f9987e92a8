"""The plant's maintenance inbox: every cell's requests, through the fabric, into one history.

`PlantInbox` commits each new request to the plant history BEFORE it is acknowledged, so a
failed commit leaves it unacknowledged and the cell republishes it (at least once, end to end);
a restarted inbox reads back what its history holds. The contract: docs/plant.md ("One
maintenance inbox")."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from dt_runtime.fabric.config import BusConfig
from dt_runtime.fabric.consumer import MaintenanceConsumer
from dt_runtime.plant.history import History, open_history


class PlantInbox:
    """A MaintenanceConsumer of one consumer group whose new requests go into the plant history.

    Parameters
    ----------
    bus : BusConfig
        The plant's bus.
    history_url : str
        The history (see open_history).
    group : str
        The consumer group.
    key_expr : str
        The requests subscribed to.
    on_request : callable or None
        Called with each new request after it is recorded.

    Raises
    ------
    StoreError
        When the history cannot be opened or read.
    BusError
        When the consumer cannot join the bus.
    """
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
        """The distinct requests received since the inbox opened."""
        return self.consumer.requests

    def wait_for(self, n: int, timeout: float) -> bool:
        """Wait until at least ``n`` distinct requests arrived.

        Parameters
        ----------
        n : int
        timeout : float
            s.

        Returns
        -------
        bool
            False on time-out.
        """
        return self.consumer.wait_for(n, timeout)

    def close(self) -> None:
        """Close the consumer, then the history."""
        try:
            self.consumer.close()
        finally:
            self.history.close()

    def __enter__(self) -> PlantInbox:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
