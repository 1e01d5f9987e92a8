"""Figures of the `dt demo` report (the paper's Figs. 8-18 equivalents), one function per figure,
each taking the summary (mm) and the arrays (SI) and returning an HTML block."""
from __future__ import annotations

import math

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.metrology.stats import finite_rows, rms_with_U, t95
from dt_runtime.metrology.uncertainty import welch_satterthwaite
from dt_runtime.reports.blocks import (
    COLORS,
    LABEL,
    LEGEND,
    TICK,
    TITLE,
    Missing,
    array,
    fixed,
    levels,
    summary_value,
    unique_in_order,
)
from dt_runtime.reports.html import fig_to_img_tag, figure_block, plt

MAGNIFY = 200  # Fig. 15: uncertainty boxes magnified x200 for visibility


def _figure(fig, alt: str, caption: str, title: str | None = None, title_size: float = TITLE, **margins: float) -> str:
    """A finished figure as an HTML block: optional title, margins, embedded PNG and caption."""
    if title:
        fig.suptitle(title, fontsize=title_size)
    fig.subplots_adjust(right=0.99, **margins)
    return figure_block(fig_to_img_tag(fig, alt=alt), caption)


def _finish_grid(fig, axs, xlabel: str, **margins: float) -> None:
    """The grid of per-axis series plots: small ticks, a light grid, the x label on the bottom row."""
    for axp in axs.ravel():
        axp.tick_params(labelsize=TICK)
        axp.grid(alpha=0.3)
    for axp in axs[-1]:
        axp.set_xlabel(xlabel, fontsize=LABEL)
    fig.subplots_adjust(right=0.99, **margins)


def _xyz_labels(axp) -> None:
    """The labels of a 3D plot in the robot frame."""
    axp.set_xlabel("X / mm", fontsize=LABEL)
    axp.set_ylabel("Y / mm", fontsize=LABEL)
    axp.set_zlabel("Z / mm", fontsize=LABEL)


def t_crit_and_flags(s: dict, a: dict):
    """Eq. 17's two-sided 95 % critical value and its combined standard uncertainty, per axis.

    Rebuilt from the summary exactly as dt_runtime.metrology.uncertainty.t_test does (u = U/k,
    Welch-Satterthwaite of the two dofs); the normal 1.96 and no u when the summary lacks them.

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (not used).

    Returns
    -------
    t_crit : ndarray
        (3,).
    u : ndarray or None
        (3,) sqrt(u^2(diff) + u^2(pred)), m.
    """
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
            tcrit = np.array([t95(x) for x in welch_satterthwaite(np.array([u1, u2]), np.array([n1, n2]))])
        except (KeyError, TypeError, ValueError):
            pass
    return tcrit, u


NAME = {"rdk": "robot encoders", "lt": "laser tracker", "mvs": "camera system"}


