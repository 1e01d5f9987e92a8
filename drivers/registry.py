"""Drivers chosen by config string: `kind` (robot, tracker, camera) and `name`.

Every driver is built the same way, whatever its name::

    create(kind, name, config=None, *, world=None, source="<config>")

which calls the class's `from_config(config, world=world, source=source)` (drivers.base.Lifecycle):
the driver is constructed from the context (`world`: the simulated cell, for drivers that run on
it; others ignore it) and, when `config` is given, configured with it (state `inactive`); with
`config=None` it is returned unconfigured. `source` names the config in error messages. Callers
never branch on a driver's name: `needs_world(kind, name)` says whether a simulated world must
exist.
"""
from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from drivers.base import Lifecycle
from dt_kernel.errors import ConfigError

# name -> "module:Class"; imported lazily so a missing optional part fails only when chosen.
_REGISTRY: dict[str, dict[str, str]] = {
    "robot": {"sim": "drivers.simulated.devices:SimRobot", "serial": "drivers.serial.controller:SerialController"},
    "tracker": {"sim": "drivers.simulated.devices:SimTracker", "serial": "drivers.serial.tracker:SerialTracker"},
    "camera": {"sim_point": "drivers.simulated.devices:SimPointCamera",
               "sim_images": "drivers.simulated.camera_images:SimCameraRig",
               "natnet": "drivers.natnet.driver:NatNetRig"},
}


def register(kind: str, name: str, target: str) -> None:
    """Add a driver: `target` is "module:Class", a Lifecycle subclass."""
    _REGISTRY[kind][name] = target


def known(kind: str) -> list[str]:
    return sorted(_REGISTRY[kind])


def driver_class(kind: str, name: str, source: str = "<config>") -> type[Lifecycle]:
    """The class registered under (kind, name); ConfigError listing the known names otherwise."""
    if kind not in _REGISTRY:
        raise ConfigError(source, "kind", kind, "one of " + ", ".join(sorted(_REGISTRY)))
    if name not in _REGISTRY[kind]:
        raise ConfigError(source, f"drivers.{kind}", name, "one of " + ", ".join(known(kind)))
    module, cls = _REGISTRY[kind][name].split(":")
    return getattr(importlib.import_module(module), cls)


def needs_world(kind: str, name: str, source: str = "<config>") -> bool:
    """True if the driver runs on a simulated world (drivers.simulated.SimWorld)."""
    return bool(getattr(driver_class(kind, name, source), "needs_world", False))


def create(kind: str, name: str, config: Mapping[str, Any] | None = None, *, world: Any = None,
           source: str = "<config>"):
    """Build the driver (kind, name); see the module docstring."""
    return driver_class(kind, name, source).from_config(config, world=world, source=source)
