"""Drivers by name, found through Python entry points (one group per kind: robot, tracker,
camera): `create(kind, name, config, world=..., source=..., key=...)` builds any driver the same
way, `check` validates its options without building it. The plugin rules and the built-in
drivers are in docs/drivers.md ("Driver plugins")."""
from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from drivers.base import Lifecycle
from dt_kernel.config import validate
from dt_kernel.errors import ConfigError

KINDS = ("robot", "tracker", "camera")
GROUP_PREFIX = "cobot_dt.drivers."
PROJECT = "cobot-dt"  # the distribution whose entry points BUILTIN mirrors

BUILTIN: dict[str, dict[str, str]] = {
    "robot": {"sim": "drivers.simulated.devices:SimRobot", "serial": "drivers.serial.controller:SerialController",
              "ur_rtde": "drivers.ur.driver:UrRtdeController"},
    "tracker": {"sim": "drivers.simulated.devices:SimTracker", "serial": "drivers.serial.tracker:SerialTracker"},
    "camera": {"sim_point": "drivers.simulated.devices:SimPointCamera",
               "sim_images": "drivers.simulated.camera_images:SimCameraRig",
               "natnet": "drivers.natnet.driver:NatNetRig"},
}


@dataclass(frozen=True)
class Entry:
    """One registered driver: its class as "module:Class" and the package that registered it."""

    target: str
    package: str


_entries: dict[str, dict[str, Entry]] | None = None
_clashes: dict[tuple[str, str], list[Entry]] = {}
_classes: dict[tuple[str, str], type[Lifecycle]] = {}


def group(kind: str) -> str:
    """The entry-point group of a kind of driver.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.

    Returns
    -------
    str
        E.g. ``cobot_dt.drivers.tracker``.
    """
    return GROUP_PREFIX + kind


def _add(table: dict[str, dict[str, Entry]], kind: str, name: str, entry: Entry) -> None:
    old = table[kind].get(name)
    if old is None:
        table[kind][name] = entry
    elif old.target != entry.target:  # the same class twice (BUILTIN and our metadata) is no clash
        _clashes.setdefault((kind, name), [old]).append(entry)


def _table() -> dict[str, dict[str, Entry]]:
    global _entries
    if _entries is None:
        _clashes.clear()
        table: dict[str, dict[str, Entry]] = {k: {} for k in KINDS}
        for kind, names in BUILTIN.items():
            for name, target in names.items():
                table[kind][name] = Entry(target, PROJECT)
        for kind in KINDS:
            for ep in metadata.entry_points(group=group(kind)):
                package = ep.dist.name if ep.dist is not None else "an unnamed package"
                _add(table, kind, ep.name, Entry(ep.value, package))
        _entries = table
    return _entries


def reload() -> dict[str, list[str]]:
    """Read the installed entry points again (a plugin installed into a running process, a test).

    Returns
    -------
    dict
        kind -> the known driver names of that kind, sorted.
    """
    global _entries
    importlib.invalidate_caches()  # importlib.metadata caches directory listings
    _entries = None
    _classes.clear()
    return {k: known(k) for k in KINDS}


def register(kind: str, name: str, target: str) -> None:
    """Add a driver in process (a notebook, a test); packages register through entry points instead.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.
    name : str
        The driver's name in the runtime YAML.
    target : str
        ``"module:Class"``, a ``drivers.base.Lifecycle`` subclass (imported when chosen).

    Raises
    ------
    ConfigError
        When ``kind`` is not a known kind.
    """
    _check_kind(kind)
    _add(_table(), kind, name, Entry(target, "registry.register()"))


def known(kind: str) -> list[str]:
    """The names of the drivers of a kind, sorted.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.

    Returns
    -------
    list of str

    Raises
    ------
    ConfigError
        When ``kind`` is not a known kind.
    """
    _check_kind(kind)
    return sorted(_table()[kind])


def entries(kind: str) -> dict[str, Entry]:
    """Every registered driver of a kind.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.

    Returns
    -------
    dict
        name -> Entry (class and package).

    Raises
    ------
    ConfigError
        When ``kind`` is not a known kind.
    """
    _check_kind(kind)
    return dict(_table()[kind])


def _check_kind(kind: str, source: str = "<config>") -> None:
    if kind not in KINDS:
        raise ConfigError(source, "kind", kind, "one of " + ", ".join(KINDS))


