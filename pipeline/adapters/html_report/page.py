"""The page around the sections: HTML escaping, tables, figures (matplotlib to inline SVG
or base64 PNG), units, the style sheet and the section wrapper that turns a failing
section into a visible error box instead of a lost run."""

from __future__ import annotations

import base64
import html
import io
import traceback
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import matplotlib
from matplotlib.figure import Figure

from pipeline.discrepancy.report import fmt_number

__all__ = ["esc", "table", "figure_svg", "figure_png", "new_figure", "section", "page",
           "ratio_unit", "fmt", "grade_badge", "SECTION_ERROR_CLASS",
           "WINDOW_COLOURS", "panel_grid"]

SECTION_ERROR_CLASS = "section-error"
WINDOW_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                  "#e377c2", "#7f7f7f"]
_GRADE_COLOURS = {"A": "#1a7f37", "B": "#4d8f2a", "C": "#b7791f", "D": "#c62828"}

_CSS = """
body{font-family:"DejaVu Sans",Arial,Helvetica,sans-serif;margin:0;color:#1b1f23;
     background:#fff;font-size:14px;line-height:1.4}
main{max-width:1360px;margin:0 auto;padding:12px 20px 40px}
h1{font-size:22px;margin:8px 0 4px}
h2{font-size:18px;margin:28px 0 8px;border-bottom:2px solid #d0d7de;padding-bottom:4px}
h3{font-size:15px;margin:16px 0 6px}
p.meta{color:#57606a;margin:2px 0}
nav{font-size:13px;margin:8px 0}
nav a{margin-right:12px}
div.scroll{max-width:100%;overflow-x:auto}
table{border-collapse:collapse;margin:6px 0 10px;font-size:13px}
th,td{border:1px solid #d0d7de;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#f3f5f7}
#candidates-table{font-size:11px}
#candidates-table td,#candidates-table th{padding:2px 4px}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
.unit{color:#57606a;font-size:11px}
.grade{display:inline-block;min-width:18px;text-align:center;color:#fff;font-weight:bold;
       border-radius:3px;padding:0 4px;margin-left:4px}
.banner{padding:10px 14px;border-radius:6px;margin:10px 0;font-size:15px}
.banner.changed{background:#fde2e1;border:2px solid #c62828}
.banner.unchanged{background:#e6f4ea;border:2px solid #1a7f37}
.section-error{background:#fff4e5;border:1px solid #b7791f;padding:8px;white-space:pre-wrap}
figure{margin:6px 0}
figcaption{color:#57606a;font-size:12px;max-width:1100px}
svg{max-width:100%;height:auto}
img.plot{max-width:100%;height:auto}
"""


def esc(value: Any) -> str:
    """``value`` as HTML text (escaped).

    Parameters
    ----------
    value : object
        Any value; None becomes an empty string.
    """
    return "" if value is None else html.escape(str(value), quote=True)


def fmt(value: Any, digits: int = 4) -> str:
    """A number to ``digits`` significant figures (``–`` when missing), escaped.

    Parameters
    ----------
    value : object
        A number as read from a result file.
    digits : int
        Significant figures.
    """
    return esc(fmt_number(value, digits))


def grade_badge(grade: str) -> str:
    """A coloured badge with the grade letter.

    Parameters
    ----------
    grade : str
        ``"A"`` … ``"D"``.
    """
    colour = _GRADE_COLOURS.get(grade, "#57606a")
    return f'<span class="grade grade-{esc(grade)}" style="background:{colour}">{esc(grade)}</span>'


def table(header: Sequence[str], rows: Iterable[Sequence[str]], *, table_id: str | None = None,
          numeric: Sequence[int] = (), caption: str | None = None) -> str:
    """An HTML table; cells are given as HTML (escape text with :func:`esc` first).

    Parameters
    ----------
    header : sequence of str
        Column headings (HTML).
    rows : iterable of sequence of str
        Cells (HTML).
    table_id : str, optional
        The table's ``id``.
    numeric : sequence of int
        Columns aligned right as numbers.
    caption : str, optional
        A caption (HTML) above the table.
    """
    ident = f' id="{esc(table_id)}"' if table_id else ""
    out = [f'<div class="scroll"><table{ident}>']
    if caption:
        out.append(f"<caption>{caption}</caption>")
    out.append("<tr>" + "".join(f"<th>{h}</th>" for h in header) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(
            f'<td class="num">{c}</td>' if k in numeric else f"<td>{c}</td>"
            for k, c in enumerate(row)) + "</tr>")
    out.append("</table></div>")
    return "\n".join(out)


