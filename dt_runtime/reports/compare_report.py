"""The `dt compare` report: one self-contained HTML page and the JSON beside it
(`write_compare_report`; docs/cli.md, "dt compare").
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis.compare import MIN_CELL
from dt_runtime.analysis.points import approach, per_point
from dt_runtime.reports.blocks import COLORS, LABEL, LEGEND, TICK, TITLE, Missing, fixed, levels, run_block
from dt_runtime.reports.html import (
    Section,
    fig_to_img_tag,
    figure_block,
    headline,
    html_page,
    html_table,
    note,
    paragraph,
    plt,
    validity_banner,
)
from dt_runtime.reports.parameter_table import html as parameters_html
from dt_runtime.reports.parameter_table import parameter_table
from dt_runtime.reports.residuals import write_residuals
from dt_runtime.reports.traceability import traceability


def _primary(a: dict) -> dict:
    ms = a.get("models") or []
    if not ms:
        raise Missing("no model results")
    return ms[-1]


def _rms_txt(b: dict) -> str:
    u = b.get("rmse_U95_mm")
    return f"{fixed(b.get('rmse_mm'))} ± {fixed(u)}" if u is not None else fixed(b.get("rmse_mm"))


def _fail_txt(b: dict) -> str:
    f = b.get("failures")
    return f"{fixed(100 * f['fraction'], 1)} % ({f['count']} rows)" if f else "–"


# --------------------------------------------------------------------------- tables

def _banner(s: dict, a: dict) -> str:
    """The validity of the primary model's stated U95 on these data (analysis.validity), and a warning
    when a model was trained on these very data: its figures are in-sample."""
    ins = s.get("in_sample") or []
    valid = validity_banner(s.get("validity"))
    if not ins:
        return valid
    return valid + note(f"<strong>Warning: in-sample figures.</strong> {', '.join(ins)} "
                f"{'was' if len(ins) == 1 else 'were'} trained on this very file: "
                "their residuals here say how well they fit, not how well they predict. Compare on other "
                "data, or with <code>dt compare --cv K</code> (each row predicted without its point).")


def _headline(s: dict, a: dict) -> str:
    ms = s["models"]
    p, asis = ms[-1], ms[0]
    cards = [headline(f"3D RMS residual, {p['name']}", f"{_rms_txt(p)} mm",
                      f"Root mean square of |e − ê| over {s['n']} measured rows (as is: {_rms_txt(asis)} mm); "
                      "± is the 95 % uncertainty of the RMS estimate.")]
    if s.get("noise_floor_mm") is not None:
        cards.append(headline("Noise floor", f"{fixed(s['noise_floor_mm'])} mm",
                              "3D RMS of the measurement's stated uncertainty: no model can go below this."))
    f = p.get("failures")
    if f:
        cards.append(headline("Outside the stated uncertainty (Eq. 17)", _fail_txt(p),
                              f"Rows failing the 95 % t-test in any axis; a consistent model fails about "
                              f"{fixed(100 * f['expected_fraction_if_consistent'], 1)} % (5 % per axis, three axes)."))
    w = p.get("worst_cells") or []
    if w:
        c = w[0]
        cards.append(headline("Worst cell", f"{c['factor']} {c['cell']}: {fixed(c['rmse_mm'])} mm",
                              f"{c['n']} rows, {fixed(c['ratio'], 2)} x the overall RMS."))
    return '<div class="cards">' + "".join(cards) + "</div>"


def _table_summary(s: dict, a: dict) -> str:
    ms = s["models"]
    names = [m["name"] for m in ms]

    def row(label, fn):
        return {"quantity": label, **{m["name"]: fn(m) for m in ms}}

    rows = [row("description", lambda m: m.get("description", "")),
            row("n", lambda m: m["n"]),
            row("3D RMS of r / mm (± U95)", _rms_txt),
            row("3D mean |r| / mm", lambda m: fixed(m["mae_mm"])),
            row("3D max |r| / mm", lambda m: fixed(m["max_mm"]))]
    for ax in AXES:
        rows.append(row(f"RMS r_{ax} / mm", lambda m, ax=ax: fixed(m["per_axis"][ax]["rmse_mm"])))
    for ax in AXES:
        rows.append(row(f"mean r_{ax} / mm", lambda m, ax=ax: fixed(m["per_axis"][ax]["mean_mm"])))
    rows.append(row("fails Eq. 17, any axis", _fail_txt))
    for ax in AXES:
        rows.append(row(f"fails Eq. 17, {ax} / %",
                        lambda m, ax=ax: fixed(100 * m["failures"]["per_axis"][ax], 1) if m.get("failures") else "–"))
    rows.append(row("training: RMS left after the effect terms, per axis / mm",
                    lambda m: fixed(m["effect_residual_rms_mm"]) if "effect_residual_rms_mm" in m else "–"))
    return (html_table(rows, ["quantity"] + names, row_header="quantity",
                       caption=f"Residual r = e − ê on {s['n']} rows of {s.get('dataset', '?')}, one column "
                               "per model in the order given ('as is': no correction)")
            + paragraph(f"Measurement uncertainty in the t-test: {s['t_test']['u_meas_source']}."))


def _fig_steps(s: dict, a: dict) -> str:
    ms = s["models"]
    ho = s.get("heldout")
    x = np.arange(len(ms))
    y = np.array([m["rmse_mm"] for m in ms])
    u = np.array([m.get("rmse_U95_mm") or 0.0 for m in ms])
    fig, ax = plt.subplots(figsize=(max(5.5, 1.3 * len(ms) + 2), 3.8))
    ax.bar(x, y, yerr=u, capsize=4, color=["0.6"] + ["tab:blue"] * (len(ms) - 1), alpha=0.85)
    ax.plot(x, y, "k.-", lw=0.8)
    for xi, yi in zip(x, y):
        ax.annotate(f"{yi:.3f}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=LABEL)
    fl = s.get("noise_floor_mm")
    if fl is not None:
        ax.axhline(fl, color="tab:red", ls="--", lw=1, label=f"noise floor {fl:.3f} mm")
        ax.legend(fontsize=LABEL)
    ax.set_xticks(x, [m["name"] for m in ms], rotation=15, fontsize=LABEL)
    ax.set_ylabel(("held-out " if ho else "") + "3D RMS of r / mm")
    if y.min() > 0 and y.max() / y.min() > 4:  # the as-is bar must not squash the steps that matter
        ax.set_yscale("log")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    what = (f"Held-out 3D RMS of the residual ({ho['method']})" if ho else
            "3D RMS of the residual on these data (held out only if the models were trained on other data; "
            "`dt compare --cv K` refits each model without the point it predicts)")
    return figure_block(fig_to_img_tag(fig, alt="3D RMS per step"),
                        what + " per step (mm; error bars: 95 % uncertainty of the RMS "
                        "estimate), as is and then each model in the order given"
                        + ("; the dashed line is the noise floor, the 3D RMS of the measurement uncertainty."
                           if fl is not None else "."))


def _table_sessions(s: dict, a: dict) -> str:
    """Data of several sessions: each session's figures, one group of columns per model."""
    ms = s["models"]
    first = ms[0].get("sessions") or []
    if not first:
        raise Missing("the data are one session")
    rr = any(x.get("after_reregistration") for m in ms for x in m.get("sessions") or [])
    rows = []
    for i, x in enumerate(first):
        r = {"session": x.get("name") or x["session"], "file": x.get("file", "–"), "n": x["n"]}
        for m in ms:
            y = m["sessions"][i]
            r[f"{m['name']}: RMS / mm"] = _rms_txt(y) + (" (in-sample)" if y.get("in_sample") else "")
            if rr:
                z = y.get("after_reregistration")
                r[f"{m['name']}: re-registered / mm"] = _rms_txt(z) if z else "–"
                y = z or y
            r[f"{m['name']}: fails Eq. 17"] = _fail_txt(y)
        rows.append(r)
    return (html_table(rows, row_header="session",
                       caption="3D RMS of r = e − ê per session (± U95 of the RMS estimate)"
                               + ("; re-registered: after the session's registration, fitted on its own points, "
                                  "is fitted again to the corrected commanded points (6 dof absorbed per session); "
                                  "the Eq. 17 failures are then those of the re-registered residual" if rr else ""))
            + paragraph("A session is one data file of the campaign, named by its file (its shortest distinct "
                        "path when file names repeat). In-sample: the model was trained on that session's file, so "
                        "its figures there say how well it fits, not how well it predicts."))


