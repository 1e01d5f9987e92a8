"""What the dashboard knows of the twin itself (read once, at start): the arm's kinematics for the
3D view, the calibrated volume as edges, the Eq. 17 thresholds, and the twin's provenance.

The arm is drawn through the twin's own kinematics: the nominal chain of the robot config its
e_LT map names (`HybridModel.chain`: the same chain the effects, `dt export` and the daemon's
inverse kinematics use), evaluated at the controller's joint angles (`q` of `.../telemetry`):
the joint origins and the TCP, in the robot frame. A twin without a robot config gets no arm,
only the points.

The calibrated volume is kept by the twin as facet planes (frames.volume); the page needs its
corners and edges: the planes' intersection (scipy's HalfspaceIntersection, from the Chebyshev
centre, the point deepest inside) and the hull of those corners.

The error map as arrows: the twin's e_LT map evaluated where it was trained, at the rows of the
campaign's DOE (the campaign.yaml its provenance names; `calibration.phase_inputs`, the rows in
time order, as the calibration fitted them), aggregated per commanded point (`analysis.points`),
in the robot's axes. An error of 0.1 mm is invisible in a 2 m cell: the arrows are drawn `scale`
times their length (1, 2 or 5 x 10^k, so the longest is about an eighth of the campaign's extent),
and the page says so ("x N").
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from dt_kernel.errors import DataError, ModelError, TwinError
from dt_runtime.analysis.points import per_point
from dt_runtime.analysis.validity import restated
from dt_runtime.frames.kinematics import Chain
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.measurements.campaign_files import read_phase
from dt_runtime.twin.calibration import phase_inputs
from dt_runtime.twin.monitor import Monitor
from dt_runtime.twin.twin import Twin
from dt_runtime.workflows.campaign_dir import read_manifest

log = logging.getLogger("dt.dashboard")


def volume_edges(volume: CalibratedVolume) -> tuple[list[list[float]], list[list[int]]]:
    """Corners and edges of the hull of the calibrated volume's facet planes.

    Parameters
    ----------
    volume : CalibratedVolume

    Returns
    -------
    corners : list of list of float
        m, robot frame.
    edges : list of list of int
        Index pairs into ``corners`` (none when the planes bound no volume).
    """
    A, b = volume.normals, volume.offsets
    # Chebyshev centre: max r subject to A x + r |A_i| <= -b (a point strictly inside)
    norm = np.linalg.norm(A, axis=1)
    res = linprog(np.r_[0.0, 0.0, 0.0, -1.0], A_ub=np.c_[A, norm], b_ub=-b,
                  bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    if not res.success or res.x[3] <= 0:
        return [], []
    try:
        corners = HalfspaceIntersection(np.c_[A, b], res.x[:3]).intersections
        hull = ConvexHull(corners)
    except QhullError:
        return [], []
    # Qhull triangulates the hull's faces: an edge is drawn only between two facets that are not
    # coplanar (the box's diagonals are not edges of the volume).
    normals: dict[tuple[int, int], list[np.ndarray]] = {}
    for simplex, eq in zip(hull.simplices, hull.equations):
        for i in range(3):
            a, c = int(simplex[i]), int(simplex[(i + 1) % 3])
            normals.setdefault((min(a, c), max(a, c)), []).append(eq[:3])
    kept = [list(e) for e, ns in sorted(normals.items()) if len(ns) != 2 or float(np.dot(ns[0], ns[1])) < 1 - 1e-9]
    return corners.tolist(), kept


def nice_scale(longest_m: float, extent_m: float, fraction: float = 0.12) -> float:
    """The factor (1, 2 or 5 x 10^k, at least 1) that draws an arrow of ``longest_m`` at about
    ``fraction`` of ``extent_m``, never longer.

    Parameters
    ----------
    longest_m : float
        m, the longest arrow.
    extent_m : float
        m, the scene's extent.
    fraction : float

    Returns
    -------
    float
    """
    if not (longest_m > 0 and extent_m > 0):
        return 1.0
    want = fraction * extent_m / longest_m
    k = 10.0 ** np.floor(np.log10(want))
    return float(max(1.0, max(m * k for m in (1.0, 2.0, 5.0) if m * k <= want * (1 + 1e-9))))


def campaign_path(prov: dict[str, Any], twin_dir: Path) -> Path | None:
    """The campaign.yaml the twin's provenance names.

    As recorded when absolute; else tried relative to the twin's parent, its grandparent and the
    working directory.

    Parameters
    ----------
    prov : dict
        The twin's provenance (``provenance``).
    twin_dir : Path

    Returns
    -------
    Path or None
        None when it is not on this machine.
    """
    rec = prov.get("campaign")
    if not rec:
        return None
    p = Path(rec)
    for cand in ([p] if p.is_absolute() else [twin_dir.parent / p, twin_dir.parent.parent / p, Path.cwd() / p]):
        if cand.is_file():
            return cand
    return None


def error_map(twin: Twin, twin_dir: Path, prov: dict[str, Any]) -> dict[str, Any]:
    """The twin's e_LT_hat at its campaign's DOE points, per commanded point (m, robot frame and axes).

    Parameters
    ----------
    twin : Twin
    twin_dir : Path
    prov : dict
        The twin's provenance.

    Returns
    -------
    dict
        ``campaign``, ``rows``, ``points``, ``e_hat`` (the mean predicted error of each point's
        rows), ``count``, ``max_m``, ``rms_m`` and the arrows' ``scale``; or ``why`` there is none.
    """
    path = campaign_path(prov, twin_dir)
    if path is None:
        return {"why": f"the campaign the twin names ({prov.get('campaign') or 'none'}) is not on this machine"}
    try:
        doe = read_phase(read_manifest(path).doe, "doe")
        ok = np.all(np.isfinite(doe.p_rdk), axis=1) & np.isfinite(doe.speed)
        e_gl = twin.e_lt.predict(phase_inputs(doe, ok))  # GL axes, the rows in time order
    except (DataError, ModelError, TwinError, OSError, ValueError) as exc:
        log.warning("no error map in the view: %s", exc)
        return {"why": f"{path}: {exc}"}
    e = e_gl @ twin.T_rdk.R  # GL -> robot axes (row vectors: R^T e), as Twin.e_lt_hat
    P, mean, cnt = per_point(doe.p_rdk[ok], e)
    norm = np.linalg.norm(mean, axis=1)
    extent = float(np.linalg.norm(np.ptp(P, axis=0))) if len(P) > 1 else 1.0
    return {"campaign": str(path), "rows": int(ok.sum()), "points": P.tolist(), "e_hat": mean.tolist(),
            "count": cnt.astype(int).tolist(), "max_m": float(norm.max()) if len(norm) else 0.0,
            "rms_m": float(np.sqrt(np.mean(norm ** 2))) if len(norm) else 0.0,
            "scale": nice_scale(float(norm.max()) if len(norm) else 0.0, extent)}


class Scene:
    """The twin's static part of the view (`to_dict` is what the page fetches from /api/scene)."""

    def __init__(self, twin_dir: str | Path, alpha: float):
        self.twin_dir = Path(twin_dir)
        self.twin = Twin.load(self.twin_dir)
        self.chain: Chain | None = None
        try:
            self.chain = self.twin.e_lt.chain()
        except (TwinError, OSError) as exc:  # the view still shows the points, without the arm
            log.warning("the twin's robot config cannot be read, no arm in the view: %s", exc)
        self.t_crit = Monitor(self.twin, alpha).t_crit
        self.alpha = alpha

    def arm(self, q: Any) -> list[list[float]] | None:
        """The arm at joint angles ``q``: the robot frame's origin, every joint's origin and the TCP.

        Parameters
        ----------
        q : array_like or None
            (dof,) rad.

        Returns
        -------
        list of list of float or None
            m, robot frame; None without a chain or for angles that do not fit it.
        """
        if self.chain is None or q is None:
            return None
        try:
            qa = np.asarray(q, dtype=float)
        except (TypeError, ValueError):
            return None
        if qa.shape != (self.chain.dof,) or not np.all(np.isfinite(qa)):
            return None
        pos, _, T = self.chain.frames(qa[None, :])
        return np.vstack([np.zeros(3), pos[0], T[0, :3, 3]]).tolist()

    def to_dict(self) -> dict[str, Any]:
        """What the page fetches from /api/scene: robot, calibrated volume, Eq. 17 thresholds, alpha,
        provenance and error map.

        Returns
        -------
        dict
        """
        corners, edges = volume_edges(self.twin.volume) if self.twin.volume is not None else ([], [])
        prov = provenance(self.twin_dir)
        return {"robot": None if self.chain is None else {"name": self.chain.name, "dof": self.chain.dof,
                                                           "reach_m": self.chain.reach_m},
                "volume": {"corners": corners, "edges": edges,
                           "margin_m": self.twin.volume.margin_m if self.twin.volume is not None else None},
                "t_crit": self.t_crit.tolist(), "alpha": self.alpha,
                "provenance": prov, "error_map": error_map(self.twin, self.twin_dir, prov)}


