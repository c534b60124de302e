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

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.filters.events import hull_radius
from diffsmf.filters.params import (
    register_remainder,
    register_remainder_margin,
    register_stirling_step,
    stirling_steps,
)
from diffsmf.filters.prediction import prediction_remainder, step_function, zonotope_prediction
from diffsmf.filters.state import (
    check_initial_set,
    expand_state_set,
    predicted_state,
    updated_state,
)
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.sets.conversions import as_parallelotope
from diffsmf.systems.system import System
from diffsmf.utils import Positive

__all__ = ["HSNSMF"]

#: The absolute Stirling step (state units) that was the default before the relative one
#: (``stirling_step=None``: ``0.5`` times the set's hull half-widths, scale-invariant); pass it
#: as ``stirling_step=DEFAULT_STIRLING_STEP`` for the earlier filter.
DEFAULT_STIRLING_STEP = 0.1


class HSNSMF(SetFilter):
    """Parallelotope set-membership filter of Wang et al. 2022 (guaranteed).

    Args:
        system: the system to filter.
        stirling_step: Stirling central-difference step h, learnable: ``None`` (default) for
            the step relative to the set, ``0.5`` times its hull half-widths (scale-invariant;
            the registered ``stirling_step`` is then the factor), or an absolute step in state
            units (scalar or ``[n]``); see `stirling_steps`.
        initial_set: override of ``system.x0_set`` (converted to an outer parallelotope).
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
        **kw: ``process_noise``, ``measurement_noise``, ``skip_nan``, ``learn_noise``
            (see `SetFilter`).

    State set: ``Parallelotope`` with batch shape ``[B]``.
    """

    #: The set contains every state consistent with the model, the noise bounds and the data.
    guaranteed: bool = True
    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "parallelotope"
    stirling_step = Positive()
    remainder_margin = Positive()

    def __init__(
        self,
        system: System,
        *,
        stirling_step: float | Tensor | None = None,
        remainder_margin: float | Tensor = 0.0,
        remainder: str = "auto",
        initial_set: ConvexSet | None = None,
        **kw,
    ) -> None:
        super().__init__(system, **kw)
        check_initial_set("initial_set", initial_set, system.n)
        register_stirling_step(self, stirling_step, system.n)
        register_remainder_margin(self, remainder_margin, system.n)
        register_remainder(self, remainder, system.n)
        self._x0 = as_parallelotope(initial_set if initial_set is not None else system.x0_set)

    def _initial_state(self, batch: int | None = None) -> FilterState:
        S = expand_state_set(self._x0, batch)
        return FilterState(set=S, consistent=torch.ones(S.batch_shape, dtype=torch.bool))

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
