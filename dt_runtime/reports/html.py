"""Small, generic building blocks for self-contained HTML reports.

Every report of the twin is ONE file: figures are inline base64 PNGs, the style sheet is inline,
nothing is fetched from the network. All text that reaches the page goes through `esc`; callers
pass plain text, never markup, except for the `body` of a section (HTML from these helpers):

    body = html_table(rows, caption="Budget (mm)") + fig_to_img_tag(fig, alt="...")
    Path("report.html").write_text(html_page("My report", [Section("Results", body)]))
"""
from __future__ import annotations

import base64
import html
import io
import math
import numbers
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import matplotlib

matplotlib.use("Agg")  # headless, before pyplot is imported anywhere through this module
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["Section", "esc", "fmt_value", "fig_to_img_tag", "html_table", "html_page", "paragraph",
           "note", "headline", "banner", "figure_block", "plt"]

NONE_MARK = "–"
_NUMERIC = re.compile(r"[-−+]?(\d+(\.\d*)?|∞)(, [-−+]?(\d+(\.\d*)?|∞))*")


@dataclass(frozen=True)
class Section:
    """One titled part of a page. `body` is HTML built with these helpers (not escaped again)."""

    title: str
    body: str
    anchor: str | None = None


def esc(text: Any) -> str:
    """Escape any value for HTML text or attribute context.

    Parameters
    ----------
    text : Any
        The value (converted with str).

    Returns
    -------
    str
    """
    return html.escape(str(text), quote=True)


def fmt_value(v: Any, digits: int = 4, none: str = NONE_MARK) -> str:
    """Plain-text rendering of a table cell: numbers with `digits` significant figures,
    NaN as 'NaN', infinities as '∞', None as `none`, sequences joined with ', '.

    Parameters
    ----------
    v : Any
        The value.
    digits : int, optional
        Significant figures.
    none : str, optional
        How None is shown.

    Returns
    -------
    str
    """
    if v is None:
        return none
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        f = float(v)
        if math.isnan(f):
            return "NaN"
        if math.isinf(f):
            return "∞" if f > 0 else "-∞"
        return f"{f:.{digits}g}"
    if isinstance(v, dict):
        return "; ".join(f"{k}: {fmt_value(x, digits, none)}" for k, x in v.items())
    if isinstance(v, (list, tuple)) or hasattr(v, "tolist"):
        seq = v.tolist() if hasattr(v, "tolist") else v
        if not isinstance(seq, list):
            return fmt_value(seq, digits, none)
        return ", ".join(fmt_value(x, digits, none) for x in seq)
    return str(v)


def fig_to_img_tag(fig, alt: str = "", dpi: int = 80, close: bool = True, width: str | None = None,
                   tight: bool = False) -> str:
    """Render a matplotlib figure as an inline base64 PNG <img> tag (and close it).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    alt : str, optional
        The image's alternative text.
    dpi : int, optional
        Resolution.
    close : bool, optional
        Close the figure after rendering.
    width : str, optional
        CSS width of the image.
    tight : bool, optional
        Crop to the drawn content.

    Returns
    -------
    str
    """
    buf = io.BytesIO()
    try:
        # bbox_inches="tight" costs a second full draw; callers lay out with tight_layout instead
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    finally:
        if close:
            plt.close(fig)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    style = f' style="width:{esc(width)}"' if width else ""
    return f'<img src="data:image/png;base64,{data}" alt="{esc(alt)}"{style}>'


def figure_block(img_tag: str, caption: str) -> str:
    """A figure with a plain-text caption (escaped).

    Parameters
    ----------
    img_tag : str
        The image (`fig_to_img_tag`).
    caption : str
        Plain text.

    Returns
    -------
    str
    """
    return f"<figure>{img_tag}<figcaption>{esc(caption)}</figcaption></figure>"


