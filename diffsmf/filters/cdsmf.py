"""CDSMF: central-difference (Stirling) ellipsoidal set-membership filter.

The ellipsoidal baseline of Wang et al. 2022 (its ref. [18], Shen et al. 2019), built from the same
pieces as `HSNSMF` so that the comparison isolates the set shape:

* predict: Stirling linearisation about the centre (Wang et al. 2022, eq. 12), DC remainder box over
the
  interval hull of the ellipsoid (eq. 14-18), remainder box + process-noise box covered by the
  ellipsoid ``diag(n r^2)`` (``Ellipsoid.from_box``; the 2-D ``2 r^2`` of Song et al. 2017, eq.
  23/29 generalised, see the erratum), then the outer Minkowski sum (Song et al. 2017, eq. 14-17)
  with the rule's weight (trace-minimal by default) times the learnable ``minkowski_scale``;
* update: the strips of Wang et al. 2022, Theorem 3 intersected one by one with
  ``Ellipsoid.intersect_strip`` (Song et al. 2017, eq. 10-13).
"""

from __future__ import annotations

from torch import Tensor

from diffsmf.filters.base import (
    FilterState,
    StrictlyPositive,
    register_minkowski_scale,
    scaled_minkowski_sum,
)
from diffsmf.filters.ellipsoidal import EllipsoidalSetFilter
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import noise_ellipsoid, prediction_remainder, step_function
from diffsmf.filters.remainder_boxes import remainder_box, rounding_margin, spent_initial_box
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System

__all__ = ["CDSMF"]

SHAPE_MARGIN = 1e-10  # relative outward margin on the shape matrix (float64 rounding)


class CDSMF(EllipsoidalSetFilter):
    """Central-difference ellipsoidal filter (guaranteed).

    Args:
        system: the system to filter.
        sum_method: ``Ellipsoid.minkowski_sum`` method: ``"scaled-trace"`` (default: the
            trace rule in coordinates normalised by the operands' widths, independent of the
            units of the states), ``"trace"`` (the rule in state units, the earlier default)
            or ``"volume"``.
        stirling_step, remainder_margin, remainder: the linearisation (`LinearisingFilter`);
            the remainder is bounded over the ellipsoid's interval hull.
        initial_set: override of ``system.x0_set`` (converted to a covering ellipsoid).
        minkowski_scale: learnable factor ``s > 0`` (scalar) on the weight of the prediction's
            Minkowski sum (Song et al. 2017, eq. 14-17; Jiang et al. 2016, eq. 34-36): ``p = s *
            p_rule`` in ``S(p) = (1 + 1/p) S1 + (1 + p) S2``, ``p_rule`` the ``sum_method`` rule of
            the step (``minkowski_weight``), ``S1`` the linearised set and ``S2`` the covering
            ellipsoid of remainder + noise. Every ``p > 0`` gives an outer bound of the sum,
            so tuning ``s`` never breaks the guarantee; 1 (default) reproduces the rule bit
            for bit. The rule minimises the trace (or volume) of one step's sum, not the
            volume after the update and later steps, which is what tuning ``s`` targets.
            Softplus-scaled (``scale * softplus(raw)``, relative steps). Raises
            ``ValueError`` for 0, negative, NaN or infinite values.

    State set: ``Ellipsoid`` with batch shape ``[B]``.
    """

    minkowski_scale = StrictlyPositive()

    def __init__(
        self,
        system: System,
        *,
        minkowski_scale: float | Tensor = 1.0,
        sum_method: str = "scaled-trace",
        **kw,
    ) -> None:
        super().__init__(system, **kw)
        register_minkowski_scale(self, minkowski_scale)
        self.sum_method = sum_method

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """``f(c) + F (E - c) (+) cover(remainder box + W)``."""
        from diffsmf.linearize import stirling_jacobian
        from diffsmf.sets.ellipsoid import Ellipsoid

        E = state.set
        c = E.center
        fn = step_function(self.system, u)
        box = remainder_box(E, state.extras)
        F = stirling_jacobian(fn, c, stirling_steps(self, c, box.radius))  # eq. 12
        R, ev = prediction_remainder(  # not finite: flagged (events), never NaN
            self.system, self.remainder_fn, fn, box, c, F, u, self.remainder_margin, events=True
        )
        Well = noise_ellipsoid(self)  # None: a box W, summed with the remainder box
        W = self.process_noise_box() if Well is None else None
        fc = fn(c)
        rad = R.radius + (W.radius if W is not None else 0.0)
        rad = rad + rounding_margin(fc, R.center, rad)
        wc = W.center if W is not None else 0.0  # an ellipsoidal Well carries its own centre
        shift = fc - (F @ c.unsqueeze(-1)).squeeze(-1) + R.center + wc
        lin = E.linear_map(F, shift)
        box = Interval(-rad, rad)
        # p = minkowski_scale * rule p (any p > 0 is an outer bound; 1 = the rule exactly)
        new = scaled_minkowski_sum(lin, box.to_ellipsoid(), self.sum_method, self.minkowski_scale)
        if Well is not None:  # an ellipsoidal / zonotope W as given, not its hull
            new = scaled_minkowski_sum(new, Well, self.sum_method, self.minkowski_scale)
        new = Ellipsoid(new.center, new.shape * (1 + SHAPE_MARGIN))
        return state.replace(set=new, extras=spent_initial_box(state.extras)).flag(ev)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Wang et al. 2022, Theorem 3 strips intersected one by one with the ellipsoid."""
        E = state.set
        new, ok, ev = stirling_strip_update(
            self, E, E.interval_hull(), y, lambda S, st: S.intersect_strip(st)
        )
        return state.replace(set=new, consistent=ok).flag(ev, unbounded=False)
