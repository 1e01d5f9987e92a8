"""Reading the JSON half of a saved model (JSON + NPZ, never pickle) with its format version."""
from __future__ import annotations

import json
from pathlib import Path

from dt_kernel.errors import ModelError


def read_meta(path: Path, version: int, what: str) -> dict:
    """The JSON metadata at `path`; ModelError if unreadable or of another format version."""
    try:
        meta = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelError(f"{Path(path).parent}: not a {what} directory ({Path(path).name} unreadable: {exc})") from exc
    if meta.get("format_version") != version:
        raise ModelError(f"{path}: format_version {meta.get('format_version')!r}, this version reads {version}")
    return meta
