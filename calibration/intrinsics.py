"""Camera intrinsics from target observations.

Two methods:

``"paper"``
    Section III.A of the method: vanishing points p, q of the two diameters from the
    harmonic conjugate of O with respect to the diameter ends, equation (4) per image,
    differences (5) stacked into ``H phi = g`` (6) over n >= 4 images, least squares, then
    alpha, beta from (4). Zero skew, no distortion. Reported in two variants: the diameter
    ends of the largest ring only (the paper), and every ring (a 1-D projective fit along
    each diameter line).
``"default"``
    Starts from the paper estimate (or OpenCV's ``calibrateCamera`` on the exact point
    correspondences), then one robust nonlinear least-squares adjustment of fx, fy, cx, cy,
    k1, k2, p1, p2, k3 and every view's pose, minimising the geometric image distance of
    every ring edge point to the projected circle of its radius and of every diameter-line
    point to the projected line (points of chessboards and circle grids: their reprojection).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calibration.observations import TargetObservation

__all__ = ["PARAM_NAMES", "IntrinsicsResult", "PaperEstimate", "calibrate_intrinsics"]

PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass
class PaperEstimate:
    """One variant of the paper's closed-form intrinsics (zero skew, no distortion).

    ``ok`` False with ``reason`` when the linear system is degenerate or gives a negative
    alpha^2 / beta^2.
    """

    variant: str
    ok: bool
    reason: str = ""
    K: NDArray = field(default_factory=lambda: np.eye(3))
    vanishing_points: list[tuple[NDArray, NDArray]] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.ok)


@dataclass
class IntrinsicsResult:
    """Calibrated intrinsics and how well they are determined.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (5,)
        OpenCV order ``(k1, k2, p1, p2, k3)``.
    image_size : tuple of int
        ``(width, height)``.
    method : str
        ``"default"`` or ``"paper"`` (the variant used for ``K`` in the latter case).
    view_indices : list of int
        Indices (into the input list) of the views used.
    cam_from_target : list of ndarray, shape (4, 4)
        Pose of each used view, in the order of ``view_indices``.
    rms_px : float
        RMS of all geometric residuals, pixels.
    per_view_rms_px : ndarray, shape (V,)
    std : dict of str to float
        Standard deviations of ``PARAM_NAMES`` (from J^T J and the residual variance).
    correlation : ndarray, shape (9, 9)
        Correlation matrix of ``PARAM_NAMES``.
    warnings : list of str
    rejected : list of tuple of (int, str)
        Input views not used, with the reason.
    paper : dict of str to PaperEstimate
        ``"diameter_ends"`` (the paper's method) and ``"all_rings"``, when computed.
    n_residuals : int
    """

    K: NDArray
    dist: NDArray
    image_size: tuple[int, int]
    method: str
    view_indices: list[int] = field(default_factory=list)
    cam_from_target: list[NDArray] = field(default_factory=list)
    rms_px: float = float("nan")
    per_view_rms_px: NDArray = field(default_factory=lambda: np.zeros(0))
    std: dict[str, float] = field(default_factory=dict)
    correlation: NDArray = field(default_factory=lambda: np.eye(len(PARAM_NAMES)))
    warnings: list[str] = field(default_factory=list)
    rejected: list[tuple[int, str]] = field(default_factory=list)
    paper: dict[str, PaperEstimate] = field(default_factory=dict)
    n_residuals: int = 0

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])


def calibrate_intrinsics(
    observations: list[TargetObservation],
    image_size: tuple[int, int],
    method: Literal["default", "paper"] = "default",
    target: object | None = None,
) -> IntrinsicsResult:
    """Calibrate the camera from observations of a planar target.

    Parameters
    ----------
    observations : list of TargetObservation
        One per image; falsy ones are reported in ``rejected`` with their reason.
    image_size : tuple of int
        ``(width, height)``, pixels.
    method : {"default", "paper"}
    target : TargetSpec, optional
        The target spec (not needed: observations carry target coordinates).

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    ValueError
        Fewer than 4 usable views, or views that cannot determine the intrinsics (e.g. the
        paper method on a non-concentric target, or all views parallel), naming what is missing.
    """
    raise NotImplementedError
