"""Hybrid error model: error = sum of physical effect terms + GP on what is left.

The effect parameters (dt_runtime.effects) are estimated jointly by ridge-regularised least
squares on standardised columns (the complete geometric set is rank deficient on purpose), with
their standard uncertainties from the residual scatter. A GP (dt_runtime.gp) then models the
residual on configurable inputs: 'tcp_speed' (the paper's Cartesian TCP and speed), 'tcp',
'joints', or 'none'. Follows scikit-learn's estimator contract.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dt_runtime.models import effects as fx
from dt_kernel.errors import DataError
from dt_runtime.models.gp import MultiOutputGP
from dt_runtime.frames.kinematics import Chain, load_robot
from dt_runtime.models.modelio import read_meta
from dt_runtime.common.paths import CONFIGS

FORMAT_VERSION = 1
GP_INPUTS = ("tcp_speed", "tcp", "joints", "none")


def gp_features(inp: fx.Inputs, kind: str) -> np.ndarray | None:
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


def robot_ref(path: str | Path | None) -> str | None:
    """How a saved model names its robot config: relative to configs/ when shipped there."""
    if path is None:
        return None
    p = Path(path).resolve()
    try:
        return str(p.relative_to(CONFIGS))
    except ValueError:
        return str(p)


def load_chain(ref: str | None) -> Chain | None:
    if ref is None:
        return None
    p = Path(ref)
    return load_robot(p if p.is_absolute() else CONFIGS / p)


class HybridModel:
    """error = sum of effect terms (dt_runtime.models.effects) + GP on what is left.

    effects: names from effects.EFFECT_NAMES; gp_inputs: one of GP_INPUTS; robot: path of a
    robot config (configs/robots/*.yaml) giving the kinematic model the joint-space effects
    need; gp_kw: MultiOutputGP options (e.g. sparse_threshold, n_inducing).
    """

    def __init__(self, effects: tuple[str, ...] = (), gp_inputs: str = "tcp_speed",
                 ridge: float = 1e-4, seed: int = 0, robot: str | Path | None = None,
                 gp_kw: dict | None = None):
        unknown = [e for e in effects if e not in fx.EFFECT_NAMES]
        if unknown:
            raise DataError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(fx.EFFECT_NAMES)}")
        if gp_inputs not in GP_INPUTS:
            raise DataError(f"unknown GP inputs '{gp_inputs}'; allowed: {', '.join(GP_INPUTS)}")
        self.effects = tuple(effects)
        self.gp_inputs = gp_inputs
        self.ridge = ridge
        self.seed = seed
        self.robot = robot_ref(robot)
        self.gp_kw = dict(gp_kw or {})

    @property
    def chain(self) -> Chain | None:
        if not hasattr(self, "_chain"):
            self._chain = load_chain(self.robot)
        return self._chain

    # --- on a measurement table ---------------------------------------------------------------
    def fit_dataset(self, ds, thetas=None) -> "HybridModel":
        """Fit on a `Dataset` (rows in time order: backlash and dynamic read the previous row)."""
        return self.fit(fx.Inputs.of(ds), ds.error, self.chain, thetas=thetas)

    def predict_dataset(self, ds, return_std: bool = False):
        return self.predict(fx.Inputs.of(ds), self.chain, return_std=return_std)

    # --- linear effect part ------------------------------------------------------------------
    def _design(self, inp: fx.Inputs, chain: Chain | None) -> tuple[np.ndarray, list[fx.Block]]:
        blocks = [fx.build(e, inp, chain) for e in self.effects]
        if not blocks:
            return np.zeros((inp.n * 3, 0)), []
        A = np.concatenate([b.A for b in blocks], axis=2)  # (n, 3, p)
        return A.reshape(inp.n * 3, -1), blocks

    def fit(self, inp: fx.Inputs, error: np.ndarray, chain: Chain | None = None,
            thetas=None) -> "HybridModel":
        A, blocks = self._design(inp, chain)
        self.param_names_ = [(b.effect, nm, u, b.report) for b in blocks for nm, u in zip(b.names, b.units)]
        return self.fit_design(A.reshape(inp.n, 3, -1), inp, error, thetas=thetas)

    def fit_design(self, A3: np.ndarray, inp: fx.Inputs, error: np.ndarray, thetas=None) -> "HybridModel":
        """Fit from a prebuilt regressor array A3 (n, 3, p) (cross-validation reuses it);
        `thetas`: fixed GP hyperparameters per axis (skips their optimisation)."""
        error = np.asarray(error, dtype=float)
        if error.shape != (inp.n, 3) or not np.all(np.isfinite(error)):
            raise DataError(f"error must be a finite (n, 3) array matching {inp.n} rows")
        A = A3.reshape(inp.n * 3, -1)
        y = error.ravel()
        p = A.shape[1]
        if not hasattr(self, "param_names_"):
            self.param_names_ = [("?", f"p{i}", "", "identity") for i in range(p)]
        if p:
            scale = np.sqrt(np.mean(A ** 2, axis=0))
            scale[scale == 0] = 1.0
            As = A / scale
            # Ridge on standardised columns: picks the smallest parameters among alike ones.
            H = As.T @ As + self.ridge * len(y) * 1e-3 * np.eye(p) / 3
            Hinv = np.linalg.inv(H)
            theta_s = Hinv @ As.T @ y
            self.theta_ = theta_s / scale
            resid = y - A @ self.theta_
            dof = max(len(y) - p, 1)
            s2 = float(resid @ resid) / dof
            cov_s = s2 * Hinv @ (As.T @ As) @ Hinv
            self.theta_u_ = np.sqrt(np.clip(np.diag(cov_s), 0, None)) / scale
        else:
            self.theta_ = np.zeros(0)
            self.theta_u_ = np.zeros(0)
        resid = (y - A @ self.theta_).reshape(-1, 3)
        X = gp_features(inp, self.gp_inputs)
        self.gp_ = (MultiOutputGP(seed=self.seed, **self.gp_kw).fit(X, resid, thetas=thetas)
                    if X is not None else None)
        self.residual_rms_ = float(np.sqrt(np.mean(resid ** 2)))
        return self

    def predict(self, inp: fx.Inputs, chain: Chain | None = None, return_std: bool = False):
        A, _ = self._design(inp, chain)
        return self.predict_design(A.reshape(inp.n, 3, -1), inp, return_std)

    def predict_design(self, A3: np.ndarray, inp: fx.Inputs, return_std: bool = False):
        A = A3.reshape(inp.n * 3, -1)
        mean = (A @ self.theta_).reshape(-1, 3) if A.shape[1] else np.zeros((inp.n, 3))
        std = np.zeros((inp.n, 3))
        if self.gp_ is not None:
            X = gp_features(inp, self.gp_inputs)
            if return_std:
                m, s = self.gp_.predict(X, return_std=True)
                mean, std = mean + m, s
            else:
                mean = mean + self.gp_.predict(X)
        return (mean, std) if return_std else mean

    def parameters(self) -> list[dict]:
        """Estimated effect parameters with standard uncertainty, in physical units."""
        rows = []
        for (effect, name, unit, report), v, u in zip(self.param_names_, self.theta_, self.theta_u_):
            row = {"effect": effect, "name": name, "value": float(v), "u": float(u), "unit": unit}
            if report == "inverse" and v > 0:
                # Stiffness k = 1/c, u(k) = u(c)/c^2 (first order).
                row.update(name=name.replace("compliance", "stiffness"), value=float(1 / v),
                           u=float(u / v ** 2), unit="N m/rad")
            rows.append(row)
        return rows

    # --- persistence (JSON + NPZ) -----------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        meta = {"format_version": FORMAT_VERSION, "kind": "cobot-dt hybrid error model",
                "effects": list(self.effects), "gp_inputs": self.gp_inputs, "ridge": self.ridge,
                "seed": self.seed, "robot": self.robot, "gp_kw": self.gp_kw,
                "param_names": self.param_names_, "parameters": self.parameters(),
                "residual_rms_m": self.residual_rms_, "units": "SI; e = commanded - measured"}
        (d / "hybrid.json").write_text(json.dumps(meta, indent=2))
        np.savez(d / "hybrid.npz", theta=self.theta_, theta_u=self.theta_u_)
        if self.gp_ is not None:
            self.gp_.save(d / "gp")
        return d

    @classmethod
    def load(cls, directory: str | Path) -> "HybridModel":
        d = Path(directory)
        meta = read_meta(d / "hybrid.json", FORMAT_VERSION, "model")
        m = cls(tuple(meta["effects"]), meta["gp_inputs"], meta["ridge"], meta["seed"])
        m.robot, m.gp_kw = meta.get("robot"), meta.get("gp_kw", {})
        arr = np.load(d / "hybrid.npz", allow_pickle=False)
        m.theta_, m.theta_u_ = arr["theta"], arr["theta_u"]
        m.param_names_ = [tuple(p) for p in meta["param_names"]]
        m.residual_rms_ = meta["residual_rms_m"]
        m.gp_ = MultiOutputGP.load(d / "gp") if meta["gp_inputs"] != "none" else None
        return m
