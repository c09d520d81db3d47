"""Reports people read, and their machine-readable twins: JSON, CSV and self-contained HTML.

``write_measurement_report(report, "out/part.json")`` writes ``part.json``, ``part.csv`` (the
table) and ``part.html`` (summary line, the colour-coded table, a picture of the cloud coloured
by deviation, residual histograms, the fits, the calibration used and when) beside each other.

Pictures: the cloud is rendered off-screen with PyVista/VTK; where VTK cannot render (no
OpenGL on a headless machine) a Matplotlib 3-D scatter stands in and a log line says so. Both
paths use the Agg/off-screen back ends only and never open a window.
"""

from __future__ import annotations

import csv
import html
import io
import logging
import math
import os
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from metrology.acceptance import FullAcceptance
from scanner.core.fileio import atomic_output, write_json_atomic
from scanner.core.tolerance import ToleranceRow, format_value, spreadsheet_safe
from scanner.formats import html as rep
from scanner.formats.calibration_file import read_calibration

__all__ = [
    "acceptance_html",
    "deviation_limit",
    "histogram_figure",
    "measurement_html",
    "provenance_items",
    "render_cloud_png",
    "write_acceptance_report",
    "write_measurement_report",
    "write_rows_csv",
]

log = logging.getLogger(__name__)

#: At most this many points are drawn (a seeded random subsample of bigger clouds).
RENDER_MAX_POINTS = 250_000


# --------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------


def deviation_limit(deviations_mm: NDArray) -> float:
    """Colour-scale half-range: the 99th percentile of ``|deviation|`` (at least 1 µm)."""
    d = np.abs(deviations_mm[np.isfinite(deviations_mm)])
    if d.size == 0:
        return 0.01
    return max(float(np.percentile(d, 99.0)), 1e-3)


def _subsample_for_render(points: NDArray, values: NDArray) -> tuple[NDArray, NDArray]:
    if len(points) <= RENDER_MAX_POINTS:
        return points, values
    idx = np.random.default_rng(0).choice(len(points), RENDER_MAX_POINTS, replace=False)
    return points[idx], values[idx]


