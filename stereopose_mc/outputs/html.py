"""HTML building blocks of the reports: escaping, number formats, tables, figures, the page.

Every report module (``report``, ``sweep_report``, ``sensitivity_report``, ``faults_report``)
builds its HTML from these, so none of them imports another for its helpers.
"""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from .figures import FigureFile

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1200px;
 padding:0 1em;color:#222;line-height:1.4}
h1{border-bottom:2px solid #444}h2{border-bottom:1px solid #bbb;margin-top:2em}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}th{background:#f0f0f0}
td.l,th.l{text-align:left}.side{display:flex;flex-wrap:wrap;gap:2em;align-items:flex-start}
.note{color:#555;font-size:.9em}figure{margin:1em 0 2em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.9em;color:#444}code{background:#f4f4f4;padding:0 .2em}
.ok{color:#1b7837;font-weight:600}.bad{color:#b2182b;font-weight:600}.verdicts li{margin:.3em 0}
.verdicts .ok,.verdicts .bad{font-weight:normal}
details{margin:.5em 0}summary{cursor:pointer;font-weight:600}.ci{color:#666;font-size:.85em;white-space:nowrap}.ci0{white-space:nowrap}
"""


def esc(v: Any) -> str:
    return html.escape(str(v), quote=True)


def fmt_num(v: Any, digits: int = 3) -> str:
    """Numbers with ``digits`` significant digits; ``inf`` / ``nan`` spelled out."""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if np.isnan(v):
            return "nan"
        if np.isinf(v):
            return "inf" if v > 0 else "-inf"
        return f"{float(v):.{digits}g}"
    return str(v)


def fmt_value(v: Any) -> str:
    """Config values: lists as ``[a, b]``, ``None`` as ``-``."""
    if v is None:
        return "-"
    if isinstance(v, list):
        return "[" + ", ".join(fmt_value(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def html_table(headers: list[str], rows: list[list[Any]], left: int = 1, caption: str | None = None) -> str:
    """An HTML table; the first ``left`` columns are left-aligned; cells are escaped."""
    cls = lambda i: ' class="l"' if i < left else ""  # noqa: E731
    out = ["<table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<tr>" + "".join(f"<th{cls(i)}>{esc(h)}</th>" for i, h in enumerate(headers)) + "</tr>")
    for r in rows:
        out.append("<tr>" + "".join(f"<td{cls(i)}>{c}</td>" for i, c in enumerate(r)) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def cells(values: list[Any]) -> list[str]:
    return [esc(fmt_num(v)) for v in values]


def data_uri_png(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def page(title: str, body: list[str]) -> str:
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{esc(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n" + "\n".join(body)
            + f"\n<p class=\"note\">Written by stereopose_mc {esc(__version__)}.</p>\n</body>\n</html>\n")  # fmt: skip


def figure_html(f: FigureFile, root: Path) -> str:
    png_rel = os.path.relpath(f.png, root)
    svg_rel = os.path.relpath(f.svg, root)
    return (f'<figure id="{esc(f.key)}"><img alt="{esc(f.title)}" src="{data_uri_png(f.png)}">'
            f"<figcaption><b>{esc(f.title)}.</b> {esc(f.caption)} Files: <code>{esc(png_rel)}</code>, "
            f"<code>{esc(svg_rel)}</code>.</figcaption></figure>")  # fmt: skip