def provenance(twin_dir: Path) -> dict[str, Any]:
    """What the page's provenance panel shows, from twin.json (and the validity line of the
    summary.json that ``dt demo`` / ``dt calibrate`` wrote beside the twin, when there is one).

    Parameters
    ----------
    twin_dir : Path

    Returns
    -------
    dict

    Raises
    ------
    OSError, ValueError
        When twin.json cannot be read or parsed.
    """
    meta = json.loads((twin_dir / "twin.json").read_text())
    p = meta.get("provenance") or {}
    out: dict[str, Any] = {
        "twin": str(twin_dir), "format_version": meta.get("format_version"),
        "software": p.get("software"), "created": p.get("created"),
        "robot": (p.get("robot") or {}).get("name"),
        "campaign": next((i["path"] for i in p.get("inputs", []) if str(i.get("path", "")).endswith("campaign.yaml")),
                         None),
        "instruments": [{k: i.get(k) for k in ("role", "kind", "model", "serial", "certificate", "calibration_date",
                                               "valid_until")} for i in p.get("instruments", [])],
        "environment": p.get("environment"), "validity": None}
    for summary in (twin_dir / "summary.json", twin_dir.parent / "summary.json"):
        if summary.is_file():
            try:
                v = json.loads(summary.read_text()).get("validity") or {}
            except (OSError, ValueError):
                continue
            out["validity"] = {"status": v.get("status"), "line": restated(v), "file": str(summary)}
            break
    return out
