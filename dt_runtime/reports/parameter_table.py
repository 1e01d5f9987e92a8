"""The effect parameters as one short table: what `dt fit` and `dt compare` print and the compare
report shows (`parameter_table`, `text`, `html`). See docs/effects.md ("Which parameters the data
determine").
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

GEOMETRIC_COLUMNS = ("offset", "dx", "dy", "dz", "rx", "ry", "rz")
COMBINED = "*"  # marks a base parameter that stands for a combination of several parameters


def shown_unit(unit: str) -> tuple[float, str]:
    """The factor and unit a value in `unit` (SI) is shown in: radians as mrad, metres as mm
    (also per hour, per kelvin, per %), 1/K as ppm/K; anything else as it is.

    Parameters
    ----------
    unit : str
        The SI unit.

    Returns
    -------
    factor : float
        What a value in `unit` is multiplied by.
    unit : str
        The unit shown.
    """
    if unit == "1/K":
        return 1e6, "ppm/K"
    m = re.fullmatch(r"(rad|m)(/.*)?", unit)
    if m:
        return 1e3, ("mrad" if m.group(1) == "rad" else "mm") + (m.group(2) or "")
    return 1.0, unit


def concise(v: float, u: float | None, plus_minus: bool = False) -> str:
    """`v` with its standard uncertainty `u`: u to two significant figures, v rounded to the same
    digit, as 0.0872(90) (GUM 7.2.2) or, with `plus_minus`, 0.0872 ± 0.0090; beyond 1e5 or
    below 1e-4 with a power of ten in steps of three, 4.8(5.3)e6.

    Parameters
    ----------
    v : float
        The value.
    u : float or None
        Its standard uncertainty (None: the value alone).
    plus_minus : bool, optional
        Write v ± u instead of the parenthesis form.

    Returns
    -------
    str
    """
    if u is None or not math.isfinite(u) or u <= 0 or (v and u < 1e-6 * abs(v)):
        return f"{v:.6g}"
    big = max(abs(v), u)
    if big >= 1e5 or big < 1e-4:
        e = 3 * math.floor(math.log10(big) / 3)
        return concise(v / 10 ** e, u / 10 ** e, plus_minus) + f"e{e}" if not plus_minus else \
            f"({concise(v / 10 ** e, u / 10 ** e, plus_minus)})e{e}"
    dec = 1 - math.floor(math.log10(u))
    if round(u, dec) >= 10 ** (2 - dec):  # 0.0995 rounds to 0.10: one digit fewer
        dec -= 1
    if dec > 0:
        vs, us, digits = f"{v:.{dec}f}", f"{u:.{dec}f}", f"{round(u * 10 ** dec):d}"
    else:
        vs, us = f"{round(v, dec):.0f}", f"{round(u, dec):.0f}"
        digits = us
    return f"{vs} ± {us}" if plus_minus else f"{vs}({digits})"


#: Smaller units a tiny value steps down to (factor from the unit before), rather than a power of
#: ten beside a unit: 0.000(34) urad, not 0(34)e-6 mrad.
_SMALLER = {"mrad": ((1e3, "µrad"), (1e3, "nrad")), "mm": ((1e3, "µm"), (1e3, "nm"))}


def with_unit(value: float, u: float | None, unit: str, plus_minus: bool = False) -> str:
    """`value` (and its standard uncertainty `u`), both in the SI `unit`, as text with the unit it is
    shown in: mrad / mm (`shown_unit`), or µrad, nrad / µm, nm when the larger of the two would
    otherwise be below 0.01 of it.

    Parameters
    ----------
    value : float
    u : float or None
    unit : str
        The SI unit ('rad', 'm', 'm/h', '1/K', ...).
    plus_minus : bool, optional
        Write v ± u instead of the parenthesis form.

    Returns
    -------
    str
    """
    f, shown = shown_unit(unit)
    v, s = value * f, (None if u is None else u * f)
    base, _, per = shown.partition("/")
    big = max(abs(v), abs(s) if s is not None and math.isfinite(s) else 0.0)
    for g, smaller in _SMALLER.get(base, ()):
        if big == 0 or big >= 1e-2:
            break
        v, s, big, base = v * g, None if s is None else s * g, big * g, smaller
    return f"{concise(v, s, plus_minus)} {base}{'/' + per if per else ''}"


def _cell(p: dict, plus_minus: bool, unit: bool = False) -> str:
    """A base parameter's value(u) in its shown unit (with `unit`, the unit after it, stepped down
    for a tiny value: `with_unit`), starred when it is a combination, '(at bound)' when physics'
    sign held it at 0."""
    f, shown = shown_unit(p["unit"])
    if unit:
        number, shown = with_unit(p["value"], p["u"], p["unit"], plus_minus).rsplit(" ", 1)
    else:
        number = concise(p["value"] * f, p["u"] * f, plus_minus)
    return number + (COMBINED if p.get("absorbs") else "") + (f" {shown}" if unit else "") + (
        " (at bound)" if p.get("at_bound") else "")


def _joint_column(name: str) -> tuple[str, str] | None:
    """(row, column) of a geometric parameter in the grid: ('joint 2', 'rx') for frame2_rx."""
    if m := re.fullmatch(r"offset_q(\d+)", name):
        return f"joint {m.group(1)}", "offset"
    if m := re.fullmatch(r"frame(\d+)_([dr][xyz])", name):
        return f"joint {m.group(1)}", m.group(2)
    if m := re.fullmatch(r"tool_(d[xyz])", name):
        return "tool", m.group(1)
    return None


@dataclass
class Grid:
    """The geometric base parameters: one row per joint frame and the tool."""

    title: str
    header: list[str]
    rows: list[list[str]]  # first cell: the row's label


@dataclass
class Line:
    """One effect's base parameters (and nonlinear parameters) in a line: (name, text) entries."""

    effect: str
    entries: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class ParameterTable:
    """A model's parameters for a report: grids (one row per joint frame), lines, how to read the
    cells, and notes.
    """
    grids: list[Grid]
    lines: list[Line]
    legend: str  # how to read the cells
    notes: list[str]  # what a star means; what the data cannot separate, one sentence


