"""The full-object job end to end on the virtual cell, judged against the true mesh."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from scanner.app.full_object import run_full_object
from scanner.core.config import CONFIG_DIR
from scanner.formats.clouds import read_cloud
from scanner.formats.meshes import read_mesh


@pytest.mark.slow
def test_a_planned_full_object_job_covers_and_measures_the_part(tmp_path):
    part = CONFIG_DIR / "parts" / "stepped.stl"
    out = tmp_path / "job"
    result = run_full_object(part, "modern", out, seed=3, step_mm=2.0, progress=False)
    assert result.predicted_coverage >= 0.95
    assert abs(result.achieved_coverage - result.predicted_coverage) <= 0.03
    job = json.loads((out / "job.json").read_text())
    assert job["sweeps"] == result.sweeps >= 2
    assert all(c["translation_mm"] < 0.1 for c in job["icp_corrections"])
    assert (out / "inspection.html").is_file() and (out / "coverage_achieved.png").is_file()
    # The merged cloud against the true mesh where the cell put it: no table, no seams.
    plan = json.loads((out / "plan" / "plan.json").read_text())
    mesh = read_mesh(part).transformed(np.asarray(plan["part"]["base_from_part"]))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
    )
    cloud = read_cloud(out / "cloud.ply")
    pts = cloud.point.positions.numpy()
    sweep = cloud.point["sweep_id"].numpy().ravel()
    d = scene.compute_signed_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert np.all(pts[:, 2] > 0.5)
    assert np.median(np.abs(d)) < 0.05
    assert np.quantile(np.abs(d), 0.99) < 0.3
    for k in np.unique(sweep):
        core = np.abs(d[sweep == k]) < 0.2
        assert abs(float(np.mean(d[sweep == k][core]))) < 0.02
