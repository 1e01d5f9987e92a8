"""The daily check: a deployed twin starts its day on N reference poses measured in the new session
(`dt calibrate --reference FILE --twin DIR`). The session's terms are fitted with the twin's
correction applied (the tracker's and, where the file has camera points, the camera's rigid
registration, with their covariance), tool and joint zeros are tested on the same poses, the
validity is checked pose by pose (leave one out) and twin.json is rewritten with the new frames and
their uncertainty; the error maps are kept as they are. docs/deployment.md.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from dt_kernel.errors import DataError
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis import validity
from dt_runtime.analysis.deployment import combined_dof
from dt_runtime.frames.registration import RigidTransform, RigidUncertainty, rigid_jacobian, rigid_uncertainty
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.models.effects import Inputs
from dt_runtime.models.effects import session as terms
from dt_runtime.twin import calibration as cal
from dt_runtime.twin.twin import Twin, TwinUncertainty

MIN_POSES = 4  # a rigid fit needs 3; one more leaves the leave-one-out check something to test
SESSION_LABEL = "u_session_reg"  # the Eq. 11 component the daily check adds (its registration)
P_TERM = 0.01  # a tool or joint change is reported as found below this p-value
SEPARABLE = 1e-5  # singular value (columns scaled to 1) below which the poses do not see a direction


@dataclass(frozen=True)
class Frame:
    """One instrument's frame refitted on the reference poses: the fit, and the change against the
    twin's frame (rotation in mrad about GL's axes, translation at GL's origin in mm) with its
    expanded uncertainty and the chi^2 p-value of 'no change'."""

    name: str
    fit: RigidUncertainty
    change: dict[str, Any]


def _target(twin: Twin, phase: PhaseData, rows: np.ndarray, instrument: str) -> np.ndarray:
    """Where each reference pose's point should map to in GL: the commanded TCP minus the twin's
    predicted error of that instrument (e_LT_hat; e_MVS_hat = e_LT_hat - e_MVS-LT_hat, Eq. 10)."""
    inp = cal.phase_inputs(phase, rows)
    target = twin.T_rdk.apply(phase.p_rdk[rows]) - twin.e_lt.predict(inp)
    if instrument == "mvs":
        target = target + twin.e_mvs_lt.predict(inp)
    return target


def _frame(name: str, old: RigidTransform, source: np.ndarray, target: np.ndarray) -> Frame:
    fit = rigid_uncertainty(source, target)
    # the change as a small motion of GL: omega x q + dt, omega from the relative rotation
    rel = fit.T.compose(old.inverse())
    theta = np.concatenate([Rotation.from_matrix(rel.R).as_rotvec(), rel.t])
    k = float(stats.t.ppf(0.975, max(fit.dof, 1)))
    U = k * np.sqrt(np.maximum(np.diag(fit.cov), 0.0))
    try:
        chi = float(theta @ np.linalg.solve(fit.cov, theta))
        p = float(stats.chi2.sf(chi, 6))
    except np.linalg.LinAlgError:
        p = float("nan")
    change = {"rotation_mrad": (theta[:3] * 1e3).tolist(), "rotation_U_mrad": (U[:3] * 1e3).tolist(),
              "translation_mm": (theta[3:] * MM_PER_M).tolist(), "translation_U_mm": (U[3:] * MM_PER_M).tolist(),
              "k": k, "dof": fit.dof, "p_value_no_change": p,
              "residual_rms_mm": fit.residual_rms_m * MM_PER_M}
    return Frame(name, fit, change)


def _term_check(twin: Twin, inp: Inputs, residual: np.ndarray, points: np.ndarray) -> list[dict]:
    """Tool offset and joint zeros tested on the reference poses beside the registration (fitted
    together with its 6 parameters): value, U (k from the residual's dof), p-value, and what these
    poses cannot separate from the set-up's rigid part. Neither is written into the twin: its maps
    were fitted with the calibration's tool and zeros."""
    chain = twin.e_lt.chain()
    if chain is None or inp.joints is None:
        return [{"term": t, "identified": False,
                 "text": f"session term '{t}' not tested: the file has no joint angles or the twin no robot model"}
                for t in ("tool", "joints")]
    rows: list[dict[str, Any]] = []
    R = rigid_jacobian(points).reshape(-1, 6)
    b = residual.reshape(-1)
    for t in ("tool", "joints"):
        A_t, names, units = terms.term_regressors(t, inp, chain)
        A_t = np.einsum("ab,nbp->nap", twin.T_rdk.R, A_t).reshape(-1, A_t.shape[2])
        # a parameter that moves no pose (a TCP on the last joint's axis) is not seen at all
        norm = np.linalg.norm(A_t, axis=0)
        blind = norm <= 1e-6 * max(float(norm.max()), 1e-12)
        M = np.hstack([R, A_t[:, ~blind]])
        Ms = M / np.linalg.norm(M, axis=0)
        _, sv, Vt = np.linalg.svd(Ms, full_matrices=False)
        null = Vt[sv <= SEPARABLE * sv[0]]
        seen = [j for j in range(len(names)) if not blind[j]]
        # a term parameter is unseparable when it takes part in a direction the poses do not see
        aliased = [names[j] for j in range(len(names)) if blind[j]] + [
            names[j] for i, j in enumerate(seen) if null.size and np.any(np.abs(null[:, 6 + i]) > 1e-3)]
        keep = [j for j in range(len(names)) if names[j] not in aliased]
        cols = list(range(6)) + [6 + j for j in keep]
        Mk = M[:, cols]
        dof = len(b) - len(cols)
        if dof < 1 or not keep:
            rows.append({"term": t, "identified": False, "unseparable": aliased,
                         "text": f"session term '{t}': these poses cannot separate it from the set-up's rigid part"})
            continue
        theta, *_ = np.linalg.lstsq(Mk, b, rcond=None)
        s2 = float(np.sum((b - Mk @ theta) ** 2)) / dof
        cov = s2 * np.linalg.pinv(Mk.T @ Mk)
        th, cv = theta[6:], cov[6:, 6:]
        k = float(stats.t.ppf(0.975, dof))
        try:
            p = float(stats.chi2.sf(float(th @ np.linalg.solve(cv, th)), len(th)))
        except np.linalg.LinAlgError:
            p = float("nan")
        shown = {"m": (MM_PER_M, "mm"), "rad": (1e3, "mrad")}
        params = [{"name": names[j], "value": float(th[i]) * shown[units[j]][0],
                   "U": k * float(np.sqrt(cv[i, i])) * shown[units[j]][0], "unit": shown[units[j]][1]}
                  for i, j in enumerate(keep)]
        found = bool(np.isfinite(p) and p < P_TERM)
        text = (f"session term '{t}': " + ", ".join(f"{q['name']} {q['value']:+.3f} ± {q['U']:.3f} {q['unit']}"
                                                    for q in params)
                + f" (p = {p:.2g}: " + ("changed: the twin's maps hold the calibration's; recalibrate or restore it"
                                        if found else "no change found") + ")"
                + (f"; not separable from the set-up here: {', '.join(aliased)}" if aliased else ""))
        rows.append({"term": t, "identified": True, "parameters": params, "p_value": p, "changed": found,
                     "unseparable": aliased, "text": text})
    return rows


def _with(s: dict, u_add: np.ndarray, dof_add: float) -> dict:
    """A stated uncertainty (twin.json's u entry) with a component added in quadrature (W-S dof)."""
    u0, d0 = np.asarray(s["u"], dtype=float), np.asarray(s["dof"], dtype=float)
    u = np.sqrt(u0 ** 2 + u_add ** 2)
    dof = combined_dof(u0, d0, u_add, dof_add)
    k = stats.t.ppf(0.975, np.minimum(dof, 1e12))
    return {"u": u.tolist(), "dof": [float(x) if np.isfinite(x) else float("inf") for x in dof], "k": k.tolist(),
            "U": (k * u).tolist()}


def _u_rms(fit: RigidUncertainty, points: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(fit.at(points) ** 2, axis=0))


def check(twin_dir: str | Path, phase: PhaseData, source: str | Path, alpha: float = 0.05) -> tuple[dict, dict]:
    """The daily check of the twin in `twin_dir` on the reference poses of `phase`.

    Parameters
    ----------
    twin_dir : str or Path
        The deployed twin.
    phase : PhaseData
        The reference poses (SI), as `measurements.campaign_files.read_phase` reads them.
    source : str or Path
        The reference file (hashed into the record).
    alpha : float
        Eq. 17's significance level.

    Returns
    -------
    summary : dict
        What the command prints (`--json`): frames refitted with their change and U, terms kept,
        the tool/joint check, the leave-one-out validity.
    meta : dict
        twin.json as it is to be written.

    Raises
    ------
    DataError
        Fewer than MIN_POSES poses the tracker measured, or the file lacks what the maps read.
    ModelError
        The twin cannot be read.
    """
    twin_dir = Path(twin_dir)
    twin = Twin.load(twin_dir)
    meta = json.loads((twin_dir / "twin.json").read_text())
    base = (meta.get("session") or {}).get("calibrated") or {
        "u": meta["u"], "position_rest": (meta.get("position_uncertainty") or {}).get("rest"),
        "T_lt": meta["T_lt"], "T_mvs": meta["T_mvs"]}
    ok = np.all(np.isfinite(phase.p_lt), axis=1) & np.all(np.isfinite(phase.p_rdk), axis=1)
    n = int(ok.sum())
    if n < MIN_POSES:
        raise DataError(f"{source}: {n} reference poses the tracker measured; the daily check needs at least "
                        f"{MIN_POSES} (10 spread over the working volume is the default)")
    rows = np.flatnonzero(ok)
    frames = {"lt": _frame("lt", twin.T_lt, phase.p_lt[rows], _target(twin, phase, rows, "lt"))}
    mvs_ok = ok & np.all(np.isfinite(phase.p_mvs), axis=1)
    if int(mvs_ok.sum()) >= MIN_POSES:
        m_rows = np.flatnonzero(mvs_ok)
        frames["mvs"] = _frame("mvs", twin.T_mvs, phase.p_mvs[m_rows], _target(twin, phase, m_rows, "mvs"))
    lt = frames["lt"]
    gl = lt.fit.T.apply(phase.p_lt[rows])
    residual = _target(twin, phase, rows, "lt") - gl
    # the rigid part's regressors at the commanded points, as the joints' (FK of the same angles)
    term_rows = _term_check(twin, cal.phase_inputs(phase, rows), residual, twin.T_rdk.apply(phase.p_rdk[rows]))
    kept = ["the error maps e_LT and e_MVS-LT (not refitted)", "the robot frame T_rdk (GL is defined on it)"]
    if "mvs" not in frames:
        kept.append("the camera frame T_mvs (the file has no camera points on enough poses)")
    kept += [r["text"] for r in term_rows if not r["identified"]]
    # the new frames' uncertainty, into the stated U: tracker registration -> Eq. 11 (and 13),
    # camera registration -> Eqs. 14, 15 (the t-test's denominator)
    u_lt = _u_rms(lt.fit, phase.p_lt[rows])
    u = {k: dict(v) for k, v in base["u"].items()}
    u["eq11_tcp_c"] = _with(u["eq11_tcp_c"], u_lt, lt.fit.dof)
    u["eq13_e_lt_hat"] = _with(u["eq13_e_lt_hat"], u_lt, lt.fit.dof)
    if "mvs" in frames:
        mv = frames["mvs"]
        u_mvs = _u_rms(mv.fit, phase.p_mvs[mvs_ok])
        u["eq14_e_lt_hat_minus_e_mvs"] = _with(u["eq14_e_lt_hat_minus_e_mvs"], u_mvs, mv.fit.dof)
        u["eq15_e_mvs"] = _with(u["eq15_e_mvs"], u_mvs, mv.fit.dof)
    new = dict(meta)
    new["T_lt"] = lt.fit.T.to_dict()
    if "mvs" in frames:
        new["T_mvs"] = frames["mvs"].fit.T.to_dict()
    new["u"] = u
    if base["position_rest"] is not None:
        comp = {"label": SESSION_LABEL, "u": u_lt.tolist(), "dof": float(lt.fit.dof), "kind": "A",
                "distribution": "normal", "note": f"daily check: registration on {n} reference poses"}
        new["position_uncertainty"] = dict(meta["position_uncertainty"], rest=[*base["position_rest"], comp])
    TwinUncertainty.from_mapping({k: {f: np.asarray(x, dtype=float) for f, x in v.items()} for k, v in u.items()})
    loo = _leave_one_out(twin, phase, rows, mvs_ok, u, alpha)
    digest = hashlib.sha256(Path(source).read_bytes()).hexdigest() if Path(source).is_file() else None
    record = {"t": time.time(), "reference": str(source), "sha256": digest, "poses": n,
              "frames": {k: f.change for k, f in frames.items()}, "terms": term_rows, "kept": kept}
    new["session"] = {"calibrated": base, "daily_check": record}
    summary = {"twin": str(twin_dir), "reference": str(source), "poses": n, "distinct_points": validity.distinct(
        phase.p_rdk[rows]), "frames": record["frames"], "terms": term_rows, "kept": kept, **loo}
    return summary, new


def _leave_one_out(twin: Twin, phase: PhaseData, rows: np.ndarray, mvs_ok: np.ndarray, u: dict,
                   alpha: float) -> dict:
    """Each reference pose scored by the frames fitted on the others: its residual against the
    stated U(TCP_c) with the registration's uncertainty added, and Eq. 17 on its camera point
    (the new Eqs. 14, 16); the validity block (`analysis.validity`) of that, naming the small sample."""
    r, U, passed = [], [], []
    inp = cal.phase_inputs(phase, rows)
    pred, sigma = twin.e_lt.predict(inp, return_std=True)
    pred_ml = twin.e_mvs_lt.predict(inp)
    tus = TwinUncertainty.from_mapping({k: {f: np.asarray(x, dtype=float) for f, x in v.items()} for k, v in u.items()})
    b14, b16 = tus.e_lt_hat_minus_e_mvs, tus.e_mvs_lt_hat
    cmd_gl = twin.T_rdk.apply(phase.p_rdk[rows])
    for i in range(len(rows)):
        others = np.arange(len(rows)) != i
        fit = rigid_uncertainty(phase.p_lt[rows][others], (cmd_gl - pred)[others])
        e_i = cmd_gl[i] - fit.T.apply(phase.p_lt[rows][i])
        u_reg = fit.at(phase.p_lt[rows][i:i + 1])[0]
        U_tw = twin.stated_U(twin.tcp_budget(phase.p_rdk[rows][i], float(phase.speed[rows][i]), sigma=sigma[i]))
        k_reg = float(stats.t.ppf(0.975, max(fit.dof, 1)))
        r.append(e_i - pred[i])
        U.append(np.sqrt(U_tw ** 2 + (k_reg * u_reg) ** 2))
        if mvs_ok[rows[i]]:
            m_others = others & mvs_ok[rows]
            if m_others.sum() >= 3:
                fm = rigid_uncertainty(phase.p_mvs[rows][m_others], (cmd_gl - pred + pred_ml)[m_others])
                e_mvs = cmd_gl[i] - fm.T.apply(phase.p_mvs[rows][i])
                tt = unc.t_test(pred[i] - e_mvs, pred_ml[i], b14.u, b16.u, b14.dof, b16.dof, alpha)
                passed.append(tt.passed[0])
    r_a, U_a = np.array(r), np.array(U)
    n = len(rows)
    what = (f"the {n} reference poses, each scored by the frames fitted on the others (leave one out; "
            f"a small sample: a coverage of {n - 1} in {n} is {100 * (n - 1) / n:.0f} %)")
    sample = validity.Sample("reference", what, "errors the laser tracker measured less the map's prediction", r_a, U_a,
                             Inputs(commanded=phase.p_rdk[rows]), stated="U(TCP_c) with the session's registration")
    rates = (("reference", validity.Eq17Rates(np.array(passed, dtype=bool).reshape(-1, 3), b14.U))
             if passed else None)
    block = validity.assess([sample], eq17=rates)
    inside = np.abs(r_a) <= U_a
    return {"leave_one_out": {
        "n": len(rows), "rms_mm": float(np.sqrt(np.mean(np.sum(r_a ** 2, axis=1)))) * MM_PER_M,
        "coverage_95": {ax: float(inside[:, k].mean()) for k, ax in enumerate(AXES)},
        "eq17_failures_per_axis": ({ax: float(1 - np.mean(np.array(passed)[:, k])) for k, ax in enumerate(AXES)}
                                   if passed else None),
        "eq17_n": len(passed)}, "validity": block}


def write(twin_dir: str | Path, out: Path, meta: dict) -> None:
    """Copy the twin's files into `out` (the staged directory) unchanged but twin.json, written from `meta`.

    Parameters
    ----------
    twin_dir : str or Path
        The twin read.
    out : Path
        Where the checked twin is assembled (`common.outputs.staged`).
    meta : dict
        twin.json's content (`check`).
    """
    import shutil

    src = Path(twin_dir)
    for p in src.iterdir():
        if p.name == "twin.json":
            continue
        (shutil.copytree if p.is_dir() else shutil.copy2)(p, out / p.name)
    (out / "twin.json").write_text(json.dumps(meta, indent=2))
    Twin.load(out)  # what was written reads back as a twin (else nothing is swapped in)


def score(twin: Twin, phase: PhaseData, alpha: float = 0.05) -> dict:
    """The twin as it stands on a phase measured without correction: each pose's tracker error less
    the prediction against its stated U(TCP_c) (coverage per axis), and Eq. 17 on its camera point
    (failure fraction per axis); for comparing a twin before and after a daily check on poses the
    check did not use.

    Parameters
    ----------
    twin : Twin
        The twin.
    phase : PhaseData
        Poses of the session (SI).
    alpha : float
        Eq. 17's significance level.

    Returns
    -------
    dict
        `n`, `rms_mm`, `coverage_95` and `eq17_failures_per_axis` ({x, y, z}).
    """
    ok = np.all(np.isfinite(phase.p_lt), axis=1) & np.all(np.isfinite(phase.p_rdk), axis=1)
    inp = cal.phase_inputs(phase, ok)
    pred, sigma = twin.e_lt.predict(inp, return_std=True)
    r = twin.T_rdk.apply(phase.p_rdk[ok]) - twin.T_lt.apply(phase.p_lt[ok]) - pred
    U = np.array([twin.stated_U(twin.tcp_budget(p, float(v), sigma=s))
                  for p, v, s in zip(phase.p_rdk[ok], phase.speed[ok], sigma)]).reshape(-1, 3)
    m = ok & np.all(np.isfinite(phase.p_mvs), axis=1)
    fails = None
    if m.any():
        mi = cal.phase_inputs(phase, m)
        e_lt_hat, pred_ml = twin.e_lt.predict(mi), twin.e_mvs_lt.predict(mi)
        e_mvs = twin.T_rdk.apply(phase.p_rdk[m]) - twin.T_mvs.apply(phase.p_mvs[m])
        b14, b16 = twin.uncertainty.e_lt_hat_minus_e_mvs, twin.uncertainty.e_mvs_lt_hat
        tt = unc.t_test(e_lt_hat - e_mvs, pred_ml, b14.u, b16.u, b14.dof, b16.dof, alpha)
        fails = {ax: float(1 - tt.passed[:, k].mean()) for k, ax in enumerate(AXES)}
    inside = np.abs(r) <= U
    return {"n": int(ok.sum()), "rms_mm": float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) * MM_PER_M,
            "coverage_95": {ax: float(inside[:, k].mean()) for k, ax in enumerate(AXES)},
            "eq17_failures_per_axis": fails}
