"""The `dt demo` and `dt calibrate` report: one self-contained HTML file a metrologist reads in
one pass (`write_demo_report`; the figures: `demo_figures`).

Its first screen says whether the figures may be trusted, then the key figures; a section that
does not apply is left out with one line saying why. See docs/cli.md ("dt demo", "dt calibrate").
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
from dt_runtime.reports.html import (
    STATUS_WORD,
    Section,
    headline,
    html_page,
    html_table,
    note,
    paragraph,
    validity_banner,
)
from dt_runtime.reports.parameter_table import html as parameters_html
from dt_runtime.reports.parameter_table import parameter_table
from dt_runtime.reports.traceability import traceability

# The paper's published values, shown beside ours for orientation (mm).
PAPER_U = {"eq18_tcp_c": (0.118, 0.109, 0.171), "eq19_e_lt_hat": (0.117, 0.108, 0.170),
           "eq20_e_lt_hat_minus_e_mvs": (0.203, 0.182, 0.198), "eq21_e_mvs": (0.166, 0.146, 0.102),
           "eq22_e_mvs_lt_hat": (0.230, 0.204, 0.214)}
EQ_LABEL = {"eq18_tcp_c": "Eq. 18  U(TCP_c), global over the DOE", "eq19_e_lt_hat": "Eq. 19  U(ê_LT)",
            "eq20_e_lt_hat_minus_e_mvs": "Eq. 20  U(ê_LT − e_MVS)", "eq21_e_mvs": "Eq. 21  U(e_MVS)",
            "eq22_e_mvs_lt_hat": "Eq. 22  U(ê_MVS-LT)"}
BUDGET_LABEL = {
    "eq11_tcp_c": "Eq. 11: u(TCP_c), the position a corrected command reaches, global over the DOE (→ Eq. 18)",
    "eq13_e_lt_hat": "Eq. 13: u(ê_LT), the twin's prediction of the laser-tracker error (→ Eq. 19)",
    "eq14_e_lt_hat_minus_e_mvs": "Eq. 14: u(ê_LT − e_MVS), the camera-tracked difference of Eq. 17 (→ Eq. 20)",
    "eq15_e_mvs": "Eq. 15: u(e_MVS), the camera system's error (→ Eq. 21)",
    "eq16_e_mvs_lt_hat": "Eq. 16: u(ê_MVS-LT), the twin's prediction of camera minus tracker (→ Eq. 22)"}
NAME_LABEL = {"rdk": "e_RDK,GL (robot encoders)", "lt": "e_LT,GL (laser tracker)", "mvs": "e_MVS,GL (camera system)",
              "e_lt_doe": "e_LT,DOE", "e_mvs_doe": "e_MVS,DOE", "e_mvs_lt_doe": "e_MVS-LT,DOE",
              "r_lt": "r_LT (held-out)", "r_mvs_lt": "r_MVS-LT (held-out)",
              "r_lt_replicate_means": "r_LT, replicate means", "r_mvs_lt_replicate_means": "r_MVS-LT, replicate means",
              "reprod_tcp": "reprod_TCP (encoders, Eq. 12)", "reprod_mvs": "reprod_MVS (camera system, Eq. 12)"}
GP_WORDS = {"tcp_speed": "GP on the TCP and speed", "tcp": "GP on the TCP", "joints": "GP on the joint angles",
            "none": "no GP"}
# The one U the key figures state, defined once (docs/demo.md: "The uncertainty of each corrected position").
U_DEFINITION = ("U(TCP_c) is the 95 % expanded uncertainty of the position a corrected command reaches, stated at "
                "that position: Eq. 11 with the error model's own spread there (λ σ_GP(c), scaled so that over the "
                "DOE it states the held-out spread) and, beyond the DOE hull, the extrapolation term κ d(c). The "
                "paper's Eq. 18 states one global value for the whole DOE (the global s(r_LT) in place of "
                "λ σ_GP(c)); it appears only in the Eq. 18 table.")


def _fmt_list(v, nd: int) -> str:
    """A per-axis list (or one number) with `nd` decimals; None as ∞ (dof)."""
    seq = v if isinstance(v, (list, tuple)) else [v]
    return ", ".join("∞" if x is None else fixed(x, nd) for x in seq)


def _check(s: dict, key: str) -> dict | None:
    """The validity check `key` (e.g. 'coverage_inside') of the summary, if there is one."""
    v = s.get("validity")
    checks = v.get("checks") if isinstance(v, dict) else None
    return next((c for c in checks or [] if isinstance(c, dict) and c.get("check") == key), None)


def _is_calibration(s: dict) -> bool:
    """A `dt calibrate` summary (no simulator: no truth, no scenario)."""
    return "scenario" not in s


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
                        "twin's error models learn and remove."))


def model_words(s: dict) -> str:
    """The e_LT map in words: 'geometric + thermal + GP on the TCP and speed', or the paper's GPR.

    Parameters
    ----------
    s : dict
        The run's summary.

    Returns
    -------
    str
    """
    m = (s.get("maps") or {}).get("e_lt") or {}
    effects = list(m.get("effects") or [])
    gp = m.get("gp_inputs", "tcp_speed")
    if not effects:
        return "GPR on the TCP and speed (the paper's)" if gp == "tcp_speed" else f"{GP_WORDS.get(gp, gp)} alone"
    return " + ".join(effects) + (f" + {GP_WORDS.get(gp, gp)}" if gp != "none" else "")


def _table_model_residuals(s: dict, a: dict) -> str:
    t4 = summary_value(s, "table4_model_residuals_cv")
    out = _mean_std_table(t4, caption="Table 4: cross-validated residuals r = e − ê of the error models")
    if isinstance(t4.get("note"), str):
        out += note(t4["note"])
    out += paragraph("Residuals of models that never saw the target point: ē near zero means the correction is "
                     "unbiased; s(r) is the model's prediction reproducibility that enters Eq. 13.")
    return out


def _table_parameters(s: dict, a: dict) -> str:
    m = (s.get("maps") or {}).get("e_lt") or {}
    if not m.get("parameters"):
        return paragraph(f"The e_LT map is {model_words(s)}: no physical effect terms, so no physical parameters; "
                         "the GP carries the whole error.")
    return (paragraph(f"The e_LT map is {model_words(s)}: the effects' fitted physical parameters below, the GP on "
                      "what they leave. Geometric parameters are reported as the base parameters the DOE determines "
                      "(combinations where it cannot separate them).")
            + parameters_html(parameter_table(m["parameters"], m.get("base_parameters"), plus_minus=True),
                              "e_LT map"))


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
                     **{f"ν_eff,{ax}": ("∞" if dof[i] is None else fixed(dof[i], 0)) for i, ax in enumerate(AXES)},
                     "paper U / mm": ", ".join(f"{p:.3f}" for p in PAPER_U[key]) if key in PAPER_U else "–"})
    if not rows:
        raise Missing("no expanded uncertainties")
    return (html_table(rows, caption="Expanded uncertainties at 95 % coverage (Eqs. 18-22), global over the DOE as the "
                                     "paper states them; k = t_0.975(ν_eff), ν_eff by Welch-Satterthwaite",
                       row_header="quantity")
            + paragraph("U is the half-width of the interval expected to contain the true value with 95 % "
                        "probability; k follows from the effective degrees of freedom, not a fixed 2. The twin "
                        "states each corrected position's own U(TCP_c) (key figures); Eq. 18 is its global "
                        "counterpart."))


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


# Decimals per budget column (mm to 0.1 um: the smallest components are a few tenths of a um).
BUDGET_COLUMNS: dict[str, tuple[str, int | None]] = {
                  "component": ("component", None), "equation": ("equation", None), "type": ("type", None),
                  "distribution": ("distribution", None),
                  **{f"u_{ax}_mm": (f"u_{ax} / mm", 4) for ax in AXES}, "dof": ("ν (dof)", 0),
                  "share_pct": ("share of u_c² / % (x, y, z)", 1), "k": ("k (x, y, z)", 3),
                  **{f"U_{ax}_mm": (f"U_{ax} / mm", 4) for ax in AXES}}


def _budget_cell(column: str, v):
    """A budget cell: a number (or a per-axis list) with its column's decimals, text as it is."""
    nd = BUDGET_COLUMNS.get(column, (column, None))[1]
    return v if nd is None else _fmt_list(v, nd)


