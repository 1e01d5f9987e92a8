"""The `dt demo` report: one self-contained HTML file for a metrologist.

`write_demo_report(result, path)` renders a `DemoResult` (summary dict in mm, arrays in SI:
metres and m/s; errors e = commanded - measured in the global frame GL, paper Eq. 8) into
headline figures, the paper's Tables 2-4, the GUM budgets and Eqs. 18-22, and Figs. 8-18
style plots. Every block is built independently: a missing summary key or array (e.g.
`e_true_doe` on real hardware) replaces that block by a note instead of failing the demo.

The generic pieces (`fig_to_img_tag`, `html_table`, `html_page`, ...) live in
`dt_runtime.htmlreport` and are re-exported here for other reports.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.metrology.stats import finite_rows, rms_with_U, t95, wilson_interval
from dt_runtime.reports.html import (  # noqa: F401  (re-exported helper API)
    Section,
    esc,
    fig_to_img_tag,
    figure_block,
    fmt_value,
    headline,
    html_page,
    html_table,
    note,
    paragraph,
    plt,
)

log = logging.getLogger(__name__)

MAGNIFY = 200  # Fig. 15: uncertainty boxes magnified x200 for visibility

# The paper's published values, shown beside ours for orientation (mm).
PAPER_U = {"eq18_tcp_c": (0.118, 0.109, 0.171), "eq19_e_lt_hat": (0.117, 0.108, 0.170),
           "eq20_e_lt_hat_minus_e_mvs": (0.203, 0.182, 0.198), "eq21_e_mvs": (0.166, 0.146, 0.102),
           "eq22_e_mvs_lt_hat": (0.230, 0.204, 0.214)}
EQ_LABEL = {"eq18_tcp_c": "Eq. 18  U(TCP_c)", "eq19_e_lt_hat": "Eq. 19  U(ê_LT)",
            "eq20_e_lt_hat_minus_e_mvs": "Eq. 20  U(ê_LT − e_MVS)", "eq21_e_mvs": "Eq. 21  U(e_MVS)",
            "eq22_e_mvs_lt_hat": "Eq. 22  U(ê_MVS-LT)"}
NAME_LABEL = {"rdk": "e_RDK,GL (robot encoders)", "lt": "e_LT,GL (laser tracker)", "mvs": "e_MVS,GL (camera system)",
              "e_lt_doe": "e_LT,DOE", "e_mvs_doe": "e_MVS,DOE", "e_mvs_lt_doe": "e_MVS-LT,DOE",
              "r_lt": "r_LT (held-out)", "r_mvs_lt": "r_MVS-LT (held-out)",
              "r_lt_replicate_means": "r_LT, replicate means", "r_mvs_lt_replicate_means": "r_MVS-LT, replicate means",
              "reprod_tcp": "reprod_TCP (encoders, Eq. 12)", "reprod_mvs": "reprod_MVS (camera system, Eq. 12)"}
COLORS = {"x": "#1f77b4", "y": "#2ca02c", "z": "#d62728"}


class Missing(Exception):
    """Data for a block is absent; the block becomes a note."""


# ---------------------------------------------------------------------------------------------
# small utilities

def _get(d: dict, *keys):
    cur: Any = d
    for k in keys:
        if not isinstance(cur, dict) or k not in cur or cur[k] is None:
            raise Missing(f"summary has no '{'.'.join(keys)}'")
        cur = cur[k]
    return cur


@overload
def _arr(arrays: dict, key: str, cols: int | None = None, required: Literal[True] = True) -> np.ndarray: ...


@overload
def _arr(arrays: dict, key: str, cols: int | None = None, *, required: bool) -> np.ndarray | None: ...


def _arr(arrays: dict, key: str, cols: int | None = None, required: bool = True) -> np.ndarray | None:
    """`arrays[key]` as a float array (n, >= cols); None only when not `required` and absent."""
    v = arrays.get(key) if isinstance(arrays, dict) else None
    if v is None:
        if required:
            raise Missing(f"array '{key}' not available")
        return None
    a = np.asarray(v, dtype=float)
    if cols is not None and (a.ndim != 2 or a.shape[1] < cols):
        if a.ndim == 1 and a.size == cols:
            return a
        raise Missing(f"array '{key}' has shape {a.shape}, expected (n, {cols})")
    if a.size == 0:
        raise Missing(f"array '{key}' is empty")
    return a




def _f(v, nd: int = 3) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "–"
    if not math.isfinite(x):
        return "∞" if x == math.inf else "NaN"
    out = f"{x:.{nd}f}"
    return out[1:] if out.startswith("-") and float(out) == 0 else out  # no "-0.000"








def _levels(v: np.ndarray, max_levels: int = 12, bins: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Level index per sample and level centres: the factor's own levels if few, else quantile bins."""
    r = np.round(v, 6)
    uniq = np.unique(r)
    if len(uniq) <= max_levels:
        return np.searchsorted(uniq, r), uniq
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    centres = np.array([v[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(edges) - 1)])
    return idx, centres


