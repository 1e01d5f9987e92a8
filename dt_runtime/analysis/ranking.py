"""One step of a diagnosis: every candidate change to a model (an effect added, the GP on other
inputs) held out against the model, and the evidence for each.

The significance test: per held-out point, the paired difference of mean squared residuals,
one-sided Wilcoxon signed rank (does the change lower the error?) on the point-grouped folds (many
independent groups). The deployment figure: the held-out 3D RMS on the scheme deployment brings
(held-out regions, sessions or later times, `validation`), which a change must also lower.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

from dt_runtime.analysis.crossval import CvResult
from dt_runtime.analysis.evaluation import Config, Evaluator
from dt_runtime.analysis.results import Gain
from dt_runtime.common.progress import Progress
from dt_runtime.metrology.stats import finite_rows, rms3
from dt_runtime.models import effects as fx

ALPHA = 0.01


def paired_gain(base: CvResult, res: CvResult) -> tuple[float, float]:
    """One-sided p-value that `res` lowers the per-group held-out error of `base` (Wilcoxon
    signed rank on the paired per-group mean squared residuals), and the held-out 3D RMS of res.

    Parameters
    ----------
    base, res : CvResult
        Cross-validations on the same scheme.

    Returns
    -------
    p_value : float
    rms : float
        m.
    """
    d = base.group_mse - res.group_mse
    d = d[np.isfinite(d)]  # a forecast never predicts its first block's points
    # Differences at round-off level (a candidate whose regressors are all zero, e.g.
    # thermal at constant temperature) are no evidence either way.
    after = rms3(res.residual[finite_rows(res.residual)])  # over the rows the scheme predicted
    if not len(d) or np.all(np.abs(d) <= 1e-9 * np.nanmean(base.group_mse)):
        return 1.0, after
    return float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue), after


def gain(kind: str, candidate: str, base: CvResult, res: CvResult, alpha: float = ALPHA) -> Gain:
    """The held-out gain of one change over the base configuration.

    Parameters
    ----------
    kind : str
        "effect", "gp_inputs" or "session".
    candidate : str
        What was changed.
    base, res : CvResult
        The base's and the changed configuration's cross-validation (same scheme).
    alpha : float, optional
        Significance level.

    Returns
    -------
    Gain
        Explained fraction of the held-out variance, one-sided p-value, RMS before and after (mm),
        and whether it is significant and lowers the RMS.
    """
    p, after = paired_gain(base, res)
    before = rms3(base.residual)
    return Gain(kind, candidate, float(1 - (after / before) ** 2), p, before * 1e3, after * 1e3,
                p < alpha and after < before)


def gp_alternatives(inp: fx.Inputs, gp_inputs: str) -> list[str]:
    """The other GP inputs worth testing: the paper's Cartesian TCP (+ speed) and the joint angles.

    Parameters
    ----------
    inp : Inputs
        The data's columns.
    gp_inputs : str
        The current GP inputs.

    Returns
    -------
    list of str
    """
    have = {"tcp_speed" if inp.speed is not None else "tcp"} | ({"joints"} if inp.joints is not None else set())
    same = {gp_inputs} | ({"tcp", "tcp_speed"} if gp_inputs in ("tcp", "tcp_speed") and inp.speed is None else set())
    return sorted(have - same)


def changed(cfg: Config, kind: str, candidate: str) -> Config:
    """The configuration after a change: an effect added, the GP on other inputs, or a session
    term added as a nuisance.

    Parameters
    ----------
    cfg : Config
        The configuration.
    kind : str
        "effect", "gp_inputs" or "session".
    candidate : str
        What changes.

    Returns
    -------
    Config
    """
    if kind == "effect":
        return cfg.plus(candidate)
    if kind == "session":
        return Config(cfg.effects, cfg.gp_inputs, (*cfg.nuisance, candidate))
    return Config(cfg.effects, candidate, cfg.nuisance)


def rank(ev: Evaluator, cfg: Config, candidates: list[str], gp_inputs: list[str],
         progress: Progress | None = None, alpha: float = ALPHA,
         session_terms: Sequence[str] = ()) -> tuple[list[Gain], list[Gain], list[Gain]]:
    """The candidates' gains against `cfg` on the point-grouped folds, best first: (effects, GP
    inputs, session terms). Each effect or session-term candidate's GP hyperparameter fit starts
    from `cfg`'s (it adds one block to that model, so the GP sees nearly the same residual); a
    switch of the GP's inputs starts cold (warm starts from a model with other inputs, and from
    one with the same inputs but other effects, led the 6-D joint GP to a poorer optimum: UR10
    Series D 0.317 instead of 0.276 mm, the switch no longer significant).

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    candidates : list of str
        Effects to test.
    gp_inputs : list of str
        GP inputs to test.
    progress : Progress, optional
        Where progress is reported.
    alpha : float, optional
        Significance level of each test.
    session_terms : sequence of str, optional
        Session terms to test.

    Returns
    -------
    effects, gp_inputs, session_terms : list of Gain
    """
    base = ev.cv(cfg, ev.points)
    steps = ([("effect", c) for c in candidates] + [("gp_inputs", g) for g in gp_inputs]
             + [("session", t) for t in session_terms])
    out: dict[str, list[Gain]] = {"effect": [], "gp_inputs": [], "session": []}
    if progress and steps:
        progress.note(f"diagnose: {len(steps)} candidate(s) against {cfg.label()}")
    results = ev.cv_many([(changed(cfg, kind, c), ev.points, base.log_hypers if kind != "gp_inputs" else None)
                          for kind, c in steps])
    for (kind, c), res in zip(steps, results):
        g = gain(kind, c, base, res, alpha)
        if kind == "effect":
            g.factor = ev.problem.catalogue.get(c).factor
        out[kind].append(g)
    for ranking in out.values():
        ranking.sort(key=lambda r: (not r.significant, -r.explained_fraction))
    return out["effect"], out["gp_inputs"], out["session"]


def deployment_figures(ev: Evaluator, cfg: Config, g: Gain) -> Gain:
    """`g` with the held-out RMS before and after on the scheme its change is judged on.

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    g : Gain
        The change's gain.

    Returns
    -------
    Gain
    """
    scheme = ev.scheme_for(g.candidate if g.kind == "effect" else None)
    g.deploy_kind = scheme.kind
    g.deploy_rmse_before_mm = ev.rms_mm(cfg, scheme)
    g.deploy_rmse_after_mm = ev.rms_mm(changed(cfg, g.kind, g.candidate), scheme)
    return g
