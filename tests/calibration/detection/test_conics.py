import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.detection.conics import (
    circle_tilt_deg,
    conic_from_coefficients,
    conic_ray_distances,
    fit_conic,
    fit_line,
    harmonic_conjugate,
    intersect_lines,
    line_conic_intersections,
    line_through,
    pencil_center,
    pencil_member,
    sampson_distances,
)


def _homography() -> np.ndarray:
    # A plane seen obliquely: K [r1 r2 t].
    K = np.array([[1500.0, 0, 640], [0, 1490.0, 512], [0, 0, 1]])
    a = np.radians(35)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    t = np.array([10.0, -20.0, 500.0])
    return K @ np.column_stack([R[:, 0], R[:, 1], t])


def _circle_image(H: np.ndarray, r: float, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    x = H @ np.vstack([r * np.cos(th), r * np.sin(th), np.ones(n)])
    pts = (x[:2] / x[2]).T
    Hi = np.linalg.inv(H)
    C = Hi.T @ np.diag([1.0, 1.0, -(r**2)]) @ Hi
    return pts, C / np.linalg.norm(C)


def test_fit_conic_recovers_projected_circle():
    rng = np.random.default_rng(0)
    pts, C_true = _circle_image(_homography(), 60.0)
    C = fit_conic(pts + rng.normal(0, 0.02, pts.shape))
    C *= np.sign(C[0, 0]) * np.sign(C_true[0, 0])
    # Sampson distances of the exact points to the fitted conic: at the noise level.
    assert np.sqrt(np.mean(sampson_distances(C, pts) ** 2)) < 0.01


@pytest.mark.parametrize("arc_deg", [360.0, 120.0, 45.0])
def test_fit_conic_reaches_the_sampson_minimum(arc_deg):
    """The refinement (five directions orthogonal to the algebraic solution) ends where a
    tightly converged fit of all six coefficients does, on whole rings and short arcs."""
    rng = np.random.default_rng(int(arc_deg))
    th = np.radians(np.linspace(0.0, arc_deg, 300, endpoint=False))
    H = _homography()
    x = H @ np.vstack([60 * np.cos(th), 60 * np.sin(th), np.ones_like(th)])
    pts = (x[:2] / x[2]).T + rng.normal(0, 0.3, (len(th), 2))
    fitted = fit_conic(pts)

    def rms(coefficients: np.ndarray) -> float:
        conic = conic_from_coefficients(coefficients)
        return float(np.sqrt(np.mean(sampson_distances(conic, pts) ** 2)))

    def resid(coefficients: np.ndarray) -> np.ndarray:
        return sampson_distances(conic_from_coefficients(coefficients), pts)

    def coefficients_of(conic: np.ndarray) -> np.ndarray:
        return np.array(
            [
                conic[0, 0],
                2 * conic[0, 1],
                conic[1, 1],
                2 * conic[0, 2],
                2 * conic[1, 2],
                conic[2, 2],
            ]
        )

    fitted_coefficients = coefficients_of(fitted)
    # The reference: every coefficient free, from a start well off the minimum.
    perturbed = fitted_coefficients + rng.normal(0, 1e-3, 6) * np.abs(fitted_coefficients).max()
    reference = least_squares(resid, perturbed, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert rms(fitted_coefficients) <= rms(reference.x) * (1 + 1e-6)
    assert rms(fitted_coefficients) < rms(coefficients_of(fit_conic(pts, geometric=False)))


def test_fit_conic_through_five_points_is_exact():
    # Five points fix a conic: the fit is the one through them (the null vector of a 5x6
    # design, which a thin SVD leaves out).
    pts, C_true = _circle_image(_homography(), 60.0, n=5)
    C = fit_conic(pts)
    assert np.max(np.abs(sampson_distances(C, pts))) < 1e-6
    assert np.allclose(C * np.sign(C[0, 0]), C_true * np.sign(C_true[0, 0]), atol=1e-9)


def test_fit_conic_refuses_too_few_points():
    with pytest.raises(ValueError, match="N >= 5"):
        fit_conic(np.zeros((4, 2)))


def test_pencil_center_is_image_of_circle_centre_not_ellipse_centre():
    H = _homography()
    _, c1 = _circle_image(H, 30.0)
    _, c2 = _circle_image(H, 80.0)
    centre, ratio = pencil_center(c1, c2)
    o = H @ [0, 0, 1.0]
    assert np.allclose(centre[:2], o[:2] / o[2], atol=1e-6)
    assert ratio == pytest.approx((80.0 / 30.0) ** 2, rel=1e-9)
    # The ellipse centre is elsewhere under perspective (why it is never used).
    ellipse_centre = -np.linalg.solve(c2[:2, :2], c2[:2, 2])
    assert np.linalg.norm(ellipse_centre - o[:2] / o[2]) > 1.0


@pytest.mark.parametrize("r", [10.0, 55.0, 120.0])
def test_pencil_member_is_the_image_of_another_concentric_circle(r):
    # from two members at their own (arbitrary, even negative) scales
    H = _homography()
    _, c1 = _circle_image(H, 30.0)
    _, c2 = _circle_image(H, 80.0)
    pts, truth = _circle_image(H, r)
    truth = truth if np.trace(truth[:2, :2]) > 0 else -truth
    for s1, s2 in ((-2.5, 0.3), (1.0, 1.0), (4.0, -0.2)):
        member = pencil_member(s1 * c1, 30.0, s2 * c2, 80.0, r)
        assert np.max(np.abs(sampson_distances(member, pts))) < 1e-6
        # one sign whatever the given conics' signs: signed distances stay comparable
        np.testing.assert_allclose(member, truth, atol=1e-9)


def test_harmonic_conjugate_gives_vanishing_point():
    H = _homography()

    def img(p):
        x = H @ [p[0], p[1], 1.0]
        return x[:2] / x[2]

    a, b, o = img((80, 0)), img((-80, 0)), img((0, 0))
    vp = harmonic_conjugate(a, b, o)
    expected = H @ [1.0, 0.0, 0.0]  # the x direction's point at infinity
    # Same homogeneous point (here at infinity: the x diameter is fronto-parallel).
    cross = np.cross(vp / np.linalg.norm(vp), expected / np.linalg.norm(expected))
    assert np.linalg.norm(cross) < 1e-9


def test_line_conic_intersections_and_line_fit():
    H = _homography()
    _pts, C = _circle_image(H, 50.0)

    def img(p):
        x = H @ [p[0], p[1], 1.0]
        return x[:2] / x[2]

    line = fit_line(np.array([img((s, 0.0)) for s in np.linspace(-70, 70, 15)]))
    got = line_conic_intersections(line, C)
    assert got.shape == (2, 2)
    want = np.array([img((50.0, 0.0)), img((-50.0, 0.0))])
    d = np.linalg.norm(got[:, None] - want[None], axis=2).min(axis=1)
    assert np.all(d < 1e-6)


def test_intersect_lines_is_numpys_cross_to_the_bit():
    rng = np.random.default_rng(20261202)
    for _ in range(500):
        a, b = rng.normal(size=(2, 3)) * rng.choice([1e-6, 1.0, 1e6], (2, 3))
        got = intersect_lines(a, b)
        np.testing.assert_array_equal(got, np.cross(a, b))
        assert got.shape == (3,) and got.dtype == np.float64
    # the homogeneous crossing of two image lines, and stacked lines as np.cross takes them
    x = intersect_lines([1.0, 0.0, -3.0], [0.0, 1.0, -5.0])
    np.testing.assert_allclose(x[:2] / x[2], [3.0, 5.0])
    stacked = rng.normal(size=(4, 3))
    np.testing.assert_array_equal(
        intersect_lines(stacked, stacked[::-1]), np.cross(stacked, stacked[::-1])
    )


def _ray_distances_reference(conic, c, dirs):
    """The positive root per direction, in NumPy's array expressions."""
    p0 = np.array([c[0], c[1], 1.0])
    cp = conic @ p0
    dx, dy = dirs[:, 0], dirs[:, 1]
    a = conic[0, 0] * dx * dx + (conic[0, 1] + conic[1, 0]) * dx * dy + conic[1, 1] * dy * dy
    b = 2.0 * (dx * cp[0] + dy * cp[1])
    disc = b * b - 4 * a * float(p0 @ cp)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        t1, t2 = (-b + sq) / (2 * a), (-b - sq) / (2 * a)
    t = np.where(t1 > 0, t1, t2)
    return np.where((disc >= 0) & (t > 0), t, np.nan)


def test_conic_ray_distances_meet_the_conic_and_are_numpys_to_the_bit():
    rng = np.random.default_rng(20261203)
    angles = np.linspace(0, 2 * np.pi, 37)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    # an ellipse around the origin: every ray from inside meets it once, at its radius
    t = conic_ray_distances(np.diag([1 / 9.0, 1 / 4.0, -1.0]), [0.0, 0.0], dirs)
    np.testing.assert_allclose(t, 1 / np.sqrt(np.cos(angles) ** 2 / 9 + np.sin(angles) ** 2 / 4))
    # from outside a circle: the rays away from it miss (NaN), those towards it meet it
    t = conic_ray_distances(np.diag([1.0, 1.0, -1.0]), [3.0, 0.0], dirs)
    assert np.isnan(t[np.cos(angles) > 0]).all() and np.isfinite(t[np.cos(angles) < -0.99]).all()
    for _ in range(300):
        m = rng.normal(size=(3, 3))
        conic = m + m.T
        c = rng.normal(size=2) * 5
        d = rng.normal(size=(int(rng.integers(1, 40)), 2))
        d[rng.random(len(d)) < 0.1] = 0.0  # (a zero direction: 0 / 0)
        got = conic_ray_distances(conic, c, d)
        np.testing.assert_array_equal(got, _ray_distances_reference(conic, c, d))


def _tilted_circle(
    rng: np.random.Generator, tilt_deg: float, principal_px: np.ndarray, size=(640, 480)
) -> tuple[np.ndarray, np.ndarray, float]:
    """A 40 mm circle 500 mm away whose plane is tilted ``tilt_deg`` from the line of sight
    through its centre, seen anywhere in the image of a camera of 0.9-2.2 widths' focal
    length: its image conic, the image of its centre and the focal length."""
    w, h = size
    f = rng.uniform(0.9, 2.2) * w
    K = np.array([[f, 0, principal_px[0]], [0, f, principal_px[1]], [0, 0, 1.0]])
    ray = np.linalg.solve(K, [rng.uniform(0, w), rng.uniform(0, h), 1.0])
    ray /= np.linalg.norm(ray)
    axis = rng.uniform(0, 2 * np.pi)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(axis), np.sin(axis), 0]))
    turn = np.cross([0.0, 0.0, 1.0], ray)
    to_ray = Rotation.from_rotvec(turn / np.linalg.norm(turn) * np.arcsin(np.linalg.norm(turn)))
    R = (to_ray * tilt * Rotation.from_euler("x", 180, degrees=True)).as_matrix()
    H = K @ np.column_stack([R[:, 0], R[:, 1], 500.0 * ray])
    Hi = np.linalg.inv(H)
    o = H @ [0.0, 0.0, 1.0]
    return Hi.T @ np.diag([1.0, 1.0, -1600.0]) @ Hi, o[:2] / o[2], f


