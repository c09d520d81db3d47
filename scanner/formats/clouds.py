"""Point clouds on disk: binary PLY (default), PCD and E57, chosen by the file's extension.

Every writer goes through :func:`scanner.core.fileio.atomic_output` (a failed write leaves the old
file untouched) and records where the cloud came from where the format allows it: PLY
``comment``/``obj_info`` header lines, E57 scan name and ``sensorSoftwareVersion``/
``description``; PCD has no place for free text, so the same record goes to a ``.json`` beside it.

Clouds are Open3D tensor point clouds (:class:`open3d.t.geometry.PointCloud`): ``positions``
(float64, base frame, mm) plus per-point attributes (``intensity``, ``width_px``, ``frame_id``,
``sweep_id``, ``flags``, optional ``normals``).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from scanner.core.fileio import InputError, atomic_output, current_umask, write_json_atomic

__all__ = [
    "CLOUD_SUFFIXES",
    "FORMATS",
    "check_ply",
    "cloud_arrays",
    "read_cloud",
    "read_ply_metadata",
    "read_points",
    "write_cloud",
]

log = logging.getLogger(__name__)

FORMATS = (".ply", ".pcd", ".e57")
#: What :func:`read_points` reads: the scanner's formats and plain point lists.
CLOUD_SUFFIXES = (".ply", ".pcd", ".e57", ".xyz", ".xyzn", ".pts", ".npy", ".txt", ".csv")

#: Bytes of each PLY scalar type.
_PLY_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
    "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip

_PLY_TYPES = {
    np.dtype(np.float64): "double",
    np.dtype(np.float32): "float",
    np.dtype(np.int32): "int",
    np.dtype(np.uint8): "uchar",
    np.dtype(np.int64): "int",
    np.dtype(np.uint16): "ushort",
}


def cloud_arrays(cloud: o3d.t.geometry.PointCloud) -> dict[str, NDArray]:
    """Per-point NumPy arrays of a tensor cloud: ``positions`` (N, 3) and each attribute."""
    out: dict[str, NDArray] = {}
    for key in cloud.point:
        arr = cloud.point[key].numpy()
        out[key] = arr
    return out


def _check_format(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in FORMATS:
        raise ValueError(
            f"{path}: expected a point-cloud extension {', '.join(FORMATS)}, got {ext or 'none'!r}"
        )
    return ext


def write_cloud(
    path: str | os.PathLike[str],
    cloud: o3d.t.geometry.PointCloud,
    metadata: Mapping[str, Any] | None = None,
    *,
    frame: str = "base",
) -> Path:
    """Write ``cloud`` atomically in the format its extension names.

    Parameters
    ----------
    path : path
        ``.ply`` (binary little-endian), ``.pcd`` (binary) or ``.e57``.
    cloud : open3d.t.geometry.PointCloud
        Positions in mm; attributes are written where the format can hold them.
    metadata : mapping, optional
        JSON-serialisable provenance (calibration file and hash, sessions, options).
    frame : str
        The frame the positions are in, named in the PLY header ("base", "nominal").

    Returns
    -------
    Path
        The written file.
    """
    target = Path(path)
    ext = _check_format(target)
    meta = dict(metadata or {})
    arrays = cloud_arrays(cloud)
    if "positions" not in arrays:
        raise ValueError("cloud: expected a positions attribute, got none")
    if ext == ".ply":
        _write_ply(target, arrays, meta, frame)
    elif ext == ".pcd":
        with atomic_output(target) as tmp:
            if not o3d.t.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
                raise OSError(f"{target}: Open3D could not write the PCD file")
            _usual_permissions(tmp)
        if meta:
            write_json_atomic(target.with_suffix(target.suffix + ".json"), meta)
    else:
        _write_e57(target, arrays, meta)
    return target


def _usual_permissions(path: Path) -> None:
    """Give a temporary file (created 0600) the mode a plain ``open`` would have (umask)."""
    os.chmod(path, 0o666 & ~current_umask())


def _ply_header(
    arrays: Mapping[str, NDArray], meta: Mapping[str, Any], n: int, frame: str
) -> tuple:
    lines = ["ply", "format binary_little_endian 1.0"]
    lines.append(f"comment robot-line-scanner point cloud, {frame} frame, units mm")
    for key, value in meta.items():
        text = json.dumps(value, default=str, separators=(",", ":"))
        lines.append(f"comment {key} {text}".replace("\n", " "))
    lines.append("obj_info " + json.dumps(dict(meta), default=str, separators=(",", ":")))
    lines.append(f"element vertex {n}")
    fields: list[tuple[str, np.dtype]] = []
    columns: list[NDArray] = []

    def add(name: str, arr: NDArray) -> None:
        dt = np.dtype(arr.dtype)
        if dt == np.int64:
            dt = np.dtype(np.int32)
        if dt not in _PLY_TYPES:
            dt = np.dtype(np.float32)
        fields.append((name, dt.newbyteorder("<")))
        columns.append(arr.astype(dt, copy=False))
        lines.append(f"property {_PLY_TYPES[dt]} {name}")

    pos = arrays["positions"]
    for i, axis in enumerate("xyz"):
        add(axis, pos[:, i])
    if "normals" in arrays:
        for i, axis in enumerate(("nx", "ny", "nz")):
            add(axis, arrays["normals"][:, i].astype(np.float32))
    for key, arr in arrays.items():
        if key in ("positions", "normals"):
            continue
        arr = arr.reshape(n, -1)
        if arr.shape[1] == 1:
            add(key, arr[:, 0])
        else:
            for j in range(arr.shape[1]):
                add(f"{key}_{j}", arr[:, j])
    lines.append("end_header")
    return "\n".join(lines) + "\n", fields, columns


def _write_ply(
    target: Path, arrays: Mapping[str, NDArray], meta: Mapping[str, Any], frame: str
) -> None:
    n = int(arrays["positions"].shape[0])
    header, fields, columns = _ply_header(arrays, meta, n, frame)
    record = np.empty(n, dtype=np.dtype(fields))
    for (name, _), col in zip(fields, columns):
        record[name] = col
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii", errors="replace"))
            record.tofile(fh)
        _usual_permissions(tmp)


def _write_e57(target: Path, arrays: Mapping[str, NDArray], meta: Mapping[str, Any]) -> None:
    import pye57  # optional at import time: only E57 output needs it
    from pye57 import libe57

    pos = arrays["positions"]
    data: dict[str, NDArray] = {
        "cartesianX": np.ascontiguousarray(pos[:, 0], dtype=np.float64),
        "cartesianY": np.ascontiguousarray(pos[:, 1], dtype=np.float64),
        "cartesianZ": np.ascontiguousarray(pos[:, 2], dtype=np.float64),
    }
    if "intensity" in arrays:
        data["intensity"] = np.ascontiguousarray(arrays["intensity"].reshape(-1), np.float64)
    if "frame_id" in arrays:
        data["rowIndex"] = np.ascontiguousarray(arrays["frame_id"].reshape(-1), np.int32)
        col = arrays.get("line")
        data["columnIndex"] = (
            np.zeros(pos.shape[0], np.int32)
            if col is None
            else np.ascontiguousarray(col.reshape(-1), np.int32)
        )
    description = json.dumps(dict(meta), default=str, separators=(",", ":"))
    name = "robot-line-scanner scan (base frame, mm)"
    with atomic_output(target) as tmp:
        tmp.unlink()  # libE57 refuses to open an existing file for writing
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            # E57 stores metres by definition: convert at this boundary.
            data_m = {k: (v / 1000.0 if k.startswith("cartesian") else v) for k, v in data.items()}
            e57.write_scan_raw(data_m, name=name)
            try:
                scan = e57.data3d[0]
                scan.set("sensorSoftwareVersion", libe57.StringNode(e57.image_file, description))
            except Exception as exc:  # the record is a courtesy; the points matter
                log.debug("E57: could not attach the provenance record: %s", exc)
        finally:
            e57.close()


def read_cloud(path: str | os.PathLike[str]) -> o3d.t.geometry.PointCloud:
    """Read a cloud written by :func:`write_cloud` (positions in mm, attributes kept)."""
    p = Path(path)
    ext = _check_format(p)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: point cloud not found")
    if ext in (".ply", ".pcd"):
        return o3d.t.io.read_point_cloud(str(p))
    import pye57

    e57 = pye57.E57(str(p))
    try:
        raw = e57.read_scan_raw(0)
    finally:
        e57.close()
    pos = np.column_stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]]) * 1000.0
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(pos))
    if "intensity" in raw:
        cloud.point["intensity"] = o3d.core.Tensor(
            np.asarray(raw["intensity"], np.float32).reshape(-1, 1)
        )
    return cloud


def _read_ply_header(path: Path) -> tuple[list[str], int]:
    """The header lines of a PLY file and the byte offset where its data starts."""
    lines: list[str] = []
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file (no 'ply' magic line)")
        lines.append("ply")
        for _ in range(10_000):
            raw = fh.readline()
            if not raw:
                raise InputError(path, "truncated PLY header (no end_header)")
            line = raw.decode("ascii", errors="replace").strip()
            lines.append(line)
            if line == "end_header":
                return lines, fh.tell()
    raise InputError(path, "PLY header too long (no end_header in 10000 lines)")


def check_ply(path: str | os.PathLike[str]) -> int:
    """Check that a PLY file holds the data its header declares; return its vertex count.

    A binary file must be exactly as long as its elements' rows (when every property is a
    scalar); an ASCII file must hold at least a line per declared row.

    Raises
    ------
    InputError
        Truncated or over-declared data, an unknown format or property type.
    """
    p = Path(path)
    lines, data_start = _read_ply_header(p)
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ")), None)
    elements: list[list] = []  # [name, count, row bytes or None for lists]
    for ln in lines:
        words = ln.split()
        if words[:1] == ["element"] and len(words) == 3:
            try:
                elements.append([words[1], int(words[2]), 0])
            except ValueError:
                raise InputError(p, f"PLY header: bad element line {ln!r}") from None
        elif words[:1] == ["property"] and elements:
            if words[1] == "list":
                elements[-1][2] = None
            elif elements[-1][2] is not None:
                if words[1] not in _PLY_SIZES:
                    raise InputError(p, f"PLY header: unknown property type {words[1]!r}")
                elements[-1][2] += _PLY_SIZES[words[1]]
    vertices = next((e[1] for e in elements if e[0] == "vertex"), 0)
    if fmt in ("binary_little_endian", "binary_big_endian"):
        if all(e[2] is not None for e in elements):
            expected = data_start + sum(e[1] * e[2] for e in elements)
            size = p.stat().st_size
            if size != expected:
                raise InputError(
                    p,
                    f"PLY data is {size - data_start} bytes, its header declares "
                    f"{expected - data_start} ({vertices} vertices): "
                    f"{'truncated' if size < expected else 'unexpected trailing data'}",
                )
    elif fmt == "ascii":
        with open(p, "rb") as fh:
            fh.seek(data_start)
            rows = sum(1 for raw in fh if raw.strip())
        declared = sum(e[1] for e in elements)
        if rows < declared:
            raise InputError(p, f"PLY holds {rows} data lines, its header declares {declared}")
    else:
        raise InputError(p, f"PLY header: unknown format {fmt!r}")
    return vertices


def read_ply_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The provenance record of a PLY written by :func:`write_cloud` (its ``obj_info`` line),
    empty when there is none or it is not a JSON object."""
    lines, _ = _read_ply_header(Path(path))
    for line in lines:
        if line.startswith("obj_info "):
            try:
                record = json.loads(line[len("obj_info ") :])
            except json.JSONDecodeError:
                return {}
            return record if isinstance(record, dict) else {}
    return {}


