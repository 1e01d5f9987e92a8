"""`dt diagnose`: which physical effect does the model lack?

For every candidate effect not in the starting model, the held-out residual of the model with
and without the effect is compared by cross-validation *grouped by target point* (a model
cannot win by remembering a point; dt_runtime.analysis.crossval). Per held-out group, the
paired difference of mean squared residuals is tested one-sided (Wilcoxon signed-rank: does
adding the effect lower the error?). The ranking orders effects by the fraction of held-out
residual variance they explain.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import stats

from dt_runtime.analysis.crossval import CvResult, cross_validate, folds_of, groups_of
from dt_runtime.analysis.data import Data, floor_of, load_data
from dt_runtime.analysis.results import DiagnoseResult, Gain
from dt_runtime.analysis.training import data_provenance
from dt_runtime.common.progress import Progress
from dt_runtime.frames.kinematics import Chain
from dt_runtime.measurements.checks import check_dataset
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.gp import GPOptions
from dt_runtime.models.hybrid import DEFAULT_RIDGE, HybridModel, load_map, resolve_chain

ALPHA = 0.01
# What the residual follows when the GP's inputs are the wrong ones (an effect's own factor is
# `Effect.factor`).
GP_FACTOR = {"tcp_speed": "the Cartesian TCP and speed", "tcp": "the Cartesian TCP",
             "joints": "the joint angles"}


def paired_gain(base: CvResult, res: CvResult) -> tuple[float, float]:
    """One-sided p-value that `res` lowers the per-group held-out error of `base` (Wilcoxon
    signed rank on the paired per-group mean squared residuals), and the held-out 3D RMS of res."""
    d = base.group_mse - res.group_mse
    # Differences at round-off level (a candidate whose regressors are all zero, e.g.
    # thermal at constant temperature) are no evidence either way.
    if np.all(np.abs(d) <= 1e-9 * np.mean(base.group_mse)):
        return 1.0, rms3(res.residual)
    return float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue), rms3(res.residual)


def _gain(kind: str, candidate: str, before: float, after: float, p: float) -> Gain:
    return Gain(kind, candidate, float(1 - (after / before) ** 2), p, before * 1e3, after * 1e3,
                p < ALPHA and after < before)


def gp_alternatives(inp: fx.Inputs, gp_inputs: str) -> list[str]:
    """The other GP inputs worth testing: the paper's Cartesian TCP (+ speed) and the joint angles."""
    have = {"tcp_speed" if inp.speed is not None else "tcp"} | ({"joints"} if inp.joints is not None else set())
    same = {gp_inputs} | ({"tcp", "tcp_speed"} if gp_inputs in ("tcp", "tcp_speed") and inp.speed is None else set())
    return sorted(have - same)


def _verdict(ranking: list[Gain], gp_ranking: list[Gain], before: float, floor: float | None,
             gp_inputs: str) -> str:
    top = ranking[0] if ranking else None
    if top and top.significant:
        verdict = (f"The model lacks '{top.candidate}': adding it explains "
                   f"{100 * top.explained_fraction:.0f} % of the held-out residual variance "
                   f"(p = {top.p_value:.2g}), because the residual follows {fx.get(top.candidate).factor}.")
    else:
        verdict = "No candidate effect explains a significant part of the held-out residual (all p >= 0.01)"
        verdict += (f"; the residual ({before * 1e3:.3f} mm RMS) is at the measurement noise floor "
                    f"({floor * 1e3:.3f} mm)." if floor and before < 1.3 * floor else ".")
    g = gp_ranking[0] if gp_ranking else None
    if g and g.significant and (top is None or not top.significant or g.explained_fraction > top.explained_fraction):
        # The advice names the command-line option: the verdict is read by the user of `dt`.
        verdict += (f" The GP on {GP_FACTOR[g.candidate]} instead of {GP_FACTOR[gp_inputs]} explains "
                    f"{100 * g.explained_fraction:.0f} % (p = {g.p_value:.2g}): "
                    f"fit with gp_inputs='{g.candidate}' (dt fit --gp-inputs {g.candidate}).")
    return verdict


