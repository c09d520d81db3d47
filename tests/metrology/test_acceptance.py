from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from metrology.acceptance import MPE, full_acceptance, load_acceptance_spec, run_acceptance
from scanner.app.cli import main
from scanner.core.config import CONFIG_DIR, ConfigError
from tests.metrology.test_measure import SPHERES, paper_scene

SPEC = CONFIG_DIR / "plans" / "acceptance_paper.toml"


def by_symbol(result) -> dict[str, list]:
    out: dict[str, list] = {}
    for c in result.characteristics:
        out.setdefault(c.symbol, []).append(c)
    return out


def test_ideal_scan_passes_with_small_errors():
    rng = np.random.default_rng(0)
    result = run_acceptance(paper_scene(rng, noise_mm=0.01), SPEC)
    assert result.passed, result.summary()
    c = by_symbol(result)
    assert len(c["PF"]) == 2 and len(c["PS"]) == 2 and len(c["SD"]) == 1 and len(c["F"]) == 1
    for pf in c["PF"]:
        # range of Gaussian noise (sigma 10 µm) over ~3000 points after the 0.3 % exclusion
        assert 0.04 < pf.value_mm < 0.08
    for ps in c["PS"]:
        assert abs(ps.value_mm) < 0.002
    assert abs(c["SD"][0].value_mm) < 0.002
    assert 0.04 < c["F"][0].value_mm < 0.08
    assert result.summary().startswith("PASS: 6 passed, 0 failed (PF +")


def test_known_errors_are_measured_and_judged():
    rng = np.random.default_rng(1)
    moved = (SPHERES[0], SPHERES[1] + [0.0, 0.2, 0.0])  # spacing sqrt(100^2 + 0.2^2)
    cloud = paper_scene(rng, noise_mm=0.005, centers=moved, diameter_mm=25.46, plate_bump_mm=0.2)
    spec = dataclasses.replace(load_acceptance_spec(SPEC), mpe=MPE(0.15, 0.05, 0.1, 0.1))
    result = run_acceptance(cloud, spec)
    c = by_symbol(result)
    for ps in c["PS"]:
        assert ps.value_mm == pytest.approx(0.06, abs=0.002)
        assert ps.row.final_status == "fail"  # MPE 0.05
    assert c["SD"][0].value_mm == pytest.approx(np.hypot(100.0, 0.2) - 100.0, abs=0.002)
    assert c["SD"][0].row.final_status == "pass"
    assert c["F"][0].value_mm > 0.19  # the bump and the noise
    assert c["F"][0].row.final_status == "fail"
    assert not result.passed and result.n_failed == 3
    assert result.worst("PS") == pytest.approx(0.06, abs=0.002)


def test_outlier_exclusion_follows_the_fraction():
    rng = np.random.default_rng(2)
    cloud = paper_scene(rng)
    spec = load_acceptance_spec(SPEC)
    kept = run_acceptance(cloud, spec)
    none = run_acceptance(cloud, dataclasses.replace(spec, outlier_fraction=0.0))
    for name in ("sphere_1", "sphere_2", "plate"):
        n = none.fits[name].n_inliers
        assert kept.n_excluded[name] == int(np.floor(0.003 * n))
        assert none.n_excluded[name] == 0
        assert kept.fits[name].range_mm <= none.fits[name].range_mm


def test_a_missing_sphere_fails_the_test_with_a_reason():
    rng = np.random.default_rng(3)
    cloud = paper_scene(rng)
    cloud = cloud[np.linalg.norm(cloud - SPHERES[0], axis=1) > 20]
    result = run_acceptance(cloud, SPEC)
    c = by_symbol(result)
    assert c["PF"][0].row.final_status == "error"
    assert "too few points" in c["PF"][0].row.note
    assert c["SD"][0].value_mm is None and c["SD"][0].row.final_status == "error"
    assert c["PF"][1].passed and c["F"][0].passed
    assert not result.passed
    data = json.loads(json.dumps(result.to_json(), allow_nan=False))
    assert data["values_mm"]["SD"] is None
    assert data["result"] == "fail"


def test_spec_validation(tmp_path: Path):
    text = SPEC.read_text().replace("sphere_spacing_mm = 0.1", "sphere_spacing_mm = -0.1")
    bad = tmp_path / "a.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=r"line \d+: mpe\.sphere_spacing_mm: expected a positive"):
        load_acceptance_spec(bad)
    with pytest.raises(ValueError, match="flatness_mm"):
        MPE(probing_form_mm=0.1, probing_size_mm=0.1, sphere_spacing_mm=0.1, flatness_mm=0.0)
    one = tmp_path / "b.toml"
    start = SPEC.read_text().index('[[spheres]]\nname = "sphere_2"')
    end = SPEC.read_text().index("[plate]")
    one.write_text(SPEC.read_text()[:start] + SPEC.read_text()[end:])
    with pytest.raises(ConfigError, match="spheres: expected 2"):
        load_acceptance_spec(one)


