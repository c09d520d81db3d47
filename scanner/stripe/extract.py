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
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from enum import IntFlag
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

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

MODES = ("fast", "precise")
ORIENTATIONS = ("auto", "rows", "cols")
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


class StripeFlag(IntFlag):
    """Quality bits of one stripe point (``StripeProfile.flags``)."""

    NONE = 0
    SATURATED = 1
    """The peak reached the saturation level; the centre is that of the saturated run."""
    AMBIGUOUS = 2
    """The line showed another candidate peak (a reflection was dropped, or two peaks merged)."""
    LOW_CONTRAST = 4
    """Contrast well below the frame's typical stripe (dark surface, grazing angle)."""
    BORDER = 8
    """The estimator's window reached the image border; a border-safe estimator was used."""
    SECONDARY = 16
    """Not the brightest peak of its line: another stripe segment sharing the line."""


@dataclass(frozen=True)
class StripeOptions:
    """Tuning of :func:`extract_stripe`; the defaults suit 8-bit frames of a 1-4 px wide stripe.

    Attributes
    ----------
    half_window_px : int or None
        Half-width of the centre-of-gravity window (fast mode); ``None``: about 2.7 sigma of
        the stripe, measured on a subset of lines (the noise-optimal width for a Gaussian).
    sigma_px : float or None
        Smoothing scale of the precise mode; ``None``: from the stripe width, clipped to 1..3 px.
    k_noise : float
        A peak needs a contrast above ``k_noise`` times the image noise (standard deviation).
    min_contrast : float or None
        Absolute minimum contrast (grey levels); ``None``: 3 % of the saturation level.
    min_relative_peak : float
        A further peak on a line needs this fraction of the line's brightest contrast.
    saturation : float or None
        Grey level counted as saturated; ``None``: the dtype's maximum (255, 65535).
    noise : float or None
        Image noise (grey levels); ``None``: estimated from pixel differences.
    background_level : float or None
        Typical background grey level for the candidate threshold; ``None``: the median of a
        sparse grid of pixels.
    link_px : float
        Peaks on neighbouring lines closer than this along the line belong to one segment.
    reflection_ratio : float
        A segment that never stands alone and stays below this fraction of its brighter
        companion's contrast is a reflection.
    low_contrast_ratio : float
        Contrast below this fraction of the frame's median stripe contrast sets LOW_CONTRAST.
    keep_reflections : bool
        Keep the peaks judged to be reflections (flagged AMBIGUOUS) instead of dropping them.
    """

    half_window_px: int | None = None
    sigma_px: float | None = None
    k_noise: float = 6.0
    min_contrast: float | None = None
    min_relative_peak: float = 0.15
    saturation: float | None = None
    noise: float | None = None
    background_level: float | None = None
    link_px: float = 3.0
    reflection_ratio: float = 0.6
    low_contrast_ratio: float = 0.25
    keep_reflections: bool = False

    def __post_init__(self) -> None:
        if self.half_window_px is not None and int(self.half_window_px) < 2:
            raise ValueError(f"half_window_px: expected >= 2, got {self.half_window_px}")
        if self.sigma_px is not None and not 0.5 <= float(self.sigma_px) <= 10.0:
            raise ValueError(f"sigma_px: expected 0.5..10 px or None, got {self.sigma_px}")
        if self.k_noise <= 0:
            raise ValueError(f"k_noise: expected > 0, got {self.k_noise}")
        if not 0.0 <= self.min_relative_peak <= 1.0:
            raise ValueError(f"min_relative_peak: expected 0..1, got {self.min_relative_peak}")


@dataclass(frozen=True)
class StripeProfile:
    """Stripe centres of one frame: ``N`` points, each a 1-D array of length ``N``.

    Attributes
    ----------
    u, v : ndarray, shape (N,), float64
        Sub-pixel centre, OpenCV pixel convention (u column, v row).
    intensity : ndarray, shape (N,), float32
        Peak grey level (background not subtracted).
    width_px : ndarray, shape (N,), float32
        Stripe width along the scan line (FWHM-equivalent of the windowed second moment).
    flags : ndarray, shape (N,), uint8
        :class:`StripeFlag` bits.
    line : ndarray, shape (N,), int32
        Scan-line index: the row (``orientation == "rows"``) or column (``"cols"``).
    orientation, mode : str
        How the frame was scanned and which estimator ran.
    noise : float
        Image noise estimate used for the thresholds (grey levels).
    """

    u: NDArray
    v: NDArray
    intensity: NDArray
    width_px: NDArray
    flags: NDArray
    line: NDArray
    orientation: str = "rows"
    mode: str = "fast"
    noise: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.u.shape[0])

    @property
    def uv(self) -> NDArray:
        """``(N, 2)`` pixel coordinates."""
        return np.column_stack([self.u, self.v])

    def select(self, mask: NDArray) -> StripeProfile:
        """The points where ``mask`` (shape (N,) bool) is true."""
        return StripeProfile(
            self.u[mask],
            self.v[mask],
            self.intensity[mask],
            self.width_px[mask],
            self.flags[mask],
            self.line[mask],
            self.orientation,
            self.mode,
            self.noise,
        )

    @classmethod
    def empty(cls, orientation: str = "rows", mode: str = "fast") -> StripeProfile:
        f = np.zeros(0)
        return cls(
            f,
            f.copy(),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
            np.zeros(0, np.uint8),
            np.zeros(0, np.int32),
            orientation,
            mode,
        )


# --------------------------------------------------------------------------------------------
# orientation


