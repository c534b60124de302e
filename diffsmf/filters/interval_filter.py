"""An interval observer: the box family of the nonlinear observer comparison (Holzinger and
Althoff 2026), the cheapest set a filter can keep.

Prediction: Stirling linearisation of ``f`` about the box's centre (Wang et al. 2022, eq. 12),
the guaranteed remainder over the box (eq. 14-18, or the other bounds of
`diffsmf.linearize`), and the interval hull of ``f(c) + F (B - c) (+) E (+) W`` (the box of the
predicted zonotope, eq. 20-21). Update: each measurement strip of Wang et al. 2022, Theorem 3
(eq. 23-29) cut from the box by `Interval.intersect_strip`, the exact hull of a box and a
strip (interval constraint propagation, Jaulin et al. 2001).
"""

from __future__ import annotations

from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import prediction_remainder, step_function, zonotope_prediction
from diffsmf.filters.state import predicted_state, updated_state
from diffsmf.filters.strips import stirling_strip_update

__all__ = ["IntervalFilter"]


class IntervalFilter(LinearisingFilter):
    """Interval (box) set-membership filter, guaranteed.

    Args:
        system: the system to filter.
        stirling_step, remainder_margin, remainder: the linearisation (`LinearisingFilter`);
            the remainder is bounded over the box.
        initial_set: override of ``system.x0_set`` (its interval hull).
        **kw: ``process_half_widths``, ``measurement_half_widths``, ``skip_nan``,
            ``learn_noise`` (see `SetFilter`).

    State set: ``Interval`` with batch shape ``[B]``. A box keeps no correlation between the
    states, so it is looser than the other families where the states are coupled; it is the
    cheapest per step.
    """

    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "interval"

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        return S.interval_hull()

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """The hull of the predicted zonotope ``f(c) + F diag(r) (+) E (+) W`` (eq. 20-21)."""
        from diffsmf.linearize.jacobians import stirling_value_jacobian

        B = state.set
        c, r = B.center, B.radius
        fn = step_function(self.system, u)
        fc, F = stirling_value_jacobian(fn, c, stirling_steps(self, c, r))  # eq. 12
        E, ev = prediction_remainder(  # not finite: flagged (events), never NaN
            self.system, self.remainder_fn, fn, B, c, F, u, self.remainder_margin, events=True
        )  # eq. 14-18 (+ margin)
        Z = zonotope_prediction(self, fc, F * r.unsqueeze(-2), E)  # F diag(r)
        return predicted_state(state, Z.interval_hull(), ev)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Theorem 3 strips (eq. 23-29), each cut from the box in turn."""
        B = state.set
        new, ok, ev = stirling_strip_update(self, B, B, y, lambda S, st: S.intersect_strip(st))
        return updated_state(state, new, ok, ev)