def test_a_circles_tilt_from_its_line_of_sight_is_read_off_its_image():
    # Exact with the principal point known, anywhere in the image (the image plane's own
    # obliquity off the axis flattens the image further: the flatness alone does not tell)
    rng = np.random.default_rng(31)
    centre = np.array([319.5, 239.5])
    flatter = 0
    for _ in range(50):
        tilt = rng.uniform(5.0, 70.0)
        conic, o, f = _tilted_circle(rng, tilt, centre)
        got = circle_tilt_deg(conic, o, centre)
        assert got is not None
        assert abs(got[0] - tilt) < 1e-6
        assert abs(got[1] - f) < 1e-6 * f
        eig = np.abs(np.linalg.eigvalsh(conic[:2, :2]))
        flatter += np.sqrt(eig.min() / eig.max()) < np.cos(np.radians(tilt)) - 0.01
    assert flatter > 5  # (views the flatness alone calls more oblique than they are)
    # with the principal point 2 % of the width off, within a degree
    for _ in range(50):
        conic, o, _ = _tilted_circle(rng, 60.0, centre + rng.uniform(-12.8, 12.8, 2))
        got = circle_tilt_deg(conic, o, centre)
        assert got is not None
        assert abs(got[0] - 60.0) < 1.0


def test_a_frontal_circles_tilt_is_not_made_up():
    # Seen straight on the vanishing line is at infinity: no focal length, no tilt.
    conic = np.diag([1.0, 1.0, -400.0])
    shift = np.array([[1.0, 0, -300.0], [0, 1.0, -200.0], [0, 0, 1.0]])
    assert circle_tilt_deg(shift.T @ conic @ shift, (300.0, 200.0), (319.5, 239.5)) is None


def test_a_line_through_a_point_along_an_angle_holds_the_point_and_runs_along_it():
    rng = np.random.default_rng(5)
    for _ in range(20):
        p, a = rng.uniform(-500, 1500, 2), rng.uniform(-np.pi, 2 * np.pi)
        ln = line_through(p, a)
        assert abs(np.hypot(ln[0], ln[1]) - 1.0) < 1e-12
        for t in (0.0, 37.5, -400.0):
            q = p + t * np.array([np.cos(a), np.sin(a)])
            assert abs(ln @ [q[0], q[1], 1.0]) < 1e-9
        off = p + 3.0 * np.array([-np.sin(a), np.cos(a)])  # 3 px across it
        assert abs(abs(ln @ [off[0], off[1], 1.0]) - 3.0) < 1e-9
