"""GUM uncertainty budgets of the paper (Sect. 2.5, Eqs. 11-17), per axis (docs/architecture.md).

Every component carries its label (the paper's symbol), type, distribution, degrees of
freedom and equation, so the budget table falls out of the computation. Combination is the
law of propagation with unit sensitivities (as in the paper); expanded uncertainties use the
Student t coverage factor for the Welch-Satterthwaite effective dof (1.96 when dof = inf).
Units: metres inside; tables in mm.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

INF = float("inf")


@dataclass(frozen=True)
class Component:
    """One labelled component of a budget: standard uncertainty per axis (m), degrees of freedom,
    type ('A' or 'B'), distribution ('normal' or 'uniform') and a note (the equation).
    """
    label: str
    u: np.ndarray  # (3,) standard uncertainty per axis, m
    dof: float
    kind: str  # 'A' or 'B'
    distribution: str  # 'normal' or 'uniform'
    note: str = ""

    @classmethod
    def type_a(cls, label: str, s, dof: float, note: str = "") -> Component:
        """A Type A component from a standard deviation.

        Parameters
        ----------
        label : str
            The paper's symbol.
        s : float or array-like
            Standard uncertainty, scalar or per axis, m.
        dof : float
            Degrees of freedom.
        note : str, optional
            The equation it belongs to.

        Returns
        -------
        Component
        """
        return cls(label, np.abs(np.asarray(s, dtype=float)) * np.ones(3), float(dof), "A", "normal", note)

    @classmethod
    def uniform_from_bias(cls, label: str, mean, note: str = "") -> Component:
        """A mean error left uncorrected, as a uniform distribution of half-width |mean|.

        u^2 = mean^2 / 3 (the paper's e_bar^2 / 3 terms).

        Parameters
        ----------
        label : str
            The paper's symbol.
        mean : float or array-like
            The mean error, m.
        note : str, optional
            The equation it belongs to.

        Returns
        -------
        Component
        """
        return cls(label, np.abs(np.asarray(mean, dtype=float)) * np.ones(3) / np.sqrt(3), INF, "B", "uniform", note)

    @classmethod
    def uniform_from_resolution(cls, label: str, resol, note: str = "") -> Component:
        """Resolution as the paper writes it: u^2 = resol^2 / 3.

        Parameters
        ----------
        label : str
            The paper's symbol.
        resol : float or array-like
            The resolution, m.
        note : str, optional
            The equation it belongs to.

        Returns
        -------
        Component
        """
        return cls(label, np.abs(np.asarray(resol, dtype=float)) * np.ones(3) / np.sqrt(3), INF, "B", "uniform", note)

    @classmethod
    def from_std(cls, label: str, u, dof: float = INF, note: str = "", kind: str = "B") -> Component:
        """A normal component from a stated standard uncertainty.

        Parameters
        ----------
        label : str
            The paper's symbol.
        u : float or array-like
            Standard uncertainty, m.
        dof : float, optional
            Degrees of freedom (infinite by default).
        note : str, optional
            The equation it belongs to.
        kind : str, optional
            'A' or 'B'.

        Returns
        -------
        Component
        """
        return cls(label, np.abs(np.asarray(u, dtype=float)) * np.ones(3), float(dof), kind, "normal", note)

    def to_dict(self) -> dict[str, Any]:
        """JSON form; an infinite dof is written as null (strict JSON has no infinity)."""
        return {"label": self.label, "u": [float(x) for x in self.u],
                "dof": float(self.dof) if np.isfinite(self.dof) else None, "kind": self.kind,
                "distribution": self.distribution, "note": self.note}

    @classmethod
    def from_dict(cls, d: Any) -> Component:
        """The component `to_dict` wrote (a null dof is infinite).

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        Component
        """
        dof = d.get("dof")
        return cls(str(d["label"]), np.asarray(d["u"], dtype=float) * np.ones(3), INF if dof is None else float(dof),
                   str(d.get("kind", "B")), str(d.get("distribution", "normal")), str(d.get("note", "")))


def coverage_factor(dof, p: float = 0.95) -> np.ndarray:
    """Coverage factor for a level of confidence: Student t for finite dof, normal for infinite.

    Parameters
    ----------
    dof : float or array-like
        Degrees of freedom (values below 1 are taken as 1).
    p : float, optional
        Level of confidence.

    Returns
    -------
    ndarray
    """
    dof = np.asarray(dof, dtype=float)
    q = 0.5 + p / 2
    # scipy.special's quantiles are what stats.t.ppf / stats.norm.ppf compute, without the
    # ~0.15 ms of argument checking per call (this runs once per corrected command).
    return np.where(np.isfinite(dof), special.stdtrit(np.where(np.isfinite(dof), np.maximum(dof, 1), 1), q),
                    special.ndtri(q))


def welch_satterthwaite(us: np.ndarray, dofs: np.ndarray) -> np.ndarray:
    """Effective degrees of freedom, nu_eff = u_c^4 / sum(u_i^4 / nu_i), per axis.

    Parameters
    ----------
    us : ndarray
        (m, 3) standard uncertainties.
    dofs : ndarray
        (m,) or (m, 3) degrees of freedom (infinite terms add nothing).

    Returns
    -------
    ndarray
        (3,); infinite when every term is.
    """
    us = np.asarray(us, dtype=float)
    dofs = np.asarray(dofs, dtype=float)
    dofs = np.broadcast_to(dofs[:, None] if dofs.ndim == 1 else dofs, us.shape)
    uc2 = np.sum(us ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(np.isfinite(dofs), us ** 4 / dofs, 0.0)
        den = np.sum(terms, axis=0)
        return np.where(den > 0, uc2 ** 2 / np.where(den > 0, den, 1.0), INF)


@dataclass(frozen=True)
class Budget:
    """A named set of components, combined with unit sensitivities (root sum of squares)."""
    name: str
    components: tuple[Component, ...] = field(default_factory=tuple)

    def _u(self) -> np.ndarray:
        return np.array([c.u for c in self.components])

    def combined(self) -> np.ndarray:
        """Combined standard uncertainty per axis, m.

        Returns
        -------
        ndarray
            (3,).
        """
        return np.sqrt(np.sum(self._u() ** 2, axis=0))

    def effective_dof(self) -> np.ndarray:
        """Welch-Satterthwaite effective degrees of freedom per axis.

        Returns
        -------
        ndarray
            (3,).
        """
        return welch_satterthwaite(self._u(), np.array([c.dof for c in self.components]))

    def coverage_factor(self, p: float = 0.95) -> np.ndarray:
        """Coverage factor per axis for the effective degrees of freedom.

        Parameters
        ----------
        p : float, optional
            Level of confidence.

        Returns
        -------
        ndarray
            (3,).
        """
        return coverage_factor(self.effective_dof(), p)

    def expanded(self, p: float = 0.95) -> np.ndarray:
        """Expanded uncertainty per axis, k times the combined, m.

        Parameters
        ----------
        p : float, optional
            Level of confidence.

        Returns
        -------
        ndarray
            (3,).
        """
        return self.coverage_factor(p) * self.combined()

    def extend(self, name: str, more) -> Budget:
        """A new budget with more components.

        Parameters
        ----------
        name : str
            The new budget's name.
        more : Budget or iterable of Component
            The components to add.

        Returns
        -------
        Budget
        """
        extra = more.components if isinstance(more, Budget) else tuple(more)
        return Budget(name, self.components + extra)

    def table(self, unit: str = "mm") -> list[dict]:
        """The budget as table rows: one per component, then the combined row (dof, k, U).

        Parameters
        ----------
        unit : str, optional
            "mm" (default) or the metres the budget holds.

        Returns
        -------
        list of dict
        """
        f = 1e3 if unit == "mm" else 1.0
        uc2 = self.combined() ** 2
        rows: list[dict[str, Any]] = []
        for c in self.components:
            share = np.divide(c.u ** 2, uc2, out=np.zeros(3), where=uc2 > 0)
            rows.append({"component": c.label, "equation": c.note, "type": c.kind,
                         "distribution": c.distribution,
                         **{f"u_{a}_{unit}": float(c.u[k] * f) for k, a in enumerate("xyz")},
                         "dof": None if not np.isfinite(c.dof) else float(c.dof),
                         "share_pct": [round(float(s) * 100, 2) for s in share]})
        dof = self.effective_dof()
        k = self.coverage_factor()
        rows.append({"component": f"combined {self.name}", "equation": "", "type": "", "distribution": "",
                     **{f"u_{a}_{unit}": float(self.combined()[i] * f) for i, a in enumerate("xyz")},
                     "dof": [None if not np.isfinite(d) else round(float(d), 1) for d in dof],
                     "k": [round(float(x), 4) for x in k],
                     **{f"U_{a}_{unit}": float(self.expanded()[i] * f) for i, a in enumerate("xyz")}})
        return rows


def lt_standard_uncertainty(L_m: float) -> float:
    """Laser tracker calibration standard uncertainty: 10 um + 0.02 um/m * L (Sect. 2.5).

    Parameters
    ----------
    L_m : float
        Distance from the tracker, m.

    Returns
    -------
    float
        Standard uncertainty, m.
    """
    return 10e-6 + 0.02e-6 * float(L_m)


@dataclass(frozen=True)
class MetrologyInputs:
    """Per-axis statistics (m) feeding Eqs. 11-16. Stats tuples are (mean (3,), std (3,), n)."""

    reprod_tcp: np.ndarray
    reprod_tcp_dof: float
    resol_tcp: float
    reg_lt: tuple
    reg_mvs: tuple
    u_lt: float
    res_lt: tuple
    res_mvs_lt: tuple
    reprod_mvs: np.ndarray
    reprod_mvs_dof: float
    resol_mvs: float
    # How registration residuals enter: 'transform' propagates the uncertainty of the fitted
    # registration, s(e_GL)/sqrt(n); 'spread' adds the residual spread s(e_GL) itself, as the
    # paper's Eqs. 13-16 write it. The spread is mostly the robot's own error along the
    # registration lines, which e_LT and its GPR already carry: validated against the
    # simulator's truth it double counts (see docs/demo.md, "Honest uncertainty").
    registration_term: str = "transform"


def _stat_pair(sym: str, st: tuple, eq: str) -> tuple[Component, Component]:
    mean, std, n = st
    return (Component.type_a(f"s({sym})", std, n - 1, eq), Component.uniform_from_bias(f"mean({sym})", mean, eq))


def _reg_pair(sym: str, st: tuple, eq: str, mode: str) -> tuple[Component, Component]:
    mean, std, n = st
    if mode == "spread":
        return _stat_pair(sym, st, eq)
    if mode != "transform":
        raise ValueError(f"registration_term must be 'transform' or 'spread', not {mode!r}")
    return (Component.type_a(f"s({sym})/sqrt(n)", np.asarray(std) / np.sqrt(n), n - 1, eq + ", fitted transform"),
            Component.uniform_from_bias(f"mean({sym})", mean, eq))


def budget_e_lt_hat(inp: MetrologyInputs) -> Budget:
    """Eq. 13: registration of LT to GL, LT traceability, GPR residuals of e_LT.

    Parameters
    ----------
    inp : MetrologyInputs
        The per-axis statistics.

    Returns
    -------
    Budget
    """
    return Budget("u(e_LT_hat)", (*_reg_pair("e_LT,GL", inp.reg_lt, "Eq. 13", inp.registration_term),
                                  Component.from_std("u_LT", inp.u_lt, note="Eq. 13, LT calibration"),
                                  *_stat_pair("r_LT", inp.res_lt, "Eq. 13")))


def budget_tcp_corrected(inp: MetrologyInputs) -> Budget:
    """Eq. 11: the corrected TCP, u(TCP_c) = robot reproducibility and resolution + Eq. 13.

    Parameters
    ----------
    inp : MetrologyInputs
        The per-axis statistics.

    Returns
    -------
    Budget
    """
    return Budget("u(TCP_c)", (Component.type_a("reprod_TCP", inp.reprod_tcp, inp.reprod_tcp_dof, "Eqs. 11-12"),
                               Component.uniform_from_resolution("resol_TCP", inp.resol_tcp, "Eq. 11"))
                  + budget_e_lt_hat(inp).components)


MODEL_TERM = "s(r_LT)"  # Eq. 11's model component: the held-out spread of the e_LT model


def budget_tcp_corrected_at(rest: Budget, u_model: np.ndarray, model_dof: float,
                            u_extrapolation: np.ndarray, extrapolation_dof: float) -> Budget:
    """Eq. 11 at one corrected position.

    The model's standard uncertainty at that position is u_model = lambda sigma_GP(c) (the GP's
    latent standard deviation scaled by its held-out calibration); outside the calibrated hull,
    u_extrapolation = kappa d(c) (see `twin.calibration`).

    Parameters
    ----------
    rest : Budget
        The position-independent components (Eq. 11 without its global model spread s(r_LT)).
    u_model : ndarray
        (3,) the model's standard uncertainty at the position, m.
    model_dof : float
        Its degrees of freedom.
    u_extrapolation : ndarray
        (3,) the extrapolation term, m.
    extrapolation_dof : float
        Its degrees of freedom.

    Returns
    -------
    Budget
    """
    return rest.extend("u(TCP_c) at c", (
        Component.type_a("lambda sigma_GP(c)", u_model, model_dof, "Eq. 11, the e_LT model at the position"),
        Component.type_a("kappa d(c)", u_extrapolation, extrapolation_dof,
                         "Eq. 11, extrapolation beyond the DOE hull")))


def _mvs_components(inp: MetrologyInputs) -> tuple[Component, ...]:
    return (Component.type_a("reprod_MVS", inp.reprod_mvs, inp.reprod_mvs_dof, "Eqs. 12, 15"),
            Component.uniform_from_resolution("resol_MVS", inp.resol_mvs, "Eq. 15"),
            *_reg_pair("e_MVS,GL", inp.reg_mvs, "Eq. 15", inp.registration_term))


def budget_e_mvs(inp: MetrologyInputs) -> Budget:
    """Eq. 15: an MVS measurement in GL.

    Parameters
    ----------
    inp : MetrologyInputs
        The per-axis statistics.

    Returns
    -------
    Budget
    """
    return Budget("u(e_MVS)", _mvs_components(inp))


def budget_elt_minus_emvs(inp: MetrologyInputs) -> Budget:
    """Eq. 14: u(e_LT_hat - e_MVS) = Eq. 13 combined with Eq. 15.

    Parameters
    ----------
    inp : MetrologyInputs
        The per-axis statistics.

    Returns
    -------
    Budget
    """
    return budget_e_lt_hat(inp).extend("u(e_LT_hat - e_MVS)", _mvs_components(inp))


def budget_e_mvs_lt_hat(inp: MetrologyInputs) -> Budget:
    """Eq. 16: the predicted MVS-LT error.

    Parameters
    ----------
    inp : MetrologyInputs
        The per-axis statistics.

    Returns
    -------
    Budget
    """
    return Budget("u(e_MVS-LT_hat)", (*_reg_pair("e_LT,GL", inp.reg_lt, "Eq. 16", inp.registration_term),
                                      *_reg_pair("e_MVS,GL", inp.reg_mvs, "Eq. 16", inp.registration_term),
                                      *_stat_pair("r_MVS-LT", inp.res_mvs_lt, "Eq. 16"),
                                      Component.type_a("reprod_MVS", inp.reprod_mvs, inp.reprod_mvs_dof, "Eq. 16"),
                                      Component.uniform_from_resolution("resol_MVS", inp.resol_mvs, "Eq. 16"),
                                      Component.from_std("u_LT", inp.u_lt, note="Eq. 16")))


@dataclass(frozen=True)
class TTest:
    """Eq. 17 results: t, dof, two-sided p-value and critical t per axis, and whether each passed."""
    t: np.ndarray  # (n,3)
    dof: np.ndarray  # (3,)
    p_value: np.ndarray  # (n,3), two-sided
    t_crit: np.ndarray  # (3,)
    passed: np.ndarray  # (n,3)

    @property
    def passed_all(self) -> np.ndarray:
        """Per row, whether all three axes passed."""
        return np.all(self.passed, axis=1)


@dataclass(frozen=True)
class TTestPlan:
    """Eq. 17 with its uncertainties fixed: the combined u, the Welch-Satterthwaite dof and the
    critical t are computed once (the daemon tests every MVS reading against the same budgets),
    each call computes only t and its p-value."""

    u: np.ndarray  # sqrt(u^2(diff) + u^2(pred))
    dof: np.ndarray
    d: np.ndarray  # dof for the t distribution (infinite -> 1e12)
    t_crit: np.ndarray

    @classmethod
    def of(cls, u_diff, u_pred, dof_diff, dof_pred, alpha: float = 0.05) -> TTestPlan:
        """The plan for fixed uncertainties.

        Parameters
        ----------
        u_diff, u_pred : float or array-like
            Standard uncertainties of the measured difference and of the prediction, m.
        dof_diff, dof_pred : float or array-like
            Their degrees of freedom.
        alpha : float, optional
            Two-sided significance level.

        Returns
        -------
        TTestPlan
        """
        u_diff, u_pred = np.asarray(u_diff, dtype=float), np.asarray(u_pred, dtype=float)
        u = np.sqrt(u_diff ** 2 + u_pred ** 2)
        dof = welch_satterthwaite(np.array([u_diff * np.ones(3), u_pred * np.ones(3)]),
                                  np.array([np.asarray(dof_diff, dtype=float) * np.ones(3),
                                            np.asarray(dof_pred, dtype=float) * np.ones(3)]))
        d = np.where(np.isfinite(dof), dof, 1e12)
        return cls(u, dof, d, special.stdtrit(d, 1 - alpha / 2))  # = stats.t.ppf(1 - alpha / 2, d)

    def __call__(self, diff, predicted) -> TTest:
        t = (np.atleast_2d(diff) - np.atleast_2d(predicted)) / self.u
        p = 2 * special.stdtr(self.d, -np.abs(t))  # = 2 stats.t.sf(|t|, d), two-sided
        return TTest(t, self.dof, p, self.t_crit, np.abs(t) <= self.t_crit)


def t_test(diff, predicted, u_diff, u_pred, dof_diff, dof_pred, alpha: float = 0.05) -> TTest:
    """Eq. 17: t = ((e_LT_hat - e_MVS) - e_MVS-LT_hat) / sqrt(u^2(diff) + u^2(pred)), per axis.

    Two-sided at level alpha, dof by Welch-Satterthwaite of the two uncertainties.

    Parameters
    ----------
    diff : array-like
        (n, 3) or (3,) measured differences e_LT_hat - e_MVS, m.
    predicted : array-like
        The predicted e_MVS-LT_hat, same shape.
    u_diff, u_pred : float or array-like
        Their standard uncertainties, m.
    dof_diff, dof_pred : float or array-like
        Their degrees of freedom.
    alpha : float, optional
        Significance level.

    Returns
    -------
    TTest
    """
    return TTestPlan.of(u_diff, u_pred, dof_diff, dof_pred, alpha)(diff, predicted)


def precision_figures(s_e_mvs_doe: np.ndarray, budget_pred: Budget) -> dict:
    """Sect. 3.3: precision as is, 2 s(e_MVS,DOE), against U(e_MVS-LT_hat) (Eq. 22).

    Parameters
    ----------
    s_e_mvs_doe : ndarray
        (3,) standard deviation of e_MVS over the DOE, m.
    budget_pred : Budget
        The Eq. 16 budget.

    Returns
    -------
    dict
        Before and after per axis and averaged (mm), and the improvement (%).
    """
    before = 2 * np.asarray(s_e_mvs_doe)
    after = budget_pred.expanded()
    b, a = float(before.mean() * 1e3), float(after.mean() * 1e3)
    return {"before_mm": (before * 1e3).tolist(), "after_mm": (after * 1e3).tolist(),
            "before_avg_mm": b, "after_avg_mm": a, "improvement_pct": 100 * (1 - a / b)}
