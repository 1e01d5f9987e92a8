"""Laser tracker adapter over a serial line, speaking `drivers.serial.protocol` (MEAS, STATUS, PING).

Same link as the controller (`drivers.serial.link`: seq, ACK/NAK, retries, reconnection).
A measurement arrives as spherical `d, azimuth, elevation` (m, rad) with a status token; it is
converted to a Cartesian point in the tracker frame. A reading whose status is not `ok` (e.g.
`beam_broken`) is returned with that status and a NaN point, as `drivers.simulated.SimTracker`
does; with status `ok`, NaN or out-of-range numbers raise DriverError.

Config keys: those of `LinkConfig` (`url`, `baudrate`, `timeout_s`, `retries`,
`reconnect_after`) and `limits`: `min_distance_m` (0.0), `max_distance_m` (80.0).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from pydantic import Field

from drivers.base import Lifecycle, TrackerReading
from drivers.serial import protocol as lp
from drivers.serial.link import LinkConfig, SerialLink, ack_fields
from dt_kernel.config import Frozen, validate
from dt_kernel.errors import DriverError, StateError
from dt_kernel.geometry import spherical_to_cartesian


class TrackerLimits(Frozen):
    min_distance_m: float = Field(0.0, ge=0)
    max_distance_m: float = Field(80.0, gt=0)


class TrackerConfig(LinkConfig):
    limits: TrackerLimits = TrackerLimits()


class SerialTracker(Lifecycle):
    """LaserTracker over the line protocol."""

    name = "serial laser tracker"

    def __init__(self, config: Mapping[str, Any] | None = None, source: str = "<serial tracker config>", *,
                 world: Any = None):  # world: unused, the registry passes it to every driver
        self._source = source
        self.cfg: TrackerConfig | None = None
        self.link: SerialLink | None = None
        if config is not None:
            self.configure(config)

    # --- configured parts (built by `configure`) ----------------------------------------
    @property
    def _link(self) -> SerialLink:
        if self.link is None:
            raise StateError(f"{self.name}: used before configure()")
        return self.link

    @property
    def _cfg(self) -> TrackerConfig:
        if self.cfg is None:
            raise StateError(f"{self.name}: used before configure()")
        return self.cfg

    def _on_configure(self, config: dict[str, Any]) -> None:
        self.cfg = validate(TrackerConfig, config, self._source)
        self.link = SerialLink(self.cfg, self.name)

    def _on_activate(self) -> None:
        self._link.open()
        try:
            f = ack_fields(self.name, "PING", self._link.request("PING"))
            if not f or f[0] != lp.PROTOCOL_VERSION:
                raise DriverError(f"{self.name}: protocol version {f[:1]} not supported")
        except DriverError:
            self._link.close()
            raise

    def _on_deactivate(self) -> None:
        self._link.close()

    def _on_close(self) -> None:
        if self.link is not None:
            self.link.close()

    def measure(self) -> TrackerReading:
        self._require("active")
        f = ack_fields(self.name, "MEAS", self._link.request("MEAS"), 5)
        t = lp.parse_float(f[0], "MEAS t")
        status = lp.parse_status(f[4])
        if status != "ok":
            # No measurement: numbers are informative only (often nan); the point is NaN.
            d_, az_, el_ = (lp.parse_float(v, "MEAS " + k, allow_nan=True) for k, v in zip(("d", "az", "el"), f[1:4]))
            return TrackerReading(point=np.full(3, np.nan), spherical=(d_, az_, el_), t=t, status=status)
        lim = self._cfg.limits
        d = lp.parse_float(f[1], "MEAS d", lim.min_distance_m, lim.max_distance_m)
        az = lp.parse_float(f[2], "MEAS azimuth", -2 * math.pi, 2 * math.pi)
        el = lp.parse_float(f[3], "MEAS elevation", -math.pi / 2, math.pi / 2)
        return TrackerReading(point=spherical_to_cartesian(d, az, el), spherical=(d, az, el), t=t, status="ok")