def _tables_budgets(s: dict, a: dict) -> str:
    budgets = summary_value(s, "budgets")
    out = [paragraph("One row per uncertainty component (standard uncertainties u, mm), then the combined "
                     "standard uncertainty u_c with its effective degrees of freedom, the coverage factor k and the "
                     "expanded uncertainty U. ν = ∞ marks a component taken as exactly known (type B without dof). "
                     "These are the paper's global budgets over the DOE.")]
    for name, rows in budgets.items():
        if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
            raise Missing(f"budget '{name}' has no rows")
        cols = [c for c in BUDGET_COLUMNS if any(c in r for r in rows)]
        cols += [c for r in rows for c in r if c not in cols and c not in BUDGET_COLUMNS]
        shown = [{c: _budget_cell(c, r[c]) for c in cols if c in r} for r in rows]
        out.append(html_table(shown, cols, headers={c: BUDGET_COLUMNS.get(c, (c, None))[0] for c in cols},
                              caption=BUDGET_LABEL.get(name, name), none="∞"))
    return "".join(out)


def _table_literal(s: dict, a: dict) -> str:
    lit = summary_value(s, "paper_literal_budget")
    rows = [{"figure": "precision after: mean U(ê_MVS-LT), Eq. 22 / mm", "value": fixed(lit.get("precision_after_mm"))},
            {"figure": "improvement / %", "value": fixed(lit.get("improvement_pct"), 1)},
            {"figure": "U(TCP_c), Eq. 18, global / mm (x, y, z)", "value": _fmt_list(lit.get("U_tcp_c_mm"), 3)}]
    cov = lit.get("coverage_95")
    if isinstance(cov, dict):
        rows.append({"figure": "coverage of that U by the true errors of the corrected validation positionings / % "
                               "(x, y, z)", "value": ", ".join(fixed(100 * cov[ax], 1) if cov.get(ax) is not None
                                                               else "–" for ax in AXES)})
    return (html_table(rows, caption="Variant: the paper's Eqs. 11-16 taken literally (registration residual spread "
                                     "added: double counts)", row_header="figure")
            + paragraph("Beside our budget for orientation only: the registration spread it adds is mostly the arm's "
                        "own error along the registration lines, which the error model already carries (docs/demo.md, "
                        "'Honest uncertainty')."))


