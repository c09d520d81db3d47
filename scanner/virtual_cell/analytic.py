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

from scanner.core.conventions import invert_transform, make_transform
from scanner.formats.calibration_file import Calibration, LightPlane
from scanner.formats.session import Frame, write_session

__all__ = [
    "StripeConditions",
    "StripeSegment",
    "TableStepScene",
    "draw_stripe_conditions",
    "render_stripe_conditions",
    "render_stripes",
    "write_table_step_sweep",
]


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


def _pixel_gaussian(u: NDArray, centre: NDArray, sigma: float) -> NDArray:
    """Gaussian integrated over each pixel's width, ``(L, W)``, ~1 at a centred pixel."""
    z1 = (u[None, :] + 0.5 - centre[:, None]) / (np.sqrt(2) * sigma)
    z0 = (u[None, :] - 0.5 - centre[:, None]) / (np.sqrt(2) * sigma)
    return 0.5 * (erf(z1) - erf(z0)) / erf(0.5 / (np.sqrt(2) * sigma))


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
            acc += _pixel_gaussian(u, c, seg.sigma_px) / supersample
        img[lines] += seg.amplitude * gain[lines, None] * acc
        truth.append((lines, centres))
    img += rng.normal(0.0, noise, img.shape)
    img = np.clip(np.rint(img), 0, full_scale).astype(dtype)
    if orientation == "cols":
        img = np.ascontiguousarray(img.T)
    return img, truth


@dataclass(frozen=True)
class TableStepScene:
    """A flat table (``z = 0`` in the base frame) with a raised block, swept by a camera.

    The camera looks straight down from ``height_mm`` and moves along base x; the laser sits
    ``baseline_mm`` beside it and its plane crosses the optical axis at the table. The block's
    top is ``z = step_mm`` for ``x0_mm <= x <= x1_mm`` (its sides are not rendered).
    """

    width: int = 320
    height: int = 240
    focal_px: float = 400.0
    height_mm: float = 300.0
    baseline_mm: float = 80.0
    step_mm: float = 20.0
    x0_mm: float = -10.0
    x1_mm: float = 10.0
    sigma_px: float = 1.5
    amplitude: float = 160.0
    noise: float = 1.0
    ambient_ramp: float = 0.0
    """Ambient light rising across the image, grey levels from the left edge to the right (on
    top of the dark frame's 6): a lit cell without a laser-off frame."""

    def calibration(self):  # -> scanner.formats.calibration_file.Calibration
        from scipy.spatial.transform import Rotation

        K = np.array(
            [
                [self.focal_px, 0.0, (self.width - 1) / 2.0],
                [0.0, self.focal_px, (self.height - 1) / 2.0],
                [0.0, 0.0, 1.0],
            ]
        )
        # Plane through (0, 0, height) and (baseline, 0, 0), containing the camera's y axis.
        normal = np.array([self.height_mm, 0.0, self.baseline_mm])
        normal /= np.linalg.norm(normal)
        d = -float(normal @ [0.0, 0.0, self.height_mm])
        flange_from_cam = make_transform(
            Rotation.from_euler("xyz", [2.0, -3.0, 90.0], degrees=True), [30.0, -12.0, 85.0]
        )
        return Calibration(
            self.width, self.height, K, np.zeros(5), LightPlane(normal, d), flange_from_cam
        )

    def base_from_cam(self, x_mm: float) -> NDArray:
        m = np.eye(4)
        m[:3, :3] = np.diag([1.0, -1.0, -1.0])  # camera z down, x along base x
        m[:3, 3] = [x_mm, 0.0, self.height_mm]
        return m

    def centres(self, x_mm: float) -> list[tuple[NDArray, NDArray]]:
        """True stripe centres ``(rows, u)`` per visible surface (table, block top)."""
        cal = self.calibration()
        n, d = cal.light_plane.normal, cal.light_plane.d
        K = cal.K
        bfc = self.base_from_cam(x_mm)
        rows = np.arange(self.height, dtype=np.float64)
        e = (rows - K[1, 2]) / K[1, 1]
        a, b = 1.0 / K[0, 0], -K[0, 2] / K[0, 0]
        out = []
        for level, inside in ((0.0, False), (self.step_mm, True)):
            # z_base(p) = level with p = s r, s = -d / (n . r), r = (a u + b, e, 1): linear in u.
            r2 = bfc[2, :3]
            t2 = bfc[2, 3] - level
            # -d (r2 . r) + t2 (n . r) = 0  ->  coefficient of u and constant term
            cu = -d * r2[0] * a + t2 * n[0] * a
            c0 = -d * (r2[0] * b + r2[1] * e + r2[2]) + t2 * (n[0] * b + n[1] * e + n[2])
            u = -c0 / cu
            r = np.column_stack([a * u + b, e, np.ones_like(e)])
            s = -d / (r @ n)
            p_base = (r * s[:, None]) @ bfc[:3, :3].T + bfc[:3, 3]
            on_block = (p_base[:, 0] >= self.x0_mm) & (p_base[:, 0] <= self.x1_mm)
            keep = (on_block if inside else ~on_block) & (u > 2) & (u < self.width - 3)
            if not inside:
                # Table points in the block's laser shadow or hidden from the camera by it.
                f = (self.height_mm - self.step_mm) / self.height_mm
                for origin_x in (x_mm + self.baseline_mm, x_mm):
                    xs = origin_x + (p_base[:, 0] - origin_x) * f
                    keep &= ~((xs >= self.x0_mm) & (xs <= self.x1_mm))
            out.append((rows[keep].astype(np.int64), u[keep]))
        return out


