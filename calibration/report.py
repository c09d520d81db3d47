"""The HTML calibration report: what was found, how well, and which frames to look at.

One self-contained page (:mod:`scanner.formats.html`): the verdict line, every figure with its
uncertainty, detected features drawn over a few images, residuals per image and per pose,
the light-plane fit and the hand-eye residuals.
"""

from __future__ import annotations

import html
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from calibration.intrinsics import IntrinsicsResult
from calibration.intrinsics_model import UncertaintyMap
from calibration.pipeline import CalibrationResult
from scanner.formats import html as rep
from scanner.formats.calibration_file import Calibration

__all__ = ["write_calibration_report"]

logger = logging.getLogger(__name__)


def _fmt(value: float, std: float | None = None, decimals: int = 4, unit: str = "") -> str:
    if value is None or not np.isfinite(value):
        return "n/a"
    s = f"{value:.{decimals}f}"
    if std is not None and np.isfinite(std):
        s += f" ± {std:.{decimals}f}"
    return f"{s} {unit}".strip()


def _features_figure(result: CalibrationResult, max_images: int = 3) -> str:
    html = ""
    shown = 0
    for fid, obs in result.observations.items():
        if not obs or shown >= max_images:
            continue
        frame = next(f for f in result.session.frames if f.id == fid)
        try:
            img = result.session.load_target_image(frame)
        except (OSError, ValueError) as exc:
            logger.debug("report: cannot load frame %s: %s", fid, exc)
            continue
        fig = Figure(figsize=(6.4, 6.4 * img.shape[0] / img.shape[1]))
        ax = fig.add_axes((0, 0, 1, 1))
        ax.imshow(img, cmap="gray")
        ax.plot(obs.points_px[:, 0], obs.points_px[:, 1], "+", color="lime", ms=6)
        for name, p in obs.named_px.items():
            if obs.labelling == "symmetry" and name != "O":
                name += "?"  # no marker, not resolved: A-D only up to a quarter turn
            # Readable on the white card and on the dark surroundings alike.
            ax.annotate(
                name, p, xytext=(4, 4), textcoords="offset points", color="black",
                fontsize=11, fontweight="bold",
                bbox={"boxstyle": "round,pad=0.15", "fc": "#ffd60a", "ec": "black", "lw": 0.6},
            )  # fmt: skip
        st = result.stripes.get(fid)
        if st is not None and len(st):
            ax.plot(st[::5, 0], st[::5, 1], ".", color="red", ms=1)
        ax.set_axis_off()
        html += rep.figure(
            fig, f"frame {fid}: {len(obs.points_px)} features detected", width_px=480
        )
        shown += 1
    return html


def _bar(ids: list[Any], values: list[float], ylabel: str, title: str) -> Figure:
    fig = Figure(figsize=(7, 2.6))
    ax = fig.add_subplot(1, 1, 1)
    ax.bar([str(i) for i in ids], values, color="#4477aa")
    ax.set_ylabel(ylabel)
    ax.set_xlabel("frame")
    ax.set_title(title)
    ax.tick_params(axis="x", labelrotation=90, labelsize=7)
    fig.tight_layout()
    return fig


def _plane_figure(result: CalibrationResult) -> Figure | None:
    lp = result.light_plane
    if lp.plane is None or len(lp.points_cam) == 0:
        return None
    pts = lp.points_cam
    r = lp.plane.signed_distance(pts)
    fig = Figure(figsize=(7, 3))
    ax = fig.add_subplot(1, 2, 1)
    ax.scatter(pts[:, 0], pts[:, 2], c=r * 1000, s=2, cmap="coolwarm")
    ax.set_xlabel("x_cam (mm)")
    ax.set_ylabel("z_cam (mm)")
    ax.set_title("stripe points")
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.hist(r * 1000, bins=50, color="#4477aa")
    ax2.set_xlabel("distance to plane (µm)")
    ax2.set_title(f"RMS {lp.rms_mm * 1000:.1f} µm")
    fig.tight_layout()
    return fig


