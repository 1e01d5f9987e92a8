"""Physical effect terms of the hybrid error model, one class per effect, each linear in
parameters that mean something physically (joint offsets in rad, stiffness in N m/rad, backlash
width in rad, expansion coefficient in 1/K, lag in s, drift in rad/h).

`REGISTRY` is the one place that lists them, in the DESIGN.md contract order: geometric,
compliance, gear, backlash, thermal, dynamic, drift. Each `Effect` subclass declares its name,
the data columns it reads, whether it needs the robot's kinematic chain and the factor the
diagnose verdict names, and builds its regressor block. Adding an effect: one module with one
`Effect` subclass, one entry in `REGISTRY`, one test (the simulator's scenario must know the
same name: tests/test_effects_registry.py).

    from dt_runtime.models import effects
    effects.get("backlash").build(effects.Inputs.of(dataset), chain)   # a Block
    effects.available(inputs, chain)                                   # names the data allows
"""
from __future__ import annotations

from types import MappingProxyType

from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.backlash import Backlash
from dt_runtime.models.effects.base import Block, Effect, Inputs, as_inputs
from dt_runtime.models.effects.compliance import Compliance
from dt_runtime.models.effects.drift import Drift
from dt_runtime.models.effects.dynamic import Dynamic
from dt_runtime.models.effects.gear import Gear
from dt_runtime.models.effects.geometric import Geometric
from dt_runtime.models.effects.thermal import Thermal

# name -> effect, in the contract order (the order diagnose tests candidates in).
REGISTRY: MappingProxyType[str, Effect] = MappingProxyType(
    {e.name: e for e in (Geometric(), Compliance(), Gear(), Backlash(), Thermal(), Dynamic(), Drift())})

__all__ = ["REGISTRY", "Block", "Effect", "Inputs", "as_inputs", "available", "build", "check_names", "get", "names"]


def names() -> tuple[str, ...]:
    """Every effect name, in the contract order."""
    return tuple(REGISTRY)


def check_names(effects) -> None:
    """DataError naming every unknown effect in `effects`."""
    unknown = [e for e in effects if e not in REGISTRY]
    if unknown:
        raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(REGISTRY)}")


def get(name: str) -> Effect:
    check_names((name,))
    return REGISTRY[name]


def build(name: str, inp: Inputs, chain: Chain | None) -> Block:
    """The regressor block of effect `name` on `inp` (DataError if the inputs do not allow it)."""
    return get(name).build(inp, chain)


def available(inp: Inputs, chain: Chain | None) -> list[str]:
    """Effects whose regressors the data's columns (and the kinematic model) allow."""
    return [name for name, e in REGISTRY.items() if e.allowed(inp, chain)]
