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

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import (
    FilterState,
    StrictlyPositive,
    register_minkowski_scale,
    scaled_minkowski_sum,
)
from diffsmf.filters.ellipsoidal import EllipsoidalSetFilter
from diffsmf.filters.params import (
    register_remainder,
    register_remainder_margin,
    register_stirling_step,
    stirling_steps,
)
from diffsmf.filters.prediction import noise_ellipsoid, prediction_remainder, step_function
from diffsmf.filters.remainders import remainder_box, rounding_margin, spent_initial_box
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System
from diffsmf.utils import Positive

__all__ = ["CDSMF"]

SHAPE_MARGIN = 1e-10  # relative outward margin on the shape matrix (float64 rounding)


class CDSMF(EllipsoidalSetFilter):
    """Central-difference ellipsoidal filter (guaranteed).

    Args:
        system: the system to filter.
        stirling_step: Stirling step h (learnable): ``None`` (default) for the step relative
            to the set, ``0.5`` times its hull half-widths (scale-invariant), or an absolute
            step in state units (scalar or ``[n]``); see
            `stirling_steps`.
        sum_method: ``Ellipsoid.minkowski_sum`` method: ``"scaled-trace"`` (default: the
            trace rule in coordinates normalised by the operands' widths, independent of the
            units of the states), ``"trace"`` (the rule in state units, the earlier default)
            or ``"volume"``.
        initial_set: override of ``system.x0_set`` (converted to a covering ellipsoid).
        remainder_margin: learnable inflation ``m >= 0`` (scalar or ``[n]``) of the guaranteed
            prediction remainder box, ``[lo - m, hi + m]``; it only ever enlarges the box, 0
            (default) is the filter without it (see
            `register_remainder_margin`).
        remainder: guaranteed remainder bound by name: ``"dc-vertices"``
            (Wang et al. 2022, eqs. 14-18, 2^n vertices), ``"lagrange"`` (interval Hessian,
            vertex-free), ``"mean-value"``
            (interval Jacobian, cheapest) or ``"auto"`` (default: ``"dc-vertices"`` up to
            n = 8, ``"lagrange"`` up to 16, ``"mean-value"`` above;
            `resolve_remainder`).
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

    #: The set contains every state consistent with the model, the noise bounds and the data.
    guaranteed: bool = True
    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "ellipsoid"
    stirling_step = Positive()
    remainder_margin = Positive()
    minkowski_scale = StrictlyPositive()

    def __init__(
        self,
        system: System,
        *,
        stirling_step: float | Tensor | None = None,
        remainder_margin: float | Tensor = 0.0,
        remainder: str = "auto",
        minkowski_scale: float | Tensor = 1.0,
        sum_method: str = "scaled-trace",
        initial_set: ConvexSet | None = None,
        **kw,
    ) -> None:
        super().__init__(system, initial_set=initial_set, **kw)
        register_stirling_step(self, stirling_step, system.n)
        register_remainder_margin(self, remainder_margin, system.n)
        register_remainder(self, remainder, system.n)
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
