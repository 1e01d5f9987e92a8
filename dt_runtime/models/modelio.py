"""Reading the JSON half of a saved model (JSON + NPZ, never pickle) with its format version."""
from __future__ import annotations

from pathlib import Path

from dt_kernel.errors import DataError, ModelError
from dt_runtime.common.safe_json import read_json


def read_meta(path: Path, version: int | tuple[int, ...], what: str, infinite_ok: tuple[str, ...] = ()) -> dict:
    """The JSON metadata at `path` (`common.safe_json.read_json`: a regular file, size, depth and
    integers bounded, every number finite but +infinity under a key ending in one of
    `infinite_ok`); ModelError if unreadable, refused or of a format version not in `version`
    (one, or those this version reads).

    Parameters
    ----------
    path : Path
        The JSON file.
    version : int or tuple of int
        The format versions read.
    what : str
        What the file should be.
    infinite_ok : tuple of str, optional
        Keys under which +infinity is allowed.

    Returns
    -------
    dict
    """
    try:
        meta = read_json(path, f"a {what} file", infinite_ok=infinite_ok)
    except DataError as exc:
        raise ModelError(f"{Path(path).parent}: not a {what} directory ({exc})") from exc
    if not isinstance(meta, dict):
        raise ModelError(f"{path}: not a {what} file (a JSON object expected)")
    versions = version if isinstance(version, tuple) else (version,)
    if meta.get("format_version") not in versions:
        raise ModelError(f"{path}: format_version {meta.get('format_version')!r}, this version reads "
                         f"{', '.join(map(str, versions))}")
    return meta