def html_table(rows: Iterable[dict], columns: Sequence[str] | None = None, *,
               headers: dict[str, str] | None = None, caption: str | None = None,
               digits: int = 4, none: str = NONE_MARK, missing: str = "",
               row_header: str | None = None) -> str:
    """A table from a list of dicts. Columns default to the union of the rows' keys in order of
    first appearance. A None value renders as `none` (e.g. '∞' for dof), a key the row lacks as
    `missing`. `headers` maps key -> display label. `row_header` names a column rendered as <th>.

    Parameters
    ----------
    rows : iterable of dict
        One dict per row.
    columns : sequence of str, optional
        The keys shown, in order.
    headers : dict, optional
        Key -> display label.
    caption : str, optional
        The table's caption.
    digits : int, optional
        Significant figures of numbers.
    none : str, optional
        How None is shown.
    missing : str, optional
        How a key the row lacks is shown.
    row_header : str, optional
        A column rendered as <th>.

    Returns
    -------
    str
    """
    rows = list(rows)
    if columns is None:
        columns = []
        for r in rows:
            for k in r:
                if k not in columns:
                    columns.append(k)
    headers = headers or {}
    out = ['<table>']
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{esc(headers.get(c, c))}</th>" for c in columns)
               + "</tr></thead><tbody>")
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c)
            tag = "th" if c == row_header else "td"
            # a number, or a number already formatted (e.g. '0.0145' or a per-axis '1.972, 1.967, 1.977')
            num = (isinstance(v, numbers.Real) and not isinstance(v, bool)) or bool(
                isinstance(v, str) and v and _NUMERIC.fullmatch(v))
            cls = ' class="num"' if num else ""
            cells.append(f"<{tag}{cls}>{esc(fmt_value(v, digits, none) if c in r else missing)}</{tag}>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def paragraph(text: str) -> str:
    """A paragraph of escaped text.

    Parameters
    ----------
    text : str
        Plain text.

    Returns
    -------
    str
    """
    return f"<p>{esc(text)}</p>"


def note(text: str) -> str:
    """A visually distinct remark (e.g. a section skipped for missing data).

    Parameters
    ----------
    text : str
        Plain text.

    Returns
    -------
    str
    """
    return f'<p class="note">{esc(text)}</p>'


def headline(label: str, value: str, sentence: str = "", status: str = "") -> str:
    """A key figure card: a label, a value (with its unit and uncertainty) and one plain sentence;
    `status` ('fail', 'warn', 'ok') colours it when the figure's validity was checked.

    Parameters
    ----------
    label : str
        What the figure is.
    value : str
        The figure with its unit and uncertainty.
    sentence : str, optional
        One plain sentence.
    status : str, optional
        'fail', 'warn', 'ok' or empty.

    Returns
    -------
    str
    """
    cls = f"card {status}" if status in STATUSES else "card"
    return (f'<div class="{cls}"><div class="label">{esc(label)}</div><div class="value">{esc(value)}</div>'
            f'<div class="say">{esc(sentence)}</div></div>')


STATUSES = ("ok", "warn", "fail", "unchecked")


def banner(status: str, title: str, items: Sequence[tuple[str, str]] = ()) -> str:
    """A box in the colour of `status` (ok, warn, fail, unchecked): a title, then one entry per
    (label, text) item, the label in bold, each line of the text ('\\n') on its own. Plain text,
    escaped.

    Parameters
    ----------
    status : str
        ok, warn, fail or unchecked.
    title : str
        The box's title.
    items : sequence of (str, str), optional
        (label, text) entries.

    Returns
    -------
    str
    """
    cls = status if status in STATUSES else "unchecked"
    lines = "".join(f"<li><strong>{esc(k)}</strong> " + "<br>".join(esc(x) for x in v.split("\n")) + "</li>"
                    for k, v in items)
    return (f'<div class="validity {cls}"><div class="vtitle">{esc(title)}</div>'
            + (f"<ul>{lines}</ul>" if lines else "") + "</div>")


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0 auto;
max-width:1180px;padding:1em 2em;color:#1b1b1b;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #2b5d8a;padding-bottom:.15em;margin-top:1.8em}
h3{margin-bottom:.3em}
table{border-collapse:collapse;margin:.6em 0 1.2em;font-size:.88em}
caption{caption-side:top;text-align:left;font-weight:600;padding:.3em 0}
th,td{border:1px solid #c9d2dc;padding:.25em .55em;vertical-align:top}
thead th{background:#e8eef5}tbody tr:nth-child(even){background:#f7f9fb}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
figure{margin:1em 0 1.6em}figure img{max-width:100%;height:auto;border:1px solid #e2e6ea}
figcaption{font-size:.88em;color:#444;margin-top:.3em}
.cards{display:flex;flex-wrap:wrap;gap:.8em}
.card{flex:1 1 260px;border:1px solid #c9d2dc;border-radius:6px;padding:.6em .8em;background:#f7f9fb}
.card .label{font-size:.85em;color:#555}.card .value{font-size:1.3em;font-weight:600;margin:.15em 0}
.card .say{font-size:.88em}
.note{background:#fff6e0;border-left:4px solid #e0a800;padding:.4em .7em}
.validity{border:2px solid #777;border-radius:6px;padding:.5em .9em;margin:.4em 0 1em;background:#f2f2f2}
.validity .vtitle{font-weight:700;font-size:1.15em}.validity ul{margin:.3em 0;padding-left:1.2em}
.validity li{margin:.25em 0}
.validity.fail,.card.fail{border-color:#c62828;background:#fdecea}
.validity.warn,.card.warn{border-color:#e0a800;background:#fff6e0}
.validity.ok,.card.ok{border-color:#2e7d32;background:#edf7ed}
.meta{color:#555;font-size:.9em}nav a{margin-right:1em}
"""


def html_page(title: str, sections: Sequence[Section | tuple[str, str]], subtitle: str = "",
              toc: bool = True) -> str:
    """A complete, self-contained HTML document (inline CSS, no scripts, no external links).

    Parameters
    ----------
    title : str
        The page's title.
    sections : sequence of Section or (str, str)
        The sections, in order.
    subtitle : str, optional
        A line under the title.
    toc : bool, optional
        Include a table of contents.

    Returns
    -------
    str
    """
    secs = [s if isinstance(s, Section) else Section(*s) for s in sections]
    anchors = [s.anchor or f"s{i + 1}" for i, s in enumerate(secs)]
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{esc(title)}</h1>"]
    if subtitle:
        parts.append(f'<p class="meta">{esc(subtitle)}</p>')
    if toc and len(secs) > 1:
        parts.append("<nav>" + "".join(f'<a href="#{esc(a)}">{esc(s.title)}</a>'
                                       for a, s in zip(anchors, secs)) + "</nav>")
    for a, s in zip(anchors, secs):
        parts.append(f'<section id="{esc(a)}"><h2>{esc(s.title)}</h2>{s.body}</section>')
    parts.append("</body></html>")
    return "\n".join(parts)


STATUS_WORD = {"ok": "OK", "warn": "WARNING", "fail": "NOT VALID", "unchecked": "NOT CHECKED"}


def validity_banner(v: Any) -> str:
    """A summary's `validity` block (analysis.validity) as the box a report opens with: may these
    figures be trusted? Each check in short when it passed, with its evidence, likely cause and next
    step when flagged.

    Parameters
    ----------
    v : dict or None
        The block; anything else (a summary written before the checks existed) gives ''.

    Returns
    -------
    str
        HTML.
    """
    if not isinstance(v, dict):
        return ""  # a summary written before the checks existed
    status = v.get("status", "unchecked")
    title = {"fail": "NOT VALID: a stated uncertainty does not cover the errors",
             "warn": "WARNING: a stated uncertainty may not fit the errors",
             "ok": "OK: the stated uncertainty covers the errors in every check",
             "unchecked": "NOT CHECKED: nothing tested the stated uncertainty"}.get(status, status)
    items = []
    checks = [c for c in v.get("checks") or [] if isinstance(c, dict)]
    for c in sorted(checks, key=lambda c: {"fail": 0, "warn": 1}.get(str(c.get("status")), 2)):
        # a check that passed in short; a flagged one with its evidence, likely cause and next step
        text = str(c.get("short" if c.get("status") == "ok" else "finding", ""))
        text = text[:1].upper() + text[1:] + "."
        if c.get("cause"):
            text += f"\nLikely cause: {c['cause']}" + (f" ({c['evidence']})" if c.get("evidence") else "") + "."
        if c.get("advice"):
            text += f"\nNext: {c['advice']}."
        items.append((STATUS_WORD.get(str(c.get("status")), "?") + ":", text))
    if not checks and v.get("finding"):
        items.append(("", str(v["finding"])[:1].upper() + str(v["finding"])[1:] + "."))
    return banner(status, f"Validity: {title}", items)
