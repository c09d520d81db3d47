"""HTML report of the EF check: a table like the paper's Table III, plus the spread of O."""

from __future__ import annotations

import math
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from metrology.ef_check import EFCheckResult
from scanner.formats import html as rep

__all__ = ["write_ef_report"]

# The paper's published figures (Table III, real cell), shown beside ours for orientation.
PAPER_MEAN_ABS_ERROR_MM = 0.33
PAPER_MEAN_REL_ERROR = 0.0021


def table_iii_rows(result: EFCheckResult) -> list[list[object]]:
    """Rows ``[real value, measured, U (k = 2), absolute error, relative error %]`` and the
    average row."""
    rows: list[list[object]] = []
    for m in result.valid:
        rows.append(
            [
                m.id,
                result.nominal_mm,
                m.length_mm,
                None if m.uncertainty is None else m.uncertainty.U,
                abs(m.error_mm),
                100.0 * abs(m.error_mm) / result.nominal_mm,
            ]
        )
    rows.append(
        [
            "Average",
            result.nominal_mm,
            result.mean_length_mm,
            None,
            result.mean_abs_error_mm,
            100.0 * result.mean_rel_error,
        ]
    )
    return rows


def write_ef_report(result: EFCheckResult, path: str | os.PathLike[str]) -> Path:
    """Write the self-contained HTML report of an EF check."""
    body = rep.key_value_table(
        [
            ("measured frames", f"{len(result.valid)} of {len(result.measurements)}"),
            ("mean absolute EF error (mm)", result.mean_abs_error_mm),
            ("mean relative EF error (%)", 100.0 * result.mean_rel_error),
            ("largest absolute EF error (mm)", result.max_abs_error_mm),
            (
                "spread of O in the base frame (mm, largest distance from the mean)",
                result.o_spread_mm,
            ),
            ("paper's real cell, for comparison", "0.33 mm mean absolute, 0.21 % mean relative"),
        ]
    )
    verdict = rep.summary_line(result.rows, detail=f"{len(result.valid)} frames measured")
    sections = [
        verdict,
        rep.section("Verdict", rep.tolerance_table(result.rows, decimals=4)),
        rep.section("Summary", body),
    ]
    sections.append(
        rep.section(
            "Length of EF (as the paper's Table III)",
            rep.table(
                [
                    "frame",
                    "real value (mm)",
                    "measured (mm)",
                    "U, k = 2 (mm)",
                    "absolute error (mm)",
                    "relative error (%)",
                ],
                table_iii_rows(result),
                decimals=3,
            ),
            note="E and F: the stripe's centre line against the largest ring's conic, triangulated "
            "through the light plane and moved into the base frame with the robot pose. U: the "
            "calibration's covariance carried to |EF| and the scatter over the images "
            "(docs/UNCERTAINTY.md).",
        )
    )
    if result.valid:
        fig, ax = plt.subplots(figsize=(7, 3))
        ids = [str(m.id) for m in result.valid]
        errs = [m.error_mm for m in result.valid]
        ax.bar(ids, errs, color=["#2e7d32" if abs(e) <= 0.05 else "#c62828" for e in errs])
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel("frame id")
        ax.set_ylabel("|EF| - nominal (mm)")
        ax.set_title("EF error per frame")
        fig.tight_layout()
        sections.append(
            rep.section("Errors per frame", rep.figure(fig, "Signed EF error per frame"))
        )
        plt.close(fig)
    o = result.o_positions_base
    if len(o):
        mean = o.mean(axis=0)
        rows = [
            [m.id, *(m.o_base - mean).tolist(), float(math.dist(m.o_base, mean))]
            for m in result.valid
            if m.o_base is not None
        ]
        sections.append(
            rep.section(
                "Spread of the target centre O in the base frame",
                rep.table(
                    ["frame", "dx (mm)", "dy (mm)", "dz (mm)", "distance (mm)"], rows, decimals=3
                ),
                note="The target stays fixed during the check, so every pose should put O at the same "
                "base-frame point: the spread tests the hand-eye transform, which |EF| cannot.",
            )
        )
    failed = [m for m in result.measurements if not m.ok]
    if failed:
        sections.append(
            rep.section(
                "Frames not measured",
                rep.table(["frame", "reason"], [[m.id, m.reason] for m in failed]),
            )
        )
    sections.append(
        rep.section(
            "Inputs",
            rep.key_value_table([("session", result.session), ("calibration", result.calibration)]),
        )
    )
    html = rep.page(
        "EF check", "".join(sections), subtitle=f"nominal diameter {result.nominal_mm:.3f} mm"
    )
    return rep.write_page(path, html)
