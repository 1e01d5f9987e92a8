"""JSON that strict consumers can read: numpy to Python, NaN and infinity to null."""
from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any


def jsonable(obj: Any, finite_only: bool = True) -> Any:
    """`obj` in types json.dumps writes as strict JSON.

    numpy scalars and arrays become Python numbers and lists, tuples lists, dict keys strings,
    objects with ``to_dict()`` their dict, and (with `finite_only`) every non-finite float None,
    since json.dumps would write NaN.

    Parameters
    ----------
    obj : Any
        The value.
    finite_only : bool, optional
        False keeps infinity, for files this project reads back itself (infinite degrees of
        freedom).

    Returns
    -------
    Any
    """
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) or not finite_only else None
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, finite_only) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, finite_only) for v in obj]
    if hasattr(obj, "to_dict"):
        return jsonable(obj.to_dict(), finite_only)
    if hasattr(obj, "tolist"):  # numpy scalars and arrays
        return jsonable(obj.tolist(), finite_only)
    return obj


def dumps(obj: Any, **kw: Any) -> str:
    """json.dumps of jsonable(obj); never writes NaN.

    Parameters
    ----------
    obj : Any
        The value.
    **kw
        Passed to json.dumps.

    Returns
    -------
    str
    """
    return json.dumps(jsonable(obj), allow_nan=False, **kw)


def compact(obj: Any) -> str:
    """dumps without spaces: one store row or bus message.

    Parameters
    ----------
    obj : Any
        The value.

    Returns
    -------
    str
    """
    return dumps(obj, separators=(",", ":"))