def rank_effects(inp: fx.Inputs, error: np.ndarray, groups: np.ndarray, chain: Chain | None,
             base_effects: tuple[str, ...] = (), gp_inputs: str = "tcp_speed",
             candidates: tuple[str, ...] | None = None, n_folds: int = 5, seed: int = 0,
             noise_floor_m: float | None = None, progress: Progress | None = None,
             gp_options: GPOptions | None = None, test_gp_inputs: bool = True,
             ridge: float = DEFAULT_RIDGE) -> DiagnoseResult:
    """Rank the candidate effects missing from `base_effects` + GP(`gp_inputs`); rows in time
    order, `groups` the target point of each row, noise_floor_m the measurement noise floor
    (3D RMS, m) if known. With test_gp_inputs, also test the same effects with the GP on the
    other inputs (`gp_inputs_ranking`): a residual that follows the joint configuration rather
    than the Cartesian position (several joint solutions per region, a real arm's elasticity
    and encoder errors) wants the GP on the joint angles."""
    fx.check_names((*(candidates or ()), *base_effects))
    folds = folds_of(groups, n_folds, seed)
    avail = fx.available(inp, chain)
    cands = [c for c in (candidates or fx.names()) if c in avail and c not in base_effects]
    skipped = [c for c in (candidates or fx.names()) if c not in avail and c not in base_effects]
    alts = gp_alternatives(inp, gp_inputs) if test_gp_inputs and gp_inputs != "none" else []
    base_model = HybridModel(tuple(base_effects), gp_inputs, ridge=ridge, seed=seed, robot=chain,
                             gp_options=gp_options)
    base = cross_validate(base_model, inp, error, groups, folds)
    before = rms3(base.residual)
    ranking: list[Gain] = []
    gp_ranking: list[Gain] = []
    steps = [("effect", c) for c in cands] + [("gp_inputs", g) for g in alts]
    for i, (kind, c) in enumerate(steps):
        if progress:
            progress.step("diagnose: candidates", i, len(steps))
        if kind == "effect":
            res = cross_validate(base_model.unfitted(effects=tuple(base_effects) + (c,)), inp, error, groups, folds)
        else:
            res = cross_validate(base_model.unfitted(gp_inputs=c), inp, error, groups, folds)
        p, after = paired_gain(base, res)
        (ranking if kind == "effect" else gp_ranking).append(_gain(kind, c, before, after, p))
    ranking.sort(key=lambda r: (not r.significant, -r.explained_fraction))
    gp_ranking.sort(key=lambda r: (not r.significant, -r.explained_fraction))
    floor = noise_floor_m
    return DiagnoseResult(list(base_effects), gp_inputs, int(inp.n), int(len(np.unique(groups))), len(folds),
                          before * 1e3, None if floor is None else floor * 1e3, ranking, gp_ranking, skipped,
                          _verdict(ranking, gp_ranking, before, floor, gp_inputs))


def diagnose(data: Data | Dataset | str | Path, model: HybridModel | str | Path | None = None,
             effects: tuple[str, ...] = (), gp_inputs: str = "tcp_speed",
             robot: str | Path | Chain | None = None, candidates: tuple[str, ...] | None = None,
             folds: int = 5, seed: int = 0, gp_options: GPOptions | None = None,
             progress: Progress | None = None, instruments: str | Path | None = None,
             inputs: Sequence[str | Path] = ()) -> DiagnoseResult:
    """Which effect does the model lack? `data`: loaded data (`load_data`), a Dataset or a
    contract CSV path. The starting model is `model` (a HybridModel, fitted or not, or a saved
    model's directory), else `effects` + GP on `gp_inputs` with the kinematic model `robot`.
    The engine on plain arrays is `rank_effects`. The result's `provenance` records the data
    file, the saved model's files, `inputs` and the `instruments` YAML (hashed), the robot and
    the instruments."""
    if isinstance(data, (str, Path)):
        data = load_data(data)
    d = data if isinstance(data, Data) else Data(data, {"n": data.n})
    ds = d.dataset
    ridge = DEFAULT_RIDGE
    if model is not None:
        m = model if isinstance(model, HybridModel) else load_map(model)
        effects, gp_inputs, robot, gp_options, ridge = m.effects, m.gp_inputs, m.robot, m.gp_options, m.ridge
    chain = resolve_chain(robot)
    d.info.update(check_dataset(ds, chain, d.info.get("data")))
    prov = data_provenance(ds, d.info.get("data"), robot, instruments, inputs, [model] if model is not None else [])
    r = rank_effects(fx.Inputs.of(ds), ds.error, groups_of(ds), chain, tuple(effects), gp_inputs,
                     candidates, folds, seed, noise_floor_m=floor_of(d), progress=progress,
                     gp_options=gp_options, ridge=ridge)
    r.source = {k: v for k, v in d.info.items() if k != "n"}
    r.provenance = prov
    return r
