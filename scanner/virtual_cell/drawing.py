"""Print-ready drawings of target specs at 1:1 scale (SVG in mm; PDF/PNG through matplotlib).

The drawing is the same card the virtual cell renders: the marks of the spec and the white
margin around them, with the card outline as a thin grey cut line. Seen from the front, the
target's x axis points right and y up (z out of the paper).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patches
from matplotlib.backends.backend_pdf import PdfPages

from scanner.core.fileio import atomic_output, write_json_atomic, write_text_atomic
from scanner.core.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    TargetSpec,
    target_to_json,
)
from scanner.virtual_cell.scene import PrintedTarget

__all__ = [
    "PAGES_MM",
    "drawing_bounds_mm",
    "save_target_drawing",
    "smallest_page",
    "target_shapes",
    "target_svg",
]


def target_shapes(printed: PrintedTarget) -> list[tuple]:
    """The marks as primitive shapes in target coordinates (mm, y up).

    ``("ring", cx, cy, r, width)``, ``("disc", cx, cy, r)``, ``("bar", x0, y0, x1, y1, width)``,
    ``("rect", x, y, w, h)`` (filled).
    """
    s = printed.spec
    out: list[tuple] = []
    if isinstance(s, ConcentricCirclesTarget):
        w = s.line_width_mm
        for r in s.ring_radii_mm:
            out.append(("ring", 0.0, 0.0, float(r), w))
        big = s.radius_mm
        out.append(("bar", -big, 0.0, big, 0.0, w))
        out.append(("bar", 0.0, -big, 0.0, big, w))
        mk = s.orientation_marker
        out.append(("disc", mk.center_mm[0], mk.center_mm[1], mk.diameter_mm / 2))
    elif isinstance(s, ChessboardTarget):
        cols, rows = s.inner_corners
        q = s.square_mm
        for i in range(-1, cols):
            for j in range(-1, rows):
                if (i + j) % 2 == 0:
                    out.append(("rect", i * q, j * q, q, q))
    elif isinstance(s, CircleGridTarget):
        rad = s.pitch_mm * printed.circle_grid_diameter_ratio / 2
        for x, y, _ in s.object_points():
            out.append(("disc", float(x), float(y), rad))
    return out


def target_svg(printed: PrintedTarget, caption: str | None = None) -> str:
    """SVG text of the card at 1:1 (width and height in mm)."""
    x0, x1, y0, y1 = printed.card_bounds_mm()
    w, h = x1 - x0, y1 - y0
    extra = STRIP_MM if caption else 0.0
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.3f}mm" height="{h + extra:.3f}mm" '
        f'viewBox="{x0:.4f} {-y1:.4f} {w:.4f} {h + extra:.4f}">',
        f'<rect x="{x0:.4f}" y="{-y1:.4f}" width="{w:.4f}" height="{h:.4f}" fill="white" '
        'stroke="#999999" stroke-width="0.1"/>',
        '<g fill="black" stroke="none">',
    ]
    for shape in target_shapes(printed):
        kind = shape[0]
        if kind == "ring":
            _, cx, cy, r, lw = shape
            parts.append(
                f'<circle cx="{cx:.4f}" cy="{-cy:.4f}" r="{r:.4f}" fill="none" stroke="black" '
                f'stroke-width="{lw:.4f}"/>'
            )
        elif kind == "disc":
            _, cx, cy, r = shape
            parts.append(f'<circle cx="{cx:.4f}" cy="{-cy:.4f}" r="{r:.4f}"/>')
        elif kind == "bar":
            _, xa, ya, xb, yb, lw = shape
            parts.append(
                f'<line x1="{xa:.4f}" y1="{-ya:.4f}" x2="{xb:.4f}" y2="{-yb:.4f}" stroke="black" '
                f'stroke-width="{lw:.4f}" stroke-linecap="butt"/>'
            )
        else:
            _, x, y, rw, rh = shape
            parts.append(
                f'<rect x="{x:.4f}" y="{-(y + rh):.4f}" width="{rw:.4f}" height="{rh:.4f}"/>'
            )
    parts.append("</g>")
    if caption:
        parts.append(
            f'<text x="{x0 + 2:.3f}" y="{-y0 + 5:.3f}" font-family="sans-serif" font-size="3">'
            f"{_escape(caption)}</text>"
        )
        length, ybar = _scale_bar_mm(printed), -(y0 - 12)
        parts.append(
            f'<line x1="{x0 + 2:.3f}" y1="{ybar:.3f}" x2="{x0 + 2 + length:.3f}" y2="{ybar:.3f}" '
            'stroke="black" stroke-width="0.3"/>'
        )
        for k in range(int(length / 10) + 1):
            tick = 2.0 if k % 5 == 0 else 1.0
            x = x0 + 2 + 10 * k
            parts.append(
                f'<line x1="{x:.3f}" y1="{ybar:.3f}" x2="{x:.3f}" y2="{ybar - tick:.3f}" '
                'stroke="black" stroke-width="0.2"/>'
            )
        parts.append(
            f'<text x="{x0 + 4 + length:.3f}" y="{ybar + 1:.3f}" font-family="sans-serif" '
            f'font-size="2.5">{length:g} mm: check the print with a ruler</text>'
        )
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _caption(spec: TargetSpec) -> str:
    if isinstance(spec, ConcentricCirclesTarget):
        d = spec.ring_diameters_mm
        return (
            f"{len(d)} rings {d[0]:g}-{d[-1]:g} mm, line {spec.line_width_mm:g} mm, "
            f"AB = CD = {d[-1]:g} mm; print at 100 %"
        )
    if isinstance(spec, ChessboardTarget):
        c, r = spec.inner_corners
        return f"chessboard {c}x{r} inner corners, {spec.square_mm:g} mm squares; print at 100 %"
    c, r = spec.grid
    return f"circle grid {c}x{r}, pitch {spec.pitch_mm:g} mm; print at 100 %"


#: Paper sizes (width, height in mm, portrait) a drawing can be laid out on.
PAGES_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "Letter": (215.9, 279.4)}
#: Printable margin kept free on every side of a page (most printers cannot print closer).
PAGE_MARGIN_MM = 10.0
#: Overlap of neighbouring tiles, where the alignment marks are.
TILE_OVERLAP_MM = 20.0
#: Largest PNG drawn (600 dpi): an A3 sheet is about 7e7 pixels.
MAX_PNG_PIXELS = 2.0e8
#: Height of the strip under the card: caption and scale bar.
STRIP_MM = 16.0


def drawing_bounds_mm(printed: PrintedTarget) -> tuple[float, float, float, float]:
    """``(x0, x1, y0, y1)`` of the whole drawing: the card and the strip under it."""
    x0, x1, y0, y1 = printed.card_bounds_mm()
    return x0, x1, y0 - STRIP_MM, y1


def smallest_page(printed: PrintedTarget) -> str | None:
    """The smallest of :data:`PAGES_MM` that holds the drawing on one page at 100 %, either
    way round, or ``None``."""
    x0, x1, y0, y1 = drawing_bounds_mm(printed)
    w, h = x1 - x0, y1 - y0
    for name, (pw, ph) in sorted(PAGES_MM.items(), key=lambda kv: kv[1][0] * kv[1][1]):
        aw, ah = pw - 2 * PAGE_MARGIN_MM, ph - 2 * PAGE_MARGIN_MM
        if (w <= aw and h <= ah) or (w <= ah and h <= aw):
            return name
    return None


def _scale_bar_mm(printed: PrintedTarget) -> float:
    x0, x1, _, _ = printed.card_bounds_mm()
    return 100.0 if x1 - x0 >= 120 else 50.0


def save_target_drawing(
    spec: TargetSpec | PrintedTarget, path: str | os.PathLike[str], page: str | None = None
) -> tuple[Path, Path]:
    """Write the drawing (``.svg``, or ``.pdf``/``.png`` via matplotlib) and the spec beside it.

    Every drawing carries a scale bar (100 mm, or 50 mm on a small card) to check the print
    with a ruler. ``page`` (``.pdf`` only: ``A4``, ``A3`` or ``Letter``) lays the drawing out at
    100 % on pages of that size: on one page when it fits, else on overlapping tiles with
    alignment marks (cut one tile along a mark, lay it over the next, marks on marks).

    Returns
    -------
    drawing, spec_json : Path
        The spec is ``<stem>.json``: the ``target`` object of ``session.json``.
    """
    printed = spec if isinstance(spec, PrintedTarget) else PrintedTarget(spec)
    out = Path(path)
    suffix = out.suffix.lower()
    caption = _caption(printed.spec)
    if page is not None and (page not in PAGES_MM or suffix != ".pdf"):
        raise ValueError(
            f"--page: expected one of {', '.join(PAGES_MM)} with a .pdf output, got {page!r} "
            f"with {out.name!r}"
        )
    if suffix == ".svg":
        write_text_atomic(out, target_svg(printed, caption))
    elif suffix in (".pdf", ".png"):
        _save_matplotlib(printed, out, caption, page)
    else:
        raise ValueError(f"target drawing: expected a .svg, .pdf or .png path, got {out.name!r}")
    spec_path = out.with_suffix(".json")
    write_json_atomic(spec_path, target_to_json(printed.spec))
    return out, spec_path


def _draw(ax: Any, printed: PrintedTarget, caption: str) -> None:
    """The card, its marks, the caption and the scale bar, in mm (1 data unit = 1 mm)."""
    x0, x1, y0, y1 = printed.card_bounds_mm()
    ax.add_patch(patches.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="#999999", lw=0.3))
    for shape in target_shapes(printed):
        kind = shape[0]
        if kind == "ring":
            _, cx, cy, r, lw = shape
            ax.add_patch(patches.Annulus((cx, cy), r + lw / 2, lw, color="black", lw=0))
        elif kind == "disc":
            _, cx, cy, r = shape
            ax.add_patch(patches.Circle((cx, cy), r, color="black", lw=0))
        elif kind == "bar":
            _, xa, ya, xb, yb, lw = shape
            if ya == yb:
                ax.add_patch(patches.Rectangle((xa, ya - lw / 2), xb - xa, lw, color="black", lw=0))
            else:
                ax.add_patch(patches.Rectangle((xa - lw / 2, ya), lw, yb - ya, color="black", lw=0))
        else:
            _, x, y, rw, rh = shape
            ax.add_patch(patches.Rectangle((x, y), rw, rh, color="black", lw=0))
    pt = 1 / 0.3528  # points per mm
    ax.text(x0 + 2, y0 - 5, caption, fontsize=3 * pt, family="sans-serif")
    length = _scale_bar_mm(printed)
    ybar = y0 - 12
    ax.plot([x0 + 2, x0 + 2 + length], [ybar, ybar], color="black", lw=0.3 * pt)
    for k in range(int(length / 10) + 1):
        tick = 2.0 if k % 5 == 0 else 1.0
        ax.plot([x0 + 2 + 10 * k] * 2, [ybar, ybar + tick], color="black", lw=0.2 * pt)
    ax.text(
        x0 + 4 + length, ybar, f"{length:g} mm: check the print with a ruler",
        fontsize=2.5 * pt, family="sans-serif", va="center",
    )  # fmt: skip


def _tiles(lo: float, hi: float, span: float) -> list[float]:
    """Starts of windows of ``span`` covering ``[lo, hi]``, neighbours overlapping."""
    if hi - lo <= span:
        return [lo]
    step = span - TILE_OVERLAP_MM
    n = int(np.ceil((hi - lo - span) / step)) + 1
    return [lo + i * step for i in range(n)]


def _save_matplotlib(printed: PrintedTarget, out: Path, caption: str, page: str | None) -> None:
    x0, x1, y0, y1 = drawing_bounds_mm(printed)
    if page is None:
        dpi = 600 if out.suffix.lower() == ".png" else None
        if dpi is not None and (x1 - x0) * (y1 - y0) * (dpi / 25.4) ** 2 > MAX_PNG_PIXELS:
            raise ValueError(
                f"{out}: a {x1 - x0:.0f} x {y1 - y0:.0f} mm drawing at {dpi} dpi is over "
                f"{MAX_PNG_PIXELS:.0e} pixels; draw it as .svg or .pdf"
            )
        fig = plt.figure(figsize=((x1 - x0) / 25.4, (y1 - y0) / 25.4))
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.axis("off")
        _draw(ax, printed, caption)
        with atomic_output(out) as tmp:
            fig.savefig(
                tmp, format=out.suffix[1:], dpi=600 if out.suffix.lower() == ".png" else None
            )
        plt.close(fig)
        return
    pw, ph = PAGES_MM[page]
    if (x1 - x0) > (y1 - y0):  # landscape for a wide drawing
        pw, ph = ph, pw
    aw, ah = pw - 2 * PAGE_MARGIN_MM, ph - 2 * PAGE_MARGIN_MM
    xs, ys = _tiles(x0, x1, aw), _tiles(y0, y1, ah)
    with atomic_output(out) as tmp, PdfPages(tmp) as pdf:
        for row, ty in enumerate(reversed(ys)):
            for col, tx in enumerate(xs):
                fig = plt.figure(figsize=(pw / 25.4, ph / 25.4))
                ax = fig.add_axes((PAGE_MARGIN_MM / pw, PAGE_MARGIN_MM / ph, aw / pw, ah / ph))
                ax.set_xlim(tx, tx + aw)
                ax.set_ylim(ty, ty + ah)
                ax.set_aspect("equal")
                ax.axis("off")
                _draw(ax, printed, caption)
                if len(xs) * len(ys) > 1:
                    _alignment_marks(ax, printed, xs, ys, aw, ah)
                    fig.text(
                        0.5, 0.5 * PAGE_MARGIN_MM / ph,
                        f"tile row {row + 1} of {len(ys)}, column {col + 1} of {len(xs)}; "
                        f"overlap {TILE_OVERLAP_MM:g} mm, print at 100 %",
                        ha="center", fontsize=8,
                    )  # fmt: skip
                pdf.savefig(fig)
                plt.close(fig)


def _alignment_marks(
    ax: Any, printed: PrintedTarget, xs: list[float], ys: list[float], aw: float, ah: float
) -> None:
    """Where neighbouring tiles overlap: a dashed cut line through the middle of the overlap
    and small crosses on it in the card's white border, at the same drawing coordinates on
    both tiles (cut one tile along its line, lay it on the next with cross on cross)."""
    cx0, cx1, cy0, cy1 = printed.card_bounds_mm()
    mids_x = [x + aw - TILE_OVERLAP_MM / 2 for x in xs[:-1]]
    mids_y = [y + ah - TILE_OVERLAP_MM / 2 for y in ys[:-1]]
    style = {"color": "#b0b0b0", "lw": 0.4, "ls": (0, (4, 4))}
    for mx in mids_x:
        ax.plot([mx, mx], [cy0 - STRIP_MM, cy1], **style)
        for my in (cy0 + 3, cy1 - 3, cy0 - STRIP_MM / 2):
            _cross(ax, mx, my)
    for my in mids_y:
        ax.plot([cx0, cx1], [my, my], **style)
        for mx in (cx0 + 3, cx1 - 3):
            _cross(ax, mx, my)


def _cross(ax: Any, x: float, y: float, half_mm: float = 2.0) -> None:
    ax.plot([x - half_mm, x + half_mm], [y, y], color="#d00000", lw=0.5)
    ax.plot([x, x], [y - half_mm, y + half_mm], color="#d00000", lw=0.5)
