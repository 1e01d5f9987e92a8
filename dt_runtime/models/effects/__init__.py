"""Physical effect terms of the hybrid error model, one class per effect (docs/effects.md).

`REGISTRY` lists them in the contract order: geometric, compliance, gear, backlash, thermal,
dynamic, drift; each is linear in parameters with a physical meaning. The user's own effects are
never registered in the process: a `Catalogue` holds the effects one call knows::

    cat = effects.default().with_file("configs/effects/humidity.yaml")
    cat.get("backlash").build(effects.Inputs.of(dataset), chain)       # a Block
"""
from __future__ import annotations

import importlib
from collections.abc import Iterable, Mapping
from pathlib import Path
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

__all__ = ["REGISTRY", "Block", "Catalogue", "Effect", "Inputs", "as_inputs", "available", "build",
           "check_names", "default", "get", "names", "plugin_effects", "read_file", "reload_entry_points"]


def _definition(effect: Effect) -> object:
    # A declared effect is its declaration (two reads of one file are the same effect); any
    # other is its class.
    return getattr(effect, "spec", type(effect))


def plugin_effects() -> dict[str, Effect]:
    """The installed packages' `cobot_dt.effects` entry points as {effect name: effect}, read now.
    DataError naming the entry point for a broken plugin, one with a catalogue effect's name, or
    two plugins defining one name differently."""
    out: dict[str, Effect] = {}
    for ep_name, effect in declared.entry_point_effects():
        where = f"effect plugin {ep_name!r} (entry point group {declared.ENTRY_POINT_GROUP})"
        if effect.name in REGISTRY:
            raise DataError(f"{where} has a catalogue effect's name {effect.name!r}; catalogue: {', '.join(REGISTRY)}")
        old = out.get(effect.name)
        if old is not None and _definition(old) != _definition(effect):
            raise DataError(f"{where}: effect {effect.name!r} is already defined differently by another plugin")
        out.setdefault(effect.name, effect)
    return out


def read_file(path: str | Path) -> list[Effect]:
    """The effects a YAML file declares (`--effects-file`, `models.effects.declared`), checked on
    their own: ConfigError naming the file, the key and the value for a bad key or value, a
    catalogue effect's name, or a name declared twice. Nothing is registered.

    Parameters
    ----------
    path : str or Path
        The effects YAML.

    Returns
    -------
    list of Effect
    """
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
    return found


