"""Rendering by inverse mapping: pixel samples -> undistorted rays -> nearest surface -> shade.

Each pixel is first shaded at its centre. Pixels whose footprint may straddle an albedo edge
(printed marks, card border), a silhouette (neighbours see different surfaces) or the laser band
are shaded again with ``n*n`` samples on an n-rooks pattern (every sample has its own column
and row offset, so even edges aligned with the pixel grid are integrated in ``n*n`` steps) and
averaged: the box integral of the pixel's footprint. Rays of sub-pixel samples come from the
exactly undistorted ray map of pixel centres by bilinear interpolation (the lens mapping is
smooth over a pixel; the interpolation error is far below 1e-4 px).

The sensor then applies, in order: vignetting (cos^4-like), laser speckle (multiplicative,
spatially correlated, on the laser light only), the optical blur (Gaussian PSF), shot noise
(Gaussian approximation of Poisson with the full-well gain), read noise, the black level and
quantisation to 8 or 16 bits, clipping at the white level (saturation). A colour camera
(:func:`expose_colour`) samples the blurred light through a Bayer mosaic, each photosite with
its own noise and clipping, and demosaics.

Radiance is in units of the sensor's full scale: 1.0 is the white level.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.conventions import invert_transform, transform_points
from scanner.virtual_cell.cell import CameraConfig, CellConfig, ImagingConfig
from scanner.virtual_cell.scene import (
    Surface,
    first_hits,
    section_points,
    segment_blocked,
)

__all__ = [
    "Laser",
    "Scene",
    "StripeTruth",
    "expose",
    "expose_colour",
    "ray_map",
    "render_radiance",
    "stripe_truth",
]

log = logging.getLogger(__name__)

_CHUNK = 1 << 18
_BAND_SIGMAS = 4.5  # exp(-4.5**2 / 2) = 4e-5 of the peak: below a grey level


@dataclass(frozen=True)
class Laser:
    """The laser in the scene's world frame: plane ``normal . p + d = 0``, origin, profile."""

    normal: NDArray
    d: float
    origin: NDArray
    sigma_mm: float
    power: float
    reference_distance_mm: float
    width_model: str = "surface"

    @classmethod
    def from_cell(cls, cell: CellConfig, world_from_cam: NDArray) -> Laser:
        """The cell's laser (given in the camera frame) moved into the world frame."""
        lc = cell.laser
        rot, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
        n = rot @ lc.normal
        origin = rot @ lc.origin + t
        return cls(
            normal=n,
            d=float(lc.d - n @ t),
            origin=origin,
            sigma_mm=lc.sigma_mm,
            power=lc.power,
            reference_distance_mm=lc.reference_distance_mm,
            width_model=lc.width_model,
        )


@dataclass
class Scene:
    """Surfaces in a world frame and where the camera is in it.

    ``paper_albedo`` is the albedo that renders at the exposure level (the white card).
    """

    surfaces: list[Surface]
    world_from_cam: NDArray
    paper_albedo: float = 0.85

    def surface_index(self, surface_id: str) -> int:
        for k, s in enumerate(self.surfaces):
            if s.id == surface_id:
                return k
        raise ValueError(
            f"surface id: expected one of {[s.id for s in self.surfaces]}, got {surface_id!r}"
        )


@dataclass(frozen=True)
class StripeTruth:
    """Exact stripe centre curve: the light plane cut with the visible, lit surfaces.

    Attributes
    ----------
    uv : ndarray, shape (M, 2)
        Projections of the curve points into the image (distorted pixels).
    surface : ndarray, shape (M,)
        Index of the surface in ``Scene.surfaces`` each point lies on.
    points_world : ndarray, shape (M, 3)
        The curve points in the scene's world frame, mm.
    surface_ids : tuple of str
        ``Scene.surfaces[k].id`` for each index k.
    """

    uv: NDArray
    surface: NDArray
    points_world: NDArray
    surface_ids: tuple[str, ...]


