"""Hybrid error model: error = sum of physical effect terms + GP on what is left (`HybridModel`).

A scikit-learn regressor (docs/library.md, docs/effects.md)::

    model = HybridModel(effects=("geometric", "backlash"), robot="configs/robots/cobot_hc20_like.yaml")
    model.fit(dataset)                      # y defaults to dataset.error (rows in time order)
    e_hat, u = model.predict(dataset, return_std=True)
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import optimize
from sklearn.base import BaseEstimator, RegressorMixin

from dt_kernel.errors import ConfigError, DataError, ModelError
from dt_runtime.common.provenance import Environment, Provenance
from dt_runtime.common.provenance import build as build_provenance
from dt_runtime.common.safe_npz import load_npz
from dt_runtime.common.threads import blas_limited
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models import effects as fx
from dt_runtime.models import hyper as hp
from dt_runtime.models import identifiability as idf
from dt_runtime.models.effects import as_inputs
from dt_runtime.models.effects import session as session_terms
from dt_runtime.models.effects.thermal import lagged
from dt_runtime.models.gp import GPOptions, MultiOutputGP
from dt_runtime.models.modelio import read_meta

FORMAT_VERSION = 1
GP_INPUTS = ("tcp_speed", "tcp", "joints", "none")
DEFAULT_RIDGE = 1e-4


def gp_features(inp: fx.Inputs, kind: str) -> np.ndarray | None:
    """The GP's input columns for one choice of inputs.

    Parameters
    ----------
    inp : Inputs
        The data's columns.
    kind : str
        One of GP_INPUTS ('tcp_speed' falls back to 'tcp' without a speed column).

    Returns
    -------
    ndarray or None
        (n, d); None for 'none'.

    Raises
    ------
    DataError
        For 'joints' without joint columns, or an unknown kind.
    """
    if kind == "none":
        return None
    if kind == "joints":
        if inp.joints is None:
            raise DataError("GP inputs 'joints' need joint angle columns q1..q6")
        return inp.joints
    if kind == "tcp_speed" and inp.speed is not None:
        return np.column_stack([inp.commanded, inp.speed])
    if kind in ("tcp", "tcp_speed"):
        return inp.commanded
    raise DataError(f"unknown GP inputs '{kind}'; allowed: {', '.join(GP_INPUTS)}")


def robot_ref(robot: str | Path | None) -> str | None:
    """How a saved model names its robot (`frames.robots`): a catalogue name, a config or URDF
    path (relative to configs/ when shipped there), with its '#link' and '?tool_mm=' if any.

    Parameters
    ----------
    robot : str, Path or None
        The robot as given.

    Returns
    -------
    str or None
    """
    return robots.reference(robot)


def load_chain(ref: str) -> Chain:
    """The kinematic chain of a robot reference (robot_ref), parsed once per process.

    Parameters
    ----------
    ref : str
        A robot reference.

    Returns
    -------
    Chain
    """
    return robots.load(ref)


def resolve_chain(robot: str | Path | Chain | None) -> Chain | None:
    """The kinematic chain a model's `robot` parameter gives: a robot reference or a Chain.

    Parameters
    ----------
    robot : str, Path, Chain or None
        The model's `robot`.

    Returns
    -------
    Chain or None

    Raises
    ------
    ModelError
        When the reference no longer resolves.
    """
    if robot is None or isinstance(robot, Chain):
        return robot
    try:
        return load_chain(str(robot))
    except DataError as exc:  # a saved model's robot that is gone: the model cannot be evaluated
        raise ModelError(f"robot config {robot}: {exc}") from exc


@dataclass(frozen=True)
class Design:
    """The effect terms' regressors on some rows: A (n, 3, p) with e = A theta, and each
    parameter's (effect, name, unit, report) ('inverse': reported as 1/x, e.g. stiffness)."""

    A: np.ndarray
    params: tuple[tuple[str, str, str, str], ...]
    nonnegative: np.ndarray | None = None  # (p,) bool: the parameters physics wants >= 0
    # The effects' nonlinear parameters the regressors were built with ({effect: {name: Estimate}},
    # models.hyper), e.g. the thermal lag.
    hyper: dict | None = None
    # The sessions the nuisance terms have parameters for (models.effects.session).
    sessions: tuple[int, ...] = ()

    def rows(self, mask) -> Design:
        """The design on the rows `mask` selects.

        Parameters
        ----------
        mask : array-like
            Boolean mask or indices of rows.

        Returns
        -------
        Design
        """
        return Design(self.A[mask], self.params, self.nonnegative, self.hyper, self.sessions)