def write_table_step_sweep(
    root,
    scene: TableStepScene | None = None,
    x_mm: Sequence[float] = tuple(np.linspace(-30.0, 30.0, 13)),
    sweep: Sequence[int] | None = None,
    seed: int = 0,
):
    """Render a sweep session of :class:`TableStepScene` into ``root``.

    Returns
    -------
    (Path, Calibration, TableStepScene)
        The session folder, the exact calibration and the scene.
    """
    from pathlib import Path

    import cv2

    scene = scene or TableStepScene()
    cal = scene.calibration()
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frames = []
    u = np.arange(scene.width, dtype=np.float64)
    cam_from_flange = invert_transform(cal.flange_from_cam)
    for i, x in enumerate(x_mm):
        img = np.full((scene.height, scene.width), 6.0) + scene.ambient_ramp * u / scene.width
        for rows, centres in scene.centres(float(x)):
            if rows.size:
                img[rows] += scene.amplitude * _pixel_gaussian(u, centres, scene.sigma_px)
        img += rng.normal(0.0, scene.noise, img.shape)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        path = root / "images" / f"laser_{i:04d}.png"
        cv2.imwrite(str(path), img)
        base_from_flange = scene.base_from_cam(float(x)) @ cam_from_flange
        frames.append(
            Frame(
                id=i,
                target_image=None,
                laser_image=path,
                base_from_flange=base_from_flange,
                sweep=0 if sweep is None else int(sweep[i]),
            )
        )
    write_session(root, "sweep", scene.width, scene.height, frames, rotation="quaternion_wxyz")
    return root, cal, scene


def table_step_plan(
    step_tolerance_mm: float = 0.2, flatness_tolerance_mm: float | None = None
) -> str:
    """An inspection plan (TOML) fitted to the default :class:`TableStepScene`.

    Parameters
    ----------
    step_tolerance_mm : float
        Tolerance of the block's step height (nominal 20 mm) above the table.
    flatness_tolerance_mm : float or None
        With a value, the plan also measures the table's flatness to this tolerance.

    Returns
    -------
    str
        The plan's text: features ``table`` and ``top``, the measurement ``step height`` and,
        with ``flatness_tolerance_mm``, ``table flatness``.
    """
    text = f"""
name = "table and block"
threshold_mm = 0.5

[[features]]
name = "table"
kind = "plane"
region = {{ box_min_mm = [-30.0, -60.0, -3.0], box_max_mm = [-14.0, 60.0, 3.0] }}
nominal = {{ normal = [0.0, 0.0, 1.0] }}

[[features]]
name = "top"
kind = "plane"
region = {{ box_min_mm = [-8.0, -60.0, 17.0], box_max_mm = [8.0, 60.0, 23.0] }}
nominal = {{ normal = [0.0, 0.0, 1.0] }}

[[measurements]]
name = "step height"
type = "distance"
features = ["top", "table"]
nominal = 20.0
tolerance = {step_tolerance_mm!r}
"""
    if flatness_tolerance_mm is not None:
        text += f"""
[[measurements]]
name = "table flatness"
type = "flatness"
features = ["table"]
tolerance = {flatness_tolerance_mm!r}
"""
    return text