def fig_registration(s: dict, a: dict) -> str:
    """Registration residuals per instrument and axis (phase 1).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    res = a.get("reg_residuals")
    if not isinstance(res, dict) or not res:
        raise Missing("array 'reg_residuals' not available")
    given = [n for n in ("rdk", "lt", "mvs") if res.get(n) is not None] + \
            [n for n in res if n not in ("rdk", "lt", "mvs") and res.get(n) is not None]

    def flat(name: str) -> bool:  # exact data (e.g. the encoders' nominal TCP): rounding noise only
        e = np.asarray(res[name], float)
        return bool(np.all(np.abs(e[np.isfinite(e)]) < 1e-9))

    zero = [n for n in given if flat(n)]
    names = [n for n in given if n not in zero]
    if not names:
        raise Missing("every registration residual is numerically zero")
    fig, axs = plt.subplots(len(names), 3, figsize=(11, 2.6 * len(names)), squeeze=False, sharex="row")
    for r, name in enumerate(names):
        e = np.asarray(res[name], float) * MM_PER_M
        for c, ax in enumerate(AXES):
            axp = axs[r, c]
            v = e[:, c] if e.ndim == 2 else np.array([])
            i = np.flatnonzero(np.isfinite(v))
            if len(i) > 1:
                axp.plot(i, v[i], "o", ms=3, color=COLORS[ax])
                m, sd = v[i].mean(), v[i].std(ddof=1)
                axp.axhline(m, color="k", lw=0.8)
                axp.axhspan(m - 2 * sd, m + 2 * sd, color=COLORS[ax], alpha=0.12, label="ē ± 2 s")
                axp.set_title(f"{NAME.get(name, name)}, {ax}: s = {sd:.3f} mm", fontsize=TITLE)
            axp.set_ylabel(f"residual {ax} / mm", fontsize=LABEL)
    _finish_grid(fig, axs, "registration positioning #", left=0.08, bottom=0.1, top=0.93, wspace=0.32, hspace=0.45)
    left_out = (" The robot encoders' residuals e_RDK,GL are numerically zero (< 1 nm: the controller's commanded "
                "TCP is exact by construction) and are not drawn." if zero else "")
    return figure_block(fig_to_img_tag(fig, alt="registration residuals"),
                        "Figs. 8a/9a/10a: registration residuals per instrument and GL axis (mm), with their mean ē "
                        "(zero by construction of the least-squares fit) and the band ē ± 2 s(e)." + left_out)


def fig_error_map(s: dict, a: dict) -> str:
    """The laser-tracker error over the DOE positions, mean per position (phase 2).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    X = array(a, "doe_X", 3)
    e = array(a, "e_lt", 3)
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
        axp.set_title(f"e_LT,{ax} (mean per position)", fontsize=TITLE)
        _xyz_labels(axp)
        axp.tick_params(labelsize=TICK)
        cb = fig.colorbar(sc, ax=axp, shrink=0.6, pad=0.16)
        cb.set_label(f"e_LT,{ax} / mm", fontsize=LABEL)
        cb.ax.tick_params(labelsize=TICK)
    fig.subplots_adjust(left=0.0, right=0.97, bottom=0.05, top=0.93, wspace=0.2)
    return figure_block(fig_to_img_tag(fig, alt="as-is error map"),
                        f"As-is error map: laser-tracker error e_LT per GL axis (mm, colour) at the {len(uniq)} DOE "
                        "positions (commanded TCP, robot frame, mm), averaged over replications and speeds. "
                        f"Dispersion of single positionings: s(e_LT) = "
                        + ", ".join(f"{np.std(E[:, k], ddof=1):.3f}" for k in range(3)) + " mm (x, y, z).")


def fig_asis_series(s: dict, a: dict) -> str:
    """The as-is errors e_LT, e_MVS and e_MVS-LT row by row, per axis (phase 2).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
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
                axp.set_title(f"{lab[n]},{ax}: ē = {fixed(m)} mm, s = {sd:.3f} mm", fontsize=TITLE)
            axp.set_ylabel("mm", fontsize=LABEL)
    _finish_grid(fig, axs, "DOE positioning # (recorded order)", left=0.06, bottom=0.09, top=0.94, wspace=0.22,
                 hspace=0.38)
    return figure_block(fig_to_img_tag(fig, alt="as-is errors per positioning"),
                        "Figs. 8b/9b/10b: as-is errors of every DOE positioning (mm), with mean ē and ē ± 2 s(e).")


def fig_main_effects(s: dict, a: dict) -> str:
    """Main effects on e_LT: mean per level of each factor with its 95 % interval (Fig. 11 style).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    X = array(a, "doe_X", 4)
    e = array(a, "e_lt", 3)
    ok = finite_rows(X[:, :4], e)
    X, E = X[ok], e[ok] * MM_PER_M
    factors = [("X / mm", X[:, 0] * MM_PER_M), ("Y / mm", X[:, 1] * MM_PER_M), ("Z / mm", X[:, 2] * MM_PER_M),
               ("speed / (mm/s)", X[:, 3] * MM_PER_M)]
    fig, axs = plt.subplots(3, 4, figsize=(13, 7.5), sharey="row", squeeze=False)
    for c, (fname, v) in enumerate(factors):
        idx, centres = levels(v)
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
            axp.tick_params(labelsize=TICK)
            if c == 0:
                axp.set_ylabel(f"mean e_LT,{ax} / mm", fontsize=TITLE)
            if r == 2:
                axp.set_xlabel(fname, fontsize=TITLE)
    return _figure(fig, "main effects",
                   "Fig. 11 style main-effects plot: mean laser-tracker error per level of each factor (levels "
                   "of the DOE, or quantile bins where a factor has many values), with the 95 % interval of the "
                   "mean; the dashed line is the grand mean. A sloped line means that factor drives the error. "
                   "The DOE is not fully orthogonal, so these are marginal (not adjusted) means.",
                   title="Main effects on e_LT (marginal means per level, ± 95 % interval of the mean)",
                   left=0.06, bottom=0.07, top=0.93, wspace=0.06, hspace=0.12)


