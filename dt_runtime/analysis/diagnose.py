"""`dt diagnose`: which physical effect does the model lack? One entry, two depths:

    r = diagnose("data.csv", DiagnoseOptions(effects=("geometric",)))     # one step: the candidates ranked
    r = diagnose("data.csv", DiagnoseOptions(auto=True, out="model"))     # the whole loop, its final model saved

How a candidate is judged: `diagnose`; the verdict's words are the reports'
(dt_runtime.reports.verdicts). See docs/cli.md ("dt diagnose") and docs/effects.md.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_runtime.analysis import parallel
from dt_runtime.analysis.columns import column_check, factor_columns, read_columns
from dt_runtime.analysis.crossval import groups_of
from dt_runtime.analysis.data import Data, floor_of, load_data, refit_sessions, select_sessions
from dt_runtime.analysis.evaluation import Config, Evaluator, Problem
from dt_runtime.analysis.options import DiagnoseOptions
from dt_runtime.analysis.ranking import ALPHA, deployment_figures, gp_alternatives, rank
from dt_runtime.analysis.results import AutoResult, DiagnoseResult
from dt_runtime.analysis.selection import select, testable
from dt_runtime.analysis.training import data_provenance
from dt_runtime.common.outputs import final_path
from dt_runtime.common.progress import Progress
from dt_runtime.common.provenance import Provenance
from dt_runtime.frames.kinematics import Chain
from dt_runtime.measurements.checks import check_dataset
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.hybrid import DEFAULT_RIDGE, HybridModel, load_map, resolve_chain

__all__ = ["ALPHA", "DiagnoseOptions", "Prepared", "diagnose", "prepare"]
log = logging.getLogger("dt.diagnose")


@dataclass
class Prepared:
    """A diagnosis's inputs, prepared once for either depth."""

    data: Data
    problem: Problem
    start: Config
    robot: str | Path | Chain | None
    floor_m: float | None
    session_names: dict[int, str]
    provenance: Provenance


def prepare(data: Data | Dataset | str | Path, options: DiagnoseOptions) -> Prepared:
    """A diagnosis's inputs, prepared once for either depth.

    Parameters
    ----------
    data : Data, Dataset, str or Path
        The measurements: a `Data`, a `Dataset` or a contract CSV's path.
    options : DiagnoseOptions
        The starting configuration (`model`, else `effects` + GP on `gp_inputs`), the kinematic
        model `robot`, the sessions (`exclude_sessions`, `reference_session`, `session_terms`), the
        files of the traceability record (`instruments`, `inputs`) and the `catalogue` (a model's
        own declared effects are added to it).

    Returns
    -------
    Prepared
        The data, the problem, the starting configuration, the noise floor, the sessions' names and
        the traceability record.
    """
    o = options
    model, effects, gp_inputs, robot, gp_options = o.model, o.effects, o.gp_inputs, o.robot, o.gp_options
    session_terms = o.session_terms
    if isinstance(data, (str, Path)):
        data = load_data(data)
    d = data if isinstance(data, Data) else Data(data, {"n": data.n})
    ridge = DEFAULT_RIDGE
    catalogue = o.catalogue if o.catalogue is not None else fx.default()
    if model is not None:
        m = model if isinstance(model, HybridModel) else load_map(model, catalogue)
        effects, gp_inputs, robot, gp_options, ridge = m.effects, m.gp_inputs, m.robot, m.gp_options, m.ridge
        session_terms = session_terms or tuple(getattr(m, "nuisance", ()))
        # the call's effects and the model's own declared ones (a saved model's carry its file's)
        catalogue = catalogue.with_own(m.effects_catalogue().own.values())
    d, names, ref = select_sessions(d, o.exclude_sessions, o.reference_session)
    ds = d.dataset
    chain = resolve_chain(robot)
    d.info.update(check_dataset(ds, chain, d.info.get("data")))
    prov = data_provenance(ds, d.info.get("data"), robot, o.instruments, o.inputs,
                           [model] if isinstance(model, (str, Path)) else [])
    session = ds.extra.get("session")
    session = session.astype(int) if session is not None and len(np.unique(session)) > 1 else None
    labels = refit_sessions(d)
    refit = set() if labels is None or session is None else {int(v) for v in np.unique(labels) if v >= 0}
    floor = floor_of(d)
    problem = Problem(fx.Inputs.of(ds), ds.error, groups_of(ds), chain, session, ds.actual, refit, gp_options,
                      ridge, ref, catalogue)
    return Prepared(d, problem, Config(tuple(effects), gp_inputs, tuple(session_terms)), robot, floor, names, prov)


def _pose(p: Problem) -> np.ndarray:
    return p.inp.joints if p.inp.joints is not None else p.inp.commanded


def _n_joints(p: Problem) -> int:
    return 0 if p.inp.joints is None else int(p.inp.joints.shape[1])


