"""The laser origin from shadow edges: lines found in a stripe, and where they meet."""

from __future__ import annotations

import numpy as np

from calibration.laser_origin import ShadowLine, estimate_laser_origin, shadow_lines
from scanner.core.camera import CameraModel
from scanner.formats.calibration_file import LightPlane

CAMERA = CameraModel(
    1280, 1024, np.array([[1800.0, 0, 640], [0, 1800.0, 512], [0, 0, 1]]), np.zeros(5)
)
ORIGIN = np.array([10.0, -140.0, -5.0])
# The plane through the origin and the optical axis at z = 350 mm, holding the x axis; the
# camera on its negative side (d < 0).
_N = np.cross([1.0, 0.0, 0.0], np.array([0.0, 0.0, 350.0]) - ORIGIN)
_N /= np.linalg.norm(_N)
_D = -float(_N @ ORIGIN)
PLANE = LightPlane(_N, _D) if _D < 0 else LightPlane(-_N, -_D)


def _on_plane(x_mm: float, z_mm: float) -> np.ndarray:
    """The point of the light plane at camera x and z (its y follows)."""
    n, d = PLANE.normal, PLANE.d
    return np.array([x_mm, -(n[0] * x_mm + n[2] * z_mm + d) / n[1], z_mm])


def _ray_point(origin: np.ndarray, through: np.ndarray, z_mm: float) -> np.ndarray:
    t = (z_mm - origin[2]) / (through[2] - origin[2])
    return origin + t * (through - origin)


def _shadow_case(rng: np.random.Generator, edge_x_mm: float, near_z: float, far_z: float):
    """A card at depth ``near_z`` ending at x = ``edge_x_mm``, a table at ``far_z`` behind it: the
    exact edge and shadow points and the stripe's pixels (1 px apart, 0.05 px noise)."""
    edge = _on_plane(edge_x_mm, near_z)
    shadow = _ray_point(ORIGIN, edge, far_z)
    card = np.array([_on_plane(x, near_z) for x in np.linspace(edge_x_mm - 60, edge_x_mm, 400)])
    table = np.array([_on_plane(x, far_z) for x in np.linspace(shadow[0], shadow[0] + 80, 400)])
    uv = []
    for pts in (card, table):
        px = CAMERA.project(pts)
        # resample at about a pixel along the stripe, from end to end
        s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(px, axis=0), axis=1))])
        steps = np.linspace(0.0, s[-1], int(s[-1]) + 1)
        uv.append(np.column_stack([np.interp(steps, s, px[:, k]) for k in range(2)]))
    uv = np.vstack(uv)
    return edge, shadow, uv + rng.normal(0, 0.05, uv.shape)


def test_a_depth_jump_gives_the_line_from_the_edge_to_its_shadow():
    rng = np.random.default_rng(0)
    edge, shadow, uv = _shadow_case(rng, 30.0, 420.0, 700.0)
    lines = shadow_lines(uv, CAMERA, PLANE, frame_id=3)
    assert len(lines) == 1
    line = lines[0]
    assert line.frame_id == 3
    # Each end within two pixels' footprint of the truth (a stripe ends to a pixel).
    assert np.linalg.norm(line.near_cam - edge) < 2 * np.linalg.norm(edge) / 1800
    assert np.linalg.norm(line.far_cam - shadow) < 2 * np.linalg.norm(shadow) / 1800
    assert np.linalg.norm(line.near_step_cam) > 0


def test_a_blurred_end_is_placed_at_its_half_contrast_point():
    rng = np.random.default_rng(5)
    edge, _, uv = _shadow_case(rng, 30.0, 420.0, 700.0)
    n_card = int(np.argmax(np.linalg.norm(np.diff(uv, axis=0), axis=1) > 5)) + 1
    # The blur spreads the card's bright stripe two pixels past the edge, fading; the last
    # exact point is at the edge itself.
    step = (uv[n_card - 1] - uv[n_card - 11]) / 10
    tail = uv[n_card - 1] + np.outer([1.0, 2.0], step)
    uv = np.vstack([uv[:n_card], tail, uv[n_card:]])
    contrast = np.full(len(uv), 200.0)
    contrast[n_card - 1 : n_card + 2] = [100.0, 40.0, 12.0]  # half of the plateau at the edge
    px_mm = np.linalg.norm(edge) / 1800
    plain = shadow_lines(uv, CAMERA, PLANE)[0]
    halved = shadow_lines(uv, CAMERA, PLANE, contrast=contrast)[0]
    assert np.linalg.norm(plain.near_cam - edge) > 1.5 * px_mm  # the last peak: 2 px out
    assert np.linalg.norm(halved.near_cam - edge) < 0.25 * px_mm


