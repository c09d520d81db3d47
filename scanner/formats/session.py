"""Reader and writer of capture-session folders (``scan-session/1``).

The format is a public contract (``shared/spec/interfaces.md``, section 1)::

    SESSION/
      session.json   # format, kind, units, camera, rotation, target
      frames.csv     # id, target_image, laser_image, x, y, z, rotation columns
      images/...

Images load lazily: a :class:`Session` holds paths, so a sweep of thousands of frames never
sits in memory whole. Validation errors name the file, the row and the column.

Extensions (optional, ignored by readers of version 1): a ``sweep`` column in ``frames.csv``
groups the frames of a multi-sweep session; ``laser_image_off`` names a laser-off frame of the
same pose (used to subtract ambient light).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from scanner.core.conventions import (
    RotationConvention,
    pose_to_transform,
    rotation_columns,
    transform_to_pose,
)
from scanner.core.fileio import InputError, json_int, read_json_object, write_text_atomic
from scanner.core.images import image_size, load_gray_image, load_laser_images
from scanner.core.targets import TargetSpec, parse_target, target_to_json

__all__ = [
    "FORMAT",
    "KINDS",
    "Frame",
    "Session",
    "read_session",
    "write_session",
]

FORMAT = "scan-session/1"
KINDS = ("calibration", "check", "sweep")


@dataclass(frozen=True)
class Frame:
    """One row of ``frames.csv``: one robot stop.

    Image paths are absolute (resolved against the session folder) or ``None`` when empty.
    """

    id: int
    target_image: Path | None
    laser_image: Path | None
    base_from_flange: NDArray | None = None
    sweep: int = 0
    laser_off_image: Path | None = None

    @property
    def has_pose(self) -> bool:
        return self.base_from_flange is not None


@dataclass
class Session:
    """A capture session read from (or to be written to) a folder."""

    root: Path
    kind: str
    width: int
    height: int
    frames: list[Frame]
    rotation: RotationConvention | None = None
    target: TargetSpec | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def posed_frames(self) -> list[Frame]:
        return [f for f in self.frames if f.has_pose]

    def load_target_image(self, frame: Frame) -> NDArray:
        if frame.target_image is None:
            raise InputError(self.root / "frames.csv", f"frame {frame.id} has no target_image")
        return load_gray_image(frame.target_image, laser=False)

    def load_laser_image(self, frame: Frame) -> NDArray:
        if frame.laser_image is None:
            raise InputError(self.root / "frames.csv", f"frame {frame.id} has no laser_image")
        return load_gray_image(frame.laser_image, laser=True)

    def load_laser_pair(self, frame: Frame) -> tuple[NDArray, NDArray | None]:
        """The frame's laser image and its laser-off image (``None`` when it has none), read
        alike (:func:`scanner.core.images.load_laser_images`)."""
        if frame.laser_image is None:
            raise InputError(self.root / "frames.csv", f"frame {frame.id} has no laser_image")
        return load_laser_images(frame.laser_image, frame.laser_off_image)


def _fail(path: Path, reason: str) -> InputError:
    return InputError(path, reason)


def _read_session_json(root: Path) -> dict[str, Any]:
    path = root / "session.json"
    if not root.is_dir():
        raise InputError(root, "session folder not found")
    if not path.is_file():
        raise InputError(path, "missing (a capture session needs session.json and frames.csv)")
    return read_json_object(path)


def _parse_float(text: str, path: Path, line: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise _fail(
            path, f"row {line}, column {column!r}: expected a number, got {text!r}"
        ) from None
    if not math.isfinite(value):
        raise _fail(path, f"row {line}, column {column!r}: expected a finite number, got {text!r}")
    return value


def read_session(root: str | os.PathLike[str], check_images: bool = True) -> Session:
    """Read and validate a ``scan-session/1`` folder.

    Parameters
    ----------
    root : path
        The session folder.
    check_images : bool
        Check that every referenced image exists, is readable and has the size given in
        ``camera`` (PNG sizes come from the header, so this stays cheap for long sweeps).

    Raises
    ------
    InputError
        One line naming the file (and row and column) and the reason.
    """
    root = Path(root)
    meta = _read_session_json(root)
    meta_path = root / "session.json"

    fmt = meta.get("format")
    if fmt != FORMAT:
        raise _fail(meta_path, f"format: expected {FORMAT!r}, got {fmt!r}")
    kind = meta.get("kind")
    if kind not in KINDS:
        raise _fail(meta_path, f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    units = meta.get("units")
    if units != "mm":
        raise _fail(meta_path, f"units: expected 'mm', got {units!r}")
    camera = meta.get("camera")
    if not isinstance(camera, dict):
        raise _fail(meta_path, "camera: expected an object {width, height}")
    try:
        width = json_int(camera["width"], "camera.width")
        height = json_int(camera["height"], "camera.height")
    except (KeyError, TypeError, ValueError):
        raise _fail(
            meta_path, f"camera: expected integer width and height, got {camera!r}"
        ) from None
    if width <= 0 or height <= 0:
        raise _fail(meta_path, f"camera: expected positive size, got {width}x{height}")
    rotation = None
    if meta.get("rotation") is not None:
        try:
            rotation = RotationConvention.parse(str(meta["rotation"]))
        except ValueError as exc:
            raise _fail(meta_path, str(exc)) from None
    target = None
    if meta.get("target") is not None:
        try:
            target = parse_target(meta["target"])
        except ValueError as exc:
            raise _fail(meta_path, str(exc)) from None
    if kind in ("calibration", "check") and target is None:
        raise _fail(meta_path, f"target: required for a {kind} session")

    frames = _read_frames(root, rotation, width, height, check_images)
    if kind == "sweep":
        for frame in frames:
            if frame.laser_image is None:
                raise _fail(root / "frames.csv", f"frame {frame.id}: a sweep row needs laser_image")
            if not frame.has_pose:
                raise _fail(
                    root / "frames.csv", f"frame {frame.id}: a sweep row needs a robot pose"
                )
    known = {"format", "kind", "units", "camera", "rotation", "target"}
    extra = {k: v for k, v in meta.items() if k not in known}
    return Session(root, kind, width, height, frames, rotation, target, extra)


#: No robot reaches farther than this from its base: a pose beyond it is a unit or typing error.
WORKSPACE_LIMIT_MM = 1.0e5

#: Set to 1 to accept image paths in frames.csv that leave the session folder.
OUTSIDE_IMAGES_ENV = "SCANNER_ALLOW_OUTSIDE_IMAGES"


def _leaves(rel: str) -> bool:
    """Whether a frames.csv image path points outside its session folder."""
    norm = os.path.normpath(rel)
    return os.path.isabs(rel) or norm == ".." or norm.startswith(".." + os.sep)


def _read_frames(
    root: Path, rotation: RotationConvention | None, width: int, height: int, check_images: bool
) -> list[Frame]:
    path = root / "frames.csv"
    images_outside = os.environ.get(OUTSIDE_IMAGES_ENV) == "1"
    if not path.is_file():
        raise InputError(path, "missing (a capture session needs session.json and frames.csv)")
    try:
        # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark.
        with open(path, newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
        if "\x00" in text:
            line = text.count("\n", 0, text.index("\x00")) + 1
            raise InputError(path, f"row {line}: a NUL byte (not a text CSV file?)")
        rows = list(csv.reader(text.splitlines()))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read: {exc}") from None
    if not rows:
        raise _fail(path, "empty (expected a header row)")
    header = [h.strip() for h in rows[0]]
    for required in ("id", "target_image", "laser_image"):
        if required not in header:
            raise _fail(path, f"header: missing column {required!r} (got {', '.join(header)})")
    col = {name: i for i, name in enumerate(header)}
    pose_cols: tuple[str, ...] = ()
    has_pose_cols = all(c in col for c in ("x", "y", "z"))
    if rotation is not None:
        pose_cols = ("x", "y", "z", *rotation_columns(rotation))
        missing = [c for c in pose_cols if c not in col]
        if missing:
            raise _fail(
                path,
                f"header: missing pose column(s) {', '.join(missing)} for rotation {rotation.value!r}",
            )

    frames: list[Frame] = []
    seen: dict[int, int] = {}
    posed_rows = unposed_rows = 0
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) > len(header) and any(c.strip() for c in row[len(header) :]):
            raise _fail(
                path,
                f"row {line}: expected at most {len(header)} cells (the header's), got "
                f"{len(row)} (a decimal comma in a number?)",
            )

        def cell(name: str, row: list[str] = row) -> str:
            i = col.get(name)
            return row[i].strip() if i is not None and i < len(row) else ""

        id_text = cell("id")
        try:
            frame_id = int(id_text)
        except ValueError:
            raise _fail(
                path, f"row {line}, column 'id': expected an integer, got {id_text!r}"
            ) from None
        if frame_id in seen:
            raise _fail(
                path,
                f"row {line}, column 'id': duplicate id {frame_id} (first on row {seen[frame_id]})",
            )
        seen[frame_id] = line

        images: dict[str, Path | None] = {}
        for name in ("target_image", "laser_image", "laser_image_off"):
            rel = cell(name)
            if not rel:
                images[name] = None
                continue
            if not images_outside and _leaves(rel):
                raise _fail(
                    path,
                    f"row {line}, column {name!r}: image {rel!r} is outside the session folder "
                    f"(set {OUTSIDE_IMAGES_ENV}=1 to allow it)",
                )
            img_path = (root / rel).resolve()
            if check_images:
                if not img_path.is_file():
                    raise _fail(path, f"row {line}, column {name!r}: image {rel!r} not found")
                try:
                    w, h = image_size(img_path)
                except InputError as exc:
                    raise _fail(
                        path, f"row {line}, column {name!r}: {exc.reason} ({rel})"
                    ) from None
                if (w, h) != (width, height):
                    raise _fail(
                        path,
                        f"row {line}, column {name!r}: image {rel!r} is {w}x{h}, expected {width}x{height} (session camera)",
                    )
            images[name] = img_path
        if images["target_image"] is None and images["laser_image"] is None:
            raise _fail(path, f"row {line}: expected target_image or laser_image, got neither")

        base_from_flange = None
        pose_texts = [cell(c) for c in ("x", "y", "z")] if has_pose_cols else []
        if rotation is not None:
            pose_texts = [cell(c) for c in pose_cols]
        if pose_texts and any(pose_texts):
            if rotation is None:
                raise _fail(root / "session.json", "rotation: required when frames.csv gives poses")
            empty = [c for c, t in zip(pose_cols, pose_texts) if not t]
            if empty:
                raise _fail(
                    path,
                    f"row {line}, column {empty[0]!r}: empty while other pose columns are given",
                )
            values = [_parse_float(t, path, line, c) for c, t in zip(pose_cols, pose_texts)]
            far = [c for c, v in zip(pose_cols[:3], values[:3]) if abs(v) > WORKSPACE_LIMIT_MM]
            if far:
                raise _fail(
                    path,
                    f"row {line}, column {far[0]!r}: expected a position within "
                    f"{WORKSPACE_LIMIT_MM:g} mm of the robot base, got {values[pose_cols.index(far[0])]:g}",
                )
            try:
                base_from_flange = pose_to_transform(values[:3], values[3:], rotation)
            except ValueError as exc:
                raise _fail(path, f"row {line}: {exc}") from None
            posed_rows += 1
        else:
            unposed_rows += 1

        sweep = 0
        if cell("sweep"):
            try:
                sweep = int(cell("sweep"))
            except ValueError:
                raise _fail(
                    path, f"row {line}, column 'sweep': expected an integer, got {cell('sweep')!r}"
                ) from None
        frames.append(
            Frame(
                id=frame_id,
                target_image=images["target_image"],
                laser_image=images["laser_image"],
                base_from_flange=base_from_flange,
                sweep=sweep,
                laser_off_image=images["laser_image_off"],
            )
        )
    if not frames:
        raise _fail(path, "no frames (expected at least one row after the header)")
    return frames


def _format_number(value: float) -> str:
    return repr(float(value))


def write_session(
    root: str | os.PathLike[str],
    kind: str,
    width: int,
    height: int,
    frames: Sequence[Frame],
    rotation: RotationConvention | str | None = None,
    target: TargetSpec | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``frames.csv`` and then ``session.json`` (last: its presence marks the session complete).

    Image paths in ``frames`` must already exist inside ``root``; they are stored relative to it.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    conv = RotationConvention.parse(rotation) if isinstance(rotation, str) else rotation
    any_pose = any(f.has_pose for f in frames)
    if any_pose and conv is None:
        raise ValueError("rotation: required when any frame has a pose")
    rot_cols = rotation_columns(conv) if conv is not None else ()
    any_off = any(f.laser_off_image is not None for f in frames)
    any_sweep = any(f.sweep != 0 for f in frames)
    header = ["id", "target_image", "laser_image"]
    if conv is not None:
        header += ["x", "y", "z", *rot_cols]
    if any_sweep:
        header.append("sweep")
    if any_off:
        header.append("laser_image_off")

    # abspath, not resolve: an images folder may be a symlink to shared images.
    root_abs = Path(os.path.abspath(root))

    def rel(p: Path | None) -> str:
        if p is None:
            return ""
        p = Path(p)
        if not p.is_absolute():
            # Relative to the session folder if it is there, else to the working directory.
            p = root / p if (root / p).exists() or not p.exists() else p
        try:
            return Path(os.path.abspath(p)).relative_to(root_abs).as_posix()
        except ValueError:
            raise ValueError(
                f"image {p}: expected a file inside the session folder {root}"
            ) from None

    lines = [",".join(header)]
    for f in frames:
        row = [str(f.id), rel(f.target_image), rel(f.laser_image)]
        if conv is not None:
            if f.base_from_flange is None:
                row += [""] * (3 + len(rot_cols))
            else:
                pos, vals = transform_to_pose(f.base_from_flange, conv)
                row += [_format_number(v) for v in (*pos, *vals)]
        if any_sweep:
            row.append(str(f.sweep))
        if any_off:
            row.append(rel(f.laser_off_image))
        lines.append(",".join(row))
    write_text_atomic(root / "frames.csv", "\n".join(lines) + "\n")

    meta: dict[str, Any] = {
        "format": FORMAT,
        "kind": kind,
        "units": "mm",
        "camera": {"width": int(width), "height": int(height)},
    }
    if conv is not None:
        meta["rotation"] = conv.value
    if target is not None:
        meta["target"] = target_to_json(target)
    if extra:
        meta.update(extra)
    write_text_atomic(root / "session.json", json.dumps(meta, indent=2) + "\n")
    return root
