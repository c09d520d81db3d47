"""An uncertainty budget: a measured value's combined standard uncertainty, its expanded
uncertainty and the sources it is made of (GUM, JCGM 100). :mod:`metrology.uncertainty`
evaluates them; the measurement report carries them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["COVERAGE_FACTOR", "Contribution", "Uncertainty"]

#: k of the expanded uncertainty U = k u (about 95 % for a normal distribution).
COVERAGE_FACTOR = 2.0


@dataclass(frozen=True)
class Contribution:
    """One line of an uncertainty budget: a source and its standard uncertainty."""

    source: str
    u: float
    method: str

    def to_json(self) -> dict[str, Any]:
        return {"source": self.source, "u": self.u, "method": self.method}


@dataclass(frozen=True)
class Uncertainty:
    """A measured value's combined standard uncertainty ``u``, ``U = k u`` and its budget."""

    u: float
    budget: tuple[Contribution, ...]
    k: float = COVERAGE_FACTOR
    not_included: tuple[str, ...] = ()

    @property
    def U(self) -> float:
        return self.k * self.u

    def to_json(self) -> dict[str, Any]:
        return {
            "u": self.u,
            "U": self.U,
            "k": self.k,
            "budget": [c.to_json() for c in self.budget],
            "not_included": list(self.not_included),
        }