class HybridModel(RegressorMixin, BaseEstimator):
    """error = sum of effect terms (dt_runtime.models.effects) + GP on what is left.

    The effect parameters are estimated jointly by ridge-regularised least squares on
    standardised columns (the complete geometric set is rank deficient on purpose), with their
    standard uncertainties from the residual scatter. A GP (dt_runtime.models.gp) then models the
    residual on configurable inputs: 'tcp_speed' (the paper's Cartesian TCP and speed), 'tcp',
    'joints', or 'none'; with a GP, the effect parameters are estimated again by generalised
    least squares under its covariance (universal kriging, `_gls`) and the GP refitted on what
    they leave, its hyperparameters kept. What the data determine is reported as base parameters
    (the identifiable combinations, `base_parameters`), what they cannot per parameter
    (`models.identifiability`); widths and compliances are kept >= 0. scikit-learn's estimator
    contract: `__init__` only stores its arguments, `fit` validates them and returns self,
    learned attributes end in `_`.

    effects: effect names (`effects.names()`); gp_inputs: one of GP_INPUTS; ridge: penalty on
    the standardised effect parameters; seed: the GP's optimiser starts; robot: a robot reference
    (a catalogue name such as 'ur5e', a robot config YAML or a URDF: `frames.robots`) or a `Chain`,
    the kinematic model the joint-space effects need; gp_options: `GPOptions` (default:
    MultiOutputGP's defaults); nuisance: session terms (models.effects.session: 'tool', 'base',
    'joints') fitted per session of the training data (the `session` column) and never deployed:
    rows without a session, or of the `reference_session`, get none, so the map predicts the
    reference session's robot; catalogue: the effects the names refer to (`effects.Catalogue`;
    None: the default one, the catalogue and the installed plugins; a loaded model's carries its
    declared effects).
    """

    def __init__(self, effects: tuple[str, ...] = (), gp_inputs: str = "tcp_speed", ridge: float = DEFAULT_RIDGE,
                 seed: int = 0, robot: str | Path | Chain | None = None, gp_options: GPOptions | None = None,
                 nuisance: tuple[str, ...] = (), reference_session: int = 0, catalogue: fx.Catalogue | None = None):
        self.effects = effects
        self.gp_inputs = gp_inputs
        self.ridge = ridge
        self.seed = seed
        self.robot = robot
        self.gp_options = gp_options
        self.nuisance = nuisance
        self.reference_session = reference_session
        self.catalogue = catalogue

    def effects_catalogue(self) -> fx.Catalogue:
        """The catalogue the effect names refer to: `catalogue`; else, fitted, the default one
        read at fit (`catalogue_`: a deployed map does not scan the plugins' entry points per
        prediction); else the default one read now (`effects.default`)."""
        if self.catalogue is not None:
            return self.catalogue
        fitted = getattr(self, "catalogue_", None)
        return fitted if fitted is not None else fx.default()

    def time_effects(self) -> tuple[str, ...]:
        """The effects of the map that vary with time itself (`Effect.drives` includes 'time': a
        drift), whose value depends on the time origin of the data they are evaluated on.

        Returns
        -------
        tuple of str
        """
        return tuple(e for e in self.effects if "time" in self.effect(e).drives())

    def effect(self, name: str) -> fx.Effect:
        """An effect by name from the model's catalogue (`effects_catalogue`).

        Parameters
        ----------
        name : str
            The effect's name.

        Returns
        -------
        Effect
        """
        return self.effects_catalogue().get(name)

    def unfitted(self, **changes) -> HybridModel:
        """An unfitted model with this one's parameters, `changes` applied (sklearn.base.clone
        without the deep copy: the parameters are immutable, a Chain is only read).

        Parameters
        ----------
        **changes
            Parameters to change.

        Returns
        -------
        HybridModel
        """
        return type(self)(**(self.get_params(deep=False) | changes))

    def _check_params(self) -> GPOptions:
        self.effects_catalogue().check_names(self.effects)
        if self.gp_inputs not in GP_INPUTS:
            raise DataError(f"unknown GP inputs '{self.gp_inputs}'; allowed: {', '.join(GP_INPUTS)}")
        bad = [t for t in self.nuisance if t not in session_terms.TERMS]
        if bad:
            raise DataError(f"unknown session term(s) {', '.join(bad)}; allowed: {', '.join(session_terms.TERMS)}")
        if self.gp_options is None:
            return GPOptions()
        if not isinstance(self.gp_options, GPOptions):
            raise DataError(f"gp_options must be a GPOptions, got {type(self.gp_options).__name__}")
        return self.gp_options

    # --- linear effect part ------------------------------------------------------------------
    def design_matrix(self, X, y=None, *, chain: Chain | None = None) -> Design:
        """The effect terms' regressors on X (rows in time order: backlash and dynamic read the
        previous row). Cross-validation builds it once on all rows and passes row subsets to
        fit/predict, so held-out rows keep their true history. The effects' nonlinear parameters
        (the thermal lag): a fitted model's; else estimated on (X, y) by profile likelihood
        (models.hyper) when the error y is given; else their defaults. `chain`: the effects'
        kinematic chain when the caller has resolved it (`MapPredictor`, once); else resolved here.

        Parameters
        ----------
        X : Dataset, Inputs or ndarray
            The rows.
        y : ndarray, optional
            (n, 3) error, m.
        chain : Chain, optional
            The resolved chain.

        Returns
        -------
        Design
        """
        inp = as_inputs(X)
        cat = self.effects_catalogue()
        cat.check_names(self.effects)
        if inp.t_origin is None and getattr(self, "t_origin_", None) is not None:
            inp = replace(inp, t_origin=self.t_origin_)
        chain = chain if chain is not None else self._effects_chain()  # MapPredictor resolves it once
        hyper = getattr(self, "hyper_", None)
        if hyper is None:
            hyper = hp.profile(self.effects, inp, y, chain, self.ridge, cat) if y is not None else {}
        blocks = [cat.build(e, inp, chain, {k: v.value for k, v in hyper.get(e, {}).items()}) for e in self.effects]
        sessions: tuple[int, ...] = ()
        if self.nuisance:
            sessions = getattr(self, "nuisance_sessions_", None) or self._sessions_of(inp)
            blocks += [session_terms.block(t, inp, resolve_chain(self.robot), sessions) for t in self.nuisance]
        if not blocks:
            return Design(np.zeros((inp.n, 3, 0)), (), hyper=hyper)
        return Design(np.concatenate([b.A for b in blocks], axis=2),
                      tuple((b.effect, nm, u, b.report) for b in blocks for nm, u in zip(b.names, b.units)),
                      np.array([b.nonnegative for b in blocks for _ in b.names], dtype=bool), hyper, sessions)

    def _stand_in_reference(self, D: Design, inp: fx.Inputs) -> Design:
        """Without rows of the reference session (it is held out), the first training session
        stands in for it: its session terms are zeroed, else they would be aliased with the effect
        terms' own (a tool offset per session beside the model's tool offset)."""
        s = session_terms.session_column(inp) if self.nuisance else None
        if s is None or not len(s) or self.reference_session in set(s.tolist()):
            return D
        stand_in = f"s{int(s.min())}_"
        cols = [i for i, (e, n, _, _) in enumerate(D.params) if e.startswith("session_") and n.startswith(stand_in)]
        if not cols:
            return D
        A = D.A.copy()
        A[:, :, cols] = 0.0
        return replace(D, A=A)

    def _sessions_of(self, inp: fx.Inputs) -> tuple[int, ...]:
        """The sessions of `inp` that get nuisance parameters: all but the reference."""
        s = session_terms.session_column(inp)
        if s is None:
            raise DataError("session terms (nuisance) need several sessions: a 'session' column (several --data files)")
        return tuple(int(v) for v in np.unique(s) if int(v) != self.reference_session)

    @blas_limited  # BLAS on one thread inside (common.threads), the caller's setting restored
    def fit(self, X, y=None, *, design: Design | None = None, thetas=None, starts=None) -> HybridModel:
        """Fit on X (a Dataset, effects.Inputs or (n, 3) commanded TCP array); y: the error
        e = commanded - measured (n, 3) m, default X.error for a Dataset. design: prebuilt
        regressors (design_matrix) of these rows; thetas: fixed GP hyperparameters per axis
        (skips their optimisation); starts: warm starts of that optimisation per axis (a nearby
        model's `gp_.log_hypers_`, e.g. the model a diagnose candidate extends).

        Parameters
        ----------
        X : Dataset, Inputs or ndarray
            The rows.
        y : ndarray, optional
            (n, 3) error, m.
        design : Design, optional
            Prebuilt regressors of these rows.
        thetas : list, optional
            Fixed GP hyperparameters per axis.
        starts : list, optional
            Warm starts per axis.

        Returns
        -------
        HybridModel
            self.
        """
        self.catalogue_ = self.catalogue if self.catalogue is not None else fx.default()
        options = self._check_params()
        inp = as_inputs(X)
        if y is None:
            if getattr(X, "error", None) is None:
                raise DataError("HybridModel.fit: y (the error, n x 3) is required unless X is a Dataset")
            y = X.error
        error = np.asarray(y, dtype=float)
        if error.shape != (inp.n, 3) or not np.all(np.isfinite(error)):
            raise DataError(f"error must be a finite (n, 3) array matching {inp.n} rows")
        # The drift term's time origin: the first training row's time, kept for prediction on
        # later data (a deployed twin reads the time in the campaign's time base).
        self.t_origin_ = inp.t_origin if inp.t_origin is not None else (
            float(inp.t[0]) if inp.t is not None and inp.n else None)
        D = design if design is not None else self.design_matrix(inp, error)
        if D.A.shape[0] != inp.n:
            raise DataError(f"design has {D.A.shape[0]} rows, X has {inp.n}")
        D = self._stand_in_reference(D, inp)
        self.hyper_ = D.hyper or {}
        self.nuisance_sessions_ = D.sessions
        self.robot_ = None if isinstance(self.robot, Chain) else robot_ref(self.robot)
        self.gp_options_ = options
        self.param_names_ = list(D.params)
        A = D.A.reshape(inp.n * 3, -1)
        y = error.ravel()
        p = A.shape[1]
        lam, sign, zero, scale = 0.0, np.zeros(p, bool), np.zeros(p, bool), np.ones(p)
        if p:
            scale = np.sqrt(np.mean(A ** 2, axis=0))
            # A column that is zero to round-off (a joint offset that cannot move a TCP on its
            # axis) is not standardised by its round-off scale (that gave offsets of 1e10 rad):
            # it stays zero, its parameter 0 and not identified (models.identifiability).
            zero = idf.zero_columns(scale)
            scale[zero] = 1.0
            As = A / scale
            As[:, zero] = 0.0
            # Ridge on standardised columns: picks the smallest parameters among alike ones.
            lam = self.ridge * len(y) * 1e-3 / 3
            H = As.T @ As + lam * np.eye(p)
            Hinv = np.linalg.inv(H)
            theta_s = Hinv @ As.T @ y
            self.at_bound_ = np.zeros(p, bool)
            sign = D.nonnegative if D.nonnegative is not None else np.zeros(p, bool)
            if np.any(sign & (theta_s < 0)):
                # Physics demands widths and compliances >= 0: the same ridge problem with those
                # bounds (scipy's bounded least squares on the augmented system).
                M = np.vstack([As, np.sqrt(lam) * np.eye(p)])
                b = np.concatenate([y, np.zeros(p)])
                res = optimize.lsq_linear(M, b, bounds=(np.where(sign, 0.0, -np.inf), np.full(p, np.inf)),
                                          method="bvls")
                theta_s = res.x
                self.at_bound_ = sign & (theta_s <= 1e-12 * max(1.0, float(np.abs(theta_s).max())))
            self.theta_ = theta_s / scale
            resid = y - A @ self.theta_
            dof = max(len(y) - p, 1)
            s2 = float(resid @ resid) / dof
            cov_s = s2 * Hinv @ (As.T @ As) @ Hinv  # sandwich: covariance of the ridge estimate
            self.theta_cov_ = cov_s / np.outer(scale, scale)
            self.theta_u_ = np.sqrt(np.clip(np.diag(self.theta_cov_), 0, None))
            self.identifiability_ = idf.analyse(As, zero, scale)
        else:
            self.theta_ = np.zeros(0)
            self.theta_u_ = np.zeros(0)
            self.theta_cov_ = np.zeros((0, 0))
            self.at_bound_ = np.zeros(0, bool)
            self.identifiability_ = idf.analyse(np.zeros((0, 0)))
        resid = (y - A @ self.theta_).reshape(-1, 3)
        Xg = gp_features(inp, self.gp_inputs)
        self.gp_ = (MultiOutputGP(seed=self.seed, **options.to_dict()).fit(Xg, resid, thetas=thetas, starts=starts)
                    if Xg is not None else None)
        if p and self.gp_ is not None and Xg is not None:
            # Effects and GP jointly: the effect parameters again by generalised least squares
            # under the GP's covariance (universal kriging), then the GP on what they leave. By
            # ordinary least squares first, a joint-space effect takes up part of the smooth
            # error the GP would model and can make the model worse, so a diagnosis from the
            # paper's GP-only model missed a backlash that is there.
            gls = self._gls(D.A / scale, error, Xg, zero, lam, sign)
            if gls is not None:
                theta_s, cov_s = gls
                self.theta_ = theta_s / scale
                self.theta_cov_ = cov_s / np.outer(scale, scale)
                self.theta_u_ = np.sqrt(np.clip(np.diag(self.theta_cov_), 0, None))
                resid = error - np.einsum("nap,p->na", D.A, self.theta_)
                self.gp_ = MultiOutputGP(seed=self.seed, **options.to_dict()).fit(Xg, resid, thetas=self.gp_.thetas_)
        self.residual_rms_ = float(np.sqrt(np.mean(resid ** 2)))
        # The training domain (ranges of the TCP and the joint angles): what the model has seen.
        self.domain_ = {"x": [float(v) for v in inp.commanded.min(0)] + [float(v) for v in inp.commanded.max(0)]}
        if inp.joints is not None:
            self.domain_["q"] = [float(v) for v in inp.joints.min(0)] + [float(v) for v in inp.joints.max(0)]
        if inp.t is not None and inp.n:  # the time the model has seen: a time term beyond it extrapolates
            self.domain_["t"] = [float(np.min(inp.t)), float(np.max(inp.t))]
        # For the traceability record (provenance) of `save`: the training data's file, if any,
        # and the temperature over the training rows.
        self.data_source_ = getattr(X, "source", None)
        self.environment_ = Environment.of(inp.temperature)
        return self

    def _gls(self, As3: np.ndarray, error: np.ndarray, Xg: np.ndarray, zero: np.ndarray, lam: float,
             sign: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Standardised effect parameters by GLS under the fitted GP (per axis: the rows' noise
        within replicate groups, the GP's collapsed covariance K^-1 between groups) and their
        covariance; None when an axis GP is sparse (no exact K^-1 to use).

        With rows grouped by distinct GP input (Z), Sigma = Z K_f Z' + s_n^2 I, and
        a' Sigma^-1 b = (a - abar)'(b - bbar) / s_n^2 + abar' (K_f + s_n^2 W^-1)^-1 bbar, where
        the last inverse is the GP's own (`_precision_dot`; W: replicate counts); all in the GP's standardised
        units, so divided by its y scale squared."""
        gps = self.gp_.models_ if self.gp_ is not None else []
        if not gps or any(g.sparse_ for g in gps):
            return None
        _, inv = np.unique(Xg, axis=0, return_inverse=True)
        inv = inv.ravel()
        p = As3.shape[2]
        N, r = np.zeros((p, p)), np.zeros(p)
        for a, g in enumerate(gps):
            d = g.n_features_in_
            sn2, ys2, cnt = float(np.exp(g.theta_[d + 1])), g.y_scale_ ** 2, g._counts
            Aa = As3[:, a, :].copy()
            Aa[:, zero] = 0.0
            ya = error[:, a] - g.mean_
            Abar = np.stack([np.bincount(inv, weights=Aa[:, k], minlength=len(cnt)) for k in range(p)], axis=1) \
                / cnt[:, None]
            ybar = np.bincount(inv, weights=ya, minlength=len(cnt)) / cnt
            Aw, yw = Aa - Abar[inv], ya - ybar[inv]
            QA = g._precision_dot(np.column_stack([Abar, ybar]))  # K^-1 [Abar, ybar]
            N += (Aw.T @ Aw / sn2 + Abar.T @ QA[:, :p]) / ys2
            r += (Aw.T @ yw / sn2 + Abar.T @ QA[:, p]) / ys2
        # The same relative ridge as the ordinary fit (its penalty against As' As).
        lam_g = lam * np.trace(N) / max(float(np.sum(As3 ** 2)), 1e-300)
        Hg = N + lam_g * np.eye(p)
        try:
            Hinv = np.linalg.inv(Hg)
        except np.linalg.LinAlgError:
            return None
        theta = Hinv @ r
        if np.any(sign & (theta < 0)):  # physics' signs, as in the ordinary fit
            L = np.linalg.cholesky(Hg)
            res = optimize.lsq_linear(L.T, np.linalg.solve(L, r),
                                      bounds=(np.where(sign, 0.0, -np.inf), np.full(p, np.inf)), method="bvls")
            theta = res.x
            self.at_bound_ = sign & (theta <= 1e-12 * max(1.0, float(np.abs(theta).max())))
        else:
            self.at_bound_ = np.zeros(p, bool)
        return theta, Hinv @ N @ Hinv

    @blas_limited
    def predict(self, X, return_std: bool = False, *, design: Design | None = None):
        """Predicted error (n, 3) m and, with return_std, its standard uncertainty per axis: the
        GP's latent standard deviation and the effect parameters' covariance propagated through
        their regressors (u^2 = s_GP^2 + a Sigma_theta a^T for each row's axis regressors a).

        Parameters
        ----------
        X : Dataset, Inputs or ndarray
            The rows.
        return_std : bool, optional
            Also return the standard uncertainty.
        design : Design, optional
            Prebuilt regressors of these rows.

        Returns
        -------
        ndarray, or (ndarray, ndarray)
            (n, 3), m.
        """
        self._check_fitted()
        inp = as_inputs(X)
        D = design if design is not None else self.design_matrix(inp)
        A = D.A
        mean = np.einsum("nap,p->na", A, self.theta_) if A.shape[2] else np.zeros((inp.n, 3))
        var = np.einsum("nap,pq,naq->na", A, self.theta_cov_, A) if A.shape[2] and return_std else np.zeros((inp.n, 3))
        if self.gp_ is not None:
            Xg = gp_features(inp, self.gp_inputs)
            if return_std:
                m, s = self.gp_.predict(Xg, return_std=True)
                mean, var = mean + m, var + s ** 2
            else:
                mean = mean + self.gp_.predict(Xg)
        return (mean, np.sqrt(np.maximum(var, 0.0))) if return_std else mean

    def outside_domain(self, X, margin: float = 0.02) -> dict | None:
        """Rows of X outside the training domain (TCP box or joint ranges, each widened by
        `margin` of its range): {'rows', 'fraction', 'columns': {name: rows}}; None when the
        model does not know its domain.

        Parameters
        ----------
        X : Dataset, Inputs or ndarray
            The rows.
        margin : float, optional
            Widening, as a fraction of each range.

        Returns
        -------
        dict or None
        """
        dom = getattr(self, "domain_", None)
        if not dom:
            return None
        inp = as_inputs(X)
        outside = np.zeros(inp.n, bool)
        cols: dict[str, int] = {}
        for key, values, names in (("x", inp.commanded, ("x", "y", "z")),
                                   ("q", inp.joints, tuple(f"q{j + 1}" for j in range(len(dom.get("q", [])) // 2)))):
            if key not in dom or values is None or values.shape[1] != len(dom[key]) // 2:
                continue
            k = values.shape[1]
            lo, hi = np.asarray(dom[key][:k]), np.asarray(dom[key][k:])
            w = margin * np.maximum(hi - lo, 1e-9)
            out = (values < lo - w) | (values > hi + w)
            outside |= out.any(axis=1)
            cols.update({n: int(c) for n, c in zip(names, out.sum(0)) if c})
        return {"rows": int(outside.sum()), "fraction": float(outside.mean()) if inp.n else 0.0, "columns": cols}

    def _check_fitted(self) -> None:
        if not hasattr(self, "theta_"):
            raise ModelError("HybridModel is not fitted; call fit(X, y) or HybridModel.load first")

    def _effects_chain(self) -> Chain | None:
        """The chain the effect terms read: only joint-space effects, or those that use it when
        given (per-link thermal), read the robot config (a GP-only map works without it)."""
        used = any(self.effect(e).needs_chain or self.effect(e).uses_chain for e in self.effects)
        return resolve_chain(self.robot) if used else None

    def needs(self) -> tuple[str, ...]:
        """The input columns (effects.Inputs fields) a prediction reads beside the commanded TCP."""
        chain = self._effects_chain()
        cols = {c for e in self.effects for c in self.effect(e).reads(chain)}
        cols |= {"tcp_speed": {"speed"}, "joints": {"joints"}}.get(self.gp_inputs, set())
        if self.lag_s() > 0:
            cols |= {"t"}  # the structure's temperature follows the logged one with time
        own = ("joints", "speed", "temperature", "payload", "t")
        # then the data's own columns the user's declared effects read (humidity, ...)
        return tuple(c for c in own if c in cols) + tuple(sorted(cols - set(own)))

    def lag_s(self) -> float:
        """The structure's thermal time constant the model uses (s; 0: the air temperature as logged)."""
        est = getattr(self, "hyper_", {}).get("thermal", {}).get("lag_s")
        return 0.0 if est is None else float(est.value)

    def chain(self) -> Chain | None:
        """The robot's nominal kinematic chain (None when the model was given none)."""
        return resolve_chain(self.robot)

    def predictor(self) -> MapPredictor:
        """The lean per-command predictor (what the twin calls on every command)."""
        self._check_fitted()
        return MapPredictor(self)

    def identifiability(self) -> dict | None:
        """Rank, condition number, the parameters the data cannot determine and their aliased
        groups (by name), or None for a model loaded from a file written before it was kept."""
        ident = getattr(self, "identifiability_", None)
        return None if ident is None else ident.to_dict([f"{e}.{n}" for e, n, _, _ in self.param_names_])

    def parameters(self) -> list[dict]:
        """Estimated effect parameters with standard uncertainty, in physical units. A parameter
        the data cannot determine (`identified: false`, models.identifiability) has no value: the
        ridge's choice along an unseen direction is not a measurement; its `group` names the
        parameters it is aliased with."""
        rows = []
        ident = getattr(self, "identifiability_", None)
        group_of = {i: g for g in (ident.groups if ident else []) for i in g}
        for i, ((effect, name, unit, report), v, u) in enumerate(zip(self.param_names_, self.theta_, self.theta_u_)):
            row = {"effect": effect, "name": name, "value": float(v), "u": float(u), "unit": unit}
            if ident is not None:
                row["identified"] = bool(ident.identified[i])
                if not row["identified"]:
                    names = [f"{self.param_names_[j][0]}.{self.param_names_[j][1]}" for j in group_of.get(i, [i])]
                    row.update(value=None, u=None, group=names)
                    rows.append(row)
                    continue
            if getattr(self, "at_bound_", None) is not None and i < len(self.at_bound_) and self.at_bound_[i]:
                row["at_bound"] = True  # physics' sign held it at 0: the data pushed the other way
            if report == "inverse" and v > 0:
                # Stiffness k = 1/c, u(k) = u(c)/c^2 (first order).
                row.update(name=name.replace("compliance", "stiffness"), value=float(1 / v),
                           u=float(u / v ** 2), unit="N m/rad")
            rows.append(row)
        for effect, params in getattr(self, "hyper_", {}).items():
            for name, est in params.items():
                choices = self.effect(effect).hyper_choices.get(name)
                if choices:  # an alternative the model uses, chosen by profile likelihood
                    rows.append({"effect": effect, "name": name, "value": est.value, "u": None, "unit": "",
                                 "choice": choices[int(round(est.value))], "identified": est.identified,
                                 "method": "profile likelihood (choice)"})
                    continue
                # A nonlinear parameter, by profile likelihood (models.hyper): no value when the
                # data do not bound it (the model then uses its default, est.value).
                rows.append({"effect": effect, "name": name, "value": est.value if est.identified else None,
                             "u": est.u, "unit": est.unit, "identified": est.identified,
                             "interval": [est.lo, est.hi], "method": "profile likelihood"})
        return rows

    def base_parameters(self) -> dict | None:
        """What the training data determine of the effect parameters: the rank r of the design and
        its r base parameters (models.identifiability: QR with column pivoting), each named by its
        leading parameter, with its value +/- standard uncertainty (from theta_cov_, through the
        combination) and the `combination` of the full set it stands for ({parameter: coefficient},
        beta = sum coefficient * theta, the leading one 1; a coefficient is in the base parameter's
        unit per that parameter's unit), `absorbs` the others in it. `no_effect`: parameters whose
        column is zero over the data. The nonlinear parameters (profile likelihood) are in
        `parameters`. None for a model saved before base parameters were kept."""
        ident: idf.Identifiability | None = getattr(self, "identifiability_", None)
        if ident is None or ident.base is None:
            return None
        base = ident.base
        full = [f"{e}.{n}" for e, n, _, _ in self.param_names_]
        beta = base.C @ self.theta_
        u = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", base.C, self.theta_cov_, base.C), 0.0, None))
        at_bound = getattr(self, "at_bound_", None)
        rows = []
        for k, i in enumerate(base.lead):
            effect, name, unit, report = self.param_names_[i]
            absorbs = base.absorbed(k)
            row = {"effect": effect, "name": name, "value": float(beta[k]), "u": float(u[k]), "unit": unit,
                   "combination": {full[j]: float(base.C[k, j]) for j in [i, *absorbs]},
                   "absorbs": [full[j] for j in absorbs]}
            if not absorbs and at_bound is not None and i < len(at_bound) and at_bound[i]:
                row["at_bound"] = True  # physics' sign held it at 0
            if report == "inverse" and not absorbs and beta[k] > 0:
                # Stiffness k = 1/c, u(k) = u(c)/c^2 (first order), as `parameters`.
                row.update(name=name.replace("compliance", "stiffness"), value=float(1 / beta[k]),
                           u=float(u[k] / beta[k] ** 2), unit="N m/rad")
            rows.append(row)
        return {"rank": base.rank, "n_params": len(full), "not_separable": len(full) - base.rank,
                "no_effect": [full[j] for j in ident.no_effect], "rcond": idf.RCOND,
                "method": "QR with column pivoting of the standardised regressor (Khalil & Dombre's base "
                          "parameters, as FIGAROH); beta = C theta",
                "parameters": rows}

    # --- persistence (JSON + NPZ) -----------------------------------------------------------
    def provenance(self) -> Provenance:
        """The traceability record `save` writes when given none: this software, now, the
        robot config (hashed; the chain's name when it came from memory) and the training data
        file (hashed) when the model was fitted on a Dataset read from a file. A loaded model
        keeps its record's inputs, instruments and environment."""
        old: Provenance | None = getattr(self, "provenance_", None)
        if not hasattr(self, "data_source_") and old is not None:
            return old.renewed()
        src = getattr(self, "data_source_", None)
        robot_file, robot_text = robots.record(self.robot_)
        return build_provenance(
            inputs=[src] if src and Path(src).is_file() else [],
            robot=robot_file,
            robot_name=self.robot.name if isinstance(self.robot, Chain) else robot_text,
            environment=getattr(self, "environment_", None))

    def save(self, directory: str | Path, provenance: Provenance | None = None) -> Path:
        """Write hybrid.json (with the traceability record `provenance`, default
        `self.provenance()`), hybrid.npz and the GP.

        Parameters
        ----------
        directory : str or Path
            The model directory.
        provenance : Provenance, optional
            The traceability record.

        Returns
        -------
        Path
        """
        self._check_fitted()
        chained = any(self.effect(e).needs_chain or self.effect(e).uses_chain for e in self.effects)
        if isinstance(self.robot, Chain) and (self.nuisance or chained):
            raise ModelError("a model given its kinematic chain as an object cannot be saved; "
                             "give robot as the path of a robot config")
        bad = [k for k, v in (("theta", self.theta_), ("theta_u", self.theta_u_), ("theta_cov", self.theta_cov_))
               if not np.all(np.isfinite(v))]
        if bad or not np.isfinite(self.residual_rms_):
            raise DataError(f"{directory}: the fitted model holds NaN or infinite values "
                            f"({', '.join(bad) or 'residual_rms'}); not saved: check the training data for absurd "
                            "values (an error of 1e300 mm, a unit mistake)")
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        meta = {"format_version": FORMAT_VERSION, "kind": "cobot-dt hybrid error model",
                "effects": list(self.effects), "gp_inputs": self.gp_inputs, "ridge": self.ridge,
                # The user's declared effects travel with the model (it loads without their file).
                "declared_effects": [eff.spec.model_dump(mode="json")
                                     for eff in self.effects_catalogue().declared(self.effects)],
                "seed": self.seed, "robot": self.robot_, "gp_options": self.gp_options_.to_dict(),
                "nuisance": list(self.nuisance), "reference_session": self.reference_session,
                "nuisance_sessions": list(getattr(self, "nuisance_sessions_", ())),
                "param_names": self.param_names_, "parameters": self.parameters(),
                "base_parameters": self.base_parameters(),  # for readers: load rebuilds it from identifiability
                "identifiability": None if getattr(self, "identifiability_", None) is None else
                self.identifiability_.state(),
                "at_bound": [bool(v) for v in getattr(self, "at_bound_", [])],
                "domain": getattr(self, "domain_", None),
                "hyper": {e: {k: v.to_dict() for k, v in ps.items()} for e, ps in getattr(self, "hyper_", {}).items()},
                "residual_rms_m": self.residual_rms_, "t_origin_s": self.t_origin_,
                "units": "SI; e = commanded - measured",
                "provenance": (provenance or self.provenance()).to_dict()}
        (d / "hybrid.json").write_text(json.dumps(meta, indent=2, allow_nan=False))
        np.savez(d / "hybrid.npz", theta=self.theta_, theta_u=self.theta_u_, theta_cov=self.theta_cov_)
        if self.gp_ is not None:
            self.gp_.save(d / "gp")
        return d

    @classmethod
    def of_gp(cls, gp: MultiOutputGP, robot: str | Path | None = None) -> HybridModel:
        """The paper's map as a fitted hybrid model: no effect terms, a fitted GP(TCP, v).

        Parameters
        ----------
        gp : MultiOutputGP
            A fitted GP(TCP, v).
        robot : str or Path, optional
            The robot reference.

        Returns
        -------
        HybridModel
        """
        if getattr(gp, "n_features_in_", None) != 4:
            raise ModelError("HybridModel.of_gp: the GP must be fitted on (x, y, z, v)")
        params = gp.get_params()
        options = GPOptions.from_dict({k: params[k] for k in GPOptions.__dataclass_fields__ if k in params})
        m = cls((), "tcp_speed", DEFAULT_RIDGE, params.get("seed", 0), robot=robot, gp_options=options)
        m.robot_, m.gp_options_, m.gp_ = robot_ref(robot), options, gp
        m.theta_, m.theta_u_, m.theta_cov_ = np.zeros(0), np.zeros(0), np.zeros((0, 0))
        m.param_names_, m.t_origin_, m.residual_rms_, m.hyper_ = [], None, float("nan"), {}
        m.provenance_, m.catalogue_ = None, fx.default()
        return m

    @classmethod
    def load(cls, directory: str | Path, catalogue: fx.Catalogue | None = None) -> HybridModel:
        """The model saved in `directory`; ModelError (or DataError for its arrays) naming the
        file for anything unreadable, non-finite, missing or of the wrong shape.

        Parameters
        ----------
        directory : the model directory (hybrid.json, hybrid.npz, gp/).
        catalogue : the effects its names may refer to beyond its own declared ones (a call's
            `effects.Catalogue`); default `effects.default()`. The model's catalogue is this one
            with the saved declarations as its own.
        """
        d = Path(directory)
        meta = read_meta(d / "hybrid.json", FORMAT_VERSION, "model")
        try:
            return cls._load(d, meta, catalogue)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
            raise ModelError(f"{d / 'hybrid.json'}: a missing or malformed entry ({exc!r})") from exc

    @classmethod
    def _load(cls, d: Path, meta: dict, base: fx.Catalogue | None) -> HybridModel:
        ref = meta.get("robot")
        try:
            # The model's declared effects are its catalogue's own: it loads without their file.
            own = [fx.declared.from_dict(e) for e in meta.get("declared_effects") or []]
            catalogue = (base if base is not None else fx.default()).with_own(own)
            catalogue.check_names(meta["effects"])  # a plugin effect whose package is not installed
        except (DataError, ConfigError) as exc:
            raise ModelError(f"{d / 'hybrid.json'}: {exc}") from exc
        # Models saved before GPOptions carry only the overridden options as "gp_kw".
        options = GPOptions.from_dict(meta["gp_options"] if "gp_options" in meta else meta.get("gp_kw"))
        m = cls(tuple(meta["effects"]), meta["gp_inputs"], meta["ridge"], meta["seed"],
                robot=ref, gp_options=options,
                nuisance=tuple(meta.get("nuisance") or ()), reference_session=int(meta.get("reference_session", 0)),
                catalogue=catalogue)
        m.nuisance_sessions_ = tuple(int(v) for v in meta.get("nuisance_sessions") or ())
        arr = load_npz(d / "hybrid.npz", ("theta", "theta_u", "theta_cov"))  # checked before reading
        m.robot_, m.gp_options_ = ref, options
        m.theta_, m.theta_u_ = arr["theta"], arr["theta_u"]
        # Models saved before the full covariance carry the standard uncertainties only.
        m.theta_cov_ = arr["theta_cov"] if "theta_cov" in arr else np.diag(m.theta_u_ ** 2)
        m.t_origin_ = meta.get("t_origin_s")
        m.param_names_ = [tuple(p) for p in meta["param_names"]]
        n = len(m.param_names_)
        if m.theta_.shape != (n,) or m.theta_u_.shape != (n,) or m.theta_cov_.shape != (n, n):
            raise ModelError(f"{d / 'hybrid.npz'}: theta {m.theta_.shape}, theta_u {m.theta_u_.shape}, theta_cov "
                             f"{m.theta_cov_.shape} do not fit the {n} parameters of hybrid.json")
        m.at_bound_ = np.asarray(meta.get("at_bound", [False] * len(m.param_names_)), dtype=bool)
        m.domain_ = meta.get("domain") or {}  # empty for a model saved before it was kept
        m.hyper_ = {e: {k: hp.Estimate.from_dict(v) for k, v in ps.items()}
                    for e, ps in (meta.get("hyper") or {}).items()}
        if meta.get("identifiability") is not None:  # models saved before it was kept have none
            m.identifiability_ = idf.Identifiability.from_state(meta["identifiability"])
        m.residual_rms_ = meta["residual_rms_m"]
        m.gp_ = MultiOutputGP.load(d / "gp") if meta["gp_inputs"] != "none" else None
        # Models saved before the traceability record have none.
        try:
            m.provenance_ = Provenance.from_dict(meta["provenance"]) if meta.get("provenance") else None
        except DataError as exc:
            raise ModelError(f"{d / 'hybrid.json'}: {exc}") from exc
        return m


def unidentified(p: dict) -> str:
    """Why a parameter (a `HybridModel.parameters` row) has no value.

    Parameters
    ----------
    p : dict
        A parameter row.

    Returns
    -------
    str
    """
    if "group" in p:
        return f"not identified (aliased with {', '.join(p['group'])})"
    lo, hi = p.get("interval", (float("nan"), float("nan")))
    return f"not bounded by the data (profile interval {lo:.4g}..{hi:.4g} {p['unit']}); the model uses the default"


def load_map(path: str | Path, catalogue: fx.Catalogue | None = None) -> HybridModel:
    """An error map as a HybridModel, from any of the places one is saved: a `dt fit` model
    directory, a twin's map directory (TWIN/e_lt), a twin directory (its e_LT map), or a
    GP-only map of a twin saved before format 2 (TWIN/e_lt.json + .npz). `catalogue`: the
    call's effects (`HybridModel.load`).

    Parameters
    ----------
    path : str or Path
        Where the map is.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    HybridModel
    """
    p = Path(path)
    if (p / "twin.json").is_file():  # a twin: its e_LT map
        p = p / "e_lt"
    if not (p / "hybrid.json").is_file() and p.with_suffix(".json").is_file():
        return HybridModel.of_gp(MultiOutputGP.load(p))
    return HybridModel.load(p, catalogue)  # a ModelError names what is missing


class MapPredictor:
    """Per-command prediction of a fitted HybridModel: mean and standard uncertainty (3,) at the
    last row of a few rows of inputs (the earlier rows are its history: the direction of
    approach). A map without effect terms on the paper's inputs goes straight to the GP's lean
    predictor (`gp_only`)."""

    def __init__(self, model: HybridModel):
        self.model = model
        self.needs = model.needs()
        self._gp = model.gp_.predictor() if model.gp_ is not None else None
        # the effects' chain, resolved once: per command it is a file lookup (~0.5 ms)
        self._chain = model._effects_chain() if model.effects else None
        # The paper's map: GP(TCP, v) only; one call of the GP's lean predictor per command.
        self.plain = not model.effects and model.gp_inputs == "tcp_speed"
        # The structure's temperature, carried from command to command when it lags the air
        # (t, logged T, structure T of the last command): a few rows of history cannot hold a
        # time constant of tens of minutes. The first command starts in equilibrium.
        self._lag = model.lag_s() if "thermal" in model.effects else 0.0
        self._thermal: tuple[float, float, float] | None = None

    def _structure_temperature(self, inp: fx.Inputs) -> fx.Inputs:
        assert inp.t is not None and inp.temperature is not None  # needs() asks for both
        t1, T1 = float(inp.t[-1]), float(inp.temperature[-1])
        if self._thermal is None or t1 < self._thermal[0]:
            ts = T1
        else:
            t0, T0, ts0 = self._thermal
            ts = float(lagged(np.array([t0, t1]), np.array([T0, T1]), self._lag, start=ts0)[1])
        self._thermal = (t1, T1, ts)
        return replace(inp, structure_temperature=np.full(inp.n, ts))

    def gp_only(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plain map at x = (x, y, z, v) (m, m/s).

        Parameters
        ----------
        x : ndarray
            (4,).

        Returns
        -------
        mean, std : ndarray
        """
        assert self._gp is not None and self.plain
        return self._gp(x)

    def gp_mean(self, x: np.ndarray) -> np.ndarray:
        """The plain map's mean at x = (x, y, z, v) (m, m/s): `gp_only`'s mean, without its std
        (Eq. 17 reads the means only).

        Parameters
        ----------
        x : ndarray
            (4,).

        Returns
        -------
        ndarray
        """
        assert self._gp is not None and self.plain
        if self._gp.shared:  # the same operations as the full call's mean: the same numbers
            return self._gp.mean_kernel(np.asarray(x, dtype=float))[0]
        return self._gp(x)[0]

    def __call__(self, inp: fx.Inputs) -> tuple[np.ndarray, np.ndarray]:
        m = self.model
        if self._lag > 0:
            inp = self._structure_temperature(inp)
        A = m.design_matrix(inp, chain=self._chain).A[-1] if m.theta_.size else np.zeros((3, 0))
        mean = A @ m.theta_ if A.shape[1] else np.zeros(3)
        var = np.einsum("ap,pq,aq->a", A, m.theta_cov_, A) if A.shape[1] else np.zeros(3)
        if self._gp is not None:
            xg = gp_features(inp, m.gp_inputs)
            assert xg is not None
            g, s = self._gp(xg[-1])
            mean, var = mean + g, var + s ** 2
        return mean, np.sqrt(np.maximum(var, 0.0))