def _unique_in_order(p: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    key = np.round(p / tol).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return p[np.sort(first)]


# ---------------------------------------------------------------------------------------------
# tables

def _mean_std_table(d: dict, names: list[str] | None = None, caption: str = "") -> str:
    names = names or [k for k, v in d.items() if isinstance(v, dict)]
    rows = []
    for name in names:
        s = d.get(name)
        if not isinstance(s, dict):
            continue
        row: dict[str, Any] = {"quantity": NAME_LABEL.get(name, name)}
        for ax in AXES:
            a = s.get(ax) or {}
            row[f"{ax}: ē / mm"] = _f(a.get("mean_mm"))
            row[f"{ax}: s(e) / mm"] = _f(a.get("std_mm"))
        row["n"] = s.get("n")
        rows.append(row)
    if not rows:
        raise Missing("no per-axis mean/std entries")
    return html_table(rows, caption=caption, row_header="quantity")


def _tables_registration(s: dict, a: dict) -> str:
    t2 = _get(s, "table2_registration_residuals")
    out = _mean_std_table(t2, caption="Table 2: registration residuals of the rototranslations (Eqs. 5-7), "
                                      "mean ē and standard deviation s(e) per GL axis")
    out += paragraph("A mean near zero is what a least-squares registration gives by construction; the standard "
                     "deviation enters the budgets as the registration reproducibility (paper, Table 2: LT 0.046, "
                     "0.042, 0.032 mm; MVS 0.080, 0.070, 0.042 mm).")
    return out


def _table_reprod(s: dict, a: dict) -> str:
    r = _get(s, "reproducibility_mm")
    paper = {"reprod_tcp": (0.0037, 0.0059, 0.0072), "reprod_mvs": (0.023, 0.019, 0.028)}
    rows = []
    for k, v in r.items():
        v = list(v) if v is not None else [None] * 3
        rows.append({"quantity": NAME_LABEL.get(k, k), **{f"{ax} / mm": _f(v[i], 4) for i, ax in enumerate(AXES)},
                     "paper / mm": ", ".join(f"{p:.4f}" for p in paper[k]) if k in paper else "–"})
    return html_table(rows, caption="Positioning reproducibilities from replicated registration positionings "
                                    "(standard deviations, Eq. 12)", row_header="quantity")


def _table_asis(s: dict, a: dict) -> str:
    t3 = _get(s, "table3_as_is")
    return (_mean_std_table(t3, caption="Table 3: the arm as is (no correction): errors e = commanded − measured "
                                        "over the DOE, in GL")
            + paragraph("ē is the systematic error (accuracy), s(e) its dispersion (precision). These are what the "
                        "twin's GPR models learn and remove."))


def _table_model_residuals(s: dict, a: dict) -> str:
    t4 = _get(s, "table4_model_residuals_cv")
    out = _mean_std_table(t4, caption="Table 4: cross-validated residuals r = e − ê of the GPR error models")
    if isinstance(t4.get("note"), str):
        out += note(t4["note"])
    out += paragraph("Residuals of models that never saw the target point: ē near zero means the correction is "
                     "unbiased; s(r) is the model's prediction reproducibility that enters Eq. 13.")
    return out


def _table_expanded(s: dict, a: dict) -> str:
    eu = _get(s, "expanded_uncertainty_95")
    rows = []
    for key, v in eu.items():
        if not isinstance(v, dict):
            continue
        U, k, dof = (list(v.get(n) or [None] * 3) for n in ("U_mm", "k", "dof_eff"))
        rows.append({"quantity": EQ_LABEL.get(key, key),
                     **{f"U_{ax} / mm": _f(U[i]) for i, ax in enumerate(AXES)},
                     **{f"k_{ax}": _f(k[i], 3) for i, ax in enumerate(AXES)},
                     **{f"ν_eff,{ax}": ("∞" if dof[i] is None else _f(dof[i], 1)) for i, ax in enumerate(AXES)},
                     "paper U / mm": ", ".join(f"{p:.3f}" for p in PAPER_U[key]) if key in PAPER_U else "–"})
    if not rows:
        raise Missing("no expanded uncertainties")
    return (html_table(rows, caption="Expanded uncertainties at 95 % coverage (Eqs. 18-22); k = t_0.975(ν_eff), "
                                     "ν_eff by Welch-Satterthwaite", row_header="quantity")
            + paragraph("U is the half-width of the interval expected to contain the true value with 95 % "
                        "probability; k follows from the effective degrees of freedom, not a fixed 2."))


def _table_precision(s: dict, a: dict) -> str:
    pp = _get(s, "precision_per_axis")
    b = list(pp.get("before_2s_e_mvs_doe_mm") or [None] * 3)
    af = list(pp.get("after_U_e_mvs_lt_hat_mm") or [None] * 3)
    rows = []
    for i, ax in enumerate(AXES):
        try:
            imp = 100 * (1 - float(af[i]) / float(b[i]))
        except (TypeError, ValueError, ZeroDivisionError):
            imp = float("nan")
        rows.append({"axis": ax, "before: 2 s(e_MVS,DOE) / mm": _f(b[i]), "after: U(ê_MVS-LT) / mm": _f(af[i]),
                     "improvement / %": _f(imp, 1)})
    rows.append({"axis": "mean", "before: 2 s(e_MVS,DOE) / mm": _f(s.get("precision_before_mm")),
                 "after: U(ê_MVS-LT) / mm": _f(s.get("precision_after_mm")),
                 "improvement / %": _f(s.get("improvement_pct"), 1)})
    return html_table(rows, caption="Tracking precision per axis (Sect. 3.3; paper: 1.256/0.958/0.576 mm → "
                                    "0.230/0.204/0.214 mm)", row_header="axis")


def _pretty_key(k: str) -> str:
    if k.endswith("_mm"):
        return k[:-3] + " / mm"
    return {"share_pct": "share of u_c² / % (x, y, z)", "dof": "ν (dof)", "k": "k (x, y, z)"}.get(k, k)


def _tables_budgets(s: dict, a: dict) -> str:
    budgets = _get(s, "budgets")
    out = [paragraph("One row per uncertainty component (standard uncertainties u, mm), then the combined "
                     "standard uncertainty u_c, the coverage factor k and the expanded uncertainty U. "
                     "ν = ∞ marks a component taken as exactly known (type B without dof).")]
    for name, rows in budgets.items():
        if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
            out.append(note(f"budget '{name}' has no rows"))
            continue
        cols: list[str] = []
        for r in rows:
            cols += [k for k in r if k not in cols]
        out.append(f"<h3>{esc(name)}</h3>")
        out.append(html_table(rows, cols, headers={c: _pretty_key(c) for c in cols}, none="∞", digits=4))
    return "".join(out)


def _table_literal(s: dict, a: dict) -> str:
    lit = _get(s, "paper_literal_budget")
    rows = [{"item": k, "value": v} for k, v in lit.items() if k != "note"]
    out = html_table(rows, caption="Variant: the paper's literal budget (values in mm or %)", row_header="item")
    if isinstance(lit.get("note"), str):
        out += note(lit["note"])
    return out


def _table_coverage(s: dict, a: dict) -> str:
    cov = _get(s, "coverage_95")
    n = s.get("n_validation")
    U = _arr(a, "U_tcp_c", required=False)
    rows = []
    for i, ax in enumerate(AXES):
        c = cov.get(ax)
        row = {"axis": ax, "coverage / %": _f(100 * c, 1) if c is not None else "–"}
        if n and c is not None:
            k = int(round(float(c) * n))
            lo, hi = wilson_interval(k, int(n))
            row["inside / n"] = f"{k} / {n}"
            row["95 % interval (Wilson) / %"] = f"{100 * lo:.1f} – {100 * hi:.1f}"
        if U is not None and U.ndim == 1 and U.size == 3:
            row["U(TCP_c) / mm"] = _f(U[i] * MM_PER_M)
        rows.append(row)
    return (html_table(rows, caption="Coverage of the 95 % expanded uncertainty U(TCP_c) by the true error of the "
                                     "corrected validation positionings", row_header="axis")
            + paragraph("If the uncertainty statement is right, about 95 % of the true errors lie inside ±U; "
                        "the interval shows how far a finite validation set can confirm that."))


def _t_crit_and_flags(s: dict, a: dict):
    """Eq. 17: t-values and the two-sided 95 % critical value per axis, rebuilt exactly as
    dt_runtime.metrology.uncertainty.t_test does (u = U/k, Welch-Satterthwaite of the two dofs)."""
    eu = s.get("expanded_uncertainty_95") or {}
    d, p = eu.get("eq20_e_lt_hat_minus_e_mvs"), eu.get("eq22_e_mvs_lt_hat")
    tcrit = np.full(3, 1.959964)
    u = None
    if isinstance(d, dict) and isinstance(p, dict):
        try:
            u1 = np.asarray(d["U_mm"], float) / np.asarray(d["k"], float) / MM_PER_M
            u2 = np.asarray(p["U_mm"], float) / np.asarray(p["k"], float) / MM_PER_M
            n1 = np.array([np.inf if x is None else x for x in d["dof_eff"]], float)
            n2 = np.array([np.inf if x is None else x for x in p["dof_eff"]], float)
            u = np.sqrt(u1 ** 2 + u2 ** 2)
            den = u1 ** 4 / n1 + u2 ** 4 / n2
            dof = np.where(den > 0, u ** 4 / np.where(den > 0, den, 1), np.inf)
            tcrit = np.array([t95(x) for x in dof])
        except (KeyError, TypeError, ValueError):
            pass
    return tcrit, u


def _table_ttest(s: dict, a: dict) -> str:
    tt = _get(s, "t_test_eq17")
    tcrit, _ = _t_crit_and_flags(s, a)
    per = tt.get("pass_fraction_per_axis") or {}
    rows = [{"axis": ax, "pass / %": _f(100 * per[ax], 1) if per.get(ax) is not None else "–",
             "t_crit (95 %, two-sided)": _f(tcrit[i], 3)} for i, ax in enumerate(AXES)]
    allp = tt.get("pass_fraction_all_axes")
    rows.append({"axis": "all three axes", "pass / %": _f(100 * allp, 1) if allp is not None else "–",
                 "t_crit (95 %, two-sided)": ""})
    return (html_table(rows, caption=f"Eq. 17 t-test on {tt.get('n', '?')} corrected validation measurements: "
                                     "t = ((ê_LT − e_MVS) − ê_MVS-LT) / sqrt(u²(ê_LT − e_MVS) + u²(ê_MVS-LT))",
                       row_header="axis")
            + paragraph("A measurement passes when |t| ≤ t_crit: the camera-tracked error agrees with the twin's "
                        "prediction within the stated uncertainty. In a healthy cell about 95 % pass per axis; a "
                        "persistent drop would trigger maintenance."))


def _table_run(s: dict, a: dict) -> str:
    keys = ["scenario", "quick", "seed", "n_validation", "n_refusals", "elapsed_s", "units"]
    rows = [{"item": k, "value": s[k]} for k in keys if k in s]
    if not rows:
        raise Missing("no run information")
    out = html_table(rows, row_header="item")
    if s.get("refusals"):
        out += html_table([{"refusal": r} if not isinstance(r, dict) else r for r in s["refusals"][:20]],
                          caption="Refused positionings (first 20)")
    return out


# ---------------------------------------------------------------------------------------------
# figures

def _fig_registration(s: dict, a: dict) -> str:
    res = a.get("reg_residuals")
    if not isinstance(res, dict) or not res:
        raise Missing("array 'reg_residuals' not available")
    names = [n for n in ("rdk", "lt", "mvs") if res.get(n) is not None] + \
            [n for n in res if n not in ("rdk", "lt", "mvs") and res.get(n) is not None]
    fig, axs = plt.subplots(len(names), 3, figsize=(11, 2.3 * len(names)), squeeze=False, sharex="row")
    for r, name in enumerate(names):
        e = np.asarray(res[name], float) * MM_PER_M
        for c, ax in enumerate(AXES):
            axp = axs[r, c]
            v = e[:, c] if e.ndim == 2 else np.array([])
            i = np.flatnonzero(np.isfinite(v))
            if len(i) and np.max(np.abs(v[i])) < 1e-6:  # exact data (e.g. encoder nominal): rounding noise only
                axp.plot(i, np.zeros(len(i)), "o", ms=3, color=COLORS[ax])
                axp.set_ylim(-0.01, 0.01)
                axp.set_title(f"{name.upper()}, {ax}: numerically zero (< 1 nm)", fontsize=9)
            elif len(i) > 1:
                axp.plot(i, v[i], "o", ms=3, color=COLORS[ax])
                m, sd = v[i].mean(), v[i].std(ddof=1)
                axp.axhline(m, color="k", lw=0.8)
                axp.axhspan(m - 2 * sd, m + 2 * sd, color=COLORS[ax], alpha=0.12, label="ē ± 2 s")
                axp.set_title(f"{name.upper()}, {ax}: ē = {_f(m)} mm, s = {sd:.3f} mm", fontsize=9)
            axp.set_ylabel(f"residual {ax} / mm", fontsize=8)
            axp.tick_params(labelsize=7)
            axp.grid(alpha=0.3)
    for c in range(3):
        axs[-1, c].set_xlabel("registration positioning #", fontsize=8)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.08, top=0.95, wspace=0.28, hspace=0.42)
    return figure_block(fig_to_img_tag(fig, alt="registration residuals"),
                        "Figs. 8a/9a/10a: registration residuals per instrument and GL axis (mm), "
                        "with mean ē and the band ē ± 2 s(e).")