def orientation_from_calibration(calibration: Any, depth_mm: float | None = None) -> str:
    """Scan orientation from the light plane's image: ``"rows"`` when its line runs top-bottom.

    The light plane is cut with a fronto-parallel plane at ``depth_mm`` (default: where the
    plane crosses the optical axis, or 300 mm) and the cut is projected through the intrinsics.

    Parameters
    ----------
    calibration : scanner.formats.calibration_file.Calibration
        Needs ``K``, ``width``, ``height`` and ``light_plane`` (``normal . p + d = 0``, camera).
    """
    n = np.asarray(calibration.light_plane.normal, dtype=np.float64)
    d = float(calibration.light_plane.d)
    if depth_mm is None:
        depth_mm = -d / n[2] if abs(n[2]) > 1e-9 and -d / n[2] > 0 else 300.0
    # The cut is the line {p: n.p + d = 0, z = depth}: its direction is n x z_axis.
    direction = np.cross(n, [0.0, 0.0, 1.0])
    if np.linalg.norm(direction) < 1e-9:  # plane facing the camera: every line looks the same
        return "rows"
    K = np.asarray(calibration.K, dtype=np.float64)
    # Image direction of a 3-D direction in the plane z = depth: K[:2,:2] @ direction[:2].
    du, dv = K[:2, :2] @ direction[:2]
    return "rows" if abs(dv) >= abs(du) else "cols"


