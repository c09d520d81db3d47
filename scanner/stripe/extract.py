"""Laser stripe extraction: one profile of sub-pixel stripe centres per frame.

A *scan line* is one image row (``orientation="rows"``: the stripe runs top to bottom and each
row is searched along u) or one image column (``orientation="cols"``: the stripe runs left to
right and each column is searched along v). The orientation comes from the light plane's image
(:func:`orientation_from_calibration`) or from the image's gradients (``"auto"``).

Two estimators share one interface:

``fast``
    The per-line maximum (``argmax`` over the whole image at once), a window gathered around it
    with fancy indexing, a linear local background (from flank pixels on both sides)
    subtracted, and the centre of gravity of what remains (all of it linear in the window's
    pixels: one matrix product for every line of the frame). Peaks that run into the image border
    use the three-point Gaussian (log-parabola) estimator on a symmetric window, which a
    truncated window cannot bias.
``precise``
    Steger's line detector restricted to a small patch around each fast-mode centre: the
    Gaussian-smoothed image's gradient and Hessian evaluated *at* the fast estimate (kernels
    shifted by its sub-pixel offset), the stripe's cross direction from the Hessian's dominant
    eigenvector, the centre from the second-order Taylor model along it, then slid along the
    stripe back onto the scan line. The local background's slope (asymmetric profiles, a lit
    surface under the stripe) is subtracted from the gradient before the Taylor step.

Several genuine peaks per line are kept (an object and the table beside it can share image
lines): every local maximum above a contrast threshold set by the image noise and by the
line's brightest peak. A weaker peak whose chain of neighbouring-line peaks never appears
without a brighter companion is taken for a reflection and dropped; the survivors on those
lines carry :attr:`StripeFlag.AMBIGUOUS`.

The parts: :mod:`scanner.stripe.profile` (the result, its flags and options),
:mod:`scanner.stripe.orientation`, :mod:`scanner.stripe.estimates` (noise, window),
:mod:`scanner.stripe.fast` (with its compiled kernel, :mod:`scanner.stripe.kernels`),
:mod:`scanner.stripe.peaks` (several peaks per line, reflections),
:mod:`scanner.stripe.background` (an uneven background taken out of a frame without a
laser-off frame) and :mod:`scanner.stripe.precise`; :func:`extract_stripe` here puts them together.
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.images import check_gray_image
from scanner.stripe.background import take_out_uneven_background
from scanner.stripe.estimates import _median, auto_half_window, estimate_noise
from scanner.stripe.fast import _measure_many as _measure_many  # for benchmarks/bench_stripe.py
from scanner.stripe.fast import _saturation_level, flag_low_contrast
from scanner.stripe.orientation import orientation_from_calibration, orientation_from_image
from scanner.stripe.peaks import _primary_and_secondary, _resolve_multi, _stretch_ends
from scanner.stripe.precise import _curvature_shift, _refine_precise
from scanner.stripe.profile import (
    _FWHM_PER_SIGMA,
    MODES,
    ORIENTATIONS,
    StripeFlag,
    StripeOptions,
    StripeProfile,
)

__all__ = [
    "StripeFlag",
    "StripeOptions",
    "StripeProfile",
    "estimate_noise",
    "extract_stripe",
    "orientation_from_calibration",
    "orientation_from_image",
]

log = logging.getLogger(__name__)


def extract_stripe(
    image: NDArray,
    mode: str = "fast",
    orientation: str = "auto",
    background: NDArray | None = None,
    options: StripeOptions | None = None,
    **overrides: Any,
) -> StripeProfile:
    """Extract the laser stripe's sub-pixel centres from one frame.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8, uint16 or float
        The laser-on frame.
    mode : {"fast", "precise"}
        Windowed centre of gravity, or Steger's Hessian-based detector around it.
    orientation : {"auto", "rows", "cols"}
        ``"rows"``: each row is a scan line (stripe running top to bottom); ``"cols"``: each
        column is; ``"auto"``: from the image's gradients. Prefer
        :func:`orientation_from_calibration` once per sweep.
    background : ndarray, shape (H, W), optional
        A laser-off frame of the same pose: subtracted (clipped at zero) before the search.
        Without one, an uneven background is estimated from the frame and taken out
        (:attr:`StripeOptions.flatten_background`).
    options : StripeOptions, optional
        Thresholds and windows; keyword ``overrides`` replace single fields.

    Returns
    -------
    StripeProfile
        Every genuine peak of every scan line, with quality flags.

    Raises
    ------
    ValueError
        Unknown mode or orientation, a non-2-D image, or a background of another shape.
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
    if orientation not in ORIENTATIONS:
        raise ValueError(
            f"orientation: expected one of {', '.join(ORIENTATIONS)}, got {orientation!r}"
        )
    opts = options or StripeOptions()
    if overrides:
        opts = StripeOptions(**{**opts.__dict__, **overrides})
    img = check_gray_image(image, "image")
    if background is not None:
        bg = check_gray_image(background, "background")
        if bg.shape != img.shape:
            raise ValueError(f"background: expected the image's shape {img.shape}, got {bg.shape}")
        # A pixel saturated in the laser-on frame stays saturated after the subtraction: on
        # a bright background the laser's clipped plateau would otherwise become a flat
        # run below the saturation level, with spurious ridges all over its noisy top.
        level = _saturation_level(img, opts)
        saturated = img >= level
        if img.dtype in (np.uint8, np.uint16) and bg.dtype == img.dtype:
            img = cv2.subtract(img, bg)
        else:
            img = np.clip(img.astype(np.float32) - bg.astype(np.float32), 0, None)
        if np.isfinite(level) and saturated.any():
            img[saturated] = level
    # The rows' noise serves the background's test and, for row scan lines, the thresholds.
    row_noise = None
    if background is None and opts.flatten_background is None and opts.noise is None:
        row_noise = estimate_noise(img)
    flattened = False
    if background is None:
        img, flattened = take_out_uneven_background(img, opts, row_noise)
    if orientation == "auto":
        orientation = orientation_from_image(img)
    # Column scan lines: the transposed view, read in place by the kernels (copied only on the
    # rarer paths that need contiguous rows).
    work = img if orientation == "rows" else img.T
    if opts.noise is not None:
        noise = float(opts.noise)
    elif row_noise is not None and orientation == "rows" and not flattened:
        noise = row_noise
    else:
        noise = estimate_noise(work)

    hw = opts.half_window_px
    hw = auto_half_window(work, noise) if hw is None else int(hw)
    peaks, multi = _primary_and_secondary(work, opts, noise, hw)
    if multi:
        peaks = _resolve_multi(peaks, opts)
        multi = not np.all(peaks.line[1:] > peaks.line[:-1])
    if peaks.line.size == 0:
        empty = StripeProfile.empty(orientation, mode)
        return StripeProfile(
            empty.u,
            empty.v,
            empty.intensity,
            empty.width_px,
            empty.flags,
            empty.line,
            orientation,
            mode,
            noise,
        )
    if peaks.line.size >= 4:
        flag_low_contrast(
            peaks.contrast, peaks.flags, opts.low_contrast_ratio, StripeFlag.LOW_CONTRAST
        )

    if opts.end_lines > 0:  # (off by default)
        ends = _stretch_ends(peaks, opts.link_px, work.shape[0], int(opts.end_lines))
        if ends.any():
            peaks.flags[ends] |= np.uint8(StripeFlag.STRETCH_END)

    pos = peaks.pos
    across = peaks.line.astype(np.float64)
    if mode == "precise":
        if opts.sigma_px is not None:
            sigma = float(opts.sigma_px)
        else:
            sigma = float(np.clip(_median(peaks.width) / _FWHM_PER_SIGMA, 1.0, 3.0))
        pos, voff = _refine_precise(work, peaks, sigma)
        pos = pos - _curvature_shift(peaks, sigma, work.shape[0], opts.link_px)
        across = across + voff
    if multi:
        order = np.lexsort((pos, peaks.line))
        pos, across = pos[order], across[order]
        peaks = peaks.take(order)
    if orientation == "rows":
        u, v = pos, across
    else:
        u, v = across, pos
    return StripeProfile(
        u=np.ascontiguousarray(u, dtype=np.float64),
        v=np.ascontiguousarray(v, dtype=np.float64),
        intensity=peaks.peak.astype(np.float32, copy=False),
        width_px=peaks.width.astype(np.float32, copy=False),
        flags=peaks.flags.astype(np.uint8, copy=False),
        line=peaks.line.astype(np.int32),
        orientation=orientation,
        mode=mode,
        noise=noise,
        contrast=peaks.contrast.astype(np.float32, copy=False),
    )
