"""`Dashboard`: the parts of `dt dashboard` put together and started (the twin's scene, the hub,
the bus feed, the web server: uvicorn in its own thread); `close()` stops them in reverse. Tests and the
benchmark start it in process; `dt dashboard` wraps it. Without a runtime config it serves the
metrologist's page only (`results`: no bus, no twin of a cell); with a plant config (`plant`), the
plant page (/plant: every cell on the fabric, plant.PlantWatch)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Protocol

from dt_kernel.errors import ConfigError
from dt_runtime.common.paths import beside
from dt_runtime.dashboard.feed import BusFeed, joining
from dt_runtime.dashboard.hub import Hub
from dt_runtime.dashboard.operators import Operators, load_operators
from dt_runtime.dashboard.plant import PERIOD_S, PlantWatch
from dt_runtime.dashboard.results import find_results
from dt_runtime.dashboard.scene import Scene
from dt_runtime.dashboard.server import DashboardServer, is_loopback
from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.auth import Signer
from dt_runtime.plant.config import PlantConfig

log = logging.getLogger("dt.dashboard")


class LiveCell(Protocol):
    """What the dashboard reads of a cell's runtime config (`service.runtime_config.RuntimeConfig`
    has it): the dashboard joins the cell's bus and shows its twin, without the daemon's modules."""

    @property
    def bus(self) -> BusConfig:
        """The cell's bus."""
        ...

    @property
    def twin(self) -> str:
        """The twin directory, relative to the config's directory unless absolute."""
        ...

    @property
    def alpha(self) -> float:
        """Eq. 17's significance level."""
        ...


class Dashboard:
    """The parts of ``dt dashboard`` put together and started; ``close()`` stops them in reverse.

    Everything is read and checked before anything opens (a bad token file or key opens no session).

    Parameters
    ----------
    cfg : LiveCell or None
        The live cell's runtime config (its twin and bus); None serves no live cell.
    config_path : str, Path or None
        The runtime config's path (the twin's path is relative to its directory).
    bus : BusConfig or None
        A bus config of the dashboard's own; by default it joins the daemon's (feed.joining).
    host : str
        The address served; beyond loopback only with TLS.
    port : int
        0 picks a free one.
    token_file : str, Path or None
        The operators' token file (operators.load_operators); without it the page is read-only.
    group : str
        The consumer group whose copy of a request the operators acknowledge.
    tls : tuple of (str or None, str or None)
        PEM certificate chain and private key, both or neither.
    max_rate_hz : float
        Batches a second per page, at most.
    results : str, Path or None
        A directory of results for the metrologist's page (/metrology).
    plant : PlantConfig or None
        A plant config for the plant page (/plant).
    plant_period_s : float
        s between the plant page's queries.

    Raises
    ------
    ConfigError
        When none of ``cfg``, ``results``, ``plant`` is given, ``results`` is not a directory, only
        one of the TLS files is given, ``host`` is not loopback without TLS, the token file or the bus
        key is refused, or the certificate cannot be read.
    BusError
        When the bus cannot be joined.
    """
    def __init__(self, cfg: LiveCell | None, config_path: str | Path | None, *, bus: BusConfig | None = None,
                 host: str = "127.0.0.1", port: int = 8765, token_file: str | Path | None = None,
                 group: str = "maintenance", tls: tuple[str | None, str | None] = (None, None),
                 max_rate_hz: float = 50.0, results: str | Path | None = None, plant: PlantConfig | None = None,
                 plant_period_s: float = PERIOD_S):
        if cfg is None and results is None and plant is None:
            raise ConfigError("<command line>", "--config/--results/--plant", None, "a runtime YAML (the live "
                              "cell), a directory of results (the metrologist's view), a plant config (the plant "
                              "page), or several")
        if results is not None:
            results = Path(results).resolve()
            find_results(results)  # a directory, or a ConfigError now rather than on the page
        cert, key = tls
        if (cert is None) != (key is None):
            raise ConfigError("<command line>", "--tls-cert/--tls-key", cert or key, "both, or neither")
        if not is_loopback(host) and cert is None:
            raise ConfigError("<command line>", "--host", host,
                              "a loopback address (127.0.0.1, ::1, localhost), or --tls-cert and --tls-key: beyond "
                              "the host the page is served over TLS only (the operators' tokens travel in it)")
        # Everything is read and checked before anything opens: a bad token file or key opens no session.
        self.operators: Operators | None = load_operators(token_file) if token_file is not None else None
        self.hub = Hub()
        self._closers: list[Any] = []
        self.scene: Scene | None = None
        self.feed: BusFeed | None = None
        self.plant: PlantWatch | None = None
        try:
            if cfg is not None:
                self._join(cfg, Path(config_path or "."), bus, group)
            if plant is not None:
                self.plant = PlantWatch(plant, plant_period_s)
                self._closers.append(self.plant.close)
            self.server = DashboardServer((host, port), self.hub, self.scene, self.feed, self.operators, max_rate_hz,
                                          results, self.plant, tls=(cert, key))
            self._closers.append(self.server.stop)
            self.server.start()
        except BaseException:
            self.close()
            raise

    def _join(self, cfg: LiveCell, config_path: Path, bus: BusConfig | None, group: str) -> None:
        """The live cell: the twin's scene and the bus feed."""
        bus_cfg = bus if bus is not None else joining(cfg.bus, str(config_path))
        # To act, the service's key (as `dt ack --bus`: never made here, a new one could not be the service's);
        # to read, the key is used when present, to refuse what the daemon did not sign.
        signer: Signer | None = None
        if self.operators is not None:
            signer = Signer(bus_cfg.auth, create=False)
        else:
            try:
                signer = Signer(bus_cfg.auth, create=False)
            except ConfigError as exc:
                log.info("dashboard: read-only without the bus key (messages not checked): %s", exc)
        twin = Path(cfg.twin)
        self.scene = Scene(beside(config_path.parent, twin), cfg.alpha)
        self.feed = BusFeed(bus_cfg, self.hub, self.scene, signer, group)
        self._closers.append(self.feed.close)

    @property
    def url(self) -> str:
        """The page's URL (``http://`` or ``https://``, with the port bound)."""
        return self.server.url

    def summary(self) -> dict[str, Any]:
        """What ``dt dashboard --json`` prints: the URL, the bus prefix, messages received, refused and
        dropped, the metrology and plant pages' URLs (False without them), the actions and the operators.

        Returns
        -------
        dict
        """
        return {"url": self.url, "bus": self.feed.prefix if self.feed else None, "received": dict(self.hub.received),
                "bus_refused": self.hub.bus_refused, "dropped": self.feed.dropped if self.feed else 0,
                "metrology": self.server.results is not None and self.url + "metrology",
                "plant": self.plant is not None and self.url + "plant",
                "actions": list(self.server.actions),
                "operators": self.operators.names if self.operators else []}

    def close(self) -> None:
        """Stop every part in reverse order (errors are logged, the rest still closed)."""
        while self._closers:
            close = self._closers.pop()
            try:
                close()
            except Exception as exc:  # noqa: BLE001 - closing is best effort, keep closing the rest
                log.warning("dashboard: while closing: %s", exc)

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