def _read_provenance(p: Path, ext: str) -> dict[str, Any]:
    if ext == ".ply":
        return read_ply_metadata(p)
    side = p.with_suffix(p.suffix + ".json")
    if ext == ".pcd" and side.is_file():
        try:
            record = json.loads(side.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        return record if isinstance(record, dict) else {}
    return {}


def read_points(path: str | os.PathLike[str]) -> tuple[NDArray, dict[str, Any]]:
    """Read a cloud's points (base frame, mm) and its provenance record, checked.

    Parameters
    ----------
    path : path
        ``.ply`` / ``.pcd`` / ``.e57`` (as :func:`write_cloud` writes them, or from another
        tool), ``.xyz`` / ``.pts`` / ``.txt`` / ``.csv`` (columns x y z first), or ``.npy``
        (an ``(N, 3)`` array).

    Returns
    -------
    points : ndarray, shape (N, 3)
    provenance : dict
        The scanner's record (calibration file, its hash, sessions), empty when absent.

    Raises
    ------
    InputError
        Missing file, unknown extension, a PLY whose data does not match its header, an
        unreadable or empty cloud, non-finite points.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "point cloud not found")
    ext = p.suffix.lower()
    if ext not in CLOUD_SUFFIXES:
        raise InputError(p, f"expected a cloud file ({', '.join(CLOUD_SUFFIXES)}), got {ext!r}")
    declared = check_ply(p) if ext == ".ply" else None
    try:
        if ext in (".ply", ".pcd", ".e57", ".xyz", ".xyzn", ".pts"):
            cloud = read_cloud(p) if ext == ".e57" else o3d.t.io.read_point_cloud(str(p))
            positions = cloud.point.positions.numpy() if "positions" in cloud.point else None
            pts = np.zeros((0, 3)) if positions is None else positions
        elif ext == ".npy":
            pts = np.load(p, allow_pickle=False)
        else:
            pts = np.loadtxt(p, delimiter="," if ext == ".csv" else None, ndmin=2, comments="#")
            pts = pts[:, :3]
    except (OSError, ValueError, UnicodeDecodeError, RuntimeError) as exc:
        raise InputError(p, f"cannot read point cloud ({exc})") from None
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(p, f"expected a non-empty (N, 3) cloud, got shape {pts.shape}")
    if declared is not None and len(pts) != declared:
        raise InputError(p, f"read {len(pts)} points, the PLY header declares {declared}")
    if not np.all(np.isfinite(pts)):
        raise InputError(p, "expected finite point coordinates, got NaN or inf")
    return pts, _read_provenance(p, ext)
