"""Settings every coarse search of the products shares (the pair's VOP match, the canopy keypoint
match, the re-survey's stem match): when two of its solutions are distinct, and how far the best
must lead the best distinct alternative. Each product nests its own, with its own defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..core.params import Params
from ..core.params import param_field as _p

__all__ = ["DistinctParams", "MarginParams"]


@dataclass(frozen=True)
class DistinctParams(Params):
    """When two solutions of a search (rotation about the vertical, horizontal translation) are
    distinct: turned or moved apart by at least this much. Closer ones are the same solution."""

    rotation_deg: float = _p(5.0, "deg", 0.01, 180.0, "Solutions turned apart by more than this are distinct")
    translation_m: float = _p(1.0, "m", 0.01, 1000.0, "Solutions moved apart by more than this are distinct")


@dataclass(frozen=True)
class MarginParams(Params):
    """How far the best solution of a search (VOPs of a pair, stems of two surveys) must lead the
    best distinct alternative to count as unambiguous."""

    min_lead: int = _p(
        2,
        "matches",
        0,
        1000,
        "The best solution must match at least this many more (VOPs, stems) than the best distinct alternative",
    )
    min_lead_fraction: float = _p(
        0.1,
        "1",
        0.0,
        1.0,
        "...and at least this fraction of its own matches more (a plantation's grid lets another solution match many)",
    )

    def needed(self, matched: int) -> int:
        """The lead over the best distinct alternative that a solution matching ``matched`` needs."""
        return max(self.min_lead, math.ceil(self.min_lead_fraction * matched))
