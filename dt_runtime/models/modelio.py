"""Reading the JSON half of a saved model (JSON + NPZ, never pickle) with its format version."""
from __future__ import annotations

import json
from pathlib import Path

from dt_kernel.errors import ModelError


def read_meta(path: Path, version: int | tuple[int, ...], what: str) -> dict:
    """The JSON metadata at `path`; ModelError if unreadable or of a format version not in
    `version` (one, or those this version reads)."""
    try:
        meta = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelError(f"{Path(path).parent}: not a {what} directory ({Path(path).name} unreadable: {exc})") from exc
    if not isinstance(meta, dict):
        raise ModelError(f"{path}: not a {what} file (a JSON object expected)")
    versions = version if isinstance(version, tuple) else (version,)
    if meta.get("format_version") not in versions:
        raise ModelError(f"{path}: format_version {meta.get('format_version')!r}, this version reads "
                         f"{', '.join(map(str, versions))}")
    return meta
