"""Report plumbing shared by the HTML reports: each block of a report is built on its own from
the result's summary (dict, mm) and arrays (SI); a missing key or array turns that block into a
note instead of sinking the report (`run_block`)."""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Literal, overload

import numpy as np

from dt_runtime.reports.html import note, plt

log = logging.getLogger(__name__)

COLORS = {"x": "#1f77b4", "y": "#2ca02c", "z": "#d62728"}  # one colour per axis in every figure
# Font sizes (pt) of every figure: at the reports' 80 dpi, shown unscaled, 10 pt is 11 px on screen.
TICK, LEGEND, LABEL, TITLE = 10, 9, 11, 11


class Missing(Exception):
    """Data for a block is absent; the block becomes a note."""


def summary_value(d: dict, *keys):
    """The value at a key path of a summary.

    Parameters
    ----------
    d : dict
        The summary.
    *keys : str
        The path, e.g. ("validation", "n").

    Returns
    -------
    Any

    Raises
    ------
    Missing
        When a key is absent or None.
    """
    cur: Any = d
    for k in keys:
        if not isinstance(cur, dict) or k not in cur or cur[k] is None:
            raise Missing(f"summary has no '{'.'.join(keys)}'")
        cur = cur[k]
    return cur


@overload


def array(arrays: dict, key: str, cols: int | None = None, required: Literal[True] = True) -> np.ndarray: ...


@overload


def array(arrays: dict, key: str, cols: int | None = None, *, required: bool) -> np.ndarray | None: ...


def array(arrays: dict, key: str, cols: int | None = None, required: bool = True) -> np.ndarray | None:
    """`arrays[key]` as a float array (n, >= cols); None only when not `required` and absent.

    Parameters
    ----------
    arrays : dict
        The arrays by key.
    key : str
        The array's key.
    cols : int, optional
        Least number of columns (a 1D array of exactly that size is accepted as is).
    required : bool, optional
        False returns None for an absent array.

    Returns
    -------
    ndarray or None

    Raises
    ------
    Missing
        When required and absent, empty or of the wrong shape.
    """
    v = arrays.get(key) if isinstance(arrays, dict) else None
    if v is None:
        if required:
            raise Missing(f"array '{key}' not available")
        return None
    a = np.asarray(v, dtype=float)
    if cols is not None and (a.ndim != 2 or a.shape[1] < cols):
        if a.ndim == 1 and a.size == cols:
            return a
        raise Missing(f"array '{key}' has shape {a.shape}, expected (n, {cols})")
    if a.size == 0:
        raise Missing(f"array '{key}' is empty")
    return a


def fixed(v, nd: int = 3) -> str:
    """A number with `nd` decimals for a table ("–" when not a number, "∞", "NaN"; never "-0.000").

    Parameters
    ----------
    v : Any
        The value.
    nd : int, optional
        Decimals.

    Returns
    -------
    str
    """
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "–"
    if not math.isfinite(x):
        return "∞" if x == math.inf else "NaN"
    out = f"{x:.{nd}f}"
    return out[1:] if out.startswith("-") and float(out) == 0 else out  # no "-0.000"


def levels(v: np.ndarray, max_levels: int = 12, bins: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Level index per sample and level centres: the factor's own levels if few, else quantile bins.

    Parameters
    ----------
    v : ndarray
        (n,) the factor's values.
    max_levels : int, optional
        Most distinct values kept as levels.
    bins : int, optional
        Quantile bins otherwise.

    Returns
    -------
    index : ndarray
        (n,) level of each sample.
    centres : ndarray
        The levels' values (bins: their means).
    """
    r = np.round(v, 6)
    uniq = np.unique(r)
    if len(uniq) <= max_levels:
        return np.searchsorted(uniq, r), uniq
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    centres = np.array([v[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(edges) - 1)])
    return idx, centres


def unique_in_order(p: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """The distinct rows of `p` (equal within `tol`), in the order of their first appearance.

    Parameters
    ----------
    p : ndarray
        (n, d).
    tol : float, optional
        Rows equal after rounding to this step are one.

    Returns
    -------
    ndarray
    """
    key = np.round(p / tol).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return p[np.sort(first)]


Block = Callable[[dict, dict], str]


def run_block(fn: Block, s: dict, a: dict) -> str:
    """One block's HTML; missing data or a failure becomes a note instead (a report never sinks the run).

    Parameters
    ----------
    fn : Block
        The block, fn(summary, arrays) -> HTML.
    s : dict
        The summary.
    a : dict
        The arrays.

    Returns
    -------
    str
    """
    try:
        return fn(s, a)
    except Missing as exc:
        return note(f"Not shown: {exc}.")
    except Exception as exc:  # a report must never sink the run that produced the numbers
        log.warning("report block %s failed", fn.__name__, exc_info=True)
        plt.close("all")
        return note(f"Not shown ({fn.__name__}): {type(exc).__name__}: {exc}")