def _fig_error_map(s: dict, a: dict) -> str:
    X = _arr(a, "doe_X", 3)
    e = _arr(a, "e_lt", 3)
    ok = finite_rows(X[:, :3], e)
    P, E = X[ok, :3] * MM_PER_M, e[ok] * MM_PER_M
    # Mean over replications and speeds per commanded position, so each location shows one colour.
    key = np.round(P, 1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    Em = np.array([np.bincount(inv, E[:, k], len(uniq)) for k in range(3)]).T / np.bincount(inv)[:, None]
    fig = plt.figure(figsize=(13, 4.2))
    for k, ax in enumerate(AXES):
        lim = np.nanmax(np.abs(Em[:, k])) or 1.0
        axp = fig.add_subplot(1, 3, k + 1, projection="3d")
        sc = axp.scatter(uniq[:, 0], uniq[:, 1], uniq[:, 2], c=Em[:, k], cmap="coolwarm", vmin=-lim, vmax=lim,
                         s=28, depthshade=False, edgecolors="k", linewidths=0.3)
        axp.set_title(f"e_LT,{ax} (mean per position)", fontsize=10)
        axp.set_xlabel("X / mm", fontsize=8), axp.set_ylabel("Y / mm", fontsize=8), axp.set_zlabel("Z / mm", fontsize=8)
        axp.tick_params(labelsize=6)
        cb = fig.colorbar(sc, ax=axp, shrink=0.6, pad=0.16)
        cb.set_label(f"e_LT,{ax} / mm", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    fig.subplots_adjust(left=0.0, right=0.97, bottom=0.05, top=0.93, wspace=0.2)
    return figure_block(fig_to_img_tag(fig, alt="as-is error map"),
                        f"As-is error map: laser-tracker error e_LT per GL axis (mm, colour) at the {len(uniq)} DOE "
                        "positions (commanded TCP, robot frame, mm), averaged over replications and speeds. "
                        f"Dispersion of single positionings: s(e_LT) = "
                        + ", ".join(f"{np.std(E[:, k], ddof=1):.3f}" for k in range(3)) + " mm (x, y, z).")


def _fig_asis_series(s: dict, a: dict) -> str:
    given = [(n, a.get(n)) for n in ("e_lt", "e_mvs", "e_mvs_lt")]
    series = [(n, np.asarray(v, float) * MM_PER_M) for n, v in given if v is not None]
    if not series:
        raise Missing("arrays 'e_lt', 'e_mvs', 'e_mvs_lt' not available")
    lab = {"e_lt": "e_LT", "e_mvs": "e_MVS", "e_mvs_lt": "e_MVS-LT"}
    fig, axs = plt.subplots(len(series), 3, figsize=(12, 2.2 * len(series)), squeeze=False, sharex=True)
    for r, (n, e) in enumerate(series):
        for c, ax in enumerate(AXES):
            v = e[:, c]
            i = np.flatnonzero(np.isfinite(v))
            axp = axs[r, c]
            axp.plot(i, v[i], ".", ms=2, color=COLORS[ax], alpha=0.6)
            if len(i) > 1:
                m, sd = v[i].mean(), v[i].std(ddof=1)
                axp.axhline(m, color="k", lw=0.8)
                axp.axhspan(m - 2 * sd, m + 2 * sd, color=COLORS[ax], alpha=0.1)
                axp.set_title(f"{lab[n]},{ax}: ē = {_f(m)} mm, s = {sd:.3f} mm", fontsize=9)
            axp.set_ylabel("mm", fontsize=8)
            axp.tick_params(labelsize=7)
            axp.grid(alpha=0.3)
    for c in range(3):
        axs[-1, c].set_xlabel("DOE positioning # (recorded order)", fontsize=8)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.09, top=0.94, wspace=0.22, hspace=0.38)
    return figure_block(fig_to_img_tag(fig, alt="as-is errors per positioning"),
                        "Figs. 8b/9b/10b: as-is errors of every DOE positioning (mm), with mean ē and ē ± 2 s(e).")


def _fig_main_effects(s: dict, a: dict) -> str:
    X = _arr(a, "doe_X", 4)
    e = _arr(a, "e_lt", 3)
    ok = finite_rows(X[:, :4], e)
    X, E = X[ok], e[ok] * MM_PER_M
    factors = [("X / mm", X[:, 0] * MM_PER_M), ("Y / mm", X[:, 1] * MM_PER_M), ("Z / mm", X[:, 2] * MM_PER_M),
               ("speed / (mm/s)", X[:, 3] * MM_PER_M)]
    fig, axs = plt.subplots(3, 4, figsize=(13, 7.5), sharey="row", squeeze=False)
    for c, (fname, v) in enumerate(factors):
        idx, centres = _levels(v)
        for r, ax in enumerate(AXES):
            means, hw = [], []
            for i in range(len(centres)):
                y = E[idx == i, r]
                means.append(y.mean() if len(y) else np.nan)
                hw.append(t95(len(y) - 1) * y.std(ddof=1) / math.sqrt(len(y)) if len(y) > 1 else np.nan)
            axp = axs[r, c]
            axp.errorbar(centres, means, yerr=hw, fmt="o-", ms=4, capsize=2, color=COLORS[ax], lw=1)
            axp.axhline(E[:, r].mean(), color="k", ls="--", lw=0.7)
            axp.grid(alpha=0.3)
            axp.tick_params(labelsize=7)
            if c == 0:
                axp.set_ylabel(f"mean e_LT,{ax} / mm", fontsize=9)
            if r == 2:
                axp.set_xlabel(fname, fontsize=9)
    fig.suptitle("Main effects on e_LT (marginal means per level, ± 95 % interval of the mean)", fontsize=11)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.07, top=0.93, wspace=0.06, hspace=0.12)
    return figure_block(fig_to_img_tag(fig, alt="main effects"),
                        "Fig. 11 style main-effects plot: mean laser-tracker error per level of each factor (levels "
                        "of the DOE, or quantile bins where a factor has many values), with the 95 % interval of the "
                        "mean; the dashed line is the grand mean. A sloped line means that factor drives the error. "
                        "The DOE is not fully orthogonal, so these are marginal (not adjusted) means.")


