"""Where a session's companion files are: the joint-angle table and the given registration of a
measurement file, named in the import mapping once for every session of a campaign
(`companion`); and the name each session is reported by (`session_names`).
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from dt_kernel.errors import ConfigError, DataError


def companion(spec: str | Mapping[str, str], data: Path, mapping_dir: Path | None, key: str,
              mapping_file: str = "<mapping>") -> Path:
    """The companion file of `data` named by `spec` (template or per-file table), which must exist.
    `key` is the mapping key (for the messages).

    Parameters
    ----------
    spec : str or Mapping
        A template ({stem}, {name}) or a table {data file name: file}.
    data : Path
        The data file.
    mapping_dir : Path or None
        Where the mapping is.
    key : str
        The mapping key, for messages.
    mapping_file : str, optional
        The mapping's name, for messages.

    Returns
    -------
    Path

    Notes
    -----
    A name may hold `{stem}` (the data file's name without its extension) or `{name}` (with it),
    so one mapping serves `s1.csv`, `s2.csv`, ... with `s1_joints.csv`, `s2_joints.csv`, ...; or the
    mapping gives a table `{data file name: companion}` (for names that follow no pattern). A
    relative name is looked up beside the data file first (a campaign folder holds its sessions'
    files), then beside the mapping (a mapping shipped with fixed companions).
    """
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


def session_names(files: Sequence[str | Path]) -> list[str]:
    """A name for each file of a campaign, to report its session by: the file's stem where no other
    file has it, else the shortest path suffix that tells it apart (`day1/points`, `day2/points`),
    else its name with the extension (`s1.csv`, `s1.xlsx`), else its whole path; the same file
    given twice gets its position too (`points (2)`).

    Parameters
    ----------
    files : sequence of str or Path
        The campaign's files, in order.

    Returns
    -------
    list of str
    """
    paths = [Path(os.path.abspath(f)) for f in files]
    unique = list(dict.fromkeys(paths))

    def candidates(p: Path) -> list[str]:
        parts = p.parent.parts[1:]  # without the root: a name is relative
        out = ["/".join([*parts[len(parts) - k:], p.stem]) for k in range(len(parts) + 1)]
        return out + ["/".join([*parts[len(parts) - k:], p.name]) for k in range(len(parts) + 1)]

    cands = {p: candidates(p) for p in unique}
    name = {}
    for p, mine in cands.items():
        others = {c for q, theirs in cands.items() if q != p for c in theirs}
        name[p] = next((c for c in mine if c not in others), mine[-1])
    seen: dict[Path, int] = {}
    out = []
    for p in paths:  # the very same file given twice: its position in the list tells them apart
        seen[p] = seen.get(p, 0) + 1
        out.append(name[p] if seen[p] == 1 else f"{name[p]} ({seen[p]})")
    return out