@functools.lru_cache(maxsize=4)
def _ray_map_cached(key: tuple) -> NDArray:
    width, height, fx, fy, cx, cy, dist = key
    cam = CameraConfig(width, height, fx, fy, cx, cy, dist).model()
    u = np.arange(-1, width + 1, dtype=np.float64)
    v = np.arange(-1, height + 1, dtype=np.float64)
    if not cam.has_distortion:
        x = (u - cx) / fx
        y = (v - cy) / fy
        xy = np.empty((len(v), len(u), 2))
        xy[:, :, 0] = x[None, :]
        xy[:, :, 1] = y[:, None]
        return xy
    uu, vv = np.meshgrid(u, v)
    xy = cam.normalize(np.column_stack([uu.ravel(), vv.ravel()]))
    return xy.reshape(len(v), len(u), 2)


def ray_map(camera: CameraConfig) -> NDArray:
    """Undistorted normalised coordinates ``(H+2, W+2, 2)`` of pixel centres u = -1..W, v = -1..H.

    Cached per camera (the exact undistortion of a megapixel frame takes about a second).
    """
    key = (
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        tuple(camera.dist),
    )
    return _ray_map_cached(key)


def _sample_offsets(n: int) -> NDArray:
    """``(n*n, 2)`` offsets in [-0.5, 0.5): stratified in 2-D and n-rooks on each axis."""
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x = (b + (a + 0.5) / n) / n - 0.5
    y = (a + (b + 0.5) / n) / n - 0.5
    return np.column_stack([x.ravel(), y.ravel()])