def fig_gpr(s: dict, a: dict, ekey: str = "e_lt", rkey: str = "r_lt", label: str = "e_LT",
             fig_ref: str = "Fig. 13", ukey: str = "eq19_e_lt_hat") -> str:
    """The GPR's fit of an error map: residuals per axis and their normal probability plot.

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).
    ekey, rkey : str, optional
        Keys of the errors and the GPR's residuals.
    label : str, optional
        The error's symbol.
    fig_ref : str, optional
        The paper's figure it mirrors.
    ukey : str, optional
        Key of the expanded uncertainty drawn, under the summary's `expanded_uncertainty_95`.

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    from scipy import stats

    e = array(a, ekey, 3)
    r = array(a, rkey, 3)
    if e.shape != r.shape:
        raise Missing(f"'{ekey}' {e.shape} and '{rkey}' {r.shape} differ in shape")
    U = None
    try:
        U = np.asarray(summary_value(s, "expanded_uncertainty_95", ukey, "U_mm"), float)
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
            axp.set_title(f"{label},{ax}: s(r) = {sr:.3f} mm, n = {len(t)}", fontsize=TITLE)
            axp.legend(fontsize=LEGEND, loc="upper left")
        axp.set_xlabel(f"true {label},{ax} / mm", fontsize=LABEL)
        axp.set_ylabel("predicted (held-out) / mm", fontsize=LABEL)
        axp.tick_params(labelsize=TICK)
        axp.grid(alpha=0.3)
        axn = axs[1, c]
        if len(res) >= 3:
            (osm, osr), (slope, icpt, rr) = stats.probplot(res, dist="norm")
            axn.plot(osm, osr, ".", ms=3, color=COLORS[ax])
            axn.plot(osm, slope * osm + icpt, "k-", lw=0.8)
            axn.set_title(f"normal probability plot of r_{ax} (R = {rr:.3f})", fontsize=TITLE)
        axn.set_xlabel("theoretical normal quantile", fontsize=LABEL)
        axn.set_ylabel(f"r_{ax} / mm", fontsize=LABEL)
        axn.tick_params(labelsize=TICK)
        axn.grid(alpha=0.3)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.07, top=0.96, wspace=0.25, hspace=0.3)
    return figure_block(fig_to_img_tag(fig, alt=f"GPR {label} true vs predicted"),
                        f"{fig_ref} style: GPR model of {label}. Top: true error against the cross-validated "
                        "prediction ê = e − r (every point predicted by a model that never saw its target point), "
                        "with the 1:1 line and ± the expanded uncertainty of the prediction. Bottom: normal "
                        "probability plot of the residuals r (a straight line means normally distributed).")


def fig_gpr_mvs(s: dict, a: dict) -> str:
    """`fig_gpr` for e_MVS-LT (Fig. 14).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    return fig_gpr(s, a, "e_mvs_lt", "r_mvs_lt", "e_MVS-LT", "Fig. 14", "eq22_e_mvs_lt_hat")


def _band(axp, n: int, U: np.ndarray, c: int, color: str, label: str):
    """±U band over an index axis; U is (3,) constant or (n,3) per point (m)."""
    x = np.arange(n)
    u = (U[:n, c] if U.ndim == 2 else np.full(n, U[c])) * MM_PER_M
    axp.fill_between(x, -u, u, step="mid", color=color, alpha=0.15, label=label)


