"""The `dt demo` report: one self-contained HTML file for a metrologist.

`write_demo_report(result, path)` renders a `DemoResult` (summary dict in mm, arrays in SI:
metres and m/s; errors e = commanded - measured in the global frame GL, paper Eq. 8) into
headline figures, the paper's Tables 2-4, the GUM budgets and Eqs. 18-22 (tables here), and
Figs. 8-18 style plots (`demo_figures`). Every block is built independently: a missing summary
key or array (e.g. `e_true_doe` on real hardware) replaces that block by a note instead of
failing the demo (`blocks.run_block`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.metrology.stats import rms_with_U, wilson_interval
from dt_runtime.reports.blocks import Block, Missing, array, fixed, run_block, summary_value
from dt_runtime.reports.demo_figures import (
    fig_asis_series,
    fig_envelope,
    fig_eq17,
    fig_error_map,
    fig_gpr,
    fig_gpr_mvs,
    fig_main_effects,
    fig_registration,
    fig_validation,
    t_crit_and_flags,
)
from dt_runtime.reports.html import Section, esc, headline, html_page, html_table, note, paragraph
from dt_runtime.reports.traceability import traceability

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
            row[f"{ax}: ē / mm"] = fixed(a.get("mean_mm"))
            row[f"{ax}: s(e) / mm"] = fixed(a.get("std_mm"))
        row["n"] = s.get("n")
        rows.append(row)
    if not rows:
        raise Missing("no per-axis mean/std entries")
    return html_table(rows, caption=caption, row_header="quantity")


def _tables_registration(s: dict, a: dict) -> str:
    t2 = summary_value(s, "table2_registration_residuals")
    out = _mean_std_table(t2, caption="Table 2: registration residuals of the rototranslations (Eqs. 5-7), "
                                      "mean ē and standard deviation s(e) per GL axis")
    out += paragraph("A mean near zero is what a least-squares registration gives by construction; the standard "
                     "deviation enters the budgets as the registration reproducibility (paper, Table 2: LT 0.046, "
                     "0.042, 0.032 mm; MVS 0.080, 0.070, 0.042 mm).")
    return out


def _table_reprod(s: dict, a: dict) -> str:
    r = summary_value(s, "reproducibility_mm")
    paper = {"reprod_tcp": (0.0037, 0.0059, 0.0072), "reprod_mvs": (0.023, 0.019, 0.028)}
    rows = []
    for k, v in r.items():
        v = list(v) if v is not None else [None] * 3
        rows.append({"quantity": NAME_LABEL.get(k, k), **{f"{ax} / mm": fixed(v[i], 4) for i, ax in enumerate(AXES)},
                     "paper / mm": ", ".join(f"{p:.4f}" for p in paper[k]) if k in paper else "–"})
    return html_table(rows, caption="Positioning reproducibilities from replicated registration positionings "
                                    "(standard deviations, Eq. 12)", row_header="quantity")


def _table_asis(s: dict, a: dict) -> str:
    t3 = summary_value(s, "table3_as_is")
    return (_mean_std_table(t3, caption="Table 3: the arm as is (no correction): errors e = commanded − measured "
                                        "over the DOE, in GL")
            + paragraph("ē is the systematic error (accuracy), s(e) its dispersion (precision). These are what the "
                        "twin's GPR models learn and remove."))


def _table_model_residuals(s: dict, a: dict) -> str:
    t4 = summary_value(s, "table4_model_residuals_cv")
    out = _mean_std_table(t4, caption="Table 4: cross-validated residuals r = e − ê of the GPR error models")
    if isinstance(t4.get("note"), str):
        out += note(t4["note"])
    out += paragraph("Residuals of models that never saw the target point: ē near zero means the correction is "
                     "unbiased; s(r) is the model's prediction reproducibility that enters Eq. 13.")
    return out


def _table_expanded(s: dict, a: dict) -> str:
    eu = summary_value(s, "expanded_uncertainty_95")
    rows = []
    for key, v in eu.items():
        if not isinstance(v, dict):
            continue
        U, k, dof = (list(v.get(n) or [None] * 3) for n in ("U_mm", "k", "dof_eff"))
        rows.append({"quantity": EQ_LABEL.get(key, key),
                     **{f"U_{ax} / mm": fixed(U[i]) for i, ax in enumerate(AXES)},
                     **{f"k_{ax}": fixed(k[i], 3) for i, ax in enumerate(AXES)},
                     **{f"ν_eff,{ax}": ("∞" if dof[i] is None else fixed(dof[i], 1)) for i, ax in enumerate(AXES)},
                     "paper U / mm": ", ".join(f"{p:.3f}" for p in PAPER_U[key]) if key in PAPER_U else "–"})
    if not rows:
        raise Missing("no expanded uncertainties")
    return (html_table(rows, caption="Expanded uncertainties at 95 % coverage (Eqs. 18-22); k = t_0.975(ν_eff), "
                                     "ν_eff by Welch-Satterthwaite", row_header="quantity")
            + paragraph("U is the half-width of the interval expected to contain the true value with 95 % "
                        "probability; k follows from the effective degrees of freedom, not a fixed 2."))


def _table_precision(s: dict, a: dict) -> str:
    pp = summary_value(s, "precision_per_axis")
    b = list(pp.get("before_2s_e_mvs_doe_mm") or [None] * 3)
    af = list(pp.get("after_U_e_mvs_lt_hat_mm") or [None] * 3)
    rows = []
    for i, ax in enumerate(AXES):
        try:
            imp = 100 * (1 - float(af[i]) / float(b[i]))
        except (TypeError, ValueError, ZeroDivisionError):
            imp = float("nan")
        rows.append({"axis": ax, "before: 2 s(e_MVS,DOE) / mm": fixed(b[i]), "after: U(ê_MVS-LT) / mm": fixed(af[i]),
                     "improvement / %": fixed(imp, 1)})
    rows.append({"axis": "mean", "before: 2 s(e_MVS,DOE) / mm": fixed(s.get("precision_before_mm")),
                 "after: U(ê_MVS-LT) / mm": fixed(s.get("precision_after_mm")),
                 "improvement / %": fixed(s.get("improvement_pct"), 1)})
    return html_table(rows, caption="Tracking precision per axis (Sect. 3.3; paper: 1.256/0.958/0.576 mm → "
                                    "0.230/0.204/0.214 mm)", row_header="axis")


def _pretty_key(k: str) -> str:
    if k.endswith("_mm"):
        return k[:-3] + " / mm"
    return {"share_pct": "share of u_c² / % (x, y, z)", "dof": "ν (dof)", "k": "k (x, y, z)"}.get(k, k)


def _tables_budgets(s: dict, a: dict) -> str:
    budgets = summary_value(s, "budgets")
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
    lit = summary_value(s, "paper_literal_budget")
    rows = [{"item": k, "value": v} for k, v in lit.items() if k != "note"]
    out = html_table(rows, caption="Variant: the paper's literal budget (values in mm or %)", row_header="item")
    if isinstance(lit.get("note"), str):
        out += note(lit["note"])
    return out


def _coverage_rows(where: str, cov: dict, n: int | None, mean_U: list | None) -> list[dict]:
    rows = []
    for i, ax in enumerate(AXES):
        c = cov.get(ax)
        row = {"targets": where, "axis": ax, "coverage / %": fixed(100 * c, 1) if c is not None else "–"}
        if n and c is not None:
            k = int(round(float(c) * n))
            lo, hi = wilson_interval(k, int(n))
            row |= {"inside / n": f"{k} / {n}", "95 % interval (Wilson) / %": f"{100 * lo:.1f} – {100 * hi:.1f}"}
        if mean_U:
            row["mean U(TCP_c) / mm"] = fixed(mean_U[i])
        rows.append(row)
    return rows


def _table_coverage(s: dict, a: dict) -> str:
    chk = s.get("coverage_check")
    if isinstance(chk, dict):  # per-position U, checked inside and outside the calibrated volume
        parts = [("inside the DOE hull", chk.get("inside")), ("50-150 mm outside", chk.get("outside")),
                 ("validation phase", chk.get("validation"))]
        rows = [r for where, c in parts if isinstance(c, dict)
                for r in _coverage_rows(where, c.get("coverage_95") or {}, c.get("n"), c.get("mean_U_mm"))]
    else:  # an older summary: one global U at the validation points
        U = array(a, "U_tcp_c", required=False)
        mean_U = list(U * MM_PER_M) if U is not None and U.ndim == 1 and U.size == 3 else None
        rows = _coverage_rows("validation phase", summary_value(s, "coverage_95"), s.get("n_validation"), mean_U)
    return (html_table(rows, caption="Coverage of the 95 % expanded uncertainty U(TCP_c) of each corrected position "
                                     "by its true error (simulator truth)", row_header="targets")
            + paragraph("If the uncertainty statement is right, about 95 % of the true errors lie inside ±U; "
                        "the interval shows how far a finite set of targets can confirm that. Outside the DOE "
                        "hull the stated U grows with the distance (extrapolation)."))


def _table_ttest(s: dict, a: dict) -> str:
    tt = summary_value(s, "t_test_eq17")
    tcrit, _ = t_crit_and_flags(s, a)
    per = tt.get("pass_fraction_per_axis") or {}
    rows = [{"axis": ax, "pass / %": fixed(100 * per[ax], 1) if per.get(ax) is not None else "–",
             "t_crit (95 %, two-sided)": fixed(tcrit[i], 3)} for i, ax in enumerate(AXES)]
    allp = tt.get("pass_fraction_all_axes")
    rows.append({"axis": "all three axes", "pass / %": fixed(100 * allp, 1) if allp is not None else "–",
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


def _headline(s: dict, a: dict) -> str:
    cards = []
    pb, pa, imp = s.get("precision_before_mm"), s.get("precision_after_mm"), s.get("improvement_pct")
    if pb is not None and pa is not None:
        cards.append(headline("Tracking precision (mean of x, y, z)", f"{fixed(pb)} mm → {fixed(pa)} mm",
                              "Before: the camera system alone scatters by 2 s(e_MVS) over the DOE. After: the twin's "
                              "prediction of the camera-vs-tracker error has this 95 % expanded uncertainty (Eq. 22)."))
    if imp is not None:
        cards.append(headline("Precision improvement", f"{fixed(imp, 1)} %",
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
            return f" ± {fixed(U * MM_PER_M)}" if math.isfinite(U) else ""

        cards.append(headline("True 3D RMS error, validation targets",
                              f"{fixed(ru)}{unc_of('val_true_err_plain')} mm → "
                              f"{fixed(rc)}{unc_of('val_true_err_corr')} mm",
                              f"Distance between where the arm was sent and where it really went (simulator truth), "
                              f"without and with the twin's correction, over {s.get('n_validation', '?')} "
                              "positionings; "
                              "± is the 95 % uncertainty of the RMS estimate."))
    if red is not None:
        cards.append(headline("True error reduction", f"{fixed(red, 1)} %",
                              "Share of the real 3D RMS positioning error the correction removes."))
    cov = s.get("coverage_95")
    if isinstance(cov, dict):
        txt = ", ".join(f"{ax} {fixed(100 * cov[ax], 1)} %" for ax in AXES if cov.get(ax) is not None)
        cards.append(headline("Coverage of U(TCP_c), 95 % nominal", txt,
                              "Fraction of corrected validation points whose true error lies inside the stated "
                              "95 % expanded uncertainty; close to 95 % means the uncertainty is honest."))
    if not cards:
        raise Missing("no headline figures in the summary")
    return ('<div class="cards">' + "".join(cards) + "</div>"
            + paragraph("All lengths in millimetres; errors are e = commanded − measured in the global frame GL "
                        "(paper Eq. 8); expanded uncertainties U are at 95 % coverage with k from the effective "
                        "degrees of freedom."))


def demo_sections(result) -> list[Section]:
    s = getattr(result, "summary", None) or {}
    a = getattr(result, "arrays", None) or {}
    plan: list[tuple[str, str, list[Block]]] = [
        ("Key figures", "key", [_headline]),
        ("Phase 1: registration of the instruments", "registration",
         [_tables_registration, _table_reprod, fig_registration]),
        ("Phase 2: the arm as is (DOE)", "asis", [_table_asis, fig_error_map, fig_asis_series, fig_main_effects]),
        ("GPR error models", "gpr", [_table_model_residuals, fig_gpr, fig_gpr_mvs]),
        ("Uncertainty (GUM)", "uncertainty",
         [_table_expanded, _table_precision, fig_envelope, _tables_budgets, _table_literal]),
        ("Phase 3: validation", "validation", [_table_coverage, fig_validation, _table_ttest, fig_eq17]),
        ("Run", "run", [_table_run]),
        ("Traceability", "traceability", [traceability]),
    ]
    return [Section(title, "".join(run_block(b, s, a) for b in blocks), anchor)
            for title, anchor, blocks in plan]


def build_demo_report(result, title: str = "Traceable digital twin of the cobot: demo report") -> str:
    s = getattr(result, "summary", None) or {}
    origin = (f"Campaign {s['campaign']}" if "scenario" not in s and s.get("campaign")
              else f"Scenario {s.get('scenario', '?')}, seed {s.get('seed', '?')}")
    sub = origin + (", quick plan" if s.get("quick") else "") + ". " + str(s.get("units", "Units: mm."))
    return html_page(title, demo_sections(result), subtitle=sub)


def write_demo_report(result, path, title: str | None = None) -> Path:
    """Write the self-contained HTML report of a `DemoResult` (or of a calibration: its summary
    and arrays, the truth-based blocks then say they are not available) to `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(build_demo_report(result, *(() if title is None else (title,))), encoding="utf-8")
    return path
