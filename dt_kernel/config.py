"""Load YAML into frozen pydantic models, turning validation errors into ConfigError.

Config is validated once, at the boundary; the error names the file, the key path, the value
seen and what is allowed. Every YAML file of the project is read here (`read_yaml`), bounded
before anything downstream sees it. See docs/cli.md ("Bounded parsing").
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from dt_kernel.errors import ConfigError

M = TypeVar("M", bound=BaseModel)


#: ~250 times the largest config the project ships (configs/cameras.yaml, 3.7 kB).
MAX_YAML_BYTES = 2 ** 20
#: A config nests a handful of levels (runtime -> drivers -> camera -> options); PyYAML's
#: composer recurses once per level, so 100,000 levels would end in RecursionError.
MAX_YAML_DEPTH = 32
#: Scalars, sequences and mappings after aliases are expanded: a config holds a few hundred.
MAX_YAML_NODES = 100_000


class _Bound(yaml.YAMLError):
    """A bound of the loader exceeded: what was seen (with its line) and what is allowed."""

    def __init__(self, seen: str, allowed: str, mark: yaml.Mark | None):
        line = f" at line {mark.line + 1}" if mark is not None else ""
        super().__init__(f"{seen}{line}")
        self.seen, self.allowed = f"{seen}{line}", allowed


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads 1.0e6 and 1e-5 as floats (YAML 1.1 wants 1.0e+6), and bounds
    what it composes: nesting depth and node count, an alias counted as the node it repeats
    (its size and its depth below), before anything is constructed."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0  # collections open around the node being composed
        self._deepest = 0  # the deepest level reached so far (aliases expanded)
        self._nodes = 0
        self._anchored: dict[str, tuple[int, int]] = {}  # anchor -> (nodes, levels below) of its finished node

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            anchor = str(event.anchor)
            if anchor not in self._anchored and anchor in self.anchors:  # the alias inside its own anchor
                raise _Bound(f"recursive alias *{anchor}", "aliases of finished nodes only", event.start_mark)
            nodes, below = self._anchored.get(anchor, (0, 0))  # an undefined alias: PyYAML's error
            self._count(nodes, event.start_mark)
            self._reach(self._depth + below, event.start_mark)
            return super().compose_node(parent, index)
        start, outer_deepest, before = self._depth, self._deepest, self._nodes
        self._deepest = start
        collection = isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent))
        if collection:
            self._depth += 1
            self._reach(self._depth, event.start_mark)
        self._count(1, event.start_mark)
        node = super().compose_node(parent, index)
        self._depth = start
        if getattr(event, "anchor", None) is not None:
            self._anchored[str(event.anchor)] = (self._nodes - before, self._deepest - start)
        self._deepest = max(outer_deepest, self._deepest)
        return node

    def _count(self, n: int, mark: yaml.Mark) -> None:
        self._nodes += n
        if self._nodes > MAX_YAML_NODES:
            raise _Bound(f"more than {MAX_YAML_NODES} values (aliases counted as what they repeat)",
                         f"at most {MAX_YAML_NODES} values: a config, not a data set (an alias bomb?)", mark)

    def _reach(self, depth: int, mark: yaml.Mark) -> None:
        if depth > MAX_YAML_DEPTH:
            raise _Bound(f"lists and mappings nested deeper than {MAX_YAML_DEPTH} levels (aliases expanded)",
                         f"at most {MAX_YAML_DEPTH} levels of nesting", mark)
        self._deepest = max(self._deepest, depth)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


class Frozen(BaseModel):
    """Base for every config object: unknown keys are errors, instances are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def _read_text(path: Path) -> str:
    """The file's text: at most MAX_YAML_BYTES read (a device such as /dev/zero ends there too),
    UTF-8 without NUL bytes; ConfigError naming what the file is instead."""
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise ConfigError(path, "<file>", str(path), f"a readable YAML file ({exc.strerror})") from exc
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(path, "<file>", f"more than {MAX_YAML_BYTES} bytes",
                          f"a YAML config of at most {MAX_YAML_BYTES} bytes")
    nul = raw.find(b"\0")
    if nul >= 0:
        raise ConfigError(path, "<file>", f"a binary file (a NUL byte at offset {nul})", "a YAML text file (UTF-8)")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(path, "<file>", f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})",
                          "a YAML text file encoded as UTF-8") from exc


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a YAML file, read within the loader's bounds.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    dict
        The top-level mapping (empty for an empty file).

    Raises
    ------
    ConfigError
        Naming the file for anything else (unreadable, too large, binary, too deep, too
        many values, not a mapping).

    Notes
    -----
    Every YAML file of the project (runtime, bus, robot, scenario, plan, import mapping, declared
    effects, instruments) is read here: at most MAX_YAML_BYTES read, text (UTF-8, no NUL bytes),
    nesting at most MAX_YAML_DEPTH deep, and at most MAX_YAML_NODES nodes with every alias counted
    as the whole node it repeats. Aliases stay usable; an alias bomb (nine aliases of nine aliases
    ..., a few hundred bytes that expand to 10^8 values) is refused while it is read, not after
    pydantic has walked the expansion.
    """
    path = Path(path)
    text = _read_text(path)
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except _Bound as exc:
        raise ConfigError(path, "<file>", exc.seen, exc.allowed) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(path, "<file>", "unparsable YAML", f"valid YAML ({exc})") from exc
    except ValueError as exc:  # PyYAML's constructors: an impossible date such as 2026-13-01
        raise ConfigError(path, "<file>", "unreadable value", f"valid YAML values ({exc})") from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(path, "<root>", type(data).__name__, "a mapping of keys to values")
    return data


def validate(model: type[M], data: dict[str, Any], source: str | Path = "<config>") -> M:
    """Validate `data` into `model`; the first problem becomes a ConfigError.

    Parameters
    ----------
    model : type
        The pydantic model.
    data : dict
        The parsed mapping.
    source : str or Path, optional
        What the error names as the file.

    Returns
    -------
    BaseModel
        An instance of `model`.
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "<root>"
        # a missing key's "input" is the mapping around it: say what is wrong instead
        value = "<missing>" if err["type"] == "missing" else err.get("input")
        if err["type"] == "extra_forbidden":
            allowed = "known keys: " + (", ".join(sorted(_fields_at(model, err["loc"][:-1]))) or "none")
        else:
            allowed = err["msg"]
        raise ConfigError(source, key, value, allowed) from exc


def load_yaml(path: str | Path, model: type[M]) -> M:
    """Read a YAML file and validate it into a frozen model.

    Parameters
    ----------
    path : str or Path
        The YAML file.
    model : type
        The pydantic model to validate into.

    Returns
    -------
    BaseModel
        An instance of `model`.

    Raises
    ------
    ConfigError
        Naming the file, key, value seen and what is allowed.
    """
    return validate(model, read_yaml(path), path)


def _fields_at(model: type[BaseModel], loc: tuple) -> list[str]:
    """Field names of the (nested) model at `loc`, for 'what is allowed' in errors."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        field = getattr(current, "model_fields", {}).get(part)
        if field is None:
            return []
        ann = field.annotation
        for cand in (ann, *getattr(ann, "__args__", ())):
            if isinstance(cand, type) and issubclass(cand, BaseModel):
                current = cand
                break
            for sub in getattr(cand, "__args__", ()):
                if isinstance(sub, type) and issubclass(sub, BaseModel):
                    current = sub
                    break
    return list(getattr(current, "model_fields", {}).keys())