def _fig_gpr(s: dict, a: dict, ekey: str = "e_lt", rkey: str = "r_lt", label: str = "e_LT",
             fig_ref: str = "Fig. 13", ukey: str = "eq19_e_lt_hat") -> str:
    from scipy import stats

    e = _arr(a, ekey, 3)
    r = _arr(a, rkey, 3)
    if e.shape != r.shape:
        raise Missing(f"'{ekey}' {e.shape} and '{rkey}' {r.shape} differ in shape")
    U = None
    try:
        U = np.asarray(_get(s, "expanded_uncertainty_95", ukey, "U_mm"), float)
    except Missing:
        pass
    fig, axs = plt.subplots(2, 3, figsize=(12, 7.4), squeeze=False)
    for c, ax in enumerate(AXES):
        ok = np.isfinite(e[:, c]) & np.isfinite(r[:, c])
        t, res = e[ok, c] * MM_PER_M, r[ok, c] * MM_PER_M
        pred = t - res  # held-out prediction: r = e - ê
        axp = axs[0, c]
        axp.plot(t, pred, ".", ms=3, alpha=0.5, color=COLORS[ax])
        if len(t):
            lo, hi = float(min(t.min(), pred.min())), float(max(t.max(), pred.max()))
            xs = np.array([lo, hi])
            axp.plot(xs, xs, "k-", lw=0.8, label="ê = e")
            if U is not None and np.isfinite(U[c]):
                axp.fill_between(xs, xs - U[c], xs + U[c], color="0.5", alpha=0.15, label=f"± U = {U[c]:.3f} mm")
            sr = res.std(ddof=1) if len(res) > 1 else float("nan")
            axp.set_title(f"{label},{ax}: s(r) = {sr:.3f} mm, n = {len(t)}", fontsize=9)
            axp.legend(fontsize=7, loc="upper left")
        axp.set_xlabel(f"true {label},{ax} / mm", fontsize=8)
        axp.set_ylabel("predicted (held-out) / mm", fontsize=8)
        axp.tick_params(labelsize=7)
        axp.grid(alpha=0.3)
        axn = axs[1, c]
        if len(res) >= 3:
            (osm, osr), (slope, icpt, rr) = stats.probplot(res, dist="norm")
            axn.plot(osm, osr, ".", ms=3, color=COLORS[ax])
            axn.plot(osm, slope * osm + icpt, "k-", lw=0.8)
            axn.set_title(f"normal probability plot of r_{ax} (R = {rr:.3f})", fontsize=9)
        axn.set_xlabel("theoretical normal quantile", fontsize=8)
        axn.set_ylabel(f"r_{ax} / mm", fontsize=8)
        axn.tick_params(labelsize=7)
        axn.grid(alpha=0.3)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.07, top=0.96, wspace=0.25, hspace=0.3)
    return figure_block(fig_to_img_tag(fig, alt=f"GPR {label} true vs predicted"),
                        f"{fig_ref} style: GPR model of {label}. Top: true error against the cross-validated "
                        "prediction ê = e − r (every point predicted by a model that never saw its target point), "
                        "with the 1:1 line and ± the expanded uncertainty of the prediction. Bottom: normal "
                        "probability plot of the residuals r (a straight line means normally distributed).")


