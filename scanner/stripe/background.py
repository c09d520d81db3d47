"""An uneven background taken out of a laser frame that has no laser-off frame.

The extractor's candidates clear one level for the whole frame (its sparse grid's median plus
the contrast threshold), and each scan line's primary peak is its brightest pixel. Both hold
where the background is nearly flat, as it is in a laser frame exposed for the laser. Ambient
light, vignetting or a lit part can make the background vary across the frame by more than a
faint stripe's contrast: its pixels then fall below the level where the background is dark,
and the brightest pixel of a line is the bright end of the background, not the stripe.

:func:`background_is_uneven` tells such a frame from its own sparse grid of pixels (the spread
between its 5th and 90th percentiles against the contrast threshold), and
:func:`flatten_background` subtracts a smooth estimate of the background (means over 32 px
blocks, the darkest block of each 5x5 neighbourhood, interpolated back to full size: a
stripe's tails reach its own block and the next, seldom the darkest block two blocks away on
its dark side, so it leaves next to no trace), keeping the darkest level as a pedestal so that the
noise is not clipped, and saturated pixels saturated. The estimate lags a shading's slope by
up to two blocks; the extractor's local linear background takes up what is left under the
stripe.

Laser frames of a lit printed target are no smooth shading: the calibration and the EF check
keep their frames as they are (their laser frames are taken with the ambient dimmed, or come
with a laser-off frame).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.stripe.estimates import estimate_noise
from scanner.stripe.fast import _saturation_level
from scanner.stripe.peaks import contrast_threshold
from scanner.stripe.profile import StripeOptions

__all__ = [
    "BLOCK_PX",
    "NEIGHBOURHOOD",
    "UNEVEN_RATIO",
    "background_is_uneven",
    "flatten_background",
    "take_out_uneven_background",
    "wants_flattening",
]

BLOCK_PX = 32
"""Side of the blocks the background is estimated on. With the darkest block of each 5x5
neighbourhood, a noise-free stripe on a ramp moves by at most 0.0001 px up to 3 px sigma,
0.011 px at 5 px and 0.024 px at 6 px (0.007-0.10 px with 16 px blocks and 3x3
neighbourhoods, which its tails reach through)."""

NEIGHBOURHOOD = 5
"""Blocks on a side of the neighbourhood whose darkest block is taken."""

UNEVEN_RATIO = 2.0
"""A background whose spread exceeds this many contrast thresholds is taken out. The virtual
cell's laser frames reach 0.52-0.65 (sweeps) and 1.1-1.6 (lit targets) and are left as they
are."""


def take_out_uneven_background(
    image: NDArray, options: StripeOptions, noise: float | None = None
) -> tuple[NDArray, bool]:
    """The frame as the extractor searches it, without a laser-off frame: with its background
    taken out where ``options.flatten_background`` says so (``None``: where the frame's own
    background is uneven against the contrast threshold of its noise).

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8, uint16 or float32, C-contiguous
    options : StripeOptions
    noise : float, optional
        The frame's noise (grey levels) where the caller has it; otherwise ``options.noise``
        or :func:`~scanner.stripe.estimates.estimate_noise` of ``image``.

    Returns
    -------
    frame : ndarray, shape (H, W), same dtype
        ``image`` itself, or :func:`flatten_background` of it.
    flattened : bool
        Whether the background was taken out.
    """
    if not wants_flattening(image, options, noise):
        return image, False
    return flatten_background(image, _saturation_level(image, options)), True


def wants_flattening(image: NDArray, options: StripeOptions, noise: float | None = None) -> bool:
    """Whether :func:`take_out_uneven_background` takes the background out of ``image``: as
    ``options.flatten_background`` says, or (``None``) where :func:`background_is_uneven`
    against the contrast threshold of the frame's noise (``noise``, else ``options.noise``,
    else estimated)."""
    if options.flatten_background is not None:
        return bool(options.flatten_background)
    if noise is None:
        noise = float(options.noise) if options.noise is not None else estimate_noise(image)
    level = _saturation_level(image, options)
    return background_is_uneven(image, contrast_threshold(image, options, noise, level))


def background_spread(image: NDArray) -> float:
    """The spread of the frame's background, grey levels: the 90th minus the 5th percentile of
    a grid of about 32 x 32 pixels (a stripe covers a few per cent of it at most: 6 px of a
    320 px line are 2 %; a linear ramp's spread is 85 % of its range).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The frame (any orientation; a view is fine).
    """
    h, w = image.shape
    grid = np.array(image[:: max(1, h // 32), :: max(1, w // 32)]).ravel()
    # The two order statistics by one partition (np.percentile costs ten times as much).
    lo, hi = int(0.05 * (grid.size - 1)), int(0.90 * (grid.size - 1))
    part = np.partition(grid, (lo, hi))
    return float(part[hi]) - float(part[lo])


def background_is_uneven(image: NDArray, contrast_threshold: float) -> bool:
    """Whether the frame's background varies by more than :data:`UNEVEN_RATIO` times
    ``contrast_threshold`` (the smallest stripe contrast the extractor accepts, grey levels)."""
    return background_spread(image) > UNEVEN_RATIO * contrast_threshold


def flatten_background(image: NDArray, saturation: float) -> NDArray:
    """``image`` with its smooth background taken out down to its darkest level.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8, uint16 or float32, C-contiguous
        A laser frame without a laser-off frame.
    saturation : float
        The grey level counted as saturated (``inf`` for float frames): pixels at or above it
        stay at it.

    Returns
    -------
    ndarray, shape (H, W), same dtype
        ``image - (background - min(background))`` (an 8- or 16-bit frame clipped at zero);
        never brighter than ``image``.
    """
    h, w = image.shape
    small = cv2.resize(
        image, (max(1, w // BLOCK_PX), max(1, h // BLOCK_PX)), interpolation=cv2.INTER_AREA
    )
    small = cv2.erode(small, np.ones((NEIGHBOURHOOD, NEIGHBOURHOOD), np.uint8))
    small = small - small.min()
    background = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if image.dtype in (np.uint8, np.uint16):
        flat = cv2.subtract(image, background)  # saturates at 0: under the pedestal only
    else:
        flat = (image - background).astype(image.dtype, copy=False)
    if np.isfinite(saturation):
        saturated = image >= saturation
        if saturated.any():
            flat[saturated] = saturation
    return flat
