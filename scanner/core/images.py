"""Images in and grey levels out: the one place a frame is read and converted to grey.

Every stage reads its images through here: a target image as its luminance, a laser image as
the laser's grey level (:func:`laser_gray`, a laser-off frame reduced like its laser frame),
and detectors work on :func:`to_gray_float` of what was read.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.fileio import InputError

__all__ = [
    "CLIPPED_COLOUR_PIXELS_PER_SIDE",
    "check_gray_image",
    "image_size",
    "laser_gray",
    "load_gray_image",
    "load_laser_images",
    "to_gray_float",
]


def image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """``(width, height)`` of an image, from the PNG header when possible (no decoding).

    Raises
    ------
    InputError
        The file is missing or not a readable image.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(24)
    except OSError as exc:
        raise InputError(p, f"cannot read image ({exc.strerror or exc})") from None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(p, "not a readable image (expected PNG, TIFF or JPEG)")
    return int(img.shape[1]), int(img.shape[0])


#: A colour laser frame is read as the mean of its channels once more of its pixels than this
#: fraction of its longer side have one channel, not all, at the maximum (a line clipped over
#: a tenth of its length, say): see :func:`laser_gray`.
CLIPPED_COLOUR_PIXELS_PER_SIDE = 0.1


def _read_image(path: str | os.PathLike[str]) -> NDArray:
    """The image at ``path`` as stored: 2-D grey or ``(H, W, 3)`` BGR, 8 or 16 bit."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "image file not found")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(p, "not a readable image (expected PNG, TIFF or JPEG)")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(p, f"expected an 8- or 16-bit image, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return img


def laser_gray(image: NDArray, reduction: str | None = None) -> tuple[NDArray, str]:
    """The laser's grey level of a laser frame, and how a colour frame was reduced.

    A colour camera's laser channel clips first: a red line on a white card is flat at the
    maximum over 10-20 px of red halo, and JPEG noise on that plateau gives several ridges
    per line. Where the laser channel clips, the other channels still rise to the line's
    white core, so the mean of the channels clips only where all three do, at the core.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        8- or 16-bit; a grey image is returned as is.
    reduction : {"max", "mean"} or None
        ``"max"``: the brightest channel per pixel (the laser's own channel, whatever its
        colour: best signal to noise while it does not clip). ``"mean"``: the mean of the
        channels, in the image's dtype (it dilutes a dim line: about a third of the laser
        channel's contrast for a red line). ``None``: ``"mean"`` when more pixels than
        :data:`CLIPPED_COLOUR_PIXELS_PER_SIDE` times the image's longer side have one
        channel, not all, at the dtype's maximum, else ``"max"``. Give a laser-off frame the
        reduction of its laser-on frame, so that the subtraction compares like with like.

    Returns
    -------
    gray : ndarray, shape (H, W)
        Same dtype as ``image``.
    reduction : str
        ``"gray"`` for a grey image, else the reduction used.
    """
    if image.ndim == 2:
        return image, "gray"
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected (H, W) or (H, W, 3), got shape {image.shape}")
    if reduction not in (None, "max", "mean"):
        raise ValueError(f"reduction: expected 'max', 'mean' or None, got {reduction!r}")
    brightest = image.max(axis=2) if reduction != "mean" else None
    if reduction is None:
        top = np.iinfo(image.dtype).max
        one_clipped = np.count_nonzero((brightest >= top) & (image.min(axis=2) < top))
        clipped = one_clipped > CLIPPED_COLOUR_PIXELS_PER_SIDE * max(image.shape[:2])
        reduction = "mean" if clipped else "max"
    if reduction == "max":
        return brightest, reduction  # type: ignore[return-value]
    total = image.astype(np.uint32).sum(axis=2)
    return ((total + 1) // 3).astype(image.dtype), reduction


def load_gray_image(path: str | os.PathLike[str], laser: bool = False) -> NDArray:
    """Load an 8- or 16-bit image as a 2-D grey array of its original dtype.

    A colour image is reduced to one grey level per pixel: for a laser image the laser's
    grey level (:func:`laser_gray`), for a target image the luminance. A laser frame with a
    laser-off frame is read with :func:`load_laser_images`, which reduces both alike.

    Raises
    ------
    InputError
        The file is missing, unreadable or of an unsupported depth.
    """
    img = _read_image(path)
    if img.ndim == 3:
        img = laser_gray(img)[0] if laser else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


def load_laser_images(
    laser_path: str | os.PathLike[str], laser_off_path: str | os.PathLike[str] | None = None
) -> tuple[NDArray, NDArray | None]:
    """A laser frame and its laser-off frame (or ``None``) as the laser's grey level.

    A colour pair is reduced the same way, as the laser-on frame decides (:func:`laser_gray`).

    Raises
    ------
    InputError
        Either file is missing, unreadable, of an unsupported depth, or the two differ in
        size or colour.
    """
    on, reduction = laser_gray(_read_image(laser_path))
    if laser_off_path is None:
        return on, None
    off_raw = _read_image(laser_off_path)
    if off_raw.ndim != (2 if reduction == "gray" else 3):
        raise InputError(laser_off_path, f"colour differs from its laser frame {laser_path}")
    off = laser_gray(off_raw, None if reduction == "gray" else reduction)[0]
    if off.shape != on.shape:
        raise InputError(
            laser_off_path,
            f"expected the size of its laser frame {on.shape[1]}x{on.shape[0]}, "
            f"got {off.shape[1]}x{off.shape[0]}",
        )
    return on, off


def to_gray_float(image: NDArray) -> NDArray:
    """A 2-D float64 copy of an 8/16-bit or float grey (or BGR colour) image, in [0, 1]."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        w = np.array([0.114, 0.587, 0.299])  # BGR luminance
        img = img[..., :3].astype(np.float64) @ w
        scale = 65535.0 if image.dtype == np.uint16 else 255.0 if image.dtype == np.uint8 else 1.0
        return img / scale
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D grey image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float64) / 65535.0
    out = img.astype(np.float64)
    if not np.all(np.isfinite(out)):
        raise ValueError("image: expected finite values, got NaN or inf")
    return out


def check_gray_image(image: NDArray, name: str) -> NDArray:
    """A 2-D grey frame, checked, as a C-contiguous array (float64 converted to float32).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        uint8, uint16, float32 or float64, at least 8x8 pixels.
    name : str
        What the image is, to name it in the error (``"image"``, ``"background"``).

    Returns
    -------
    ndarray, shape (H, W)
        The image itself when it is already C-contiguous and not float64.

    Raises
    ------
    ValueError
        Not 2-D, of another dtype, or smaller than 8x8 pixels.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D grey image (H, W), got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise ValueError(f"{name}: expected uint8, uint16 or float image, got {img.dtype}")
    if img.shape[0] < 8 or img.shape[1] < 8:
        raise ValueError(f"{name}: expected at least 8x8 pixels, got {img.shape[1]}x{img.shape[0]}")
    if img.dtype == np.float64:
        img = img.astype(np.float32)
    return np.ascontiguousarray(img)