def diagnose(data: Data | Dataset | str | Path, options: DiagnoseOptions | None = None, *,
             progress: Progress | None = None) -> DiagnoseResult | AutoResult:
    """Which effect does the model lack?

    Both depths prepare the data the same way (`prepare`: the measurement table or a mapped file,
    the robot's kinematic model, the noise floor, the sessions, the traceability record) and
    judge every candidate the way the twin will be used:

    - the significance test holds out whole target points (analysis.ranking: a model cannot win
      by remembering a point; paired one-sided Wilcoxon per point);
    - the decision also needs a lower held-out RMS on the deployment scheme (analysis.validation:
      held-out regions of the workspace, held-out sessions when there are several, a forecast of
      later times for a time-dependent term), and both figures are reported side by side;
    - a candidate the campaign cannot separate from the pose is not tested (analysis.confounding);
    - several sessions: held out one at a time, and their disagreement tested against the
      session terms (analysis.sessions).

    Parameters
    ----------
    data : Data, Dataset, str or Path
        The measurements (`prepare`).
    options : DiagnoseOptions or None
        What is asked; None: ``DiagnoseOptions()`` (the paper's model, every candidate, one step).
        `auto`: the whole loop (analysis.selection) and, with `out`, its final model saved there.
    progress : Progress or None
        Where the steps report their progress (stderr); None: silent.

    Returns
    -------
    DiagnoseResult or AutoResult
        One step's ranking, or the loop's steps and verdict figures (`auto`). Its `provenance`
        records the data file, the saved model's files, `inputs` and the `instruments` YAML
        (hashed), the robot and the instruments.
    """
    o = options if options is not None else DiagnoseOptions()
    prep = prepare(data, o)
    n = parallel.workers()
    pool = parallel.Pool(prep.problem, o.folds, o.seed, n) if n > 1 else None
    try:
        ev = Evaluator(prep.problem, o.folds, o.seed, pool)
        if o.auto:
            return _auto(prep, ev, o.candidates, o.alpha, o.min_explained, o.max_steps, progress, o.out)
        return _plain(prep, ev, o.candidates, o.alpha, progress)
    finally:
        if pool is not None:
            pool.close()


def _source(prep: Prepared) -> dict:
    return {k: v for k, v in prep.data.info.items() if k != "n"}


def _plain(prep: Prepared, ev: Evaluator, candidates: tuple[str, ...] | None, alpha: float,
           progress: Progress | None) -> DiagnoseResult:
    p, cfg = prep.problem, prep.start
    cat = p.catalogue
    names = [c for c in (candidates or cat.names()) if c not in cfg.effects]
    cat.check_names((*names, *cfg.effects))
    cands, not_testable = testable(ev, names)
    eff, gps, _ = rank(ev, cfg, cands, gp_alternatives(p.inp, cfg.gp_inputs) if cfg.gp_inputs != "none" else [],
                       progress, alpha)
    for g in eff + gps:
        if g.significant:
            deployment_figures(ev, cfg, g)
    base = ev.cv(cfg, ev.points)
    r = DiagnoseResult(list(cfg.effects), cfg.gp_inputs, p.n, int(len(np.unique(p.groups))), ev.points.k,
                       rms3(base.residual) * 1e3, None if prep.floor_m is None else prep.floor_m * 1e3, eff, gps,
                       not_testable, source=_source(prep), provenance=prep.provenance,
                       base_group_mse=base.group_mse, base_residual=base.residual,
                       validation={"significance": ev.points.to_dict(), "deployment": ev.deploy.to_dict(),
                                   "time": ev.time.to_dict()})
    r.columns = column_check(base.residual, p.groups, factor_columns(prep.data.dataset), catalogue=cat,
                             pose=_pose(p))
    r.model_columns = sorted(read_columns(cfg.effects, cfg.gp_inputs, _n_joints(p), cat))
    return r


