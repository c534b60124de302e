"""HS-NSMF: hyperparallel-space (parallelotope) nonlinear set-membership filter, Wang et al. 2022.

Prediction (Theorem 1-2, eq. 10-22): Stirling linearisation of ``f`` about the centre, the
DC-programming remainder box (with the Hessian-bound alpha of the Wang et al. 2022 erratum), the box
sum remainder + process noise (Theorem 2), the zonotope ``[F T, T_e + T_w]`` (eq. 20-21) and
its minimal-volume outer parallelotope (Chisci 1996, eq. 22).

Update (Theorem 3, eq. 23-41): each measurement component becomes a strip (Stirling
linearisation of ``h`` about the predicted centre, remainder and noise bound folded into the
half-width) intersected one by one with the parallelotope (eq. 30-41).
"""

from __future__ import annotations

from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState
from diffsmf.filters.events import hull_radius
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import prediction_remainder, step_function, zonotope_prediction
from diffsmf.filters.state import predicted_state, updated_state
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.sets.conversions import as_parallelotope

__all__ = ["HSNSMF"]

#: The absolute Stirling step (state units) that was the default before the relative one
#: (``stirling_step=None``: ``0.5`` times the set's hull half-widths, scale-invariant); pass it
#: as ``stirling_step=DEFAULT_STIRLING_STEP`` for the earlier filter.
DEFAULT_STIRLING_STEP = 0.1


class HSNSMF(LinearisingFilter):
    """Parallelotope set-membership filter of Wang et al. 2022 (guaranteed).

    Args:
        system: the system to filter.
        stirling_step, remainder_margin, remainder: the linearisation (`LinearisingFilter`):
            by default the Stirling step relative to the set and ``remainder="auto"``
            (Wang et al. 2022's DC vertex bound, eq. 14-18, up to n = 8).
        initial_set: override of ``system.x0_set`` (converted to an outer parallelotope).
        **kw: ``process_noise``, ``measurement_noise``, ``skip_nan``, ``learn_noise``
            (see `SetFilter`).

    State set: ``Parallelotope`` with batch shape ``[B]``.
    """

    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "parallelotope"

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        return as_parallelotope(S)

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Theorem 1-2 (eq. 20-22): zonotope ``[F T, T_e + T_w]`` -> outer parallelotope."""
        from diffsmf.linearize.jacobians import stirling_value_jacobian

        P = state.set
        c, T = P.center, P.T
        fn = step_function(self.system, u)
        h = stirling_steps(self, c, hull_radius(P))  # the hull's half-widths sum_j |T_ij|
        fc, F = stirling_value_jacobian(fn, c, h)  # eq. 12 and f(c) in one call of f
        E, ev = prediction_remainder(  # not finite: flagged (events), never NaN
            self.system, self.remainder_fn, fn, P, c, F, u, self.remainder_margin, events=True
        )  # eq. 14-18 (+ margin)
        Z = zonotope_prediction(self, fc, linalg.traced_matmul(F, T), E)  # eq. 20-21
        return predicted_state(state, Z.to_parallelotope(), ev)  # eq. 22 (Chisci)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Theorem 3 strips (eq. 23-29) intersected one by one (eq. 30-41)."""
        P = state.set  # remainder of h at the parallelotope's vertices
        new, ok, ev = stirling_strip_update(self, P, P, y, lambda S, st: S.intersect_strip(st))
        return updated_state(state, new, ok, ev)