def _fig_gpr_mvs(s: dict, a: dict) -> str:
    return _fig_gpr(s, a, "e_mvs_lt", "r_mvs_lt", "e_MVS-LT", "Fig. 14", "eq22_e_mvs_lt_hat")


def _band(axp, n: int, U: np.ndarray, c: int, color: str, label: str):
    """±U band over an index axis; U is (3,) constant or (n,3) per point (m)."""
    x = np.arange(n)
    u = (U[:n, c] if U.ndim == 2 else np.full(n, U[c])) * MM_PER_M
    axp.fill_between(x, -u, u, step="mid", color=color, alpha=0.15, label=label)


def _fig_validation(s: dict, a: dict) -> str:
    ep = _arr(a, "val_true_err_plain", 3, required=False)
    ec = _arr(a, "val_true_err_corr", 3)
    U = _arr(a, "U_tcp_c")
    rms_p = rms_with_U(ep) if ep is not None else None
    rms_c = rms_with_U(ec)
    fig, axs = plt.subplots(3, 2, figsize=(13, 8.2), sharex=True, squeeze=False)
    i = np.arange(len(ec))
    for c, ax in enumerate(AXES):
        Uc = U[:len(ec), c] if U.ndim == 2 else np.full(len(ec), U[c])
        inside = np.abs(ec[:, c]) <= Uc
        # left: both commands at the scale of the uncorrected error; right: corrected only, zoomed to +-2 U
        for col, axp in enumerate(axs[c]):
            nb = max(len(ec), len(ep) if ep is not None and col == 0 else 0) if U.ndim == 1 else len(ec)
            _band(axp, nb, U, c, "tab:blue", "± U(TCP_c), 95 %")
            if ep is not None and col == 0:
                axp.plot(np.arange(len(ep)), ep[:, c] * MM_PER_M, "s", ms=3, color="0.55", label="uncorrected command")
            axp.plot(i[inside], ec[inside, c] * MM_PER_M, "o", ms=3 if col == 0 else 3.5, color="tab:blue",
                     label="corrected command")
            if np.any(~inside):
                axp.plot(i[~inside], ec[~inside, c] * MM_PER_M, "o", ms=5, mfc="none", mec="tab:red", mew=1.5,
                         label="corrected, outside ± U")
            axp.axhline(0, color="k", lw=0.6)
            axp.grid(alpha=0.3)
            axp.tick_params(labelsize=7)
        fin = np.isfinite(ec[:, c])
        lim = max(2 * float(np.max(Uc)), 1.1 * float(np.max(np.abs(ec[fin, c]))) if fin.any() else 0.0) * MM_PER_M
        if np.isfinite(lim) and lim > 0:
            axs[c, 1].set_ylim(-lim, lim)
        axs[c, 0].set_ylabel(f"true error {ax} / mm", fontsize=9)
        axs[c, 1].set_title(f"corrected only, {ax}: {int(inside.sum())} of {len(ec)} inside ± U", fontsize=9)
    axs[0, 0].legend(fontsize=7, ncol=2, loc="upper right")
    for col in range(2):
        axs[-1, col].set_xlabel("validation positioning # (recorded order)", fontsize=9)
    t = f"3D RMS: corrected {rms_c[0] * MM_PER_M:.3f} ± {rms_c[1] * MM_PER_M:.3f} mm"
    if rms_p:
        t = f"3D RMS: uncorrected {rms_p[0] * MM_PER_M:.3f} ± {rms_p[1] * MM_PER_M:.3f} mm, " + t.split(": ")[1]
    fig.suptitle(t + " (± U95 of the RMS estimate)", fontsize=10)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.07, top=0.92, hspace=0.25, wspace=0.15)
    return figure_block(fig_to_img_tag(fig, alt="validation true errors"),
                        "Validation against the simulator's truth: true error (intended target − where the arm "
                        "went, GL, mm) of each validation positioning, commanded without (grey) and with (blue) the "
                        "twin's correction; the band is the 95 % expanded uncertainty U(TCP_c) of Eq. 18. Right: "
                        "the corrected errors alone, zoomed; red rings lie outside ± U.")


