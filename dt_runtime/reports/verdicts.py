"""The words of a diagnosis: the verdict of `dt diagnose` (one step) and `dt diagnose --auto`,
written from the results' JSON (analysis.results.DiagnoseResult / AutoResult.to_dict), so the
library's figures and the sentences a user reads cannot drift apart. The last sentence of an
--auto verdict says whether the final model may be deployed and, when not, what to do.
"""
from __future__ import annotations

from typing import Any

from dt_runtime.analysis.change import Change


def verdict(result: Any) -> str:
    """The verdict of a diagnosis result (analysis.results.DiagnoseResult or AutoResult, or its
    `to_dict()`).

    Parameters
    ----------
    result : DiagnoseResult, AutoResult or dict
        The result.

    Returns
    -------
    str
    """
    d = result if isinstance(result, dict) else result.to_dict()
    return auto_verdict(d) if "steps" in d else ranking_verdict(d)


def with_verdict(result: Any) -> dict:
    """The result's JSON object with its `verdict` (what `dt diagnose --json` prints).

    Parameters
    ----------
    result : DiagnoseResult, AutoResult or dict
        The result.

    Returns
    -------
    dict
    """
    d = result if isinstance(result, dict) else result.to_dict()
    return d | {"verdict": verdict(d)}


GP_FACTOR = {"tcp_speed": "the Cartesian TCP and speed", "tcp": "the Cartesian TCP", "joints": "the joint angles"}
SCHEME = {"regions": "held-out regions of the workspace", "sessions": "held-out sessions",
          "forward": "later times (a forecast: fitted on the earlier part only)", "points": "held-out points"}
FACTOR = {"time": "the time", "temperature": "the temperature", "speed": "the speed", "payload": "the payload",
          "direction": "the direction of approach"}
# What would make a confounded factor testable.
REMEDY = {"time": "repeat about 10 poses spread over the workspace at the end of the campaign (or every hour)",
          "temperature": "measure the same poses again at another temperature (a second pass after the hall "
                         "warmed or cooled)",
          "speed": "measure the same poses at two or more speeds",
          "payload": "measure the same poses with two or more payloads",
          "direction": "approach the same poses from other directions (a second pass in another order)"}
SESSION_TERM = {"tool": "a tool (SMR) offset", "base": "a set-up (base) change",
                "joints": "a change of the joint zeros"}


def _factor(f: str) -> str:
    return FACTOR.get(f, f"the column '{f}'")


def not_testable_sentences(items: list[dict]) -> str:
    """Sentences for the candidates the campaign could not separate from the pose.

    Parameters
    ----------
    items : list of dict
        The result's `not_testable` entries.

    Returns
    -------
    str
    """
    out = []
    for it in items:
        if it.get("reason") != "confounded":
            continue
        for f in it["findings"]:
            name, factor = it["candidate"], f["factor"]
            if f["against"] == "constant":
                why = f"{_factor(factor)} did not vary in this campaign"
            elif f["against"] == "scan":
                why = (f"{_factor(factor)} moved with the position: no pose was measured again later (a scan: "
                       f"{f.get('revisited', 0)} of {f.get('points', 0)} poses revisited after "
                       f"{100 * f.get('min_gap', 0.1):.0f} % of the campaign's time), so an error that changes with "
                       f"{_factor(factor)} cannot be told from one that changes with position")
            elif f["against"] == "missing":
                why = f"the data have no {_factor(factor)}"
            else:
                why = (f"{_factor(factor)} followed the pose (R^2 {f['r2']:.2f} of its value predicted from the "
                       f"neighbouring poses: each pose was measured at one {factor if factor in FACTOR else 'value'}"
                       f"{', in a scan' if factor == 'time' else ''}), so an error that changes with "
                       f"{_factor(factor)} cannot be told from one that changes with position")
            out.append(f" '{name}' is not testable on this campaign: {why}; to test it, "
                       f"{REMEDY.get(factor, f'measure the same poses at other values of {_factor(factor)}')}.")
    return "".join(out)


