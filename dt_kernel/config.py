"""Load YAML into frozen pydantic models, turning validation errors into ConfigError.

Config is validated once, at the boundary; the error names the file, the key path, the value
seen and what is allowed.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from dt_kernel.errors import ConfigError

M = TypeVar("M", bound=BaseModel)


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads 1.0e6 and 1e-5 as floats (YAML 1.1 wants 1.0e+6)."""


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


def read_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(path, "<file>", str(path), f"a readable YAML file ({exc.strerror})") from exc
    try:
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
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
    """Validate `data` into `model`; the first problem becomes a ConfigError."""
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
