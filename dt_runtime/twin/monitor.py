"""Eq. 17 for a camera (MVS) measurement of a commanded position, against the twin's
prediction: the in-service check of the twin (docs/service.md, "Inside the daemon").
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError, UnreachableError
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.twin.bounds import CorrectionFault
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.twin import Twin


@dataclass(frozen=True)
class Check:
    """The Eq. 17 check of one camera measurement.

    Attributes
    ----------
    t : ndarray
        (3,) Eq. 17's t per GL axis.
    p_value : ndarray
        (3,) two-sided p-value per axis.
    passed : bool
        Every axis passes at the monitor's alpha.
    diff : ndarray
        (3,) m, e_LT_hat - e_MVS, GL axes.
    predicted : ndarray
        (3,) m, e_MVS-LT_hat, GL axes.
    """

    t: np.ndarray  # (3,) Eq. 17
    p_value: np.ndarray
    passed: bool
    diff: np.ndarray  # e_LT_hat - e_MVS, GL, m
    predicted: np.ndarray  # e_MVS-LT_hat, GL, m


class Monitor:
    """Eq. 17 for one MVS measurement of a commanded position, against the twin's prediction.

    Parameters
    ----------
    twin : Twin
        The calibrated twin: its budgets of Eqs. 14 and 16 make the test's denominator.
    alpha : float
        Significance level of the two-sided test.
    """

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
        degrees of freedom kept (an infinite-dof term only raises them: the test stays conservative).

        Parameters
        ----------
        command : ndarray
            (3,) m, the commanded position (robot frame).
        speed : float
            m/s.
        p_mvs : ndarray
            (3,) m, the camera's measurement (MVS frame).
        cond : Conditions or None
            What the maps read beside the command (`Twin.needs`).
        u_extra : ndarray or None
            (3,) m, an extra standard uncertainty per axis.

        Returns
        -------
        Check

        Raises
        ------
        CorrectionFault
            `p_mvs` is not a finite 3-vector, or the maps give no finite prediction at `command`.
        """
        p_mvs = np.asarray(p_mvs, dtype=float)
        if p_mvs.shape != (3,) or not np.all(np.isfinite(p_mvs)):
            raise CorrectionFault(f"MVS point {p_mvs!r} is not a finite 3-vector")
        tw = self.twin
        cmd_gl = tw.T_rdk.apply(command)
        e_mvs = cmd_gl - tw.T_mvs.apply(p_mvs)
        try:
            e_lt, pred = tw.predicted_means(command, speed, cond)
            e_lt_hat = tw.T_rdk.R @ e_lt  # back to GL axes
        except (DataError, UnreachableError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise CorrectionFault(f"no prediction at command {np.round(command * 1e3, 1).tolist()} mm: {exc}") from exc
        if not (np.all(np.isfinite(e_lt_hat)) and np.all(np.isfinite(pred))):
            raise CorrectionFault(f"the error model predicts NaN at command {np.round(command * 1e3, 1).tolist()} mm")
        plan = self._t_test
        if u_extra is not None and np.any(u_extra):
            plan = dataclasses.replace(plan, u=np.sqrt(plan.u ** 2 + np.asarray(u_extra, dtype=float) ** 2))
        tt = plan(e_lt_hat - e_mvs, pred)
        return Check(tt.t[0], tt.p_value[0], bool(tt.passed_all[0]), e_lt_hat - e_mvs, pred)
