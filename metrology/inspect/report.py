"""The HTML report of a scan-to-CAD inspection: one self-contained page a person reads.

``write_inspection_report(result, "out/part.html")`` writes the verdict, the part coloured by
deviation (a picture and several orthographic views with the nominal's edges), the deviation
histogram with the band, the regions' table, the section cuts, the alignment, the uncertainty,
the inputs, and an interactive 3-D view (:mod:`metrology.inspect.viewer`) that a browser opens
from disk without a network.

The colour scale is symmetric and comes from the tolerance band: blue below the nominal (too
little material), red above (too much), white on it, saturated at twice the band's wider side;
outliers are grey. Big clouds are subsampled (seeded) for every picture; statistics use every
point.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from numpy.typing import NDArray

from metrology.inspect.result import InspectionResult, RegionResult
from metrology.inspect.sections import SectionCut, sections_of
from metrology.inspect.viewer import (
    VIEWS,
    cloud_viewer_html,
    feature_edges,
    project,
    rasterise,
    shade,
)
from metrology.report import histogram_figure, provenance_items
from scanner.core.tolerance import format_tolerance, format_value
from scanner.formats import html as rep

__all__ = [
    "COLOUR_MAP",
    "OUTLIER_RGB",
    "colour_limit",
    "deviation_colours",
    "inspection_html",
    "write_inspection_report",
]

#: The diverging colour map of every picture (blue below, red above the nominal).
COLOUR_MAP = "RdBu_r"
#: Colour of outliers (not judged), as in the measurement report's pictures.
OUTLIER_RGB = (184, 188, 194)
#: Points drawn in the orthographic views and in each section plot (seeded subsample).
VIEW_MAX_POINTS = 200_000
SECTION_MAX_POINTS = 20_000
#: Largest pixel size of one orthographic view.
_VIEW_PX = (560, 420)


def colour_limit(lower_mm: float, upper_mm: float) -> float:
    """Half-range of the colour scale: twice the band's wider side (at least 1 µm)."""
    return max(2.0 * max(abs(lower_mm), abs(upper_mm)), 1e-3)


def deviation_colours(
    deviation_mm: NDArray, outlier: NDArray, limit_mm: float
) -> NDArray[np.uint8]:
    """RGB colours ``(N, 3)`` uint8 of deviations ``(N,)`` on ``[-limit, limit]``; outliers grey."""
    cmap = matplotlib.colormaps[COLOUR_MAP]
    rgba = cmap(Normalize(-limit_mm, limit_mm, clip=True)(np.asarray(deviation_mm, dtype=float)))
    rgb = np.round(np.asarray(rgba)[:, :3] * 255).astype(np.uint8)
    rgb[np.asarray(outlier, dtype=bool)] = OUTLIER_RGB
    return rgb


def _subsample(count: int, limit: int, seed: int = 0) -> NDArray[np.int64]:
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, limit, replace=False))


# --------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------


def _views_figure(
    points: NDArray,
    normals: NDArray,
    colours: NDArray,
    outlier: NDArray,
    edges: NDArray,
    limit: float,
    band: tuple[float, float],
    names: tuple[str, ...] = ("top", "front", "side", "rear iso"),
) -> Figure:
    """Orthographic views (``names`` of :data:`VIEWS`) with the nominal's edges and the scale.

    Four views make a 2 x 2 figure; one view a large single picture.
    """
    single = len(names) == 1
    fig = Figure(figsize=(12.0, 7.0 if single else 8.6), dpi=100, layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, 1) if single else fig.subplots(2, 2))
    pixels = (2 * _VIEW_PX[0], 2 * _VIEW_PX[1]) if single else _VIEW_PX
    for ax, name in zip(axes.flat, names):
        yaw, pitch = VIEWS[name]
        view = project(points, yaw, pitch)
        edge_view = project(edges.reshape(-1, 3), yaw, pitch) if len(edges) else np.zeros((0, 3))
        both = np.concatenate([view, edge_view]) if len(edge_view) else view
        lo, hi = both.min(axis=0), both.max(axis=0)
        pad = 0.03 * float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
        box = (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)
        shaded = np.where(outlier[:, None], colours, shade(colours, normals, yaw, pitch))
        image, extent = rasterise(view, shaded, box, pixels)
        ax.imshow(image, extent=extent, interpolation="nearest")
        if len(edge_view):
            lines = edge_view[:, :2].reshape(-1, 2, 2)
            ax.add_collection(LineCollection(lines, colors="#2b2f36", linewidths=0.6, alpha=0.35))
        ax.set_xlim(box[0], box[1])
        ax.set_ylim(box[2], box[3])
        ax.set_title(name, fontsize=10)
        ax.set_axis_off()
    _colour_bar(fig, axes, limit, band)
    return fig