def orientation_from_image(image: NDArray) -> str:
    """``"rows"`` when the bright stripe runs top-bottom (its gradients point along u)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D grey image, got shape {img.shape}")
    small = img[::2, ::2].astype(np.float32)
    gu = np.abs(np.diff(small, axis=1)).sum()
    gv = np.abs(np.diff(small, axis=0)).sum()
    return "rows" if gu >= gv else "cols"


# --------------------------------------------------------------------------------------------
# noise


def _median(values: NDArray) -> float:
    """Median: of 8/16-bit values the lower middle one, of floats as :func:`numpy.median`.

    Small samples by partitioning, large 8-bit ones by histogram (several times faster).
    """
    v = np.asarray(values).reshape(-1)
    if 0 < v.size <= 4096 and v.dtype in (np.uint8, np.uint16):  # lower median, as below
        k = (v.size - 1) // 2
        return float(np.partition(v, k)[k])
    if v.dtype.kind == "f" and v.size:  # as np.median: the two middle values' mean
        k = v.size // 2
        if v.size % 2:
            return float(np.partition(v, k)[k])
        part = np.partition(v, (k - 1, k))
        return 0.5 * (float(part[k - 1]) + float(part[k]))
    if v.dtype == np.uint8 and v.size < 2**24:  # float32 counts stay exact
        # One row: OpenCV takes a 1-D array for a column, pixel by pixel (twice as slow).
        counts = cv2.calcHist([v.reshape(1, -1)], [0], None, [256], [0, 256]).reshape(-1)
        return float(np.searchsorted(np.cumsum(counts), (v.size + 1) // 2))
    if v.dtype in (np.uint8, np.uint16) and v.size:
        counts = np.bincount(v, minlength=1)
        return float(np.searchsorted(np.cumsum(counts), (v.size + 1) // 2))
    return float(np.median(v))


def estimate_noise(image: NDArray, step: int = 32) -> float:
    """Robust standard deviation of the image noise, grey levels (at least 0.5).

    From the median absolute difference of horizontally adjacent pixels on every ``step``-th
    row, which smooth shading and a thin stripe barely touch.
    """
    rows = np.asarray(image)[::step]
    if rows.dtype in (np.uint8, np.uint16):
        diff = cv2.absdiff(rows[:, 1:], rows[:, :-1])  # |a - b| without a wider dtype
    else:
        diff = np.abs(np.diff(rows.astype(np.float32), axis=1))
    mad = _median(diff)
    return max(0.5, 1.4826 * mad / np.sqrt(2.0))


# --------------------------------------------------------------------------------------------
# fast mode: windowed centre of gravity


def _saturation_level(img: NDArray, options: StripeOptions) -> float:
    if options.saturation is not None:
        return float(options.saturation)
    if img.dtype == np.uint8:
        return 255.0
    if img.dtype == np.uint16:
        return 65535.0
    return float("inf")


@dataclass
class _Peaks:
    """Peaks in the working orientation (lines are rows, positions along axis 1)."""

    line: NDArray  # (M,) int
    pos: NDArray  # (M,) float64 centre along the line
    peak: NDArray  # (M,) float32 peak grey level
    contrast: NDArray  # (M,) float32 peak minus local background
    width: NDArray  # (M,) float32
    flags: NDArray  # (M,) uint8
    slope: NDArray  # (M,) float32 local background slope along the line (grey/px)

    def take(self, idx: NDArray) -> _Peaks:
        return _Peaks(*(getattr(self, k)[idx] for k in _Peaks.__dataclass_fields__))

    @staticmethod
    def concat(parts: list[_Peaks]) -> _Peaks:
        return _Peaks(
            *(np.concatenate([getattr(p, k) for p in parts]) for k in _Peaks.__dataclass_fields__)
        )


def _measure(
    img: NDArray,
    lines: NDArray,
    cols: NDArray,
    hw: int,
    sat: float,
    count_above: float | None = None,
    typical: float | None = None,
) -> tuple[_Peaks, NDArray | None]:
    """Centre of gravity around integer peak columns ``cols`` on ``lines`` (vectorised).

    Returns the peaks and, when ``count_above`` is given, how many window pixels exceed it.
    ``typical``: the batch's typical width (windows wider than 1.3 times it are searched for a
    second maximum); ``None``: the median width of this batch.
    """
    W = img.shape[1]
    flat = img.reshape(-1)
    off = np.arange(-hw - 2, hw + 3)
    c = cols[:, None] + off
    near = np.flatnonzero((cols < hw + 2) | (cols >= W - hw - 2))
    if near.size:
        inside_near = (c[near] >= 0) & (c[near] < W)
        np.clip(c, 0, W - 1, out=c)
    idx = c
    idx += (lines * W)[:, None]
    vals = flat.take(idx)
    vals = vals.astype(np.float32)
    ones = np.ones(2 * hw + 1, np.float32)
    counts = None
    if count_above is not None:
        counts = (vals[:, 2:-2] > count_above).astype(np.float32) @ ones
    peak = vals[:, hw + 2].copy()

    # Linear background from two flank pixels each side (a missing side: the other one, flat).
    left = 0.5 * (vals[:, 0] + vals[:, 1])
    right = 0.5 * (vals[:, -1] + vals[:, -2])
    if near.size:
        lf_ok = inside_near[:, 0] & inside_near[:, 1]
        rf_ok = inside_near[:, -1] & inside_near[:, -2]
        ln, rn = left[near], right[near]
        left[near] = np.where(lf_ok, ln, rn)
        right[near] = np.where(rf_ok, rn, ln)
    xc = off[2:-2].astype(np.float32)
    slope = (right - left) * np.float32(1.0 / (2 * hw + 3))
    mean = 0.5 * (left + right)
    w = vals[:, 2:-2]
    w -= mean[:, None]
    w -= slope[:, None] * xc[None, :]
    border = np.zeros(len(cols), bool)
    if near.size:
        # Symmetric window about the peak pixel where the border cuts it.
        core_in = inside_near[:, 2:-2]
        sym_near = core_in & core_in[:, ::-1]
        w[near] = np.where(sym_near, w[near], 0.0)
        border[near] = ~np.all(core_in, axis=1)
    contrast = peak - mean

    sw = w @ ones
    ok = sw > 0
    safe = np.where(ok, sw, 1.0)
    mu = (w @ xc) / safe
    var = (w @ (xc * xc)) / safe - mu * mu
    width = _FWHM_PER_SIGMA * np.sqrt(np.maximum(var, 0.0))
    pos = cols + mu.astype(np.float64)
    flags = np.zeros(len(cols), np.uint8)

    # A second maximum inside the window (a reflection or another segment a few pixels away)
    # would pull the centre of gravity between the two: measure those on the peak alone. Only
    # windows wider than usual can hold two maxima, so only those are searched.
    double = np.zeros(len(cols), bool)
    if len(cols) > 2 or typical is not None:
        if typical is None:
            typical = np.partition(width, width.size // 2)[width.size // 2]
        wide = np.flatnonzero(width > 1.3 * typical)
        if wide.size:
            ww = w[wide]
            inner = ww[:, 1:-1]
            level = (0.3 * np.maximum(contrast[wide], 0.0))[:, None]
            local_max = (inner > ww[:, :-2]) & (inner >= ww[:, 2:]) & (inner > level)
            double[wide] = np.count_nonzero(local_max, axis=1) > 1
    else:
        inner = w[:, 1:-1]
        level = (0.3 * np.maximum(contrast, 0.0))[:, None]
        local_max = (inner > w[:, :-2]) & (inner >= w[:, 2:]) & (inner > level)
        double = np.count_nonzero(local_max, axis=1) > 1
    if np.any(double):
        flags[double] |= np.uint8(StripeFlag.AMBIGUOUS)

    use3 = border | double
    if np.any(use3):
        # Three-point Gaussian (log-parabola) on background-subtracted values: unbiased for a
        # Gaussian profile whatever the window, needs only the two neighbours.
        b = np.flatnonzero(use3)
        k = hw  # index of the peak pixel inside w
        a0 = w[b, k - 1].astype(np.float64)
        a1 = w[b, k].astype(np.float64)
        a2 = w[b, k + 1].astype(np.float64)
        good = (a0 > 0) & (a1 > 0) & (a2 > 0)
        la0, la1, la2 = (np.log(np.where(good, a, 1.0)) for a in (a0, a1, a2))
        den = la0 - 2 * la1 + la2
        delta = np.where(good & (den < 0), 0.5 * (la0 - la2) / np.where(den < 0, den, -1.0), 0.0)
        pos[b] = np.where(good & (np.abs(delta) <= 1.0), cols[b] + delta, pos[b])
        flags[b[border[b]]] |= np.uint8(StripeFlag.BORDER)

    saturated = peak >= sat
    if np.any(saturated):
        s_idx = np.flatnonzero(saturated)
        pos[s_idx], width[s_idx] = _saturated_centres(img, lines[s_idx], cols[s_idx], sat)
        flags[s_idx] |= np.uint8(StripeFlag.SATURATED)
    contrast = np.where(ok, contrast, 0.0).astype(np.float32)
    peaks = _Peaks(
        lines.astype(np.int64, copy=False),
        pos,
        peak,
        contrast,
        width.astype(np.float32),
        flags,
        slope,
    )
    return peaks, counts


@functools.lru_cache(maxsize=32)
def _window_matrix(hw: int) -> NDArray:
    """``(6, 2 hw + 5)`` rows giving, from a window's pixels, quantities linear in them.

    Peak pixel; contrast (peak minus the linear background's level at the peak); background
    slope; and the background-subtracted window's sum and first and second moments about the
    peak pixel (``x = -hw..hw``). The background is the line through the means of the two
    flank pixels on each side (at ``x = -/+ (hw + 1.5)``).
    """
    n = 2 * hw + 5
    x = np.arange(-hw, hw + 1, dtype=np.float64)
    left = np.zeros(n)
    left[:2] = 0.5
    right = left[::-1]
    mean = 0.5 * (left + right)
    slope = (right - left) / (2 * hw + 3)
    core = np.zeros(n)
    core[2:-2] = 1.0
    peak = np.zeros(n)
    peak[hw + 2] = 1.0
    xw = np.zeros(n)
    xw[2:-2] = x
    x2 = float(np.sum(x * x))
    m = np.stack(
        [
            peak,
            peak - mean,
            slope,
            core - (2 * hw + 1) * mean,  # sum x^0 (w - mean - slope x); sum x = 0
            xw - x2 * slope,  # sum x (w - mean - slope x)
            xw * xw - x2 * mean,  # sum x^2 (w - mean - slope x); sum x^3 = 0
        ]
    ).astype(np.float32)
    m.flags.writeable = False
    return m


def _row_windows(img: NDArray, size: int, length: int | None = None) -> NDArray:
    """Every run of ``size`` consecutive pixels of the flat image, as rows of a view."""
    flat = img.reshape(-1)
    rows = flat.size - size + 1 if length is None else length
    step = flat.strides[0]
    return np.ndarray((rows, size), flat.dtype, flat, 0, (step, step))


def _measure_many(
    img: NDArray,
    lines: NDArray,
    cols: NDArray,
    hw: int,
    sat: float,
    clear: NDArray | None = None,
    typical: float | None = None,
) -> _Peaks:
    """:func:`_measure` for a whole frame's peaks, the common case by one matrix product.

    The background-subtracted centre of gravity's sums are linear in the window's pixels, so
    those of every peak come from one product of the gathered windows with a fixed matrix
    (:func:`_window_matrix`). The uncommon peaks (a window reaching the border, saturation, a
    window wider than usual that may hold two maxima) are measured again by :func:`_measure`,
    with the same typical width, and replace those. ``clear``: an array of the image's shape
    whose pixels in each peak's window ``cols - hw .. cols + hw`` (clipped to the image) are
    set to 0. ``typical``: the typical width; ``None``: the median over the windows inside the
    image.
    """
    n = cols.size
    W = img.shape[1]
    if n <= 2 or W < 2 * hw + 5:
        if clear is not None:
            _clear_windows(clear, lines, cols, hw)
        return _measure(img, lines, cols, hw, sat)[0]
    # Windows reaching past the border (two reductions decide the common case: none).
    any_near = bool(cols.min() < hw + 2 or cols.max() > W - hw - 3)
    near = (cols < hw + 2) | (cols > W - hw - 3) if any_near else None
    start = lines * W + (np.clip(cols, hw + 2, W - hw - 3) if any_near else cols)
    start -= hw + 2
    vals = _row_windows(img, 2 * hw + 5)[start]  # one gather of n runs of pixels
    if clear is not None:
        if any_near:
            _clear_windows(clear, lines, cols, hw)
        else:
            _row_windows(clear, 2 * hw + 1)[start + 2] = 0  # cols - hw .. cols + hw
    # float32 product: exact for 8-bit frames (integer sums below 2**24).
    res = _window_matrix(hw) @ vals.T.astype(np.float32)
    peak, contrast, slope, s0 = res[0], res[1], res[2], res[3]
    if not s0.min() > 0:  # also when NaN
        ok = s0 > 0
        s0 = np.where(ok, s0, np.float32(1.0))
        contrast[~ok] = 0.0
    mu, var = res[4:] / s0
    var -= mu * mu
    np.maximum(var, 0.0, out=var)
    width = np.sqrt(var, out=var)
    width *= np.float32(_FWHM_PER_SIGMA)
    if typical is None:
        far_w = width[~near] if any_near else width
        if far_w.size == 0:
            return _measure(img, lines, cols, hw, sat)[0]
        typical = float(np.partition(far_w, far_w.size // 2)[far_w.size // 2])
    odd = width > 1.3 * typical
    if peak.max() >= sat:
        odd |= peak >= sat
    if any_near:
        odd |= near
    peaks = _Peaks(
        lines.astype(np.int64, copy=False),
        cols + mu,
        peak,
        contrast,
        width,
        np.zeros(n, np.uint8),
        slope,
    )
    if odd.any():
        special = np.flatnonzero(odd)
        sub, _ = _measure(img, lines[special], cols[special], hw, sat, typical=typical)
        for k in _Peaks.__dataclass_fields__:
            getattr(peaks, k)[special] = getattr(sub, k)
    return peaks


def _clear_windows(clear: NDArray, lines: NDArray, cols: NDArray, hw: int) -> None:
    W = clear.shape[1]
    c = np.clip(cols[:, None] + np.arange(-hw, hw + 1), 0, W - 1)
    clear.reshape(-1)[c + (lines * W)[:, None]] = 0


def _saturated_centres(
    img: NDArray, lines: NDArray, cols: NDArray, sat: float, reach: int = 24
) -> tuple[NDArray, NDArray]:
    """Centre of the saturated run through ``cols`` and the run's length.

    The run's midpoint is refined with the unsaturated flanks: the logarithm of a Gaussian is a
    parabola, fitted by weighted least squares (weights ``w**2``, Caruana's weighting) to the
    unsaturated pixels above 5 % of the saturation contrast on both sides, and its vertex taken.
    Where that fit is not possible (one flank missing, a flat profile), the midpoint stays.
    """
    W = img.shape[1]
    off = np.arange(-reach, reach + 1)
    c = cols[:, None] + off
    inside = (c >= 0) & (c < W)
    vals = img.reshape(-1).take(lines[:, None] * W + np.clip(c, 0, W - 1)).astype(np.float64)
    vals = np.where(inside, vals, -np.inf)
    on = vals >= sat
    mid = reach
    # Run length to the right and to the left of the peak pixel (cumulative product trick).
    n_right = np.cumprod(on[:, mid:], axis=1).sum(axis=1) - 1
    n_left = np.cumprod(on[:, mid::-1], axis=1).sum(axis=1) - 1
    a = mid - n_left  # first saturated index
    b = mid + n_right  # last saturated index
    centre = 0.5 * (a + b)
    run = (b - a + 1).astype(np.float64)

    # Background: the lower of the mean levels at the window's two ends (inside the image).
    ends = []
    for sl in (slice(0, 6), slice(-6, None)):
        fin = inside[:, sl]
        n_fin = fin.sum(axis=1)
        level = np.where(fin, vals[:, sl], 0.0).sum(axis=1) / np.maximum(n_fin, 1)
        ends.append(np.where(n_fin > 0, level, np.inf))
    bg = np.minimum(ends[0], ends[1])
    bg = np.where(np.isfinite(bg), bg, 0.0)
    w = vals - bg[:, None]
    x = off[None, :].astype(np.float64)
    # Flank pixels: unsaturated, inside, above 5 % of the contrast, within 3 run-lengths + 4 px.
    span = (3 * run + 4)[:, None]
    dist = np.abs(x - (centre - mid)[:, None])
    use = np.isfinite(vals) & ~on & (w > 0.05 * (sat - bg)[:, None]) & (dist <= span)
    left_n = np.count_nonzero(use & (x < (a - mid)[:, None]), axis=1)
    right_n = np.count_nonzero(use & (x > (b - mid)[:, None]), axis=1)
    wt = np.where(use, np.maximum(w, 1e-9) ** 2, 0.0)
    y = np.log(np.maximum(w, 1e-9))
    xc = x - (centre - mid)[:, None]  # centred for conditioning
    m = np.empty((len(cols), 3, 3))
    r = np.empty((len(cols), 3))
    sums = []
    term = wt
    for k in range(5):  # sum w x^k, k = 0..4: the normal equations' distinct entries
        if k:
            term = term * xc
        sums.append(term.sum(axis=1))
    for i in range(3):
        for j in range(3):
            m[:, i, j] = sums[i + j]
    wy = wt * y
    r[:, 0] = wy.sum(axis=1)
    r[:, 1] = (wy * xc).sum(axis=1)
    r[:, 2] = (wy * xc * xc).sum(axis=1)
    fit_ok = (left_n >= 1) & (right_n >= 1) & (left_n + right_n >= 3)
    refined = centre.copy()
    if np.any(fit_ok):
        k = np.flatnonzero(fit_ok)
        det = np.linalg.det(m[k])
        good = np.abs(det) > 1e-12
        coef = np.zeros((k.size, 3))
        coef[good] = np.linalg.solve(m[k][good], r[k][good][:, :, None])[:, :, 0]
        c2 = coef[:, 2]
        vertex = np.where(c2 < 0, -coef[:, 1] / (2 * np.where(c2 < 0, c2, -1.0)), np.nan)
        plausible = good & np.isfinite(vertex) & (np.abs(vertex) <= 0.5 * run[k] + 0.5)
        refined[k] = np.where(plausible, centre[k] + vertex, centre[k])
    return cols + refined - mid, run


def auto_half_window(img: NDArray, noise: float, step: int = 16) -> int:
    """Noise-optimal centre-of-gravity half-window (about 2.7 sigma) from every ``step``-th line."""
    H = img.shape[0]
    lines = np.arange(0, H, step)
    cols = img[::step].argmax(axis=1)
    # Widths and contrasts only: no search for second maxima (it moves centres, not widths).
    m = _measure_many(img, lines, cols, 10, float("inf"), typical=float("inf"))
    ok = m.contrast > 10.0 * noise
    if np.count_nonzero(ok) < 3:
        return 6
    # np.median's value (float32 mean of the middle two) without its overhead.
    w = m.width[ok]
    k = w.size // 2
    part = np.partition(w, (k - 1, k))
    sigma = float(part[k] if w.size % 2 else (part[k - 1] + part[k]) / 2) / _FWHM_PER_SIGMA
    return int(np.clip(np.rint(2.7 * sigma), 3, 20))


def _primary_and_secondary(
    img: NDArray, options: StripeOptions, noise: float, hw: int
) -> tuple[_Peaks, bool]:
    """All peaks of the working-orientation image (rows are scan lines).

    Returns the peaks and whether the lines may hold several peaks (``False``: at most one per
    line, in line order).
    """
    H, W = img.shape
    sat = _saturation_level(img, options)
    min_contrast = options.min_contrast
    if min_contrast is None:
        min_contrast = 0.03 * (sat if np.isfinite(sat) else float(img.max()))
    thr_contrast = max(options.k_noise * noise, float(min_contrast))

    lines = np.arange(H)
    cols = img.argmax(axis=1)
    # Lines where something else clears the threshold outside the primary's window are searched
    # for further peaks; the common frame (one stripe, dark background) skips this entirely.
    if options.background_level is not None:
        bg_level = float(options.background_level)
    else:
        bg_level = _median(img[:: max(1, H // 32), :: max(1, W // 32)])
    thr = bg_level + thr_contrast
    # Pixels above the level, the primary windows cleared: what remains is elsewhere on its line.
    if img.dtype == np.uint8:
        _, mask = cv2.threshold(img, min(thr, 254.0), 1, cv2.THRESH_BINARY)
    elif img.dtype == np.float32:
        mask = cv2.threshold(img, thr, 1, cv2.THRESH_BINARY)[1].astype(np.uint8)
    else:
        mask = (img > thr).astype(np.uint8)
    prim = _measure_many(img, lines, cols, hw, sat, clear=mask)
    extra = np.flatnonzero(cv2.reduce(mask, 1, cv2.REDUCE_MAX).reshape(-1))
    parts = [prim]
    if extra.size:
        # The global level is only a first sieve: a further peak must clear its own line's
        # background and the fraction of the line's brightest contrast.
        line_bg = prim.peak[extra] - prim.contrast[extra]
        line_thr = np.maximum(line_bg, bg_level) + np.maximum(
            thr_contrast, options.min_relative_peak * np.maximum(prim.contrast[extra], 0.0)
        )
        above = img[extra] > line_thr[:, None]
        win = cols[extra][:, None] + np.arange(-hw, hw + 1)
        in_line_win = np.take_along_axis(above, np.clip(win, 0, W - 1), axis=1) & (
            (win >= 0) & (win < W)
        )
        extra = extra[above.sum(axis=1) > in_line_win.sum(axis=1)]
        if extra.size:
            parts.append(_secondary_peaks(img, extra, cols[extra], hw, sat, thr))
    if len(parts) == 1:
        # One peak per line: the line's brightest is the peak itself, only the noise and
        # absolute thresholds apply.
        keep = prim.contrast >= thr_contrast
        if np.all(keep):
            return prim, False
        return prim.take(np.flatnonzero(keep)), False
    peaks = _Peaks.concat(parts)

    # Contrast thresholds: noise, absolute, and relative to the line's brightest peak.
    best = _line_max(peaks.line, peaks.contrast, H)
    keep = (peaks.contrast >= thr_contrast) & (
        peaks.contrast >= options.min_relative_peak * best[peaks.line]
    )
    peaks = peaks.take(np.flatnonzero(keep))
    return _dedupe(peaks, hw), True


def _line_max(line: NDArray, value: NDArray, n_lines: int) -> NDArray:
    """Per-line maximum of ``value`` (0 where a line has none); fast when lines are unique."""
    best = np.zeros(n_lines, np.float32)
    if line.size and np.all(line[1:] > line[:-1]):
        best[line] = value
        return best
    # Two sorted runs (primary peaks, then further peaks): a stable sort merges them cheaply.
    order = np.argsort(line, kind="stable")
    ls = line[order]
    starts = np.flatnonzero(np.concatenate([[True], ls[1:] != ls[:-1]]))
    best[ls[starts]] = np.maximum.reduceat(value[order], starts)
    return best


def _secondary_peaks(
    img: NDArray,
    lines: NDArray,
    primary_cols: NDArray,
    hw: int,
    sat: float,
    thr: float,
) -> _Peaks:
    """Local maxima above ``thr`` on ``lines``, away from the primary peak's window."""
    sub = img[lines].astype(np.float32)
    mx = ndimage.maximum_filter1d(sub, size=2 * hw + 1, axis=1, mode="nearest")
    is_max = (sub >= mx) & (sub > thr)
    # A plateau (saturation) gives a run of equal maxima: keep its first pixel only.
    is_max[:, 1:] &= ~(is_max[:, :-1] & (sub[:, 1:] == sub[:, :-1]))
    r, c = np.nonzero(is_max)
    far = np.abs(c - primary_cols[r]) > hw
    # Also drop pixels inside a saturated run that continues from the primary peak.
    r, c = r[far], c[far]
    if r.size == 0:
        return _empty_peaks()
    return _measure_many(img, lines[r], c, hw, sat)


def _empty_peaks() -> _Peaks:
    return _Peaks(
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.uint8),
        np.zeros(0, np.float32),
    )


def _dedupe(peaks: _Peaks, hw: int) -> _Peaks:
    """Merge peaks of one line that landed within a window of each other (keep the brighter)."""
    if peaks.line.size < 2:
        return peaks
    order = np.lexsort((peaks.pos, peaks.line))
    p = peaks.take(order)
    same = (p.line[1:] == p.line[:-1]) & (np.abs(p.pos[1:] - p.pos[:-1]) <= hw)
    if not np.any(same):
        return p
    drop = np.zeros(p.line.size, bool)
    idx = np.flatnonzero(same)
    weaker_first = p.contrast[idx] < p.contrast[idx + 1]
    drop[np.where(weaker_first, idx, idx + 1)] = True
    keep_idx = np.flatnonzero(~drop)
    out = p.take(keep_idx)
    # The kept neighbour of a merged pair saw two maxima in its window.
    merged_into = np.where(weaker_first, idx + 1, idx)
    amb = np.zeros(p.line.size, bool)
    amb[merged_into] = True
    out.flags[amb[keep_idx]] |= np.uint8(StripeFlag.AMBIGUOUS)
    return out


def _segments(peaks: _Peaks, link_px: float) -> NDArray:
    """Segment label per peak: chains of peaks on consecutive lines within ``link_px``."""
    n = peaks.line.size
    order = np.lexsort((peaks.pos, peaks.line))
    line = peaks.line[order]
    pos = peaks.pos[order]
    # Nearest peak on the previous line, via a sorted key line * big + pos.
    big = float(max(1e6, pos.max() + 10 * link_px + 1))
    key = line * big + pos
    target = (line - 1) * big + pos
    j = np.searchsorted(key, target)
    src, dst = [], []
    for cand in (j - 1, j):
        ok = (cand >= 0) & (cand < n)
        cc = np.clip(cand, 0, n - 1)
        ok &= (line[cc] == line - 1) & (np.abs(pos[cc] - pos) <= link_px)
        src.append(np.flatnonzero(ok))
        dst.append(cc[ok])
    s = np.concatenate(src)
    d = np.concatenate(dst)
    graph = coo_matrix((np.ones(s.size), (s, d)), shape=(n, n))
    _, labels_sorted = connected_components(graph, directed=False)
    labels = np.empty(n, np.int64)
    labels[order] = labels_sorted
    return labels


def _resolve_multi(peaks: _Peaks, options: StripeOptions) -> _Peaks:
    """Drop reflections, flag ambiguity and secondary segments on lines with several peaks."""
    n = peaks.line.size
    if n < 2 or np.all(peaks.line[1:] > peaks.line[:-1]):  # one peak per line: nothing to do
        return peaks
    counts = np.bincount(peaks.line)
    multi_line = counts[peaks.line] > 1
    if not np.any(multi_line):
        return peaks
    labels = _segments(peaks, options.link_px)
    best = _line_max(peaks.line, peaks.contrast, counts.size)
    is_best = peaks.contrast >= best[peaks.line]
    ratio = peaks.contrast / np.maximum(best[peaks.line], 1e-6)
    # A segment is a reflection when none of its peaks is alone on its line and each stays
    # below reflection_ratio of its line's brightest peak.
    n_lab = int(labels.max()) + 1
    alone = np.zeros(n_lab, bool)
    alone[labels[~multi_line]] = True
    strong = np.zeros(n_lab, bool)
    strong[labels[ratio >= options.reflection_ratio]] = True
    reflection = ~alone[labels] & ~strong[labels] & ~is_best
    peaks.flags[multi_line & ~is_best] |= np.uint8(StripeFlag.SECONDARY)
    amb_lines = np.unique(peaks.line[reflection])
    amb = np.isin(peaks.line, amb_lines)
    peaks.flags[amb] |= np.uint8(StripeFlag.AMBIGUOUS)
    if options.keep_reflections:
        return peaks
    return peaks.take(np.flatnonzero(~reflection))


# --------------------------------------------------------------------------------------------
# precise mode: Steger at the fast estimate


def _gauss_kernels(x: NDArray, sigma: float) -> tuple[NDArray, NDArray, NDArray]:
    """Sampled Gaussian and its first and second derivatives at ``x`` (any shape)."""
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= np.sqrt(2 * np.pi) * sigma
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1.0 / sigma**2) * g
    return g, g1, g2


