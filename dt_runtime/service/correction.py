"""The per-command path: bounded GPR correction and the Eq. 17 check of an MVS measurement.

A model that asks for more correction than configured (magnitude or change from the previous
command) is a fault, never a big move: the command is refused with CorrectionFault and the
robot is not moved. Targets outside the workspace box or speeds above the limit are refused
before the model is consulted; a corrected command outside the workspace is refused too, and,
when configured (`refuse_outside_volume`), one outside the calibrated volume (the DOE's hull plus
its margin), where the error model extrapolates. Each accepted command carries the uncertainty of
the position it reaches (Eq. 11 at that position, `Twin.correct`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from dt_kernel.config import Frozen
from dt_kernel.errors import DataError, TwinError, UnreachableError
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.twin import Twin


class CorrectionFault(TwinError):
    """The correction asked for is out of bounds, or an input is invalid; nothing was moved."""


class Limits(Frozen):
    """Bounds of every command, in metres (m/s for speed), each within a stated plausible range
    so that neither a typo (2.0 meant as mm) nor `.inf` can switch a safeguard off:
    workspace corners within +-5 m of the base and min < max on every axis; max_speed_m_s in
    (0, 5]; max_correction_m in (0, 0.05] (a cobot's error map corrects millimetres: 50 mm is
    already a broken model); max_correction_step_m in (0, 0.05];
    max_correction_gradient in (0, 1]."""

    workspace_min_m: tuple[float, float, float] = (0.2, -0.8, 0.05)
    workspace_max_m: tuple[float, float, float] = (1.6, 0.8, 1.3)
    max_speed_m_s: float = Field(1.0, gt=0, le=5.0)
    max_correction_m: float = Field(2.0e-3, gt=0, le=0.05)  # |c - target|
    # Change of the correction between consecutive commands: an allowance plus a bound on its
    # gradient along the path (the error map of an arm changes by a few mm per metre; a model
    # whose correction jumps faster than that is broken).
    max_correction_step_m: float = Field(0.2e-3, gt=0, le=0.05)
    max_correction_gradient: float = Field(0.01, gt=0, le=1.0)  # m of correction per m of travel
    # Refuse a command outside the calibrated volume instead of only flagging it.
    refuse_outside_volume: bool = False

    @model_validator(mode="after")
    def _check(self) -> Limits:
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if not all(math.isfinite(v) and abs(v) <= 5.0 for v in (*lo, *hi)):
            raise ValueError(f"workspace corners {list(lo)}, {list(hi)} m must be finite and within +-5 m "
                             "(metres, not mm)")
        if not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(f"workspace_min_m {list(lo)} must be below workspace_max_m {list(hi)} on every axis")
        return self


@dataclass(frozen=True)
class Corrected:
    target: np.ndarray
    command: np.ndarray
    correction: np.ndarray  # command - target (robot frame, m)
    u_tcp: np.ndarray  # standard uncertainty of the corrected TCP (Eq. 11 at this position), m
    U_tcp: np.ndarray  # expanded, 95 %
    inside: bool = True  # the command lies in the calibrated volume
    distance_m: float = float("nan")  # signed distance of the command to the DOE hull (< 0 inside)


class Corrector:
    def __init__(self, twin: Twin, limits: Limits):
        self.twin, self.limits = twin, limits
        self._lo, self._hi = np.array(limits.workspace_min_m), np.array(limits.workspace_max_m)
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        b = twin.uncertainty.tcp_c  # Eq. 11
        self._u, self._U = b.u, b.U

    def _check_target(self, target: np.ndarray, speed: float) -> np.ndarray:
        target = np.asarray(target, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)):
            raise CorrectionFault(f"target {target!r} is not a finite 3-vector")
        if not (np.isfinite(speed) and 0 < speed <= self.limits.max_speed_m_s):
            raise CorrectionFault(f"speed {speed!r} m/s outside (0, {self.limits.max_speed_m_s}]")
        if np.any(target < self._lo) or np.any(target > self._hi):
            raise CorrectionFault(f"target {np.round(target * 1e3, 1).tolist()} mm outside the workspace "
                                  f"{(self._lo * 1e3).tolist()} .. {(self._hi * 1e3).tolist()} mm")
        return target

    def uncorrected(self, target: np.ndarray, speed: float) -> Corrected:
        """The target commanded as is (the twin's correction is not trusted): the same checks of
        target and speed; no uncertainty is claimed (NaN). The next corrected command starts a
        new step sequence."""
        target = self._check_target(target, speed)
        self._last = None
        nan = np.full(3, np.nan)
        return Corrected(target, target.copy(), np.zeros(3), nan, nan, True, float("nan"))

    def __call__(self, target: np.ndarray, speed: float, cond: Conditions | None = None) -> Corrected:
        """The bounded correction of `target` at `speed` under the cell's conditions `cond` (what
        the twin's maps read beside the command: `Twin.needs`); CorrectionFault if refused."""
        target = self._check_target(target, speed)
        try:
            res = self.twin.correct(target, speed, cond)
        except (DataError, UnreachableError, FloatingPointError, np.linalg.LinAlgError) as exc:
            # a condition missing, no IK, a NaN map: refused, never a crash of the loop
            raise CorrectionFault(f"no correction for target {np.round(target * 1e3, 1).tolist()} mm: {exc}") from exc
        c = res.command
        corr = c - target
        if not np.all(np.isfinite(corr)) or not np.all(np.isfinite(res.U)):
            raise CorrectionFault("the error model returned NaN")
        # The corrected command, not only the target, must lie in the workspace.
        if np.any(c < self._lo) or np.any(c > self._hi):
            raise CorrectionFault(f"corrected command {np.round(c * 1e3, 1).tolist()} mm outside the workspace "
                                  f"{(self._lo * 1e3).tolist()} .. {(self._hi * 1e3).tolist()} mm")
        if not res.inside and self.limits.refuse_outside_volume:
            raise CorrectionFault(f"command {np.round(c * 1e3, 1).tolist()} mm lies {res.distance_m * 1e3:.1f} mm "
                                  "outside the calibrated volume (the error model would extrapolate)")
        mag = float(np.linalg.norm(corr))
        if mag > self.limits.max_correction_m:
            raise CorrectionFault(f"correction {mag * 1e3:.3f} mm exceeds the bound "
                                  f"{self.limits.max_correction_m * 1e3:.3f} mm")
        if self._last is not None:
            last_target, last_corr = self._last
            why = _step_fault(self.limits, float(np.linalg.norm(corr - last_corr)),
                              float(np.linalg.norm(target - last_target)))
            if why:
                raise CorrectionFault(why)
        self._last = (target, corr)
        if res.budget is None:  # an older twin: the global Eq. 11 figures
            return Corrected(target, c, corr, self._u, self._U, res.inside, res.distance_m)
        return Corrected(target, c, corr, res.budget.combined(), res.U, res.inside, res.distance_m)


def _step_fault(limits: Limits, step: float, travel: float) -> str:
    """Why a change of the correction by `step` over `travel` (m) breaks the step bound ('' if not)."""
    bound = limits.max_correction_step_m + limits.max_correction_gradient * travel
    if step > bound:
        return (f"correction changes by {step * 1e3:.3f} mm over {travel * 1e3:.1f} mm of travel, "
                f"bound {bound * 1e3:.3f} mm")
    return ""


def check_path_bounds(limits: Limits, targets: np.ndarray, commands: np.ndarray) -> str:
    """The bounded-correction rules of `Corrector` over a whole path's set-points (n, 3) m and
    their commands: why the first one that breaks them would be refused, or ''."""
    lo, hi = np.array(limits.workspace_min_m), np.array(limits.workspace_max_m)
    corr = commands - targets
    for k in range(len(targets)):
        c = commands[k]
        if not np.all(np.isfinite(c)):
            return f"set-point {k + 1}: no finite correction"
        if np.any(targets[k] < lo) or np.any(targets[k] > hi) or np.any(c < lo) or np.any(c > hi):
            return (f"set-point {k + 1}: target {np.round(targets[k] * 1e3, 1).tolist()} mm or its command outside "
                    f"the workspace {(lo * 1e3).tolist()} .. {(hi * 1e3).tolist()} mm")
        mag = float(np.linalg.norm(corr[k]))
        if mag > limits.max_correction_m:
            return (f"set-point {k + 1}: correction {mag * 1e3:.3f} mm exceeds the bound "
                    f"{limits.max_correction_m * 1e3:.3f} mm")
        if k:
            why = _step_fault(limits, float(np.linalg.norm(corr[k] - corr[k - 1])),
                              float(np.linalg.norm(targets[k] - targets[k - 1])))
            if why:
                return f"set-point {k + 1}: {why}"
    return ""


@dataclass(frozen=True)
class Check:
    t: np.ndarray  # (3,) Eq. 17
    p_value: np.ndarray
    passed: bool
    diff: np.ndarray  # e_LT_hat - e_MVS, GL, m
    predicted: np.ndarray  # e_MVS-LT_hat, GL, m


class Monitor:
    """Eq. 17 for one MVS measurement of a commanded position, against the twin's prediction."""

    def __init__(self, twin: Twin, alpha: float = 0.05):
        self.twin, self.alpha = twin, alpha
        b14, b16 = twin.uncertainty.e_lt_hat_minus_e_mvs, twin.uncertainty.e_mvs_lt_hat  # Eqs. 14, 16
        self._t_test = unc.TTestPlan.of(b14.u, b16.u, b14.dof, b16.dof, alpha)  # the same budgets every reading

    @property
    def t_crit(self) -> np.ndarray:
        """The critical |t| per axis (two-sided at alpha, Welch-Satterthwaite dof): a reading
        passes Eq. 17 on an axis when its |t| is at most this."""
        return self._t_test.t_crit

    @property
    def u(self) -> np.ndarray:
        """Eq. 17's combined standard uncertainty per axis, sqrt(u^2(diff) + u^2(pred)), m."""
        return self._t_test.u

    def __call__(self, command: np.ndarray, speed: float, p_mvs: np.ndarray, cond: Conditions | None = None,
                 u_extra: np.ndarray | None = None) -> Check:
        """Eq. 17 of `p_mvs` (MVS frame) against the arm at `command`; `u_extra` (per axis, m) adds
        a Type B component to the denominator (a moving arm's timing term, metrology.timing), the
        degrees of freedom kept (an infinite-dof term only raises them: the test stays conservative)."""
        p_mvs = np.asarray(p_mvs, dtype=float)
        if p_mvs.shape != (3,) or not np.all(np.isfinite(p_mvs)):
            raise CorrectionFault(f"MVS point {p_mvs!r} is not a finite 3-vector")
        tw = self.twin
        cmd_gl = tw.T_rdk.apply(command)
        e_mvs = cmd_gl - tw.T_mvs.apply(p_mvs)
        try:
            e_lt_hat = tw.T_rdk.R @ tw.e_lt_hat(command, speed, cond)[0]  # back to GL axes
            pred = tw.e_mvs_lt_hat(command, speed, cond)[0]
        except (DataError, UnreachableError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise CorrectionFault(f"no prediction at command {np.round(command * 1e3, 1).tolist()} mm: {exc}") from exc
        if not (np.all(np.isfinite(e_lt_hat)) and np.all(np.isfinite(pred))):
            raise CorrectionFault(f"the error model predicts NaN at command {np.round(command * 1e3, 1).tolist()} mm")
        plan = self._t_test
        if u_extra is not None and np.any(u_extra):
            plan = dataclasses.replace(plan, u=np.sqrt(plan.u ** 2 + np.asarray(u_extra, dtype=float) ** 2))
        tt = plan(e_lt_hat - e_mvs, pred)
        return Check(tt.t[0], tt.p_value[0], bool(tt.passed_all[0]), e_lt_hat - e_mvs, pred)
