"""Sessions that disagree are a finding: a campaign of several sessions (files, each with its own
set-up) is held out one session at a time (`held_out`), and the difference between sessions is
tested against the session terms (`term_values`; models.effects.session: a re-mounted tool or
SMR, the set-up's rigid part, changed joint zeros). See docs/campaigns.md ("Sessions that disagree").
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from dt_runtime.analysis import reregister
from dt_runtime.analysis.evaluation import Config, Evaluator
from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.effects import session as terms

UNIT_SCALE = {"m": (1e3, "mm"), "rad": (1e3, "mrad")}


def available_terms(ev: Evaluator) -> list[str]:
    """The session terms the data allow (tool and joint zeros need the joints and the robot's model).

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.

    Returns
    -------
    list of str
    """
    p = ev.problem
    joints = p.inp.joints is not None and p.chain is not None
    return [t for t in terms.TERMS if t == "base" or joints]


def term_values(ev: Evaluator, cfg: Config, names: dict[int, str], which: tuple[str, ...]) -> list[dict]:
    """The fitted nuisance parameters of the session terms `which` of `cfg`, per session against the
    reference session, in mm or mrad with the expanded uncertainty (95 %, k from the residual's
    degrees of freedom), and whether the session differs at all (chi^2 of its parameters against 0).

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    names : dict of int to str
        Session names.
    which : tuple of str
        The session terms.

    Returns
    -------
    list of dict
    """
    p = ev.problem
    m = ev.model(cfg).fit(p.inp, p.error)
    dof = max(3 * p.n - len(m.theta_), 1)
    k = float(stats.t.ppf(0.975, dof))
    groups: dict[tuple[int, str], list[int]] = {}
    for i, (effect, name, _, _) in enumerate(m.param_names_):
        if effect.startswith("session_") and effect[8:] in which:
            groups.setdefault((int(name.split("_", 1)[0][1:]), effect[8:]), []).append(i)
    rows = []
    for (sid, term), idx in sorted(groups.items()):
        params = []
        for i in idx:
            _, name, unit, _ = m.param_names_[i]
            scale, shown = UNIT_SCALE.get(unit, (1.0, unit))
            params.append({"name": name.split("_", 1)[1], "value": float(m.theta_[i]) * scale,
                           "U": k * float(m.theta_u_[i]) * scale, "unit": shown})
        th, cov = m.theta_[idx], m.theta_cov_[np.ix_(idx, idx)]
        try:
            pval: float | None = float(stats.chi2.sf(float(th @ np.linalg.solve(cov, th)), len(idx)))
        except np.linalg.LinAlgError:
            pval = None
        rows.append({"session": sid, "name": names.get(sid, str(sid)), "term": term, "parameters": params, "k": k,
                     "p_value": pval})
    return rows


def absorbed(ev: Evaluator, cfg: Config, residual: np.ndarray) -> tuple[np.ndarray, dict[int, tuple[int, list]]]:
    """`residual` (held out by session) scored the way a new session is: re-registered where the
    session's registration was fitted on its own points (6 dof), and with `cfg`'s session terms
    measured again on the session. Returns it and, per session, (dof absorbed, what was absorbed).

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    residual : ndarray
        (n, 3), m.

    Returns
    -------
    residual : ndarray
    info : dict
    """
    p = ev.problem
    assert p.session is not None
    out = np.array(residual, dtype=float, copy=True)
    info: dict[int, tuple[int, list]] = {}
    for sid in np.unique(p.session):
        f = p.session == sid
        r = out[f]
        dof, what = 0, []
        rereg = int(sid) in p.refit_sessions and p.measured is not None
        if rereg:
            assert p.measured is not None
            r = reregister.reregistered(p.measured[f], r)[0]
            dof, what = reregister.DOF, ["registration"]
        # the session terms measured again (the set-up's rigid part is the registration's, when refitted)
        for t in [t for t in cfg.nuisance if not (t == "base" and rereg)]:
            r, k = terms.absorb(t, p.inp.subset(f), p.chain, r)
            dof += k
            what.append(f"session term {t}")
        out[f] = r
        info[int(sid)] = (dof, what)
    return out, info


def held_out(ev: Evaluator, cfg: Config, names: dict[int, str]) -> list[dict]:
    """Each session predicted by `cfg` fitted on the others, beside the session as is.

    Both are scored the way a new session is (`absorbed`): after re-registration where the
    session's registration was fitted on its own points (6 dof), and after measuring again
    whatever session term the model carries as a nuisance (its dof); and the rows outside the
    others' domain are counted.

    Parameters
    ----------
    ev : Evaluator
        The problem (several sessions, deployment scheme by session).
    cfg : Config
        The configuration.
    names : dict
        Session index -> name.

    Returns
    -------
    list of dict
        One row per session.
    """
    p = ev.problem
    assert p.session is not None and ev.deploy.kind == "sessions"
    raw = ev.cv(cfg, ev.deploy).residual
    model_r, info = absorbed(ev, cfg, raw)
    as_is, _ = absorbed(ev, cfg, p.error)
    rows = []
    for sid in np.unique(p.session):
        f = p.session == sid
        dof, what = info[int(sid)]
        rows.append({"session": int(sid), "name": names.get(int(sid), str(int(sid))), "rows": int(f.sum()),
                     "rmse_mm": rms3(model_r[f]) * 1e3, "as_is_rmse_mm": rms3(as_is[f]) * 1e3,
                     "rmse_raw_mm": rms3(raw[f]) * 1e3, "dof_absorbed": dof,
                     "reregistered": "registration" in what, "absorbed": what,
                     "outside_training": outside_others(p.inp, f)})
    return rows


def outside_others(inp: fx.Inputs, test: np.ndarray, margin: float = 0.02) -> dict:
    """Rows of the `test` mask outside the range of the other rows (TCP box, joint ranges; each
    widened by `margin` of its range, as HybridModel.outside_domain): {'rows', 'columns': {name: rows}}.

    Parameters
    ----------
    inp : Inputs
        The data's columns.
    test : ndarray
        (n,) bool.
    margin : float, optional
        Widening, as a fraction of each range.

    Returns
    -------
    dict
    """
    outside = np.zeros(int(test.sum()), bool)
    cols: dict[str, int] = {}
    blocks: list[tuple[np.ndarray, tuple[str, ...]]] = [(inp.commanded, ("x", "y", "z"))]
    if inp.joints is not None:
        blocks.append((inp.joints, tuple(f"q{j + 1}" for j in range(inp.joints.shape[1]))))
    for values, names in blocks:
        lo, hi = values[~test].min(0), values[~test].max(0)
        w = margin * np.maximum(hi - lo, 1e-9)
        out = (values[test] < lo - w) | (values[test] > hi + w)
        outside |= out.any(axis=1)
        cols.update({n: int(c) for n, c in zip(names, out.sum(0)) if c})
    return {"rows": int(outside.sum()), "columns": cols}
