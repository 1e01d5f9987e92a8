"""One diagnosis's cross-validations: each model configuration held out once per scheme, reused
by every step that needs it (`Evaluator`).

    ev = Evaluator(problem, folds=5, seed=0)
    cv = ev.cv(Config(("geometric",), "joints"), ev.points)      # a CvResult, memoised
    ev.rms_mm(cfg, ev.deploy)                                        # its held-out 3D RMS
"""
from __future__ import annotations

from concurrent.futures import as_completed
from dataclasses import dataclass, field, replace

import numpy as np

from dt_runtime.analysis import parallel, validation
from dt_runtime.analysis.crossval import CvResult, cross_validate, fit_hypers
from dt_runtime.frames.kinematics import Chain
from dt_runtime.metrology.stats import finite_rows, rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.gp import GPOptions
from dt_runtime.models.hybrid import DEFAULT_RIDGE, HybridModel

GP_LABEL = {"tcp_speed": "GP(TCP, v)", "tcp": "GP(TCP)", "joints": "GP(joints)", "none": "no GP"}


@dataclass(frozen=True)
class Config:
    """A model configuration: effect terms, the GP's inputs and session nuisance terms."""

    effects: tuple[str, ...] = ()
    gp_inputs: str = "tcp_speed"
    nuisance: tuple[str, ...] = ()

    def label(self) -> str:
        """The configuration in words, e.g. "geometric + GP(TCP, v) [session tool]".

        Returns
        -------
        str
        """
        parts = [*self.effects, GP_LABEL[self.gp_inputs]]
        text = " + ".join(parts)
        return text + (f" [session {', '.join(self.nuisance)}]" if self.nuisance else "")

    def plus(self, effect: str) -> Config:
        """This configuration with one more effect.

        Parameters
        ----------
        effect : str
            The effect's name.

        Returns
        -------
        Config
        """
        return replace(self, effects=(*self.effects, effect))

    def to_dict(self) -> dict:
        """The configuration as a JSON-ready dict (`of` reads it back)."""
        return {"effects": list(self.effects), "gp_inputs": self.gp_inputs, "session_terms": list(self.nuisance)}

    @classmethod
    def of(cls, d: dict) -> Config:
        """The configuration of `to_dict`'s dict (a step's `config`).

        Parameters
        ----------
        d : dict
            From `to_dict`.

        Returns
        -------
        Config
        """
        return cls(tuple(d["effects"]), d["gp_inputs"], tuple(d["session_terms"]))


@dataclass
class Problem:
    """What a diagnosis works on: rows in time order, SI units."""

    inp: fx.Inputs
    error: np.ndarray  # (n, 3) m
    groups: np.ndarray  # target point of each row
    chain: Chain | None
    session: np.ndarray | None = None  # session index per row (None: one session)
    measured: np.ndarray | None = None  # robot-frame measured points (re-registration)
    refit_sessions: set[int] = field(default_factory=set)  # sessions whose registration was fitted on their rows
    gp_options: GPOptions | None = None
    ridge: float = DEFAULT_RIDGE
    reference_session: int = 0
    # The effects the names refer to (the call's: --effects-file's, a loaded model's own), pickled
    # with the problem to the pool's workers (analysis.parallel), which register nothing.
    catalogue: fx.Catalogue = field(default_factory=fx.default)

    @property
    def n(self) -> int:
        """Number of rows."""
        return int(self.inp.n)