def _tables_worst(s: dict, a: dict) -> str:
    w = s.get("worst_cells") or []
    if not w:
        raise Missing(f"no breakdown cell has {MIN_CELL} or more rows")
    rows = [{"rank": i + 1, "factor": c["factor"], "cell": c["cell"], "n": c["n"], "3D RMS / mm": fixed(c["rmse_mm"]),
             "ratio to overall": fixed(c["ratio"], 2),
             "mean r (x, y, z) / mm": ", ".join(fixed(v) for v in c["mean_mm"])} for i, c in enumerate(w)]
    return html_table(rows, row_header="rank",
                      caption=f"Worst cells for {s['primary']} (any factor, n ≥ {MIN_CELL}), overall 3D RMS "
                              f"{fixed(s['rmse_mm'])} mm")


def _tables_breakdown(s: dict, a: dict) -> str:
    ms = s["models"]
    if not s.get("breakdown"):
        raise Missing("no factor varies in these data")
    out = [paragraph("3D RMS of the residual per cell of each factor, one column per model. Region: thirds "
                     "(−, 0, +) of the commanded TCP bounding box along x, y, z. Configuration: sign of q3 "
                     "(elbow up/down) and q5 (wrist flip). Factors missing from the data or constant are left out.")]
    for factor, cells in s["breakdown"].items():
        per_model = [{c["cell"]: c for c in m["breakdown"].get(factor, [])} for m in ms]
        rows = []
        for c in cells:
            r = {"cell": c["cell"], "n": c["n"]}
            for m, pm in zip(ms, per_model):
                r[f"{m['name']}: RMS / mm"] = fixed(pm[c["cell"]]["rmse_mm"]) if c["cell"] in pm else "–"
            r[f"mean r (x, y, z) / mm, {s['primary']}"] = ", ".join(fixed(v) for v in c["mean_mm"])
            rows.append(r)
        out.append(html_table(rows, row_header="cell", caption=f"By {factor}"))
    return "".join(out)


