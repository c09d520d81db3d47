"""Statuses and tolerance bands, as every report and the PLC gate judge them."""

from __future__ import annotations

import pytest

from scanner.core import tolerance as tol


def test_status_follows_tolerance_band():
    assert tol.status_of(0.01, -0.05, 0.05) == tol.STATUS_PASS
    assert tol.status_of(0.06, -0.05, 0.05) == tol.STATUS_FAIL
    assert tol.status_of(-0.06, -0.05, None) == tol.STATUS_FAIL
    assert tol.status_of(-1.0, None, 0.05) == tol.STATUS_PASS
    assert tol.status_of(1.0, None, None) == tol.STATUS_NA
    assert tol.status_of(None, -1, 1) == tol.STATUS_ERROR
    assert tol.status_of(float("nan"), -1, 1) == tol.STATUS_ERROR


def test_tolerance_formats_symmetric_asymmetric_and_one_sided():
    assert tol.format_tolerance(-0.05, 0.05) == "±0.050"
    assert tol.format_tolerance(-0.02, 0.05) == "+0.050 / -0.020"
    assert tol.format_tolerance(None, 0.05) == "≤ +0.050"
    assert tol.format_tolerance(None, None) == "-"


def test_row_json_has_the_same_numbers():
    row = tol.ToleranceRow("spacing", 100.0, 100.02, -0.05, 0.05)
    j = row.to_json()
    assert j["deviation"] == pytest.approx(0.02)
    assert j["status"] == "pass"


def test_csv_cells_that_a_spreadsheet_would_evaluate_are_quoted():
    assert tol.spreadsheet_safe("=HYPERLINK(1)") == "'=HYPERLINK(1)"
    for text in ("+1", "-x", "@SUM(A1)", "\tx"):
        assert tol.spreadsheet_safe(text) == "'" + text
    assert tol.spreadsheet_safe("sphere 1") == "sphere 1"
    assert tol.spreadsheet_safe(-0.5) == -0.5  # numbers are numbers