def legacy_base(parameters: list[dict]) -> dict:
    """A stand-in for the base parameters of a model saved before they were kept: its identified
    parameters, each on its own (the others, aliased, are counted as not identified).

    Parameters
    ----------
    parameters : list of dict
        The model's parameters (HybridModel.parameters).

    Returns
    -------
    dict
        In the form of HybridModel.base_parameters.
    """
    linear = [p for p in parameters if p.get("method") != "profile likelihood"]
    shown = [p for p in linear if p["value"] is not None]
    return {"rank": len(shown), "n_params": len(linear), "not_separable": len(linear) - len(shown),
            "no_effect": [], "parameters": shown, "legacy": True}


def parameter_table(parameters: list[dict], base: dict | None, plus_minus: bool = False) -> ParameterTable:
    """The table of a model's `parameters` (HybridModel.parameters: for the nonlinear ones) and its
    `base` (HybridModel.base_parameters; None for a model saved before they were kept:
    `legacy_base`).

    Parameters
    ----------
    parameters : list of dict
        HybridModel.parameters.
    base : dict or None
        HybridModel.base_parameters.
    plus_minus : bool, optional
        Write v ± u instead of the parenthesis form.

    Returns
    -------
    ParameterTable

    Notes
    -----
    The rows are the base parameters (the combinations the data determine), not the full
    rank-deficient set: the geometric effect as a grid, one row per joint frame (its offset,
    translation and rotation errors) plus the tool, the other effects one line each, and what the
    data cannot separate as one count; the per-parameter list (with the aliased groups) stays in the
    JSON. Values are shown in mrad and mm (radians and metres inside), with their standard
    uncertainty in the concise notation of the GUM (JCGM 100, 7.2.2): 0.087(9) mrad is 0.087 mrad
    with u = 0.009 mrad (`concise`).
    """
    base = base if base is not None else legacy_base(parameters)
    grids: list[Grid] = []
    lines: dict[str, Line] = {}
    geo = [p for p in base["parameters"] if p["effect"] == "geometric"]
    placed = {id(p): _joint_column(p["name"]) for p in geo}
    if geo and all(placed.values()):
        n_geo = sum(1 for p in parameters if p["effect"] == "geometric" and "method" not in p)
        cells: dict[str, dict[str, str]] = {}
        for p in geo:
            row, col = placed[id(p)]  # type: ignore[misc]
            cells.setdefault(row, {})[col] = _cell(p, plus_minus)
        order = sorted(cells, key=lambda r: (r == "tool", int(r.split()[1]) if r != "tool" else 0))
        units = {c: "mrad" if c in ("offset", "rx", "ry", "rz") else "mm" for c in GEOMETRIC_COLUMNS}
        used = [c for c in GEOMETRIC_COLUMNS if any(c in cells[r] for r in cells)]
        what = "identified parameters" if base.get("legacy") else "base parameters"
        grids.append(Grid(f"geometric: {len(geo)} {what} of {n_geo}", [""] + [f"{c}/{units[c]}" for c in used],
                          [[r] + [cells[r].get(c, "") for c in used] for r in order]))
    else:
        for p in geo:
            lines.setdefault("geometric", Line("geometric")).entries.append((p["name"], _cell(p, plus_minus, True)))
    for p in base["parameters"]:
        if p["effect"] != "geometric":
            lines.setdefault(p["effect"], Line(p["effect"])).entries.append((p["name"], _cell(p, plus_minus, True)))
    for p in parameters:
        if p.get("method") != "profile likelihood":
            continue
        text = (f"{with_unit(p['value'], p['u'], p['unit'], plus_minus)} (profile likelihood)"
                if p["value"] is not None else "not bounded by the data (default used)")
        lines.setdefault(p["effect"], Line(p["effect"])).entries.append((p["name"], text))
    legend = "value ± standard uncertainty" if plus_minus else "value(u), u the standard uncertainty in the last digits"
    notes = [f"{COMBINED} a combination of several parameters: base_parameters[].combination in the JSON"] \
        if any(p.get("absorbs") for p in base["parameters"]) else []
    k = base["not_separable"]
    if k:
        zero = [n.split(".", 1)[1] for n in base.get("no_effect") or []]
        none = ", ".join(zero) if len(zero) <= 4 else f"{len(zero)} parameters"
        notes.append(f"{k} of {base['n_params']} parameters not identified (aliased; the model was saved before "
                     "base parameters were kept): see parameters[].group in the JSON" if base.get("legacy") else
                     f"{k} direction{'s' if k != 1 else ''} of {base['n_params']} not separable by these data"
                     + (f" ({none}: no effect at all)" if none else "") + ": see parameters[].group in the JSON")
    return ParameterTable(grids, list(lines.values()), legend, notes)


