"""Printable targets: 1:1 with a scale bar, laid out on a paper size when asked."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from scanner.app.cli import main
from scanner.virtual_cell.capture import printed_target
from scanner.virtual_cell.cell import load_cell
from scanner.virtual_cell.drawing import save_target_drawing, smallest_page


def _pdf_pages(path: Path) -> list[tuple[float, float]]:
    """Page sizes (pt) from the PDF's MediaBox entries."""
    text = path.read_bytes().decode("latin-1")
    boxes = re.findall(r"/MediaBox\s*\[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", text)
    return [(float(w), float(h)) for w, h in boxes]


def test_every_drawing_carries_a_scale_bar(tmp_path: Path):
    printed = printed_target(load_cell("paper"))
    drawing, _ = save_target_drawing(printed, tmp_path / "t.svg")
    svg = drawing.read_text()
    assert "100 mm: check the print with a ruler" in svg
    width_mm = float(re.search(r'width="([\d.]+)mm"', svg).group(1))
    assert width_mm == pytest.approx(216.0)  # 1:1


def test_the_papers_target_is_tiled_on_a4_and_whole_on_a3(tmp_path: Path):
    printed = printed_target(load_cell("paper"))
    assert smallest_page(printed) == "A3"  # 216 x 232 mm does not fit A4's printable area
    a4, _ = save_target_drawing(printed, tmp_path / "a4.pdf", page="A4")
    a3, _ = save_target_drawing(printed, tmp_path / "a3.pdf", page="A3")
    mm = 25.4 / 72
    pages = _pdf_pages(a4)
    assert len(pages) == 2
    assert all(
        w * mm == pytest.approx(210, abs=0.5) and h * mm == pytest.approx(297, abs=0.5)
        for w, h in pages
    )
    assert len(_pdf_pages(a3)) == 1


def test_page_needs_a_pdf(tmp_path: Path, capsys):
    assert main(["target", "--out", str(tmp_path / "t.svg"), "--page", "A4"]) == 2
    assert "--page: expected one of A4, A3, Letter with a .pdf output" in capsys.readouterr().err


def test_a_target_drawn_from_a_session_cannot_overwrite_it(tmp_path: Path, capsys):
    spec = tmp_path / "session.json"
    spec.write_text('{"target": {"kind": "chessboard", "inner_corners": [9, 6], "square_mm": 20}}')
    assert main(["target", "--spec", str(spec), "--out", str(tmp_path / "session.svg")]) == 2
    assert "would overwrite the input" in capsys.readouterr().err


def test_a_huge_png_is_refused_before_drawing(tmp_path: Path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text('{"kind": "chessboard", "inner_corners": [9, 6], "square_mm": 10000}')
    assert main(["target", "--spec", str(spec), "--out", str(tmp_path / "big.png")]) == 2
    assert "draw it as .svg or .pdf" in capsys.readouterr().err
    assert not (tmp_path / "big.png").exists()


def test_a_negative_seed_is_refused(tmp_path: Path, capsys):
    assert main(["simulate", "--seed", "-1", "--out", str(tmp_path / "s")]) == 2
    assert "--seed: expected >= 0, got -1" in capsys.readouterr().err
