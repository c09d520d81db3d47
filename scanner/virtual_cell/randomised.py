"""Randomised views of the concentric-circles target: a domain to test detection on.

Independent of the cells and of the physically based renderer: a pinhole camera sees the
printed card (:class:`~scanner.virtual_cell.scene.PrintedTarget`, the same marks the virtual
cell renders) through the exact homography of the target plane, over surroundings that are
dark, cluttered or brighter than the paper. The image chain then adds what real images
bring and our cells do not vary much: any size on the image, tilt and in-plane rotation,
rings cut by the border, printed line widths of 1 to 8 px, defocus, paper grain, an
illumination gradient and vignetting, a laser stripe, sensor noise, JPEG and 8 / 16 bits,
and target specs with other ring counts, spacings and marker places.

:func:`draw_conditions` draws one view's :class:`ViewConditions` from a seeded generator;
:func:`render_view` renders it and returns the image with its truth
(:class:`RenderedView`): the image positions of O and of every ring's crossings with the
diameters, named as the detector names them, and whether the target is detectable by the
spec's rules (centre and at least 3 rings in the image, the orientation marker in the image
for the labelling, lines resolvable above the noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.targets import ConcentricCirclesTarget, OrientationMarker
from scanner.virtual_cell.scene import PrintedTarget

__all__ = [
    "IMAGE_SIZES",
    "RenderedView",
    "ViewConditions",
    "draw_conditions",
    "paper_dark_surroundings",
    "render_view",
    "target_spec",
]

#: Image sizes ``(width, height)`` a view is drawn at.
IMAGE_SIZES: tuple[tuple[int, int], ...] = ((640, 480), (1024, 768), (1280, 1024), (1600, 1200))
#: Fewest rings (from the centre out) that must lie mostly inside the image.
MIN_VISIBLE_RINGS = 3
#: Line contrast after blur over the noise below which a view is not called detectable.
MIN_LINE_SNR = 3.0
_SUPERSAMPLE = 4


@dataclass(frozen=True)
class ViewConditions:
    """Everything that decides one randomised view (drawn by :func:`draw_conditions`).

    Lengths on the target are mm, on the image px, angles deg, levels 8-bit grey levels
    (a 16-bit image carries the same levels times 257).
    """

    width: int
    """Image width, px."""
    height: int
    """Image height, px."""
    has_target: bool = True
    """False: surroundings only (a view that must be refused)."""
    ring_count: int = 14
    ring_min_diameter_mm: float = 50.0
    ring_max_diameter_mm: float = 160.0
    line_width_mm: float = 0.6
    marker_diameter_mm: float = 8.0
    marker_center_mm: tuple[float, float] = (92.0, 0.0)
    card_margin_mm: float = 12.0
    """White paper around the marks; beyond the card are the surroundings."""
    focal_px: float = 1940.0
    """Pinhole focal length (square pixels, principal point at the image centre), px."""
    distance_mm: float = 600.0
    """Depth of the target centre O in the camera frame, mm."""
    centre_px: tuple[float, float] = (512.0, 384.0)
    """Where O is seen, px."""
    tilt_deg: float = 0.0
    """Angle between the target normal and the line of sight, deg."""
    tilt_axis_deg: float = 0.0
    """Direction of the tilt axis in the target plane, deg."""
    roll_deg: float = 0.0
    """In-plane rotation of the target, deg."""
    paper_grey: float = 200.0
    """Level of the lit paper at the image centre, grey levels."""
    contrast_grey: float = 150.0
    """Paper minus ink, grey levels."""
    blur_px: float = 0.7
    """Sigma of the Gaussian defocus, px."""
    noise_grey: float = 2.0
    """Sigma of the sensor noise, grey levels."""
    grain: float = 0.0
    """Relative sigma of the paper grain (multiplies the card's light)."""
    grain_px: float = 1.0
    """Correlation length of the grain, px."""
    gradient: float = 0.0
    """Relative change of the illumination across the image (0: even)."""
    gradient_dir_deg: float = 0.0
    vignetting: float = 0.0
    """Relative loss of light in the image corners."""
    surroundings: str = "dark"
    """``"dark"``, ``"cluttered"`` or ``"bright"``."""
    surround_grey: float = 10.0
    """Mean level of the surroundings, grey levels."""
    laser: bool = False
    """A bright laser stripe across the target."""
    laser_width_px: float = 3.0
    """Sigma of the stripe's profile, px."""
    laser_peak_grey: float = 200.0
    """Added light on the stripe's centre, grey levels (clipped at white)."""
    laser_angle_deg: float = 0.0
    laser_offset_px: float = 0.0
    """Distance of the stripe from O, px."""
    jpeg_quality: int = 0
    """JPEG quality of an 8-bit image (0: not compressed)."""
    bit_depth: int = 8
    seed: int = 0
    """Seed of the clutter and grain patterns."""

    def __post_init__(self) -> None:
        if self.surroundings not in ("dark", "cluttered", "bright"):
            raise ValueError(
                f"surroundings: expected 'dark', 'cluttered' or 'bright', got {self.surroundings!r}"
            )
        if self.bit_depth not in (8, 16):
            raise ValueError(f"bit_depth: expected 8 or 16, got {self.bit_depth}")
        if self.width < 32 or self.height < 32:
            raise ValueError(f"image size: expected >= 32 px, got {self.width}x{self.height}")

    @property
    def target_diameter_frac(self) -> float:
        """Largest ring diameter on a frontal view over the image height."""
        return self.focal_px * self.ring_max_diameter_mm / self.distance_mm / self.height

    @property
    def line_width_px(self) -> float:
        """Printed line width on a frontal view at O's depth, px."""
        return self.focal_px * self.line_width_mm / self.distance_mm


@dataclass(frozen=True)
class RenderedView:
    """A rendered view and its truth.

    Attributes
    ----------
    image : ndarray, shape (H, W)
        uint8 or uint16.
    conditions : ViewConditions
    spec : ConcentricCirclesTarget
    K : ndarray, shape (3, 3)
    cam_from_target : ndarray, shape (4, 4)
    center_px : ndarray, shape (2,)
        Image of O.
    named_px : dict of str to ndarray (2,)
        O and the ends A-D of the largest ring's diameters that are inside the image.
    points_target : ndarray, shape (M, 3)
        O and every ring's crossings with the diameters, target frame, mm.
    points_px : ndarray, shape (M, 2)
        Their images, px (possibly outside the image).
    point_names : list of str
        ``"O"``, ``"r{k}+x"``, ``"r{k}-y"``..., as the detector names them.
    detectable : bool
        The spec's rules: O, at least 3 rings and the marker in the image, lines resolvable.
    why_not : str
        Why not detectable ("" when detectable).
    surround_frac : float
        Fraction of the image off the card.
    visible_rings : int
        Rings from the centre out with most of their circumference inside the image.
    line_snr : float
        Peak darkness of a blurred printed line over the noise.
    min_spacing_px : float
        Smallest image distance between neighbouring rings.
    """

    image: NDArray
    conditions: ViewConditions
    spec: ConcentricCirclesTarget
    K: NDArray
    cam_from_target: NDArray
    center_px: NDArray
    named_px: dict[str, NDArray]
    points_target: NDArray
    points_px: NDArray
    point_names: list[str]
    detectable: bool
    why_not: str
    surround_frac: float
    visible_rings: int
    line_snr: float
    min_spacing_px: float


def target_spec(c: ViewConditions) -> ConcentricCirclesTarget:
    """The target spec of a view: evenly spaced ring diameters from the conditions."""
    diam = np.linspace(c.ring_min_diameter_mm, c.ring_max_diameter_mm, c.ring_count)
    return ConcentricCirclesTarget(
        ring_diameters_mm=tuple(float(d) for d in diam),
        line_width_mm=c.line_width_mm,
        orientation_marker=OrientationMarker(c.marker_diameter_mm, c.marker_center_mm),
    )


def paper_dark_surroundings(noise_grey: float = 1.5, seed: int = 0) -> ViewConditions:
    """The paper's set-up seen frontally at 600 mm, 1024x768, dark around a small card."""
    return ViewConditions(
        width=1024,
        height=768,
        focal_px=1940.0,
        distance_mm=600.0,
        centre_px=(530.0, 370.0),
        tilt_deg=4.0,
        tilt_axis_deg=30.0,
        roll_deg=2.0,
        card_margin_mm=6.0,
        paper_grey=190.0,
        contrast_grey=160.0,
        blur_px=0.8,
        noise_grey=noise_grey,
        grain=0.02,
        grain_px=1.0,
        surroundings="dark",
        surround_grey=6.0,
        seed=seed,
    )


def _cam_from_target(c: ViewConditions, K: NDArray) -> NDArray:
    """Pose with O on the ray through ``centre_px`` at depth ``distance_mm``."""
    face = Rotation.from_euler("x", 180, degrees=True)  # target z towards the camera
    ax = np.radians(c.tilt_axis_deg)
    tilt = Rotation.from_rotvec(np.radians(c.tilt_deg) * np.array([np.cos(ax), np.sin(ax), 0.0]))
    roll = Rotation.from_euler("z", c.roll_deg, degrees=True)
    # Tilt about an axis seen in the image, then turn the target so O's ray is its axis.
    ray = np.linalg.solve(K, np.array([c.centre_px[0], c.centre_px[1], 1.0]))
    ray /= np.linalg.norm(ray)
    to_ray = _rotation_between(np.array([0.0, 0.0, 1.0]), ray)
    rot = to_ray * tilt * face * roll
    T = np.eye(4)
    T[:3, :3] = rot.as_matrix()
    T[:3, 3] = ray * c.distance_mm / ray[2]
    return T


def _rotation_between(a: NDArray, b: NDArray) -> Rotation:
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return Rotation.identity()
    return Rotation.from_rotvec(axis / s * np.arctan2(s, float(a @ b)))


def draw_conditions(rng: np.random.Generator, has_target: bool = True) -> ViewConditions:
    """Draw one view's conditions over the randomised domain.

    The spec is drawn so that its rings are resolvable at the drawn scale (ring spacing at
    least three line widths and 5 px on the frontal view, foreshortened by the tilt).

    Parameters
    ----------
    rng : numpy.random.Generator
        Seeded generator; the same state draws the same view.
    has_target : bool
        False draws surroundings only (cluttered half the time), to check refusals.

    Returns
    -------
    ViewConditions
    """
    w, h = IMAGE_SIZES[int(rng.integers(len(IMAGE_SIZES)))]
    focal = float(rng.uniform(0.9, 2.2) * w)
    frac = float(rng.uniform(0.15, 0.95))
    tilt = float(rng.choice([rng.uniform(0.0, 5.0), rng.uniform(0.0, 65.0)], p=[0.25, 0.75]))
    cos_t = np.cos(np.radians(tilt))
    r_px = 0.5 * frac * h
    # Spec: ring count, spacing and line width resolvable at this scale.
    min_frac = float(rng.uniform(0.15, 0.5))
    lw_px = float(np.exp(rng.uniform(np.log(1.0), np.log(8.0))))
    n_rings = int(rng.integers(4, 17))
    for _ in range(40):
        spacing = r_px * (1 - min_frac) / (n_rings - 1) * cos_t * 0.85
        if spacing >= max(3.0 * lw_px, 5.0 + lw_px):
            break
        if n_rings > 4:
            n_rings -= 1
        else:
            lw_px = max(1.0, 0.8 * lw_px)
            min_frac = max(0.1, 0.8 * min_frac)
    d_max = float(rng.choice([120.0, 160.0, 200.0, 300.0]))
    d_min = min_frac * d_max
    mm_per_px = d_max / (frac * h)
    line_mm = min(lw_px * mm_per_px, 0.45 * (d_max - d_min) / (n_rings - 1))
    gap_mm = (d_max - d_min) / 2 / (n_rings - 1)
    # Marker: outside the largest ring (on the +x axis or off it), or in a gap between rings.
    place = rng.choice(["axis", "outside", "gap"], p=[0.5, 0.3, 0.2])
    marker_d = float(rng.uniform(0.04, 0.07) * d_max)
    big = d_max / 2
    if place == "gap" and gap_mm > 5 * line_mm + 3.0:
        marker_d = min(marker_d, (gap_mm - line_mm) / 3.4 * 2)
        k = int(rng.integers(1, n_rings - 1))
        rad = d_min / 2 + (k + 0.5) * gap_mm
        ang = np.radians(rng.uniform(15.0, 75.0))
    else:
        rad = big + float(rng.uniform(1.8, 3.0)) * marker_d
        ang = 0.0 if place != "outside" else np.radians(rng.uniform(15.0, 75.0))
    marker = (float(rad * np.cos(ang)), float(rad * np.sin(ang)))
    distance = focal * d_max / (frac * h)
    # Where O is seen: the card in the image, or (a third of the views) cut by the border.
    cut = rng.random() < 0.3
    if cut:
        reach = r_px * float(rng.uniform(0.45, 0.9))
        side = int(rng.integers(4))
        u = float(rng.uniform(reach, w - reach)) if side >= 2 else None
        v = float(rng.uniform(reach, h - reach)) if side < 2 else None
        centre = (
            (reach if side == 0 else w - reach, v)
            if side < 2
            else (u, reach if side == 2 else h - reach)
        )
    else:
        ext = r_px * 1.25
        centre = (
            float(rng.uniform(min(ext, w / 2), max(w - ext, w / 2))),
            float(rng.uniform(min(ext, h / 2), max(h - ext, h / 2))),
        )
    surroundings = str(rng.choice(["dark", "cluttered", "bright"], p=[0.5, 0.3, 0.2]))
    contrast = float(np.exp(rng.uniform(np.log(20.0), np.log(200.0))))
    paper = float(rng.uniform(max(contrast + 8.0, 70.0), 245.0))
    surround = {
        "dark": float(rng.uniform(0.0, 0.25) * paper),
        "cluttered": float(rng.uniform(0.2, 0.9) * paper),
        "bright": float(min(255.0, rng.uniform(1.05, 1.4) * paper)),
    }[surroundings]
    # Card size: the surroundings cover 0-85 % of a frontal view's frame (as far as the target
    # size allows: a small target on a large card, a large one cut by the frame).
    sf = float(rng.uniform(0.0, 0.85))
    ext = max(big, float(np.hypot(*marker)) + marker_d / 2)
    margin = max(0.05 * big, 0.5 * np.sqrt((1.0 - sf) * w * h) * mm_per_px - ext)
    # Noise: log-uniform 0.5-8 grey levels, lowered (nine times in ten) where the blurred
    # lines would not stand out of it (see MIN_LINE_SNR).
    blur = float(rng.uniform(0.3, 2.0))
    noise = float(np.exp(rng.uniform(np.log(0.5), np.log(8.0))))
    line_peak = contrast * math.erf(lw_px * cos_t / 2 / (blur * np.sqrt(2.0)))
    if line_peak / noise < 1.5 * MIN_LINE_SNR and rng.random() < 0.9:
        noise = max(0.5, line_peak / (1.5 * MIN_LINE_SNR))
    return ViewConditions(
        width=w,
        height=h,
        has_target=has_target,
        ring_count=n_rings,
        ring_min_diameter_mm=d_min,
        ring_max_diameter_mm=d_max,
        line_width_mm=line_mm,
        marker_diameter_mm=marker_d,
        marker_center_mm=marker,
        card_margin_mm=margin,
        focal_px=focal,
        distance_mm=distance,
        centre_px=(float(centre[0]), float(centre[1])),
        tilt_deg=tilt,
        tilt_axis_deg=float(rng.uniform(0.0, 360.0)),
        roll_deg=float(rng.uniform(0.0, 360.0)),
        paper_grey=paper,
        contrast_grey=contrast,
        blur_px=blur,
        noise_grey=noise,
        grain=float(rng.uniform(0.0, 0.04)),
        grain_px=float(rng.uniform(0.5, 3.0)),
        gradient=float(rng.uniform(0.0, 0.5)),
        gradient_dir_deg=float(rng.uniform(0.0, 360.0)),
        vignetting=float(rng.uniform(0.0, 0.5)),
        surroundings=surroundings,
        surround_grey=surround,
        laser=bool(rng.random() < 0.3),
        laser_width_px=float(rng.uniform(1.0, 5.0)),
        laser_peak_grey=float(rng.uniform(50.0, 300.0)),
        laser_angle_deg=float(rng.uniform(0.0, 180.0)),
        laser_offset_px=float(rng.uniform(-0.5, 0.5) * r_px),
        jpeg_quality=int(rng.choice([0, 0, 95, 85, 70])),
        bit_depth=int(rng.choice([8, 8, 16])),
        seed=int(rng.integers(2**31)),
    )


def _surroundings(c: ViewConditions, rng: np.random.Generator) -> NDArray:
    """The light of whatever is around the card, ``(H, W)`` grey levels."""
    h, w = c.height, c.width
    img = np.full((h, w), c.surround_grey, np.float32)
    if c.surroundings == "bright":
        return img
    # Low-frequency unevenness, then (cluttered) objects: blocks, bars, thin lines, circles.
    coarse = rng.normal(0.0, 0.15, (8, 8)).astype(np.float32)
    img *= 1.0 + cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    if c.surroundings == "dark":
        return np.clip(img, 0.0, None)
    top = max(c.paper_grey * 1.1, 60.0)
    for _ in range(int(rng.integers(10, 40))):
        kind = int(rng.integers(4))
        grey = float(rng.uniform(0.0, top))
        p = (int(rng.integers(w)), int(rng.integers(h)))
        if kind == 0:
            q = (
                p[0] + int(rng.integers(-w // 4, w // 4)),
                p[1] + int(rng.integers(-h // 4, h // 4)),
            )
            cv2.rectangle(img, p, q, grey, -1)
        elif kind == 1:
            q = (int(rng.integers(w)), int(rng.integers(h)))
            cv2.line(img, p, q, grey, int(rng.integers(1, 9)), cv2.LINE_AA)
        elif kind == 2:
            cv2.circle(img, p, int(rng.integers(5, h // 3)), grey, int(rng.integers(1, 6)))
        else:
            axes = (int(rng.integers(5, w // 5)), int(rng.integers(5, h // 5)))
            cv2.ellipse(img, p, axes, float(rng.uniform(0, 180)), 0, 360, grey, -1)
    return img


def _card_light(
    c: ViewConditions, printed: PrintedTarget, Hinv: NDArray
) -> tuple[NDArray, NDArray]:
    """Pixel-integrated albedo of the card (paper 1, ink 0) and its coverage, ``(H, W)``."""
    h, w = c.height, c.width
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x0, x1, y0, y1 = printed.card_bounds_mm()
    span = printed.paper_albedo - printed.ink_albedo

    def sample(u: NDArray, v: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        den = Hinv[2, 0] * u + Hinv[2, 1] * v + Hinv[2, 2]
        x = (Hinv[0, 0] * u + Hinv[0, 1] * v + Hinv[0, 2]) / den
        y = (Hinv[1, 0] * u + Hinv[1, 1] * v + Hinv[1, 2]) / den
        on = (den > 0) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        xs, ys = np.where(on, x, 0.0), np.where(on, y, 0.0)
        alb, edge = printed.albedo(xs, ys)
        return (alb - printed.ink_albedo) / span, on, edge, x, y

    alb, on, edge, x, y = sample(uu.ravel(), vv.ravel())
    x, y = x.reshape(h, w), y.reshape(h, w)
    foot = np.hypot(*np.gradient(x)) + np.hypot(*np.gradient(y))
    foot = np.where(np.isfinite(foot), foot, np.inf).ravel()
    light = np.where(on, alb, 0.0)
    cover = on.astype(np.float64)
    # Pixels near an edge (ink, card border, horizon): box integral over n x n samples.
    onb = on.reshape(h, w).astype(np.uint8)
    border = cv2.dilate(onb, np.ones((3, 3), np.uint8)) != cv2.erode(onb, np.ones((3, 3)))
    todo = np.flatnonzero((on & (edge < foot)) | border.ravel())
    n = _SUPERSAMPLE
    offs = (np.arange(n) + 0.5) / n - 0.5
    ou, ov = (a.ravel() for a in np.meshgrid(offs, offs))
    for s in range(0, len(todo), 65536):
        pix = todo[s : s + 65536]
        u = (pix % w)[:, None] + ou[None, :]
        v = (pix // w)[:, None] + ov[None, :]
        a, o, _, _, _ = sample(u.ravel(), v.ravel())
        light[pix] = np.where(o, a, 0.0).reshape(len(pix), -1).mean(axis=1)
        cover[pix] = o.reshape(len(pix), -1).mean(axis=1)
    return light.reshape(h, w), cover.reshape(h, w)


def render_view(c: ViewConditions, rng: np.random.Generator) -> RenderedView:
    """Render one view and its truth.

    Parameters
    ----------
    c : ViewConditions
    rng : numpy.random.Generator
        Draws the sensor noise (the clutter and grain come from ``c.seed``).

    Returns
    -------
    RenderedView
    """
    h, w = c.height, c.width
    K = np.array([[c.focal_px, 0.0, (w - 1) / 2], [0.0, c.focal_px, (h - 1) / 2], [0, 0, 1.0]])
    spec = target_spec(c)
    printed = PrintedTarget(spec, card_margin_mm=c.card_margin_mm)
    T = _cam_from_target(c, K)
    H = K @ T[:3, [0, 1, 3]]
    prng = np.random.default_rng(c.seed)
    img = _surroundings(c, prng)
    if c.has_target:
        light, cover = _card_light(c, printed, np.linalg.inv(H))
        if c.grain > 0:
            g = prng.standard_normal((h, w)).astype(np.float32)
            g = cv2.GaussianBlur(g, (0, 0), c.grain_px)
            g *= c.grain / max(float(g.std()), 1e-9)
            light = light * (1.0 + g)
        ink = c.paper_grey - c.contrast_grey
        card = ink + c.contrast_grey * light
        img = (img * (1.0 - cover) + card * cover).astype(np.float32)
    else:
        cover = np.zeros((h, w))
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    du, dv = (uu - w / 2) / (w / 2), (vv - h / 2) / (h / 2)
    g = np.radians(c.gradient_dir_deg)
    illum = 1.0 + 0.5 * c.gradient * (np.cos(g) * du + np.sin(g) * dv)
    illum *= 1.0 - c.vignetting * (du * du + dv * dv) / 2.0
    img = img * illum
    if c.laser:
        a = np.radians(c.laser_angle_deg)
        nrm = np.array([-np.sin(a), np.cos(a)])
        dist = (uu - c.centre_px[0]) * nrm[0] + (vv - c.centre_px[1]) * nrm[1] - c.laser_offset_px
        img = img + c.laser_peak_grey * np.exp(-0.5 * (dist / c.laser_width_px) ** 2)
    if c.blur_px > 0:
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), c.blur_px)
    img = img + rng.normal(0.0, c.noise_grey, img.shape).astype(np.float32)
    if c.bit_depth == 16:
        out = np.clip(np.rint(img * 257.0), 0, 65535).astype(np.uint16)
    else:
        out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if c.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, c.jpeg_quality])
            if ok:
                out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return _with_truth(c, out, spec, K, T, H, float(1.0 - cover.mean()))


def _project(H: NDArray, pts: NDArray) -> NDArray:
    x = np.column_stack([pts[:, :2], np.ones(len(pts))]) @ H.T
    return x[:, :2] / x[:, 2:3]


def _with_truth(
    c: ViewConditions,
    image: NDArray,
    spec: ConcentricCirclesTarget,
    K: NDArray,
    T: NDArray,
    H: NDArray,
    surround_frac: float,
) -> RenderedView:
    w, h = c.width, c.height
    radii = spec.ring_radii_mm
    names, pts = ["O"], [np.zeros(3)]
    for k, r in enumerate(radii):
        for axis, idx in (("x", 0), ("y", 1)):
            for sgn, mark in ((1.0, "+"), (-1.0, "-")):
                p = np.zeros(3)
                p[idx] = sgn * r
                names.append(f"r{k}{mark}{axis}")
                pts.append(p)
    pts_t = np.asarray(pts)
    pts_px = _project(H, pts_t)

    def inside(p: NDArray, margin: float = 0.0) -> NDArray:
        return (
            (p[:, 0] >= margin)
            & (p[:, 0] <= w - 1 - margin)
            & (p[:, 1] >= margin)
            & (p[:, 1] <= h - 1 - margin)
        )

    named = {"O": pts_px[0]}
    kmax = len(radii) - 1
    for key, nm in (
        ("A", f"r{kmax}+x"),
        ("B", f"r{kmax}-x"),
        ("C", f"r{kmax}+y"),
        ("D", f"r{kmax}-y"),
    ):
        p = pts_px[names.index(nm)]
        if inside(p[None])[0]:
            named[key] = p
    # Rings from the centre out with >= 60 % of their circumference inside the image.
    ang = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    unit = np.column_stack([np.cos(ang), np.sin(ang)])
    visible = 0
    spacing = np.inf
    prev = None
    for r in radii:
        ring = _project(H, r * unit)
        if prev is not None:
            spacing = min(spacing, float(np.min(np.linalg.norm(ring - prev, axis=1))))
        prev = ring
        if np.mean(inside(ring, 3.0)) >= 0.6 and visible == int(np.flatnonzero(radii == r)[0]):
            visible += 1
    # Marker and the paper around it (the labeller compares the disc with 1.6 radii).
    m = spec.orientation_marker
    mk = np.asarray(m.center_mm) + 0.8 * m.diameter_mm * unit[::10]
    marker_in = bool(np.all(inside(_project(H, mk), 2.0)))
    # Line contrast after blur (a box of the line width through a Gaussian) over the noise.
    lw = c.line_width_px * np.cos(np.radians(c.tilt_deg))
    s = max(c.blur_px, 1e-3) * np.sqrt(2.0)
    peak = math.erf(lw / 2 / s)
    snr = c.contrast_grey * (1 - c.vignetting) * peak / max(c.noise_grey, 1e-3)
    why = ""
    if not c.has_target:
        why = "no target"
    elif not inside(pts_px[:1], 5.0)[0]:
        why = "centre outside the image"
    elif visible < MIN_VISIBLE_RINGS:
        why = f"{visible} rings inside the image"
    elif not marker_in:
        why = "orientation marker outside the image"
    elif snr < MIN_LINE_SNR:
        why = f"line contrast over noise {snr:.1f} < {MIN_LINE_SNR}"
    return RenderedView(
        image=image,
        conditions=c,
        spec=spec,
        K=K,
        cam_from_target=T,
        center_px=pts_px[0],
        named_px=named,
        points_target=pts_t,
        points_px=pts_px,
        point_names=names,
        detectable=not why,
        why_not=why,
        surround_frac=surround_frac,
        visible_rings=visible,
        line_snr=float(snr),
        min_spacing_px=float(spacing),
    )
