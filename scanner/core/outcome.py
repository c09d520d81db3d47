"""Results that may have failed: falsy, with the reason, instead of raising.

A calibration stage that cannot produce its result for one view or one data set (too few
features, a degenerate fit) returns a failed result the caller can skip and report; the result
classes build on :class:`Outcome` so that all of them answer ``if result:`` and ``result.reason``
the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Outcome"]


@dataclass
class Outcome:
    """Whether a result was obtained, and why not when it was not (falsy then).

    Subclasses add their own fields, all with defaults, so that ``Subclass(False, "why")`` is a
    failed result and ``Subclass(True, field=...)`` a good one.

    Attributes
    ----------
    ok : bool
    reason : str
        Why the result could not be obtained; empty when ``ok``.
    """

    ok: bool
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok
