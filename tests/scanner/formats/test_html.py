from __future__ import annotations

import base64
import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from scanner.core.tolerance import ToleranceRow
from scanner.formats import html as rep


def _png_bytes() -> bytes:
    fig = Figure(figsize=(2, 1.5))
    ax = fig.add_subplot()
    ax.hist(np.random.default_rng(0).normal(size=200), bins=20)
    return rep._figure_png(fig, dpi=50)


def test_table_rows_are_colour_coded_and_escaped():
    rows = [
        ToleranceRow("ok <b>", 100.0, 100.01, -0.05, 0.05),
        ToleranceRow("bad", 25.4, 25.5, -0.05, 0.05),
        ToleranceRow("failed fit", 25.4, None, -0.05, 0.05, note="too few points"),
    ]
    html_text = rep.tolerance_table(rows)
    assert html_text.count('<tr class="pass">') == 1
    assert html_text.count('<tr class="fail">') == 1
    assert html_text.count('<tr class="error">') == 1
    assert "ok &lt;b&gt;" in html_text and "<b>" not in html_text
    assert "+0.100" in html_text  # deviation of the bad row
    summary = rep.summary_line(rows, detail="cloud.ply")
    assert "1 passed, 2 failed" in summary and 'class="summary fail"' in summary
    assert 'class="summary pass"' in rep.summary_line((3, 0))


def test_page_is_self_contained_with_embedded_figure(tmp_path: Path):
    png = _png_bytes()
    (tmp_path / "f.png").write_bytes(png)
    body = (
        rep.summary_line((1, 0))
        + rep.section("Figures", rep.figure(png, "hist") + rep.figure(tmp_path / "f.png", "again"))
        + rep.section("Calibration", rep.key_value_table({"file": "c.json", "rms_px": 0.1234567}))
    )
    out = rep.write_page(tmp_path / "r.html", rep.page("Report", body, subtitle="test"))
    text = out.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    # No external resources: every src is a data URI.
    srcs = re.findall(r'src="([^"]+)"', text)
    assert len(srcs) == 2 and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert base64.b64decode(srcs[0].split(",", 1)[1]) == png
    assert "0.1235" in text
    assert "href=" not in text


def test_figure_accepts_matplotlib_figure_and_refuses_non_png():
    fig = Figure(figsize=(1, 1))
    fig.add_subplot().plot([0, 1], [0, 1])
    assert "data:image/png;base64," in rep.figure(fig, "line")
    with pytest.raises(ValueError, match="expected PNG"):
        rep.png_data_uri(b"GIF89a....")


def test_plain_table_formats_numbers_and_escapes_text():
    html_text = rep.table(["name", "value", "count"], [["a<b", 1.23456, 7], ["c", None, 0]], 2)
    assert "a&lt;b" in html_text
    assert '<td class="num">1.23</td>' in html_text
    assert '<td class="num">7</td>' in html_text
    assert '<td class="num">-</td>' in html_text