def _refine_precise(img: NDArray, peaks: _Peaks, sigma: float) -> tuple[NDArray, NDArray]:
    """Steger refinement of ``peaks`` (working orientation). Returns ``(pos, v_offset)``.

    ``pos`` is the centre on the scan line; ``v_offset`` is 0 where the point was slid back onto
    its line and the across-line offset otherwise (kept for stripes parallel to the lines).
    """
    H, W = img.shape
    R = int(np.ceil(2.5 * sigma))
    n = peaks.line.size
    pos = peaks.pos.copy()
    voff = np.zeros(n)
    sat = (peaks.flags & np.uint8(StripeFlag.SATURATED)) != 0
    c0 = np.rint(pos).astype(np.int64)
    delta = pos - c0
    j = np.arange(-R, R + 1)
    line = peaks.line
    rows_in = (line >= R) & (line < H - R)
    cols_in = (c0 >= R) & (c0 < W - R)
    # One broadcast index for all patches, ordered (row v, point, column u); rows or columns
    # past the border are clamped by ``clip`` (their points fall back to the 1-D estimate or
    # keep the fast one, below).
    P = j.size
    idx = (j * W)[:, None] + ((line * W + c0)[:, None] + j).reshape(-1)  # (P, n * P)
    patch = img.reshape(-1).take(idx, mode="clip").astype(np.float32)

    # Kernels along the line evaluated at the fast estimate: (I * g')(pos) = sum I(c) g'(pos - c).
    x = (delta[:, None] - j[None, :]).astype(np.float32)
    inv_s2 = np.float32(1.0 / sigma**2)
    x2 = x * x
    x2 *= inv_s2
    g0 = np.exp(np.float32(-0.5) * x2)
    g0 /= (g0 @ np.ones(P, np.float32))[:, None]
    g1 = x * g0
    g1 *= -inv_s2
    x2 -= 1.0
    x2 *= inv_s2
    g2 = x2 * g0
    # Across the lines: the same sampled derivatives, all scaled by one factor (as along the
    # line), so that the Hessian's mixed and pure terms compare.
    kv0, kv1, kv2 = _gauss_kernels(-j.astype(np.float64), sigma)
    kv0, kv1, kv2 = (k * (1.0 / kv0.sum()) for k in (kv0, kv1, kv2))
    centre = (j == 0).astype(np.float64)
    # Seven responses (kernel along v, kernel along u): ru (kv0, g1), ruu (kv0, g2),
    # rv (kv1, g0), ruv (kv1, g1), rvv (kv2, g0) and, on the centre row, r1 (g1), r2 (g2).
    # Along v with the fixed kernels, all points by one matrix product; then along u with each
    # point's own kernels.
    kv = np.stack([kv0, kv0, kv1, kv1, kv2, centre, centre]).astype(np.float32)
    resp = (kv @ patch).reshape(7, n, P)
    resp *= np.stack([g1, g2, g0, g1, g0, g1, g2])
    resp = (resp.reshape(7 * n, P) @ np.ones(P, np.float32)).reshape(7, n)
    ru, ruu, rv, ruv, rvv, r1, r2 = resp
    # The local background's slope along the line biases the gradient of an asymmetric profile.
    ru = ru - peaks.slope

    # 1-D estimate along the centre row (lines at the image's top and bottom).
    r1 = r1 - peaks.slope
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = -r1 / r2
    # 2-D: cross direction = eigenvector of the most negative Hessian eigenvalue.
    tr_half = 0.5 * (ruu + rvv)
    disc = np.sqrt(0.25 * (ruu - rvv) ** 2 + ruv**2)
    lam = tr_half - disc  # most negative
    nu = ruv
    nv = lam - ruu
    # Fall back to the other eigenvector form where this one degenerates.
    alt = np.abs(nu) + np.abs(nv) < 1e-12
    nu = np.where(alt, lam - rvv, nu)
    nv = np.where(alt, ruv, nv)
    norm = np.hypot(nu, nv)
    norm = np.where(norm > 0, norm, 1.0)
    nu, nv = nu / norm, nv / norm
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(ru * nu + rv * nv) / lam
        du, dv = t * nu, t * nv
        # Slide along the stripe (tangent (-nv, nu)) back onto the scan line.
        tu, tv = -nv, nu
        s = -dv / tv
        on_line = du + s * tu
    steep = np.abs(tv) > 0.3
    use2d = rows_in & cols_in & (lam < 0) & np.isfinite(on_line) & steep & (np.abs(on_line) < 1.5)
    use1d = ~use2d & cols_in & (r2 < 0) & np.isfinite(t1) & (np.abs(t1) < 1.5)
    pos = np.where(use2d, pos + on_line, pos)
    pos = np.where(use1d, peaks.pos + t1, pos)
    # Saturated peaks keep the saturated-run centre: the Taylor model of a flat top is wrong.
    if sat.any():
        pos = np.where(sat, peaks.pos, pos)
    return pos, voff


