"""The shared start of the ellipsoidal filters (CDSMF, ESMF).
"""

from __future__ import annotations

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.remainder_boxes import X0_LOWER, X0_UPPER
from diffsmf.sets.conversions import as_ellipsoid

__all__ = [
    "EllipsoidalSetFilter",
]


class EllipsoidalSetFilter(LinearisingFilter):
    """Shared start of the ellipsoidal filters (CDSMF, ESMF): the covering ellipsoid of the
    initial set, and its interval hull kept in ``extras[X0_LOWER]`` / ``extras[X0_UPPER]`` so
    that the first remainder is bounded over (ellipsoid hull) ∩ (initial box), see
    `remainder_box`."""

    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "ellipsoid"

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        self._x0_box = S.interval_hull()
        return as_ellipsoid(S)

    def _initial_state(self, batch: int | None = None) -> FilterState:
        state = super()._initial_state(batch)
        shape = (*state.set.batch_shape, self.system.n)
        lo, hi = self._x0_box.lower.expand(shape), self._x0_box.upper.expand(shape)
        return state.replace(extras={X0_LOWER: lo, X0_UPPER: hi})