def _targets_label(key: str, c: dict) -> str:
    n, asked = c.get("n"), c.get("n_requested")
    extra = f" ({asked} asked for)" if asked and n is not None and n < asked else ""
    return {"inside": f"{n} random targets inside the DOE hull{extra}",
            "outside": f"{n} random targets 50-150 mm outside the hull{extra}",
            "validation": f"the {n} corrected validation positionings"}.get(key, key)


def _coverage_rows(key: str, where: str, cov: dict, n: int | None, mean_U: list | None, s: dict) -> list[dict]:
    check = _check(s, f"coverage_{key}") or {}
    n_eff = int(check.get("n_distinct") or n or 0)
    rows = []
    for i, ax in enumerate(AXES):
        c = cov.get(ax)
        row = {"targets": where, "axis": ax, "coverage / %": fixed(100 * c, 1) if c is not None else "–"}
        if n and c is not None:
            k = int(round(float(c) * n))
            lo, hi = wilson_interval(float(c) * n_eff, n_eff)
            row |= {"inside / n": f"{k} / {n}", "95 % interval / %": f"{100 * lo:.1f} – {100 * hi:.1f}"}
        if mean_U:
            row["mean U(TCP_c) / mm"] = fixed(mean_U[i])
        axis = (check.get("axes") or {}).get(ax) or {}
        if axis.get("status"):
            row["status"] = STATUS_WORD[axis["status"]]
        rows.append(row)
    return rows