def _render_pyvista(
    points: NDArray, values: NDArray, limit: float, title: str, size: tuple[int, int]
) -> bytes:
    import pyvista as pv

    try:  # VTK's own warnings (no X display) would clutter the console
        from vtkmodules.vtkCommonCore import vtkLogger

        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    except ImportError:  # pragma: no cover
        pass
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        plotter.set_background("white")
        known = np.isfinite(values)
        if np.any(~known):
            plotter.add_points(
                points[~known], color="#b8bcc2", point_size=2.0, render_points_as_spheres=False
            )
        if np.any(known):
            cloud = pv.PolyData(points[known])
            cloud["deviation (mm)"] = values[known]
            plotter.add_points(
                cloud,
                scalars="deviation (mm)",
                cmap="RdBu_r",
                clim=(-limit, limit),
                point_size=3.0,
                render_points_as_spheres=False,
                scalar_bar_args={
                    "title": "deviation (mm)",
                    "color": "black",
                    "fmt": "%.3f",
                    "vertical": True,
                    "position_x": 0.86,
                    "position_y": 0.2,
                    "height": 0.6,
                    "width": 0.06,
                    "title_font_size": 14,
                    "label_font_size": 12,
                },
            )
        plotter.add_text(title, font_size=10, color="black")
        # Looking down at the table (base z up) from the front, 35 degrees above it.
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre = (lo + hi) / 2
        radius = float(np.linalg.norm(hi - lo)) / 2 or 1.0
        direction = np.array([0.45, -0.75, 0.65])
        direction /= np.linalg.norm(direction)
        plotter.camera_position = [
            tuple(centre + 2.7 * radius * direction),
            tuple(centre),
            (0.0, 0.0, 1.0),
        ]
        plotter.camera.view_angle = 30.0
        img = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    from matplotlib.figure import Figure

    h, w = img.shape[:2]
    fig = Figure(figsize=(w / 100, h / 100), dpi=100)
    fig.figimage(img, 0, 0)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _render_matplotlib(
    points: NDArray, values: NDArray, limit: float, title: str, size: tuple[int, int]
) -> bytes:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")
    known = np.isfinite(values)
    ax.scatter(*points[~known].T, s=0.3, c="#b8bcc2", depthshade=False)
    sc = ax.scatter(
        *points[known].T, s=0.6, c=values[known], cmap="RdBu_r", vmin=-limit, vmax=limit,
        depthshade=False,
    )  # fmt: skip
    fig.colorbar(sc, ax=ax, shrink=0.6, label="deviation (mm)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    span = np.ptp(points, axis=0).max() / 2 if len(points) else 1.0
    mid = (points.max(axis=0) + points.min(axis=0)) / 2 if len(points) else np.zeros(3)
    for setter, m in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid):
        setter(m - span, m + span)
    ax.set_title(title, fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def render_cloud_png(
    points_base: NDArray,
    deviations_mm: NDArray,
    title: str = "",
    limit_mm: float | None = None,
    size: tuple[int, int] = (1000, 650),
) -> tuple[bytes, str]:
    """A picture of the cloud coloured by deviation (blue below, red above, grey unassigned).

    Parameters
    ----------
    points_base : ndarray, shape (N, 3)
        The cloud, mm.
    deviations_mm : ndarray, shape (N,)
        Signed deviation per point; NaN for points no feature used.
    limit_mm : float, optional
        Colour scale ``[-limit, limit]``; :func:`deviation_limit` when omitted.

    Returns
    -------
    png : bytes
    renderer : str
        ``"pyvista"`` or ``"matplotlib"`` (the fallback when VTK cannot render here).
    """
    pts, vals = _subsample_for_render(
        np.asarray(points_base, dtype=np.float64), np.asarray(deviations_mm, dtype=np.float64)
    )
    limit = deviation_limit(vals) if limit_mm is None else float(limit_mm)
    if os.environ.get("SCANNER_RENDERER", "").lower() != "matplotlib":
        try:
            return _render_pyvista(pts, vals, limit, title, size), "pyvista"
        except Exception as exc:  # VTK without a usable OpenGL context, or no pyvista
            log.warning(
                "off-screen VTK rendering failed (%s: %s); using a Matplotlib 3-D scatter",
                type(exc).__name__,
                exc,
            )
    else:
        log.info("SCANNER_RENDERER=matplotlib: drawing the cloud with Matplotlib")
    return _render_matplotlib(pts, vals, limit, title, size), "matplotlib"


def histogram_figure(
    residuals: Sequence[tuple[str, NDArray]], columns: int = 3, unit_um: bool = True
) -> Any:
    """Small multiples: one residual histogram per named residual array (Matplotlib Figure)."""
    from matplotlib.figure import Figure

    n = max(1, len(residuals))
    cols = min(columns, n)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(3.6 * cols, 2.6 * rows), dpi=100, layout="constrained")
    scale, unit = (1000.0, "µm") if unit_um else (1.0, "mm")
    for i, (name, res) in enumerate(residuals):
        ax = fig.add_subplot(rows, cols, i + 1)
        r = np.asarray(res, dtype=np.float64) * scale
        if r.size:
            ax.hist(r, bins=min(60, max(10, int(np.sqrt(r.size)))), color="#4a78b5")
            rms = float(np.sqrt(np.mean(r**2)))
            ax.axvline(0.0, color="black", linewidth=0.8)
            ax.set_title(f"{name}\nRMS {rms:.1f} {unit}, range {np.ptp(r):.1f} {unit}", fontsize=9)
        else:
            ax.set_title(f"{name}: no residuals", fontsize=9)
        ax.set_xlabel(f"residual ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
    return fig


# --------------------------------------------------------------------------------------------
# Provenance and CSV
# --------------------------------------------------------------------------------------------


def _mtime_utc(path: Path) -> str:
    try:
        ts = path.stat().st_mtime
    except OSError:
        return "unknown (file not found)"
    return datetime.fromtimestamp(ts, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def provenance_items(provenance: dict[str, Any], cloud_path: str | None) -> list[tuple[str, Any]]:
    """Key-value lines about the cloud and the calibration it was scanned with, and when."""
    items: list[tuple[str, Any]] = []
    if cloud_path:
        items.append(("cloud file", cloud_path))
        items.append(("cloud written", _mtime_utc(Path(cloud_path))))
    cal = provenance.get("calibration")
    if cal:
        items.append(("calibration file", cal))
        items.append(("calibration written", _mtime_utc(Path(cal))))
        try:
            q = read_calibration(cal).quality
            figures = {
                "method": q.method,
                "verdict": q.verdict,
                "intrinsics RMS (px)": q.intrinsics_rms_px,
                "chain RMS (px)": q.hand_eye_rms_px,
                "light-plane RMS (mm)": q.light_plane_rms_mm,
            }
            items += [(f"calibration {k}", v) for k, v in figures.items() if v is not None]
        except (ValueError, OSError) as exc:
            items.append(("calibration note", f"cannot read it now: {exc}"))
    elif provenance:
        items.append(("calibration", "not recorded in the cloud"))
    else:
        items.append(("calibration", "unknown (the cloud carries no provenance record)"))
    if provenance.get("calibration_sha256"):
        items.append(("calibration sha256", provenance["calibration_sha256"]))
    for key in ("sessions", "frames", "sweeps", "mode"):
        if key in provenance:
            value = provenance[key]
            items.append((key, ", ".join(map(str, value)) if isinstance(value, list) else value))
    return items


def _inputs_section(
    result: Any, verb: str, extra: list[tuple[str, Any]], title: str = "Calibration and inputs"
) -> str:
    """ "Calibration and inputs": where the cloud came from, what else, when and how long."""
    items = provenance_items(result.provenance, result.cloud_path) + extra
    items += [
        (verb, result.created.strftime("%Y-%m-%d %H:%M:%S UTC")),
        ("run time", f"{result.seconds:.2f} s"),
    ]
    return rep.section(title, rep.key_value_table(items))


def write_rows_csv(path: str | os.PathLike[str], rows: Sequence[ToleranceRow]) -> None:
    """The Nominal / Actual / Deviation / Tolerance / Status table as CSV (atomic)."""
    cols = ["name", "unit", "nominal", "actual", "deviation", "lower", "upper", "status", "note"]
    cols += ["u", "U", "decision_rule"]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    for r in rows:
        j = r.to_json()
        writer.writerow(["" if j.get(c) is None else spreadsheet_safe(j[c]) for c in cols])
    with atomic_output(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")


# --------------------------------------------------------------------------------------------
# Measurement report
# --------------------------------------------------------------------------------------------


def _fit_parameters(fit: Any) -> str:
    """A compact human-readable line of a fit's parameters."""
    if not fit:
        return f"failed: {fit.reason}"

    def v3(a: NDArray, d: int = 3) -> str:
        return "(" + ", ".join(format_value(float(x), d) for x in a) + ")"

    kind = fit.kind
    if kind == "plane":
        return f"normal {v3(fit.normal, 5)}, d {fit.d_mm:.4f} mm"
    if kind == "sphere":
        return f"centre {v3(fit.center_mm)} mm, Ø {fit.diameter_mm:.4f} mm"
    if kind == "cylinder":
        return f"axis {v3(fit.axis, 5)} through {v3(fit.point_mm)} mm, Ø {fit.diameter_mm:.4f} mm"
    if kind == "circle":
        return (
            f"centre {v3(fit.center_mm)} mm, normal {v3(fit.normal, 5)}, Ø {fit.diameter_mm:.4f} mm"
        )
    return f"through {v3(fit.point_mm)} mm along {v3(fit.direction, 5)}"


def _off_nominal(spec: Any, fit: Any) -> str:
    """How far the fitted feature sits from its nominal: centre offset, axis/normal angle."""
    if not fit:
        return "-"
    nom = spec.nominal
    parts = []
    if nom.center_mm is not None and hasattr(fit, "center_mm"):
        offset = np.asarray(fit.center_mm) - np.asarray(nom.center_mm)
        parts.append(f"centre {np.linalg.norm(offset):.3f} mm")
    if nom.diameter_mm is not None and hasattr(fit, "radius_mm"):
        parts.append(f"Ø {2 * fit.radius_mm - nom.diameter_mm:+.3f} mm")
    direction = nom.normal if nom.normal is not None else nom.axis
    if direction is not None:
        got = getattr(fit, "normal", getattr(fit, "axis", getattr(fit, "direction", None)))
        if got is not None:
            d = np.asarray(direction, dtype=np.float64)
            c = abs(float(np.asarray(got) @ d)) / float(np.linalg.norm(d))
            parts.append(f"{math.degrees(math.acos(min(1.0, c))):.3f}°")
    return ", ".join(parts) or "-"


def _features_table(report: Any) -> str:
    rows = []
    for f in report.features:
        fit = f.fit
        rows.append(
            [
                f.spec.name,
                f.spec.kind,
                int(f.region_indices.size),
                fit.n_inliers if fit else 0,
                _fit_parameters(fit),
                _off_nominal(f.spec, fit),
                fit.rms_mm * 1000 if fit else None,
                fit.range_mm * 1000 if fit else None,
                fit.min_zone_mm * 1000 if fit and fit.min_zone_mm is not None else None,
            ]
        )
    return rep.table(
        ["Feature", "Kind", "Region pts", "Inliers", "Fitted geometry", "Off nominal",
         "RMS µm", "Range µm", "Min zone µm"],
        rows,
        decimals=1,
    )  # fmt: skip


def measurement_html(report: Any, renderer_note: bool = True) -> str:
    """The complete HTML page of a :class:`~metrology.measure.MeasurementReport`."""
    cloud_name = Path(report.cloud_path).name if report.cloud_path else "points given in memory"
    body = [
        rep.summary_line(report.rows, detail=f"plan {report.plan.name}, cloud {cloud_name}"),
        rep.section("Measurements", rep.tolerance_table(report.rows)),
    ]
    png, renderer = render_cloud_png(
        report.points_base,
        report.deviations_mm,
        title=f"{cloud_name}: deviation from the fitted features",
    )
    limit = deviation_limit(report.deviations_mm)
    caption = (
        f"{len(report.points_base)} points; colour = signed deviation from the fitted feature "
        f"(±{limit * 1000:.0f} µm, blue inside/below, red outside/above), grey = not in any "
        f"feature. Rendered with {renderer}."
    )
    body.append(rep.section("Cloud coloured by deviation", rep.figure(png, caption)))
    residuals = [(f.spec.name, f.fit.residuals_mm) for f in report.features if f.fit]
    if residuals:
        body.append(
            rep.section(
                "Residual histograms",
                rep.figure(histogram_figure(residuals), "Orthogonal residuals of each fit"),
            )
        )
    budgets = [m for m in report.measurements if m.uncertainty is not None]
    if budgets:
        body.append(rep.section("Uncertainty budgets", _budget_section(budgets)))
    body.append(rep.section("Fitted features", _features_table(report)))
    failed = [f for f in report.features if not f.fit]
    if failed:
        body.append(
            rep.section(
                "Fits that failed",
                rep.table(["Feature", "Reason"], [[f.spec.name, f.fit.reason] for f in failed]),
            )
        )
    extra = [("plan", report.plan_path or report.plan.name), ("plan cell", report.plan.cell or "-")]
    body.append(_inputs_section(report, "measured", extra))
    return rep.page(
        f"Measurement report — {report.plan.name}",
        "".join(body),
        subtitle=report.plan.description,
        generated=report.created,
    )


def budget_figure(measurements: Sequence[Any]) -> Any:
    """Stacked bars: each measurement's variance shares by source (Matplotlib Figure)."""
    from matplotlib.figure import Figure

    sources = list(dict.fromkeys(c.source for m in measurements for c in m.uncertainty.budget))
    colours = ["#4a78b5", "#d98c2b", "#5aa469", "#b55d8e", "#8c8c8c", "#c44e52"]
    fig = Figure(figsize=(9.0, 0.45 * len(measurements) + 1.4), dpi=100, layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    names = [m.spec.name for m in measurements]
    left = np.zeros(len(measurements))
    for k, source in enumerate(sources):
        share = np.array(
            [
                sum(c.u**2 for c in m.uncertainty.budget if c.source == source)
                / max(m.uncertainty.u**2, 1e-300)
                * 100.0
                for m in measurements
            ]
        )
        ax.barh(names, share, left=left, color=colours[k % len(colours)], label=source)
        left += share
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("share of the variance u² (%)", fontsize=8)
    ax.tick_params(labelsize=7.5)
    ax.legend(fontsize=7.5, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(sources))
    return fig


def _in_unit(value: float, unit: str) -> str:
    """A small uncertainty as people read it: µm for mm values, else in the value's unit."""
    return f"{value * 1000:.1f} µm" if unit == "mm" else f"{value:.4f} {unit}"


def _budget_section(measurements: Sequence[Any]) -> str:
    rows = []
    for m in measurements:
        unc, unit = m.uncertainty, m.row.unit
        for c in unc.budget:
            share = 100.0 * c.u**2 / max(unc.u**2, 1e-300)
            rows.append([m.spec.name, c.source, _in_unit(c.u, unit), f"{share:.0f} %", c.method])
        rows.append(
            [
                m.spec.name,
                "combined u; expanded U (k = 2)",
                _in_unit(unc.u, unit),
                "100 %",
                f"U = {_in_unit(unc.U, unit)}",
            ]
        )
    missing = sorted({s for m in measurements for s in m.uncertainty.not_included})
    note = (
        '<p class="note">Not included: ' + html.escape("; ".join(missing)) + "</p>"
        if missing
        else ""
    )
    return (
        rep.figure(budget_figure(measurements), "Where each measurement's uncertainty comes from")
        + rep.table(["Measurement", "Source", "u", "Share", "How"], rows)
        + note
    )


def _write_judged(result: Any, out_json: str | os.PathLike[str], html_text: str) -> None:
    """``<out>.json`` (the result with the names of its twins), ``<out>.csv`` (its rows) and
    ``<out>.html`` (``html_text``)."""
    out = Path(out_json)
    if out.suffix.lower() != ".json":
        raise ValueError(f"--out: expected a .json file name, got {out.name!r}")
    csv_path, html_path = out.with_suffix(".csv"), out.with_suffix(".html")
    data = result.to_json()
    data["files"] = {"csv": csv_path.name, "html": html_path.name}
    write_json_atomic(out, data)
    write_rows_csv(csv_path, result.rows)
    rep.write_page(html_path, html_text)


def write_measurement_report(report: Any, out_json: str | os.PathLike[str]) -> None:
    """Write ``<out>.json``, ``<out>.csv`` and ``<out>.html`` for a measurement report."""
    _write_judged(report, out_json, measurement_html(report))


# --------------------------------------------------------------------------------------------
# Acceptance report (VDI/VDE 2634 Part 2)
# --------------------------------------------------------------------------------------------


def acceptance_html(result: Any) -> str:
    """The complete HTML page of an :class:`~metrology.acceptance.AcceptanceResult`."""
    spec = result.spec
    cloud_name = Path(result.cloud_path).name if result.cloud_path else "points given in memory"
    body = [
        rep.summary_line(result.rows, detail=f"{spec.name}, cloud {cloud_name}"),
        rep.section(
            "Characteristics",
            rep.tolerance_table(result.rows, decimals=4),
            note="Tolerance column: the maximum permissible error (MPE). PF and F are ranges "
            "(never negative, pass when <= MPE); PS and SD are signed deviations (pass when "
            "|deviation| <= MPE).",
        ),
    ]
    body.append(rep.section("Scan coloured by residual", _residual_figure(result, cloud_name)))
    residuals = [(name, f.residuals_mm) for name, f in result.fits.items() if f]
    if residuals:
        body.append(
            rep.section(
                "Residual histograms",
                rep.figure(
                    histogram_figure(residuals), "Radial (spheres) and normal (plate) residuals"
                ),
            )
        )
    rows = []
    for name, fit in result.fits.items():
        rows.append(
            [
                name,
                fit.kind,
                fit.n_inliers if fit else 0,
                int(result.n_excluded.get(name, 0)),
                _fit_parameters(fit),
                fit.rms_mm * 1000 if fit else None,
                fit.range_mm * 1000 if fit else None,
            ]
        )
    body.append(
        rep.section(
            "Fits",
            rep.table(
                ["Artefact", "Kind", "Points", "Excluded", "Fitted geometry", "RMS µm", "Range µm"],
                rows,
                decimals=1,
            ),
            note=f"Excluded: the {spec.outlier_fraction * 100:.1f} % of points with the largest "
            "residuals, as the guideline permits, before the final least-squares fit.",
        )
    )
    body.append(
        _acceptance_spec_section(
            spec,
            result.spec_path,
            "VDI/VDE 2634 Part 2, one scan (the full test repeats it in several positions and "
            "keeps the worst values: give scanner acceptance every scan)",
        )
    )
    body.append(_inputs_section(result, "evaluated", []))
    return rep.page(
        f"Acceptance test (VDI/VDE 2634-2) — {spec.name}",
        "".join(body),
        subtitle=spec.description,
        generated=result.created,
    )


def _residual_figure(scan: Any, cloud_name: str) -> str:
    """One acceptance scan's points coloured by their artefact's fit residual."""
    png, renderer = render_cloud_png(
        scan.points_base, scan.deviations_mm, title=f"{cloud_name}: artefact residuals"
    )
    limit = deviation_limit(scan.deviations_mm)
    return rep.figure(
        png,
        f"{cloud_name}: residuals of the sphere and plane fits (±{limit * 1000:.0f} µm); grey = "
        f"not part of an artefact. Rendered with {renderer}.",
    )


def _acceptance_spec_section(spec: Any, spec_path: str | None, standard: str) -> str:
    """The "Specification" section of an acceptance report: artefacts and MPEs."""
    mpe = spec.mpe
    spec_items: list[tuple[str, Any]] = [
        ("standard", standard),
        ("specification", spec_path or spec.name),
        ("cell", spec.cell or "-"),
        ("calibrated centre distance", f"{spec.calibrated_distance_mm:.4f} mm"),
    ]
    for s in spec.spheres:
        spec_items.append((f"{s.name} calibrated diameter", f"{s.calibrated_diameter_mm:.4f} mm"))
    spec_items += [
        ("MPE PF / PS / SD / F", f"{mpe.probing_form_mm:.4f} / {mpe.probing_size_mm:.4f} / "
         f"{mpe.sphere_spacing_mm:.4f} / {mpe.flatness_mm:.4f} mm"),
    ]  # fmt: skip
    return rep.section("Specification", rep.key_value_table(spec_items))


def full_acceptance_html(result: FullAcceptance) -> str:
    """The complete HTML page of a :class:`~metrology.acceptance.FullAcceptance`: the
    decisive rows, every scan's values, every scan's residuals."""
    spec = result.spec
    n = len(result.scans)
    names = [Path(r.cloud_path).name if r.cloud_path else "in memory" for r in result.scans]
    body = [
        rep.summary_line(result.rows, detail=f"{spec.name}, {n} scans"),
        rep.section(
            "Characteristics: the worst scan decides",
            rep.tolerance_table(result.rows, decimals=4),
            note="Each row from the scan where its value is largest in magnitude (named in "
            "the note); a scan where it could not be evaluated decides it. Tolerance column: "
            "the maximum permissible error (MPE).",
        ),
    ]
    columns = [f"{c.symbol} {c.artefact}" for c in result.scans[0].characteristics]
    rows = [
        [f"{k + 1}: {name}", "pass" if r.passed else "fail"]
        + [None if c.value_mm is None else c.value_mm * 1000 for c in r.characteristics]
        for k, (r, name) in enumerate(zip(result.scans, names))
    ]
    body.append(
        rep.section(
            "Every scan",
            rep.table(["Scan", "Result", *(f"{c} µm" for c in columns)], rows, decimals=1),
        )
    )
    figures = [_residual_figure(r, name) for r, name in zip(result.scans, names)]
    body.append(rep.section("Scans coloured by residual", "".join(figures)))
    body.append(
        _acceptance_spec_section(
            spec, result.scans[0].spec_path, f"VDI/VDE 2634 Part 2, full test over {n} scans"
        )
    )
    for r, name in zip(result.scans, names):
        body.append(_inputs_section(r, "evaluated", [], f"Calibration and inputs: scan {name}"))
    return rep.page(
        f"Acceptance test (VDI/VDE 2634-2) — {spec.name}, {n} scans",
        "".join(body),
        subtitle=spec.description,
        generated=result.created,
    )


def write_acceptance_report(result: Any, out_json: str | os.PathLike[str]) -> None:
    """Write ``<out>.json``, ``<out>.csv`` and ``<out>.html`` for an acceptance result: one
    scan's (:class:`~metrology.acceptance.AcceptanceResult`) or a full test's
    (:class:`~metrology.acceptance.FullAcceptance`)."""
    full = isinstance(result, FullAcceptance)
    html_text = full_acceptance_html(result) if full else acceptance_html(result)
    _write_judged(result, out_json, html_text)