def _colour_bar(fig: Figure, axes: Any, limit: float, band: tuple[float, float]) -> None:
    mappable = ScalarMappable(Normalize(-limit, limit), COLOUR_MAP)
    bar = fig.colorbar(mappable, ax=axes, shrink=0.7, label="deviation (mm)")
    for edge in band:
        bar.ax.axhline(edge, color="black", linewidth=1.2)


def _robust_span(deviation_mm: NDArray, band: tuple[float, float]) -> float:
    """Half-range of a deviation axis: the band with room, and the bulk of the points (mm)."""
    wide = 1.5 * max(abs(band[0]), abs(band[1]))
    bulk = float(np.percentile(np.abs(deviation_mm), 99.5)) if deviation_mm.size else 0.0
    return 1.1 * max(wide, 1.2 * bulk)


def _histogram(result: InspectionResult) -> tuple[Figure, int]:
    """The deviation histogram of the judged points (µm), the band marked, and how many
    points lie beyond its axis (not drawn)."""
    band = (result.spec.lower_mm, result.spec.upper_mm)
    judged = result.deviation_mm[~result.outlier]
    span = _robust_span(judged, band)
    shown = judged[np.abs(judged) <= span]
    fig = histogram_figure([(f"{shown.size} judged points within ±{span:.3f} mm", shown)])
    ax = fig.axes[0]
    lower, upper = band[0] * 1000, band[1] * 1000
    ax.axvspan(lower, upper, color="#1b7f3b", alpha=0.12, zorder=0, label="band")
    for edge in (lower, upper):
        ax.axvline(edge, color="#1b7f3b", linewidth=1.2)
    ax.set_xlim(-span * 1000, span * 1000)
    ax.set_xlabel("deviation (µm)", fontsize=8)
    ax.legend(fontsize=7)
    fig.set_size_inches(7.5, 3.2)
    return fig, int(judged.size - shown.size)


