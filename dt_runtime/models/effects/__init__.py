"""Physical effect terms of the hybrid error model, one class per effect, each linear in
parameters that mean something physically (joint offsets in rad, stiffness in N m/rad, backlash
width in rad, expansion coefficient in 1/K, lag in s, drift in rad/h).

`REGISTRY` is the one place that lists them, in the DESIGN.md contract order: geometric,
compliance, gear, backlash, thermal, dynamic, drift. Each `Effect` subclass declares its name,
the data columns it reads, whether it needs the robot's kinematic chain and the factor the
diagnose verdict names, and builds its regressor block. Adding an effect: one module with one
`Effect` subclass, one entry in `REGISTRY`, one test (the simulator's scenario must know the
same name: tests/test_effects_registry.py). The user's own effects (declared in YAML or from a
package's entry point, `models.effects.declared`) are registered beside the catalogue.

    from dt_runtime.models import effects
    effects.get("backlash").build(effects.Inputs.of(dataset), chain)   # a Block
    effects.available(inputs, chain)                                   # names the data allows
"""
from __future__ import annotations

from types import MappingProxyType

from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects import declared
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
# The user's own effects (models.effects.declared): declared in YAML or from installed packages'
# entry points; tested by diagnose after the catalogue.
_USER: dict[str, Effect] = {}
_entry_points_loaded = False

__all__ = ["REGISTRY", "Block", "Effect", "Inputs", "as_inputs", "available", "build", "check_names", "get", "names",
           "register", "unregister", "user_effects"]


def _load_entry_points() -> None:
    global _entry_points_loaded
    if not _entry_points_loaded:
        _entry_points_loaded = True
        for name, effect in declared.entry_point_effects():
            register(effect, source=f"entry point {name}")


def register(effect: Effect, source: str = "") -> Effect:
    """Add the user's effect (a declared or plugin one) to the candidates. A catalogue name, or
    the same name with another definition, is a DataError; the same declaration again is a no-op."""
    if effect.name in REGISTRY:
        raise DataError(f"effect {effect.name!r}{f' ({source})' if source else ''} has a catalogue effect's name; "
                        f"catalogue: {', '.join(REGISTRY)}")
    old = _USER.get(effect.name)
    if old is not None and getattr(old, "spec", old) != getattr(effect, "spec", effect):
        raise DataError(f"effect {effect.name!r}{f' ({source})' if source else ''} is already defined differently")
    _USER.setdefault(effect.name, effect)
    return _USER[effect.name]


def unregister(name: str) -> None:
    """Forget a user effect (tests; a session that declared another file)."""
    _USER.pop(name, None)


def user_effects() -> dict[str, Effect]:
    """The user's effects registered so far (declared and entry points)."""
    _load_entry_points()
    return dict(_USER)


def names() -> tuple[str, ...]:
    """Every effect name: the catalogue in the contract order, then the user's own."""
    _load_entry_points()
    return (*REGISTRY, *_USER)


def check_names(effects) -> None:
    """DataError naming every unknown effect in `effects`."""
    known = names()
    unknown = [e for e in effects if e not in known]
    if unknown:
        raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(known)} (declare your own "
                        "with --effects-file, docs/effects.md)")


def get(name: str) -> Effect:
    check_names((name,))
    return REGISTRY[name] if name in REGISTRY else _USER[name]


def build(name: str, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
    """The regressor block of effect `name` on `inp` (DataError if the inputs do not allow it),
    with `hyper` the values of its nonlinear parameters (`Effect.hyper`)."""
    return get(name).build(inp, chain, hyper)


def available(inp: Inputs, chain: Chain | None) -> list[str]:
    """Effects whose regressors the data's columns (and the kinematic model) allow."""
    return [name for name in names() if get(name).allowed(inp, chain)]