def _fig_eq17(s: dict, a: dict) -> str:
    diff = _arr(a, "val_diff", 3)
    pred = _arr(a, "val_pred", 3)
    if diff.shape != pred.shape:
        raise Missing(f"'val_diff' {diff.shape} and 'val_pred' {pred.shape} differ in shape")
    Ud = _arr(a, "U_diff", required=False)
    Up = _arr(a, "U_e_mvs_lt_hat", required=False)
    eu = s.get("expanded_uncertainty_95") or {}
    if Ud is None and isinstance(eu.get("eq20_e_lt_hat_minus_e_mvs"), dict):
        Ud = np.asarray(eu["eq20_e_lt_hat_minus_e_mvs"]["U_mm"], float) / MM_PER_M
    if Up is None and isinstance(eu.get("eq22_e_mvs_lt_hat"), dict):
        Up = np.asarray(eu["eq22_e_mvs_lt_hat"]["U_mm"], float) / MM_PER_M
    if Ud is None or Up is None:
        raise Missing("expanded uncertainties U(ê_LT − e_MVS) / U(ê_MVS-LT) not available")
    tcrit, u = _t_crit_and_flags(s, a)
    tv = _arr(a, "t_values", 3, required=False)
    if tv is None or tv.shape != diff.shape:
        k = 1.959964
        uu = u if u is not None else np.sqrt((Ud / k) ** 2 + (Up / k) ** 2)
        tv = (diff - pred) / uu
    n = len(diff)
    i = np.arange(n)
    fig, axs = plt.subplots(3, 1, figsize=(12, 8.4), sharex=True, squeeze=False)
    for c, ax in enumerate(AXES):
        axp = axs[c, 0]
        p = pred[:, c] * MM_PER_M
        up = (Up[:, c] if Up.ndim == 2 else np.full(n, Up[c])) * MM_PER_M
        ud = (Ud[:, c] if Ud.ndim == 2 else np.full(n, Ud[c])) * MM_PER_M
        axp.plot(i, p, "-", color="tab:blue", lw=1, label="DT prediction ê_MVS-LT")
        axp.fill_between(i, p - up, p + up, color="tab:blue", alpha=0.18, label="± U(ê_MVS-LT)")
        fail = np.abs(tv[:, c]) > tcrit[c]
        ok = ~fail & np.isfinite(diff[:, c])
        axp.errorbar(i[ok], diff[ok, c] * MM_PER_M, yerr=ud[ok], fmt="o", ms=3, color="k", ecolor="0.6", elinewidth=0.8,
                     capsize=1.5, label="actual ê_LT − e_MVS ± U")
        if np.any(fail):
            axp.errorbar(i[fail], diff[fail, c] * MM_PER_M, yerr=ud[fail], fmt="o", ms=4, color="tab:red",
                         ecolor="tab:red", elinewidth=0.8, capsize=1.5,
                         label=f"|t| > {tcrit[c]:.2f} (fails Eq. 17)")
        axp.set_ylabel(f"{ax} / mm", fontsize=9)
        axp.set_title(f"{ax}-axis: {int(np.sum(~fail))} of {n} pass", fontsize=9)
        axp.grid(alpha=0.3)
        axp.tick_params(labelsize=7)
        axp.legend(fontsize=7, ncol=4, loc="upper right")
    axs[-1, 0].set_xlabel("corrected validation measurement # (recorded order)", fontsize=9)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.07, top=0.96, hspace=0.2)
    return figure_block(fig_to_img_tag(fig, alt="Eq. 17 comparison"),
                        "Figs. 16-18 style, Eq. 17: the camera-tracked difference ê_LT − e_MVS (actual, with its "
                        "95 % expanded uncertainty, Eq. 20) against the twin's prediction ê_MVS-LT (blue, band = "
                        "Eq. 22), per axis, in recorded order. Red points fail the t-test at 95 %.")


