"""The "Traceability" block of every report: which software made it and when, from which input
files (short SHA-256), on which robot, with which instruments (certificate and stated
uncertainty) and at what temperature, from the result's `provenance` record
(dt_runtime.common.provenance, as JSON)."""
from __future__ import annotations

from typing import Any

from dt_runtime.reports.blocks import fixed
from dt_runtime.reports.html import html_table, note

SHORT = 12  # hex digits of a SHA-256 shown in a report


def _uncertainty(u: Any) -> str:
    if not isinstance(u, dict):
        return "–"
    if u.get("text"):
        return str(u["text"])
    terms = u.get("terms") or {}
    txt = " + ".join(f"{t.get('value')} {t.get('unit')}" for t in terms.values() if isinstance(t, dict))
    kind = u.get("kind") or ""
    return f"{kind} {txt}".strip() + (f" (k = {u['k']})" if u.get("k") else "")


def traceability(s: dict, a: dict) -> str:
    """The block of the `provenance` key of a summary or result (a report block).

    Parameters
    ----------
    s : dict
        The summary or result (`to_dict()`).
    a : dict
        Its arrays.

    Returns
    -------
    str
        HTML.
    """
    p = s.get("provenance") if isinstance(s, dict) else None
    if not isinstance(p, dict):  # a result saved before the record existed
        return note("This result carries no traceability record (key 'provenance'): it was made by a "
                    "version of the software that did not write one.")
    sw = p.get("software") or {}
    rows: list[dict[str, Any]] = [
        {"item": "software", "value": f"{sw.get('name', '?')} {sw.get('version', '?')}"},
        {"item": "commit", "value": sw.get("commit") or "– (not run from a git checkout)"},
        {"item": "created (UTC)", "value": p.get("created")},
        {"item": "Python", "value": p.get("python")}]
    rob = p.get("robot")
    if isinstance(rob, dict):
        what = rob.get("path") or rob.get("name") or "?"
        rows.append({"item": "robot", "value": what + (f" (sha256 {rob['sha256'][:SHORT]})" if rob.get("sha256")
                                                      else "")})
    env = p.get("environment")
    t = env.get("temperature_c") if isinstance(env, dict) else None
    rows.append({"item": "temperature", "value": (f"{fixed(t.get('min'), 2)} – {fixed(t.get('max'), 2)} °C, mean "
                                                  f"{fixed(t.get('mean'), 2)} °C over {t.get('n')} rows")
                 if isinstance(t, dict) else "not recorded (the data have no temperature column)"})
    out = html_table(rows, row_header="item", caption="What produced these results")
    files = [f for f in p.get("inputs") or [] if isinstance(f, dict)]
    if files:
        out += html_table([{"file": f.get("path"), "sha256 (first 12)": str(f.get("sha256", ""))[:SHORT],
                            "bytes": f.get("size_bytes")} for f in files], row_header="file",
                          caption="Input files (SHA-256: the full digest is in the JSON)")
    inst = [i for i in p.get("instruments") or [] if isinstance(i, dict)]
    if inst:
        out += html_table([{"role": i.get("role"), "instrument": i.get("kind"), "driver": i.get("driver"),
                            "model / serial": " / ".join(str(v) for v in (i.get("model"), i.get("serial")) if v)
                            or "–",
                            "certificate": i.get("certificate") or "none stated",
                            "calibrated": i.get("calibration_date"),
                            "stated uncertainty": _uncertainty(i.get("uncertainty"))} for i in inst],
                          row_header="role", caption="Instruments and their stated uncertainty")
    else:
        out += note("No instruments recorded: give the campaign's instruments and certificates with "
                    "--instruments (configs/instruments_example.yaml).")
    return out