def _table_parameters(s: dict, a: dict) -> str:
    out = []
    for m in s["models"][1:]:
        ps = m.get("parameters") or []
        if not ps:
            out.append(paragraph(f"{m['name']} ({m.get('description', '')}): no physical effect terms."))
            continue
        out.append(parameters_html(parameter_table(ps, m.get("base_parameters"), plus_minus=True),
                                   f"{m['name']} ({m.get('description', '')})"))
    return "".join(out)


def _table_method(s: dict, a: dict) -> str:
    t = s["t_test"]
    rows = [{"item": "data", "value": s.get("dataset")}, {"item": "rows", "value": s["n"]},
            {"item": "t-test", "value": t["equation"]}, {"item": "u_model", "value": t["u_model"]},
            {"item": "u_meas", "value": t["u_meas_source"]}, {"item": "units", "value": s.get("units")}]
    return html_table(rows, row_header="item")


# --------------------------------------------------------------------------- figures

def _fig_maps(s: dict, a: dict) -> str:
    p = _primary(a)
    fail_rows = p["fail"].any(axis=1) if p["fail"] is not None else np.zeros(len(p["residual"]), bool)
    P, agg, cnt = per_point(a["commanded"], np.column_stack([p["residual"], fail_rows]))
    P = P * MM_PER_M
    r = np.linalg.norm(agg[:, :3], axis=1) * MM_PER_M  # |mean residual| of each point's replicates
    frac = agg[:, 3]
    fail = frac >= 0.5
    vmax = float(np.percentile(r, 95)) or 1.0  # robust: one outlier must not set the scale
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.8))
    for axp, (i, j) in zip(axs, ((0, 1), (0, 2))):
        sc = axp.scatter(P[:, i], P[:, j], c=np.minimum(r, vmax), cmap="viridis", s=10 + 6 * np.sqrt(cnt),
                         vmin=0, vmax=vmax)
        if fail.any():
            axp.scatter(P[fail, i], P[fail, j], marker="x", s=40, color="tab:red", lw=1.2,
                        label=f"fails Eq. 17 in >= half its rows ({int(fail.sum())} of {len(r)} points)")
            axp.legend(fontsize=LABEL, loc="best")
        axp.set_xlabel(f"{AXES[i]} / mm"), axp.set_ylabel(f"{AXES[j]} / mm")
        axp.set_title(f"{AXES[i]}-{AXES[j]} view", fontsize=TITLE)
        axp.grid(alpha=0.3)
        fig.colorbar(sc, ax=axp, extend="max").set_label("|mean r| per point / mm")
    fig.tight_layout()
    return figure_block(fig_to_img_tag(fig, alt="residual maps"),
                        f"Residual maps of {p['name']}, one marker per commanded point (robot frame, mm; size: its "
                        f"number of rows): colour is the 3D norm of the point's mean residual |mean(e − ê)| (mm; the "
                        f"scale ends at the 95th percentile, {vmax:.3f} mm, so one outlier does not wash out the "
                        f"rest); red crosses mark points failing the Eq. 17 t-test in at least half of their rows "
                        f"({100 * float(fail_rows.mean()):.1f} % of all rows fail in at least one axis).")