def _table_coverage(s: dict, a: dict) -> str:
    chk = s.get("coverage_check")
    if isinstance(chk, dict):  # per-position U, checked inside and outside the calibrated volume
        rows = [r for key in ("inside", "outside", "validation") if isinstance(chk.get(key), dict)
                for r in _coverage_rows(key, _targets_label(key, chk[key]), chk[key].get("coverage_95") or {},
                                        chk[key].get("n"), chk[key].get("mean_U_mm"), s)]
    else:  # an older summary: one global U at the validation points
        U = array(a, "U_tcp_c", required=False)
        mean_U = list(U * MM_PER_M) if U is not None and U.ndim == 1 and U.size == 3 else None
        rows = _coverage_rows("validation", "validation phase", summary_value(s, "coverage_95"),
                              s.get("n_validation"), mean_U, s)
    return (html_table(rows, caption="Coverage of each corrected position's U(TCP_c) (95 %) by its true error "
                                     "(simulator truth); band 90-99 %", row_header="targets")
            + paragraph("If the uncertainty statement is right, about 95 % of the true errors lie inside ±U. The "
                        "interval (Wilson, 95 %) is over the distinct targets: the replicates of one target share "
                        "its model error. Outside the DOE hull the stated U grows with the distance "
                        "(extrapolation)."))


def _table_validation_tracker(s: dict, a: dict) -> str:
    """A campaign's validation phase against the laser tracker (dt calibrate)."""
    v = summary_value(s, "validation")
    rows = [{"figure": "positionings (uncorrected commands)", "value": str(v.get("n"))},
            {"figure": "3D RMS of the tracker-measured error e_LT / mm", "value": fixed(v.get("rms_e_lt_mm"), 4)},
            {"figure": "3D RMS of e_LT − ê_LT, what a corrected command would keep / mm",
             "value": fixed(v.get("rms_after_map_mm"), 4)},
            {"figure": "reduction / %", "value": fixed(v.get("reduction_pct"), 1)}]
    cov = v.get("coverage_95") or {}
    out = html_table(rows, row_header="figure", caption="Validation phase: the twin against the laser tracker at "
                                                        "points the maps never saw")
    out += html_table(_coverage_rows("validation", f"the {v.get('n')} validation positionings", cov, v.get("n"),
                                     v.get("mean_U_mm"), s),
                      caption="Coverage of each position's U(TCP_c) (95 %) by e_LT − ê_LT; band 90-99 %",
                      row_header="targets")
    return out + paragraph("The tracker's reading carries its own noise and the positioning reproducibility, so "
                           "this coverage tests the stated U a little more strictly than the truth would.")


def _table_ttest(s: dict, a: dict) -> str:
    tt = summary_value(s, "t_test_eq17") if "t_test_eq17" in s else summary_value(s, "validation", "t_test_eq17")
    tcrit, _ = t_crit_and_flags(s, a)
    per = tt.get("pass_fraction_per_axis") or {}
    rows = [{"axis": ax, "pass / %": fixed(100 * per[ax], 1) if per.get(ax) is not None else "–",
             "t_crit (95 %, two-sided)": fixed(tcrit[i], 3)} for i, ax in enumerate(AXES)]
    allp = tt.get("pass_fraction_all_axes")
    rows.append({"axis": "all three axes", "pass / %": fixed(100 * allp, 1) if allp is not None else "–",
                 "t_crit (95 %, two-sided)": ""})
    out = html_table(rows, caption=f"Eq. 17 t-test on {tt.get('n', '?')} validation measurements: "
                                   "t = ((ê_LT − e_MVS) − ê_MVS-LT) / sqrt(u²(ê_LT − e_MVS) + u²(ê_MVS-LT))",
                     row_header="axis")
    out += paragraph("A measurement passes when |t| ≤ t_crit: the camera-tracked error agrees with the twin's "
                     "prediction within the stated uncertainty. In a healthy cell about 95 % pass per axis; a "
                     "persistent drop would trigger maintenance.")
    eq = _check(s, "eq17_vs_coverage")
    if eq and eq.get("status") == "fail":
        out += note(f"{eq['finding']}: {eq.get('evidence', '')}.")
    return out


