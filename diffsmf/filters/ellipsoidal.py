"""The shared start of the ellipsoidal filters (CDSMF, ESMF).
"""

from __future__ import annotations

import torch

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.filters.remainders import X0_LOWER, X0_UPPER
from diffsmf.filters.state import check_initial_set, expand_state_set
from diffsmf.sets.conversions import as_ellipsoid
from diffsmf.systems.system import System

__all__ = [
    "EllipsoidalSetFilter",
]


class EllipsoidalSetFilter(SetFilter):
    """Shared start of the ellipsoidal filters (CDSMF, ESMF): the covering ellipsoid of the
    initial set, and its interval hull kept in ``extras[X0_LOWER]`` / ``extras[X0_UPPER]`` so
    that the first remainder is bounded over (ellipsoid hull) ∩ (initial box), see
    `remainder_box`."""

    def __init__(self, system: System, initial_set: ConvexSet | None = None, **kw) -> None:
        super().__init__(system, **kw)
        check_initial_set("initial_set", initial_set, system.n)
        given = initial_set if initial_set is not None else system.x0_set
        self._x0 = as_ellipsoid(given)
        self._x0_box = given.interval_hull()

    def _initial_state(self, batch: int | None = None) -> FilterState:
        S = expand_state_set(self._x0, batch)
        ok = torch.ones(S.batch_shape, dtype=torch.bool)
        shape = (*S.batch_shape, self.system.n)
        lo, hi = self._x0_box.lower.expand(shape), self._x0_box.upper.expand(shape)
        return FilterState(set=S, consistent=ok, extras={X0_LOWER: lo, X0_UPPER: hi})
