from __future__ import annotations

import csv
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from metrology import report as mreport
from metrology.acceptance import run_acceptance
from metrology.measure import measure_cloud
from scanner.core.config import CONFIG_DIR
from scanner.formats.calibration_file import Calibration, LightPlane, write_calibration
from tests.metrology.test_measure import PAPER_PLAN, paper_scene


@pytest.fixture(scope="module")
def measured():
    return measure_cloud(paper_scene(np.random.default_rng(0), n=6000), PAPER_PLAN)


def is_png(data: bytes) -> bool:
    return data[:8] == b"\x89PNG\r\n\x1a\n"


def test_measurement_report_files_agree(tmp_path: Path, measured, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")
    mreport.write_measurement_report(measured, tmp_path / "m.json")
    data = json.loads((tmp_path / "m.json").read_text())
    with open(tmp_path / "m.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["name"] for r in rows] == [m["name"] for m in data["measurements"]]
    for r, m in zip(rows, data["measurements"]):
        assert float(r["actual"]) == pytest.approx(m["actual"], rel=1e-12)
        assert r["status"] == m["status"]
    html_text = (tmp_path / "m.html").read_text(encoding="utf-8")
    assert "PASS — 11 passed, 0 failed" in html_text
    assert html_text.count('<tr class="pass">') == 11
    # self-contained: no external resources, every image embedded
    assert not re.search(r'(src|href)="(?!data:)', html_text)
    assert html_text.count('src="data:image/png;base64,') == 2  # cloud picture, histograms
    assert "Rendered with matplotlib" in html_text
    assert "Calibration and inputs" in html_text
    assert data["files"] == {"csv": "m.csv", "html": "m.html"}


def test_report_refuses_a_non_json_name(tmp_path: Path, measured):
    with pytest.raises(ValueError, match=r"expected a \.json"):
        mreport.write_measurement_report(measured, tmp_path / "m.html")


def test_render_falls_back_to_matplotlib_and_says_so(monkeypatch, caplog):
    def broken(*args, **kwargs):
        raise RuntimeError("no OpenGL context")

    monkeypatch.delenv("SCANNER_RENDERER", raising=False)
    monkeypatch.setattr(mreport, "_render_pyvista", broken)
    pts = np.random.default_rng(1).uniform(0, 10, (500, 3))
    dev = np.where(pts[:, 0] > 5, pts[:, 2] / 100, np.nan)
    with caplog.at_level(logging.WARNING, logger="metrology.report"):
        png, renderer = mreport.render_cloud_png(pts, dev, "t")
    assert renderer == "matplotlib" and is_png(png)
    assert "Matplotlib 3-D scatter" in caplog.text and "no OpenGL context" in caplog.text


@pytest.mark.slow
def test_render_with_pyvista_off_screen():
    pts = np.random.default_rng(2).uniform(0, 10, (2000, 3))
    png, renderer = mreport.render_cloud_png(pts, pts[:, 2] - 5, "t", size=(320, 240))
    assert is_png(png)
    if renderer != "pyvista":
        pytest.skip("VTK cannot render off-screen on this machine (fell back to Matplotlib)")


def test_histograms_and_colour_limit():
    fig = mreport.histogram_figure([("a", np.ones(10) * 0.01), ("b", np.zeros(0))])
    assert len(fig.axes) == 2
    dev = np.r_[np.linspace(-0.01, 0.01, 999), 5.0, np.nan]
    assert mreport.deviation_limit(dev) == pytest.approx(0.01, rel=0.05)
    assert mreport.deviation_limit(np.full(3, np.nan)) == 0.01


def test_provenance_names_the_calibration_and_when(tmp_path: Path):
    cal = tmp_path / "calib.json"
    write_calibration(
        cal,
        Calibration(
            width=640, height=480, K=[[800, 0, 320], [0, 800, 240], [0, 0, 1]], dist=[0] * 5,
            light_plane=LightPlane.from_coefficients(0, 1, 1, -300), flange_from_cam=np.eye(4),
            quality={"method": "default"},
        ),
    )  # fmt: skip
    items = dict(mreport.provenance_items({"calibration": str(cal)}, None))
    assert items["calibration file"] == str(cal)
    assert items["calibration written"].endswith("UTC")
    assert items["calibration method"] == "default"
    missing = dict(mreport.provenance_items({"calibration": str(tmp_path / "gone.json")}, None))
    assert "not found" in missing["calibration written"]
    assert "unknown" in dict(mreport.provenance_items({}, None))["calibration"]


def test_acceptance_report_page(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")
    result = run_acceptance(
        paper_scene(np.random.default_rng(3), n=6000),
        CONFIG_DIR / "plans" / "acceptance_paper.toml",
    )
    mreport.write_acceptance_report(result, tmp_path / "a.json")
    html_text = (tmp_path / "a.html").read_text(encoding="utf-8")
    assert "VDI/VDE 2634" in html_text
    assert "PF probing error, form" in html_text and "SD sphere-spacing error" in html_text
    assert not re.search(r'(src|href)="(?!data:)', html_text)
    assert json.loads((tmp_path / "a.json").read_text())["summary"]["passed"] == 6