def _deploy_clause(g: dict) -> str:
    kind = g.get("deploy_kind")
    if kind is None:
        return ""
    a, b = g["deploy_rmse_before_mm"], g["deploy_rmse_after_mm"]
    if b < a:
        return f"; on {SCHEME[kind]} it lowers the 3D RMS from {a:.4f} to {b:.4f} mm"
    return (f"; but on {SCHEME[kind]} it raises the 3D RMS from {a:.4f} to {b:.4f} mm: it wins between measured "
            "points only, do not add it for new poses")


def column_sentence(checks: list[dict], model_columns: set[str]) -> str:
    """'The residual follows column X' for the best significant column the model does not read.

    Parameters
    ----------
    checks : list of dict
        The column checks of the held-out residual.
    model_columns : set of str
        The columns the model reads.

    Returns
    -------
    str
        Empty when no such column.
    """
    top = next((c for c in checks if c["significant"] and c["column"] not in model_columns), None)
    if top is None:
        return ""
    text = (f" The held-out residual follows the column '{top['column']}' (p = {top['p_value']:.2g}, "
            f"{100 * top['explained_fraction']:.0f} % of its variance over the points)")
    r2 = top.get("pose_r2")
    if r2 is not None and r2 > 0.9:
        return text + (f", but the column itself followed the pose (R^2 {r2:.2f}): the residual may follow the "
                       "position instead, which this campaign cannot tell apart; measure the same poses at other "
                       f"values of '{top['column']}'.")
    if top["column"] in ("speed", "temperature", "payload", "t") or top["column"].startswith("q"):
        return text + "."
    # The user's own effects that read it were candidates and did not make it: their form is wrong.
    own = top.get("read_by") or []
    if own:
        return text + (f": your effect(s) {', '.join(own)} read it but did not explain a significant part; the "
                       "error follows it in another form (another axis, joint-space, a lag?).")
    return text + ": no effect of the catalogue reads it; declare an effect of your own."


def ranking_verdict(d: dict) -> str:
    """The one-step verdict: the effect the model lacks (or none), with the deployment figure.

    Parameters
    ----------
    d : dict
        `DiagnoseResult.to_dict()`.

    Returns
    -------
    str
    """
    ranking, gps = d["ranking"], d.get("gp_inputs_ranking", [])
    top = ranking[0] if ranking else None
    before, floor = d["rmse_base_mm"], d.get("noise_floor_mm")
    if top and top["significant"]:
        text = (f"The model lacks '{top['effect']}': adding it explains {100 * top['explained_fraction']:.0f} % of "
                f"the held-out residual variance (p = {top['p_value']:.2g}), because the residual follows "
                f"{top.get('factor') or 'its factor'}{_deploy_clause(top)}.")
    else:
        text = "No candidate effect explains a significant part of the held-out residual (all p >= 0.01)"
        text += (f"; the residual ({before:.3f} mm RMS) is at the measurement noise floor ({floor:.3f} mm)."
                 if floor and before < 1.3 * floor else ".")
    g = gps[0] if gps else None
    if g and g["significant"] and (top is None or not top["significant"]
                                   or g["explained_fraction"] > top["explained_fraction"]):
        # The advice names the command-line option: the verdict is read by the user of `dt`.
        text += (f" The GP on {GP_FACTOR[g['gp_inputs']]} instead of {GP_FACTOR[d['gp_inputs']]} explains "
                 f"{100 * g['explained_fraction']:.0f} % (p = {g['p_value']:.2g}){_deploy_clause(g)}: "
                 f"fit with gp_inputs='{g['gp_inputs']}' (dt fit --gp-inputs {g['gp_inputs']}).")
    text += not_testable_sentences(d.get("not_testable", []))
    text += column_sentence(d.get("columns", []), set(d.get("model_columns", [])))
    return text