def new_figure(width_in: float, height_in: float) -> Figure:
    """A matplotlib figure without pyplot (no global state, no GUI backend).

    Parameters
    ----------
    width_in : float
        Width, inches.
    height_in : float
        Height, inches.
    """
    return Figure(figsize=(width_in, height_in), dpi=100)


def panel_grid(fig: Figure, n_rows: int, n_cols: int, *, panel_w: float, panel_h: float,
               left: float, bottom: float, right: float = 0.15, top: float = 0.35,
               head: float = 0.0) -> list[list[Any]]:
    """Axes of identical size in a grid, placed in inches (a panel whose tick labels are
    long keeps the size of the others, unlike an automatic layout).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        Its size must be ``n_cols·(left+panel_w+right)`` × ``head + n_rows·(top+panel_h+bottom)``.
    n_rows, n_cols : int
        Grid shape.
    panel_w, panel_h : float
        Size of each axes, inches.
    left, bottom, right, top : float
        Margins of each cell around its axes (labels, title), inches.
    head : float
        Space above the grid (a legend), inches.
    """
    fw, fh = fig.get_size_inches()
    cw, ch = left + panel_w + right, top + panel_h + bottom
    axes = []
    for r in range(n_rows):
        row = []
        for c in range(n_cols):
            x0 = c * cw + left
            y0 = fh - head - (r + 1) * ch + bottom
            row.append(fig.add_axes((x0 / fw, y0 / fh, panel_w / fw, panel_h / fh)))
        axes.append(row)
    return axes


def figure_svg(fig: Figure, key: str) -> str:
    """The figure as an inline ``<svg>`` element with its text kept as text (searchable,
    and the ids salted with ``key`` so several figures on one page do not share ids).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    key : str
        Unique per figure on the page.
    """
    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": f"plantdyn-{key}"}):
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    text = buf.getvalue()
    return text[text.index("<svg"):]


def figure_png(fig: Figure, *, alt: str, dpi: int = 90) -> str:
    """The figure as an ``<img>`` with a base64 PNG (dense time series stay small).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    alt : str
        Alternative text.
    dpi : int
        Resolution.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img class="plot" alt="{esc(alt)}" src="data:image/png;base64,{data}">'


def section(section_id: str, title: str, body: Callable[[], str]) -> str:
    """A ``<section>`` with a heading; if ``body()`` raises, the section shows the error
    (a warning is issued too) so one figure that cannot be drawn costs that section, not
    the run.

    Parameters
    ----------
    section_id : str
        The section's ``id`` (tests and links find it by that).
    title : str
        Heading text.
    body : callable () -> str
        Builds the section's HTML.
    """
    try:
        inner = body()
    except Exception as exc:  # a broken section is shown, never a lost run
        warnings.warn(f"report.html section {section_id!r} failed: {exc!r}", RuntimeWarning,
                      stacklevel=2)
        inner = (f'<div class="{SECTION_ERROR_CLASS}">This section could not be drawn: '
                 f"{esc(type(exc).__name__)}: {esc(exc)}\n"
                 f"{esc(''.join(traceback.format_exception(exc)[-3:]))}</div>")
    return f'<section id="{esc(section_id)}">\n<h2>{esc(title)}</h2>\n{inner}\n</section>'


def page(title: str, body: str) -> str:
    """The whole self-contained document.

    Parameters
    ----------
    title : str
        The document title (text).
    body : str
        The content of ``<main>`` (HTML).
    """
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{esc(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n"
            f"{body}\n</main>\n</body>\n</html>\n")


def ratio_unit(num: str, den: str) -> str:
    """``"bar per kg/s"``: the unit of an output per unit of an input.

    Parameters
    ----------
    num : str
        Output unit (empty: not given).
    den : str
        Input unit (empty: not given).
    """
    return f"{num or 'output unit'} per {den or 'input unit'}"
