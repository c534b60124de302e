"""CZSMF: constrained-zonotope set-membership filter for nonlinear systems (guaranteed).

The set family of Scott, Raimondo, Marseglia, Braatz (Automatica 69, 2016, "Scott 2016"),
`ConstrainedZonotope`, with the linearisation and guaranteed remainders of
the other filters (Wang et al. 2022):

* predict: with ``p`` the midpoint of the interval hull of ``Z`` (the expansion point),
  ``F`` the Stirling slopes of ``f`` at ``p`` (Wang et al. 2022, eq. 12) and ``E`` the guaranteed
  remainder box of ``f(x) - f(p) - F (x - p)`` over the hull (``dc_remainder`` or
  ``lagrange_remainder`` through `prediction_remainder`),
  ``Z+ = F Z + (f(p) - F p + mid E + c_W) (+) box(rad E + r_W) (+) W0`` with W as given
  (`CZSMF._noise`: a box W is ``c_W + box(r_W)``, a zonotope W adds its own generators
  ``W0``, an ellipsoid W its constrained-zonotope cover) -- the linear map and the Minkowski
  sums are exact (Scott 2016 eq. 11-12); the box is merged into the axis generators of the
  generator reduction (Scott 2016 sec. 5) once the generator cap is reached;
* update: the Wang et al. 2022, Theorem 3 strips (eq. 23-29, `
  measurement_strips`, Stirling slopes of ``h`` at the predicted hull midpoint, remainder over
  the predicted hull) are intersected exactly (Scott 2016 eq. 13: one generator and one
  constraint per output), then constraints are eliminated down to the cap (Scott 2016 sec.
  4.2, Prop. 5, Appendix A heuristic);
* consistency: an update is inconsistent when a strip misses the interval hull of the
  predicted set or the updated set is certified empty (crossed LP bounds, a Farkas
  certificate of the dual, `diffsmf.sets.czono_lp`). Only provable emptiness is flagged;
  the filter then carries on with the predicted set (the strips of that element are replaced by
  strips that contain the predicted set, so every element keeps the same shape).

Fixed size: after the first steps every set has exactly ``max_generators`` generators and
``max_constraints`` constraints, so the cost per step is constant. ``max_generators=None`` and
``max_constraints=None`` turn reduction off: the set is then the exact image of the linearised
model (on a linear system: the exact feasible set, see docs/constrained_zonotopes.md).

Discrete choices, made without gradient: which generator/constraint pair to eliminate, which
generators to box, the LP bases of the certificates, the propagation box of the rescaling.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, check_count, stack, where
from diffsmf.filters.base import (
    MAX_SET_RADIUS,
    FilterResult,
    FilterState,
    bounded_result,
    carry,
)
from diffsmf.filters.events import LOSES_BOUND, FilterEvent
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import noise_generators, prediction_remainder, step_function
from diffsmf.filters.remainder_boxes import rounding_margin
from diffsmf.filters.state import expand_state_set
from diffsmf.filters.strips import measurement_strips
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System, check_system
from diffsmf.utils import is_int, tracing

__all__ = ["CZSMF"]


class CZSMF(LinearisingFilter):
    """Constrained-zonotope filter (Scott 2016 set family, Wang et al. 2022 linearisation),
    guaranteed.

    Args:
        system: the system to filter.
        max_generators: generator cap ``q`` (``None``: no reduction), at least
            ``n + max_constraints + 1``. Default ``"auto"``: ``35 n + max_constraints`` (80 for
            n = 2, m = 1: 1.0000 of the exact hull widths on the linear benchmark, see
            docs/constrained_zonotopes.md for the measured table of tightness vs cost).
        max_constraints: constraint cap (``None``: no reduction). Default ``"auto"``: ``4 + 6 m``.
        elimination: choice of the eliminated constraint (Scott 2016 sec. 4.2): ``"hull"``
            (default: the ``HULL_CANDIDATES = 4`` best Appendix A candidates, each eliminated
            exactly and ranked by the hull of the result, 2 n x 4 batched LPs per eliminated
            constraint, whose solutions also certify the kept set's hull), ``"lp"`` (Appendix A
            with LP ranges) or
            ``"propagation"`` (Appendix A as published, interval propagation; cheapest).
        reduce_method: lifted generator reduction, ``"girard"`` | ``"combastel"``.
        stirling_step, remainder_margin, remainder: the linearisation (`LinearisingFilter`);
            the remainder is bounded over the set's certified interval hull (``"dc"``: the
            alias of ``"dc-vertices"``, the bound at the hull's corners).
        rescale: apply the exact propagation rescaling (Scott 2016 Appendix A) before each
            reduction.
        lp_iters: interior-point iterations of the hull LPs (every bound is certified
            whatever the count).
        initial_set: override of ``system.x0_set`` (converted by
            `ConstrainedZonotope.from_set`: exact for boxes/zonotopes, outer for
            ellipsoids).
        **kw: ``process_noise``, ``measurement_noise``, ``skip_nan``, ``learn_noise``
            (`SetFilter`).

    State set: ``ConstrainedZonotope`` with batch shape ``[B]``; ``state.extras["lower"]`` /
    ``["upper"]`` hold its certified interval hull ``[B, n]`` (computed once per set).
    """

    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "constrained-zonotope"
    _constant_set_size = False  # the predicted set has more generators than the capped update

    def __init__(
        self,
        system: System,
        *,
        max_generators: int | str | None = "auto",
        max_constraints: int | str | None = "auto",
        reduce_method: str = "girard",
        rescale: bool = True,
        lp_iters: int = 15,
        elimination: str = "hull",
        **kw,
    ) -> None:
        check_system("system", system)
        n, m = system.n, system.m
        if isinstance(max_constraints, str) and max_constraints == "auto":
            max_constraints = 4 + 6 * m
        if max_constraints is not None and (
            not is_int(max_constraints) or max_constraints < 0
        ):
            raise ValueError(
                f"max_constraints: must be an integer >= 0, \"auto\" or None, got "
                f"{max_constraints!r}"
            )
        if isinstance(max_generators, str) and max_generators == "auto":
            max_generators = 35 * n + (max_constraints or 0)
        if (max_generators is None) != (max_constraints is None):
            raise ValueError("max_generators: give both caps or None for both (no reduction)")
        if max_generators is not None and (
            not is_int(max_generators) or max_generators < n + max_constraints + 1
        ):
            raise ValueError(
                f"max_generators: must be an integer >= n + max_constraints + 1 = "
                f"{n + (max_constraints or 0) + 1}, \"auto\" or None, got {max_generators!r}"
            )
        if reduce_method not in ("girard", "combastel"):
            raise ValueError(f"reduce_method: unknown {reduce_method!r} (girard | combastel)")
        check_count("lp_iters", lp_iters)
        if elimination not in ("hull", "lp", "propagation"):
            raise ValueError(f"elimination: unknown {elimination!r} (hull | lp | propagation)")
        super().__init__(system, **kw)
        self.max_generators = None if max_generators is None else int(max_generators)
        self.max_constraints = None if max_constraints is None else int(max_constraints)
        self.reduce_method = reduce_method
        self.rescale = rescale
        self.lp_iters = lp_iters
        self.elimination = elimination

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        """Exact for boxes and zonotopes, outer for ellipsoids (`ConstrainedZonotope.from_set`)."""
        return ConstrainedZonotope.from_set(S)

    # ------------------------------------------------------------------ helpers

    def _noise(self) -> tuple[Tensor, Tensor, ConstrainedZonotope | None]:
        """The process noise W as given -> ``(center [n], box half-widths
        [n], W0)``, ``W = center + box(half-widths) (+) W0``.

        * box W (every built-in): ``(c, r, None)``, added as the diagonal box generators, bit
          for bit as before (`noise_generators`);
        * Zonotope / Parallelotope W: ``(c, 0, {G xi})``, its generators added as they are
          (Scott 2016 eq. 12, exact);
        * Ellipsoid W: ``(c, 0, W0)`` with ``W0`` the guaranteed constrained-zonotope cover of
          `ConstrainedZonotope.from_set` (the parallelotope ``Q^(1/2) [-1, 1]^n``
          intersected with the interval hull of W, ``2 n`` generators and ``n`` constraints,
          inflated by 1e-9 relative): contained in both the interval hull and the
          parallelotope cover, so never looser than either.

        ``W`` is `SetFilter.process_noise_set` (the system's set scaled per component by
        the learnable ``process_noise``; differentiable).
        """
        from diffsmf.sets.ellipsoid import Ellipsoid

        W = self.process_noise_set()
        if isinstance(W, Ellipsoid):
            c = W.center
            W0 = ConstrainedZonotope.from_set(W).translate(-c)
            return c, torch.zeros_like(c), W0
        wc, wr, Gw = noise_generators(self)
        if Gw is None:
            return wc, wr, None
        return wc, wr, ConstrainedZonotope._from_generators(torch.zeros_like(wc), Gw)

    def _hull(self, Z: ConstrainedZonotope) -> tuple[Tensor, Tensor]:
        H = Z.interval_hull(iters=self.lp_iters)
        return H.lower, H.upper

    def _state(self, Z: ConstrainedZonotope, ok: Tensor) -> FilterState:
        lo, hi = self._hull(Z)
        return FilterState(set=Z, consistent=ok, extras={"lower": lo, "upper": hi})

    @property
    def reduces(self) -> bool:
        return self.max_generators is not None

    # ------------------------------------------------------------------ contract
    def _initial_state(self, batch: int | None = None) -> FilterState:
        Z = expand_state_set(self._x0, batch)
        if self.reduces:
            Z = self._cap(Z)
        ok = torch.ones(Z.batch_shape, dtype=torch.bool, device=Z.device)
        return self._state(Z, ok)

    def _cap(self, Z: ConstrainedZonotope, box: Tensor | None = None) -> ConstrainedZonotope:
        """Constraint elimination then lifted generator reduction to the caps (``box``: the
        box radius ``[B, n]`` to add exactly, merged into the reduction's axis generators)."""
        return self._cap_hull(Z, box)[0]

    def _cap_hull(
        self, Z: ConstrainedZonotope, box: Tensor | None = None
    ) -> tuple[ConstrainedZonotope, tuple[Tensor, Tensor] | None]:
        """`_cap` -> ``(Z, duals)``: ``duals`` are the hull LP solutions of the result
        when its last operation was a ``"hull"`` elimination (the ranking solved them), else
        ``None``."""
        duals = None
        if Z.num_constraints > self.max_constraints:
            if self.rescale:
                Z = Z.rescale()
            Z, duals = Z._reduce_constraints(self.max_constraints, self.elimination)
        extra = 0 if box is None else Z.dim
        if Z.num_generators + extra > self.max_generators:
            if self.rescale and Z.num_constraints:
                Z = Z.rescale()
            Z = Z.reduce_generators(self.max_generators, self.reduce_method, box_radius=box)
            return Z, None
        return (Z, duals) if box is None else (Z._append_box(box), None)

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """``F Z + f(p) - F p + E + W`` (Scott 2016 eq. 11-12, Wang et al. 2022, eq. 12-21)."""
        from diffsmf.linearize import stirling_jacobian

        Z = state.set
        lo, hi = state.extras["lower"], state.extras["upper"]
        hull = Interval._make(lo, hi)
        p = 0.5 * (lo + hi)  # expansion point: the hull midpoint
        fn = step_function(self.system, u)
        F = stirling_jacobian(fn, p, stirling_steps(self, p, hull.radius))  # eq. 12
        E, ev = prediction_remainder(  # not finite: flagged unbounded (placeholder set)
            self.system, self.remainder_fn, fn, hull, p, F, u, self.remainder_margin,
            events=True,
        )  # remainder over the interval hull of Z (+ margin)
        wc, wr, Wz = self._noise()
        fp = fn(p)
        Fp = (F @ p.unsqueeze(-1)).squeeze(-1)
        FZ = Z.linear_map(F)
        shift = fp - Fp + E.center + wc
        rad = E.radius + wr
        rad = rad + rounding_margin(fp, Fp, E.center, (F.abs() @ Z.generators.abs()).sum(-1), rad)
        Zp = FZ.translate(shift)
        if Wz is not None:  # a non-box W: its own generators (and constraints), exact
            Zp = Zp.minkowski_sum(Wz)
        Zp, rad, ev = _finite_or_point(Zp, rad, ev, state.bounded)  # no NaN reaches the LPs
        Zp = self._cap(Zp, rad) if self.reduces else Zp._append_box(rad)
        new = self._state(Zp, state.consistent).replace(bounded=state.bounded)
        return new.flag(ev)

    def _guarded_update(self, state: FilterState, y: Tensor, bad: Tensor) -> FilterState:
        """`update` on a validated ``y [B, m]`` (``bad [B]``: its NaN rows, which leave the set
        unchanged: replaced by strips that contain it, so the shapes stay equal)."""
        y = torch.where(bad.unsqueeze(-1), torch.zeros_like(y), y)
        return carry(state, self._update(state, y, skip=bad), update=True)

    def _update(self, state: FilterState, y: Tensor, skip: Tensor | None = None) -> FilterState:
        """Theorem 3 strips intersected exactly (Scott 2016 eq. 13), then eliminated to the cap."""
        from diffsmf.linearize import stirling_jacobian

        Z = state.set
        lo, hi = state.extras["lower"], state.extras["upper"]
        hull = Interval._make(lo, hi)
        p = 0.5 * (lo + hi)
        H = stirling_jacobian(self.system.h, p, stirling_steps(self, p, hull.radius))  # eq. 13
        a, d, w, ev = measurement_strips(
            self.system.h, self.remainder_fn, hull, p, H, y, self.measurement_noise_box(),
            self.system, events=True,
        )  # eq. 23-29: |a_i x - d_i| <= w_i, [B, m, n], [B, m], [B, m]
        # (a degenerate row, a zero or non-finite normal or a non-finite offset, is all of R^n
        # here already: measurement_strips, with the event DEGENERATE_STRIP)
        # projection of the predicted hull on each normal: the strip that contains the set
        pm = (a * p.unsqueeze(-2)).sum(-1)
        pr = (a.abs() * (0.5 * (hi - lo)).unsqueeze(-2)).sum(-1)
        pr = pr + rounding_margin(pm, pr)
        atol = rounding_margin(d, w).detach()
        miss = ((pm - d).abs() > pr + w + atol).any(-1)  # a strip misses the hull: empty
        miss = miss & torch.isfinite(w).all(-1)
        # a skipped measurement or an unbounded remainder of h (infinite half-width) does not
        # shrink the set: its strips are replaced by ones that contain the predicted set
        off = miss | torch.isinf(w).any(-1)
        off = off if skip is None else off | skip
        o1 = off.unsqueeze(-1)
        d = torch.where(o1, pm, d)
        w = torch.where(o1, pr, w)
        Zu = Z._intersect_strips(a, d, w)  # Scott 2016 eq. 13, exact (w >= 0 by eq. 23-29)
        duals = None
        if self.reduces:
            Zu, duals = self._cap_hull(Zu)
        if duals is None:
            ulo, uhi = self._hull(Zu)
        else:  # certified from the elimination ranking's LP solutions: no second solve
            H = Zu._hull_from_duals(*duals)
            ulo, uhi = H.lower, H.upper
        empty = (ulo > uhi).any(-1)  # certified: crossed dual bounds
        ok = ~miss & ~empty
        if skip is not None:
            ok = torch.where(skip, state.consistent, ok)
        # certified-empty elements carry on with the predicted set; a rare fault path (one
        # host sync per step; while tracing it is always taken, branch-free)
        if tracing() or bool(empty.any()):
            Zu = where(empty, self._fault_set(Z, Zu, a, pm, pr), Zu)
            e1 = empty.unsqueeze(-1)
            ulo, uhi = torch.where(e1, lo, ulo), torch.where(e1, hi, uhi)
        bounded = torch.isfinite(ulo).all(-1) & torch.isfinite(uhi).all(-1)
        bounded = bounded & ((uhi - ulo) <= 2 * MAX_SET_RADIUS).all(-1)
        if state.bounded is not None:
            bounded = bounded & state.bounded
        Zu, _, _ = _finite_or_point(Zu, ulo, torch.zeros_like(ev), bounded)
        ulo = torch.where(bounded.unsqueeze(-1), ulo, torch.zeros_like(ulo))
        uhi = torch.where(bounded.unsqueeze(-1), uhi, torch.zeros_like(uhi))
        new = FilterState(set=Zu, consistent=ok, extras={"lower": ulo, "upper": uhi})
        was = torch.ones_like(bounded) if state.bounded is None else state.bounded
        ev = ev | torch.where(was & ~bounded, int(FilterEvent.DIVERGED), 0)
        return new.replace(bounded=state.bounded).and_bounded(bounded).flag(ev, unbounded=False)

    def _fault_set(
        self, Z: ConstrainedZonotope, Zu: ConstrainedZonotope, a: Tensor, pm: Tensor, pr: Tensor
    ) -> ConstrainedZonotope:
        """The predicted set ``Z`` in the shape of the updated ``Zu``: ``Z`` itself when the
        shapes agree (at the caps, every step that ``compile()`` traces), else ``Z``
        intersected with its containing strips ``|a_i x - pm_i| <= pr_i`` (the same set, the
        shape of ``Zu`` before the cap) and capped like ``Zu`` (an outer bound of ``Z``)."""
        shape = (Z.num_generators, Z.num_constraints)
        if shape == (Zu.num_generators, Zu.num_constraints):
            return Z
        Zf = Z._intersect_strips(a, pm, pr)
        return self._cap(Zf) if self.reduces else Zf

    def _compile_ready(self, state: FilterState) -> bool:
        """The compiled graph serves the fixed-size phase only: a step whose state set is not
        yet at the caps (the first steps, while generators and constraints grow; every step
        with ``max_generators=None``) runs eagerly, so that one graph (static shapes) serves
        every later step. While tracing, the LPs run their fixed iteration count
        (`box_lp`) and the fault path is taken branch-free.
        Eager steps do not count towards ``forward``'s guard skip: the first compiled calls at
        the caps run Dynamo's full guard check (`diffsmf.filters.runtime.GUARDED_STEPS`)."""
        S = state.set
        at_caps = self.reduces and (S.num_generators, S.num_constraints) == (
            self.max_generators, self.max_constraints
        )
        return at_caps and super()._compile_ready(state)

    def collect(self, states: list[FilterState]) -> FilterResult:
        """Results from the cached hulls (no LP re-solve); sets padded to a common size."""
        mg = max(s.set.num_generators for s in states)
        mc = max(s.set.num_constraints for s in states)
        sets = stack([s.set.pad(mg, mc) for s in states], dim=1)
        lower = torch.stack([s.extras["lower"] for s in states], 1)
        upper = torch.stack([s.extras["upper"] for s in states], 1)
        center = 0.5 * (lower + upper)
        volume = (upper - lower).clamp_min(0).prod(-1)
        return bounded_result(
            FilterResult, states, sets, center, lower, upper, volume,
            {"lower": lower, "upper": upper},
        )


def _finite_or_point(
    Z: ConstrainedZonotope, rad: Tensor, ev: Tensor, bounded: Tensor | None
) -> tuple[ConstrainedZonotope, Tensor, Tensor]:
    """``(Z', rad', ev')``: where ``Z [B]`` or ``rad [B, n]`` has a non-finite entry (event
    ``NON_FINITE``), an event already lost the bound, or ``bounded [B]`` is False, the set is
    replaced by the point 0 (every field 0) and ``rad`` by 0: a finite placeholder of the same
    shape, so that no NaN / inf reaches the LPs of the batch; those elements are flagged
    unbounded and never read. Branch-free."""
    nb = len(Z.batch_shape)
    fin = torch.isfinite(rad).all(-1)
    for t in Z._tensors():
        fin = fin & torch.isfinite(t.detach()).flatten(nb).all(-1)
    was = torch.ones_like(fin) if bounded is None else bounded
    ev = ev | torch.where(was & ~fin & (ev == 0), int(FilterEvent.NON_FINITE), 0)
    keep = fin & was & ((ev & LOSES_BOUND) == 0)
    Z0 = Z._rebuild([torch.zeros_like(t) for t in Z._tensors()])
    return where(keep, Z, Z0), torch.where(keep.unsqueeze(-1), rad, torch.zeros_like(rad)), ev