class Catalogue:
    """The effects one call knows: the catalogue (`REGISTRY`), the installed plugins and its own
    (a YAML file's declarations, a saved model's). Built once per call and passed down (a model's
    `catalogue`, a diagnosis's `Problem`, which carries it to its worker processes), so what one
    call declares never changes what another knows.

    Parameters
    ----------
    own : the catalogue's own effects ({name: effect} or effects); one with a catalogue effect's
        name is a DataError; one with a plugin's name takes its place.
    plugins : {name: effect} of the plugins; None (default): the installed entry points, read now
        (`plugin_effects`).
    """

    def __init__(self, own: Mapping[str, Effect] | Iterable[Effect] | None = None,
                 plugins: Mapping[str, Effect] | None = None):
        self.plugins: dict[str, Effect] = dict(plugin_effects() if plugins is None else plugins)
        effects = own.values() if isinstance(own, Mapping) else (own or ())
        self.own: dict[str, Effect] = {e.name: e for e in effects}
        clash = [n for n in self.own if n in REGISTRY]
        if clash:
            raise DataError(f"effect(s) {', '.join(clash)} have a catalogue effect's name; catalogue: "
                            f"{', '.join(REGISTRY)}")

    def __repr__(self) -> str:  # a model's repr (sklearn's) shows what its names refer to
        return f"Catalogue(own={list(self.own)}, plugins={list(self.plugins)})"

    def with_own(self, effects: Iterable[Effect]) -> Catalogue:
        """This catalogue with `effects` added to its own (the same plugins, not read again).

        Parameters
        ----------
        effects : iterable of Effect
            The effects to add.

        Returns
        -------
        Catalogue
        """
        return Catalogue([*self.own.values(), *effects], self.plugins)

    def with_file(self, path: str | Path) -> Catalogue:
        """This catalogue with the effects the YAML file at `path` declares (`read_file`) as its
        own. ConfigError naming the file, the key and the value when a name is a plugin's or
        already this catalogue's own with another definition.

        Parameters
        ----------
        path : str or Path
            The effects YAML.

        Returns
        -------
        Catalogue
        """
        found = read_file(path)
        for i, effect in enumerate(found):
            taken = self.own.get(effect.name) or self.plugins.get(effect.name)
            if taken is not None and _definition(taken) != _definition(effect):
                where = getattr(taken, "source", "") or "an installed plugin"
                raise ConfigError(path, f"effects.{i}.name", effect.name,
                                  f"a name not taken (already defined differently, in {where})")
        return self.with_own(found)

    def names(self) -> tuple[str, ...]:
        """Every effect name: the catalogue in the contract order, then the plugins', then its own."""
        return tuple(dict.fromkeys((*REGISTRY, *self.plugins, *self.own)))

    def get(self, name: str) -> Effect:
        """The effect `name` (its own first); DataError naming the known ones if there is none.

        Parameters
        ----------
        name : str
            The effect's name.

        Returns
        -------
        Effect
        """
        for where in (self.own, self.plugins, REGISTRY):
            if name in where:
                return where[name]
        self.check_names((name,))
        raise AssertionError(name)  # check_names raised

    def check_names(self, effects: Iterable[str]) -> None:
        """DataError naming every unknown effect in `effects` and the known ones.

        Parameters
        ----------
        effects : iterable of str
            Effect names.

        Raises
        ------
        DataError
        """
        known = self.names()
        unknown = [e for e in effects if e not in known]
        if unknown:
            raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(known)} (declare your own "
                            "with --effects-file, docs/effects.md)")

    def build(self, name: str, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
        """The regressor block of effect `name` on `inp` (DataError if the inputs do not allow it),
        with `hyper` the values of its nonlinear parameters (`Effect.hyper`).

        Parameters
        ----------
        name : str
            The effect's name.
        inp : Inputs
            The data's columns.
        chain : Chain or None
            The robot's kinematic chain.
        hyper : dict, optional
            Values of its nonlinear parameters.

        Returns
        -------
        Block
        """
        return self.get(name).build(inp, chain, hyper)

    def available(self, inp: Inputs, chain: Chain | None) -> list[str]:
        """Effects whose regressors the data's columns (and the kinematic model) allow.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain or None
            The robot's kinematic chain.

        Returns
        -------
        list of str
        """
        return [n for n in self.names() if self.get(n).allowed(inp, chain)]

    def user_effects(self) -> dict[str, Effect]:
        """The effects beyond the catalogue: the plugins' and its own."""
        return self.plugins | self.own

    def declared(self, effects: Iterable[str]) -> list[declared.DeclaredEffect]:
        """The declared (YAML) effects among `effects`: what a saved model carries.

        Parameters
        ----------
        effects : iterable of str
            Effect names.

        Returns
        -------
        list of DeclaredEffect
        """
        return [e for e in map(self.get, effects) if isinstance(e, declared.DeclaredEffect)]


def default() -> Catalogue:
    """The catalogue and the installed plugins (read now), no declared effects."""
    return Catalogue()


def reload_entry_points() -> list[str]:
    """The plugin effects' names after a package was installed or removed in this process (a
    notebook, a test): importlib's caches of directory listings are dropped first. Catalogues
    built before keep the plugins they read."""
    importlib.invalidate_caches()
    return list(plugin_effects())


# The default catalogue, for a look from a shell or a test; code that has a call's catalogue uses it.
def names() -> tuple[str, ...]:
    """Every effect name of the default catalogue: the catalogue in the contract order, then the plugins'."""
    return default().names()


def check_names(effects: Iterable[str]) -> None:
    """DataError naming every effect in `effects` the default catalogue does not know.

    Parameters
    ----------
    effects : iterable of str
        Effect names.

    Raises
    ------
    DataError
    """
    default().check_names(effects)


def get(name: str) -> Effect:
    """Effect `name` of the default catalogue.

    Parameters
    ----------
    name : str
        The effect's name.

    Returns
    -------
    Effect
    """
    return default().get(name)


def build(name: str, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
    """The regressor block of the default catalogue's effect `name` (`Catalogue.build`).

    Parameters
    ----------
    name : str
        The effect's name.
    inp : Inputs
        The data's columns.
    chain : Chain or None
        The robot's kinematic chain.
    hyper : dict, optional
        Values of its nonlinear parameters.

    Returns
    -------
    Block
    """
    return default().build(name, inp, chain, hyper)


def available(inp: Inputs, chain: Chain | None) -> list[str]:
    """The default catalogue's effects that the data's columns (and the kinematic model) allow.

    Parameters
    ----------
    inp : Inputs
        The data's columns.
    chain : Chain or None
        The robot's kinematic chain.

    Returns
    -------
    list of str
    """
    return default().available(inp, chain)