def _table_run(s: dict, a: dict) -> str:
    labels = {"scenario": "scenario (the simulated plant)", "quick": "quick plan", "seed": "seed", "n_doe": "DOE rows",
              "n_validation": "validation positionings", "n_refusals": "refused positionings",
              "elapsed_s": "run time / s", "campaign": "campaign manifest"}
    rows = [{"item": label, "value": s[k]} for k, label in labels.items() if k in s]
    if not rows:
        raise Missing("no run information")
    out = html_table(rows, row_header="item")
    if s.get("refusals"):
        out += html_table([{"refusal": r} if not isinstance(r, dict) else r for r in s["refusals"][:20]],
                          caption="Refused positionings (first 20)")
    return out


def _validity(s: dict, a: dict) -> str:
    """The first thing on the page: may these figures be trusted (the summary's `validity`)?"""
    return validity_banner(s.get("validity"))


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
    if isinstance(s.get("maps"), dict):
        cards.append(headline("Error model e_LT", model_words(s), _model_sentence(s)))
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
                              "positionings; ± is the 95 % uncertainty of the RMS estimate."))
    if red is not None:
        cards.append(headline("True error reduction", f"{fixed(red, 1)} %",
                              "Share of the real 3D RMS positioning error the correction removes."))
    val = s.get("validation")
    if isinstance(val, dict) and val.get("n"):
        cards.append(headline(f"Laser-tracker error at the {val['n']} validation positionings (3D RMS)",
                              f"{fixed(val.get('rms_e_lt_mm'))} mm → {fixed(val.get('rms_after_map_mm'))} mm",
                              "Uncorrected commands at points the maps never saw, and what is left after subtracting "
                              "the twin's prediction: the error a corrected command would keep."))
    cards += _coverage_cards(s)
    if not cards:
        raise Missing("no headline figures in the summary")
    return ('<div class="cards">' + "".join(cards) + "</div>"
            + paragraph(U_DEFINITION)
            + paragraph("All lengths in millimetres; errors are e = commanded − measured in the global frame GL "
                        "(paper Eq. 8); expanded uncertainties U are at 95 % coverage with k from the effective "
                        "degrees of freedom (Welch-Satterthwaite)."))


def _model_sentence(s: dict) -> str:
    """The e_LT map's physical parameters in one sentence (the non-geometric effects' lines)."""
    m = (s.get("maps") or {}).get("e_lt") or {}
    if not m.get("parameters"):
        return "The paper's model: a Gaussian process on what the arm does, no physical effect terms."
    t = parameter_table(m["parameters"], m.get("base_parameters"), plus_minus=True)
    parts = [f"{ln.effect}: " + ", ".join(f"{k} {v}" for k, v in ln.entries) for ln in t.lines]
    parts += [g.title for g in t.grids]
    return "Fitted: " + "; ".join(parts) + " (section 'Error model')."