def _auto(prep: Prepared, ev: Evaluator, candidates: tuple[str, ...] | None, alpha: float, min_explained: float,
          max_steps: int, progress: Progress | None, out: str | Path | None) -> AutoResult:
    p = prep.problem
    p.catalogue.check_names((*(candidates or ()), *prep.start.effects))
    sel = select(ev, prep.start, candidates, alpha, min_explained, max_steps, prep.floor_m, progress)
    final = sel.final
    last = ev.cv(final, ev.points)
    floor = None if prep.floor_m is None else prep.floor_m * 1e3
    final_mm = sel.steps[-1].rmse_mm
    as_is_mm = rms3(p.error) * 1e3
    r = AutoResult(start=prep.start.label(), start_config=prep.start.to_dict(), steps=sel.steps,
                   added=[s.change.label() for s in sel.steps if s.change], final_config=final.to_dict(),
                   effects=list(final.effects), gp_inputs=final.gp_inputs, session_terms=list(final.nuisance),
                   final_rmse_mm=final_mm, final_deploy_rmse_mm=ev.rms_mm(final, ev.deploy),
                   deploy_kind=ev.deploy.kind, as_is_rmse_mm=as_is_mm, noise_floor_mm=floor,
                   floor_ratio=None if floor is None else final_mm / floor, stop_reason=sel.stop_reason,
                   not_testable=sel.not_testable, alpha=alpha, min_explained=min_explained, n=p.n,
                   folds=ev.points.k,
                   validation={"significance": ev.points.to_dict(), "deployment": ev.deploy.to_dict(),
                               "time": ev.time.to_dict()},
                   source=_source(prep), provenance=prep.provenance)
    r.columns = column_check(last.residual, p.groups, factor_columns(prep.data.dataset), catalogue=p.catalogue,
                             pose=_pose(p))
    r.model_columns = sorted(read_columns(final.effects, final.gp_inputs, _n_joints(p), p.catalogue))
    if p.session is not None:
        from dt_runtime.analysis import sessions

        r.reference_session = prep.session_names.get(p.reference_session)
        r.sessions = sessions.held_out(ev, final, prep.session_names)
        start_rows = sessions.held_out(ev, prep.start, prep.session_names) if prep.start != final else r.sessions
        for row, s0 in zip(r.sessions, start_rows):
            row["start_rmse_mm"], row["start_rmse_raw_mm"] = s0["rmse_mm"], s0["rmse_raw_mm"]
            dom = row["outside_training"]
            if dom["rows"]:
                log.warning("session %d (%s): %d of %d rows lie outside the other sessions' domain (%s): predicting it "
                            "extrapolates", row["session"], row["name"], dom["rows"], row["rows"],
                            ", ".join(f"{c} {n}" for c, n in dom["columns"].items()))
        r.session_terms_tested = [g.to_dict() for g in sel.session_terms]
        found = tuple(s.change.name for s in sel.steps if s.change and s.change.kind == "session")
        if found:
            r.session_term_values = sessions.term_values(ev, final, prep.session_names, found)
        r.deploy = {"ok": all(s["rmse_mm"] <= s["as_is_rmse_mm"] for s in r.sessions), "by": "sessions"}
    else:
        r.deploy = {"ok": r.final_deploy_rmse_mm < as_is_mm, "by": ev.deploy.kind}
    if out is not None:
        r.model_out = str(final_path(save_final(prep, ev, final, out, r)))  # where it is once swapped in
    r.evaluator = ev
    r.heldout_rows = heldout_rows(prep, ev, Config.of(sel.steps[0].config), final)
    return r


def heldout_rows(prep: Prepared, ev: Evaluator, first: Config, final: Config) -> dict:
    """The rows and the held-out residuals by point of the `first` model (before any step) and the
    `final` one, as reports.residuals writes them: the cross-validations the steps already ran
    (memoised), nothing refitted. The model names say which is which; one model when nothing
    was changed.

    Parameters
    ----------
    prep : Prepared
        The prepared data.
    ev : Evaluator
        The problem and its memoised cross-validations.
    first, final : Config
        The configurations.

    Returns
    -------
    dict
    """
    ds = prep.data.dataset
    pair = [("first", first), ("final", final)] if first != final else [("first = final", final)]
    return {"commanded": ds.commanded, "speed": ds.speed, "joints": ds.joints, "session": ds.extra.get("session"),
            "point_id": ds.point_id, "lines": ds.lines,
            "models": [{"name": f"{which}: {cfg.label()}", "residual": ev.cv(cfg, ev.points).residual}
                       for which, cfg in pair]}


def save_final(prep: Prepared, ev: Evaluator, cfg: Config, out: str | Path, result: AutoResult) -> Path:
    """Fit the final configuration on all rows and save it, ready for dt compare, dt calibrate
    --model and dt export (`dt diagnose --auto --out` writes the result beside it, diagnose.json).

    Parameters
    ----------
    prep : Prepared
        The prepared data.
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    out : str or Path
        The model directory.
    result : AutoResult
        The loop's result.

    Returns
    -------
    Path
    """
    p = prep.problem
    robot = prep.robot if not isinstance(prep.robot, Chain) else p.chain
    m = HybridModel(cfg.effects, cfg.gp_inputs, ridge=p.ridge, seed=ev.seed, robot=robot,
                    gp_options=p.gp_options, nuisance=cfg.nuisance, reference_session=p.reference_session,
                    catalogue=p.catalogue)  # its declared effects are saved with it
    # its GP hyperparameters start from those the loop fitted on all rows (the same configuration)
    m.fit(prep.data.dataset, starts=ev.cv(cfg, ev.points).log_hypers)
    return m.save(out, provenance=prep.provenance)