Factor = tuple[str, np.ndarray, list[str] | None]  # label, values, category names (None: a numeric factor)


def _factor_values(a: dict) -> list[Factor]:
    out: list[Factor] = []
    for key, label, f in (("speed", "speed / (mm/s)", MM_PER_M), ("payload", "payload / kg", 1.0),
                          ("temperature", "temperature / °C", 1.0), ("t", "time from start / s", 1.0)):
        v = a.get(key)
        if v is not None and np.nanstd(v) > 0:
            v = np.asarray(v, float) * f
            out.append((label, v - np.nanmin(v) if key == "t" else v, None))
    q = a.get("joints")
    if q is not None:
        j = 2 if q.shape[1] > 2 else 0  # the elbow: the joint whose angle most changes the reach
        out.append((f"q{j + 1} / deg", np.degrees(q[:, j]), None))
    return out


APPROACH = {-1.0: "−", 0.0: "still", 1.0: "+"}


def _approach(a: dict) -> list[Factor]:
    """The direction from which each joint approached (sign of its change from the previous row;
    rows in time order), for the joints that move: what backlash and lag follow. Categorical."""
    q = a.get("joints")
    if q is None or len(q) < 3:
        return []
    d = approach(q)
    out: list[Factor] = []
    for j in range(q.shape[1]):
        if not np.any(d[:, j] != 0):
            continue
        levels_ = sorted(set(d[:, j].tolist()))
        idx = np.searchsorted(np.array(levels_), d[:, j]).astype(float)
        out.append((f"approach of q{j + 1}", idx, [APPROACH[v] for v in levels_]))
    return out[:3]


def _configuration(a: dict) -> list[Factor]:
    """The joint configuration (signs of the elbow and wrist joints), when the rows span several."""
    lab = (a.get("cells") or {}).get("configuration")
    if lab is None:
        return []
    names = sorted(set(lab.tolist() if hasattr(lab, "tolist") else lab))
    if len(names) < 2:
        return []
    index = {n: i for i, n in enumerate(names)}
    return [("joint configuration", np.array([index[x] for x in lab], float), names)]


PER_ROW = 4  # factor panels per row: the figure stays at the page's width, its fonts readable


def _fig_factors(s: dict, a: dict) -> str:
    models = a.get("models") or []
    if not models:
        raise Missing("no model results")
    fv = _factor_values(a) + _approach(a) + _configuration(a)
    if not fv:
        raise Missing("the data have no speed, payload, temperature, time or joint columns")
    ncol = min(len(fv), PER_ROW)
    nrow = -(-len(fv) // ncol)
    fig, axs = plt.subplots(nrow, ncol, figsize=(3.2 * ncol + 0.8, 3.3 * nrow + 0.5), squeeze=False, sharey=True)
    for axp in axs.ravel()[len(fv):]:
        axp.set_visible(False)
    cmap = plt.get_cmap("tab10")
    style = [("0.45", "--")] + [(cmap(i % 10), "-") for i in range(len(models) - 1)]  # 'as is' first, grey
    for axp, (label, v, cats) in zip(axs.ravel(), fv):
        ok = np.isfinite(v)
        if cats is None:
            idx, centres = levels(v[ok])
        else:  # categories: one position each, the models side by side, no line between them
            idx, centres = v[ok].astype(int), np.arange(len(cats), dtype=float)
        width = 0.5 / max(len(models), 1)
        for mi, (m, (color, ls)) in enumerate(zip(models, style)):
            r = np.linalg.norm(m["residual"], axis=1)[ok] * MM_PER_M
            rms = np.array([np.sqrt(np.mean(r[idx == i] ** 2)) if np.any(idx == i) else np.nan
                            for i in range(len(centres))])
            if cats is None:
                axp.plot(centres, rms, "o", ls=ls, ms=3, lw=1.2, color=color, label=m["name"])
            else:
                axp.plot(centres + (mi - (len(models) - 1) / 2) * width, rms, "o", ms=6, color=color,
                         label=m["name"])
        if cats is not None:
            axp.set_xticks(centres, cats, fontsize=TICK)
            axp.set_xlim(-0.6, len(cats) - 0.4)
        axp.set_xlabel(label, fontsize=LABEL)
        axp.grid(alpha=0.3)
        axp.tick_params(labelsize=TICK)
    for row in axs:
        row[0].set_ylabel("3D RMS of r / mm", fontsize=LABEL)
    handles, names = axs[0, 0].get_legend_handles_labels()
    fig.legend(handles, names, loc="upper center", ncol=len(models), fontsize=LEGEND + 1, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / (3.3 * nrow + 0.5)))
    return figure_block(fig_to_img_tag(fig, alt="residual against each factor"),
                        "3D RMS of the residual (mm) of every model ('as is', dashed grey: no correction) per level "
                        "or quantile bin of each numeric factor, and per category of the direction of approach of "
                        "the moving joints (−: the angle fell, +: it rose) and of the joint configuration (signs of "
                        "the elbow and wrist joints): a model whose curve rises or steps where the others stay flat "
                        "misses the effect that follows that factor.")


