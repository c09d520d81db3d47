"""scan_session end to end on a rendered table-and-block sweep (scanner.virtual_cell.analytic)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from scanner.core.fileio import InputError
from scanner.formats.calibration_file import read_calibration, write_calibration
from scanner.formats.clouds import read_cloud, read_ply_metadata
from scanner.formats.session import read_session, write_session
from scanner.scanning import pipeline
from scanner.scanning.pipeline import ScanOptions, scan_session, table_cut_mm
from scanner.stripe.profile import StripeOptions
from scanner.virtual_cell.analytic import TableStepScene, write_table_step_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    session, cal, scene = write_table_step_sweep(root / "session", seed=0)
    cal_path = root / "calibration.json"
    write_calibration(cal_path, cal)
    return session, cal_path, scene


@pytest.fixture(scope="module")
def dense_sweep(tmp_path_factory):
    """Frames 1 mm apart: dense enough for normals and ICP."""
    root = tmp_path_factory.mktemp("dense")
    session, cal, scene = write_table_step_sweep(
        root / "session", x_mm=np.linspace(-30.0, 30.0, 61), seed=1
    )
    cal_path = root / "calibration.json"
    write_calibration(cal_path, cal)
    return session, cal_path, scene


def _surfaces(points: np.ndarray, scene: TableStepScene):
    """z of the points on the table and on the block, checking each lies where its surface is."""
    x, z = points[:, 0], points[:, 2]
    table = np.abs(z) < 2.0
    top = np.abs(z - scene.step_mm) < 2.0
    assert np.all(table | top)  # no stray points, none blended between the surfaces
    assert not np.any(table & (x > scene.x0_mm + 0.5) & (x < scene.x1_mm - 0.5))
    assert not np.any(top & ((x < scene.x0_mm - 0.5) | (x > scene.x1_mm + 0.5)))
    return z[table], z[top]


@pytest.mark.parametrize(("mode", "rms_max_mm"), [("fast", 0.12), ("precise", 0.05)])
def test_scan_recovers_table_and_block_in_the_base_frame(sweep, tmp_path, mode, rms_max_mm):
    session, cal_path, scene = sweep
    out = tmp_path / "cloud.ply"
    result = scan_session(session, cal_path, ScanOptions(mode=mode), out, progress=False)
    pts = result.cloud.point.positions.numpy()
    table_z, top_z = _surfaces(pts, scene)
    # About 2.8 mm of depth per pixel of stripe here: 0.03 px (fast) ~ 0.08 mm.
    assert table_z.size > 1000 and top_z.size > 300
    assert np.sqrt(np.mean(table_z**2)) < rms_max_mm
    assert np.sqrt(np.mean((top_z - scene.step_mm) ** 2)) < rms_max_mm
    assert result.n_frames == 13 and result.n_points == len(pts)
    back = read_cloud(out)
    assert len(back.point.positions) == len(pts)
    for key in ("intensity", "width_px", "flags", "frame_id", "sweep_id"):
        assert key in back.point
    meta = read_ply_metadata(out)
    assert meta["units"] == "mm" and meta["frame"] == "base"
    assert meta["sessions"] == [str(session.resolve())]


def test_interrupted_run_resumes_from_saved_chunks(sweep, tmp_path):
    session, cal_path, _ = sweep
    work = tmp_path / "work"
    opts = ScanOptions(chunk_frames=4, workers=1)
    first = scan_session(session, cal_path, opts, tmp_path / "a.ply", work_dir=work, progress=False)
    chunks = sorted(work.rglob("chunk_*.npz"))
    assert len(chunks) == 4 and first.chunks_resumed == 0
    chunks[-1].unlink()  # as if stopped before the last chunk
    second = scan_session(
        session, cal_path, opts, tmp_path / "b.ply", work_dir=work, progress=False
    )
    assert second.chunks_resumed == 3
    np.testing.assert_array_equal(
        first.cloud.point.positions.numpy(), second.cloud.point.positions.numpy()
    )
    # Other extraction options: another work folder, nothing reused.
    third = scan_session(
        session,
        cal_path,
        ScanOptions(chunk_frames=4, workers=1, mode="precise"),
        tmp_path / "c.ply",
        work_dir=work,
        progress=False,
    )
    assert third.chunks_resumed == 0


def test_two_workers_give_the_same_cloud_as_one(sweep, tmp_path):
    """Two worker threads: the same cloud, and this process's OpenCV settings left alone."""
    session, cal_path, _ = sweep
    threads_before = cv2.getNumThreads()
    cv2.setNumThreads(3)  # not 1, which a worker setting its own would leave too
    try:
        one = scan_session(
            session, cal_path, ScanOptions(workers=1, chunk_frames=3), None, progress=False
        )
        two = scan_session(
            session, cal_path, ScanOptions(workers=2, chunk_frames=3), None, progress=False
        )
        threads_after = cv2.getNumThreads()
    finally:
        cv2.setNumThreads(threads_before)
    np.testing.assert_array_equal(
        one.cloud.point.positions.numpy(), two.cloud.point.positions.numpy()
    )
    assert threads_after == 3