def _follows(step: dict) -> str:
    change = Change.parse(step["change"])
    if change.kind == "session":
        return ": the sessions differ by " + SESSION_TERM[change.name]
    if step.get("follows"):
        return f": the residual followed {step['follows']}"
    return ""


def _why(step: dict) -> str:
    if Change.parse(step["change"]).kind == "remove":  # the backward pass (analysis.selection.prune)
        return (f"{step['change']} (in the final model it explained {100 * (step['explained_fraction'] or 0):.1f} % "
                f"more, p = {step['p_value']:.2g}: no longer needed once the later changes were in)")
    return (f"{step['change']} (explains {100 * (step['explained_fraction'] or 0):.0f} %, p = {step['p_value']:.2g}"
            + _follows(step) + ")")


def _head_to_head(h: dict) -> str:
    a, b, f = h["a"], h["b"], h["factor"]
    both = f"'{a}' and '{b}' both read {_factor(f) if f in FACTOR else f}; tested head to head in both orders"
    figures = ""
    if "deploy_rmse_a_mm" in h:  # each alone, held out on the deployment scheme
        dep = {a: h["deploy_rmse_a_mm"], b: h["deploy_rmse_b_mm"]}
        win, lose = h.get("winner", a), h.get("loser", b)
        figures = (f" Held out on {h['deploy_kind']}: with '{win}' {dep[win]:.4f} mm, with '{lose}' {dep[lose]:.4f} mm;"
                   f" winner '{win}', loser '{lose}'.")
    if h["preferred"] in (a, b):
        win, lose = (a, b) if h["preferred"] == a else (b, a)
        p_lose = h["p_b_beyond_a"] if win == a else h["p_a_beyond_b"]
        p_win = h["p_a_beyond_b"] if win == a else h["p_b_beyond_a"]
        return (f" {both}, the data prefer '{win}' ('{lose}' explains nothing beyond it, p = {p_lose:.2g}; "
                f"'{win}' beyond '{lose}': p = {p_win:.2g})." + figures)
    if h["preferred"] == "both":
        return f" {both}, each explains part of the residual the other leaves: both are real." + figures
    took = h.get("winner", a)
    return (f" {both}, neither explains anything beyond the other: this campaign cannot tell them apart "
            f"(took '{took}', the lower held-out error); {REMEDY.get(f, 'vary the factors independently')} to "
            "separate them." + figures)


def _vector(params: list[dict], unit: str) -> str:
    """'(dx, dy, dz) = (0.449, -0.299, 0.354) mm +/- 0.003 mm' for the parameters in `unit`."""
    par = [q for q in params if q["unit"] == unit]
    names = ", ".join(q["name"] for q in par)
    values = ", ".join(f"{q['value']:.3f}" for q in par)
    return f"({names}) = ({values}) {unit} +/- {max(q['U'] for q in par):.3f} {unit}"