def _fig_normal(s: dict, a: dict) -> str:
    from scipy import stats

    p = _primary(a)
    r = p["residual"] * MM_PER_M
    if len(r) < 3:
        raise Missing("fewer than 3 rows")
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.6))
    for k, ax in enumerate(AXES):
        (osm, osr), (slope, icpt, rr) = stats.probplot(r[:, k], dist="norm")
        axs[k].plot(osm, osr, ".", ms=3, color=COLORS[ax])
        axs[k].plot(osm, slope * osm + icpt, "k-", lw=0.8)
        axs[k].set_title(f"r_{ax}: R = {rr:.3f}, slope {slope:.3f} mm", fontsize=TITLE)
        axs[k].set_xlabel("theoretical normal quantile", fontsize=LABEL)
        axs[k].set_ylabel(f"r_{ax} / mm", fontsize=LABEL)
        axs[k].grid(alpha=0.3)
    fig.tight_layout()
    return figure_block(fig_to_img_tag(fig, alt="normal probability plot"),
                        f"Normal probability plots of the residual components of {p['name']} (mm): a straight line "
                        "means normal residuals; bent tails or steps mean outliers or a missing effect.")


# --------------------------------------------------------------------------- assembly

def compare_sections(result: dict, arrays: dict) -> list[Section]:
    """The compare report's sections, each from its blocks.

    Parameters
    ----------
    result : dict
        `CompareResult.to_dict()`.
    arrays : dict
        The SI arrays `compare` returned.

    Returns
    -------
    list of Section
    """
    plan = [("Key figures", "key", [_banner, _headline]),
            ("Models side by side", "summary", [_table_summary, _fig_steps]),
            *([("Session by session", "sessions", [_table_sessions])] if result.get("sessions") else []),
            ("Where the model fails", "where", [_fig_maps, _tables_worst]),
            ("Residual against each factor", "factors", [_fig_factors]),
            ("Normality of the residuals", "normal", [_fig_normal]),
            ("Breakdown by factor", "breakdown", [_tables_breakdown]),
            ("Model parameters", "parameters", [_table_parameters]),
            ("Method and data", "method", [_table_method]),
            ("Traceability", "traceability", [traceability])]
    return [Section(title, "".join(run_block(b, result, arrays) for b in blocks), anchor)
            for title, anchor, blocks in plan]


def build_compare_report(result: dict, arrays: dict) -> str:
    """The compare report as one self-contained HTML page.

    Parameters
    ----------
    result : dict
        `CompareResult.to_dict()`.
    arrays : dict
        The SI arrays `compare` returned.

    Returns
    -------
    str
    """
    names = ", ".join(m["name"] for m in result.get("models", []))
    return html_page("Cobot digital twin: model against measurements", compare_sections(result, arrays),
                     subtitle=f"{result.get('n', '?')} rows of {result.get('dataset', '?')}; columns: {names}. "
                              "Lengths in mm; e = commanded − measured (paper Eq. 8), r = e − ê.")


def write_compare_report(result: dict, arrays: dict, out_dir) -> Path:
    """Write out_dir/report.html, out_dir/compare.json and out_dir/residuals.csv (every row's
    residual per model: reports.residuals); return the HTML path.

    Parameters
    ----------
    result : dict
        `CompareResult.to_dict()`.
    arrays : dict
        The SI arrays `compare` returned.
    out_dir : str or Path
        The directory (made if needed).

    Returns
    -------
    Path

    Notes
    -----
    The page shows the models side by side, the "watch the error fall" plot, where the primary
    model (the last one) fails (residual maps, the worst cells), every model's residual against each
    factor (numeric factors by level, the direction of approach and the joint configuration as
    categories), whether its residuals look normal, and each model's effect parameters (the short
    base-parameter table, reports.parameter_table). A block that cannot be drawn becomes a note, as
    in the demo report.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.json").write_text(json.dumps(result, indent=2, ensure_ascii=False), encoding="utf-8")
    write_residuals(arrays, out)
    path = out / "report.html"
    path.write_text(build_compare_report(result, arrays), encoding="utf-8")
    return path
