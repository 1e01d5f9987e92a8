"""Physical effect terms of the hybrid error model, one class per effect, each linear in
parameters that mean something physically (joint offsets in rad, stiffness in N m/rad, backlash
width in rad, expansion coefficient in 1/K, lag in s, drift in rad/h).

`REGISTRY` is the one place that lists them, in the contract order (docs/effects.md): geometric,
compliance, gear, backlash, thermal, dynamic, drift. Each `Effect` subclass declares its name,
the data columns it reads, whether it needs the robot's kinematic chain and the factor the
diagnose verdict names, and builds its regressor block. Adding an effect: one module with one
`Effect` subclass, one entry in `REGISTRY`, one test (the simulator's scenario must know the
same name: tests/unit/test_effects_registry.py). The user's own effects (declared in YAML or from a
package's entry point, `models.effects.declared`) are registered beside the catalogue.

    from dt_runtime.models import effects
    effects.get("backlash").build(effects.Inputs.of(dataset), chain)   # a Block
    effects.available(inputs, chain)                                   # names the data allows
"""
from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from dt_kernel.errors import ConfigError, DataError
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
_SOURCE: dict[str, str] = {}  # name -> where it came from ("entry point x", a YAML file, a saved model)
_entry_points_loaded = False

__all__ = ["PROCESS", "REGISTRY", "Block", "Catalogue", "Effect", "Inputs", "as_inputs", "available", "build",
           "check_names", "get", "names", "register", "register_file", "reload_entry_points", "unregister",
           "user_effects"]


def _load_entry_points() -> None:
    global _entry_points_loaded
    if not _entry_points_loaded:
        # Marked loaded only once every plugin registered: a broken one raises on every call,
        # rather than once and then being silently left out.
        for name, effect in declared.entry_point_effects():
            register(effect, source=f"entry point {name}")
        _entry_points_loaded = True


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
    _SOURCE.setdefault(effect.name, source)
    return _USER[effect.name]


def register_file(path) -> list[str]:
    """Register the effects a YAML file declares (`--effects-file`, `models.effects.declared`) and
    return their names. ConfigError naming the file, the key and the value: a bad key or value
    (pydantic), a catalogue name, a name declared twice, or a name registered already with another
    definition (a plugin's, a loaded model's)."""
    _load_entry_points()  # a clash with a plugin is found here, not on first use
    found = declared.read_file(path)
    seen: set[str] = set()
    for i, effect in enumerate(found):
        key = f"effects.{i}.name"
        if effect.name in REGISTRY:
            raise ConfigError(path, key, effect.name, f"not a catalogue effect's name ({', '.join(REGISTRY)}); "
                              "name your own effect after what drives it")
        if effect.name in seen:
            raise ConfigError(path, key, effect.name, "each name once in the file")
        seen.add(effect.name)
        try:
            register(effect, source=str(path))
        except DataError as exc:
            raise ConfigError(path, key, effect.name, f"a name not taken ({exc}; from {_SOURCE.get(effect.name)})"
                              ) from exc
    return [e.name for e in found]


def unregister(name: str) -> None:
    """Forget a user effect (tests; a session that declared another file)."""
    _USER.pop(name, None)
    _SOURCE.pop(name, None)


def reload_entry_points() -> list[str]:
    """Read the installed packages' `cobot_dt.effects` entry points again and return the plugin
    effects' names. `names()` reads them once per process (scanning every installed distribution
    on each call would cost milliseconds per call), so a plugin installed into a running process
    (a notebook, a test) is seen only after this."""
    import importlib

    global _entry_points_loaded
    for name in [n for n, s in _SOURCE.items() if s.startswith("entry point ")]:
        unregister(name)
    importlib.invalidate_caches()  # importlib.metadata caches directory listings
    _entry_points_loaded = False
    _load_entry_points()
    return [n for n, s in _SOURCE.items() if s.startswith("entry point ")]


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


class Catalogue:
    """The effects one model or one diagnosis knows: the process's (the catalogue, installed
    plugins, the --effects-file declarations) and its own (a saved model's declared effects). A
    loaded model carries its own in its catalogue instead of registering them in the process, so
    loading a model does not change what another diagnosis tests."""

    def __init__(self, own: Mapping[str, Effect] | None = None):
        self.own: dict[str, Effect] = dict(own or {})

    def names(self) -> tuple[str, ...]:
        base = names()
        return (*base, *(n for n in self.own if n not in base))

    def get(self, name: str) -> Effect:
        if name in self.own:
            return self.own[name]
        return get(name)

    def check_names(self, effects) -> None:
        unknown = [e for e in effects if e not in self.own and e not in names()]
        if unknown:
            known = self.names()
            raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(known)} (declare your own "
                            "with --effects-file, docs/effects.md)")

    def build(self, name: str, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
        return self.get(name).build(inp, chain, hyper)

    def available(self, inp: Inputs, chain: Chain | None) -> list[str]:
        return [n for n in self.names() if self.get(n).allowed(inp, chain)]

    def user_effects(self) -> dict[str, Effect]:
        return user_effects() | self.own

    def declared(self, effects) -> list[declared.DeclaredEffect]:
        """The declared (YAML) effects among `effects`: what a saved model carries."""
        return [e for e in map(self.get, effects) if isinstance(e, declared.DeclaredEffect)]


PROCESS = Catalogue()  # the process's effects, no model's own
