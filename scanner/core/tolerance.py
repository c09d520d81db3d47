"""Tolerances and pass/fail: the status of a measured value against its nominal and band.

Every stage that judges a value (measurement plans, the acceptance test, the EF check, the PLC
gate) uses these types; the HTML reports only draw them.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, Literal

__all__ = [
    "DECISION_RULES",
    "STATUS_ERROR",
    "STATUS_FAIL",
    "STATUS_NA",
    "STATUS_NOT_PROVEN",
    "STATUS_PASS",
    "DecisionRule",
    "RowCounts",
    "Status",
    "ToleranceRow",
    "format_tolerance",
    "format_value",
    "spreadsheet_safe",
    "status_of",
    "verdict_of_statuses",
]

Status = Literal["pass", "fail", "not proven", "n/a", "error"]
STATUS_PASS: Status = "pass"
STATUS_FAIL: Status = "fail"
STATUS_NA: Status = "n/a"
"""No tolerance given: reported, not judged."""
STATUS_ERROR: Status = "error"
"""The value could not be measured (a failed fit): counts as failed."""
STATUS_NOT_PROVEN: Status = "not proven"
"""Guarded acceptance: inside the tolerance, but nearer a limit than its uncertainty U (or
without a U), so conformity is not proven (ISO 14253-1); neither passed nor failed."""

DecisionRule = Literal["simple", "guarded"]
"""How a measured value is judged against its tolerance (ISO 14253-1, ILAC-G8):

- ``simple``: pass inside the tolerance, fail outside; U is reported, not used;
- ``guarded``: pass only inside the tolerance shrunk by U on each bounded side (conformity
  proven), fail outside the tolerance, ``not proven`` between.
"""
DECISION_RULES: tuple[DecisionRule, ...] = ("simple", "guarded")


def format_value(value: float | None, decimals: int = 3, signed: bool = False) -> str:
    """A number as the tables print it: fixed decimals, ``-`` for None, ``NaN`` kept visible."""
    if value is None:
        return "-"
    v = float(value)
    if not math.isfinite(v):
        return "NaN" if math.isnan(v) else ("+inf" if v > 0 else "-inf")
    text = f"{v:.{decimals}f}"
    if float(text) == 0.0:  # no "-0.000" for a value that rounds to zero
        return f"{0.0:.{decimals}f}"
    return f"{v:+.{decimals}f}" if signed else text


def format_tolerance(lower: float | None, upper: float | None, decimals: int = 3) -> str:
    """``±0.050`` for a symmetric band, ``+0.050 / -0.020`` otherwise, ``≤ 0.050`` one-sided.

    ``lower`` and ``upper`` are the permitted deviations from nominal (``lower <= 0 <= upper``
    in the usual case); None means unbounded on that side.
    """
    if lower is None and upper is None:
        return "-"
    if lower is None:
        return f"≤ {format_value(upper, decimals, signed=True)}"
    if upper is None:
        return f"≥ {format_value(lower, decimals, signed=True)}"
    if math.isclose(-lower, upper, rel_tol=1e-9, abs_tol=1e-12):
        return f"±{format_value(upper, decimals)}"
    return f"{format_value(upper, decimals, signed=True)} / {format_value(lower, decimals, signed=True)}"


def status_of(deviation: float | None, lower: float | None, upper: float | None) -> Status:
    """``pass`` if ``lower <= deviation <= upper`` (None bounds are open), ``error`` if the
    deviation is None or not finite, ``n/a`` if neither bound is given."""
    if deviation is None or not math.isfinite(float(deviation)):
        return STATUS_ERROR
    if lower is None and upper is None:
        return STATUS_NA
    ok = (lower is None or deviation >= lower) and (upper is None or deviation <= upper)
    return STATUS_PASS if ok else STATUS_FAIL


def verdict_of_statuses(
    statuses: Collection[str],
) -> Literal["pass", "fail", "not proven", "error"]:
    """``error`` if a value could not be measured, else ``fail`` if one is out of tolerance,
    else ``not proven`` if one's conformity is not proven, else ``pass``."""
    if STATUS_ERROR in statuses:
        return "error"
    if STATUS_FAIL in statuses:
        return "fail"
    return "not proven" if STATUS_NOT_PROVEN in statuses else "pass"