def test_acceptance_command(tmp_path: Path, capsys, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")
    cloud = tmp_path / "scan.npy"
    np.save(cloud, paper_scene(np.random.default_rng(4), n=6000, diameter_mm=25.8))
    out = tmp_path / "acc.json"
    args = ["acceptance", str(cloud), "--spec", "acceptance_paper", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "acceptance: FAIL: 4 passed, 2 failed" in printed
    assert "FAIL: PS sphere_1" in printed
    data = json.loads(out.read_text())
    assert data["standard"] == "VDI/VDE 2634 Part 2"
    assert data["values_mm"]["PS"] == pytest.approx(0.4, abs=0.005)
    assert out.with_suffix(".html").is_file() and out.with_suffix(".csv").is_file()
    assert main([*args, "--strict"]) == 1
    capsys.readouterr()
    assert main(["acceptance", str(cloud), "--spec", "nope", "--out", str(out)]) == 2
    assert "config not found" in capsys.readouterr().err


def test_the_full_test_takes_each_characteristics_worst_scan():
    # Three positions of the bar: sizes off by +0.06, -0.05 and +0.01 mm (the positive one
    # decides), spacings off by 0, -0.3 and +0.1 mm (the negative one decides), the third
    # plate bumped. Each row must come from the scan where its magnitude is largest, with
    # that scan's signed value, whatever the scans' order.
    rng = np.random.default_rng(5)
    axis = (SPHERES[1] - SPHERES[0]) / np.linalg.norm(SPHERES[1] - SPHERES[0])
    shorter = (SPHERES[0], SPHERES[1] - 0.3 * axis)
    longer = (SPHERES[0], SPHERES[1] + 0.1 * axis)
    spec = dataclasses.replace(load_acceptance_spec(SPEC), mpe=MPE(0.15, 0.04, 0.1, 0.1))
    clouds = [
        paper_scene(rng, noise_mm=0.005, diameter_mm=25.46),
        paper_scene(rng, noise_mm=0.005, diameter_mm=25.35, centers=shorter),
        paper_scene(rng, noise_mm=0.005, diameter_mm=25.41, centers=longer, plate_bump_mm=0.2),
    ]
    scans = [run_acceptance(c, spec) for c in clouds]
    for k, scan in enumerate(scans):
        scan.cloud_path = f"position_{k}.ply"
    full = full_acceptance(scans)
    c = by_symbol(full)
    for ps in c["PS"]:
        assert ps.value_mm == pytest.approx(0.06, abs=0.002)
        assert ps.row.final_status == "fail"  # MPE 0.04
        assert ps.row.note.startswith("scan 1 of 3, position_0.ply")
    assert c["SD"][0].value_mm == pytest.approx(-0.3, abs=0.002)
    assert c["SD"][0].row.note.startswith("scan 2 of 3, position_1.ply")
    assert c["F"][0].value_mm == pytest.approx(scans[2].worst("F"))
    # rows: PF and PS of sphere_1, of sphere_2, SD, F
    assert [full.decided_by[i] for i in (1, 3, 4, 5)] == [0, 0, 1, 2]
    assert full.worst("PS") == pytest.approx(0.06, abs=0.002)
    assert full.worst("SD") == pytest.approx(-0.3, abs=0.002)
    assert not full.passed and full.n_failed == 4  # both PS, SD, F
    again = full_acceptance(scans[::-1])
    assert [ch.value_mm for ch in again.characteristics] == [
        ch.value_mm for ch in full.characteristics
    ]
    data = json.loads(json.dumps(full.to_json(), allow_nan=False))
    assert [ch["scan_index"] for ch in data["characteristics"]] == full.decided_by
    assert data["characteristics"][4]["cloud"] == "position_1.ply"
    assert len(data["scans"]) == 3
    assert data["scans"][1]["values_mm"]["SD"] == pytest.approx(-0.3, abs=0.002)


def test_a_scan_that_cannot_be_evaluated_decides_the_full_test():
    rng = np.random.default_rng(6)
    whole = paper_scene(rng)
    cut = paper_scene(rng)
    cut = cut[np.linalg.norm(cut - SPHERES[0], axis=1) > 20]
    full = full_acceptance([run_acceptance(whole, SPEC), run_acceptance(cut, SPEC)])
    c = by_symbol(full)
    assert c["PF"][0].row.final_status == "error" and full.decided_by[0] == 1
    assert c["SD"][0].value_mm is None and not full.passed
    with pytest.raises(ValueError, match="expected at least one"):
        full_acceptance([])
    other = dataclasses.replace(load_acceptance_spec(SPEC), name="other")
    with pytest.raises(ValueError, match=r"scans\[1\]: expected the specification"):
        full_acceptance([run_acceptance(whole, SPEC), run_acceptance(whole, other)])


def test_acceptance_command_with_several_scans(tmp_path: Path, capsys, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")
    clouds = []
    for k, d in enumerate((25.42, 25.33)):
        clouds.append(tmp_path / f"position_{k}.npy")
        np.save(clouds[-1], paper_scene(np.random.default_rng(7 + k), n=6000, diameter_mm=d))
    out = tmp_path / "acc.json"
    args = ["acceptance", *map(str, clouds), "--spec", "acceptance_paper", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "acceptance: PASS: 6 passed, 0 failed" in printed
    data = json.loads(out.read_text())
    assert data["values_mm"]["PS"] == pytest.approx(-0.07, abs=0.005)
    assert [s["cloud"]["path"] for s in data["scans"]] == list(map(str, clouds))
    html = out.with_suffix(".html").read_text()
    assert "the worst scan decides" in html and "position_1.npy" in html
    assert len(out.with_suffix(".csv").read_text().splitlines()) == 7  # header + 6 rows
    # the same scan twice (by another name too) is refused, and nothing is written over the
    # first run's files; so is a missing scan, before any is read
    (tmp_path / "linked.npy").hardlink_to(clouds[0])
    before = {p.name: p.read_bytes() for p in tmp_path.glob("acc.*")}
    for second, why in [(clouds[0], "given twice"), (tmp_path / "linked.npy", "given twice"),
                        (tmp_path / "gone.npy", "point cloud not found")]:  # fmt: skip
        argv = ["acceptance", str(clouds[0]), str(second), "--spec", "acceptance_paper"]
        assert main([*argv, "--out", str(out)]) == 2
        assert why in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in tmp_path.glob("acc.*")} == before