class _Stop(Exception):
    pass


@pytest.mark.parametrize("workers", [1, 2])
def test_a_cancelled_scan_stops_after_the_chunk_it_is_on(dense_sweep, tmp_path, workers):
    """A PLC job's cancellation is checked after every chunk: the chunks not started are
    dropped (61 frames in chunks of 2: 31 chunks), the error reaches the caller, nothing is
    written and no work folder is left behind."""
    session, cal_path, _ = dense_sweep
    started = []
    extract = pipeline._extract_chunk

    def counted(job):
        started.append(job.chunk)
        return extract(job)

    def cancel_after_two():
        if len(started) >= 2:
            raise _Stop

    out = tmp_path / "cloud.ply"
    with pytest.MonkeyPatch.context() as m:
        m.setattr(pipeline, "_extract_chunk", counted)
        with pytest.raises(_Stop):
            scan_session(
                session,
                cal_path,
                ScanOptions(workers=workers, chunk_frames=2),
                out,
                progress=False,
                check_cancelled=cancel_after_two,
            )
    assert 2 <= len(started) <= 2 + 2 * workers  # not the 31 chunks
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == []


def test_a_scan_cancelled_after_its_extraction_writes_nothing(dense_sweep, tmp_path):
    """The check is called after the last chunk too, after the triangulation (61 frames in
    chunks of 8: 8 chunks, then the ninth call)."""
    session, cal_path, _ = dense_sweep
    calls = []

    def cancel_after_extraction():
        calls.append(1)
        if len(calls) == 9:
            raise _Stop

    out = tmp_path / "cloud.ply"
    with pytest.raises(_Stop):
        scan_session(
            session,
            cal_path,
            ScanOptions(workers=2, chunk_frames=8),
            out,
            progress=False,
            check_cancelled=cancel_after_extraction,
        )
    assert not out.exists() and list(tmp_path.iterdir()) == []


def _shifted_copy(session_root, dest, dz_mm: float):
    """The same sweep with every robot pose raised by ``dz_mm`` (a pose error to be found)."""
    s = read_session(session_root)
    frames = []
    from dataclasses import replace

    for f in s.frames:
        m = f.base_from_flange.copy()
        m[2, 3] += dz_mm
        frames.append(replace(f, base_from_flange=m))
    dest.mkdir(parents=True)
    (dest / "images").symlink_to(session_root / "images")
    frames = [replace(f, laser_image=dest / "images" / f.laser_image.name) for f in frames]
    write_session(dest, "sweep", s.width, s.height, frames, rotation=s.rotation)
    return dest


