"""Shared building blocks of the HTML reports people read (calibration, EF check, measure).

Every report is one self-contained HTML file that opens from disk: the CSS is inline and the
figures are PNGs embedded as base64 data URIs, so the file can be mailed or archived alone.
The blocks return HTML fragments (strings) that a report concatenates and hands to
:func:`page`::

    from scanner.formats import html as rep

    rows = [rep.ToleranceRow("sphere spacing", nominal=100.0, actual=100.012,
                             lower=-0.05, upper=0.05, unit="mm")]
    body = (rep.summary_line(rows)
            + rep.section("Results", rep.tolerance_table(rows))
            + rep.section("Residuals", rep.figure(fig, "Residual histogram"))
            + rep.section("Calibration", rep.key_value_table({"file": "calib.json"})))
    rep.write_page("reports/measure.html", rep.page("Measurement report", body))

Values are escaped here; pass plain text, not HTML, except where a parameter says ``_html``.
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from scanner import __version__
from scanner.core.fileio import write_text_atomic
from scanner.core.tolerance import (
    STATUS_ERROR,
    STATUS_FAIL,
    STATUS_NA,
    STATUS_NOT_PROVEN,
    STATUS_PASS,
    ToleranceRow,
    format_tolerance,
    format_value,
)

__all__ = [
    "figure",
    "key_value_table",
    "page",
    "png_data_uri",
    "section",
    "summary_line",
    "table",
    "tolerance_table",
    "write_page",
]

_CSS = """
:root { --ok: #1b7f3b; --ok-bg: #e3f4e8; --bad: #b3261e; --bad-bg: #fbe4e2;
        --warn: #8a5a00; --warn-bg: #fdf0d5;
        --na: #5f6368; --na-bg: #eef0f2; --line: #d0d4d9; --ink: #1f2328; }
* { box-sizing: border-box; }
body { font: 14px/1.45 -apple-system, "Segoe UI", Roboto, "DejaVu Sans", Arial, sans-serif;
       color: var(--ink); margin: 0 auto; padding: 24px 32px 48px; max-width: 1180px; }
header { border-bottom: 2px solid var(--ink); margin-bottom: 16px; padding-bottom: 8px; }
h1 { font-size: 22px; margin: 0 0 4px; }
h2 { font-size: 17px; margin: 28px 0 8px; border-bottom: 1px solid var(--line);
     padding-bottom: 3px; }
.subtitle, .generated { color: var(--na); font-size: 12.5px; margin: 0; }
.summary { font-size: 17px; font-weight: 600; padding: 10px 14px; border-radius: 6px;
           margin: 12px 0 4px; border: 1px solid var(--line); }
.summary.pass { background: var(--ok-bg); color: var(--ok); border-color: var(--ok); }
.summary.fail { background: var(--bad-bg); color: var(--bad); border-color: var(--bad); }
.summary.na { background: var(--na-bg); color: var(--na); }
.summary.notproven { background: var(--warn-bg); color: var(--warn); border-color: var(--warn); }
.summary .detail { font-weight: 400; color: var(--ink); font-size: 13.5px; }
table { border-collapse: collapse; margin: 6px 0 10px; font-size: 13.5px; }
th, td { border: 1px solid var(--line); padding: 4px 10px; vertical-align: top; }
th { background: #f4f5f7; text-align: left; font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap;
         font-family: "DejaVu Sans Mono", Menlo, Consolas, monospace; font-size: 12.5px; }
table.tol { width: 100%; }
tr.pass td.status { background: var(--ok-bg); color: var(--ok); font-weight: 700; }
tr.fail td.status, tr.error td.status { background: var(--bad-bg); color: var(--bad);
                                         font-weight: 700; }
tr.fail td.dev, tr.error td.dev { color: var(--bad); font-weight: 600; }
tr.na td.status { background: var(--na-bg); color: var(--na); }
tr.notproven td.status { background: var(--warn-bg); color: var(--warn); font-weight: 700; }
td.status { text-align: center; text-transform: uppercase; letter-spacing: .04em;
            white-space: nowrap; }
td.note { color: var(--na); font-size: 12.5px; }
table.kv th { width: 1%; white-space: nowrap; }
table.kv td { font-family: "DejaVu Sans Mono", Menlo, Consolas, monospace; font-size: 12.5px;
              word-break: break-all; }
figure { display: inline-block; margin: 8px 16px 12px 0; vertical-align: top; }
figure img { max-width: 100%; border: 1px solid var(--line); }
figcaption { color: var(--na); font-size: 12.5px; margin-top: 3px; max-width: 640px; }
.note { color: var(--na); font-size: 12.5px; }
footer { margin-top: 36px; color: var(--na); font-size: 11.5px;
         border-top: 1px solid var(--line); padding-top: 6px; }
@media print { body { padding: 0; } h2 { break-after: avoid; } figure { break-inside: avoid; } }
"""


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def summary_line(rows_or_counts: Iterable[ToleranceRow] | tuple[int, int], detail: str = "") -> str:
    """The headline: "PASS — 7 passed, 0 failed" (green) or "FAIL — 5 passed, 2 failed" (red).

    Parameters
    ----------
    rows_or_counts : iterable of ToleranceRow, or (n_passed, n_failed)
        Rows with status ``error`` count as failed; ``n/a`` rows count as neither.
    detail : str
        Plain text appended after the counts (e.g. the cloud's file name).
    """
    n_unproven = 0
    if (
        isinstance(rows_or_counts, tuple)
        and len(rows_or_counts) == 2
        and all(isinstance(c, int) for c in rows_or_counts)
    ):
        n_pass, n_fail = rows_or_counts
    else:
        statuses = [r.final_status for r in rows_or_counts]  # type: ignore[union-attr]
        n_pass = sum(s == STATUS_PASS for s in statuses)
        n_fail = sum(s in (STATUS_FAIL, STATUS_ERROR) for s in statuses)
        n_unproven = sum(s == STATUS_NOT_PROVEN for s in statuses)
    if n_fail:
        cls, word = "fail", "FAIL"
    elif n_unproven:
        cls, word = "notproven", "CONFORMITY NOT PROVEN"
    elif n_pass:
        cls, word = "pass", "PASS"
    else:
        cls, word = "na", "NOT JUDGED"
    extra = f' <span class="detail">— {_esc(detail)}</span>' if detail else ""
    unproven = f", {n_unproven} not proven" if n_unproven else ""
    return (
        f'<div class="summary {cls}">{word} — {n_pass} passed, {n_fail} failed{unproven}'
        f"{extra}</div>\n"
    )


def tolerance_table(rows: Sequence[ToleranceRow], decimals: int = 3) -> str:
    """The colour-coded Nominal / Actual / Deviation / Tolerance / Status table."""
    with_u = any(r.U is not None for r in rows)
    u_head = "<th>U (k=2)</th>" if with_u else ""
    out = [
        '<table class="tol">\n<thead><tr><th>Characteristic</th><th>Unit</th><th>Nominal</th>'
        f"<th>Actual</th>{u_head}<th>Deviation</th><th>Tolerance</th><th>Status</th>"
        "<th>Note</th></tr></thead>\n<tbody>\n"
    ]
    for r in rows:
        st = r.final_status
        cls = {STATUS_NA: "na", STATUS_NOT_PROVEN: "notproven"}.get(st, st)
        u_cell = f'<td class="num">±{format_value(r.U, decimals)}</td>' if with_u else ""
        if with_u and r.U is None:
            u_cell = '<td class="num">-</td>'
        rule = " (guarded)" if r.rule == "guarded" else ""
        out.append(
            f'<tr class="{cls}"><td>{_esc(r.name)}</td><td>{_esc(r.unit)}</td>'
            f'<td class="num">{format_value(r.nominal, decimals)}</td>'
            f'<td class="num">{format_value(r.actual, decimals)}</td>{u_cell}'
            f'<td class="num dev">{format_value(r.deviation, decimals, signed=True)}</td>'
            f'<td class="num">{_esc(format_tolerance(r.lower, r.upper, decimals))}</td>'
            f'<td class="status">{_esc(st + rule)}</td><td class="note">{_esc(r.note)}</td></tr>\n'
        )
    out.append("</tbody></table>\n")
    return "".join(out)


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]], decimals: int = 4) -> str:
    """A plain table: a header row, then one row per sequence of cells.

    Floats print with ``decimals`` decimals in right-aligned monospace cells, None as ``-``;
    everything else with ``str``. Values are escaped.
    """
    out = ["<table><thead><tr>"]
    out += [f"<th>{_esc(h)}</th>" for h in headers]
    out.append("</tr></thead>\n<tbody>\n")
    for row in rows:
        out.append("<tr>")
        for cell in row:
            if isinstance(cell, float) or cell is None:
                out.append(f'<td class="num">{format_value(cell, decimals)}</td>')
            elif isinstance(cell, int) and not isinstance(cell, bool):
                out.append(f'<td class="num">{cell}</td>')
            else:
                out.append(f"<td>{_esc(cell)}</td>")
        out.append("</tr>\n")
    out.append("</tbody></table>\n")
    return "".join(out)


def key_value_table(items: Mapping[str, Any] | Iterable[tuple[str, Any]]) -> str:
    """A two-column table (calibration file used, its date, cloud size, options...).

    Floats print with 4 decimals (a figure of a report, not a float's repr), very small or
    very large ones with 4 significant digits; other values with ``str``.
    """
    pairs = items.items() if isinstance(items, Mapping) else items
    out = ['<table class="kv"><tbody>\n']
    for key, value in pairs:
        if isinstance(value, float):
            plain = value == 0 or 1e-3 <= abs(value) < 1e6 or not math.isfinite(value)
            text = f"{value:.4f}" if plain else f"{value:.4g}"
        elif value is None:
            text = "-"
        else:
            text = str(value)
        out.append(f"<tr><th>{_esc(key)}</th><td>{_esc(text)}</td></tr>\n")
    out.append("</tbody></table>\n")
    return "".join(out)


def png_data_uri(png: bytes | str | os.PathLike[str]) -> str:
    """``data:image/png;base64,...`` from PNG bytes or a PNG file's path."""
    data = png if isinstance(png, bytes | bytearray) else Path(png).read_bytes()
    if not bytes(data[:8]) == b"\x89PNG\r\n\x1a\n":
        raise ValueError("png: expected PNG data (signature \\x89PNG), got something else")
    return "data:image/png;base64," + base64.b64encode(bytes(data)).decode("ascii")


def _figure_png(fig: Any, dpi: int) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def figure(
    image: Any,
    caption: str = "",
    alt: str | None = None,
    width_px: int | None = None,
    dpi: int = 100,
) -> str:
    """An embedded figure: ``<figure><img src="data:..."><figcaption>``.

    Parameters
    ----------
    image : bytes, path, or matplotlib Figure
        PNG bytes, a PNG file, or a Matplotlib figure (saved at ``dpi``; build it with
        ``matplotlib.figure.Figure()`` so no GUI backend is touched).
    caption : str
        Plain text under the image.
    width_px : int, optional
        Display width; the image keeps its aspect ratio.
    """
    png = _figure_png(image, dpi) if hasattr(image, "savefig") else image
    width = f' width="{int(width_px)}"' if width_px else ""
    cap = f"<figcaption>{_esc(caption)}</figcaption>" if caption else ""
    return (
        f'<figure><img src="{png_data_uri(png)}" alt="{_esc(alt if alt is not None else caption)}"'
        f"{width}>{cap}</figure>\n"
    )


def section(title: str, content_html: str, note: str = "") -> str:
    """``<h2>title</h2>`` then the content (HTML), with an optional plain-text note under it."""
    extra = f'<p class="note">{_esc(note)}</p>\n' if note else ""
    return f"<section><h2>{_esc(title)}</h2>\n{content_html}{extra}</section>\n"


def page(title: str, body_html: str, subtitle: str = "", generated: datetime | None = None) -> str:
    """The complete self-contained HTML document around ``body_html``.

    The header shows ``title``, ``subtitle`` (plain text) and when the page was generated
    (UTC, now unless given).
    """
    when = (generated or datetime.now(timezone.utc)).astimezone(timezone.utc)
    stamp = when.strftime("%Y-%m-%d %H:%M:%S UTC")
    sub = f'<p class="subtitle">{_esc(subtitle)}</p>' if subtitle else ""

    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{_esc(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        f"<header><h1>{_esc(title)}</h1>{sub}"
        f'<p class="generated">Generated {stamp}</p></header>\n'
        f"{body_html}"
        f"<footer>robot-line-scanner {_esc(__version__)} — {stamp}</footer>\n"
        "</body>\n</html>\n"
    )


def write_page(path: str | os.PathLike[str], html_text: str) -> Path:
    """Write the page atomically (UTF-8) and return its path."""
    p = Path(path)
    write_text_atomic(p, html_text)
    return p