def _box_faces(c: np.ndarray, h: np.ndarray) -> list[np.ndarray]:
    sx, sy, sz = h
    v = np.array([[dx, dy, dz] for dx in (-sx, sx) for dy in (-sy, sy) for dz in (-sz, sz)]) + c
    idx = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return [v[list(f)] for f in idx]


def _fig_envelope(s: dict, a: dict) -> str:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    tgt = _arr(a, "val_target", 3)
    U = _arr(a, "U_tcp_c")
    ok = finite_rows(tgt)
    if U.ndim == 2:
        if len(U) != len(tgt):
            raise Missing("per-point U(TCP_c) does not match the validation targets")
        ok &= finite_rows(U)
        U = U[ok]
    tgt = tgt[ok]
    if U.ndim == 1:
        path = _unique_in_order(tgt)
        Up = np.tile(U, (len(path), 1))
    else:  # per-point uncertainty: first occurrence of each target
        key = np.round(tgt / 1e-6).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        first = np.sort(first)
        path, Up = tgt[first], U[first]
    if len(path) == 0:
        raise Missing("no finite validation targets")
    P, H = path * MM_PER_M, Up * MM_PER_M * MAGNIFY
    fig = plt.figure(figsize=(13, 6))
    ax1 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2, projection="3d")
    dark = [f for p, h in zip(P, H) for f in _box_faces(p, h)]
    ax1.add_collection3d(Poly3DCollection(dark, facecolor="#1f4e8c", edgecolor="#0b2545", alpha=0.35, linewidths=0.4))
    ax1.plot(P[:, 0], P[:, 1], P[:, 2], "k.", ms=3)
    # Fig. 15b: uncertainty interpolated linearly along the path (light), boxes at the targets (dark).
    light = []
    for j in range(len(P) - 1):
        # enough boxes per segment that neighbours overlap into a continuous tube
        steps = int(np.clip(np.linalg.norm(P[j + 1] - P[j]) / max(H[j].min(), 1e-9), 2, 40))
        for f in np.linspace(0, 1, steps, endpoint=False)[1:]:
            light += _box_faces(P[j] + f * (P[j + 1] - P[j]), H[j] + f * (H[j + 1] - H[j]))
    if light:
        ax2.add_collection3d(Poly3DCollection(light, facecolor="#8ecae6", edgecolor="none", alpha=0.10))
    ax2.add_collection3d(Poly3DCollection(list(dark), facecolor="#1f4e8c", edgecolor="#0b2545", alpha=0.45,
                                          linewidths=0.4))
    ax2.plot(P[:, 0], P[:, 1], P[:, 2], "-", color="#023047", lw=1)
    lo, hi = (P - H).min(0), (P + H).max(0)
    for axp, t in ((ax1, "a) 3D uncertainty at the validation targets"), (ax2, "b) envelope along the path")):
        axp.set_xlim(lo[0], hi[0]), axp.set_ylim(lo[1], hi[1]), axp.set_zlim(lo[2], hi[2])
        axp.set_box_aspect(np.maximum(hi - lo, 1e-9))
        axp.set_xlabel("X / mm", fontsize=8), axp.set_ylabel("Y / mm", fontsize=8), axp.set_zlabel("Z / mm", fontsize=8)
        axp.tick_params(labelsize=6)
        axp.set_title(t, fontsize=10)
    fig.subplots_adjust(left=0.0, right=0.96, bottom=0.02, top=0.95, wspace=0.05)
    Um = np.asarray(Up, float).mean(0) * MM_PER_M
    return figure_block(fig_to_img_tag(fig, alt="3D uncertainty envelope"),
                        f"Fig. 15 style: the {len(P)} validation targets joined in plan order as a path (robot "
                        f"frame, mm), each with a box of half-sides U(TCP_c) = {Um[0]:.3f}, {Um[1]:.3f}, "
                        f"{Um[2]:.3f} mm (x, y, z; 95 %) along the GL axes, magnified x{MAGNIFY} for visibility; "
                        "right, the uncertainty interpolated linearly along the path.")