def test_a_stretch_ending_at_the_image_border_gives_no_line():
    rng = np.random.default_rng(1)
    edge, _, uv = _shadow_case(rng, 30.0, 420.0, 700.0)
    assert len(shadow_lines(uv, CAMERA, PLANE)) == 1
    # The same stripe seen by a narrower camera whose right border falls on the card's end:
    # there the stretch leaves the image, and the end it shows is not the card's edge.
    edge_u = float(CAMERA.project(edge[None])[0, 0])
    narrow = CameraModel(int(np.ceil(edge_u + 1.0)), CAMERA.height, CAMERA.K, CAMERA.dist)
    assert shadow_lines(uv, narrow, PLANE) == []


def test_a_broken_stretch_gives_no_line_at_its_break():
    rng = np.random.default_rng(4)
    _, _, uv = _shadow_case(rng, 30.0, 420.0, 700.0)
    # A 6-px dropout in the middle of the card's stretch (speckle) is bridged or skipped: the
    # one line found is still the edge's.
    card = np.flatnonzero(np.arange(len(uv)) < len(uv) // 2)
    keep = np.ones(len(uv), bool)
    keep[card[len(card) // 2 : len(card) // 2 + 6]] = False
    lines = shadow_lines(uv[keep], CAMERA, PLANE)
    assert len(lines) == 1 and np.linalg.norm(lines[0].far_cam - lines[0].near_cam) > 100


def _line(frame: int, edge_x: float, near_z: float, far_z: float, sigma: float, rng):
    edge = _on_plane(edge_x, near_z)
    far = _ray_point(ORIGIN, edge, far_z)
    u = (far - edge) / np.linalg.norm(far - edge)
    across = np.cross(PLANE.normal, u)
    # One pixel outwards along each surface's stretch: +x on the card, -x on the table.
    along_x = _on_plane(1.0, 0.0) - _on_plane(0.0, 0.0)
    return ShadowLine(
        frame,
        edge + rng.normal(0, sigma) * across,
        far + rng.normal(0, sigma) * across,
        sigma,
        sigma,
        0.25 * along_x,
        -0.4 * along_x,
    )


def test_the_origin_is_where_the_shadow_lines_meet_within_its_uncertainty():
    rng = np.random.default_rng(2)
    errors = []
    for _ in range(20):
        lines = [
            _line(k, x, z, z + rng.uniform(150, 350), 0.1, rng)
            for k, (x, z) in enumerate(
                zip(rng.uniform(-120, 120, 12), rng.uniform(330, 480, 12), strict=True)
            )
        ]
        # Lines that miss the origin by centimetres (the camera's view ends the far stripe).
        for k in range(4):
            bad = _line(100 + k, rng.uniform(-100, 100), 400.0, 650.0, 0.1, rng)
            lines.append(
                ShadowLine(
                    bad.frame_id,
                    bad.near_cam,
                    bad.far_cam + 40.0 * (_on_plane(1.0, 0.0) - _on_plane(0.0, 0.0)),
                    0.1,
                    0.1,
                    bad.near_step_cam,
                    bad.far_step_cam,
                )
            )
        res = estimate_laser_origin(lines, PLANE)
        assert res, res.reason
        assert res.inliers >= 10 and not set(res.frames) & {100, 101, 102, 103}
        assert abs(PLANE.signed_distance(res.origin_cam[None])[0]) < 1e-6
        err = res.origin_cam - ORIGIN
        errors.append(np.sqrt(err @ np.linalg.pinv(res.covariance_mm2) @ err))
        assert np.linalg.norm(err) < 5 * res.std_mm
    # The stated covariance is honest: Mahalanobis distances (2 dof) mostly within 2.5.
    assert np.mean(np.array(errors) < 2.5) >= 0.8


def test_too_few_or_one_frames_lines_are_refused_with_the_reason():
    rng = np.random.default_rng(3)
    res = estimate_laser_origin([_line(0, 10.0, 400.0, 700.0, 0.1, rng)], PLANE)
    assert not res and "at least 3" in res.reason
    same_frame = [_line(0, x, 400.0, 700.0, 0.1, rng) for x in (-80.0, 0.0, 80.0)]
    res = estimate_laser_origin(same_frame, PLANE)
    assert not res and res.reason
