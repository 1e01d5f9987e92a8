"""Where a session's companion files are: the joint-angle table and the given registration of a
measurement file, named in the import mapping once for every session of a campaign.

A name may hold `{stem}` (the data file's name without its extension) or `{name}` (with it), so
one mapping serves `s1.csv`, `s2.csv`, ... with `s1_joints.csv`, `s2_joints.csv`, ...; or the
mapping gives a table `{data file name: companion}` (for names that follow no pattern). A relative
name is looked up beside the data file first (a campaign folder holds its sessions' files), then
beside the mapping (a mapping shipped with fixed companions).
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from dt_kernel.errors import ConfigError, DataError


def companion(spec: str | Mapping[str, str], data: Path, mapping_dir: Path | None, key: str,
              mapping_file: str = "<mapping>") -> Path:
    """The companion file of `data` named by `spec` (template or per-file table), which must exist.
    `key` is the mapping key (for the messages)."""
    if isinstance(spec, Mapping):
        if data.name not in spec:
            raise ConfigError(mapping_file, key, sorted(spec), f"an entry for the data file '{data.name}'")
        name = spec[data.name]
    else:
        try:
            name = spec.format(stem=data.stem, name=data.name)
        except (KeyError, IndexError, ValueError) as exc:
            raise ConfigError(mapping_file, key, spec, "a file name; placeholders {stem} and {name} only") from exc
    p = Path(name)
    if p.is_absolute():
        tried = [p]
    else:
        tried = [data.parent / p] + ([mapping_dir / p] if mapping_dir is not None else [])
    for c in tried:
        if c.is_file():
            return c
    raise DataError(f"{data}: mapping key '{key}' names {name!r}; no such file (looked for "
                    + ", ".join(str(c) for c in tried) + ")")
