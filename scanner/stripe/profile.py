"""Stripe profiles and their vocabulary: quality flags, options, and the peaks worked on.

:class:`StripeProfile` is what :func:`scanner.stripe.extract.extract_stripe` returns (one
frame's sub-pixel centres); :class:`StripeOptions` tunes it; :class:`StripeFlag` holds the
quality bits of each point. ``_Peaks`` is the estimators' working set: peaks in the working
orientation, where every scan line is an image row.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["MODES", "ORIENTATIONS", "StripeFlag", "StripeOptions", "StripeProfile"]

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
    GRAZING = 32
    """Set by scanning: the surface is seen or lit beyond the incidence limit."""
    STRETCH_END = 64
    """Within ``end_lines`` lines of where its run of linked peaks ends inside the image: the
    stripe there is cut by a depth jump, a shadow or an object's edge, and the centre mixes
    what lies on both sides (mixed pixels; on the virtual cell 3-4 times the error inside).
    Only set when :attr:`StripeOptions.end_lines` asks for it."""


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
    flatten_background : bool or None
        Take a smooth background out of a frame that has no laser-off frame
        (:func:`scanner.stripe.background.flatten_background`), so that a faint stripe on an
        unevenly lit frame clears the threshold and is each line's brightest peak; ``None``:
        where the frame's own background varies by more than twice the contrast threshold
        (:func:`scanner.stripe.background.background_is_uneven`), which the virtual cell's
        frames do not. A scan decides it once, from a few of its frames.
    end_lines : int
        Peaks fewer than this many lines from the end of their run of linked peaks (a run
        ending at the image's first or last line does not end there) get STRETCH_END; 0 (the
        default): none. 3 suits features many lines across (on the virtual cell it halves a
        plate's tilt error); on a feature only a few lines across (the paper cell's 8 mm bar,
        precise mode) it leaves too little of the section: its diameter went 0.49 mm off.
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
    flatten_background: bool | None = None
    end_lines: int = 0

    def __post_init__(self) -> None:
        if self.half_window_px is not None and int(self.half_window_px) < 2:
            raise ValueError(f"half_window_px: expected >= 2, got {self.half_window_px}")
        if self.sigma_px is not None and not 0.5 <= float(self.sigma_px) <= 10.0:
            raise ValueError(f"sigma_px: expected 0.5..10 px or None, got {self.sigma_px}")
        if self.k_noise <= 0:
            raise ValueError(f"k_noise: expected > 0, got {self.k_noise}")
        if not 0.0 <= self.min_relative_peak <= 1.0:
            raise ValueError(f"min_relative_peak: expected 0..1, got {self.min_relative_peak}")
        if int(self.end_lines) < 0:
            raise ValueError(f"end_lines: expected >= 0, got {self.end_lines}")


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
    contrast : ndarray, shape (N,), float32, or None
        Peak height above the line's local background (grey levels), where the extractor
        gave it.
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
    contrast: NDArray | None = None

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
            contrast=None if self.contrast is None else self.contrast[mask],
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