def test_several_sweeps_merge_and_icp_reports_the_correction(dense_sweep, tmp_path):
    session, cal_path, _ = dense_sweep
    other = _shifted_copy(session, tmp_path / "shifted", dz_mm=0.6)
    plain = scan_session([session, other], cal_path, ScanOptions(), None, progress=False)
    sid = plain.cloud.point.sweep_id.numpy().ravel()
    assert plain.n_sweeps == 2 and set(np.unique(sid)) == {0, 1}
    z = plain.cloud.point.positions.numpy()[:, 2]
    assert np.median(z[(sid == 1) & (np.abs(z) < 5)]) == pytest.approx(0.6, abs=0.05)

    refined = scan_session([session, other], cal_path, ScanOptions(icp=True), None, progress=False)
    (c,) = refined.corrections
    assert c.applied and c.sweep == 1
    assert c.transform[2, 3] == pytest.approx(-0.6, abs=0.05)
    assert c.translation_mm > 0.5
    assert any("ICP correction" in w for w in refined.warnings)
    z = refined.cloud.point.positions.numpy()[:, 2]
    assert abs(np.median(z[(sid == 1) & (np.abs(z) < 5)])) < 0.05


def test_sweep_column_splits_one_session(tmp_path):
    session, cal, _ = write_table_step_sweep(
        tmp_path / "s", x_mm=np.linspace(-30, 30, 6), sweep=[0, 0, 0, 1, 1, 1]
    )
    write_calibration(tmp_path / "c.json", cal)
    r = scan_session(session, tmp_path / "c.json", ScanOptions(workers=1), None, progress=False)
    assert r.n_sweeps == 2
    assert set(np.unique(r.cloud.point.sweep_id.numpy())) == {0, 1}


@pytest.mark.parametrize("ext", [".pcd", ".e57"])
def test_other_formats_by_extension(sweep, tmp_path, ext):
    session, cal_path, _ = sweep
    out = tmp_path / f"cloud{ext}"
    r = scan_session(session, cal_path, ScanOptions(voxel_mm=0.5), out, progress=False)
    back = read_cloud(out)
    np.testing.assert_allclose(
        back.point.positions.numpy(), r.cloud.point.positions.numpy(), atol=1e-6
    )
    if ext == ".pcd":
        assert json.loads((tmp_path / "cloud.pcd.json").read_text())["units"] == "mm"
    else:
        import pye57

        e57 = pye57.E57(str(out))
        try:
            record = json.loads(e57.data3d[0]["sensorSoftwareVersion"].value())
        finally:
            e57.close()
        assert record["calibration"] == str(cal_path.resolve())


def test_filters_voxel_outliers_normals(dense_sweep, tmp_path):
    session, cal_path, _ = dense_sweep
    full = scan_session(session, cal_path, ScanOptions(), None, progress=False)
    r = scan_session(
        session,
        cal_path,
        ScanOptions(voxel_mm=2.0, outlier_neighbors=10, normals_radius_mm=5.0),
        None,
        progress=False,
    )
    assert 0 < r.n_points < full.n_points
    normals = r.cloud.point.normals.numpy()
    assert np.median(np.abs(normals[:, 2])) > 0.99  # table and block top face up


def test_incidence_limit_keeps_face_on_surfaces_and_reports_the_view_angle(dense_sweep):
    session, cal_path, _ = dense_sweep
    full = scan_session(session, cal_path, ScanOptions(), None, progress=False)
    r = scan_session(
        session,
        cal_path,
        ScanOptions(max_incidence_deg=60.0, incidence_radius_mm=3.0),
        None,
        progress=False,
    )
    assert r.n_points > 0.97 * full.n_points  # table and block top face the camera
    pts = r.cloud.point.positions.numpy()
    cos_view = r.cloud.point.cos_view.numpy().ravel()
    assert np.all(np.isnan(r.cloud.point.cos_laser.numpy()))  # no laser origin given
    # The true cosine: both surfaces face up (+z), seen from each frame's camera centre.
    cal = read_calibration(cal_path)
    centres = {
        f.id: (f.base_from_flange @ cal.flange_from_cam)[:3, 3]
        for f in read_session(session).frames
    }
    to_cam = np.stack([centres[i] for i in r.cloud.point.frame_id.numpy().ravel()]) - pts
    true_cos = np.abs(to_cam[:, 2]) / np.linalg.norm(to_cam, axis=1)
    ok = np.isfinite(cos_view)
    assert np.count_nonzero(ok) > 0.95 * len(ok)
    assert np.median(np.abs(cos_view[ok] - true_cos[ok])) < 0.01