class Evaluator:
    """Cross-validations of configurations on the problem's schemes, memoised; with a `pool`
    (analysis.parallel), `cv_many` runs the missing ones in its worker processes.

    The GP hyperparameters of a configuration are fitted once on all rows (its first
    cross-validation, warm-started from the configuration it extends) and kept fixed in every fold
    of every scheme: a few smoothness and noise numbers see the held-out rows, no row's error does.
    """

    def __init__(self, problem: Problem, folds: int = 5, seed: int = 0, pool=None):
        self.problem = problem
        self.seed = seed
        self.pool = pool
        p = problem
        self.points = validation.points(p.groups, folds, seed)
        self.deploy = validation.deployment(p.inp.commanded, p.groups, p.session, folds, seed)
        self.time = (validation.forward(p.inp.t, p.n, folds) if p.session is None and p.inp.t is not None
                     else self.deploy)
        self._cv: dict[tuple[Config, str], CvResult] = {}
        self._thetas: dict[Config, list] = {}
        self._log_hypers: dict[Config, list | None] = {}

    def scheme(self, kind: str) -> validation.Scheme:
        """The validation scheme of a kind.

        Parameters
        ----------
        kind : str
            "points", the deployment scheme's kind, or the time scheme's ("forward").

        Returns
        -------
        validation.Scheme
        """
        return {s.kind: s for s in (self.time, self.deploy, self.points)}[kind]

    def model(self, cfg: Config) -> HybridModel:
        """An unfitted model of the configuration on this problem's robot, ridge and GP options.

        Parameters
        ----------
        cfg : Config
            The configuration.

        Returns
        -------
        HybridModel
        """
        p = self.problem
        return HybridModel(cfg.effects, cfg.gp_inputs, ridge=p.ridge, seed=self.seed, robot=p.chain,
                           gp_options=p.gp_options, nuisance=cfg.nuisance, reference_session=p.reference_session,
                           catalogue=p.catalogue)

    def scheme_for(self, change: str | None) -> validation.Scheme:
        """The deployment scheme a change is judged on: a forecast (later times) for a time-dependent
        effect.

        Parameters
        ----------
        change : str or None
            The changed effect's name.

        Returns
        -------
        validation.Scheme
        """
        cat = self.problem.catalogue
        if change and change in cat.names() and ({"time", "temperature"} & set(cat.get(change).drives())):
            return self.time
        return self.deploy

    def compute(self, cfg: Config, scheme: validation.Scheme, starts=None, thetas=None) -> CvResult:
        """One cross-validation, not memoised: `thetas` fixed GP hyperparameters, else fitted on all
        rows from `starts`.

        Parameters
        ----------
        cfg : Config
            The configuration.
        scheme : validation.Scheme
            The folds.
        starts : list, optional
            Warm starts.
        thetas : list, optional
            Fixed GP hyperparameters.

        Returns
        -------
        CvResult
        """
        p = self.problem
        return cross_validate(self.model(cfg), p.inp, p.error, p.groups, scheme.splits(), thetas=thetas,
                              starts=None if thetas is not None else starts)

    def hypers(self, cfg: Config, starts=None):
        """The GP hyperparameters `compute` fits on all rows when not given them, (thetas,
        log_hypers) per axis, or (None, None) without a GP; not memoised.

        Parameters
        ----------
        cfg : Config
            The configuration.
        starts : list, optional
            Warm starts.

        Returns
        -------
        tuple
        """
        p = self.problem
        return fit_hypers(self.model(cfg), p.inp, p.error, starts)

    def _store(self, cfg: Config, scheme: validation.Scheme, res: CvResult, fixed) -> CvResult:
        if fixed is None and res.thetas is not None:
            self._thetas[cfg], self._log_hypers[cfg] = res.thetas, res.log_hypers
        res.log_hypers = self._log_hypers.get(cfg)
        self._cv[(cfg, scheme.kind)] = res
        return res

    def cv(self, cfg: Config, scheme: validation.Scheme, starts=None) -> CvResult:
        """`cfg` held out on `scheme` (memoised). `starts`: warm starts of its GP hyperparameter fit
        (the log hyperparameters of the configuration it extends), used by its first cross-validation.

        Parameters
        ----------
        cfg : Config
            The configuration.
        scheme : validation.Scheme
            The folds.
        starts : list, optional
            Warm starts.

        Returns
        -------
        CvResult
        """
        key = (cfg, scheme.kind)
        if key not in self._cv:
            fixed = self._thetas.get(cfg)
            self._store(cfg, scheme, self.compute(cfg, scheme, starts, fixed), fixed)
        return self._cv[key]

    def cv_many(self, jobs: list[tuple[Config, validation.Scheme, list | None]]) -> list[CvResult]:
        """Several cross-validations (cfg, scheme, starts), the missing ones at once in the pool's
        workers when there is a pool.

        Parameters
        ----------
        jobs : list of (Config, Scheme, list or None)
            The cross-validations.

        Returns
        -------
        list of CvResult
        """
        todo = list(dict.fromkeys((cfg, scheme.kind) for cfg, scheme, _ in jobs if (cfg, scheme.kind) not in self._cv))
        if self.pool is not None and len(todo) > 1:
            self._run_in_pool(todo, {(cfg, scheme.kind): st for cfg, scheme, st in jobs})
        return [self.cv(cfg, scheme, st) for cfg, scheme, st in jobs]

    def _run_in_pool(self, todo: list[tuple[Config, str]], starts: dict) -> None:
        """The cross-validations `todo` in the pool's workers. A configuration wanted on several
        schemes whose hyperparameters are not known yet has them fitted once, in one task, and its
        cross-validations sent with them fixed as soon as they are there: sent at once, every
        worker fitted the same hyperparameters again (the same numbers, the most expensive part).
        The other cross-validations run meanwhile."""
        assert self.pool is not None
        n_schemes: dict[Config, int] = {}
        for cfg, _ in todo:
            n_schemes[cfg] = n_schemes.get(cfg, 0) + 1
        shared = {cfg for cfg, k in n_schemes.items()
                  if k > 1 and cfg not in self._thetas and cfg.gp_inputs != "none"}
        first = {cfg: starts[(cfg, kind)] for cfg, kind in reversed(todo)}  # cv's: its first job's starts
        fits = {self.pool.submit(parallel.hypers, (cfg, first[cfg])): cfg for cfg in dict.fromkeys(
            c for c, _ in todo if c in shared)}
        sent = {}
        for cfg, kind in todo:
            if cfg not in shared:
                fixed = self._thetas.get(cfg)
                sent[(cfg, kind)] = (self.pool.submit(parallel.cross_validation,
                                                      (cfg, kind, starts[(cfg, kind)], fixed)), fixed)
        for fut in as_completed(fits):
            cfg = fits[fut]
            self._thetas[cfg], self._log_hypers[cfg] = fut.result()
            for c, kind in todo:
                if c == cfg:
                    sent[(c, kind)] = (self.pool.submit(parallel.cross_validation,
                                                        (c, kind, None, self._thetas[c])), self._thetas[c])
        for cfg, kind in todo:
            fut, fixed = sent[(cfg, kind)]
            self._store(cfg, self.scheme(kind), fut.result(), fixed)

    def residual(self, cfg: Config, scheme: validation.Scheme) -> np.ndarray:
        """`cfg`'s held-out residual on `scheme`; held-out sessions scored the way a new session
        is (re-registered where fitted, its session terms measured again: analysis.sessions).

        Parameters
        ----------
        cfg : Config
            The configuration.
        scheme : validation.Scheme
            The folds.

        Returns
        -------
        ndarray
            (n, 3), m.
        """
        res = self.cv(cfg, scheme).residual
        if scheme.kind == "sessions" and (self.problem.refit_sessions or cfg.nuisance):
            from dt_runtime.analysis.sessions import absorbed

            return absorbed(self, cfg, res)[0]
        return res

    def rms_mm(self, cfg: Config, scheme: validation.Scheme) -> float:
        """The held-out 3D RMS (mm) over the rows the scheme predicts (a forecast never predicts
        its first block).

        Parameters
        ----------
        cfg : Config
            The configuration.
        scheme : validation.Scheme
            The folds.

        Returns
        -------
        float
        """
        r = self.residual(cfg, scheme)
        return rms3(r[finite_rows(r)]) * 1e3
