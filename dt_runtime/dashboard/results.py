"""The metrologist's view's inputs: the results under a directory (`dt dashboard --results DIR`)
and what the page needs of each, read when the page asks for it.

A result is a directory holding one of:
    compare.json   `dt compare --report DIR`: its models' figures, every row's residual per model
                   (residuals.csv, reports.residuals) and the report's figures (report.html)
    diagnose.json  `dt diagnose --auto --out MODEL`: the steps (the change at each step, the
                   held-out error before and after it), the verdict and every row's held-out
                   residual of the first and the final model (residuals.csv, reports.residuals)
    twin.json      `dt demo` / `dt calibrate`: the twin's provenance, its e_LT map at its campaign's
                   points (scene.error_map) and the figures of the report beside it (`dt demo`'s)
DIR itself may be a result; results below it are found down to `MAX_DEPTH` directories. The
report's figures are its own PNGs (the base64 <img> of each <figure> with its caption), never
drawn again here.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

from dt_kernel.errors import ConfigError, DataError, ModelError, TwinError
from dt_runtime.common.safe_files import read_regular
from dt_runtime.common.safe_json import read_json
from dt_runtime.reports.residuals import NAME as RESIDUALS
from dt_runtime.reports.residuals import read_residuals

log = logging.getLogger("dt.dashboard")
MARKS = {"compare.json": "compare", "diagnose.json": "diagnose", "twin.json": "twin"}
MAX_DEPTH = 3
MAX_RESULTS = 200
MAX_REPORT_BYTES = 64 * 2 ** 20


@dataclass(frozen=True)
class Result:
    """One result found under --results: its ``kind`` (compare, diagnose or twin), its directory and its name below the
    results directory (``.`` for the directory itself)."""
    kind: str  # compare, diagnose or twin
    path: Path  # its directory
    name: str  # the path below the results directory ('.' for the directory itself)


def find_results(root: str | Path) -> list[Result]:
    """The results in ``root`` and below (breadth first to depth 3, sorted by name, at most MAX_RESULTS).

    A directory holding compare.json, diagnose.json or twin.json is a result.

    Parameters
    ----------
    root : str or Path

    Returns
    -------
    list of Result

    Raises
    ------
    ConfigError
        When ``root`` is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise ConfigError("<command line>", "--results", str(root), "a directory holding results of dt compare "
                          "--report, dt diagnose --auto --out or a twin (or one of them)")
    found: list[Result] = []
    level = [root]
    for _ in range(MAX_DEPTH + 1):
        nxt: list[Path] = []
        for d in sorted(level):
            kind = next((k for mark, k in MARKS.items() if (d / mark).is_file()), None)
            if kind is not None:
                found.append(Result(kind, d, str(d.relative_to(root)) or "."))
            try:
                nxt += [c for c in d.iterdir() if c.is_dir() and not c.is_symlink() and not c.name.startswith(".")]
            except OSError:
                continue
        level = nxt
    return sorted(found, key=lambda r: r.name)[:MAX_RESULTS]


class _Figures(HTMLParser):
    """Each <figure>'s inline PNG, its alt text and its caption, from a report of reports.html."""

    def __init__(self) -> None:
        super().__init__()
        self.figures: list[dict[str, str]] = []
        self._in_fig = self._in_cap = False
        self._cur: dict[str, str] = {}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "figure":
            self._in_fig, self._cur = True, {"caption": ""}
        elif tag == "img" and self._in_fig and (a.get("src") or "").startswith("data:image/png;base64,"):
            self._cur.update(src=a["src"] or "", alt=a.get("alt") or "")
        elif tag == "figcaption" and self._in_fig:
            self._in_cap = True

    def handle_endtag(self, tag: str) -> None:
        if tag == "figcaption":
            self._in_cap = False
        elif tag == "figure" and self._in_fig:
            self._in_fig = False
            if "src" in self._cur:
                self.figures.append(self._cur)

    def handle_data(self, data: str) -> None:
        if self._in_cap:
            self._cur["caption"] += data


def report_figures(report: Path) -> list[dict[str, str]]:
    """The figures of a report (``src`` a data: URI, ``alt``, ``caption``); none without the file.

    Parameters
    ----------
    report : Path
        A report.html.

    Returns
    -------
    list of dict

    Raises
    ------
    DataError
        When the file cannot be read (not a regular file, too large).
    """
    if not report.is_file():
        return []
    p = _Figures()
    p.feed(read_regular(report, MAX_REPORT_BYTES, "a report").decode("utf-8", errors="replace"))
    return p.figures


