"""A whole inspection against the truth: planted deviations read back, strays marked, regions
judged, every point kept."""

from __future__ import annotations

import numpy as np
import pytest

from metrology.inspect.align import pose_distance_mm
from metrology.inspect.inspect import AlignmentFailed, inspect_cloud
from metrology.inspect.spec import AlignmentSpec, DatumSpec, InspectionRegion, InspectionSpec
from metrology.inspect.surface import NominalSurface
from scanner.virtual_cell.parts import boss_part, scan_part


@pytest.fixture(scope="module")
def bumped():
    """A boss part scanned with a 0.15 mm bump (sigma 3 mm) on its top face and strays."""
    rng = np.random.default_rng(11)
    bump = (np.array([30.0, 30.0, 30.0]), 0.15, 3.0)
    scan = scan_part(boss_part(), rng, count=150_000, stray_share=0.003, bumps=[bump])
    top = InspectionRegion("top", normal=(0.0, 0.0, 1.0), max_angle_deg=5.0)
    ring = InspectionRegion("bump", center_mm=(30.0, 30.0, 30.0), radius_mm=6.0, upper_mm=0.05)
    spec = InspectionSpec(regions=(top, ring))
    return scan, inspect_cloud(scan.points_cloud, boss_part(), spec)


def test_every_point_is_kept_and_strays_are_marked(bumped) -> None:
    scan, result = bumped
    assert result.points == len(scan.points_cloud)
    assert result.deviation_mm.shape == result.outlier.shape == (len(scan.points_cloud),)
    # Strays farther than the outlier limit are marked; no true surface point is.
    far = np.abs(result.deviation_mm) > 1.0
    np.testing.assert_array_equal(result.outlier, far)
    assert not np.any(result.outlier & ~scan.stray)
    assert np.count_nonzero(result.outlier) > 0.5 * np.count_nonzero(scan.stray)


def test_the_planted_bump_is_read_back(bumped) -> None:
    scan, result = bumped
    centre = np.array([30.0, 30.0, 30.0])
    near = (np.linalg.norm(result.points_nominal - centre, axis=1) < 0.75) & ~scan.stray
    measured = result.deviation_mm[near].mean()
    true = scan.true_deviation_mm[near].mean()
    assert measured == pytest.approx(true, abs=0.015)
    # Away from the bump and the strays, the deviation is the noise.
    away = (np.linalg.norm(result.points_nominal - centre, axis=1) > 12) & ~scan.stray
    assert np.sqrt(np.mean(result.deviation_mm[away] ** 2)) < 1.5 * 0.02


def test_regions_are_judged_on_their_bands(bumped) -> None:
    _, result = bumped
    names = [r.name for r in result.regions]
    assert names == ["all", "top", "bump"]
    everything, top, bump = result.regions
    assert everything.status == "pass"  # the bump is inside +-0.1 mm
    assert top.status == "pass"
    assert bump.status == "fail"  # its own band ends at +0.05 mm; the bump reaches 0.15 mm
    assert bump.stats.max > 0.12
    assert result.verdict == "fail"
    assert 0 < bump.share_in_band < 0.99


def test_uncertainty_is_the_noise_and_a_small_pose_share(bumped) -> None:
    _, result = bumped
    u = result.uncertainty
    assert u.noise_mm == pytest.approx(0.02, rel=0.15)
    assert 0 < u.alignment_mm < 0.005
    assert u.combined_mm == pytest.approx(np.hypot(u.noise_mm, u.alignment_mm))


def test_json_follows_the_contract(bumped) -> None:
    _, result = bumped
    data = result.to_json()
    assert data["format"] == "scan-inspection/1"
    assert np.asarray(data["nominal_from_cloud"]).shape == (4, 4)
    assert {"method", "rms_mm", "points_used"} <= set(data["alignment"])
    assert set(data["deviation_mm"]) == {"mean", "rms", "min", "max", "p01", "p99"}
    assert data["points"] == result.points
    assert data["verdict"] in ("pass", "fail")


def test_a_cloud_of_another_part_is_refused() -> None:
    rng = np.random.default_rng(2)
    # A sphere of points is not a scan of the block.
    d = rng.normal(size=(5000, 3))
    sphere = 40.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + [500.0, 0.0, 0.0]
    with pytest.raises(AlignmentFailed):
        inspect_cloud(sphere, boss_part(), InspectionSpec(outlier_limit_mm=0.5))


@pytest.mark.parametrize(
    "points,reason",
    [
        (np.zeros((10, 3)), "N >= 100"),
        (np.full((200, 3), np.nan), "finite"),
        (np.zeros((200, 2)), "(N, 3)"),
    ],
)
def test_bad_points_refused(points: np.ndarray, reason: str) -> None:
    with pytest.raises(ValueError, match=reason.replace("(", r"\(").replace(")", r"\)")):
        inspect_cloud(points, boss_part(), InspectionSpec())


def test_rps_alignment_follows_the_datum_faces() -> None:
    """3-2-1 on top (z), front (-y) and left (-x) faces: the datum faces read zero even when
    the rest of the part is off (a boss 0.3 mm too tall pulls a best-fit, not the RPS)."""
    rng = np.random.default_rng(4)
    mesh = boss_part()
    bump = (np.array([70.0, 20.0, 50.0]), 0.3, 6.0)  # the boss's top, raised
    scan = scan_part(mesh, rng, count=120_000, bumps=[bump])
    datums = (
        DatumSpec("plane", InspectionRegion("top", box_min_mm=(0, 0, 29), box_max_mm=(60, 60, 31))),
        DatumSpec("line", InspectionRegion("front", normal=(0, -1, 0), max_angle_deg=5)),
        DatumSpec("point", InspectionRegion("left", normal=(-1, 0, 0), max_angle_deg=5)),
    )
    spec = InspectionSpec(alignment=AlignmentSpec(method="rps", datums=datums))
    result = inspect_cloud(scan.points_cloud, mesh, spec)
    assert result.alignment.method.startswith("rps")
    corners = NominalSurface(mesh).corners()
    error = pose_distance_mm(result.alignment.nominal_from_cloud, scan.nominal_from_cloud, corners)
    assert error < 0.02
    on_top = (np.abs(result.points_nominal[:, 2] - 30) < 0.5) & (result.points_nominal[:, 0] < 60)
    assert abs(np.mean(result.deviation_mm[on_top])) < 0.003


def test_local_best_fit_fits_one_region_only() -> None:
    rng = np.random.default_rng(6)
    mesh = boss_part()
    bump = (np.array([70.0, 20.0, 50.0]), 0.3, 6.0)
    scan = scan_part(mesh, rng, count=120_000, bumps=[bump])
    block = InspectionRegion("block", box_min_mm=(-1, -1, -1), box_max_mm=(101, 61, 31))
    spec = InspectionSpec(regions=(block,), alignment=AlignmentSpec(region="block"))
    result = inspect_cloud(scan.points_cloud, mesh, spec)
    assert "local" in result.alignment.method
    corners = NominalSurface(mesh).corners()
    error = pose_distance_mm(result.alignment.nominal_from_cloud, scan.nominal_from_cloud, corners)
    assert error < 0.01