@functools.lru_cache(maxsize=8)
def _local_fit_kernels(k: int) -> tuple[NDArray, NDArray]:
    """Convolution kernels of a least-squares line's slope and parabola's ``x**2`` coefficient
    through ``2 k + 1`` equally spaced samples (reversed for :func:`numpy.convolve`)."""
    x = np.arange(-k, k + 1, dtype=np.float64)
    q = x * x - np.mean(x * x)
    w2 = q / np.sum(q * q)  # least-squares quadratic coefficient
    w1 = x / np.sum(x * x)  # least-squares slope (symmetric window)
    w1, w2 = np.ascontiguousarray(w1[::-1]), np.ascontiguousarray(w2[::-1])
    w1.flags.writeable = False
    w2.flags.writeable = False
    return w1, w2


def _curvature_shift(
    peaks: _Peaks, sigma: float, n_lines: int, link_px: float, k: int = 6
) -> NDArray:
    """Shift of the smoothed ridge of a curved stripe along its scan line, to subtract.

    Smoothing a curved line with a Gaussian of ``sigma`` moves its ridge towards the centre of
    curvature by ``sigma**2 * kappa / 2`` (along the normal), which is
    ``sigma**2 * pos'' / (2 (1 + pos'**2))`` along the scan line. ``pos'`` and ``pos''`` come
    from a least-squares quadratic through the fast centres of the ``2 k + 1`` neighbouring
    lines of the same segment (noise on ``pos''`` is then ~1/20 of the centres' own). Points
    without a full, continuous neighbourhood are left as they are.
    """
    shift = np.zeros(peaks.line.size)
    if peaks.line.size < 2 * k + 1:
        return shift
    # Segments as index arrays, and whether each has one point per line.
    if np.all(peaks.line[1:] > peaks.line[:-1]):
        groups = [(np.arange(peaks.line.size), True)]
    else:
        labels = _segments(peaks, link_px)
        groups = [(np.flatnonzero(labels == lab), False) for lab in np.unique(labels)]
    w1, w2 = _local_fit_kernels(k)
    for sel, unique in groups:
        if sel.size < 2 * k + 1:
            continue
        ln = peaks.line[sel]
        lo, hi = int(ln.min()), int(ln.max())
        span = hi - lo + 1
        if span < 2 * k + 1:
            continue
        if unique:
            one = np.ones(sel.size, bool)
            dense = np.full(span, np.nan)  # NaN: lines without a point
            dense[ln - lo] = peaks.pos[sel]
        else:
            counts = np.bincount(ln - lo, minlength=span)
            dense = np.full(span, np.nan)
            one = counts[ln - lo] == 1
            dense[ln[one] - lo] = peaks.pos[sel[one]]
        # A jump between neighbouring lines (another surface) breaks the neighbourhood.
        steps = np.abs(np.diff(dense)) > link_px
        c2 = np.convolve(dense, w2, mode="same")
        c1 = np.convolve(dense, w1, mode="same")
        valid = np.isfinite(c2) & np.isfinite(c1)
        if steps.any():
            jump = np.zeros(span)
            jump[1:] = np.where(steps, np.nan, 0.0)
            valid &= np.isfinite(np.convolve(jump, np.ones(2 * k + 1), mode="same"))
        valid[:k] = False
        valid[span - k :] = False
        along = np.where(valid, sigma**2 * c2 / (1.0 + c1 * c1), 0.0)  # sigma^2/2 * 2 c2
        shift[sel[one]] = along[ln[one] - lo]
    return shift


# --------------------------------------------------------------------------------------------
# public entry


def _as_gray(image: NDArray, name: str) -> NDArray:
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
    img = _as_gray(image, "image")
    if background is not None:
        bg = _as_gray(background, "background")
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
    if orientation == "auto":
        orientation = orientation_from_image(img)
    work = img if orientation == "rows" else cv2.transpose(img)
    noise = float(opts.noise) if opts.noise is not None else estimate_noise(work)

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
        typical = float(np.partition(peaks.contrast, peaks.line.size // 2)[peaks.line.size // 2])
        low = peaks.contrast < opts.low_contrast_ratio * typical
        if low.any():
            peaks.flags[low] |= np.uint8(StripeFlag.LOW_CONTRAST)

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
    )