def driver_class(kind: str, name: str, source: str = "<config>", key: str | None = None) -> type[Lifecycle]:
    """The class registered under (kind, name), imported on first use and cached.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.
    name : str
        The driver's name.
    source : str
        Names the config file in errors.
    key : str or None
        Where the name sits in the file (default ``drivers.<kind>``).

    Returns
    -------
    type
        A ``drivers.base.Lifecycle`` subclass.

    Raises
    ------
    ConfigError
        At ``key``: listing the known names when ``name`` is unknown; naming both packages when two
        register it; naming the plugin and its import error when it does not load; or when the
        target is not a Lifecycle subclass.
    """
    _check_kind(kind, source)
    key = key or f"drivers.{kind}"
    cached = _classes.get((kind, name))
    if cached is not None:
        return cached
    table = _table()
    if name not in table[kind]:
        raise ConfigError(source, key, name, f"one of {', '.join(known(kind))} (the {kind} drivers installed: "
                                             f"entry point group {group(kind)})")
    if (kind, name) in _clashes:
        claims = "; ".join(f"{e.package} ({e.target})" for e in _clashes[kind, name])
        raise ConfigError(source, key, name, f"a name one package claims; {claims} all register it in "
                                             f"{group(kind)}: uninstall one")
    entry = table[kind][name]
    what = f"{kind} driver {name!r} of {entry.package} ({entry.target})"
    try:
        module, _, attr = entry.target.partition(":")
        cls = getattr(importlib.import_module(module), attr)
    except Exception as exc:  # a broken plugin names itself, whatever it raised on import
        raise ConfigError(source, key, name, f"a driver that loads; {what} does not: "
                                             f"{type(exc).__name__}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Lifecycle)):
        raise ConfigError(source, key, name, f"a drivers.base.Lifecycle subclass; {what} is {cls!r}")
    _classes[kind, name] = cls
    return cls


def needs_world(kind: str, name: str, source: str = "<config>") -> bool:
    """True if the driver runs on a simulated world (drivers.simulated.SimWorld).

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.
    name : str
        The driver's name.
    source : str
        Names the config file in errors.

    Returns
    -------
    bool

    Raises
    ------
    ConfigError
        As ``driver_class``.
    """
    return bool(getattr(driver_class(kind, name, source), "needs_world", False))


def _rekeyed(exc: ConfigError, key: str) -> ConfigError:
    """The driver's own error (key `url`) placed in the file's key path (`drivers.tracker.url`)."""
    return ConfigError(exc.file, f"{key}.{exc.key}", exc.value, exc.allowed)


def check(kind: str, name: str, config: Mapping[str, Any] | None, *, source: str = "<config>",
          key: str | None = None) -> None:
    """Validate a driver's options without building it.

    The class must load, and the options must fit its ``config_model`` when it declares one (a
    driver without one checks them in ``configure``).

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.
    name : str
        The driver's name.
    config : Mapping or None
        The driver's options.
    source : str
        Names the config file in errors.
    key : str or None
        Where the driver's section sits in the file (e.g. ``drivers.tracker``); given, a bad option
        is reported at ``drivers.tracker.<option>``.

    Raises
    ------
    ConfigError
        When the class does not load or an option does not fit.
    """
    cls = driver_class(kind, name, source, f"{key}.kind" if key else None)
    model = getattr(cls, "config_model", None)
    if model is not None:
        try:
            validate(model, dict(config or {}), source)
        except ConfigError as exc:
            if key is None:
                raise
            raise _rekeyed(exc, key) from exc


def create(kind: str, name: str, config: Mapping[str, Any] | None = None, *, world: Any = None,
           source: str = "<config>", key: str | None = None):
    """Build the driver (kind, name) through its class's ``from_config``.

    Parameters
    ----------
    kind : str
        ``robot``, ``tracker`` or ``camera``.
    name : str
        The driver's name.
    config : Mapping or None
        The driver's options; given, the driver is configured (state ``inactive``), else it is
        returned unconfigured.
    world : object, optional
        The simulated cell, for drivers that run on it (``needs_world``); others ignore it.
    source : str
        Names the config file in errors.
    key : str or None
        Where the driver's section sits in the file (e.g. ``drivers.tracker``); given, a bad option
        is reported at ``drivers.tracker.<option>``.

    Returns
    -------
    Lifecycle
        The driver.

    Raises
    ------
    ConfigError
        When the class does not load or the driver refuses its options.
    """
    cls = driver_class(kind, name, source, f"{key}.kind" if key else None)
    try:
        return cls.from_config(config, world=world, source=source)
    except ConfigError as exc:
        if key is None:
            raise
        raise _rekeyed(exc, key) from exc