def _coverage_cards(s: dict) -> list[str]:
    """One card per coverage the validity checks: the fraction of positions inside their own U."""
    out = []
    chk: dict = s["coverage_check"] if isinstance(s.get("coverage_check"), dict) else {}
    sources = [(k, chk[k], "true errors (simulator)") for k in ("inside", "validation")
               if isinstance(chk.get(k), dict) and chk[k].get("n")]
    if not sources and isinstance(s.get("coverage_95"), dict):  # an older summary
        sources = [("validation", {"coverage_95": s["coverage_95"], "n": s.get("n_validation")},
                    "true errors (simulator)")]
    val = s.get("validation")
    if isinstance(val, dict) and val.get("n"):
        sources.append(("validation", val, "tracker-measured e_LT − ê_LT"))
    for key, c, truth in sources:
        cov = c.get("coverage_95") or {}
        txt = ", ".join(f"{ax} {fixed(100 * cov[ax], 1)} %" for ax in AXES if cov.get(ax) is not None)
        check = _check(s, f"coverage_{key}") or {}
        where = _targets_label(key, c) if truth.startswith("true") else f"the {c['n']} validation positionings"
        out.append(headline(f"Coverage of U(TCP_c) at {where}", txt,
                            f"Fraction of the {truth} inside the stated 95 % U of their own position; the band is "
                            "90-99 %." + (f" {STATUS_WORD[check['status']]}." if check.get("status") else ""),
                            status=check.get("status", "")))
    return out


def _next_steps(s: dict, a: dict) -> str:
    """The last section: where the twin and its records are, and what to do with it now."""
    twin = s.get("twin")
    if not twin:
        raise Missing("the summary does not say where the twin was written (key 'twin')")
    out_dir = Path(twin) if _is_calibration(s) else Path(twin).parent
    rows = [{"what": "the twin (error maps, budgets, calibrated volume; JSON + NPZ)", "where": str(twin)},
            {"what": "this report", "where": str(out_dir / "report.html")},
            {"what": "the summary (every figure, the validity block)", "where": str(out_dir / "summary.json")}]
    if s.get("campaign"):
        rows.append({"what": "the campaign's files it was calibrated from", "where": str(s["campaign"])})
    out = html_table(rows, row_header="what", caption="Where the twin is")
    v: dict = s["validity"] if isinstance(s.get("validity"), dict) else {}
    status = v.get("status")
    flagged = [c for c in v.get("checks") or [] if c.get("status") in ("fail", "warn") and c.get("advice")]
    first = [(f"Fix: {c['cause']}" if c.get("cause") else "Fix", c["advice"]) for c in flagged]
    if status == "unchecked":
        first.append(("Validate it", "measure a validation phase (uncorrected commands at points the DOE did not "
                                     "visit) and give it to dt calibrate with --validation"))
    if first:
        out += html_table([{"step": k, "how": v} for k, v in first], row_header="step",
                          caption="What to do first" + (": do not rely on its stated uncertainty until its "
                                                        "checks pass" if status == "fail" else ""))
    steps = [("Correct a program offline",
               f"dt correct --twin {twin} --targets program.csv --out program_corrected.csv"),
              ("Run it in the cell", f"dt run --config RUNTIME.yaml with 'twin: {twin}' (docs/service.md)"),
              ("Check it on new measurements", f"dt compare --model {twin} --data new.csv --report compare"),
              ("Look for a missing physical effect", f"dt diagnose --model {twin} --data new.csv"),
              ("Export the calibrated robot", f"dt export --twin {twin} --format urdf --out robot.urdf")]
    return out + html_table([{"step": k, "how": v} for k, v in steps], row_header="step",
                            caption="Then" if first else "What to do next")


