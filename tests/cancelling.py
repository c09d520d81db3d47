"""A stand-in for a PLC job's cancellation check, for the tests of cooperative cancellation."""

from __future__ import annotations


class Cancelled(Exception):
    """What :class:`CancelAt` raises."""


class CancelAt:
    """A ``check_cancelled`` callable that raises :class:`Cancelled` on its ``n``-th call.

    ``calls`` counts the calls made (the raising one included).
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.calls = 0

    def __call__(self) -> None:
        self.calls += 1
        if self.calls == self.n:
            raise Cancelled
