"""ZBSMF: a zonotope-bundle filter (the zonotope-bundle family of Althoff & Krogh 2011, with
the linearisation and remainder of Wang et al. 2022).

The set is a `ZonotopeBundle`: the intersection of k zonotopes, each updated by its own strip
weight (``weights``, names of `Zonotope.intersect_strip`: ``"fradius"``, ``"volume"``,
``"bravo"``). One linearisation serves every member: the Stirling slopes at the centre of the
bundle's outer box and the remainder over that box, the intersection of the members' hulls, so
each member's prediction contains the image of the whole bundle and is no wider than MSZM's
of that member alone:

* predict: ``Z_i+ = f(c) + F (Z_i - c) (+) E (+) W`` for every member (Alamo 2005, Property 1
  as in `MSZM`), then each member reduced to ``order * n`` generators;
* update: the measurement strips (Wang et al. 2022, eq. 23-29, linearised about ``c`` over the
  box) intersected with each member by its weight, then reduced.

A strip that misses some member misses the bundle: the step is then inconsistent and keeps the
prediction, as in the other filters.
"""

from __future__ import annotations

from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet, where
from diffsmf.filters.base import FilterState
from diffsmf.filters.mszm import MSZM
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import prediction_remainder, step_function, zonotope_prediction
from diffsmf.filters.state import predicted_state, updated_state
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.sets.conversions import as_zonotope
from diffsmf.sets.interval import Interval
from diffsmf.sets.zonotope_bundle import ZonotopeBundle
from diffsmf.systems.system import System

__all__ = ["ZBSMF"]

#: The strip weights a bundle member may take (one strip at a time)
MEMBER_WEIGHTS = ("fradius", "volume", "bravo")


class ZBSMF(MSZM):
    """Zonotope-bundle filter, guaranteed.

    Args:
        system: the system to filter.
        weights: the strip weight of each member (`MEMBER_WEIGHTS`), at least one; default
            ``("fradius", "bravo")``: CORA's FRad-A and VolMin-B in one set.
        order, reduce_method: each member's reduction (`MSZM`).
        stirling_step, remainder_margin, remainder, initial_set, **kw: as `MSZM`.

    State set: `ZonotopeBundle` with batch shape ``[B]``, ``len(weights)`` members of
    ``order * n`` generators.
    """

    set_family: str = "zonotope-bundle"

    def __init__(self, system: System, *, weights: tuple[str, ...] = ("fradius", "bravo"),
                 **kw) -> None:
        weights = (weights,) if isinstance(weights, str) else tuple(weights)
        bad = [w for w in weights if w not in MEMBER_WEIGHTS]
        if not weights or bad:
            raise ValueError(f"weights: expected one or more of {MEMBER_WEIGHTS}, got "
                             f"{list(weights)}")
        if "strip_method" in kw or "tighten_strips" in kw:
            raise ValueError("weights: a bundle takes its strip weights as weights=, not "
                             "strip_method= or tighten_strips=")
        object.__setattr__(self, "weights", weights)  # read by _convert_initial in __init__
        super().__init__(system, strip_method=weights[0], **kw)

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        return ZonotopeBundle.from_zonotope(as_zonotope(S), len(self.weights))

    def _fit(self, Z: ConvexSet) -> ConvexSet:
        """Each member reduced and padded to ``order * n`` generators (`MSZM._fit`)."""
        if isinstance(Z, ZonotopeBundle):
            return Z.with_members(super()._fit(Z.members))
        return super()._fit(Z)

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        from diffsmf.linearize.jacobians import stirling_value_jacobian

        Bn = state.set
        hull = Bn.interval_hull()  # the outer box of the bundle, [B, n]
        c = hull.center
        fn = step_function(self.system, u)
        fc, F = stirling_value_jacobian(fn, c, stirling_steps(self, c, hull.radius))
        E, ev = prediction_remainder(
            self.system, self.remainder_fn, fn, hull, c, F, u, self.remainder_margin,
            events=True,
        )
        M = Bn.members  # [B, k]
        Fk = F.unsqueeze(-3)
        FG = linalg.traced_matmul(Fk, M.generators)  # [B, k, n, m]
        fck = fc.unsqueeze(-2) + (Fk @ (M.center - c.unsqueeze(-2)).unsqueeze(-1)).squeeze(-1)
        Ek = Interval._make(E.lower.unsqueeze(-2).expand_as(fck),
                            E.upper.unsqueeze(-2).expand_as(fck))
        Zp = zonotope_prediction(self, fck, FG, Ek)
        return predicted_state(state, self._fit(Bn.with_members(Zp)), ev)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        Bn = state.set
        new, ok, ev = stirling_strip_update(
            self, Bn, Bn.interval_hull(), y, lambda S, st: S.intersect_strip(st, self.weights),
        )
        new = where(ok, self._fit(new), Bn)
        return updated_state(state, new, ok, ev)