@dataclass(frozen=True)
class ToleranceRow:
    """One line of the Nominal / Actual / Deviation / Tolerance / Status table.

    Parameters
    ----------
    name : str
        What was measured ("sphere spacing A-B").
    nominal, actual : float or None
        Nominal and measured value in ``unit``; ``actual`` None means it could not be measured.
    lower, upper : float or None
        Permitted deviation from nominal below and above (``-0.05, 0.05`` for ±0.05); None
        leaves that side open (a maximum permissible error is ``lower=None, upper=MPE`` with
        nominal 0).
    unit : str
        Printed after the name ("mm", "deg", "µm").
    status : str or None
        Overrides the status computed from the deviation (e.g. ``"error"`` with a note).
    note : str
        Short free text shown in the last column (why a fit failed, which features).
    u, U : float or None
        Combined standard uncertainty and expanded uncertainty (k = 2) of ``actual``, in
        ``unit``; None when not evaluated.
    rule : DecisionRule
        How the status follows from the deviation, the tolerance and ``U``.
    """

    name: str
    nominal: float | None
    actual: float | None
    lower: float | None = None
    upper: float | None = None
    unit: str = "mm"
    status: Status | None = None
    note: str = ""
    u: float | None = None
    U: float | None = None
    rule: DecisionRule = "simple"

    @property
    def deviation(self) -> float | None:
        """``actual - nominal``; the actual value itself when there is no nominal."""
        if self.actual is None:
            return None
        return float(self.actual) - float(self.nominal or 0.0)

    @property
    def final_status(self) -> Status:
        if self.status:
            return self.status
        simple = status_of(self.deviation, self.lower, self.upper)
        if self.rule == "simple" or simple != STATUS_PASS:
            return simple
        dev = float(self.deviation)  # type: ignore[arg-type]
        if self.U is None or not math.isfinite(self.U):
            return STATUS_NOT_PROVEN
        near_lower = self.lower is not None and dev < self.lower + self.U
        near_upper = self.upper is not None and dev > self.upper - self.U
        return STATUS_NOT_PROVEN if near_lower or near_upper else STATUS_PASS

    def to_json(self) -> dict[str, Any]:
        """The same numbers as the HTML row, for the JSON/CSV twin of a report."""
        return {
            "name": self.name,
            "unit": self.unit,
            "nominal": self.nominal,
            "actual": self.actual,
            "deviation": self.deviation,
            "lower": self.lower,
            "upper": self.upper,
            "status": self.final_status,
            "note": self.note,
            **({} if self.u is None else {"u": self.u}),
            **({} if self.U is None else {"U": self.U}),
            "decision_rule": self.rule,
        }


class RowCounts:
    """Counts and the verdict of a result made of :class:`ToleranceRow` s (its ``rows``).

    A row that could not be evaluated (``error``) counts as failed; ``n/a`` (no tolerance)
    as neither.
    """

    @property
    def rows(self) -> list[ToleranceRow]:
        raise NotImplementedError

    @property
    def n_passed(self) -> int:
        return sum(r.final_status == STATUS_PASS for r in self.rows)

    @property
    def n_failed(self) -> int:
        return sum(r.final_status in (STATUS_FAIL, STATUS_ERROR) for r in self.rows)

    @property
    def n_not_judged(self) -> int:
        return sum(r.final_status == STATUS_NA for r in self.rows)

    @property
    def n_not_proven(self) -> int:
        return sum(r.final_status == STATUS_NOT_PROVEN for r in self.rows)

    @property
    def passed(self) -> bool:
        """True when no row failed, could not be evaluated, or was left not proven."""
        return self.n_failed == 0 and self.n_not_proven == 0

    @property
    def verdict(self) -> Literal["pass", "fail", "not proven"]:
        """``fail`` when a row failed; else ``not proven`` when one was; else ``pass``."""
        if self.n_failed:
            return "fail"
        return "not proven" if self.n_not_proven else "pass"


def spreadsheet_safe(cell: object) -> object:
    """A CSV cell a spreadsheet shows as text: a string starting with ``= + - @`` (or a tab
    or carriage return) would be evaluated as a formula, so it gets a leading apostrophe.
    Numbers pass unchanged."""
    if isinstance(cell, str) and cell[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + cell
    return cell
