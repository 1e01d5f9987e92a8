"""Scenario: which physical error effects the simulated plant has, and how large they are.

Effect names are a contract shared with the model side: geometric, compliance, gear, backlash,
thermal, dynamic, drift. Loaded from YAML (configs/scenarios/) and validated once.
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator

from dt_kernel.config import Frozen, load_yaml

EFFECTS = ("geometric", "compliance", "gear", "backlash", "thermal", "dynamic", "drift")
N_JOINTS = 6

Six = Annotated[list[float], Field(min_length=N_JOINTS, max_length=N_JOINTS)]


class Geometric(Frozen):
    """Geometric effect: seeded random shifts of every joint origin (``link_sigma_m``, m), twists
    (``twist_sigma_rad``, rad) and joint zero offsets (``joint_offset_sigma_rad``, rad).
    """
    enabled: bool = False
    # Random perturbation of every joint origin (link lengths, offsets) drawn with the seed.
    link_sigma_m: float = Field(3.0e-4, ge=0, le=0.01)
    twist_sigma_rad: float = Field(1.0e-4, ge=0, le=0.01)
    joint_offset_sigma_rad: float = Field(1.5e-4, ge=0, le=0.01)


class Compliance(Frozen):
    """Compliance effect: joint stiffness (N m/rad, six, > 0); deflection = -holding torque / stiffness."""
    enabled: bool = False
    # Joint stiffness (N m / rad): deflection = -holding torque / stiffness.
    stiffness_nm_per_rad: Six = [2.0e6, 1.0e6, 6.0e5, 2.0e5, 2.0e5, 1.0e5]

    @field_validator("stiffness_nm_per_rad")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if any(k <= 0 for k in v):
            raise ValueError("every joint stiffness must be > 0 N m/rad")
        return v


class Gear(Frozen):
    """Gear transmission error per joint: ``amplitude_rad * sin(harmonic * q + phase_rad)`` (rad)."""
    enabled: bool = False
    # Transmission error: amplitude * sin(harmonic * q + phase) per joint.
    amplitude_rad: Six = [4e-5, 5e-5, 5e-5, 3e-5, 3e-5, 0.0]
    harmonic: Six = [2.0, 2.0, 3.0, 2.0, 2.0, 1.0]
    phase_rad: Six = [0.3, 1.1, 2.0, 0.7, 0.1, 0.0]


class Backlash(Frozen):
    """Backlash: full width per joint (rad, >= 0); the joint lags by width/2 opposite to its approach."""
    enabled: bool = False
    # Full backlash width (rad): the joint lags by width/2 opposite to its direction of approach.
    width_rad: Six = [6e-5, 8e-5, 8e-5, 4e-5, 4e-5, 0.0]

    @field_validator("width_rad")
    @classmethod
    def _nonneg(cls, v: list[float]) -> list[float]:
        if any(w < 0 for w in v):
            raise ValueError("backlash width must be >= 0 rad")
        return v


class Thermal(Frozen):
    """Thermal expansion of the arm about its base: ``expansion_per_k`` (1/K) of the structure's
    temperature above ``reference_c`` (deg C), the structure following the air through a first-order
    lag ``lag_s`` (s; 0: at once).
    """
    enabled: bool = False
    expansion_per_k: float = Field(2.3e-5, ge=0, le=1e-3)  # aluminium arm
    reference_c: float = 20.0
    # The structure follows the air temperature through a first-order lag (s; 0: at once).
    # Industrial arms warm up over tens of minutes.
    lag_s: float = Field(0.0, ge=0, le=86400)


class Dynamic(Frozen):
    """Dynamic error at the stop: a following error ``lag_s * v`` along the approach and a sag
    ``sag_s * v`` along -z (s; v the speed, m/s).
    """
    enabled: bool = False
    # Residual following error at the stop, along the direction of approach: lag_s * v.
    lag_s: float = Field(1.5e-4, ge=0, le=0.05)
    # Speed-dependent sag from the deceleration the settling window leaves: sag_s * v along -z.
    sag_s: float = Field(1.0e-4, ge=0, le=0.05)


class Drift(Frozen):
    """Joint drift: a constant rate per joint (rad/h)."""
    enabled: bool = False
    joint_rate_rad_per_h: Six = [0.0, 2e-5, -2e-5, 0.0, 1e-5, 0.0]


class Effects(Frozen):
    """The seven error effects of a scenario, each switched on by its ``enabled``."""
    geometric: Geometric = Geometric()
    compliance: Compliance = Compliance()
    gear: Gear = Gear()
    backlash: Backlash = Backlash()
    thermal: Thermal = Thermal()
    dynamic: Dynamic = Dynamic()
    drift: Drift = Drift()

    def enabled(self) -> list[str]:
        """The names of the effects switched on, in ``EFFECTS`` order.

        Returns
        -------
        list of str
        """
        return [name for name in EFFECTS if getattr(self, name).enabled]


class Temperature(Frozen):
    """Temperature (deg C) time series: base + ramp * t + amplitude * sin(2 pi t / period)."""

    base_c: float = 20.0
    ramp_c_per_h: float = 0.0
    amplitude_c: float = Field(0.0, ge=0)
    period_h: float = Field(8.0, gt=0)


class PayloadStep(Frozen):
    """A payload change: ``kg`` from time ``at_s`` (s) on."""
    at_s: float = Field(ge=0)
    kg: float = Field(ge=0, le=20)


class Scenario(Frozen):
    """A simulated plant's scenario (configs/scenarios/): seed, payload (kg) and its schedule, air
    temperature, joint repeatability noise (rad), the controller's TCP resolution (m), speed limit
    (m/s), dwell per positioning (s) and the error effects.
    """
    name: str = "unnamed"
    seed: int = 0
    payload_kg: float = Field(2.0, ge=0, le=20)  # nominal payload 20 kg
    payload_schedule: list[PayloadStep] = []  # optional steps in time
    temperature: Temperature = Temperature()
    joint_noise_rad: float = Field(2.5e-6, ge=0, le=1e-3)  # repeatability, ~5 um at the TCP
    tcp_resolution_m: float = Field(1.0e-6, gt=0, le=1e-3)  # encoder resolution at the TCP
    max_speed_m_s: float = Field(1.0, gt=0, le=5)
    dwell_s: float = Field(5.0, ge=0)  # settle + measure time per positioning
    effects: Effects = Effects()

    def payload_at(self, t: float) -> float:
        """The payload at a time: the last step at or before ``t``, else ``payload_kg``.

        Parameters
        ----------
        t : float
            s, simulated clock.

        Returns
        -------
        float
            kg.
        """
        kg = self.payload_kg
        for step in sorted(self.payload_schedule, key=lambda s: s.at_s):
            if t >= step.at_s:
                kg = step.kg
        return kg


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Scenario

    Raises
    ------
    ConfigError
        When the file cannot be read or does not validate.
    """
    return load_yaml(path, Scenario)