# ---------------------------------------------------------------------------------------------
# headline

def _headline(s: dict, a: dict) -> str:
    cards = []
    pb, pa, imp = s.get("precision_before_mm"), s.get("precision_after_mm"), s.get("improvement_pct")
    if pb is not None and pa is not None:
        cards.append(headline("Tracking precision (mean of x, y, z)", f"{_f(pb)} mm → {_f(pa)} mm",
                              "Before: the camera system alone scatters by 2 s(e_MVS) over the DOE. After: the twin's "
                              "prediction of the camera-vs-tracker error has this 95 % expanded uncertainty (Eq. 22)."))
    if imp is not None:
        cards.append(headline("Precision improvement", f"{_f(imp, 1)} %",
                              "How much narrower the twin makes the tracking uncertainty (paper: 77.8 %)."))
    ru, rc, red = s.get("true_rms_uncorrected_mm"), s.get("true_rms_corrected_mm"), s.get("true_error_reduction_pct")
    if ru is not None and rc is not None:
        def unc_of(key):
            e = a.get(key) if isinstance(a, dict) else None
            if e is None:
                return ""
            e = np.asarray(e, float)
            if e.ndim != 2 or e.shape[1] != 3:
                return ""
            _, U, n = rms_with_U(e)
            return f" ± {_f(U * MM_PER_M)}" if math.isfinite(U) else ""

        cards.append(headline("True 3D RMS error, validation targets",
                              f"{_f(ru)}{unc_of('val_true_err_plain')} mm → {_f(rc)}{unc_of('val_true_err_corr')} mm",
                              f"Distance between where the arm was sent and where it really went (simulator truth), "
                              f"without and with the twin's correction, over {s.get('n_validation', '?')} "
                              "positionings; "
                              "± is the 95 % uncertainty of the RMS estimate."))
    if red is not None:
        cards.append(headline("True error reduction", f"{_f(red, 1)} %",
                              "Share of the real 3D RMS positioning error the correction removes."))
    cov = s.get("coverage_95")
    if isinstance(cov, dict):
        txt = ", ".join(f"{ax} {_f(100 * cov[ax], 1)} %" for ax in AXES if cov.get(ax) is not None)
        cards.append(headline("Coverage of U(TCP_c), 95 % nominal", txt,
                              "Fraction of corrected validation points whose true error lies inside the stated "
                              "95 % expanded uncertainty; close to 95 % means the uncertainty is honest."))
    if not cards:
        raise Missing("no headline figures in the summary")
    return ('<div class="cards">' + "".join(cards) + "</div>"
            + paragraph("All lengths in millimetres; errors are e = commanded − measured in the global frame GL "
                        "(paper Eq. 8); expanded uncertainties U are at 95 % coverage with k from the effective "
                        "degrees of freedom."))


# ---------------------------------------------------------------------------------------------
# assembly

Block = Callable[[dict, dict], str]


def _run_block(fn: Block, s: dict, a: dict) -> str:
    try:
        return fn(s, a)
    except Missing as exc:
        return note(f"Not shown: {exc}.")
    except Exception as exc:  # a report must never sink the run that produced the numbers
        log.warning("report block %s failed", fn.__name__, exc_info=True)
        plt.close("all")
        return note(f"Not shown ({fn.__name__}): {type(exc).__name__}: {exc}")


def demo_sections(result) -> list[Section]:
    s = getattr(result, "summary", None) or {}
    a = getattr(result, "arrays", None) or {}
    plan: list[tuple[str, str, list[Block]]] = [
        ("Key figures", "key", [_headline]),
        ("Phase 1: registration of the instruments", "registration",
         [_tables_registration, _table_reprod, _fig_registration]),
        ("Phase 2: the arm as is (DOE)", "asis", [_table_asis, _fig_error_map, _fig_asis_series, _fig_main_effects]),
        ("GPR error models", "gpr", [_table_model_residuals, _fig_gpr, _fig_gpr_mvs]),
        ("Uncertainty (GUM)", "uncertainty",
         [_table_expanded, _table_precision, _fig_envelope, _tables_budgets, _table_literal]),
        ("Phase 3: validation", "validation", [_table_coverage, _fig_validation, _table_ttest, _fig_eq17]),
        ("Run", "run", [_table_run]),
    ]
    return [Section(title, "".join(_run_block(b, s, a) for b in blocks), anchor)
            for title, anchor, blocks in plan]


def build_demo_report(result) -> str:
    s = getattr(result, "summary", None) or {}
    sub = (f"Scenario {s.get('scenario', '?')}, seed {s.get('seed', '?')}"
           + (", quick plan" if s.get("quick") else "") + ". " + str(s.get("units", "Units: mm.")))
    return html_page("Traceable digital twin of the cobot: demo report", demo_sections(result), subtitle=sub)


def write_demo_report(result, path) -> Path:
    """Write the self-contained HTML report of a `DemoResult` to `path` and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(build_demo_report(result), encoding="utf-8")
    return path
