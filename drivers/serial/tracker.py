"""Laser tracker over a serial line, speaking `drivers.serial.protocol` (MEAS, STATUS, PING)
through the same link as the controller. A measurement arrives as spherical d, azimuth,
elevation (m, rad) and is converted to a Cartesian point in the tracker frame. The protocol and
the config keys: docs/drivers.md ("Serial line protocol")."""
from __future__ import annotations

import math
import time

import numpy as np
from pydantic import Field

from drivers.base import TrackerReading
from drivers.serial import protocol as lp
from drivers.serial.device import SerialDevice
from drivers.serial.link import LinkConfig, ack_fields
from dt_kernel.config import Frozen
from dt_kernel.geometry import spherical_to_cartesian


class TrackerLimits(Frozen):
    """Ranges the tracker driver checks: ``min_distance_m`` and ``max_distance_m`` (m)."""
    min_distance_m: float = Field(0.0, ge=0)
    max_distance_m: float = Field(80.0, gt=0)


class TrackerConfig(LinkConfig):
    """The serial tracker's options: the line's (``LinkConfig``) and ``limits``."""
    limits: TrackerLimits = TrackerLimits()


class SerialTracker(SerialDevice[TrackerConfig]):
    """LaserTracker over the line protocol."""

    name = "serial laser tracker"
    config_model = TrackerConfig

    def measure(self) -> TrackerReading:
        """Measure the SMR (MEAS).

        Returns
        -------
        TrackerReading
            ``point`` (3,) m in the tracker frame; when the tracker's status is not ``ok`` (e.g.
            ``beam_broken``) the reading carries that status and a NaN point.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the reply is refused or malformed, or, with status ``ok``, a number is NaN or out of
            range (distance outside the limits, azimuth beyond ±2 pi, elevation beyond ±pi/2 rad).
        """
        self._require("active")
        reply = self._link.request("MEAS")
        host_time = time.monotonic()  # at receipt, before parsing
        f = ack_fields(self.name, "MEAS", reply, 5)
        t = lp.parse_float(f[0], "MEAS t")
        status = lp.parse_status(f[4])
        if status != "ok":
            # No measurement: numbers are informative only (often nan); the point is NaN.
            d_, az_, el_ = (lp.parse_float(v, "MEAS " + k, allow_nan=True) for k, v in zip(("d", "az", "el"), f[1:4]))
            return TrackerReading(point=np.full(3, np.nan), spherical=(d_, az_, el_), t=t, status=status,
                                  host_time=host_time)
        lim = self._cfg.limits
        d = lp.parse_float(f[1], "MEAS d", lim.min_distance_m, lim.max_distance_m)
        az = lp.parse_float(f[2], "MEAS azimuth", -2 * math.pi, 2 * math.pi)
        el = lp.parse_float(f[3], "MEAS elevation", -math.pi / 2, math.pi / 2)
        return TrackerReading(point=spherical_to_cartesian(d, az, el), spherical=(d, az, el), t=t, status="ok",
                              host_time=host_time)