def session_sentences(d: dict) -> str:
    """Sentences on the sessions: how each fares held out, and the session terms found.

    Parameters
    ----------
    d : dict
        The result's JSON object.

    Returns
    -------
    str
        Empty for one session.
    """
    rows = d.get("sessions") or []
    if not rows:
        return ""
    text = ""
    tested = d.get("session_terms_tested") or []
    values = d.get("session_term_values") or []
    if values:
        ref = d.get("reference_session")
        for v in values:
            sig = v.get("p_value")
            parts = [_vector(v["parameters"], unit) for unit in dict.fromkeys(q["unit"] for q in v["parameters"])]
            text += (f" Session {v['session']} ({v['name']}) differs from the reference session"
                     f"{f' ({ref})' if ref else ''} by {SESSION_TERM[v['term']]}: {' and '.join(parts)} (expanded, "
                     f"95 %, k = {v['k']:.2f}{f'; p = {sig:.2g}' if sig is not None else ''}).")
        text += (" The model carries it as a nuisance (fitted per session, not deployed: it predicts the "
                 "reference session's robot); held-out sessions are scored after measuring it again.")
    worse = [r for r in rows if r["rmse_mm"] > r["as_is_rmse_mm"]]
    text += " Held out by session (each predicted by the model fitted on the others"
    absorbed = sorted({a for r in rows for a in r.get("absorbed", [])})
    text += f", after {' and '.join(absorbed)} measured again" if absorbed else ""
    text += "): " + "; ".join(f"{r['name']} {r['rmse_mm']:.4f} mm (as is {r['as_is_rmse_mm']:.4f})" for r in rows)
    text += "."
    if worse and not values:
        sig = [g for g in tested if g.get("significant")]
        tested_txt = ", ".join(f"{SESSION_TERM[g['session']]} p = {g['p_value']:.2g}" for g in tested)
        if not sig:
            text += (f" The sessions disagree: the model of the others predicts "
                     f"{', '.join(r['name'] for r in worse)} worse than no correction, by nothing a session term "
                     f"explains ({tested_txt}); check that session's set-up and registration, or leave it out "
                     f"(--exclude-session {worse[0]['name']}).")
    for r in rows:
        dom = r.get("outside_training") or {}
        if dom.get("rows"):
            text += (f" Session {r['session']} ({r['name']}) leaves the other sessions' domain in {dom['rows']} of "
                     f"{r['rows']} rows ("
                     + ", ".join(f"{c}: {n}" for c, n in dom["columns"].items())
                     + "): its figures are an extrapolation.")
    return text


def auto_verdict(d: dict) -> str:
    """The verdict of `dt diagnose --auto` in words: what was added or removed, the figures before
    and after on the deployment scheme, and what is left.

    Parameters
    ----------
    d : dict
        `AutoResult.to_dict()`.

    Returns
    -------
    str
    """
    steps = [s for s in d["steps"] if s["change"]]
    first, final = d["steps"][0]["rmse_mm"], d["final_rmse_mm"]
    kind = d["deploy_kind"]
    # the JSON carries each change's label; read back as a typed change (analysis.change)
    removed = any(Change.parse(a).kind == "remove" for a in d["added"])
    if steps:
        why = "; ".join(_why(s) for s in steps)
        text = (f"{'Changed' if removed else 'Added'} {', '.join(d['added'])}: "
                f"the 3D RMS held out by point fell from {first:.4f} to {final:.4f} mm, "
                f"on {SCHEME[kind]} from {d['steps'][0]['deploy_rmse_mm']:.4f} to {d['final_deploy_rmse_mm']:.4f} mm "
                f"({why}). Each addition{' (or pair of additions)' if _pairs(d) else ''} "
                f"was significant by point and lowered the RMS on {SCHEME[kind]}"
                + (" (a forecast of later times for a time-dependent term)" if kind == "regions" else "")
                + ("; each removal no longer lowered the error significantly and left that RMS no higher"
                   if removed else "") + ".")
    else:
        text = (f"Nothing to add: the 3D RMS stays {final:.4f} mm held out by point, "
                f"{d['final_deploy_rmse_mm']:.4f} mm on {SCHEME[kind]}.")
    rejected: dict[str, list[dict]] = {}
    for s in d["steps"]:
        for h in s.get("head_to_head") or []:
            text += _head_to_head(h)
        for r in s.get("rejected") or []:
            rejected.setdefault(r["change"], []).append(r)
        if (t := s.get("together")) is not None:  # vetoed alone, taken with the next change
            rejected.pop(t["first"], None)
            text += (f" {t['first']} alone raised the RMS on {SCHEME[t['deploy_kind']]}, but with {t['with']} "
                     f"(beyond it p = {t['p_with']:.2g}) the pair lowers it from {t['deploy_rmse_before_mm']:.4f} to "
                     f"{t['deploy_rmse_after_mm']:.4f} mm: both taken (the first, fitted without the second, bent to "
                     "what the second explains).")
    for change, rs in rejected.items():
        r = rs[-1]
        at = f" (at {len(rs)} steps; the last:" if len(rs) > 1 else " ("
        text += (f" {change} was significant by point but raised the RMS on {SCHEME[r['deploy_kind']]}{at} p = "
                 f"{r['p_value']:.2g}, explains {100 * r['explained_fraction']:.0f} %, "
                 f"{r['deploy_rmse_before_mm']:.4f} -> {r['deploy_rmse_after_mm']:.4f} mm): not added (it fits the "
                 "campaign, not the next measurements).")
    text += not_testable_sentences(d.get("not_testable", []))
    text += column_sentence(d.get("columns", []), set(d.get("model_columns", [])))
    text += session_sentences(d)
    text += _floor_sentence(d)
    text += _deploy_sentence(d)
    return text


