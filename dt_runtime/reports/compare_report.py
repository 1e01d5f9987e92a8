"""The `dt compare` report: one self-contained HTML page and the JSON beside it.

`write_compare_report(result, arrays, out_dir)` renders what `dt_runtime.compare.compare`
returns: the models side by side, the "watch the error fall" plot, where the primary model
(the last one) fails (residual maps, residual against each factor, the worst cells), whether
its residuals look normal, and each model's effect parameters (the short base-parameter table,
reports.parameter_table). The HTML helpers and the per-block
fallback (a block that cannot be drawn becomes a note) are those of the demo report.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis.compare import MIN_CELL
from dt_runtime.reports.blocks import COLORS, Missing, fixed, levels, run_block
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
)
from dt_runtime.reports.parameter_table import parameter_table
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
    """A warning when a model was trained on these very data: its figures are in-sample."""
    ins = s.get("in_sample") or []
    if not ins:
        return ""
    return note(f"<strong>Warning: in-sample figures.</strong> {', '.join(ins)} "
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
        ax.annotate(f"{yi:.3f}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    fl = s.get("noise_floor_mm")
    if fl is not None:
        ax.axhline(fl, color="tab:red", ls="--", lw=1, label=f"noise floor {fl:.3f} mm")
        ax.legend(fontsize=8)
    ax.set_xticks(x, [m["name"] for m in ms], rotation=15, fontsize=8)
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
            out.append(note(f"{m['name']} ({m.get('description', '')}): no physical effect terms."))
            continue
        t = parameter_table(ps, m.get("base_parameters"), plus_minus=True)
        for g in t.grids:
            out.append(html_table([dict(zip(g.header, r)) for r in g.rows], g.header, row_header="",
                                  caption=f"{m['name']} ({m.get('description', '')}): {g.title}, {t.legend}"))
        if t.lines:
            out.append(html_table([{"effect": ln.effect, "parameters": ", ".join(f"{k} {v}" for k, v in ln.entries)}
                                   for ln in t.lines], ["effect", "parameters"], row_header="effect",
                                  caption=f"{m['name']}: " + ("other effects' " if t.grids else "")
                                          + f"base parameters, {t.legend}"))
        out += [paragraph(n) for n in t.notes]
    return "".join(out)


def _table_method(s: dict, a: dict) -> str:
    t = s["t_test"]
    rows = [{"item": "data", "value": s.get("dataset")}, {"item": "rows", "value": s["n"]},
            {"item": "t-test", "value": t["equation"]}, {"item": "u_model", "value": t["u_model"]},
            {"item": "u_meas", "value": t["u_meas_source"]}, {"item": "units", "value": s.get("units")}]
    return html_table(rows, row_header="item")


# --------------------------------------------------------------------------- figures

def per_point(commanded: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replicates aggregated per commanded position (1 um): (positions, mean of `values` per
    position, row count per position)."""
    key = np.round(np.asarray(commanded, float) / 1e-6).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(float)
    v = np.asarray(values, float).reshape(len(inv), -1)
    means = np.stack([np.bincount(inv, weights=v[:, k]) for k in range(v.shape[1])], axis=1) / cnt[:, None]
    return np.asarray(commanded)[first], means, cnt


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
            axp.legend(fontsize=8, loc="best")
        axp.set_xlabel(f"{AXES[i]} / mm"), axp.set_ylabel(f"{AXES[j]} / mm")
        axp.set_title(f"{AXES[i]}-{AXES[j]} view", fontsize=10)
        axp.grid(alpha=0.3)
        fig.colorbar(sc, ax=axp, extend="max").set_label("|mean r| per point / mm")
    fig.tight_layout()
    return figure_block(fig_to_img_tag(fig, alt="residual maps"),
                        f"Residual maps of {p['name']}, one marker per commanded point (robot frame, mm; size: its "
                        f"number of rows): colour is the 3D norm of the point's mean residual |mean(e − ê)| (mm; the "
                        f"scale ends at the 95th percentile, {vmax:.3f} mm, so one outlier does not wash out the "
                        f"rest); red crosses mark points failing the Eq. 17 t-test in at least half of their rows "
                        f"({100 * float(fail_rows.mean()):.1f} % of all rows fail in at least one axis).")


