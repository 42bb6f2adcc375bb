"""HTML pieces of the report pages: their one look (stylesheet and page frame), number format, escaping,
tables, cells, figures. Both pages (reports/index.html, reports/deployment.html) are built from these."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any


def fmt(value: Any) -> str:
    """A table number: 2 decimals from 1 up (as the thesis), 3 significant digits below; n/a if missing."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    v = float(value)
    if abs(v) >= 1e5:
        return f"{v:.3e}"
    if abs(v) >= 1:
        return f"{v:.2f}"
    return f"{v:.3g}"


def esc(text: Any) -> str:
    """`text` escaped for HTML."""
    return html.escape(str(text))


def table(header: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "", raw_html: bool = False) -> str:
    """An HTML table; cells are escaped unless `raw_html` (then the caller escaped them)."""
    wrap = (lambda c: c) if raw_html else esc
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{wrap(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def cell(value: Any, good: bool | None = None, bold: bool = False) -> str:
    """A <td> with a number, green/red when `good` says whether it meets its target."""
    text = esc(fmt(value))
    text = f"<b>{text}</b>" if bold else text
    cls = "" if good is None else (' class="ok"' if good else ' class="bad"')
    return f"<td{cls}>{text}</td>"


def img(src: str, alt: str) -> str:
    """A linked figure with its caption (`src` relative to the page)."""
    src, alt = esc(src), esc(alt)
    return (
        f'<figure><a href="{src}"><img src="{src}" alt="{alt}" loading="lazy"></a>'
        f"<figcaption>{alt}</figcaption></figure>"
    )


def warning(title: str, summary: str, detail: str = "", ok: bool = False) -> str:
    """One line of a page's warnings: `title` and `summary` (HTML, escaped by the caller) on the line, the
    `detail` (HTML) folded below it; green where `ok` (nothing wrong: said once, in one line)."""
    line = f"<b>{title}:</b> {summary}"
    cls = "flags none" if ok else "flags"
    if not detail:
        return f"<div class='{cls} line'>{line}</div>"
    return (
        f"<details class='{cls} line'><summary>{line}</summary><div class='detail'>{detail}</div></details>"
    )


# Laid out for a laptop's window (1366-1440 px) and wider: the widest table (the summary, 24 columns) fits
# 1366 px; a table wider than its window (a narrower one) scrolls in its own box instead of being cut off.
CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1500px;
 padding:0 20px 60px;color:#222}
h1{margin-bottom:4px} h2{border-bottom:2px solid #ddd;padding-bottom:4px;margin-top:48px}
h3{margin-top:28px} h4{margin:18px 0 6px}
.meta{color:#666;font-size:13px}
table{border-collapse:collapse;margin:6px 0 14px;font-size:13px;display:block;max-width:100%;overflow-x:auto}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right;white-space:nowrap}
th{background:#f2f2f2;white-space:normal;text-align:center}
td:first-child,th:first-child{text-align:left} td.deploy{text-align:left;white-space:normal;min-width:5em}
table.summary{font-size:12.5px} table.summary th,table.summary td{padding:2px 5px}
table.num td{font-variant-numeric:tabular-nums}
.ok{background:#e3f4e3} .bad{background:#fbe0e0}
.flags{border:2px solid #c62828;background:#fdecea;padding:10px 16px;border-radius:6px;margin:14px 0}
.flags.none{border-color:#2e7d32;background:#edf7ed}
.flags.line{padding:5px 12px;margin:5px 0;font-size:13.5px;border-width:1px}
details.flags summary{cursor:pointer} .flags .detail{margin-top:6px;font-size:13px}
table.answer{font-size:14px} table.answer td.verdict{text-align:left;white-space:normal;min-width:16em}
table.answer td.verdict details summary{cursor:pointer;font-weight:600}
.tables{display:flex;flex-wrap:wrap;gap:22px;align-items:flex-start}
figure{margin:10px 0 18px} figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:12px;color:#555}
nav{font-size:13px;columns:3;background:#fafafa;border:1px solid #eee;padding:8px 16px}
nav a{display:block} .note{font-size:13px;color:#444;max-width:1100px}
"""


def document(title: str, parts: Sequence[str]) -> str:
    """A whole page in the reports' one look: `parts` (HTML) in a body under the shared stylesheet."""
    head = f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
    return "\n".join([f"{head}<style>{CSS}</style></head><body>", *parts, "</body></html>"])
