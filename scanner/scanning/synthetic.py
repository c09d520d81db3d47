"""Analytic stripe frames with known centres, for tests and benchmarks of the extractor.

Independent of the virtual cell: each segment is a Gaussian cross-section along the scan line
around a polynomial centre line, integrated exactly over each pixel's width (error functions)
and supersampled across lines, then shaded, clipped, noised and quantised like a camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import erf

__all__ = ["StripeSegment", "render_stripes"]


@dataclass(frozen=True)
class StripeSegment:
    """One stripe segment in working orientation (lines are rows, positions along u).

    Attributes
    ----------
    lines : (int, int)
        First line and one past the last line it covers.
    coeffs : (float, ...)
        Centre ``pos(line) = c0 + c1 * line + c2 * line**2 ...`` in pixels.
    amplitude : float
        Peak grey level above the background (before clipping); may exceed saturation.
    sigma_px : float
        Gaussian standard deviation of the cross-section along the line, pixels.
    """

    lines: tuple[int, int]
    coeffs: tuple[float, ...]
    amplitude: float = 180.0
    sigma_px: float = 1.5

    def centre(self, line: NDArray) -> NDArray:
        return np.polynomial.polynomial.polyval(np.asarray(line, dtype=np.float64), self.coeffs)


def render_stripes(
    shape: tuple[int, int],
    segments: Sequence[StripeSegment],
    *,
    background: float = 8.0,
    gradient_per_px: float = 0.0,
    noise: float = 1.0,
    dark: Sequence[tuple[int, int, float]] = (),
    lit_region: tuple[int, int, int, int, float] | None = None,
    dtype: type = np.uint8,
    full_scale: float = 255.0,
    orientation: str = "rows",
    supersample: int = 4,
    seed: int = 0,
) -> tuple[NDArray, list[tuple[NDArray, NDArray]]]:
    """Render a frame and the true centre of each segment on each of its lines.

    Parameters
    ----------
    shape : (H, W)
        Image size in the *working* orientation (rows are scan lines).
    segments : sequence of StripeSegment
    background, gradient_per_px : float
        Ambient level and its slope along the scan line (grey levels, grey levels per pixel).
    noise : float
        Standard deviation of additive Gaussian noise, grey levels.
    dark : sequence of (first_line, end_line, reflectance)
        Dark ink bands: the stripe's amplitude times ``reflectance`` on those lines.
    lit_region : (line0, line1, pos0, pos1, level), optional
        A lit rectangle (e.g. a printed target under ambient light) added to the background.
    orientation : {"rows", "cols"}
        ``"cols"`` transposes the rendered frame (the truth stays as ``(line, pos)``).

    Returns
    -------
    image : ndarray, shape (H, W) (or (W, H) for ``"cols"``)
    truth : list of (lines, pos) per segment, each ndarray shape (L,)
    """
    H, W = shape
    rng = np.random.default_rng(seed)
    u = np.arange(W, dtype=np.float64)
    img = np.full((H, W), float(background)) + gradient_per_px * (u[None, :] - W / 2)
    if lit_region is not None:
        l0, l1, p0, p1, level = lit_region
        img[l0:l1, p0:p1] += level
    gain = np.ones(H)
    for l0, l1, refl in dark:
        gain[l0:l1] = refl
    truth = []
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    for seg in segments:
        lines = np.arange(max(0, seg.lines[0]), min(H, seg.lines[1]))
        acc = np.zeros((lines.size, W))
        centres = np.zeros(lines.size)
        for s in sub:
            c = seg.centre(lines + s)
            centres += c / supersample
            z1 = (u[None, :] + 0.5 - c[:, None]) / (np.sqrt(2) * seg.sigma_px)
            z0 = (u[None, :] - 0.5 - c[:, None]) / (np.sqrt(2) * seg.sigma_px)
            # Pixel-integrated Gaussian scaled so that a centred pixel reads ~amplitude.
            acc += 0.5 * (erf(z1) - erf(z0)) / supersample
        peak_scale = erf(0.5 / (np.sqrt(2) * seg.sigma_px))
        img[lines] += seg.amplitude * gain[lines, None] * acc / peak_scale
        truth.append((lines, centres))
    img += rng.normal(0.0, noise, img.shape)
    img = np.clip(np.rint(img), 0, full_scale).astype(dtype)
    if orientation == "cols":
        img = np.ascontiguousarray(img.T)
    return img, truth