def _origin_figure(result: CalibrationResult) -> Figure | None:
    """The shadow lines in the light plane (camera x, z) and where they meet: the laser origin
    with its 2-sigma ellipse."""
    origin = result.laser_origin
    if origin is None or len(origin.near_cam) == 0:
        return None
    fig = Figure(figsize=(6.4, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    for near, far, used in zip(origin.near_cam, origin.far_cam, origin.inlier, strict=True):
        ax.plot(
            [near[0], far[0]],
            [near[2], far[2]],
            color="#4477aa" if used else "#bbbbbb",
            linewidth=1.2 if used else 0.8,
        )
        if used and origin:
            ax.plot(
                [origin.origin_cam[0], near[0]],
                [origin.origin_cam[2], near[2]],
                color="#4477aa",
                linewidth=0.5,
                linestyle=":",
            )
    if origin:
        o = origin.origin_cam
        cov = origin.covariance_mm2[np.ix_([0, 2], [0, 2])]
        vals, vecs = np.linalg.eigh(cov)
        t = np.linspace(0.0, 2 * np.pi, 100)
        ring = vecs @ (2 * np.sqrt(np.clip(vals, 0.0, None))[:, None] * [np.cos(t), np.sin(t)])
        ax.plot(o[0] + ring[0], o[2] + ring[1], color="#cc3311", linewidth=1.0)
        ax.plot(o[0], o[2], "+", color="#cc3311", markersize=10)
        ax.set_title(
            f"laser origin: {origin.inliers} of {origin.lines} shadow edges meet "
            f"(2-sigma ellipse, std {origin.std_mm:.2f} mm)",
            fontsize=9,
        )
    else:
        ax.set_title(f"no laser origin: {origin.reason}", fontsize=8)
    ax.set_xlabel("x_cam (mm)")
    ax.set_ylabel("z_cam (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    fig.tight_layout()
    return fig


def _uncertainty_figure(umap: UncertaintyMap) -> Figure:
    fig = Figure(figsize=(6.4, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    extent = (0.0, float(umap.u_px[-1] + umap.u_px[0]), float(umap.v_px[-1] + umap.v_px[0]), 0.0)
    shown = ax.imshow(umap.sigma_px, extent=extent, cmap="viridis", vmin=0.0)
    levels = np.quantile(umap.sigma_px, [0.5, 0.9])
    if levels[1] > levels[0] > 0:
        uu, vv = np.meshgrid(umap.u_px, umap.v_px)
        lines = ax.contour(uu, vv, umap.sigma_px, levels=levels, colors="white", linewidths=0.8)
        ax.clabel(lines, fmt="%.3f px", fontsize=7)
    fig.colorbar(shown, ax=ax, label="1-sigma projection uncertainty (px)")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    fig.tight_layout()
    return fig


def _origin_text(cal: Calibration) -> str:
    """The laser origin written to the file, its source and uncertainty, or why there is none."""
    record = cal.quality.record.get("laser_origin")
    est = record if isinstance(record, dict) else {}
    if cal.laser_origin_cam is None:
        why = est.get("reason") or (
            f"estimate too uncertain (std {est['std_mm']:.1f} mm)" if "std_mm" in est else ""
        )
        return f"not written: {why}" if why else "not written"
    xyz = " ".join(f"{v:.2f}" for v in cal.laser_origin_cam)
    source = cal.quality.record.get("laser_origin_source", "")
    if "std_mm" in est and str(source).startswith("estimated"):
        return (
            f"{xyz} (std {est['std_mm']:.2f} mm within the plane; {est['inliers']} shadow edges "
            f"in {len(est['frames'])} frames)"
        )
    return f"{xyz} ({source})" if source else xyz


def _model_section(intr: IntrinsicsResult) -> str:
    """How the distortion terms were chosen, and where the camera model is least certain."""
    out = ""
    sel = intr.model_selection
    if sel is not None:
        rows = [
            (
                s.name,
                f"{s.held_out_rms_px:.4f}",
                f"{s.fit_rms_px:.4f}",
                f"{s.uncertainty_rms_px:.4f}",
                "chosen" if s.name == sel.chosen else "",
            )
            for s in sel.scores
        ]
        out += (
            rep.table(
                [
                    "distortion terms",
                    "held-out RMS (px)",
                    "fit RMS (px)",
                    "uncertainty RMS (px)",
                    "",
                ],
                rows,
            )
            + f"<p>{html.escape(sel.reason)} ({sel.folds}-fold, views held out in turn).</p>"
        )
    umap = intr.uncertainty_map
    if umap is not None:
        out += rep.figure(
            _uncertainty_figure(umap),
            f"Projection uncertainty over the image (1 sigma; median {umap.median_px:.3f} px, "
            f"largest {umap.max_px:.3f} px): where it is high, add views whose target covers "
            "that part of the image",
        )
    return out


def _verdict_box(verdict: str, warnings: tuple[str, ...]) -> str:
    """The verdict as a coloured banner: green when good, red when poor, grey otherwise."""
    cls = {"good": "pass", "poor": "fail"}.get(verdict.split()[0].lower(), "na")
    detail = f"{len(warnings)} warning(s), listed at the end" if warnings else "no warnings"
    return (
        f'<div class="summary {cls}">Verdict: {html.escape(verdict)} '
        f'<span class="detail">— {detail}</span></div>\n'
    )


def _matrix_table(matrix: NDArray) -> str:
    """A 4x4 transform as a 4-row table of fixed decimals."""
    return rep.table(
        ["", "x", "y", "z", "t (mm)"], [[f"row {i}", *row] for i, row in enumerate(matrix)], 6
    )


def write_calibration_report(
    result: CalibrationResult, report_dir: str | os.PathLike[str], name: str = "calibration.html"
) -> Path:
    """Write the calibration report page and return its path.

    Parameters
    ----------
    result : CalibrationResult
    report_dir : path
        Folder for the page (created if needed).
    name : str
        File name of the page.
    """
    q = result.calibration.quality
    cal = result.calibration
    intr = result.intrinsics
    std = dict(intr.std)
    body = _verdict_box(q.verdict or "unknown", q.warnings)

    body += rep.section(
        "Camera",
        rep.key_value_table(
            {
                "method": intr.method,
                "image": f"{cal.width} x {cal.height}",
                "fx (px)": _fmt(cal.K[0, 0], std.get("fx"), 3),
                "fy (px)": _fmt(cal.K[1, 1], std.get("fy"), 3),
                "cx (px)": _fmt(cal.K[0, 2], std.get("cx"), 3),
                "cy (px)": _fmt(cal.K[1, 2], std.get("cy"), 3),
                "dist (k1 k2 p1 p2 k3)": " ".join(f"{d:.5g}" for d in cal.dist),
                "distortion terms fitted": intr.distortion_model,
                "reprojection RMS (px)": _fmt(intr.rms_px, None, 4),
            }
        )
        + _model_section(intr),
    )
    lpq = result.light_plane
    if lpq is None:
        body += rep.section(
            "Light plane",
            "<p>None: the session has no laser images, so this is a camera and hand-eye "
            "calibration (<code>light_plane: null</code>). <code>scanner scan</code> and "
            "<code>scanner check</code> need a light plane; every other reader uses the file.</p>",
        )
    else:
        body += rep.section(
            "Light plane (camera frame, n·p + d = 0)",
            rep.key_value_table(
                {
                    "method": lpq.method,
                    "normal": " ".join(f"{v:.6f}" for v in cal.light_plane.normal),
                    "normal uncertainty (deg)": _fmt(lpq.std_normal_deg, None, 5),
                    "d (mm)": _fmt(cal.light_plane.d, lpq.std_d_mm, 4),
                    "residual RMS (mm)": _fmt(lpq.rms_mm, None, 4),
                    "points": lpq.n_points,
                    "frames used / rejected": f"{len(lpq.per_frame)} / {len(lpq.rejected)}",
                    "laser origin (mm, camera frame)": _origin_text(cal),
                }
            )
            + (
                rep.figure(
                    fig, "Stripe points in the camera frame and their distances to the plane"
                )
                if (fig := _plane_figure(result)) is not None
                else ""
            )
            + (
                rep.figure(
                    fig,
                    "Shadow edges in the light plane: the stripe's end on the card and its "
                    "restart on the background lie on one ray from the laser; blue lines meet "
                    "at the origin (grey: the camera's view, not the shadow, ended the stripe)",
                )
                if (fig := _origin_figure(result)) is not None
                else ""
            )
            + (
                rep.figure(
                    _bar(
                        [p["frame_id"] for p in lpq.per_frame],
                        [p["rms_mm"] * 1000 for p in lpq.per_frame],
                        "RMS (µm)",
                        "light plane residual per frame",
                    ),
                    "Light-plane residual RMS per frame",
                )
                if lpq.per_frame
                else ""
            ),
        )
    he = result.hand_eye
    x = cal.flange_from_cam
    body += rep.section(
        "Hand-eye (flange_from_cam)",
        rep.key_value_table(
            {
                "method": he.method,
                "translation (mm)": " ".join(
                    _fmt(x[i, 3], float(he.std_translation_mm[i]), 3) for i in range(3)
                ),
                "rotation uncertainty (deg, about cam x y z)": " ".join(
                    _fmt(v, None, 4) for v in he.std_rotation_deg
                ),
                "chain reprojection RMS (px)": _fmt(he.rms_px, None, 3),
                "target origin scatter in base, std x y z (mm)": " ".join(
                    _fmt(v, None, 3) for v in he.target_spread_mm
                ),
                "closed forms tried (RMS px)": ", ".join(
                    f"{k} {v:.3f}" for k, v in (he.candidates or {}).items()
                )
                or "n/a",
            }
        )
        + _matrix_table(x)
        + (
            rep.figure(
                _bar(
                    [p["frame_id"] for p in he.per_pose],
                    [p.get("rms_px", p.get("scatter_mm", np.nan)) for p in he.per_pose],
                    "RMS (px)" if he.per_pose and "rms_px" in he.per_pose[0] else "mm",
                    "hand-eye residual per pose",
                ),
                "Hand-eye chain residual per pose",
            )
            if he.per_pose
            else ""
        ),
    )
    cov = cal.covariance
    if cov is not None:
        sd = cov.std
        body += rep.section(
            "Uncertainty carried into measurements (covariance key)",
            rep.key_value_table(
                {
                    "how estimated": cov.method,
                    "fx fy cx cy (px, 1 sigma)": " ".join(
                        _fmt(sd[k], None, 4) for k in ("fx", "fy", "cx", "cy")
                    ),
                    "light-plane tilt (deg) / offset d (mm)": (
                        f"{np.degrees(np.hypot(sd['plane_a'], sd['plane_b'])):.5f} / "
                        f"{sd['plane_d']:.4f}"
                    ),
                    "hand-eye rotation (deg, cam x y z)": " ".join(
                        _fmt(np.degrees(sd[k]), None, 5) for k in ("cam_rx", "cam_ry", "cam_rz")
                    ),
                    "hand-eye translation (mm, cam x y z)": " ".join(
                        _fmt(sd[k], None, 4) for k in ("cam_tx", "cam_ty", "cam_tz")
                    ),
                    "robot repeatability (deg / mm per axis)": (
                        f"{cov.robot_rotation_deg:.4f} / {cov.robot_translation_mm:.4f}"
                    ),
                }
            ),
            note="Each measurement's uncertainty budget carries these through the same fits "
            "(docs/UNCERTAINTY.md).",
        )
    per_view = {str(k): v for k, v in result.per_view_rms_px.items()}
    if per_view:
        body += rep.section(
            "Residuals per image (intrinsics)",
            rep.figure(
                _bar(list(per_view), list(per_view.values()), "RMS (px)", "per image"),
                "Intrinsics residual RMS per image",
            ),
        )
    body += rep.section("Detected features", _features_figure(result))
    labelling = q.record.get("labelling") or {}
    if labelling.get("symmetry"):
        resolved = labelling.get("resolved", {})
        unresolved = labelling.get("unresolved", {})
        rows_l = [
            (
                f"frame {i}",
                f"quarter turns {resolved[str(i)]['quarter_turns']} from the robot's motion "
                f"(pose within {resolved[str(i)]['angle_deg']:.2f} deg of the prediction)"
                if str(i) in resolved
                else f"intrinsics and light plane only: {unresolved.get(str(i), 'not posed')}",
            )
            for i in labelling["symmetry"]
        ]
        body += rep.section(
            "Views without the orientation marker (labelled up to the target's symmetry)",
            rep.key_value_table(rows_l),
        )
    rows = [(str(r.frame_id), f"{r.stage}: {r.reason}") for r in result.rejected]
    rows += [("warning", w) for w in q.warnings]
    if rows:
        body += rep.section("Rejected frames and warnings", rep.key_value_table(rows))
    body += rep.section(
        "Timings", rep.key_value_table({k: f"{v:.2f}" for k, v in result.timings.items()})
    )
    page = rep.page("Calibration report", body, subtitle=str(result.session.root))
    return rep.write_page(Path(report_dir) / name, page)
