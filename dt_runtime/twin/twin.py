"""The calibrated twin: frames, GPR error models and uncertainty, with the correction law.

Sign convention (DESIGN.md, Eq. 8): e = commanded - measured. The twin's estimate of where the
robot really is: TCP_hat = TCP_cmd - e_hat(TCP_cmd, v). To reach a target the corrected command
solves c - e_hat(c, v) = target by fixed-point iteration, starting at c = target + e_hat(target, v).
Models predict errors in the GL axes; the robot frame is rotated by R_RDK^GL (nearly identity).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.models.modelio import read_meta
from dt_runtime.models.gp import MultiOutputGP
from dt_runtime.frames.registration import RigidTransform

FORMAT_VERSION = 1


@dataclass
class Twin:
    T_rdk: RigidTransform  # robot frame -> GL
    T_lt: RigidTransform  # tracker frame -> GL
    T_mvs: RigidTransform  # MVS frame -> GL
    e_lt: MultiOutputGP  # e_LT_hat(TCP robot frame m, v m/s) -> GL axes, m
    e_mvs_lt: MultiOutputGP  # e_MVS-LT_hat(TCP, v)
    u: dict  # standard uncertainties (m, per axis) and dof: u_tcp_c, u_e_lt, u_diff, u_e_mvs_lt, ...
    instruments: dict = field(default_factory=dict)  # drivers it was calibrated with, e.g. camera

    def __post_init__(self):
        self._p_lt = self.e_lt.predictor()
        self._p_mvs_lt = self.e_mvs_lt.predictor()
        self._Rt = self.T_rdk.R.T  # GL axes -> robot axes

    def e_lt_hat(self, c: np.ndarray, v: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted LT error at command c (robot frame): mean and GP std, robot axes, m."""
        m, s = self._p_lt(np.array([c[0], c[1], c[2], v]))
        return self._Rt @ m, s

    def e_mvs_lt_hat(self, c: np.ndarray, v: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted e_MVS-LT at command c, GL axes, m."""
        return self._p_mvs_lt(np.array([c[0], c[1], c[2], v]))

    def corrected_command(self, target: np.ndarray, v: float, iters: int = 6,
                          tol: float = 1e-8) -> np.ndarray:
        """Solve c - e_hat(c, v) = target (fixed point; the map contracts as grad e << 1)."""
        target = np.asarray(target, dtype=float)
        c = target + self.e_lt_hat(target, v)[0]
        for _ in range(iters):
            c_new = target + self.e_lt_hat(c, v)[0]
            done = np.max(np.abs(c_new - c)) < tol
            c = c_new
            if done:
                break
        return c

    # --- persistence: JSON + NPZ, no pickle ------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.e_lt.save(d / "e_lt")
        self.e_mvs_lt.save(d / "e_mvs_lt")
        meta = {
            "format_version": FORMAT_VERSION,
            "kind": "cobot-dt twin",
            "units": "SI (m, m/s); errors e = commanded - measured",
            "T_rdk": self.T_rdk.to_dict(), "T_lt": self.T_lt.to_dict(), "T_mvs": self.T_mvs.to_dict(),
            "u": jsonable(self.u, finite_only=False),
            "instruments": self.instruments,
        }
        (d / "twin.json").write_text(json.dumps(meta, indent=2))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> "Twin":
        d = Path(directory)
        meta = read_meta(d / "twin.json", FORMAT_VERSION, "twin")
        u = {k: (np.array(v) if isinstance(v, list) else v) for k, v in meta["u"].items()}
        return cls(RigidTransform.from_dict(meta["T_rdk"]), RigidTransform.from_dict(meta["T_lt"]),
                   RigidTransform.from_dict(meta["T_mvs"]), MultiOutputGP.load(d / "e_lt"),
                   MultiOutputGP.load(d / "e_mvs_lt"), u, meta.get("instruments", {}))

