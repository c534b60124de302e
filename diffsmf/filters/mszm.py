"""MSZM: zonotope set-membership filter of Alamo, Bravo & Camacho (Automatica 2005).

The baseline "minimum segments zonotopic method" of Wang et al. 2022 (ref. [19]). Same Stirling
linearisation and DC remainder as `HSNSMF`, evaluated over the interval
hull of the zonotope (Alamo 2005 bounds the remainder over the box hull; Wang et al. 2022, sec. 4.1
names exactly this outer box as a source of the baselines' conservatism; the 2^m vertices of a
zonotope with m generators would also be far too many); the set is a zonotope:

* predict: ``Z+ = f(c) + F (Z - c) (+) E (+) W`` (Alamo 2005 Property 1 / Wang et al. 2022, eq. 9),
  then ``reduce(order, method)`` to at most ``order * n`` generators;
* update: each measurement strip is intersected with ``Zonotope.intersect_strip`` (Alamo 2005
  Property 2, weight by ``strip_method``), then the result is reduced to the same
  ``order * n`` generators (zero-padded), so every step has the same generator count.

Default ``order=12`` (chosen from ``benchmarks/mszm_order_bench.py``: Girard
reduction, F-radius strips, 25 vertex-noise steps, tightness relative to order 60, which never
reduces there; ms per filter step, B = 10, 1 thread, shared 2-core machine, +-20 %):

==================  =====  ===========  ============  ==========
system              order  width/full   volume/full   ms / step
==================  =====  ===========  ============  ==========
spring_damper       5      1.040        1.019         12.9
spring_damper       8      1.019        1.019         11.9
spring_damper       12     1.007        1.008         12.8
spring_damper       20     1.001        1.002         12.5
oscillator_chain    5      1.120        1.100         553
oscillator_chain    12     1.022        0.992         882
==================  =====  ===========  ============  ==========

(bilinear, fermenter and the linear system of ``tests/test_linear_references.py`` hardly
depend on the order: within 0.3 % of order 60 from order 5 on, or below 1 because the
F-radius weight is a heuristic.) Order 12 is the smallest order within 1 % of no reduction on
``spring_damper`` (2.2 % at n = 8); it costs no measurable extra time at B = 10 and n = 2,
about 1.25x the per-step time of order 5 at B = 100 (43 vs 35 ms) and 1.6x at n = 8. Pass
``order=5`` for the earlier, cheaper default. Order is not monotone in tightness with the
F-radius weight: on ``mismatch_quadratic`` order 12 is 10-13 % looser in mean volume than
order 5 (full audit), on ``vdp`` 27 % tighter. Full table in ``docs/filters.md``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet, where
from diffsmf.filters.base import FilterState
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.prediction import prediction_remainder, step_function, zonotope_prediction
from diffsmf.filters.state import predicted_state, updated_state
from diffsmf.filters.strips import stirling_strip_update
from diffsmf.filters.zonotope_gains import GAINS, STRIP_WEIGHTS
from diffsmf.sets.conversions import as_zonotope
from diffsmf.systems.system import System
from diffsmf.utils import descending_order, is_int, tracing, user_stacklevel

__all__ = ["MSZM", "STRIP_WEIGHTS"]


class MSZM(LinearisingFilter):
    """Zonotope filter (Alamo et al. 2005), guaranteed.

    Args:
        system: the system to filter.
        order: reduction order q (at most ``q * n`` generators after each step), >= 1;
            default 12 (measured table in the module docstring).
        reduce_method: ``Zonotope.reduce`` method (``"girard"``, ``"combastel"``, ...).
        strip_method: the weight of the strip intersection, by `STRIP_WEIGHTS` name (CORA's
            observer in brackets): ``"fradius"`` (FRad-A, Alamo et al. 2005, the default),
            ``"volume"`` (VolMin-A, Alamo et al. 2005), ``"bravo"`` (VolMin-B, Bravo et al.
            2006), one strip at a time (`Zonotope.intersect_strip`); ``"wang"`` (FRad-B,
            Wang, Puig & Cembrano 2018) and ``"combastel"`` (FRad-C, Combastel 2015), all
            strips at once with one gain matrix (`Zonotope.intersect_strips`);
            ``"pradius-a"`` / ``"pradius-b"`` (PRad-A / PRad-B, Le et al. 2013) the same with a
            fixed gain designed once by an LMI (`diffsmf.filters.pradius`) on the model
            linearised at the initial set's centre (buffer ``strip_gain [n, m]``, the design
            in ``gain_design``; a design the numpy check does not verify warns). Every weight
            gives a guaranteed set; they differ in tightness.
        tighten_strips: cut each measurement strip to the zonotope's range along it before
            the intersection (``Zonotope.intersect_strip(tighten=True)``): the same
            guaranteed set, tighter where the prior and the strip overlap only in part.
            Off by default (Alamo et al. 2005 as published, CORA's FRad-A).
        stirling_step, remainder_margin, remainder: the linearisation (`LinearisingFilter`);
            the remainder is bounded over the zonotope's interval hull.
        initial_set: override of ``system.x0_set`` (converted to a zonotope).
        **kw: ``process_noise``, ``measurement_noise``, ``skip_nan``, ``learn_noise``
            (see `SetFilter`).

    State set: ``Zonotope`` with batch shape ``[B]`` and ``order * n`` generators.
    """

    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "zonotope"

    def __init__(
        self,
        system: System,
        *,
        order: int = 12,
        reduce_method: str = "girard",
        strip_method: str = "fradius",
        tighten_strips: bool = False,
        **kw,
    ) -> None:
        if not is_int(order) or order < 1:
            raise ValueError(f"order: must be an integer >= 1, got {order!r}")
        super().__init__(system, **kw)
        self.order = int(order)
        self.reduce_method = reduce_method
        if strip_method not in STRIP_WEIGHTS:
            raise ValueError(f"strip_method: unknown strip weight {strip_method!r}; choose "
                             f"from {list(STRIP_WEIGHTS)}")
        self.strip_method = strip_method
        if not isinstance(tighten_strips, bool):
            raise ValueError(f"tighten_strips: expected True or False, got {tighten_strips!r}")
        if tighten_strips and strip_method in GAINS:
            raise ValueError(f"tighten_strips: cuts the strips of the one-at-a-time weights; "
                             f"strip_method={strip_method!r} takes all strips at once")
        self.tighten_strips = tighten_strips
        if strip_method in ("pradius-a", "pradius-b"):
            self._design_gain(per_output=strip_method == "pradius-a")

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        return as_zonotope(S)

    def _design_gain(self, per_output: bool) -> None:
        """PRad-A/B's offline gain (Le et al. 2013) on ``f`` and ``h`` linearised at the
        initial set's centre (the first scheduled input, or 0), with the noises' generators."""
        import warnings

        from diffsmf.filters.pradius import pradius_gain
        from diffsmf.filters.prediction import noise_generators
        from diffsmf.linearize.jacobians import jacobian

        s = self.system
        c = self._x0.center.detach().reshape(1, -1)
        u = s.input_at(0, 1) if s.inputs is not None else (
            None if s.n_inputs == 0 else c.new_zeros(1, s.n_inputs))
        fn = step_function(s, u)
        with torch.no_grad():
            A = jacobian(fn, c)[0].numpy()
            C = jacobian(s.h, c)[0].numpy()
            _, wr, Gw = noise_generators(self)
            E = torch.diag(wr) if Gw is None else torch.cat([torch.diag(wr), Gw], -1)
            E = E[:, E.abs().sum(0) > 0].numpy()
            F = torch.diag(self.measurement_half_widths).numpy()
        design = pradius_gain(A, C, E if E.shape[1] else np.zeros((A.shape[0], 1)), F,
                              per_output=per_output)
        if design.status != "verified":
            warnings.warn(f"strip_method: the P-radius gain is {design.status} "
                          f"({design.message}); the sets stay guaranteed, only less tight",
                          stacklevel=user_stacklevel())
        self.gain_design = design
        self.register_buffer("strip_gain", torch.as_tensor(design.gain, dtype=c.dtype))

    @property
    def n_generators(self) -> int:
        return self.order * self.system.n

    def _fit(self, Z: ConvexSet) -> ConvexSet:
        """Per batch element: reduce to ``order`` only if its *non-zero* generators exceed
        ``order * n`` (zero columns are padding), then zero-pad to exactly ``order * n``.

        Zero generators are moved last (stable, detached choice) so that the padding never
        triggers or takes part in a reduction; batch elements then behave as if run alone.
        """
        from diffsmf.sets.zonotope import Zonotope

        q = self.n_generators
        G = Z.generators
        if G.shape[-1] <= q:
            return Z.pad_generators(q)
        with torch.no_grad():
            nonzero = (G != 0).any(-2)  # [..., M]
            count = nonzero.sum(-1)  # [...]
        if not tracing() and count.numel() > 0:  # eager: one host read of min and max count
            lo, hi = torch.stack(torch.aminmax(count)).tolist()
            if lo == G.shape[-1]:  # no zero columns: the same, sync-cheap
                return Z.reduce(self.order, method=self.reduce_method)
            if hi <= q:  # nothing to reduce: the stable partition's first q columns
                with torch.no_grad():
                    perm = descending_order(nonzero)[..., :q]
                idx = perm.unsqueeze(-2).expand(*G.shape[:-1], q)
                return Zonotope._make(Z.center, torch.gather(G, -1, idx))
        with torch.no_grad():
            dest = _stable_partition(nonzero, count)
        Gc = torch.zeros_like(G).scatter(-1, dest.unsqueeze(-2).expand_as(G), G)
        small = Zonotope(Z.center, Gc[..., :q])  # exact where count <= q
        over = count > q
        if not tracing() and not bool(over.any()):  # nothing to reduce (eager)
            return small
        red = Zonotope(Z.center, Gc).reduce(self.order, method=self.reduce_method)
        return where(over, red.pad_generators(q), small)

    def _initial_state(self, batch: int | None = None) -> FilterState:
        state = super()._initial_state(batch)
        state = state.replace(set=self._fit(state.set))
        if self.strip_method != "wang":
            return state
        # FRad-B's gain maps the set by the last prediction's Jacobian; before the first
        # prediction there is none, and the identity stands in
        c = state.set.center
        eye = torch.eye(c.shape[-1], dtype=c.dtype, device=c.device)
        return state.replace(extras={**state.extras, "_jacobian": eye.expand(*c.shape, -1)})

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """``f(c) + F (Z - c) (+) E (+) W`` then reduction (Alamo 2005 sec. 4)."""
        from diffsmf.linearize.jacobians import stirling_value_jacobian

        Z = state.set
        c, G = Z.center, Z.generators
        fn = step_function(self.system, u)
        hull = Z.interval_hull()
        # Wang 2022, eq. 12, and f(c) in one call of f
        fc, F = stirling_value_jacobian(fn, c, stirling_steps(self, c, hull.radius))
        # remainder over the interval hull (Alamo 2005; Wang et al. 2022, sec. 4.1: the baselines
        # bound the linearisation error over the outer box, HS-NSMF over the parallelotope vertices)
        E, ev = prediction_remainder(  # not finite: flagged (events), never NaN
            self.system, self.remainder_fn, fn, hull, c, F, u, self.remainder_margin,
            events=True,
        )
        FG = linalg.traced_matmul(F, G)
        Zp = zonotope_prediction(self, fc, FG, E)  # W's own generators (Alamo 2005)
        if self.strip_method == "wang":  # FRad-B's gain needs the Jacobian (Wang et al. 2018)
            J = F.expand(*fc.shape, fc.shape[-1])
            state = state.replace(extras={**state.extras, "_jacobian": J})
        return predicted_state(state, self._fit(Zp), ev)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Strips (Wang et al. 2022, eq. 23-29) intersected with Alamo 2005 Property 2, then
        reduced."""
        Z = state.set
        gain = GAINS.get(self.strip_method)
        new, ok, ev = stirling_strip_update(
            self, Z, Z.interval_hull(), y,
            lambda S, st: S.intersect_strip(st, method=self.strip_method,
                                            tighten=self.tighten_strips),
            gain=None if gain is None else lambda S, A, w: gain(self, state, S, A, w),
        )
        new = where(ok, self._fit(new), Z)  # inconsistent: keep the predicted set exactly
        return updated_state(state, new, ok, ev)


def _stable_partition(keep: Tensor, count: Tensor) -> Tensor:
    """Destination of each column ``[..., M]`` (int64) in the stable partition that puts the
    ``keep`` columns first, each group in its original order; ``count [...]`` the number of
    kept columns. The permutation of a stable sort of ``~keep``, from one running sum instead
    of a sort (an extern call under ``torch.compile``): with ``s_j`` the kept columns
    up to ``j``, a kept column goes to ``s_j - 1`` and a dropped one to ``count + j - s_j``
    (``j + 1 - s_j`` dropped columns up to ``j``)."""
    s = torch.cumsum(keep.to(torch.int64), -1)
    j = torch.arange(keep.shape[-1], device=keep.device)
    return torch.where(keep, s - 1, count.unsqueeze(-1) + j - s)
