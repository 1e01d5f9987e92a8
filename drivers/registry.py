"""Drivers chosen by config string: `kind` (robot, tracker, camera) and `name`."""
from __future__ import annotations

import importlib
from typing import Any

from dt_kernel.errors import ConfigError

# name -> "module:Class"; imported lazily so a missing optional part fails only when chosen.
_REGISTRY: dict[str, dict[str, str]] = {
    "robot": {"sim": "drivers.simulated.devices:SimRobot", "serial": "drivers.serial.controller:SerialController"},
    "tracker": {"sim": "drivers.simulated.devices:SimTracker", "serial": "drivers.serial.tracker:SerialTracker"},
    "camera": {"sim_point": "drivers.simulated.devices:SimPointCamera", "sim_images": "drivers.simulated.camera_images:SimCameraRig"},
}


def register(kind: str, name: str, target: str) -> None:
    _REGISTRY[kind][name] = target


def known(kind: str) -> list[str]:
    return sorted(_REGISTRY[kind])


def create(kind: str, name: str, source: str = "<config>", **kwargs: Any):
    if kind not in _REGISTRY:
        raise ConfigError(source, "kind", kind, "one of " + ", ".join(sorted(_REGISTRY)))
    if name not in _REGISTRY[kind]:
        raise ConfigError(source, f"drivers.{kind}", name, "one of " + ", ".join(known(kind)))
    module, cls = _REGISTRY[kind][name].split(":")
    return getattr(importlib.import_module(module), cls)(**kwargs)