def load(result: Result) -> dict[str, Any]:
    """What the page shows of a result (JSON-able; mm as the files hold them).

    Parameters
    ----------
    result : Result

    Returns
    -------
    dict

    Raises
    ------
    DataError, ModelError
        Naming the file, for one that cannot be read.
    """
    out: dict[str, Any] = {"kind": result.kind, "name": result.name, "path": str(result.path)}
    if result.kind == "compare":
        return out | _compare(result.path)
    if result.kind == "diagnose":
        return out | _diagnose(result.path)
    return out | _twin(result.path)


def _compare(d: Path) -> dict[str, Any]:
    c = read_json(d / "compare.json", "a dt compare result")
    models = [{"name": m.get("name"), "description": m.get("description"), "n": m.get("n"),
               "rmse_mm": m.get("rmse_mm"), "rmse_U95_mm": m.get("rmse_U95_mm"), "mae_mm": m.get("mae_mm"),
               "max_mm": m.get("max_mm"), "fails": (m.get("failures") or {}).get("fraction")}
              for m in c.get("models") or []]
    first = (c.get("models") or [{}])[0].get("sessions") or []
    return {"dataset": c.get("dataset"), "n": c.get("n"), "noise_floor_mm": c.get("noise_floor_mm"),
            "heldout": c.get("heldout"), "in_sample": c.get("in_sample") or [], "models": models,
            "sessions": {str(s.get("session")): s.get("name") or s.get("file") for s in first},
            "worst_cells": c.get("worst_cells") or [],
            "figures": report_figures(d / "report.html")} | _rows(d, "dt compare --report", "")


def _rows(d: Path, command: str, instead: str) -> dict[str, Any]:
    """The result's residuals.csv (`rows`), or why there is none (`rows_why`): a result written
    before its command wrote one."""
    if (d / RESIDUALS).is_file():
        return {"rows": read_residuals(d / RESIDUALS), "rows_why": None}
    return {"rows": None, "rows_why": f"no {RESIDUALS} in {d} (written by {command} since the dashboard's "
                                      f"metrologist's view){instead}"}


STEP_KEYS = ("model", "rmse_mm", "u_rmse_mm", "deploy_rmse_mm", "deploy_kind", "change", "p_value",
             "explained_fraction", "alpha", "change_deploy_kind", "change_deploy_rmse_mm", "follows")


def _diagnose(d: Path) -> dict[str, Any]:
    g = read_json(d / "diagnose.json", "a dt diagnose result")
    steps = g.get("steps")
    if not isinstance(steps, list):  # without --auto: a ranking, shown as one step per candidate
        steps = []
    return {"dataset": (g.get("data") or {}).get("path") if isinstance(g.get("data"), dict) else g.get("data"),
            "n": g.get("n"), "start": g.get("start"), "added": g.get("added"), "as_is_rmse_mm": g.get("as_is_rmse_mm"),
            "final_rmse_mm": g.get("final_rmse_mm"), "final_deploy_rmse_mm": g.get("final_deploy_rmse_mm"),
            "deploy_kind": g.get("deploy_kind"), "noise_floor_mm": g.get("noise_floor_mm"),
            "stop_reason": g.get("stop_reason"), "verdict": g.get("verdict"),
            "steps": [{k: s.get(k) for k in STEP_KEYS} for s in steps if isinstance(s, dict)],
            "ranking": g.get("ranking") or [], "heldout": {"method": "by point, the steps' folds (residuals.csv)"},
            "sessions": {str(s.get("session")): s.get("name") for s in g.get("sessions") or [] if isinstance(s, dict)},
            "figures": []} | _rows(d, "dt diagnose --auto --out", ": compare its model on the data (dt compare "
                                   "--model DIR --data FILE --report OUT) and open that result")


def _twin(d: Path) -> dict[str, Any]:
    from dt_runtime.dashboard.scene import error_map, provenance
    from dt_runtime.twin.twin import Twin

    prov = provenance(d)
    try:
        em = error_map(Twin.load(d), d, prov)
    except (ModelError, TwinError, DataError) as exc:
        em = {"why": str(exc)}
    return {"provenance": prov, "error_map": em, "figures": report_figures(d.parent / "report.html")}
