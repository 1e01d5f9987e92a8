"""`dt diagnose`: which physical effect does the model lack?

For every candidate effect not in the starting model, the held-out residual of the model with
and without the effect is compared by cross-validation *grouped by target point* (a model
cannot win by remembering a point). Per held-out group, the paired difference of mean squared
residuals is tested one-sided (Wilcoxon signed-rank: does adding the effect lower the error?).
The ranking orders effects by the fraction of held-out residual variance they explain.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_kernel.errors import DataError
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.frames.kinematics import Chain

ALPHA = 0.01
# What the residual follows, per effect: the factor named in the one-sentence verdict.
FACTOR = {"geometric": "the joint configuration (joint zero offsets and link errors)",
          "compliance": "the payload torque on the joints",
          "gear": "a periodic pattern in the joint angles",
          "backlash": "the direction from which each joint approached",
          "thermal": "the temperature, growing with distance from the base",
          "dynamic": "the commanded speed and direction of travel",
          "drift": "the time since the start of the data"}
GP_FACTOR = {"tcp_speed": "the Cartesian TCP and speed", "tcp": "the Cartesian TCP",
             "joints": "the joint angles"}


@dataclass
class CvResult:
    residual: np.ndarray  # (n,3) held-out residuals
    group_mse: np.ndarray  # (g,) per-group mean squared 3D residual
    std: np.ndarray | None  # (n,3) the fold models' stated standard uncertainty (return_std)




def folds_of(groups: np.ndarray, k: int, seed: int) -> list[np.ndarray]:
    ids = np.unique(groups)
    rng = np.random.default_rng(seed)
    rng.shuffle(ids)
    k = min(k, len(ids))
    return [np.isin(groups, ids[f::k]) for f in range(k)]


def cross_validate(effects: tuple[str, ...], inp: fx.Inputs, error: np.ndarray, groups: np.ndarray,
                   chain: Chain | None, gp_inputs: str, folds: list[np.ndarray], seed: int,
                   gp_kw: dict | None = None, thetas=None, return_std: bool = False,
                   hyper_per_fold: bool = False) -> CvResult:
    """Held-out residuals of the model (effects + GP on gp_inputs), each row predicted by a model
    fitted on the other folds (rows in no fold stay NaN). `thetas`: GP hyperparameters to keep
    fixed (e.g. a saved model's); default: fitted once on all rows (below), or with
    hyper_per_fold inside every fold (strict, slower). return_std: also the fold models' stated
    standard uncertainty of each prediction (its variance costs more than the mean)."""
    # Regressors that look at the previous row (approach direction) are built on the full,
    # time-ordered data and then split, so held-out rows keep their true history.
    resid = np.full_like(error, np.nan)
    std = np.zeros_like(error) if return_std else None
    full = HybridModel(effects, gp_inputs, seed=seed, gp_kw=gp_kw)
    A_full, _ = full._design(inp, chain)
    A_full = A_full.reshape(inp.n, 3, -1)
    # GP hyperparameters are fitted once per candidate model on all rows and kept fixed in
    # the folds (the fold models refit the effect parameters and the GP posterior): a few
    # smoothness/noise numbers leak, no point's error does, and the loop runs 5x faster.
    if gp_inputs != "none" and thetas is None and not hyper_per_fold:
        full.fit_design(A_full, inp, error)
        thetas = full.gp_.thetas_
    for te in folds:
        tr = ~te
        m = HybridModel(effects, gp_inputs, seed=seed, gp_kw=gp_kw)
        m.fit_design(A_full[tr], inp.subset(tr), error[tr], thetas=thetas)
        if return_std:
            pred, std[te] = m.predict_design(A_full[te], inp.subset(te), return_std=True)
        else:
            pred = m.predict_design(A_full[te], inp.subset(te))
        resid[te] = error[te] - pred
    ug = np.unique(groups)
    sq = np.sum(resid ** 2, axis=1)
    gm = np.array([sq[groups == g].mean() for g in ug])
    return CvResult(resid, gm, std)


def noise_floor(u: np.ndarray | None) -> float | None:
    """3D RMS of the stated measurement standard uncertainty (m), if the data states it."""
    if u is None or not np.all(np.isfinite(u)):
        return None
    return float(np.sqrt(np.mean(np.sum(u ** 2, axis=1))))


def paired_gain(base: CvResult, res: CvResult) -> tuple[float, float]:
    """One-sided p-value that `res` lowers the per-group held-out error of `base` (Wilcoxon
    signed rank on the paired per-group mean squared residuals), and the held-out 3D RMS of res."""
    d = base.group_mse - res.group_mse
    # Differences at round-off level (a candidate whose regressors are all zero, e.g.
    # thermal at constant temperature) are no evidence either way.
    if np.all(np.abs(d) <= 1e-9 * np.mean(base.group_mse)):
        return 1.0, rms3(res.residual)
    return float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue), rms3(res.residual)


def _row(before: float, after: float, p: float, **key) -> dict:
    return {**key, "explained_fraction": float(1 - (after / before) ** 2), "p_value": p,
            "rmse_before_mm": before * 1e3, "rmse_after_mm": after * 1e3,
            "significant": p < ALPHA and after < before}


def gp_alternatives(inp: fx.Inputs, gp_inputs: str) -> list[str]:
    """The other GP inputs worth testing: the paper's Cartesian TCP (+ speed) and the joint angles."""
    have = {"tcp_speed" if inp.speed is not None else "tcp"} | ({"joints"} if inp.joints is not None else set())
    same = {gp_inputs} | ({"tcp", "tcp_speed"} if gp_inputs in ("tcp", "tcp_speed") and inp.speed is None else set())
    return sorted(have - same)


def diagnose(inp: fx.Inputs, error: np.ndarray, groups: np.ndarray, chain: Chain | None,
             base_effects: tuple[str, ...] = (), gp_inputs: str = "tcp_speed",
             candidates: tuple[str, ...] | None = None, n_folds: int = 5, seed: int = 0,
             noise_floor_m: float | None = None, progress=None, gp_kw: dict | None = None,
             test_gp_inputs: bool = True) -> dict:
    """Rank the candidate effects missing from `base_effects` + GP(`gp_inputs`); rows in time
    order, `groups` the target point of each row, noise_floor_m the measurement noise floor
    (3D RMS, m) if known. With test_gp_inputs, also test the same effects with the GP on the
    other inputs (`gp_inputs_ranking`): a residual that follows the joint configuration rather
    than the Cartesian position (several joint solutions per region, a real arm's elasticity
    and encoder errors) wants the GP on the joint angles."""
    unknown = [c for c in (*(candidates or ()), *base_effects) if c not in fx.EFFECT_NAMES]
    if unknown:
        raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(fx.EFFECT_NAMES)}")
    folds = folds_of(groups, n_folds, seed)
    avail = fx.available(inp, chain)
    cands = [c for c in (candidates or fx.EFFECT_NAMES) if c in avail and c not in base_effects]
    skipped = [c for c in (candidates or fx.EFFECT_NAMES) if c not in avail and c not in base_effects]
    alts = gp_alternatives(inp, gp_inputs) if test_gp_inputs and gp_inputs != "none" else []
    base = cross_validate(tuple(base_effects), inp, error, groups, chain, gp_inputs, folds, seed, gp_kw)
    before = rms3(base.residual)
    ranking, gp_ranking = [], []
    steps = [("effect", c) for c in cands] + [("gp_inputs", g) for g in alts]
    for i, (kind, c) in enumerate(steps):
        if progress:
            progress.step("diagnose: candidates", i, len(steps))
        if kind == "effect":
            res = cross_validate(tuple(base_effects) + (c,), inp, error, groups, chain, gp_inputs, folds, seed, gp_kw)
            p, after = paired_gain(base, res)
            ranking.append(_row(before, after, p, effect=c))
        else:
            res = cross_validate(tuple(base_effects), inp, error, groups, chain, c, folds, seed, gp_kw)
            p, after = paired_gain(base, res)
            gp_ranking.append(_row(before, after, p, gp_inputs=c))
    ranking.sort(key=lambda r: (not r["significant"], -r["explained_fraction"]))
    gp_ranking.sort(key=lambda r: (not r["significant"], -r["explained_fraction"]))
    floor = noise_floor_m
    top = ranking[0] if ranking else None
    if top and top["significant"]:
        verdict = (f"The model lacks '{top['effect']}': adding it explains "
                   f"{100 * top['explained_fraction']:.0f} % of the held-out residual variance "
                   f"(p = {top['p_value']:.2g}), because the residual follows {FACTOR[top['effect']]}.")
    else:
        verdict = "No candidate effect explains a significant part of the held-out residual (all p >= 0.01)"
        verdict += (f"; the residual ({before * 1e3:.3f} mm RMS) is at the measurement noise floor "
                    f"({floor * 1e3:.3f} mm)." if floor and before < 1.3 * floor else ".")
    g = gp_ranking[0] if gp_ranking else None
    if g and g["significant"] and (top is None or not top["significant"]
                                   or g["explained_fraction"] > top["explained_fraction"]):
        verdict += (f" The GP on {GP_FACTOR[g['gp_inputs']]} instead of {GP_FACTOR[gp_inputs]} explains "
                    f"{100 * g['explained_fraction']:.0f} % (p = {g['p_value']:.2g}): "
                    f"fit with --gp-inputs {g['gp_inputs']}.")
    return {"base_effects": list(base_effects), "gp_inputs": gp_inputs, "n": int(inp.n),
            "n_groups": int(len(np.unique(groups))), "folds": len(folds),
            "rmse_base_mm": before * 1e3, "noise_floor_mm": None if floor is None else floor * 1e3,
            "ranking": ranking, "gp_inputs_ranking": gp_ranking, "not_testable": skipped, "verdict": verdict}