def test_bad_input_is_refused_before_any_work(sweep, tmp_path):
    session, cal_path, _ = sweep
    work = tmp_path / "w"
    # Calibration for another image size.
    cal = TableStepScene(width=640, height=480).calibration()
    write_calibration(tmp_path / "big.json", cal)
    with pytest.raises(InputError, match="images are 320x240, the calibration is for 640x480"):
        scan_session(
            session, tmp_path / "big.json", ScanOptions(), tmp_path / "x.ply", work_dir=work
        )
    with pytest.raises(InputError, match="calibration file not found"):
        scan_session(
            session, tmp_path / "none.json", ScanOptions(), tmp_path / "x.ply", work_dir=work
        )
    with pytest.raises(ValueError, match="expected a point-cloud extension"):
        scan_session(session, cal_path, ScanOptions(), tmp_path / "x.xyz", work_dir=work)
    # A check session is not a sweep.
    _shifted_copy(session, tmp_path / "nosweep", dz_mm=0.0)
    meta = json.loads((tmp_path / "nosweep" / "session.json").read_text())
    meta["kind"] = "check"
    meta["target"] = {"kind": "chessboard", "inner_corners": [9, 6], "square_mm": 20.0}
    (tmp_path / "nosweep" / "session.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="kind: expected 'sweep' for scanning, got 'check'"):
        scan_session(
            tmp_path / "nosweep", cal_path, ScanOptions(), tmp_path / "x.ply", work_dir=work
        )
    assert not work.exists() and not (tmp_path / "x.ply").exists()


@pytest.mark.slow
def test_virtual_cell_sweep_lands_on_the_true_table_and_plate(tmp_path):
    simulate = pytest.importorskip("scanner.virtual_cell.simulate")
    truth = simulate.simulate_cell("modern", tmp_path, seed=3, sweep_frames=12, sessions=("sweep",))
    result = scan_session(
        tmp_path / "sweep", tmp_path / "calibration_true.json", ScanOptions(), None, progress=False
    )
    z = result.cloud.point.positions.numpy()[:, 2]
    table = np.abs(z) < 1.0
    plate_top = -truth.object("plate").params["top_plane"]["d"]
    plate = np.abs(z - plate_top) < 1.0
    assert np.count_nonzero(table) > 2000 and np.count_nonzero(plate) > 500
    # Speckle limits each point to ~0.06 mm, correlated along a profile: 12 profiles over the
    # sweep (a few on the plate) give means
    # good to ~0.01 mm (40 frames: 0.001 mm).
    assert abs(np.mean(z[table])) < 0.03
    assert np.sqrt(np.mean(z[table] ** 2)) < 0.12
    assert abs(np.mean(z[plate] - plate_top)) < 0.03


def test_crop_leaves_out_the_table_and_keeps_the_part(sweep):
    session, cal_path, scene = sweep
    whole = scan_session(session, cal_path, ScanOptions(workers=1), None, progress=False)
    cropped = scan_session(
        session, cal_path, ScanOptions(workers=1, table_z_mm=0.0), None, progress=False
    )
    z_all = whole.cloud.point.positions.numpy()[:, 2]
    z = cropped.cloud.point.positions.numpy()[:, 2]
    assert np.all(z > 0.5)
    on_block = np.abs(z_all - scene.step_mm) < 1.0
    assert on_block.sum() > 100
    assert len(z) == np.count_nonzero(z_all > 0.5)


def test_the_table_cut_follows_the_tables_own_measured_level():
    """A sensor that sees the table 0.6 mm high and noisier loses all of it, not its upper
    half; a clean table keeps the 0.5 mm floor; the part above stays."""
    rng = np.random.default_rng(12)
    table = 0.6 + rng.normal(0.0, 0.1, 20_000)
    part = rng.uniform(2.0, 40.0, 5_000)
    cut = table_cut_mm(np.concatenate([table, part]), 0.0)
    assert np.mean(table > cut) < 1e-3
    assert np.all(part > cut)
    clean = rng.normal(0.0, 0.02, 20_000)
    assert table_cut_mm(clean, 0.0) == pytest.approx(0.5)


def test_a_region_keeps_only_the_points_inside_its_box(sweep):
    session, cal_path, _ = sweep
    box = ((-5.0, -1e3, -1e3), (5.0, 1e3, 1e3))
    options = ScanOptions(workers=1, region_mm=box)
    kept = scan_session(session, cal_path, options, None, progress=False)
    whole = scan_session(session, cal_path, ScanOptions(workers=1), None, progress=False)
    x = kept.cloud.point.positions.numpy()[:, 0]
    x_all = whole.cloud.point.positions.numpy()[:, 0]
    assert len(x) == np.count_nonzero(np.abs(x_all) <= 5.0) > 0
    assert np.all(np.abs(x) <= 5.0)


def _rms(errors_mm: np.ndarray) -> float:
    return float(np.sqrt(np.mean(errors_mm**2)))


def test_a_faint_stripe_in_a_lit_cell_is_scanned_whole(sweep, tmp_path):
    # Ambient light rising by 60 grey levels across the frame, a stripe of 25 above it, no
    # laser-off frames: the scan's probe frames find the background uneven and every frame has
    # it taken out, decided once for the whole scan.
    scene = TableStepScene(amplitude=25.0, ambient_ramp=60.0)
    session, cal, _ = write_table_step_sweep(tmp_path / "lit", scene=scene, seed=3)
    cal_path = tmp_path / "calibration.json"
    write_calibration(cal_path, cal)
    frames = read_session(session).frames
    lit = pipeline._sweep_stripe_options(frames, ScanOptions(), "rows")
    assert lit.flatten_background is True and lit.noise is not None
    dark = pipeline._sweep_stripe_options(read_session(sweep[0]).frames, ScanOptions(), "rows")
    assert dark.flatten_background is False
    result = scan_session(session, cal_path, ScanOptions(), tmp_path / "cloud.ply", progress=False)
    table_z, top_z = _surfaces(result.cloud.point.positions.numpy(), scene)
    assert table_z.size > 1000 and top_z.size > 300
    # As accurate as the same faint stripe in a dark cell, within a tenth (its own noise:
    # 0.32 mm on the table and 0.17 mm on the step, 0.11 and 0.06 px at about 2.8 mm of
    # depth per pixel; 0.33 and 0.18 mm lit).
    dark_scene = TableStepScene(amplitude=25.0)
    dark, _, _ = write_table_step_sweep(tmp_path / "dark", scene=dark_scene, seed=3)
    twin = scan_session(dark, cal_path, ScanOptions(), tmp_path / "dark.ply", progress=False)
    dark_table, dark_top = _surfaces(twin.cloud.point.positions.numpy(), dark_scene)
    assert _rms(table_z) < 1.1 * _rms(dark_table)
    assert _rms(top_z - scene.step_mm) < 1.1 * _rms(dark_top - scene.step_mm)
    # The same sweep with the background left in: no line keeps the stripe, and the scan is
    # refused with its reason instead of writing an empty cloud.
    options = ScanOptions(stripe=StripeOptions(flatten_background=False))
    with pytest.raises(InputError, match="no stripe points found in any of the 13 frames"):
        scan_session(session, cal_path, options, tmp_path / "before.ply", progress=False)
    assert not (tmp_path / "before.ply").exists()