def text(table: ParameterTable, width: int = 110) -> list[str]:
    """The table as lines of text: each grid with aligned columns, each effect on one line
    (wrapped at `width`).

    Parameters
    ----------
    table : ParameterTable
        The table.
    width : int, optional
        Line width of the wrapped lines.

    Returns
    -------
    list of str
    """
    out = []
    for g in table.grids:
        out.append(f"{g.title}, {table.legend}")
        rows = [g.header] + g.rows
        w = [max(len(r[c]) for r in rows) for c in range(len(g.header))]
        out += ["  " + "  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows]
    if table.lines and not table.grids:
        out.append(table.legend)
    for ln in table.lines:
        cur, first = f"{ln.effect}: ", True
        for name, txt in ln.entries:
            item = f"{name} {txt}"
            if not first and len(cur) + len(item) + 2 > width:
                out.append(cur + ",")
                cur, first = "    ", True
            cur += ("" if first else ", ") + item
            first = False
        out.append(cur)
    return out + table.notes


def html(table: ParameterTable, title: str) -> str:
    """The table as HTML: each grid as a table, the other effects' lines as one table, the notes
    as paragraphs; `title` heads the captions (e.g. the model's name).

    Parameters
    ----------
    table : ParameterTable
        The table.
    title : str
        Heads the captions.

    Returns
    -------
    str
    """
    from dt_runtime.reports.html import html_table, paragraph

    out = [html_table([dict(zip(g.header, r)) for r in g.rows], g.header, row_header="",
                      caption=f"{title}: {g.title}, {table.legend}") for g in table.grids]
    if table.lines:
        out.append(html_table([{"effect": ln.effect, "parameters": ", ".join(f"{k} {v}" for k, v in ln.entries)}
                               for ln in table.lines], ["effect", "parameters"], row_header="effect",
                              caption=f"{title}: " + ("other effects' " if table.grids else "")
                                      + f"base parameters, {table.legend}"))
    return "".join(out) + "".join(paragraph(n) for n in table.notes)
