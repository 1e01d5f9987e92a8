"""`dt diagnose --auto`: forward selection over the effects, the session terms and the GP's
inputs, judged the way the twin will be used (`select`; docs/cli.md, "dt diagnose").
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from dt_runtime.analysis import confounding
from dt_runtime.analysis.change import Change
from dt_runtime.analysis.evaluation import Config, Evaluator
from dt_runtime.analysis.ranking import ALPHA, changed, deployment_figures, gp_alternatives, paired_gain, rank
from dt_runtime.analysis.results import Gain
from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.common.progress import Progress
from dt_runtime.metrology.stats import rms3

FLOOR_STOP = 1.05  # a held-out RMS within this factor of the noise floor: nothing left to find
MAX_RIVALS = 2  # qualifying effects tested head to head against the best one, at most


@dataclass
class Step:
    """One step: the model before it, its held-out figures (by point and on the deployment scheme),
    what was added and its evidence, what qualified but was not taken, and head-to-head tests."""

    model: str
    config: dict
    rmse_mm: float  # held out by point
    u_rmse_mm: float  # standard uncertainty of that RMS (from the spread over held-out points)
    deploy_rmse_mm: float  # held out on the deployment scheme (deploy_kind)
    deploy_kind: str
    change: Change | None  # shown as "+backlash", "GP -> joints", "+session tool"; None on the last step
    p_value: float | None
    explained_fraction: float | None
    alpha: float  # the step's significance level (alpha / number of changes tested)
    change_deploy_kind: str | None = None  # the scheme the change was judged on (a forecast for a time term)
    change_deploy_rmse_mm: tuple[float, float] | None = None  # that figure before and after the change
    follows: str | None = None  # what the residual followed, for an added effect (Effect.factor)
    rejected: list[dict] = field(default_factory=list)
    head_to_head: list[dict] = field(default_factory=list)
    together: dict | None = None  # a change vetoed alone, taken with the next one (`_pair`)

    def to_dict(self) -> dict:
        """The step as JSON: the change as its label (the `change` key's strings)."""
        return jsonable({**self.__dict__, "change": None if self.change is None else self.change.label()})


@dataclass
class Selection:
    """The loop's steps, the final configuration, why it stopped, the candidates it could not test
    and the session terms found.
    """
    steps: list[Step]
    final: Config
    stop_reason: str  # "floor", "nothing passes", "max steps"
    not_testable: list[dict]
    session_terms: list[Gain] = field(default_factory=list)


def _rms_u(res_mse: np.ndarray) -> float:
    """Standard uncertainty of the held-out RMS from the per-group mean squares (delta method)."""
    m = float(np.mean(res_mse))
    if len(res_mse) < 2 or m <= 0:
        return float("nan")
    return float(np.std(res_mse, ddof=1) / np.sqrt(len(res_mse)) / (2 * np.sqrt(m)))


def _change(g: Gain) -> Change:
    return Change("session" if g.kind == "session" else "effect" if g.kind == "effect" else "gp_inputs", g.candidate)


def testable(ev: Evaluator, candidates: list[str]) -> tuple[list[str], list[dict]]:
    """The candidates the data allow and can separate from the pose, and the others with why.

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    candidates : list of str
        Effect names.

    Returns
    -------
    testable : list of str
    not_testable : list of dict
    """
    p = ev.problem
    cat = p.catalogue
    allowed = cat.available(p.inp, p.chain)
    out, skipped = [], []
    for c in candidates:
        if c not in allowed:
            skipped.append({"candidate": c, "reason": "columns", "needs": list(cat.get(c).reads(p.chain)),
                            "needs_chain": cat.get(c).needs_chain and p.chain is None})
    ok = [c for c in candidates if c in allowed]
    findings = confounding.check(ok, p.inp, p.groups, cat)
    bad = {f.candidate for f in findings if not f.testable}
    for c in ok:
        if c in bad:
            skipped.append({"candidate": c, "reason": "confounded",
                            "findings": [f.to_dict() for f in findings if f.candidate == c and not f.testable]})
        else:
            out.append(c)
    return out, skipped


def _scheme(ev: Evaluator, *effects: str):
    """The deployment scheme two rivals are compared on: a forecast when either reads time."""
    schemes = [ev.scheme_for(e) for e in effects]
    return next((sc for sc in schemes if sc is not ev.deploy), ev.deploy)


def _verdict(p_b_beyond_a: float, p_a_beyond_b: float, level: float) -> str:
    if p_b_beyond_a < level <= p_a_beyond_b:
        return "b"
    if p_a_beyond_b < level <= p_b_beyond_a:
        return "a"
    return "both" if p_a_beyond_b < level and p_b_beyond_a < level else "neither"


def _duel(ev: Evaluator, cfg: Config, a: str, b: str, factor: str, level: float) -> dict:
    """Two rivals not yet in `cfg`, in both orders: the model with both against each with one,
    paired per held-out point (does b explain what a leaves? does a explain what b leaves?), and
    each alone on the deployment scheme. The data prefer the one the other adds nothing to; when
    the points cannot tell ('both' real or 'neither' separable), the lower deployment RMS decides.
    The points decide first: on held-out regions a rival can extrapolate better only because a
    third effect is still missing (backlash against dynamic before geometric is in: dynamic 0.182,
    backlash 0.208 mm on regions, while by point backlash explains what dynamic leaves and not the
    reverse); each later step drops the one the model no longer needs (`_removable`)."""
    ca, cb = cfg.plus(a), cfg.plus(b)
    cva, cvb = ev.cv(ca, ev.points), ev.cv(cb, ev.points)
    both = ev.cv(ca.plus(b), ev.points, starts=cva.log_hypers)
    p_b_beyond_a, p_a_beyond_b = paired_gain(cva, both)[0], paired_gain(cvb, both)[0]
    scheme = _scheme(ev, a, b)
    dep_a, dep_b = ev.rms_mm(ca, scheme), ev.rms_mm(cb, scheme)
    v = _verdict(p_b_beyond_a, p_a_beyond_b, level)
    preferred = {"a": a, "b": b}.get(v, v)
    first = preferred if preferred in (a, b) else (a if dep_a <= dep_b else b)
    return {"a": a, "b": b, "factor": factor, "p_b_beyond_a": p_b_beyond_a, "p_a_beyond_b": p_a_beyond_b,
            "rmse_a_mm": rms3(cva.residual) * 1e3, "rmse_b_mm": rms3(cvb.residual) * 1e3,
            "deploy_kind": scheme.kind, "deploy_rmse_a_mm": dep_a, "deploy_rmse_b_mm": dep_b,
            "preferred": preferred, "winner": first, "loser": b if first == a else a}


def _rivals(ev: Evaluator, top: str, names) -> list[tuple[str, str]]:
    """The candidates among `names` that read a factor `top` reads, with that factor."""
    p = ev.problem
    out = []
    for name in names:
        if name != top and (shared := confounding.competing(top, name, p.inp, p.catalogue)) is not None:
            out.append((name, shared))
    return out


def head_to_head(ev: Evaluator, cfg: Config, ok: list[Gain], level: float,
                 tested: Sequence[Gain] = ()) -> tuple[list[Gain], list[dict]]:
    """The best qualifying effect met by every tested effect that reads the same factor (qualifying
    or not: a rival that explains the residual only partly alone may still be the cause), in both
    orders (`_duel`). Returns the qualifying list with the preferred one first, and the duels.

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    cfg : Config
        The configuration.
    ok : list of Gain
        The qualifying gains, best first.
    level : float
        The step's significance level.
    tested : sequence of Gain, optional
        Every gain tested in the step.

    Returns
    -------
    ok : list of Gain
    duels : list of dict
    """
    if not ok or ok[0].kind != "effect":
        return ok, []
    top = ok[0]
    pool = {g.candidate: g for g in [*ok, *tested] if g.kind == "effect" and g.rmse_after_mm < g.rmse_before_mm}
    records = []
    for rival, shared in _rivals(ev, top.candidate, list(pool))[:MAX_RIVALS]:
        rec = _duel(ev, cfg, top.candidate, rival, shared, level)
        records.append(rec)
        # a rival that did not qualify alone is not taken in its place (its own test failed); when
        # it is the cause, a later step adds it and drops the top one (`_removable`)
        if rec["winner"] == rival and any(g.candidate == rival for g in ok):
            ok = [pool[rival]] + [g for g in ok if g.candidate != rival]
            break
    return ok, records


def _removable(ev: Evaluator, start: Config, cfg: Config, alpha: float, protect: str | None = None):
    """The weakest effect the loop added that the current model no longer needs: it lowers the
    error of `cfg` by point no more than chance (p >= alpha / number added) and the model without it
    is no worse on its deployment scheme (a rival added later explains what it explained). Returns
    (effect, model without it, p) or None; `protect`: the effect just added (never removed at once)."""
    added = [e for e in cfg.effects if e not in start.effects and e != protect]
    if not added:
        return None
    level = alpha / len(added)
    cur = ev.cv(cfg, ev.points)
    fewer = [Config(tuple(x for x in cfg.effects if x != e), cfg.gp_inputs, cfg.nuisance) for e in added]
    results = ev.cv_many([(f, ev.points, cur.log_hypers) for f in fewer])
    effect, without, res = max(zip(added, fewer, results), key=lambda t: paired_gain(t[2], cur)[0])
    p = paired_gain(res, cur)[0]
    scheme = ev.scheme_for(effect)
    if p < level or ev.rms_mm(without, scheme) > ev.rms_mm(cfg, scheme):
        return None
    return effect, without, p


def _choose(ev: Evaluator, cfg: Config, base, tested: list[Gain], level: float, min_explained: float,
            step: Step, vetoed: list[Gain]) -> Gain | None:
    """The change a step takes among `tested`: the one explaining most held-out variance whose p is
    below `level`, that explains at least `min_explained` and lowers the RMS by point, after rival
    effects met head to head, and that also lowers the RMS on its deployment scheme (a session term,
    never deployed, needs only the points). Records rejections and head-to-head tests on `step`;
    the qualifying changes the deployment scheme vetoed are appended to `vetoed`."""
    ok = sorted([g for g in tested if g.p_value < level and g.explained_fraction >= min_explained
                 and g.rmse_after_mm < g.rmse_before_mm], key=lambda g: -g.explained_fraction)
    ok, h2h = head_to_head(ev, cfg, ok, level, tested)
    step.head_to_head += h2h
    # the deployment figures the veto below will most likely need, at once
    ev.cv_many([(changed(cfg, g.kind, g.candidate), ev.scheme_for(g.candidate if g.kind == "effect" else None),
                 base.log_hypers if g.kind != "gp_inputs" else None) for g in ok[:2] if g.kind != "session"])
    for g in ok:
        if g.kind == "session":  # a nuisance is never deployed: its evidence is the held-out points
            return g
        deployment_figures(ev, cfg, g)
        if g.deploys:
            return g
        vetoed.append(g)
        step.rejected.append({"change": _change(g).label(), "reason": "deployment", "p_value": g.p_value,
                              "explained_fraction": g.explained_fraction, "deploy_kind": g.deploy_kind,
                              "deploy_rmse_before_mm": g.deploy_rmse_before_mm,
                              "deploy_rmse_after_mm": g.deploy_rmse_after_mm})
    return None


def _pair(ev: Evaluator, cfg: Config, base, vetoed: list[Gain], tested: Sequence[Gain], level: float,
          step: Step) -> tuple[Gain, Gain] | None:
    """When every qualifying effect was vetoed on the deployment scheme: one of them may hold only
    together with another effect (a geometric term fitted while backlash is left out bends to it and
    extrapolates badly; with backlash it holds). Each vetoed effect g is tried with each other tested
    effect h: the pair is taken when h lowers the error of cfg + g significantly by point and
    cfg + g + h lowers the deployment RMS below cfg's. The best such pair by the deployment RMS, as
    (g, h's gain beyond cfg + g), or None. Recorded on `step` (`together`)."""
    effects = [g.candidate for g in tested if g.kind == "effect"]
    pairs = [(g.candidate, h) for g in vetoed if g.kind == "effect" for h in effects if h != g.candidate]
    if not pairs:
        return None
    jobs = [(cfg.plus(a).plus(b), ev.points, base.log_hypers) for a, b in pairs]
    jobs += [(cfg.plus(a).plus(b), _scheme(ev, a, b), base.log_hypers) for a, b in pairs]
    ev.cv_many(jobs)
    best = None
    for a, b in pairs:
        one, two = ev.cv(cfg.plus(a), ev.points), ev.cv(cfg.plus(a).plus(b), ev.points)
        p_b, after = paired_gain(one, two)
        scheme = _scheme(ev, a, b)
        dep_before, dep_after = ev.rms_mm(cfg, scheme), ev.rms_mm(cfg.plus(a).plus(b), scheme)
        if p_b < level and dep_after < dep_before and (best is None or dep_after < best[2]):
            before = rms3(one.residual)
            gain_b = Gain("effect", b, float(1 - (after / before) ** 2), p_b, before * 1e3, after * 1e3, True)
            gain_b.factor = ev.problem.catalogue.get(b).factor
            gain_b.deploy_kind, gain_b.deploy_rmse_before_mm = scheme.kind, dep_before
            gain_b.deploy_rmse_after_mm = dep_after
            best = (a, gain_b, dep_after)
    if best is None:
        return None
    g = next(x for x in vetoed if x.candidate == best[0])
    step.together = {"first": _change(g).label(), "with": _change(best[1]).label(), "p_with": best[1].p_value,
                     "deploy_kind": best[1].deploy_kind, "deploy_rmse_before_mm": best[1].deploy_rmse_before_mm,
                     "deploy_rmse_after_mm": best[1].deploy_rmse_after_mm}
    return g, best[1]


def select(ev: Evaluator, start: Config, candidates: tuple[str, ...] | None, alpha: float = ALPHA,
           min_explained: float = 0.02, max_steps: int = 10, floor_m: float | None = None,
           progress: Progress | None = None) -> Selection:
    """Forward selection from `start`, judged the way the twin will be used.

    Each step:

    1. Candidates the campaign cannot separate from the pose are not tested (analysis.confounding:
       a time-dependent effect in a scan, one speed for a speed effect, ...); they are reported
       with what would make them testable.
    2. Every effect and session term not yet in the model is held out by point (analysis.ranking):
       it qualifies when its one-sided p is below alpha / m (m: every change the step may test, the
       GP's inputs included; Bonferroni), it explains at least `min_explained` of the held-out
       variance and lowers the held-out RMS.
    3. The best qualifying effect meets every tested effect that reads the same factor (backlash
       and dynamic both read the direction of travel; thermal and drift when the temperature
       followed time) head to head, in both orders: the model with both against each with one, by
       point, and each alone on the deployment scheme; the one the data prefer goes first (`_duel`).
    4. The best qualifying change is taken only if it also lowers the held-out RMS on the
       deployment scheme (held-out regions, held-out sessions, or a forecast of later times for a
       time-dependent term: analysis.validation); otherwise the next qualifying one is tried. So the
       final model is never worse than its predecessor on the deployment figures. A session term
       is a nuisance (never deployed): the points decide it.
    5. Only when no effect or session term passes are the GP's other inputs tested (the same
       rules): physics first, the GP, which takes up anything, last (UR10 Series D: switching first
       left backlash out, 0.280 instead of 0.276 mm).

    Before adding, each step drops an effect an earlier step added that the model no longer needs
    (a rival added later explains it: `_removable`). The loop stops when the held-out residual is
    at the noise floor, or when no change passes; a backward pass (`prune`) then removes what the
    final model no longer needs.

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    start : Config
        The starting configuration.
    candidates : tuple of str or None
        The effects to try; None: every effect of the problem's catalogue.
    alpha : float, optional
        Family-wise significance level of a step.
    min_explained : float, optional
        Least fraction of the held-out variance a change must explain.
    max_steps : int, optional
        At most this many steps.
    floor_m : float, optional
        The noise floor, m: the loop stops when the held-out residual reaches it.
    progress : Progress, optional
        Where the steps report their progress.

    Returns
    -------
    Selection
    """
    p = ev.problem
    cfg = start
    steps: list[Step] = []
    names = list(candidates or p.catalogue.names())
    cands, not_testable = testable(ev, names)
    session_gains: list[Gain] = []
    terms: list[str] = []
    if p.session is not None:
        from dt_runtime.analysis.sessions import available_terms

        if p.refit_sessions and "base" not in cfg.nuisance:
            # Each session's registration was fitted on its own points: its rigid part is the
            # registration's by construction (a set-up term, not a finding), tested no further.
            cfg = Config(cfg.effects, cfg.gp_inputs, (*cfg.nuisance, "base"))
        terms = [t for t in available_terms(ev) if t not in cfg.nuisance]
    stop = "max steps"
    just_added: str | None = None
    forced: Gain | None = None
    for k in range(max_steps + 1):
        if progress:
            progress.note(f"diagnose --auto: step {len(steps) + 1}: {cfg.label()}")
        base = ev.cv(cfg, ev.points)
        before_mm = rms3(base.residual) * 1e3
        step = Step(cfg.label(), cfg.to_dict(), before_mm, _rms_u(base.group_mse) * 1e3, ev.rms_mm(cfg, ev.deploy),
                    ev.deploy.kind, None, None, None, alpha)
        steps.append(step)
        if floor_m is not None and before_mm <= FLOOR_STOP * floor_m * 1e3:
            stop = "floor"
            break
        if k == max_steps:
            break
        # What the last change made redundant goes first (a rival that now explains nothing more)
        if k and forced is None and (gone := _removable(ev, start, cfg, alpha, protect=just_added)) is not None:
            effect, without, p_rm = gone
            _removal(ev, step, cfg, without, effect, p_rm)
            cfg, just_added = without, None
            continue
        todo = [c for c in cands if c not in cfg.effects]
        alts = gp_alternatives(p.inp, cfg.gp_inputs)
        sess_todo = [t for t in terms if t not in cfg.nuisance]
        # Bonferroni over every change the step may test (the GP's inputs included, tested last)
        level = alpha / max(len(todo) + len(sess_todo) + len(alts), 1)
        step.alpha = level
        # Physical terms first: the GP's inputs change only when no effect or session term passes
        # (the GP is the catch-all; an effect is physics that holds beyond the data).
        chosen: Gain | None
        if forced is not None:  # the second of a pair that holds only together (`_pair`)
            chosen, forced = forced, None
        else:
            eff, _, sess = rank(ev, cfg, todo, [], progress, session_terms=sess_todo)
            session_gains = sess or session_gains
            vetoed: list[Gain] = []
            chosen = _choose(ev, cfg, base, eff + sess, level, min_explained, step, vetoed)
            if chosen is None and (pair := _pair(ev, cfg, base, vetoed, eff, level, step)) is not None:
                chosen, forced = pair
            if chosen is None and alts:
                _, gps, _ = rank(ev, cfg, [], alts, progress)
                chosen = _choose(ev, cfg, base, gps, level, min_explained, step, [])
        if chosen is None:
            stop = "nothing passes"
            break
        step.change, step.p_value, step.explained_fraction = _change(chosen), chosen.p_value, chosen.explained_fraction
        step.follows = chosen.factor
        if chosen.deploy_rmse_before_mm is not None and chosen.deploy_rmse_after_mm is not None:
            step.change_deploy_kind = chosen.deploy_kind
            step.change_deploy_rmse_mm = (chosen.deploy_rmse_before_mm, chosen.deploy_rmse_after_mm)
        cfg = changed(cfg, chosen.kind, chosen.candidate)
        just_added = chosen.candidate if chosen.kind == "effect" else None
    cfg = prune(ev, start, cfg, steps, alpha)
    return Selection(steps, cfg, stop, not_testable, session_gains)


def _removal(ev: Evaluator, step: Step, cfg: Config, without: Config, effect: str, p: float) -> None:
    """Record on `step` (the model `cfg`) the removal of `effect`."""
    scheme = ev.scheme_for(effect)
    step.change, step.p_value, step.follows = Change("remove", effect), p, None
    step.explained_fraction = float(1 - (step.rmse_mm / ev.rms_mm(without, ev.points)) ** 2)
    step.change_deploy_kind = scheme.kind
    step.change_deploy_rmse_mm = (ev.rms_mm(cfg, scheme), ev.rms_mm(without, scheme))


def prune(ev: Evaluator, start: Config, cfg: Config, steps: list[Step], alpha: float) -> Config:
    """The backward pass: an effect the loop added can be redundant once later changes are in (a
    thermal term taken before the GP moved to the joint angles, which then carry the same error; a
    rival of an effect added later). Each added effect is tested again against the final model
    without it (`_removable`); removals are steps too ("-thermal"), one at a time, weakest first.

    Parameters
    ----------
    ev : Evaluator
        The problem and its memoised cross-validations.
    start : Config
        The loop's start.
    cfg : Config
        The configuration.
    steps : list of Step
        The steps so far (removals are appended).
    alpha : float
        Significance level.

    Returns
    -------
    Config
    """
    while (gone := _removable(ev, start, cfg, alpha)) is not None:
        effect, without, p = gone
        _removal(ev, steps[-1], cfg, without, effect, p)
        cfg = without
        base = ev.cv(cfg, ev.points)
        steps.append(Step(cfg.label(), cfg.to_dict(), rms3(base.residual) * 1e3, _rms_u(base.group_mse) * 1e3,
                          ev.rms_mm(cfg, ev.deploy), ev.deploy.kind, None, None, None, alpha))
    return cfg