def demo_sections(result) -> list[Section]:
    """The demo or calibration report's sections, each from its blocks.

    Parameters
    ----------
    result : DemoResult or calibration
        Anything with `summary` and `arrays`.

    Returns
    -------
    list of Section
    """
    s = getattr(result, "summary", None) or {}
    a = getattr(result, "arrays", None) or {}
    truth = array(a, "val_true_err_corr", 3, required=False) is not None or "true_rms_corrected_mm" in s
    if truth:  # the demo: the simulator's truth at the validation and the coverage checks
        validation: list[Block] = [_table_coverage, fig_validation, _table_ttest, fig_eq17]
    elif isinstance(s.get("validation"), dict) and s["validation"].get("n"):  # a campaign's tracker validation
        validation = [_table_validation_tracker, _table_ttest]
    else:
        validation = [_left_out("The campaign has no validation phase, so nothing here tests the stated "
                                "uncertainty (measure one and give it with --validation).")]
    envelope = [fig_envelope] if array(a, "val_target", 3, required=False) is not None else []
    plan: list[tuple[str, str, list[Block]]] = [
        ("Key figures", "key", [_validity, _headline]),
        ("Phase 1: registration of the instruments", "registration",
         [_tables_registration, _table_reprod, fig_registration]),
        ("Phase 2: the arm as is (DOE)", "asis", [_table_asis, fig_error_map, fig_asis_series, fig_main_effects]),
        (f"Error model: {model_words(s)}", "model", [_table_parameters, _table_model_residuals, fig_gpr,
                                                                fig_gpr_mvs]),
        ("Uncertainty (GUM)", "uncertainty", [_table_expanded, _table_precision, *envelope, _tables_budgets,
                                               _table_literal]),
        ("Phase 3: validation" + ("" if truth else " against the laser tracker"), "validation", validation),
        ("Run" if not _is_calibration(s) else "Campaign", "run", [_table_run]),
        ("Traceability", "traceability", [traceability]),
        ("Where the twin is and what to do next", "next", [_next_steps]),
    ]
    return [Section(title, "".join(run_block(b, s, a) for b in blocks), anchor)
            for title, anchor, blocks in plan]


def _left_out(why: str) -> Block:
    """A block standing for a section that does not apply: one line saying why."""
    def block(s: dict, a: dict) -> str:
        return paragraph(why)
    return block


def build_demo_report(result, title: str = "Traceable digital twin of the cobot: demo report") -> str:
    """The demo or calibration report as one self-contained HTML page.

    Parameters
    ----------
    result : DemoResult or calibration
        Anything with `summary` and `arrays`.
    title : str, optional
        The page's title.

    Returns
    -------
    str
    """
    s = getattr(result, "summary", None) or {}
    origin = (f"Campaign {s['campaign']}" if _is_calibration(s) and s.get("campaign")
              else f"Scenario {s.get('scenario', '?')}, seed {s.get('seed', '?')}")
    sub = (origin + (", quick plan" if s.get("quick") else "") + ". Lengths in mm; errors e = commanded − measured, "
           "in the global frame GL.")
    return html_page(title, demo_sections(result), subtitle=sub)


def write_demo_report(result, path, title: str | None = None) -> Path:
    """Write the self-contained HTML report of a `DemoResult` (or of a calibration: its summary
    and arrays; its sections are those a campaign without truth gives) to `path`.

    The summary dict is in mm, the arrays in SI (metres and m/s; errors e = commanded - measured
    in the global frame GL, paper Eq. 8). The report's first screen says whether the figures may be
    trusted (the summary's `validity`, `analysis.validity`), then the key figures with the definition of
    the one U they state; then the paper's Tables 2-4, the error model with its effects and their
    fitted physical parameters, the GUM budgets and Eqs. 18-22, the validation (against the
    simulator's truth in the demo, the laser tracker in a campaign's validation phase), Figs. 8-18
    style plots (`demo_figures`), the traceability record and, last, where the twin is and what to
    do next. A section is chosen by what the result holds (a calibration has no truth; a campaign
    may have no validation phase): one that does not apply is left out with one line saying why. A
    block that fails on damaged data becomes a note instead of sinking the run (`blocks.run_block`).

    Parameters
    ----------
    result : DemoResult or calibration
        Anything with `summary` and `arrays`.
    path : str or Path
        The HTML file (its directory is made if needed).
    title : str, optional
        The page's title.

    Returns
    -------
    Path
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(build_demo_report(result, *(() if title is None else (title,))), encoding="utf-8")
    return path
