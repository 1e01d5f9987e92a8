"""`dt compare`: error models against measurements, side by side (docs/cli.md, "dt compare").

    result, arrays = compare(["models/v1", "models/v2"], read_table("held_out.csv"))
    compare_report.write_compare_report(result.to_dict(), arrays, "out/")

`result` is a `CompareResult` (dt_runtime.analysis.results) whose `to_dict()` is the JSON object
(mm); `arrays` holds the SI arrays the report plots.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError, ModelError, TwinError
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis import deployment, reregister, validity
from dt_runtime.analysis.crossval import cross_validate, folds_of, groups_of
from dt_runtime.analysis.data import noise_floor
from dt_runtime.analysis.results import CompareResult, ModelScore
from dt_runtime.analysis.training import data_provenance
from dt_runtime.analysis.validity import configuration
from dt_runtime.common.progress import Progress
from dt_runtime.common.provenance import FileRecord
from dt_runtime.measurements.checks import check_dataset
from dt_runtime.measurements.dataset import Dataset, read_table
from dt_runtime.metrology import conformal as cp
from dt_runtime.metrology.stats import rms3, rms_with_U
from dt_runtime.metrology.uncertainty import INF, t_test
from dt_runtime.models import effects as fx
from dt_runtime.models.effects import Catalogue
from dt_runtime.models.hybrid import HybridModel, load_map

log = logging.getLogger("dt.compare")
AS_IS = "as is"
P95 = 0.95
MAX_ROWS = 50  # failing row indices listed in the JSON
MIN_CELL = 5  # a breakdown cell needs this many rows to be named among the worst
N_WORST = 5
# With three independent per-axis tests at 95 %, a consistent model still fails "any axis" on
# 1 - 0.95^3 = 14.3 % of the rows: the number to read the any-axis fraction against.
EXPECTED_ANY_AXIS = 1 - P95 ** 3
SIGN = ("-", "0", "+")


# --------------------------------------------------------------------------- inputs

def trained_on(fitted: Sequence[tuple[str, HybridModel]], ds: Dataset | str | Path) -> list[str]:
    """The models whose training data was this dataset's file, or this file (same SHA-256 in their
    provenance).

    Parameters
    ----------
    fitted : sequence of (str, HybridModel)
        The models by name.
    ds : Dataset, str or Path
        The data or its file.

    Returns
    -------
    list of str
        The models' names.
    """
    src = Path(ds.source if isinstance(ds, Dataset) else ds)
    if not src.is_file():
        return []
    digest = FileRecord.of(src).sha256
    out = []
    for name, m in fitted:
        try:
            prov = m.provenance()  # a loaded model's record, or a fitted one's training file
        except (TwinError, OSError):
            continue
        if any(f.sha256 == digest for f in prov.inputs):
            out.append(name)
    return out


def load_models(models: Sequence, names: Sequence[str] | None = None,
                catalogue: Catalogue | None = None) -> list[tuple[str, HybridModel]]:
    """(name, model) per entry; entries are HybridModel instances or model directories, loaded
    with `catalogue` (the call's effects, `HybridModel.load`) beside their own declared ones.

    Parameters
    ----------
    models : sequence
        HybridModel instances or model directories.
    names : sequence of str, optional
        Their names (default: each directory's).
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    list of (str, HybridModel)
    """
    if names is not None and len(names) != len(models):
        raise DataError(f"compare: {len(names)} names for {len(models)} models")
    out: list[tuple[str, HybridModel]] = []
    for i, m in enumerate(models):
        if isinstance(m, HybridModel):
            if not hasattr(m, "theta_"):
                raise ModelError(f"compare: model {i + 1} ({describe(m)}) is not fitted: call its fit() first "
                                 "(with cv_folds, compare refits its configuration without each held-out point)")
            name = f"model {i + 1}"
        else:
            p = Path(m)
            if not p.is_dir():
                raise ModelError(f"{p}: no such model directory (expected the output of `dt fit`, or a twin)")
            try:
                m = load_map(p, catalogue)
            except ModelError:
                raise
            except (OSError, KeyError, ValueError, DataError) as exc:  # a damaged save: name it, not numpy
                raise ModelError(f"{p}: cannot load the model ({type(exc).__name__}: {exc})") from exc
            name = p.name or str(p)
        out.append((names[i] if names is not None else name, m))
    seen: dict[str, int] = {AS_IS: 1}
    for i, (name, m) in enumerate(out):  # unique column names: the report keys on them
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:
            out[i] = (f"{name} ({seen[name]})", m)
    return out


def describe(model: HybridModel) -> str:
    """A model's configuration in words, e.g. "geometric+thermal, GP on tcp_speed".

    Parameters
    ----------
    model : HybridModel
        The model.

    Returns
    -------
    str
    """
    fx = "+".join(model.effects) or "no effects"
    return f"{fx}, GP on {model.gp_inputs}" if model.gp_inputs != "none" else f"{fx}, no GP"


def _noise_of(model: HybridModel) -> tuple[np.ndarray, np.ndarray]:
    """The model's estimate of the scatter of one measurement about the error map (m) per axis,
    and its dof: the GP's fitted white noise, else the effect fit's residual RMS."""
    if model.gp_ is not None:
        return np.sqrt([g.noise_var_ for g in model.gp_.models_]), _model_dof(model)
    return np.full(3, float(model.residual_rms_)), np.full(3, INF)


def _model_dof(model: HybridModel) -> np.ndarray:
    """dof of the GP's estimates (latent std, noise): from its training rows (type A)."""
    if model.gp_ is None:
        return np.full(3, INF)
    return np.array([max(g.n_train_ - 1, 1) for g in model.gp_.models_], dtype=float)


# --------------------------------------------------------------------------- figures of merit

def metrics(r: np.ndarray) -> dict:
    """3D and per-axis figures of residuals r (n,3) m, in mm.

    Parameters
    ----------
    r : ndarray
        (n, 3), m.

    Returns
    -------
    dict
    """
    norm = np.linalg.norm(r, axis=1)
    _, U, _ = rms_with_U(r)  # only its 95 % uncertainty; the RMS itself is rms3
    return {"rmse_mm": rms3(r) * MM_PER_M, "rmse_U95_mm": U * MM_PER_M if math.isfinite(U) else None,
            "mae_mm": float(norm.mean()) * MM_PER_M, "max_mm": float(norm.max()) * MM_PER_M,
            "max_row": int(np.argmax(norm)),
            "per_axis": {ax: {"rmse_mm": float(np.sqrt(np.mean(r[:, k] ** 2))) * MM_PER_M,
                              "mae_mm": float(np.mean(np.abs(r[:, k]))) * MM_PER_M,
                              "max_mm": float(np.max(np.abs(r[:, k]))) * MM_PER_M,
                              "mean_mm": float(np.mean(r[:, k])) * MM_PER_M} for k, ax in enumerate(AXES)}}


def _u_meas(ds: Dataset, fitted: list[tuple[str, HybridModel]]):
    """Standard uncertainty (n,3) m and dof (n,3) of each measured error, and where it came from.

    The dataset's ux..uz when stated (type B, dof inf). Otherwise the smallest fitted noise of
    the models, per axis: a model that misses an effect absorbs it into its noise, so the
    smallest estimate is the closest to the measurement's own scatter; one value for every
    column keeps the columns comparable. None when neither exists (only "as is")."""
    n = ds.n
    est = None
    if fitted:
        cands = [(_noise_of(m), name) for name, m in fitted]
        s = np.array([c[0][0] for c in cands])
        d = np.array([c[0][1] for c in cands])
        j = np.argmin(s, axis=0)
        est = (s[j, range(3)], d[j, range(3)], [cands[k][1] for k in j])
    if ds.u is not None and np.all(np.isfinite(ds.u)):
        return ds.u, np.full((n, 3), INF), "dataset columns ux, uy, uz (type B, dof = inf)"
    if est is None:
        return None, None, "not available: the dataset has no ux, uy, uz and there is no model"
    u, dof, who = est
    txt = ("not in the dataset: the smallest fitted measurement noise of the models, "
           + ", ".join(f"{ax} {u[k] * MM_PER_M:.4g} mm ({who[k]})" for k, ax in enumerate(AXES)))
    if ds.u is not None:  # partly stated: stated where given, estimated elsewhere
        ok = np.isfinite(ds.u)
        return (np.where(ok, ds.u, u), np.where(ok, INF, np.broadcast_to(dof, (n, 3))),
                f"dataset ux, uy, uz where stated ({int(ok.all(1).sum())} rows); elsewhere {txt}")
    return np.broadcast_to(u, (n, 3)), np.broadcast_to(dof, (n, 3)), txt


def failures(e, pred, std, dof_model, u_meas, dof_meas, lines=None):
    """Eq. 17 per row and axis: t = (e - e_hat) / sqrt(u_meas^2 + u_model^2), two-sided 95 %,
    dof by Welch-Satterthwaite (dt_runtime.metrology.uncertainty.t_test).

    Parameters
    ----------
    e : ndarray
        (n, 3) measured error, m.
    pred : ndarray
        (n, 3) the model's prediction, m.
    std : ndarray
        (n, 3) its standard uncertainty, m.
    dof_model : ndarray
        Its degrees of freedom per axis.
    u_meas : ndarray
        The measurement's standard uncertainty, m.
    dof_meas : float
        Its degrees of freedom.
    lines : sequence of int, optional
        The rows' file lines, for the worst rows named.

    Returns
    -------
    summary : dict
        Fraction and count of failing rows, per axis, and what a consistent model would give.
    test : TTest
    fail : ndarray
        (n, 3) bool: the row fails on that axis (a NaN t passes).
    """
    n = len(e)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = t_test(e, pred, u_meas, std, np.broadcast_to(dof_meas, (n, 3)),
                    np.broadcast_to(dof_model, (n, 3)), alpha=1 - P95)
    fail = ~tt.passed  # NaN t (zero uncertainty and zero residual) passes below
    fail &= ~(np.isnan(tt.t))
    rows = np.flatnonzero(fail.any(axis=1))
    out = {"fraction": float(len(rows) / n), "count": int(len(rows)),
           "per_axis": {ax: float(fail[:, k].mean()) for k, ax in enumerate(AXES)},
           "expected_fraction_if_consistent": EXPECTED_ANY_AXIS,
           "expected_per_axis_if_consistent": 1 - P95,
           "t_crit_median": [float(np.median(tt.t_crit[:, k])) for k in range(3)],
           "rows": rows[:MAX_ROWS].tolist()}
    if lines is not None:
        out["lines"] = np.asarray(lines)[rows[:MAX_ROWS]].tolist()
    return out, tt, fail


# --------------------------------------------------------------------------- breakdown

def _bins(v: np.ndarray, unit: str, max_levels: int = 6, n_bins: int = 4, fmt: str = ".4g"):
    """Cell label per row ('' where v is NaN): the distinct values if few, else quantile bins.
    None if v is constant (a factor that does not vary explains nothing)."""
    ok = np.isfinite(v)
    if ok.sum() == 0:
        return None
    uniq = np.unique(np.round(v[ok], 9))
    if len(uniq) < 2:
        return None
    lab = np.full(len(v), "", dtype=object)
    if len(uniq) <= max_levels:
        names = [f"{u:{fmt}} {unit}" for u in uniq]
        lab[ok] = [names[i] for i in np.searchsorted(uniq, np.round(v[ok], 9))]
        return lab, names
    edges = np.unique(np.quantile(v[ok], np.linspace(0, 1, n_bins + 1)))
    idx = np.clip(np.searchsorted(edges, v[ok], side="right") - 1, 0, len(edges) - 2)
    names = [f"{edges[i]:{fmt}}–{edges[i + 1]:{fmt}} {unit}" for i in range(len(edges) - 1)]
    lab[ok] = [names[i] for i in idx]
    return lab, names


def _region(P: np.ndarray):
    """3 x 3 x 3 grid over the commanded TCP bounding box: 'x-,y0,z+' (low, middle, high third)."""
    lo, span = P.min(0), np.ptp(P, axis=0)
    idx = np.where(span > 1e-9, np.floor((P - lo) / np.where(span > 0, span, 1) * 3), 1)
    idx = np.clip(idx, 0, 2).astype(int)
    lab = np.array([f"x{SIGN[i]},y{SIGN[j]},z{SIGN[k]}" for i, j, k in idx], dtype=object)
    order = sorted(set(lab), key=lambda s: [SIGN.index(s[p]) for p in (1, 4, 7)])
    return lab, order


def _configuration(q: np.ndarray):
    """The configuration factor's cells, None when the rows are all in one."""
    lab = configuration(q)
    names = sorted(set(lab))
    return (lab, names) if len(names) > 1 else None


def factor_cells(ds: Dataset) -> dict[str, tuple[np.ndarray, list[str]]]:
    """Factor name -> (cell label per row, cells in order); missing or constant factors skipped.

    Parameters
    ----------
    ds : Dataset
        The data.

    Returns
    -------
    dict
    """
    out = {"region": _region(ds.commanded)}
    for name, v, unit, fmt in (("speed", ds.speed, "mm/s", ".4g"), ("payload", ds.payload, "kg", ".3g"),
                               ("temperature", ds.temperature, "°C", ".3g"),
                               # relative time: epoch seconds would print as equal bins
                               ("time", None if ds.t is None else ds.t - np.nanmin(ds.t), "s from start", ".4g")):
        if v is not None:
            b = _bins(v * (MM_PER_M if name == "speed" else 1.0), unit, fmt=fmt)
            if b is not None:
                out[name] = b
    if ds.joints is not None:
        c = _configuration(ds.joints)
        if c is not None:
            out["configuration"] = c
    if len(out["region"][1]) < 2:
        del out["region"]
    return out


def breakdown(r: np.ndarray, cells: dict) -> dict:
    """3D RMS (mm), n and mean residual vector (mm) of r (n,3) m per cell of each factor.

    Parameters
    ----------
    r : ndarray
        (n, 3), m.
    cells : dict
        From `factor_cells`.

    Returns
    -------
    dict
    """
    out = {}
    for factor, (lab, names) in cells.items():
        rows = []
        for c in names:
            m = lab == c
            if m.any():
                rows.append({"cell": c, "n": int(m.sum()), "rmse_mm": rms3(r[m]) * MM_PER_M,
                             "mean_mm": (r[m].mean(0) * MM_PER_M).tolist()})
        out[factor] = rows
    return out


def worst_cells(bd: dict, overall_mm: float, k: int = N_WORST, min_n: int = MIN_CELL) -> list[dict]:
    """The factor cells with the largest residual RMS.

    Parameters
    ----------
    bd : dict
        The breakdown: factor -> its cells ({cell, n, rmse_mm, mean_mm}).
    overall_mm : float
        The overall RMS, mm (for each cell's ratio).
    k : int, optional
        How many cells.
    min_n : int, optional
        Cells with fewer rows are not named.

    Returns
    -------
    list of dict
        {factor, cell, n, rmse_mm, ratio, mean_mm}, worst first.
    """
    cand = [{"factor": f, "cell": c["cell"], "n": c["n"], "rmse_mm": c["rmse_mm"],
             "ratio": c["rmse_mm"] / overall_mm if overall_mm > 0 else None, "mean_mm": c["mean_mm"]}
            for f, cells in bd.items() for c in cells if c["n"] >= min_n]
    return sorted(cand, key=lambda c: -c["rmse_mm"])[:k]


# --------------------------------------------------------------------------- the comparison

def _score(name, kind, description, pred, std, ds, cells, um, dm, dof_model, model=None, split=None):
    """One column: its ModelScore and the SI arrays the report plots (`split`: the sessions, `_split`)."""
    r = ds.error - pred
    m = metrics(r)
    arr = {"name": name, "predicted": pred, "std": std, "residual": r, "t": None, "fail": None, "t_crit": None}
    fails = None
    if um is not None:
        fails, tt, fail = failures(ds.error, pred, std, dof_model, um, dm, ds.lines)
        arr.update(t=tt.t, fail=fail, t_crit=tt.t_crit)
    bd = breakdown(r, cells)
    per_session = None if split is None else _by_session(ds, pred, std, dof_model, um, dm, *split,
                                                         column=name if kind == "model" else None)
    return ModelScore(name, kind, ds.n, m, fails, bd, worst_cells(bd, m["rmse_mm"]), description, model,
                      per_session), arr


def _split(ds: Dataset, sessions: Sequence[dict] | None, refit_sessions: np.ndarray | None,
           fitted: Sequence[tuple[str, HybridModel]]):
    """(session label per row, {session: its file and name}, sessions to re-register, {session:
    the models trained on its file}) for data of two or more sessions, else None."""
    if "session" not in ds.extra:
        return None
    label = ds.extra["session"].astype(int)
    ids = [int(i) for i in np.unique(label)]
    if len(ids) < 2:
        return None
    about = {i: {k: f[k] for k in ("name", "file") if f.get(k) is not None}
             for i, f in enumerate(sessions or []) if i in ids}
    refit = set() if refit_sessions is None else {int(v) for v in np.unique(refit_sessions) if v >= 0}
    trained = {i: trained_on(fitted, a["file"]) for i, a in about.items() if "file" in a}
    for i, names_ in trained.items():
        if names_:
            log.warning("session %d (%s) was used to train %s: its figures are in-sample, not a test", i,
                        about[i].get("name", about[i]["file"]), ", ".join(names_))
    return label, about, refit, trained


def _session_figures(e, pred, std, dof_model, um, dm, lines, index) -> dict:
    """n, the figures of merit and the Eq. 17 failures of the rows `index` (failing rows named by
    their index in the whole data, as the top-level figures do, and their file lines)."""
    out = {"n": int(len(index)), **metrics(e - pred)}
    out["max_row"] = int(index[out["max_row"]])
    out["failures"] = None
    if um is not None:
        f, _, _ = failures(e, pred, std, dof_model, um, dm, lines)
        f["rows"] = index[f["rows"]].tolist()
        out["failures"] = f
    return out


def _rows(a, rows: np.ndarray):
    return None if a is None else np.asarray(a)[rows]


def _by_session(ds, pred, std, dof_model, um, dm, label, about, refit, trained, column=None) -> list[dict]:
    """Each session's figures, and after re-registration for the sessions in `refit` (their
    registration fitted on their own points: 6 dof absorbed again, as `after_reregistration`);
    for a model's `column`, whether the model was trained on the session's file (`in_sample`)."""
    out = []
    for s in np.unique(label):
        rows = np.flatnonzero(label == s)
        args = (std[rows], dof_model, _rows(um, rows), _rows(dm, rows), _rows(ds.lines, rows), rows)
        row = {"session": int(s), **about.get(int(s), {}),
               **_session_figures(ds.error[rows], pred[rows], *args), "reregistered": int(s) in refit}
        if column is not None:
            row["in_sample"] = column in trained.get(int(s), [])
        if int(s) in refit:
            rr, _ = reregister.reregistered(ds.actual[rows], ds.error[rows] - pred[rows])
            # the re-registered residual as the error a prediction left: e' - e_hat = rr
            row["after_reregistration"] = {**_session_figures(pred[rows] + rr, pred[rows], *args),
                                           "dof_absorbed": reregister.DOF}
        out.append(row)
    return out


def _after_reregistration(ds: Dataset, pred: np.ndarray, session: np.ndarray) -> dict | None:
    """The model's 3D RMS after each fitted session is registered again against the corrected
    commanded points (the rigid part the session's own registration absorbed is not the model's
    error; 6 dof per session absorbed). None when no row's registration was fitted."""
    refit = {int(s) for s in np.unique(session) if s >= 0}
    if not refit:
        return None
    rr = reregister.by_session(ds.actual, ds.error - pred, np.asarray(session), refit)
    return {"rmse_mm": rms3(rr) * MM_PER_M, "sessions": len(refit), "dof_absorbed": reregister.DOF * len(refit),
            "method": "per session, the rigid registration refitted: measured points -> commanded - predicted error"}


def _coverage(r: np.ndarray, U: np.ndarray) -> dict:
    """Per axis, the fraction of rows whose residual lies within their U95."""
    inside = np.abs(r) <= U
    return {ax: float(inside[:, k].mean()) for k, ax in enumerate(AXES)}


def _u95(um: np.ndarray, std: np.ndarray, tt) -> np.ndarray:
    """The stated U95 of each row's prediction of e: Eq. 17's t_crit times its combined u."""
    return tt.t_crit * np.sqrt(um ** 2 + std ** 2)


def _session_labels(ds: Dataset) -> np.ndarray:
    """Each row's session index (0 for data of one session)."""
    return ds.extra["session"].astype(int) if "session" in ds.extra else np.zeros(ds.n, dtype=int)


def _to_register(ds: Dataset, reference: int | None, refit_sessions: np.ndarray | None, sessions, trained):
    """(session label per row, {session: its name}, the sessions to register on reference poses, K),
    or None: by default (reference None) the sessions whose registration the data fitted on their own
    points, with K = DEFAULT_REFERENCE; with K > 0 every session; sessions a model was trained on are
    left out (their registration is the training's)."""
    if reference == 0 or (reference is None and refit_sessions is None):
        return None
    label = _session_labels(ds)
    if reference is None:
        assert refit_sessions is not None
        chosen = {int(v) for v in np.unique(label[np.asarray(refit_sessions) >= 0])}
    else:
        chosen = {int(v) for v in np.unique(label)}
    chosen -= set(trained)
    names = {i: f.get("name") or f.get("file") for i, f in enumerate(sessions or [])}
    k = deployment.DEFAULT_REFERENCE if reference is None else int(reference)
    return (label, names, sorted(chosen), k) if chosen else None


def _trained_sessions(name: str, m: HybridModel, ds: Dataset, split) -> set[int]:
    """The sessions of these data model `name` was trained on (their files in its provenance)."""
    if split is not None:
        return {s for s, names_ in split[3].items() if name in names_}
    return {0} if trained_on([(name, m)], ds) else set()


def _after_registration(ds: Dataset, pred, std, dof_model, um, dm, plan) -> tuple[dict, dict] | None:
    """Each session of `plan` (`_to_register`) registered on its reference poses with the model's
    correction applied and scored on its other rows, the registration's uncertainty in Eq. 17 (and
    the same rows under the data's own registration: `before`); the block and the arrays of the
    rows scored. None without a measurement uncertainty (no Eq. 17, no coverage)."""
    if um is None or plan is None:
        return None
    label, names, chosen, k = plan
    per, skipped = [], []
    r_all, U_all, r0_all, U0_all, rows_all, fail_all, fail0_all = [], [], [], [], [], [], []
    for s in chosen:
        rows = np.flatnonzero(label == s)
        try:
            ref = deployment.reference_rows(ds.commanded[rows], k)
            reg = deployment.register(ds.actual[rows], ds.error[rows] - pred[rows], ref)
        except DataError as exc:
            skipped.append({"session": s, "name": names.get(s), "why": str(exc)})
            continue
        t = reg.test
        idx = rows[t]
        u_reg = reg.u[t]
        std_t = np.sqrt(std[idx] ** 2 + u_reg ** 2)
        dof_t = deployment.combined_dof(std[idx], np.broadcast_to(dof_model, (len(idx), 3)), u_reg, reg.fit.dof)
        r, r0 = reg.residual[t], ds.error[idx] - pred[idx]  # after / under the data's own registration
        f, tt, fail = failures(pred[idx] + r, pred[idx], std_t, dof_t, um[idx], dm[idx], _rows(ds.lines, idx))
        f["rows"] = idx[f["rows"]].tolist()
        f0, tt0, fail0 = failures(ds.error[idx], pred[idx], std[idx], dof_model, um[idx], dm[idx])
        U, U0 = _u95(um[idx], std_t, tt), _u95(um[idx], std[idx], tt0)
        per.append({"session": s, "name": names.get(s), "reference_rows": int(ref.sum()), "n": int(len(idx)),
                    **{k_: v for k_, v in metrics(r).items() if k_ in ("rmse_mm", "per_axis")},
                    "failures": f, "coverage_95": _coverage(r, U),
                    "u_registration_mm": {ax: float(np.sqrt(np.mean(u_reg[:, i] ** 2))) * MM_PER_M
                                          for i, ax in enumerate(AXES)},
                    "registration_residual_mm": reg.fit.residual_rms_m * MM_PER_M, "registration_dof": reg.fit.dof,
                    "before": {"rmse_mm": metrics(r0)["rmse_mm"], "failures_per_axis": f0["per_axis"],
                               "coverage_95": _coverage(r0, U0)}})
        r_all.append(r)
        U_all.append(U)
        r0_all.append(r0)
        U0_all.append(U0)
        rows_all.append(idx)
        fail_all.append(fail)
        fail0_all.append(fail0)
    if not per:
        return {"reference_poses": k, "sessions": [], "skipped": skipped, "n": 0}, {}
    r, U, r0, U0 = (np.concatenate(a) for a in (r_all, U_all, r0_all, U0_all))
    fail, fail0, idx = np.concatenate(fail_all), np.concatenate(fail0_all), np.concatenate(rows_all)
    block = {"method": (f"each session's registration refitted on {k} reference poses (spread over its points) "
                        "against the commanded points minus the model's prediction; the other rows scored, the "
                        "registration's uncertainty added to Eq. 17's"),
             "reference_poses": k, "n": int(len(idx)), **{k_: v for k_, v in metrics(r).items()
                                                          if k_ in ("rmse_mm", "per_axis")},
             "failures_per_axis": {ax: float(fail[:, i].mean()) for i, ax in enumerate(AXES)},
             "coverage_95": _coverage(r, U),
             "before": {"rmse_mm": metrics(r0)["rmse_mm"],
                        "failures_per_axis": {ax: float(fail0[:, i].mean()) for i, ax in enumerate(AXES)},
                        "coverage_95": _coverage(r0, U0)},
             "sessions": per, "skipped": skipped}
    return block, {"rows": idx, "residual": r, "U": U}


def _validity(name: str, in_sample: bool, um, scored: dict | None, ds: Dataset, pred, std,
              tt, domain: dict | None = None) -> tuple[dict, dict | None]:
    """The `validity` block of the primary model on these data: the coverage of its stated U95 (model,
    measurement and, after a registration on reference poses, registration) over the rows it did not
    see, with the band and what to do (analysis.validity); and the rows it checked ({rows, residual,
    U} m), None when it checked none."""
    if in_sample:
        return validity.assess([], unchecked=f"{ds.source} was used to train '{name}': its figures are in-sample, "
                                             "not a test; compare on another session's file, or use --cv K"), None
    if um is None or tt is None:
        return validity.assess([], unchecked="no measurement uncertainty (ux, uy, uz, --mpe-mm or a model's "
                                             "fitted noise): no stated U to check"), None
    if scored:
        rows, r, U = scored["rows"], scored["residual"], scored["U"]
        what = (f"the {len(rows)} rows of the new session(s) not used by the registration on reference poses")
    else:
        rows, r = np.arange(ds.n), ds.error - pred
        U = _u95(um, std, tt)
        what = f"the {ds.n} rows under the data's own registration"
    outside = None
    if domain and domain.get("fraction", 0.0) >= OUTSIDE_SHARE:
        outside = (f"{domain['rows']} of {ds.n} rows lie outside the model's training domain ("
                   + ", ".join(f"{c} {n}" for c, n in domain["columns"].items()) + ")")
    sample = validity.Sample("new_data", what, "errors the instrument measured", r, U,
                             fx.Inputs(commanded=ds.commanded[rows]),
                             stated="U95 of the prediction", outside_domain=outside)
    return validity.assess([sample]), {"rows": rows, "residual": r, "U": U}


OUTSIDE_SHARE = 0.5  # rows outside the training domain from which a low coverage is put down to extrapolation
STATED_U95 = "U95 = t_crit sqrt(u_meas^2 + u_model^2 [+ u_reg^2]) (GUM, Eq. 17's)"


def _conformal(r: np.ndarray, U: np.ndarray, groups: np.ndarray, folds: list[np.ndarray]) -> dict:
    """The split conformal factor of the stated U95 on the held-out rows (`metrology.conformal`), and the
    coverage it gives on rows it was not calibrated on: each fold's rows covered by max(1, c) U95
    with c from the other folds (cross-fitted), beside the coverage of U95 itself."""
    scale = cp.calibrate(r, U, groups)
    inside = np.zeros(r.shape, dtype=bool)
    for test in folds:
        f = cp.calibrate(r[~test], U[~test], groups[~test]).factor
        inside[test] = np.abs(r[test]) <= f * U[test]
    return {**scale.to_dict(),
            "note": "from the held-out rows of the grouped cross-validation; apply max(1, c) x U95 to new data of "
                    "the same kind (dt calibrate stores it in the twin)",
            "coverage_95_gum": _coverage(r, U),
            "coverage_95_conformal_cross_fitted": {ax: float(inside[:, k].mean()) for k, ax in enumerate(AXES)}}


def _predict_cv(m: HybridModel, ds: Dataset, folds: list[np.ndarray], groups: np.ndarray):
    """Held-out prediction and std of every row by the model's configuration (effects, GP inputs,
    robot, GP options) refitted on the other folds, with the saved model's GP hyperparameters."""
    thetas = m.gp_.thetas_ if m.gp_ is not None else None
    cv = cross_validate(m, ds, ds.error, groups, folds, thetas=thetas, return_std=True)
    return ds.error - cv.residual, cv.std


def compare(models: Sequence, dataset: Dataset | str | Path, names: Sequence[str] | None = None,
            noise_floor_m: float | None = None, cv_folds: int = 0, seed: int = 0,
            progress: Progress | None = None, instruments: str | Path | None = None,
            inputs: Sequence[str | Path] = (), refit_sessions: np.ndarray | None = None,
            sessions: Sequence[dict] | None = None,
            catalogue: Catalogue | None = None, reference: int | None = None) -> tuple[CompareResult, dict]:
    """Compare models with the measured errors of `dataset`; "as is" is added first.

    For every model (and "as is", no model: e_hat = 0) the residual r = e - e_hat of each
    measured row (e = commanded - measured, paper Eq. 8) gives the 3D and per-axis figures, the
    Eq. 17 t-test of every row against the model's stated uncertainty, and the residual broken
    down by factor (workspace region, speed, payload, temperature, time, joint configuration), so
    a user sees where a model fails and which factor the failure follows. The primary model (the
    last one given) is also at the top level of the JSON (`n`, `rmse_mm`, `mae_mm`, `max_mm`,
    `per_axis`, `failures`: the contract of docs/cli.md). Data of several sessions are also
    scored session by session.

    Parameters
    ----------
    models : sequence
        HybridModel instances or model directories, oldest first.
    dataset : Dataset, str or Path
        The measurements, or a contract CSV.
    names : sequence of str, optional
        The models' names.
    noise_floor_m : float, optional
        The measurement noise floor (m) if known from elsewhere (e.g. a simulation sidecar);
        default: 3D RMS of the dataset's ux..uz, if stated.
    cv_folds : int, optional
        0 compares the models as saved (use data they were not trained on); K > 1 predicts every
        row by each model's configuration refitted on the other K-1 folds, grouped by target
        point (`dt_runtime.analysis.crossval.cross_validate`): held-out figures from the training
        file.
    seed : int, optional
        Seed of the folds.
    progress : Progress, optional
        Where progress is reported.
    instruments : str or Path, optional
        The campaign's instruments YAML, for the traceability record (`provenance`).
    inputs : sequence of str or Path, optional
        Other input files (e.g. an import mapping) for the record, beside the data file and the
        model directories' files.
    refit_sessions : ndarray, optional
        Per row, the session whose registration was fitted on its own points (-1: given or
        none); each model then also gets its figure after re-registration
        (`after_reregistration`, dt_runtime.analysis.reregister).
    sessions : sequence of dict, optional
        For data of several sessions (`dataset.extra['session']`), what each one is ({'file',
        'name'} by session index: `Data.info['session_files']`); every column then has its
        figures per session (`ModelScore.sessions`).
    catalogue : Catalogue, optional
        The effects a saved model's names may refer to beyond its own declared ones (e.g.
        --effects-file's); default `effects.default()`.
    reference : int, optional
        Reference poses per new session: its registration refitted on that many poses with the
        model's correction applied, the other rows scored after it (`after_registration`,
        analysis.deployment). None: `deployment.DEFAULT_REFERENCE` for the sessions whose
        registration the data fitted on their own points (`refit_sessions`); K > 0: every session
        a model was not trained on; 0: none.

    Returns
    -------
    result : CompareResult
        `result.to_dict()` is the JSON (mm).
    arrays : dict
        SI arrays for the report.
    """
    ds = dataset if isinstance(dataset, Dataset) else read_table(dataset)
    if ds.n == 0:
        raise DataError(f"{ds.source}: no data rows to compare with")
    check_dataset(ds, None)  # units and ranges; the models' robots check their joints when they read them
    models = list(models)
    prov = data_provenance(ds, None, None, instruments, inputs, models)
    fitted = load_models(models, names, catalogue)
    um, dm, u_source = _u_meas(ds, fitted)
    cells = factor_cells(ds)
    zeros = np.zeros((ds.n, 3))
    scores, arrs = [], []
    split = _split(ds, sessions, refit_sessions, fitted)
    last = None
    b, a = _score(AS_IS, "as is", "no correction: e_hat = 0", zeros, zeros, ds, cells, um, dm, np.full(3, INF),
                  split=split)
    scores.append(b)
    arrs.append(a)
    if cv_folds > 1:
        groups = groups_of(ds)
        folds = folds_of(groups, cv_folds, seed)
    for i, (name, m) in enumerate(fitted):
        if progress is not None:
            progress.step("compare: models" + (f" ({cv_folds}-fold grouped CV)" if cv_folds > 1 else ""),
                          i, len(fitted))
        if m.gp_ is not None and m.gp_.n_features_in_ == 4 and ds.speed is None:  # GP on TCP + speed
            raise DataError(f"model '{name}' was trained on TCP and speed; {ds.source} has no speed column")
        trained_s = _trained_sessions(name, m, ds, split)
        time_note = None
        try:
            if cv_folds > 1:
                pred, std = _predict_cv(m, ds, folds, groups)
            else:
                label = _session_labels(ds)
                design, time_note = deployment.time_terms(m, ds, ~np.isin(label, sorted(trained_s)))
                pred, std = m.predict(ds, return_std=True, design=design)
        except (DataError, ModelError) as exc:
            raise type(exc)(f"model '{name}' cannot predict the rows of {ds.source}: {exc}") from exc
        dom = m.outside_domain(ds)
        if dom and dom["rows"]:
            log.warning("model '%s': %d of %d rows of %s lie outside its training domain (%s): it extrapolates there",
                        name, dom["rows"], ds.n, ds.source, ", ".join(f"{c} {n}" for c, n in dom["columns"].items()))
        about = {"outside_training": dom, "effects": list(m.effects), "gp_inputs": m.gp_inputs,
                 "effect_residual_rms_mm": float(m.residual_rms_) * MM_PER_M, "parameters": m.parameters(),
                 "base_parameters": m.base_parameters()}
        if refit_sessions is not None:
            about["after_reregistration"] = _after_reregistration(ds, pred, refit_sessions)
        if time_note is not None:
            about["time_terms"] = time_note
            log.warning("model '%s': %s", name, time_note["text"])
        plan = _to_register(ds, reference, refit_sessions, sessions, trained_s)
        reg = _after_registration(ds, pred, std, _model_dof(m), um, dm, plan)
        scored = None
        if reg is not None:
            about["after_registration"], scored = reg
        last = (name, m, pred, std, scored)
        b, a = _score(name, "model", describe(m), pred, std, ds, cells, um, dm, _model_dof(m), about, split)
        scores.append(b)
        arrs.append(a)
    floor = noise_floor_m if noise_floor_m is not None else noise_floor(ds.u)
    in_sample = [] if cv_folds > 1 else trained_on(fitted, ds)
    conf, checked = None, None
    if last is None:
        valid = validity.assess([], unchecked="no model to check")
    else:
        name, m, pred, std, scored = last
        tt = failures(ds.error, pred, std, _model_dof(m), um, dm)[1] if um is not None else None
        valid, checked = _validity(name, name in in_sample, um, scored, ds, pred, std, tt, m.outside_domain(ds))
        valid["stated_U"] = STATED_U95
        if cv_folds > 1 and tt is not None:
            conf = _conformal(ds.error - pred, _u95(um, std, tt), groups, folds)
    result = CompareResult(
        scores, ds.source, floor * MM_PER_M if floor is not None else None,
        heldout=({"method": f"{len(folds)}-fold cross-validation grouped by target point: each row "
                            "predicted by the model's configuration refitted without its point",
                  "folds": len(folds)} if cv_folds > 1 else None),
        t_test={"equation": "Eq. 17: t = (e - e_hat) / sqrt(u_meas^2 + u_model^2) per axis, "
                            "two-sided 95 %, dof by Welch-Satterthwaite",
                "u_model": "the prediction's standard uncertainty at the row: the GP's latent standard deviation "
                           "and the effect parameters' covariance propagated through the row's regressors "
                           "(u^2 = s_GP^2 + a Sigma_theta a^T; dof: the GP's training rows, else infinite)",
                "u_meas_source": u_source},
        factors={f: names_ for f, (_, names_) in cells.items()},
        provenance=prov, in_sample=in_sample, validity=valid, conformal=conf)
    if result.in_sample:
        log.warning("%s was used to train %s: these figures are in-sample, not a test (use --cv K or other data)",
                    ds.source, ", ".join(result.in_sample))
    arrays = {"commanded": ds.commanded, "error": ds.error, "u": ds.u, "u_meas": um,
              "speed": ds.speed, "payload": ds.payload, "temperature": ds.temperature, "t": ds.t,
              "joints": ds.joints, "cells": {f: lab for f, (lab, _) in cells.items()}, "models": arrs,
              "session": ds.extra.get("session"), "point_id": ds.point_id, "lines": ds.lines,
              "validity": checked}
    return result, arrays