def _section_figure(cut: SectionCut, limit: float, band: tuple[float, float]) -> Figure:
    """The profile with the section's points coloured by deviation; deviation along it."""
    fig = Figure(figsize=(11.0, 6.6), dpi=100, layout="constrained")
    top, bottom = fig.subplots(2, 1, height_ratios=[3, 2])
    pick = _subsample(len(cut.point_index), SECTION_MAX_POINTS)
    uv, dev, out = cut.points_uv[pick], cut.deviation_mm[pick], cut.outlier[pick]
    if len(cut.segments_uv):
        top.add_collection(
            LineCollection(cut.segments_uv, colors="black", linewidths=0.9, zorder=3)
        )
    ink = {"s": 9, "edgecolors": "#3a3f47", "linewidths": 0.25}
    top.scatter(*uv[out].T, c="#b8bcc2", **ink)
    sc = top.scatter(*uv[~out].T, c=dev[~out], cmap=COLOUR_MAP, vmin=-limit, vmax=limit, **ink)
    top.set_aspect("equal", adjustable="datalim")
    top.autoscale_view()
    top.set_xlabel(cut.axis_label("u"), fontsize=8)
    top.set_ylabel(cut.axis_label("v"), fontsize=8)
    top.set_title(f"{cut.name}: nominal profile (black) and measured points", fontsize=10)
    bar = fig.colorbar(sc, ax=top, shrink=0.9, label="deviation (mm)")
    for edge in band:
        bar.ax.axhline(edge, color="black", linewidth=1.2)
    arc = cut.arc_mm[pick]
    bottom.axhspan(*band, color="#1b7f3b", alpha=0.12, zorder=0)
    bottom.axhline(0.0, color="black", linewidth=0.6)
    # The scale shows the band and the bulk of the points; the rest sit on its edge as triangles.
    span = _robust_span(dev[~out], band)
    clipped = np.clip(dev, -span, span)
    beyond = np.abs(dev) > span
    for mask, colour in ((out, "#b8bcc2"), (~out, None)):
        for edge_mask, marker in (
            (~beyond, "o"),
            (beyond & (dev > 0), "^"),
            (beyond & (dev < 0), "v"),
        ):
            m = mask & edge_mask
            if not np.any(m):
                continue
            if colour:
                style: dict[str, Any] = {"c": colour}
            else:
                style = {"c": dev[m], "cmap": COLOUR_MAP, "vmin": -limit, "vmax": limit}
            bottom.scatter(arc[m], clipped[m], marker=marker, **style, **ink)
    bottom.set_ylim(-1.06 * span, 1.06 * span)
    bottom.set_xlim(0.0, max(cut.profile_length_mm, 1e-6))
    bottom.set_xlabel("position along the profile (mm)", fontsize=8)
    bottom.set_ylabel("deviation (mm)", fontsize=8)
    bottom.set_title("deviation along the section (band shaded)", fontsize=10)
    for ax in (top, bottom):
        ax.tick_params(labelsize=7)
        ax.grid(True, linewidth=0.3, alpha=0.5)
    return fig


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def _regions_table(regions: list[RegionResult]) -> str:
    """The regions with their bands, statistics and status (colour-coded like the other tables)."""
    headers = ["Region", "Selector", "Band (mm)", "Points", "Outliers", "In band"]
    headers += ["Mean", "RMS", "Min", "Max", "P01", "P99", "Status"]
    out = ['<table class="tol"><thead><tr>']
    out += [f"<th>{html.escape(h)}</th>" for h in headers]
    out.append("</tr></thead>\n<tbody>\n")
    for r in regions:
        s = r.stats
        cls = {"pass": "pass", "fail": "fail"}.get(r.status, "na")
        share = "-" if not np.isfinite(r.share_in_band) else f"{100 * r.share_in_band:.2f} %"
        cells = [
            f"<td>{html.escape(r.name)}</td>",
            f'<td class="note">{html.escape(r.description)}</td>',
            f'<td class="num">{html.escape(format_tolerance(r.lower_mm, r.upper_mm))}</td>',
            f'<td class="num">{s.count}</td>',
            f'<td class="num">{r.outliers}</td>',
            f'<td class="num dev">{share}</td>',
        ]
        for value in (s.mean, s.rms, s.min, s.max, s.p01, s.p99):
            cells.append(f'<td class="num">{format_value(value, 4, signed=True)}</td>')
        cells.append(f'<td class="status">{html.escape(r.status)}</td>')
        out.append(f'<tr class="{cls}">{"".join(cells)}</tr>\n')
    out.append("</tbody></table>\n")
    return "".join(out)


def _alignment_section(result: InspectionResult) -> str:
    a = result.alignment
    items: list[tuple[str, Any]] = [
        ("method", a.method),
        ("converged", "yes" if a.converged else "NO"),
        ("iterations", a.iterations),
        ("RMS of the fit (mm)", a.rms_mm),
        ("points used", f"{a.points_used} of {result.points}"),
        ("pose uncertainty, 1 sigma at the farthest point (mm)", a.pose_u_mm),
        ("candidate poses compared", a.candidates),
        ("runner-up RMS (mm)", a.runner_up_rms_mm),
        ("ambiguous", "YES" if a.ambiguous else "no"),
        ("alignment spec", f"{result.spec.alignment.method}"
         + (f", on region {result.spec.alignment.region!r}" if result.spec.alignment.region else "")),
    ]  # fmt: skip
    warnings = "".join(
        f'<div class="summary fail">Alignment warning: {html.escape(w)}</div>\n' for w in a.warnings
    )
    matrix = rep.table(
        ["", "x", "y", "z", "t (mm)"], _matrix_rows(a.nominal_from_cloud), decimals=6
    )
    return rep.section(
        "Alignment",
        warnings
        + rep.key_value_table(items)
        + "<p><b>nominal_from_cloud</b> (maps cloud points into the nominal frame)</p>\n"
        + matrix,
    )