def _factor_values(a: dict) -> list[tuple[str, np.ndarray]]:
    out = []
    for key, label, f in (("speed", "speed / (mm/s)", MM_PER_M), ("payload", "payload / kg", 1.0),
                          ("temperature", "temperature / °C", 1.0), ("t", "time from start / s", 1.0)):
        v = a.get(key)
        if v is not None and np.nanstd(v) > 0:
            v = np.asarray(v, float) * f
            out.append((label, v - np.nanmin(v) if key == "t" else v))
    q = a.get("joints")
    if q is not None:
        j = 2 if q.shape[1] > 2 else 0  # the elbow: the joint whose angle most changes the reach
        out.append((f"q{j + 1} / deg", np.degrees(q[:, j])))
    return out


def _approach(a: dict) -> list[tuple[str, np.ndarray]]:
    """The direction from which each joint approached (sign of its change from the previous row;
    rows in time order), for the joints that move: what backlash and lag follow."""
    q = a.get("joints")
    if q is None or len(q) < 3:
        return []
    d = np.sign(np.diff(q, axis=0, prepend=q[:1]))
    d[0] = d[1]
    return [(f"approach of q{j + 1} (-1 / +1)", d[:, j]) for j in range(q.shape[1]) if np.any(d[:, j] != 0)][:3]


def _fig_factors(s: dict, a: dict) -> str:
    models = (a.get("models") or [])[1:] or [_primary(a)]  # every model (as is has its own table)
    fv = _factor_values(a) + _approach(a)
    if not fv:
        raise Missing("the data have no speed, payload, temperature, time or joint columns")
    fig, axs = plt.subplots(1, len(fv), figsize=(3.3 * len(fv) + 1, 3.6), squeeze=False, sharey=True)
    cmap = plt.get_cmap("tab10")
    for axp, (label, v) in zip(axs[0], fv):
        ok = np.isfinite(v)
        idx, centres = levels(v[ok])
        for mi, m in enumerate(models):
            r = np.linalg.norm(m["residual"], axis=1)[ok] * MM_PER_M
            means = [np.sqrt(np.mean(r[idx == i] ** 2)) if np.any(idx == i) else np.nan for i in range(len(centres))]
            axp.plot(centres, means, "o-", ms=3, lw=1.2, color=cmap(mi % 10), label=m["name"])
        axp.set_xlabel(label, fontsize=9)
        axp.grid(alpha=0.3)
        axp.tick_params(labelsize=7)
    axs[0, 0].set_ylabel("3D RMS of r per level / mm")
    axs[0, 0].legend(fontsize=7)
    fig.tight_layout()
    return figure_block(fig_to_img_tag(fig, alt="residual against each factor"),
                        "3D RMS of the residual (mm) of every model per level or quantile bin of each factor, "
                        "the direction of approach of the moving joints included: a model whose curve rises or "
                        "steps where the others stay flat misses the effect that follows that factor.")


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
        axs[k].set_title(f"r_{ax}: R = {rr:.3f}, slope {slope:.3f} mm", fontsize=9)
        axs[k].set_xlabel("theoretical normal quantile", fontsize=8)
        axs[k].set_ylabel(f"r_{ax} / mm", fontsize=8)
        axs[k].grid(alpha=0.3)
    fig.tight_layout()
    return figure_block(fig_to_img_tag(fig, alt="normal probability plot"),
                        f"Normal probability plots of the residual components of {p['name']} (mm): a straight line "
                        "means normal residuals; bent tails or steps mean outliers or a missing effect.")


# --------------------------------------------------------------------------- assembly

def compare_sections(result: dict, arrays: dict) -> list[Section]:
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
    names = ", ".join(m["name"] for m in result.get("models", []))
    return html_page("Cobot digital twin: model against measurements", compare_sections(result, arrays),
                     subtitle=f"{result.get('n', '?')} rows of {result.get('dataset', '?')}; columns: {names}. "
                              "Lengths in mm; e = commanded − measured (paper Eq. 8), r = e − ê.")


def write_compare_report(result: dict, arrays: dict, out_dir) -> Path:
    """Write out_dir/report.html and out_dir/compare.json; return the HTML path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.json").write_text(json.dumps(result, indent=2, ensure_ascii=False), encoding="utf-8")
    path = out / "report.html"
    path.write_text(build_compare_report(result, arrays), encoding="utf-8")
    return path