@dataclass(frozen=True)
class StripeConditions:
    """One randomised stripe frame (:func:`draw_stripe_conditions`): a Gaussian stripe along a
    curved centre line over a shaded background, as cameras of other cells give it.

    Attributes
    ----------
    shape : (int, int)
        ``(H, W)`` in working orientation (rows are scan lines).
    sigma_px, amplitude, noise : float
        The cross-section's sigma along the scan line (px), its peak above the background and
        the noise's standard deviation (8-bit grey levels, scaled by 257 for 16 bits).
    background, gradient_per_px : float
        The background's level at the image's centre and its slope along the scan line.
    coeffs : (float, float, float)
        The centre line ``pos(line)`` (:class:`StripeSegment`).
    bit_depth : int
        8 or 16.
    orientation : {"rows", "cols"}
        How the frame is stored (``"cols"``: transposed).
    """

    shape: tuple[int, int]
    sigma_px: float
    amplitude: float
    noise: float
    background: float
    gradient_per_px: float
    coeffs: tuple[float, float, float]
    bit_depth: int
    orientation: str

    @property
    def snr(self) -> float:
        """The stripe's peak contrast over the noise, as far as saturation lets it show."""
        return min(self.amplitude, 255.0 - self.background) / self.noise

    @property
    def background_range(self) -> float:
        """How much the background varies along a scan line, 8-bit grey levels."""
        return abs(self.gradient_per_px) * self.shape[1]


def draw_stripe_conditions(rng: np.random.Generator) -> StripeConditions:
    """Conditions of one stripe frame over a domain wider than any one cell's.

    Image 640x480, 1024x768 or 1280x1024; stripe sigma 0.5-5 px and amplitude 15-700 grey
    levels (log-uniform: faint to saturated), background 0-120 with a slope along the scan
    line of up to +-0.05 grey levels per px (up to +-32 grey levels at a 1280 px line's ends),
    noise 0.3-6 grey levels (log-uniform), the stripe slanted up to 0.8 px per line and
    curved, 8 bits or (a quarter) 16 bits, stored row- or column-wise.
    """
    h, w = [(480, 640), (768, 1024), (1024, 1280)][int(rng.integers(3))]
    slope = float(rng.uniform(-0.8, 0.8))
    curvature = float(rng.uniform(-3e-4, 3e-4))
    c0 = w / 2 - slope * h / 2 - curvature * (h / 2) ** 2 + float(rng.uniform(-0.2, 0.2)) * w
    return StripeConditions(
        shape=(h, w),
        sigma_px=float(np.exp(rng.uniform(np.log(0.5), np.log(5.0)))),
        amplitude=float(np.exp(rng.uniform(np.log(15.0), np.log(700.0)))),
        noise=float(np.exp(rng.uniform(np.log(0.3), np.log(6.0)))),
        background=float(rng.uniform(0.0, 120.0)),
        gradient_per_px=float(rng.uniform(-0.05, 0.05)),
        coeffs=(c0, slope, curvature),
        bit_depth=16 if rng.random() < 0.25 else 8,
        orientation="rows" if rng.random() < 0.5 else "cols",
    )


def render_stripe_conditions(
    c: StripeConditions, seed: int = 0
) -> tuple[NDArray, NDArray, NDArray]:
    """The frame of ``c`` and its truth.

    Returns
    -------
    image : ndarray, shape (H, W) (``(W, H)`` for ``"cols"``), uint8 or uint16
    lines : ndarray, shape (L,), int
        The scan lines the stripe covers.
    pos : ndarray, shape (L,)
        Its true centre along each of them, px.
    """
    scale = 257.0 if c.bit_depth == 16 else 1.0
    seg = StripeSegment((0, c.shape[0]), c.coeffs, c.amplitude * scale, c.sigma_px)
    image, truth = render_stripes(
        c.shape,
        [seg],
        background=c.background * scale,
        gradient_per_px=c.gradient_per_px * scale,
        noise=c.noise * scale,
        dtype=np.uint16 if c.bit_depth == 16 else np.uint8,
        full_scale=65535.0 if c.bit_depth == 16 else 255.0,
        orientation=c.orientation,
        seed=seed,
    )
    return image, truth[0][0], truth[0][1]