def _matrix_rows(transform: NDArray) -> list[list[Any]]:
    t = np.asarray(transform, dtype=np.float64)
    return [[name, *(float(v) for v in t[i])] for i, name in enumerate(("x", "y", "z", ""))]


def _uncertainty_section(result: InspectionResult) -> str:
    u = result.uncertainty
    items = [
        ("point noise, 1 sigma (mm)", u.noise_mm),
        ("alignment, 1 sigma (mm)", u.alignment_mm),
        (
            "calibration, 1 sigma, 95 % of the points within (mm)",
            u.calibration_mm if u.calibration_mm is not None else "not known",
        ),
        ("combined standard uncertainty u (mm)", u.combined_mm),
        ("expanded uncertainty U, k = 2 (mm)", 2.0 * u.combined_mm),
    ]
    band = min(abs(result.spec.lower_mm), abs(result.spec.upper_mm))
    note = (
        f"U is {100 * 2.0 * u.combined_mm / band:.0f} % of the band's narrower side."
        if band > 0 and np.isfinite(u.combined_mm)
        else ""
    )
    if u.not_included:
        note += f" Not included: {'; '.join(u.not_included)}."
    return rep.section("Uncertainty of a point's deviation", rep.key_value_table(items), note)


def _inputs_section(result: InspectionResult) -> str:
    spec = result.spec
    items: list[tuple[str, Any]] = [
        ("nominal", result.nominal_path or "given in memory"),
        ("nominal triangles", len(result.nominal.triangles)),
        ("spec", result.spec_path or spec.name),
        ("global band (mm)", format_tolerance(spec.lower_mm, spec.upper_mm)),
        ("a region passes with", f"{100 * spec.min_share_in_band:g} % of its points in band"),
        ("outlier limit (mm)", spec.outlier_limit_mm),
        ("points", result.points),
        ("outliers", int(np.count_nonzero(result.outlier))),
    ]
    items += provenance_items(result.provenance, result.cloud_path or None)
    items += [(f"time: {k} (s)", float(v)) for k, v in result.seconds.items()]
    return rep.section("Inputs and provenance", rep.key_value_table(items))


def _legend_html(limit: float, band: tuple[float, float]) -> str:
    cmap = matplotlib.colormaps[COLOUR_MAP]
    stops = ", ".join(
        "rgb({}, {}, {}) {:.0f}%".format(*(round(255 * float(c)) for c in cmap(t)[:3]), 100 * t)
        for t in np.linspace(0.0, 1.0, 11)
    )
    ticks = "".join(
        f'<span class="tick" style="left: {100 * (b + limit) / (2 * limit):.1f}%"></span>'
        for b in band
    )
    grey = "rgb({}, {}, {})".format(*OUTLIER_RGB)
    return (
        f'<div class="legend"><span>{-limit:+.3f} mm</span>'
        f'<span class="ramp" style="background: linear-gradient(to right, {stops})">{ticks}</span>'
        f"<span>{limit:+.3f} mm</span>"
        f'<span class="note">(marks: band {format_tolerance(*band)} mm)</span>'
        f'<span class="swatch" style="background: {grey}"></span> outlier</div>\n'
    )


# --------------------------------------------------------------------------------------------
# The page
# --------------------------------------------------------------------------------------------