def _pairs(d: dict) -> bool:
    return any(s.get("together") for s in d["steps"])


def floor_unknown(d: dict) -> str:
    """That the noise floor is not known, and what to measure for it (the result's
    `noise_floor.to_measure`): the sentence of the verdict and of the command's text.

    Parameters
    ----------
    d : dict
        The result's JSON object.

    Returns
    -------
    str
    """
    measure = (d.get("noise_floor") or {}).get("to_measure") or "measure some poses repeatedly"
    return ("The noise floor is not known: the data state no uncertainty ux..uz and hold no replicates (give the "
            f"instrument's MPE with --mpe-mm, or {measure})")


def _floor_sentence(d: dict) -> str:
    floor, ratio, final = d.get("noise_floor_mm"), d.get("floor_ratio"), d["final_rmse_mm"]
    info = d.get("noise_floor") or {}
    src = f" (from {info['source']})" if info.get("source") else ""
    stop = d.get("stop_reason")
    if ratio is None:
        return " " + floor_unknown(d) + "."
    if ratio <= 1.3:
        return (f" Stopped{' at the floor' if stop == 'floor' else ': nothing more passes'}; the residual is at the "
                f"noise floor ({final:.4f} mm vs {floor:.4f} mm{src}: {ratio:.2f}x).")
    return (f" Stopped: nothing more passes; the residual is still {ratio:.1f}x the noise floor ({floor:.4f} mm{src}) "
            "and no candidate of the catalogue explains a significant part of it that holds on new measurements: "
            "something the catalogue does not know is missing"
            + (" (see the column above)." if column_sentence(d.get("columns", []), set(d.get("model_columns", [])))
               else
               " (no column of the data explains it either: a factor that was not logged?)."))


def _deploy_sentence(d: dict) -> str:
    dep = d.get("deploy") or {}
    where = f" Saved to {d['model_out']}." if d.get("model_out") else ""
    if dep.get("ok"):
        if dep.get("by") == "sessions":
            return (" Deploy: every held-out session is predicted better than with no correction." + where)
        return (f" Deploy: on {SCHEME[dep.get('by', 'regions')]} the final model predicts "
                f"{d['final_deploy_rmse_mm']:.4f} mm against {d['as_is_rmse_mm']:.4f} mm with no correction." + where)
    if dep.get("by") == "sessions":
        worse = [r["name"] for r in d.get("sessions", []) if r["rmse_mm"] > r["as_is_rmse_mm"]]
        return (f" Do not deploy: held out, {', '.join(worse)} would be predicted worse than with no correction; "
                "see the sessions above (fit with the session term they name, or leave the odd session out)." + where)
    return (f" Do not deploy: on {SCHEME[dep.get('by', 'regions')]} the final model ({d['final_deploy_rmse_mm']:.4f} "
            f"mm) is no better than no correction ({d['as_is_rmse_mm']:.4f} mm)." + where)