def _shade(
    scene: Scene,
    laser: Laser | None,
    xy: NDArray,
    ambient: float,
    focal_px: float,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Shade rays through undistorted normalised coordinates ``xy`` (N, 2).

    Returns ambient radiance, laser radiance, surface index (-1: nothing), "needs
    supersampling" (an edge or the laser band within the pixel footprint) and "in the laser
    band", each ``(N,)``.
    """
    n = len(xy)
    rot = scene.world_from_cam[:3, :3]
    origin = scene.world_from_cam[:3, 3]
    dirs = np.empty((n, 3))
    for k in range(3):
        dirs[:, k] = xy[:, 0] * rot[k, 0] + xy[:, 1] * rot[k, 1] + rot[k, 2]
    t, idx = first_hits(scene.surfaces, origin, dirs)
    hit = idx >= 0
    t = np.where(hit, t, 0.0)
    albedo = np.zeros(n)
    edge = np.full(n, np.inf)
    for k, surf in enumerate(scene.surfaces):
        sel = np.flatnonzero(idx == k)
        if not len(sel):
            continue
        if surf.textured:
            albedo[sel], edge[sel] = surf.albedo(origin + dirs[sel] * t[sel, None])
        else:
            albedo[sel] = surf.albedo_value
    rel = albedo / scene.paper_albedo
    amb = rel * ambient
    las = np.zeros(n)
    need = np.zeros(n, dtype=bool)
    # Size of one pixel on a surface seen face-on; grazing views stretch it up to 10 times.
    px_mm = t * np.sqrt(np.einsum("ij,ij->i", dirs, dirs)) / focal_px
    cand = hit & (edge < 10.0 * px_mm)
    f = None
    if laser is not None:
        band_mm = _BAND_SIGMAS * laser.sigma_mm
        f = (laser.normal @ origin + laser.d) + t * (dirs @ laser.normal)
        cand |= hit & (np.abs(f) < band_mm + 10.0 * px_mm)
    band = np.zeros(n, dtype=bool)
    c = np.flatnonzero(cand)
    if not len(c):
        return amb, las, idx, need, band
    d_c = dirs[c]
    p = origin + d_c * t[c, None]
    normals = np.empty((len(c), 3))
    for k in np.unique(idx[c]):
        sel = idx[c] == k
        normals[sel] = scene.surfaces[k].normal(p[sel])
    dist = np.linalg.norm(d_c, axis=1)
    cos_view = np.abs(np.einsum("ij,ij->i", normals, d_c)) / dist
    footprint = t[c] * dist / focal_px / np.maximum(cos_view, 0.1)
    need_c = edge[c] < 0.75 * footprint  # a pixel corner is 0.71 px from its centre
    if laser is not None and f is not None:
        f_c = f[c]
        if laser.width_model == "surface":
            sin_cut = np.sqrt(np.clip(1 - (normals @ laser.normal) ** 2, 1e-6, None))
            s_mm = f_c / sin_cut
        else:
            s_mm = f_c
        near = np.abs(s_mm) < band_mm + footprint
        need_c |= near
        band[c] = near
        b = np.flatnonzero(np.abs(s_mm) < band_mm)
        if len(b):
            pb = p[b]
            to_p = pb - laser.origin
            r = np.linalg.norm(to_p, axis=1)
            cos_in = np.abs(np.einsum("ij,ij->i", normals[b], to_p)) / r
            lit = ~segment_blocked(scene.surfaces, laser.origin, pb)
            profile = np.exp(-0.5 * (s_mm[b] / laser.sigma_mm) ** 2)
            las[c[b]] = (
                laser.power * rel[c[b]] * cos_in * (laser.reference_distance_mm / r) * profile * lit
            )
    need[c] = need_c
    return amb, las, idx, need, band


def _supersample(
    scene: Scene,
    laser: Laser | None,
    rmap: NDArray,
    pixels: NDArray,
    width: int,
    n: int,
    ambient: float,
    focal: float,
) -> tuple[NDArray, NDArray]:
    """Mean ambient and laser radiance over ``n*n`` samples in each of ``pixels`` (flat ids)."""
    offsets = _sample_offsets(n)
    amb = np.empty(len(pixels))
    las = np.empty(len(pixels))
    per_chunk = max(1, _CHUNK // len(offsets))
    for s in range(0, len(pixels), per_chunk):
        pix = pixels[s : s + per_chunk]
        u = pix % width + 1
        v = pix // width + 1
        centre = rmap[v, u]
        ju = (rmap[v, u + 1] - rmap[v, u - 1]) / 2
        jv = (rmap[v + 1, u] - rmap[v - 1, u]) / 2
        # Local affine model of the lens over one pixel (its curvature is negligible there).
        xy = (
            centre[:, None, :]
            + ju[:, None, :] * offsets[None, :, :1]
            + jv[:, None, :] * offsets[None, :, 1:]
        ).reshape(-1, 2)
        a, l_, _, _, _ = _shade(scene, laser, xy, ambient, focal)
        amb[s : s + per_chunk] = a.reshape(len(pix), -1).mean(axis=1)
        las[s : s + per_chunk] = l_.reshape(len(pix), -1).mean(axis=1)
    return amb, las


def _vignetting(imaging: ImagingConfig, xy: NDArray) -> NDArray:
    c2 = 1.0 / (1.0 + np.einsum("ij,ij->i", xy, xy))
    return (1.0 - imaging.vignetting) + imaging.vignetting * c2 * c2


def render_radiance_coarse_ambient(
    camera: CameraConfig,
    imaging: ImagingConfig,
    scene: Scene,
    ambient: float,
    laser: Laser,
    step: int = 2,
) -> tuple[NDArray, NDArray]:
    """Like :func:`render_radiance`, faster, for laser images whose ambient light is dim.

    The scene is shaded every ``step`` pixels and the (dim) ambient image interpolated in
    between; every pixel near the laser line is shaded fully, with supersampling. The laser
    light is exactly as in :func:`render_radiance`; the ambient light loses detail finer than
    ``step`` pixels (a few grey levels at silhouettes, under the noise of a laser image).
    """
    w, h = camera.width, camera.height
    rmap = ray_map(camera)
    wc, hc = (w + step - 1) // step, (h + step - 1) // step
    centres = rmap[1 : h + 1 : step, 1 : w + 1 : step].reshape(-1, 2)
    focal = float(min(camera.fx, camera.fy))
    amb_c = np.empty(len(centres))
    band_c = np.empty(len(centres), dtype=bool)
    for s in range(0, len(centres), _CHUNK):
        sl = slice(s, s + _CHUNK)
        amb_c[sl], _, _, _, band_c[sl] = _shade(scene, laser, centres[sl], ambient, focal)
    to_full = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    amb = (
        cv2.warpAffine(
            amb_c.reshape(hc, wc).astype(np.float32),
            to_full,
            (w, h),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        .ravel()
        .astype(np.float64)
    )
    band = cv2.dilate(band_c.reshape(hc, wc).astype(np.uint8), np.ones((3, 3), np.uint8))
    band = np.repeat(np.repeat(band, step, axis=0), step, axis=1)[:h, :w]
    todo = np.flatnonzero(band.ravel())
    las = np.zeros(w * h)
    if len(todo):
        amb[todo], las[todo] = _supersample(
            scene, laser, rmap, todo, w, max(imaging.supersample, 1), ambient, focal
        )
    vig = _vignetting(imaging, rmap[1:-1, 1:-1].reshape(-1, 2))
    return (amb * vig).reshape(h, w).astype(np.float32), (las * vig).reshape(h, w).astype(
        np.float32
    )


def render_radiance(
    camera: CameraConfig,
    imaging: ImagingConfig,
    scene: Scene,
    ambient: float,
    laser: Laser | None = None,
) -> tuple[NDArray, NDArray]:
    """Pixel-integrated radiance images, vignetting applied, before blur and noise.

    Parameters
    ----------
    camera, imaging
        The cell's camera and imaging chain.
    scene : Scene
    ambient : float
        Radiance of the white card under the ambient light (fraction of full scale).
    laser : Laser, optional
        The laser in the scene's world frame; None: laser off.

    Returns
    -------
    ambient_image, laser_image : ndarray, shape (H, W), float32
    """
    w, h = camera.width, camera.height
    rmap = ray_map(camera)
    centres = rmap[1:-1, 1:-1].reshape(-1, 2)
    focal = float(min(camera.fx, camera.fy))
    amb = np.empty(w * h)
    las = np.empty(w * h)
    idx = np.empty(w * h, dtype=np.int32)
    need = np.empty(w * h, dtype=bool)
    for s in range(0, w * h, _CHUNK):
        sl = slice(s, s + _CHUNK)
        amb[sl], las[sl], idx[sl], need[sl], _ = _shade(scene, laser, centres[sl], ambient, focal)
    idx2 = idx.reshape(h, w)
    sil = np.zeros((h, w), dtype=bool)
    dv = idx2[1:, :] != idx2[:-1, :]
    du = idx2[:, 1:] != idx2[:, :-1]
    sil[1:, :] |= dv
    sil[:-1, :] |= dv
    sil[:, 1:] |= du
    sil[:, :-1] |= du
    todo = np.flatnonzero(need | sil.ravel())
    if imaging.supersample > 1 and len(todo):
        amb[todo], las[todo] = _supersample(
            scene, laser, rmap, todo, w, imaging.supersample, ambient, focal
        )
    log.debug("supersampled %d of %d pixels", len(todo), w * h)
    vig = _vignetting(imaging, centres)
    amb = (amb * vig).reshape(h, w).astype(np.float32)
    las = (las * vig).reshape(h, w).astype(np.float32)
    return amb, las


def speckle_field(
    shape: tuple[int, int], contrast: float, size_px: float, rng: np.random.Generator
) -> NDArray:
    """Multiplicative speckle: mean 1, spatially correlated over ``size_px``, >= 0."""
    noise = rng.standard_normal(shape, dtype=np.float32)
    if size_px > 0:
        noise = cv2.GaussianBlur(noise, (0, 0), size_px)
        noise /= max(float(noise.std()), 1e-9)
    return np.clip(1.0 + contrast * noise, 0.0, None)


def expose(
    radiance: NDArray,
    imaging: ImagingConfig,
    bit_depth: int,
    rng: np.random.Generator | None,
) -> NDArray:
    """Blur, noise, black level and quantisation of a radiance image (full scale = 1).

    ``rng=None`` gives the noise-free image (blur and quantisation only).
    """
    return _sense(_blur(radiance, imaging), imaging, bit_depth, rng)


def expose_colour(
    ambient: NDArray,
    laser: NDArray,
    laser_rgb: tuple[float, float, float],
    imaging: ImagingConfig,
    bit_depth: int,
    rng: np.random.Generator | None,
) -> NDArray:
    """The colour camera's ``(H, W, 3)`` BGR image of white ambient light and the laser.

    The optics blur the light; each photosite of the Bayer mosaic (blue at even rows and
    columns, red at odd ones, green between) sees its own filter's share of it, with its own
    noise and clipping; the camera then interpolates the missing colours (OpenCV's bilinear
    demosaicing). A red laser strong enough to clip the red pixels leaves the green and
    blue ones below full scale, as real colour cameras do.
    """
    amb = _blur(ambient, imaging)
    las = _blur(laser, imaging)
    h, w = amb.shape
    odd_row = (np.arange(h) % 2 == 1)[:, None]
    odd_col = (np.arange(w) % 2 == 1)[None, :]
    red, green, blue = (np.float32(g) for g in laser_rgb)
    gain = np.where(odd_row & odd_col, red, np.where(~odd_row & ~odd_col, blue, green))
    raw = _sense(amb + las * gain, imaging, bit_depth, rng)
    # OpenCV names a Bayer pattern by the second row's second and third pixels: red, green.
    return cv2.cvtColor(raw, cv2.COLOR_BayerRG2BGR)


def _blur(radiance: NDArray, imaging: ImagingConfig) -> NDArray:
    img = np.asarray(radiance, dtype=np.float32)
    if imaging.psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), imaging.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    return img


def _sense(
    img: NDArray, imaging: ImagingConfig, bit_depth: int, rng: np.random.Generator | None
) -> NDArray:
    """Shot and read noise, black level, quantisation and clipping of blurred radiance."""
    if rng is not None:
        electrons = img * np.float32(imaging.full_well_e)
        shot = np.sqrt(np.clip(electrons, 0, None)) * rng.standard_normal(
            img.shape, dtype=np.float32
        )
        read = np.float32(imaging.read_noise_e) * rng.standard_normal(img.shape, dtype=np.float32)
        img = (electrons + shot + read) / np.float32(imaging.full_well_e)
    full = 255.0 if bit_depth == 8 else 65535.0
    black = imaging.black_level_dn * full / 255.0
    dn = np.rint(img * np.float32(full - black) + np.float32(black))
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.clip(dn, 0, full).astype(dtype)


def stripe_truth(
    camera: CameraConfig, scene: Scene, laser: Laser, step_px: float = 0.5
) -> StripeTruth:
    """The exact laser line: plane-surface cuts that the camera sees and the laser lights.

    Points are sampled about every ``step_px`` pixels (at the scene's mean depth), kept where
    the camera ray meets that surface first (occlusion), the segment from the laser origin is
    free (shadows) and the projection falls inside the image.
    """
    cam_from_world = invert_transform(scene.world_from_cam)
    origin = scene.world_from_cam[:3, 3]
    # Sampling step from the distance of the camera to the laser-lit region.
    # Sampling step: step_px at the median distance of the lit curve seen in the image, found
    # from a coarse pass (unbounded surfaces are cut within a generous radius of the camera).
    reach = max(abs(laser.d + laser.normal @ origin), 50.0) * 12
    coarse, _ = section_points(
        scene.surfaces, laser.normal, laser.d, 2.0, clip_center=origin, clip_radius=reach
    )
    focal = max(camera.fx, camera.fy)
    if len(coarse):
        pc0 = transform_points(cam_from_world, coarse)
        ok = pc0[:, 2] > 1e-3
        uv0 = camera.model().project(pc0[ok]) if np.any(ok) else np.zeros((0, 2))
        seen = camera.model().in_image(uv0, -50.0)
        dist = np.linalg.norm(pc0[ok][seen], axis=1) if np.any(seen) else np.array([reach / 4])
        reach = min(reach, float(dist.max()) * 1.5)
        step_mm = step_px * float(np.median(dist)) / focal
    else:
        step_mm = step_px * reach / 12 / focal
    pts, sid = section_points(
        scene.surfaces, laser.normal, laser.d, step_mm, clip_center=origin, clip_radius=reach
    )
    ids = tuple(s.id for s in scene.surfaces)
    empty = StripeTruth(np.zeros((0, 2)), np.zeros(0, dtype=np.int32), np.zeros((0, 3)), ids)
    if not len(pts):
        return empty
    pc = transform_points(cam_from_world, pts)
    front = pc[:, 2] > 1e-3
    pts, sid, pc = pts[front], sid[front], pc[front]
    if not len(pts):
        return empty
    t, idx = first_hits(scene.surfaces, origin, pts - origin)
    visible = (idx == sid) & (t > 1.0 - 1e-7)
    lit = ~segment_blocked(scene.surfaces, laser.origin, pts)
    keep = visible & lit
    model = camera.model()
    uv = model.project(pc[keep])
    inside = model.in_image(uv)
    if model.has_distortion and np.any(inside):
        # Far outside the field the distortion polynomial folds back into the image: keep
        # only points whose pixel undistorts to their own ray (as the renderer sees them).
        xy = pc[keep][:, :2] / pc[keep][:, 2:]
        back = np.full_like(xy, np.inf)
        back[inside] = model.normalize(uv[inside])
        inside &= np.linalg.norm(back - xy, axis=1) < 1e-6
    return StripeTruth(uv[inside], sid[keep][inside], pts[keep][inside], ids)
