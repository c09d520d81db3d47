"""Planned sweeps on disk (``scan-plan/1``): the robot poses to send, and what the plan expects.

::

    PLAN/
      plan.json    # format, rotation, part, sweeps (start, direction, length, step), coverage
      sweeps.csv   # id, sweep, x, y, z, rotation columns: one flange pose per profile

``sweeps.csv`` uses the session format's pose columns (``shared/spec/interfaces.md`` section
1) with the ``sweep`` column of multi-sweep sessions, so a robot program (or the virtual cell)
drives each row in order and a sweep session captured from it keeps the same ids.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanner.core.conventions import (
    RotationConvention,
    check_transform,
    pose_to_transform,
    rotation_columns,
    transform_to_pose,
)
from scanner.core.fileio import InputError, read_json_object, write_json_atomic, write_text_atomic

__all__ = ["FORMAT", "ScanPlanFile", "read_scan_plan", "write_scan_plan"]

FORMAT = "scan-plan/1"


@dataclass(frozen=True)
class ScanPlanFile:
    """A plan as read back.

    Attributes
    ----------
    base_from_flange : tuple of ndarray, each shape (F_k, 4, 4)
        The flange poses of each sweep, in order.
    rotation : str
        The rotation convention of ``sweeps.csv``.
    record : dict
        The rest of ``plan.json`` (part, sweep parameters, predicted coverage), as written.
    base_from_part : ndarray, shape (4, 4), or None
        Where the plan put the part (``part.base_from_part``), when it says.
    """

    base_from_flange: tuple[NDArray[np.float64], ...]
    rotation: RotationConvention
    record: dict[str, Any] = field(default_factory=dict)
    base_from_part: NDArray[np.float64] | None = None

    @property
    def frames(self) -> int:
        return sum(len(p) for p in self.base_from_flange)


def write_scan_plan(
    folder: str | os.PathLike[str],
    base_from_flange: list[NDArray[np.float64]],
    record: dict[str, Any],
    rotation: RotationConvention | str = RotationConvention.QUATERNION_WXYZ,
) -> tuple[Path, Path]:
    """Write ``plan.json`` and ``sweeps.csv`` into ``folder``; returns their paths."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    rotation = RotationConvention.parse(rotation)
    columns = rotation_columns(rotation)
    rows = [["id", "sweep", "x", "y", "z", *columns]]
    fid = 0
    for k, poses in enumerate(base_from_flange):
        for pose in poses:
            position, angles = transform_to_pose(pose, rotation)
            numbers = [*np.asarray(position).tolist(), *np.asarray(angles).tolist()]
            rows.append([str(fid), str(k), *(f"{v:.9g}" for v in numbers)])
            fid += 1
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    csv_path = root / "sweeps.csv"
    json_path = root / "plan.json"
    write_text_atomic(csv_path, buf.getvalue())
    write_json_atomic(json_path, {"format": FORMAT, "rotation": rotation.value, **record})
    return json_path, csv_path


def read_scan_plan(folder: str | os.PathLike[str]) -> ScanPlanFile:
    """Read a plan folder (or its ``plan.json``), checking every row.

    Raises
    ------
    InputError
        Missing files, another format, unknown rotation, a bad number or an empty plan.
    """
    root = Path(folder)
    if root.name == "plan.json":
        root = root.parent
    meta = read_json_object(root / "plan.json")
    if meta.get("format") != FORMAT:
        raise InputError(
            root / "plan.json", f"expected format {FORMAT!r}, got {meta.get('format')!r}"
        )
    try:
        rotation = RotationConvention.parse(str(meta.get("rotation")), "plan.json rotation")
        columns = rotation_columns(rotation)
    except ValueError as exc:
        raise InputError(root / "plan.json", str(exc)) from None
    path = root / "sweeps.csv"
    if not path.is_file():
        raise InputError(path, "planned sweeps not found")
    reader = csv.DictReader(io.StringIO(path.read_text(encoding="utf-8")))
    need = ["id", "sweep", "x", "y", "z", *columns]
    missing = [c for c in need if c not in (reader.fieldnames or [])]
    if missing:
        raise InputError(path, f"expected columns {need}, missing {missing}")
    sweeps: dict[int, list[NDArray]] = {}
    for line, row in enumerate(reader, start=2):
        try:
            values = [float(row[c]) for c in ("x", "y", "z", *columns)]
            sweep = int(row["sweep"])
        except (TypeError, ValueError):
            raise InputError(path, f"row {line}: expected numbers in {need}") from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(path, f"row {line}: expected finite numbers")
        try:
            pose = pose_to_transform(values[:3], values[3:], rotation)
        except ValueError as exc:
            raise InputError(path, f"row {line}: {exc}") from None
        sweeps.setdefault(sweep, []).append(pose)
    if not sweeps:
        raise InputError(path, "expected at least one pose, got none")
    record = {k: v for k, v in meta.items() if k not in ("format", "rotation")}
    ordered = tuple(np.stack(sweeps[k]) for k in sorted(sweeps))
    part = record.get("part")
    base_from_part = None
    if isinstance(part, dict) and "base_from_part" in part:
        try:
            base_from_part = check_transform(
                np.asarray(part["base_from_part"], dtype=np.float64), "part.base_from_part"
            )
        except (TypeError, ValueError) as exc:
            raise InputError(root / "plan.json", str(exc)) from None
    return ScanPlanFile(ordered, rotation, record, base_from_part)
