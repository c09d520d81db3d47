"""Print-ready drawings of target specs at 1:1 scale (SVG in mm; PDF/PNG through matplotlib).

The drawing is the same card the virtual cell renders: the marks of the spec and the white
margin around them, with the card outline as a thin grey cut line. Seen from the front, the
target's x axis points right and y up (z out of the paper).
"""

from __future__ import annotations

import os
from pathlib import Path

from scanner.core.fileio import atomic_output, write_json_atomic, write_text_atomic
from scanner.core.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    TargetSpec,
    target_to_json,
)
from scanner.virtual_cell.scene import PrintedTarget

__all__ = ["save_target_drawing", "target_shapes", "target_svg"]


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
    extra = 8.0 if caption else 0.0
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


def save_target_drawing(
    spec: TargetSpec | PrintedTarget, path: str | os.PathLike[str]
) -> tuple[Path, Path]:
    """Write the drawing (``.svg``, or ``.pdf``/``.png`` via matplotlib) and the spec beside it.

    Returns
    -------
    drawing, spec_json : Path
        The spec is ``<stem>.json``: the ``target`` object of ``session.json``.
    """
    printed = spec if isinstance(spec, PrintedTarget) else PrintedTarget(spec)
    out = Path(path)
    suffix = out.suffix.lower()
    caption = _caption(printed.spec)
    if suffix == ".svg":
        write_text_atomic(out, target_svg(printed, caption))
    elif suffix in (".pdf", ".png"):
        _save_matplotlib(printed, out, caption)
    else:
        raise ValueError(f"target drawing: expected a .svg, .pdf or .png path, got {out.name!r}")
    spec_path = out.with_suffix(".json")
    write_json_atomic(spec_path, target_to_json(printed.spec))
    return out, spec_path


def _save_matplotlib(printed: PrintedTarget, out: Path, caption: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import patches
    from matplotlib import pyplot as plt

    x0, x1, y0, y1 = printed.card_bounds_mm()
    extra = 8.0
    w, h = x1 - x0, y1 - y0 + extra
    fig = plt.figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0 - extra, y1)
    ax.set_aspect("equal")
    ax.axis("off")
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
    ax.text(x0 + 2, y0 - 5, caption, fontsize=3 / 0.3528, family="sans-serif")
    with atomic_output(out) as tmp:
        fig.savefig(tmp, format=out.suffix[1:], dpi=600 if out.suffix.lower() == ".png" else None)
    plt.close(fig)