def inspection_html(result: InspectionResult) -> str:
    """The complete self-contained HTML page of an inspection."""
    spec = result.spec
    band = (spec.lower_mm, spec.upper_mm)
    limit = colour_limit(*band)
    cloud_name = Path(result.cloud_path).name if result.cloud_path else "points given in memory"
    judged = [r for r in result.regions if r.status != "no points"]
    n_pass = sum(r.status == "pass" for r in judged)
    n_fail = sum(r.status == "fail" for r in judged)
    detail = f"{n_pass} of {len(result.regions)} regions pass; part {spec.name}, cloud {cloud_name}"
    body = [rep.summary_line((n_pass, n_fail), detail=detail)]
    if result.verdict == "fail" and n_fail == 0:
        body.append('<div class="summary fail">Verdict: FAIL</div>\n')
    if not result.alignment:
        body.append(
            '<div class="summary fail">The alignment is not trustworthy (not converged or '
            "ambiguous): see Alignment below.</div>\n"
        )
    outliers = int(np.count_nonzero(result.outlier))
    s = result.stats
    body.append(
        f'<p class="note">{result.points} points, {outliers} outliers (beyond '
        f"±{spec.outlier_limit_mm:g} mm, grey, not judged); deviation mean {s.mean:+.4f} mm, "
        f"RMS {s.rms:.4f} mm, range {s.min:+.4f} .. {s.max:+.4f} mm.</p>\n"
    )
    body.append(rep.section("Regions", _regions_table(result.regions)))

    colours = deviation_colours(result.deviation_mm, result.outlier, limit)
    edges = feature_edges(result.nominal)
    pick = _subsample(result.points, VIEW_MAX_POINTS)
    drawn = (
        result.points_nominal[pick],
        result.face_normals[pick],
        colours[pick],
        result.outlier[pick],
        edges,
        limit,
        band,
    )
    overview = _views_figure(*drawn, names=("iso",))
    views = _views_figure(*drawn)
    caption = (
        f"Signed deviation from the nominal, ±{limit:.3f} mm (blue: too little material, red: "
        f"too much; band {format_tolerance(*band)} mm marked on the scale), grey: outliers."
    )
    body.append(
        rep.section(
            "Part coloured by deviation",
            rep.figure(overview, f"{caption} Shaded by the surface's slope to the eye.")
            + rep.figure(views, "Orthographic views (nominal frame) with the nominal's edges."),
        )
    )
    body.append(
        rep.section(
            "Interactive 3-D view",
            cloud_viewer_html(
                result.points_nominal,
                result.deviation_mm,
                colours,
                result.outlier,
                edges,
                _legend_html(limit, band),
                normals=result.face_normals,
            ),
            note="Runs in the page itself (no network); the nominal frame, z up.",
        )
    )
    histogram, beyond = _histogram(result)
    caption = f"Band {format_tolerance(*band)} mm shaded."
    if beyond:
        caption += f" {beyond} judged points lie beyond the axis (see the regions' min and max)."
    body.append(rep.section("Deviation histogram", rep.figure(histogram, caption)))
    cuts = sections_of(result)
    if cuts:
        parts = []
        for cut in cuts:
            judged_here = cut.deviation_mm[~cut.outlier]
            note = (
                f"{cut.name}: plane through {list(cut.spec.point_mm)} with normal "
                f"{list(cut.spec.normal)}, slab {cut.spec.thickness_mm:g} mm; "
                f"{len(cut.point_index)} points"
            )
            if judged_here.size:
                note += f", deviation {judged_here.min():+.4f} .. {judged_here.max():+.4f} mm"
            if not len(cut.segments_uv):
                note += "; the plane misses the nominal"
            parts.append(rep.figure(_section_figure(cut, limit, band), note + "."))
        body.append(rep.section("Sections", "".join(parts)))
    body.append(_alignment_section(result))
    body.append(_uncertainty_section(result))
    body.append(_inputs_section(result))
    return rep.page(
        f"Inspection report — {spec.name}",
        "".join(body),
        subtitle=f"{cloud_name} against {Path(result.nominal_path).name or 'the nominal'}",
    )


def write_inspection_report(result: InspectionResult, path: Path) -> Path:
    """Write the inspection's self-contained HTML report to ``path`` (atomically) and return it."""
    return rep.write_page(path, inspection_html(result))
