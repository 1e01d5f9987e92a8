"""The plant config (`configs/plant/*.yaml`: router, bus, cells, dashboards, history), validated
once into frozen models; a plain bus config is read as a plant of that bus. The keys:
docs/plant.md ("The plant config")."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, field_validator, model_validator

from dt_kernel.config import Frozen, read_yaml, validate
from dt_runtime.common.paths import beside
from dt_runtime.fabric.config import (
    AccessControlConfig,
    BusConfig,
    TlsConfig,
    check_endpoint,
    zenoh_config,
)

#: Top-level keys that make a YAML a plant config rather than a bus config.
PLANT_KEYS = ("router", "bus", "cells", "dashboards", "history")
POSTGRES_SCHEMES = ("postgresql://", "postgres://")


class RouterConfig(Frozen):
    """The router a plant (or a hall) runs: endpoints, TLS and access control as the bus's."""

    listen: list[str] = ["tcp/127.0.0.1:7447"]
    connect: list[str] = []  # other routers: a hall's router connects to the plant's
    multicast_scouting: bool = False
    gossip_scouting: bool = True
    # Zenoh's default is 1000 sessions per router: a plant of more cells (plus its tools) would
    # have the 1001st refused. A session costs the router about 0.1 MB (benchmarks.plant).
    max_sessions: int = Field(10_000, ge=1)
    # Shared memory between the router and clients on its host: off. Zenoh negotiates it per
    # session and refuses new sessions once its segment's counters run out (about 350 sessions on
    # one host, zenoh 1.10: benchmarks.plant); a plant's messages are small, nothing to gain.
    shared_memory: bool = False
    tls: TlsConfig | None = None
    access_control: AccessControlConfig | None = None
    extra: dict[str, Any] = {}

    @field_validator("listen", "connect")
    @classmethod
    def _eps(cls, v: list[str]) -> list[str]:
        return [check_endpoint(e) for e in v]

    @model_validator(mode="after")
    def _shape(self) -> RouterConfig:
        if not self.listen:
            raise ValueError("a router needs at least one listen endpoint (the cells connect to it)")
        if self.tls is not None and not any(e.startswith(("tls/", "quic/")) for e in self.listen + self.connect):
            raise ValueError("tls is configured but no listen/connect endpoint uses tls/ or quic/")
        return self

    def zenoh_config(self):
        """The Zenoh configuration of this router (router mode, endpoints, TLS, access control,
        ``max_sessions``, shared memory, then ``extra``).

        Returns
        -------
        zenoh.Config
        """
        extra = {"transport/unicast/max_sessions": self.max_sessions,
                 "transport/shared_memory/enabled": self.shared_memory} | self.extra
        return zenoh_config("router", self.listen, self.connect, self.multicast_scouting, self.gossip_scouting,
                            self.tls, self.access_control, extra)


class HistoryConfig(Frozen):
    """Where the plant's inbox records what it received: a file path (SQLite, relative to the
    config's directory) or a `postgresql://` URL."""

    url: str = "plant_history.sqlite"

    @field_validator("url")
    @classmethod
    def _url(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("history.url must be a file path (SQLite) or a postgresql:// URL")
        if "://" in v and not v.startswith(POSTGRES_SCHEMES + ("sqlite:///",)):
            raise ValueError(f"{v!r}: a file path (SQLite), sqlite:///PATH or postgresql://... (other databases: "
                             "not supported)")
        return v

    @property
    def is_postgres(self) -> bool:
        """True for a ``postgresql://`` (or ``postgres://``) URL."""
        return self.url.startswith(POSTGRES_SCHEMES)


class PlantConfig(Frozen):
    """A plant: its router (None when this host runs none), the bus the plant's tools join, the cells
    expected to answer (``cell/robot``), each cell's dashboard URL, and the history.
    """
    router: RouterConfig | None = None
    bus: BusConfig = BusConfig()
    cells: list[str] = []  # `cell/robot` of every cell expected to answer
    # `cell/robot` -> the URL of that cell's own `dt dashboard`: the plant page's click opens it
    dashboards: dict[str, str] = {}
    history: HistoryConfig = HistoryConfig()

    @field_validator("dashboards")
    @classmethod
    def _dashboards(cls, v: dict[str, str]) -> dict[str, str]:
        for c, url in v.items():
            cls._cells([c])
            if not url.startswith(("http://", "https://")) or any(ch.isspace() or ch in "\"'<>" for ch in url):
                raise ValueError(f"dashboards[{c!r}] = {url!r}: an http:// or https:// URL (a cell's dt dashboard)")
        return v

    @field_validator("cells")
    @classmethod
    def _cells(cls, v: list[str]) -> list[str]:
        for c in v:
            parts = c.split("/")
            if len(parts) != 2 or any(not p or any(ch in p for ch in "*$?#") for p in parts):
                raise ValueError(f"{c!r} must be 'cell/robot' (two key chunks, no * $ ? #)")
        if len(set(v)) != len(v):
            raise ValueError(f"cells {v} name a cell twice")
        return v


def load_plant_config(path: str | Path) -> PlantConfig:
    """A plant config, or a plain bus config taken as a plant of that bus.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    PlantConfig

    Raises
    ------
    ConfigError
        When the file cannot be read or does not validate (naming the key).
    """
    data = read_yaml(path)
    if data and not any(k in data for k in PLANT_KEYS):
        return PlantConfig(bus=validate(BusConfig, data, path))
    return validate(PlantConfig, data, path)


def history_url(cfg: PlantConfig, base: Path) -> str:
    """The history's URL with a relative SQLite path taken from ``base``.

    Parameters
    ----------
    cfg : PlantConfig
    base : Path
        The config's directory.

    Returns
    -------
    str
        A PostgreSQL URL as it is, else a SQLite file path.
    """
    url = cfg.history.url
    if cfg.history.is_postgres:
        return url
    return str(beside(base, url.removeprefix("sqlite:///") if url.startswith("sqlite:///") else url))
