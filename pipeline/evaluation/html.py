"""HTML pieces of the report pages: number format, escaping, tables, cells, figures."""

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
