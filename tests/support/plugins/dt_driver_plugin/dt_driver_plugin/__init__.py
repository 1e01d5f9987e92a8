"""A laser tracker driver from outside the project: it reports a fixed SMR position (spherical,
tracker frame) with seeded noise, and a broken beam every `beam_broken_every` readings. It uses
only the public driver API: drivers.base (Lifecycle, TrackerReading) and a Frozen options model,
so the runtime checks its options when the YAML is read."""
from __future__ import annotations

import numpy as np
from pydantic import Field

from drivers.base import Lifecycle, TrackerReading
from dt_kernel.config import Frozen, validate
from dt_kernel.geometry import spherical_to_cartesian


class ScriptedOptions(Frozen):
    distance_m: float = Field(2.5, gt=0, le=80)
    azimuth_rad: float = Field(0.2, ge=-np.pi, le=np.pi)
    elevation_rad: float = Field(-0.1, ge=-np.pi / 2, le=np.pi / 2)
    noise_m: float = Field(1e-5, ge=0, le=1e-3)
    beam_broken_every: int = Field(0, ge=0)  # 0: never
    seed: int = 0


class ScriptedTracker(Lifecycle):
    """LaserTracker (drivers.base) with a scripted target."""

    config_model = ScriptedOptions

    def __init__(self, *, world=None, source: str = "<scripted tracker config>"):
        super().__init__(world=world, source=source)
        self._opts = ScriptedOptions()
        self._n = 0
        self._rng = np.random.default_rng(0)
        self._t0 = 0.0

    def _on_configure(self, config: dict) -> None:
        self._opts = validate(ScriptedOptions, config, self._source)

    def _on_activate(self) -> None:
        self._rng = np.random.default_rng(self._opts.seed)
        self._n = 0

    def measure(self) -> TrackerReading:
        self._require("active")
        o = self._opts
        self._n += 1
        t = self._n / 1000.0  # the device's own clock: a 1 kHz sample counter
        if o.beam_broken_every and self._n % o.beam_broken_every == 0:
            return TrackerReading(point=np.full(3, np.nan), spherical=(np.nan, np.nan, np.nan), t=t,
                                  status="beam_broken")
        d = o.distance_m + o.noise_m * self._rng.standard_normal()
        return TrackerReading(point=spherical_to_cartesian(d, o.azimuth_rad, o.elevation_rad),
                              spherical=(d, o.azimuth_rad, o.elevation_rad), t=t)