def fig_validation(s: dict, a: dict) -> str:
    """Validation: the true error of the corrected (and plain) commands against the stated U.

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    ep = array(a, "val_true_err_plain", 3, required=False)
    ec = array(a, "val_true_err_corr", 3)
    U = array(a, "U_tcp_c")
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
            axp.tick_params(labelsize=TICK)
        fin = np.isfinite(ec[:, c])
        lim = max(2 * float(np.max(Uc)), 1.1 * float(np.max(np.abs(ec[fin, c]))) if fin.any() else 0.0) * MM_PER_M
        if np.isfinite(lim) and lim > 0:
            axs[c, 1].set_ylim(-lim, lim)
        axs[c, 0].set_ylabel(f"true error {ax} / mm", fontsize=TITLE)
        axs[c, 1].set_title(f"corrected only, {ax}: {int(inside.sum())} of {len(ec)} inside ± U", fontsize=TITLE)
    axs[0, 0].legend(fontsize=LEGEND, ncol=2, loc="upper right")
    for col in range(2):
        axs[-1, col].set_xlabel("validation positioning # (recorded order)", fontsize=TITLE)
    t = f"3D RMS: corrected {rms_c[0] * MM_PER_M:.3f} ± {rms_c[1] * MM_PER_M:.3f} mm"
    if rms_p:
        t = f"3D RMS: uncorrected {rms_p[0] * MM_PER_M:.3f} ± {rms_p[1] * MM_PER_M:.3f} mm, " + t.split(": ")[1]
    return _figure(fig, "validation true errors",
                   "Validation against the simulator's truth: true error (intended target − where the arm "
                   "went, GL, mm) of each validation positioning, commanded without (grey) and with (blue) the "
                   "twin's correction; the band is the 95 % expanded uncertainty U(TCP_c) of Eq. 11 at each "
                   "corrected position. Right: the corrected errors alone, zoomed; red rings lie outside ± U.",
                   title=t + " (± U95 of the RMS estimate)", title_size=TITLE,
                   left=0.06, bottom=0.07, top=0.92, hspace=0.25, wspace=0.15)


def fig_eq17(s: dict, a: dict) -> str:
    """The Eq. 17 t-test of every validation reading, per axis.

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    diff = array(a, "val_diff", 3)
    pred = array(a, "val_pred", 3)
    if diff.shape != pred.shape:
        raise Missing(f"'val_diff' {diff.shape} and 'val_pred' {pred.shape} differ in shape")
    Ud = array(a, "U_diff", required=False)
    Up = array(a, "U_e_mvs_lt_hat", required=False)
    eu = s.get("expanded_uncertainty_95") or {}
    if Ud is None and isinstance(eu.get("eq20_e_lt_hat_minus_e_mvs"), dict):
        Ud = np.asarray(eu["eq20_e_lt_hat_minus_e_mvs"]["U_mm"], float) / MM_PER_M
    if Up is None and isinstance(eu.get("eq22_e_mvs_lt_hat"), dict):
        Up = np.asarray(eu["eq22_e_mvs_lt_hat"]["U_mm"], float) / MM_PER_M
    if Ud is None or Up is None:
        raise Missing("expanded uncertainties U(ê_LT − e_MVS) / U(ê_MVS-LT) not available")
    tcrit, u = t_crit_and_flags(s, a)
    tv = array(a, "t_values", 3, required=False)
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
        axp.set_ylabel(f"{ax} / mm", fontsize=TITLE)
        axp.set_title(f"{ax}-axis: {int(np.sum(~fail))} of {n} pass", fontsize=TITLE)
        axp.grid(alpha=0.3)
        axp.tick_params(labelsize=TICK)
        axp.legend(fontsize=LEGEND, ncol=4, loc="upper right")
    axs[-1, 0].set_xlabel("corrected validation measurement # (recorded order)", fontsize=TITLE)
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


def fig_envelope(s: dict, a: dict) -> str:
    """The validation targets as a path with their uncertainty boxes, magnified (Fig. 15 style).

    Parameters
    ----------
    s : dict
        The run's summary.
    a : dict
        Its arrays (SI).

    Returns
    -------
    str
        The HTML figure block.

    Raises
    ------
    Missing
        When an array it plots is absent.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    tgt = array(a, "val_target", 3)
    U = array(a, "U_tcp_c")
    ok = finite_rows(tgt)
    if U.ndim == 2:
        if len(U) != len(tgt):
            raise Missing("per-point U(TCP_c) does not match the validation targets")
        ok &= finite_rows(U)
        U = U[ok]
    tgt = tgt[ok]
    if U.ndim == 1:
        path = unique_in_order(tgt)
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
        _xyz_labels(axp)
        axp.tick_params(labelsize=TICK)
        axp.set_title(t, fontsize=TITLE)
    fig.subplots_adjust(left=0.0, right=0.96, bottom=0.02, top=0.95, wspace=0.05)
    Um = np.asarray(Up, float).mean(0) * MM_PER_M
    return figure_block(fig_to_img_tag(fig, alt="3D uncertainty envelope"),
                        f"Fig. 15 style: the {len(P)} validation targets joined in plan order as a path (robot "
                        f"frame, mm), each with a box of half-sides its own U(TCP_c) (the per-position U of the key "
                        f"figures, Eq. 11 at that target; mean {Um[0]:.3f}, {Um[1]:.3f}, {Um[2]:.3f} mm in x, y, z, "
                        f"95 %) along the GL axes, magnified x{MAGNIFY} for visibility; right, the uncertainty "
                        "interpolated linearly along the path. The Eq. 18 table's U(TCP_c) is the paper's one "
                        "global value over the DOE.")
