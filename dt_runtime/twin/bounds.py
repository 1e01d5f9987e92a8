"""The bounds every command of a cell passes around the correction law (`twin.corrector`): a
target or speed out of bounds, or a correction too large or changing too fast, is refused with
CorrectionFault and the robot is not moved (docs/service.md, "Inside the daemon").

CorrectionFault (dt_kernel.errors) is what a refusal raises: a bus client of the correction service
raises it too without loading the twin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from dt_kernel.config import Frozen
from dt_kernel.errors import CorrectionFault, DataError, UnreachableError
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.twin import Twin


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
    """A command that passed the bounds.

    Attributes
    ----------
    target, command, correction : ndarray
        (3,) m, robot frame; correction = command - target.
    u_tcp, U_tcp : ndarray
        (3,) m, standard and expanded (95 %) uncertainty of the position reached (Eq. 11 there),
        per GL axis; NaN for a target sent uncorrected.
    inside : bool
        The command lies in the calibrated volume.
    distance_m : float
        Signed distance of the command to the DOE hull (m, < 0 inside), NaN if unknown.
    """

    target: np.ndarray
    command: np.ndarray
    correction: np.ndarray
    u_tcp: np.ndarray
    U_tcp: np.ndarray
    inside: bool = True
    distance_m: float = float("nan")


class Guard:
    """The twin's correction law (`Corrector`) behind a cell's bounds: the target and speed checked
    before, the command, its size and its change from the previous command after.

    Parameters
    ----------
    twin : Twin
        The calibrated twin; its own corrector is used unless `corrector` is given.
    limits : Limits
        The cell's bounds.
    corrector : Corrector or None
        The law to guard (a server or loop that keeps its own state); None: `twin.corrector`.
    """

    def __init__(self, twin: Twin, limits: Limits, corrector: Corrector | None = None):
        self.twin, self.limits = twin, limits
        self.corrector = twin.corrector if corrector is None else corrector
        self._lo, self._hi = np.array(limits.workspace_min_m), np.array(limits.workspace_max_m)
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        b = twin.uncertainty.tcp_c  # Eq. 11 (u: the GUM figure; U: as the law states it, conformal factor included)
        self._u, self._U = b.u, twin.conformal.factor * b.U

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
        new step sequence.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s.

        Returns
        -------
        Corrected
        """
        target = self._check_target(target, speed)
        self._last = None
        nan = np.full(3, np.nan)
        return Corrected(target, target.copy(), np.zeros(3), nan, nan, True, float("nan"))

    def __call__(self, target: np.ndarray, speed: float, cond: Conditions | None = None) -> Corrected:
        """The bounded correction of a target.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s.
        cond : Conditions or None
            The cell's conditions (what the twin's maps read beside the command: `Twin.needs`).

        Returns
        -------
        Corrected

        Raises
        ------
        CorrectionFault
            The target, speed or correction is out of bounds, or the map gives none.
        """
        target = self._check_target(target, speed)
        try:
            res = self.corrector.correct(target, speed, cond)
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
        budget = self.corrector.budget(res)
        if budget is None:  # an older twin: the global Eq. 11 figures
            return Corrected(target, c, corr, self._u, self._U, res.inside, res.distance_m)
        return Corrected(target, c, corr, budget.combined(), res.U, res.inside, res.distance_m)


def _step_fault(limits: Limits, step: float, travel: float) -> str:
    """Why a change of the correction by `step` over `travel` (m) breaks the step bound ('' if not)."""
    bound = limits.max_correction_step_m + limits.max_correction_gradient * travel
    if step > bound:
        return (f"correction changes by {step * 1e3:.3f} mm over {travel * 1e3:.1f} mm of travel, "
                f"bound {bound * 1e3:.3f} mm")
    return ""


def check_path_bounds(limits: Limits, targets: np.ndarray, commands: np.ndarray) -> str:
    """The rules of `Guard` over a whole path's set-points: why the first one that breaks them
    would be refused, or ''.

    Parameters
    ----------
    limits : Limits
        The cell's bounds.
    targets, commands : ndarray
        (n, 3) m, the set-points and their corrected commands.

    Returns
    -------
    str
    """
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
