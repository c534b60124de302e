"""Constrained zonotopes ``{c + G xi : A xi = b, ||xi||_inf <= 1}``, batched and differentiable.

Scott, Raimondo, Marseglia, Braatz, "Constrained zonotopes: a new tool for set-based estimation
and fault detection", Automatica 69 (2016) 126-136 ("Scott 2016" below). ``center [..., n]``,
``generators [..., n, m]``, ``A [..., k, m]``, ``b [..., k]``; every convex polytope is one.

Exact operations (Scott 2016 sec. 3): linear map and Minkowski sum (eq. 11-12), generalised
intersection (eq. 13) -- in particular with a strip or a half-space, which adds one generator
and one constraint. Outer operations: constraint elimination (sec. 4.2, Prop. 5, with the
Hausdorff heuristic of Appendix A), generator reduction through the lifted zonotope (sec. 5),
the outer bound of an ellipsoid. The support function, interval hull, emptiness and
membership need LPs, solved batched in torch by `diffsmf.sets.czono_lp`; every reported
bound is a weak-duality certificate (valid even if the solver stopped early), see there.

Discrete choices (which constraint / generator to eliminate, which generators to box, the
basis of the LP certificate) are made on detached values; the chosen formula is then evaluated
with gradients.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, as_offset, as_tensor, check_count, check_finite, strip_fields
from diffsmf.sets.czono_elimination import (
    PROPAGATION_SWEEPS,
    _eliminate,
    _elimination_choice,
    _propagate,
)
from diffsmf.sets.czono_lp import LP_ITERS, box_lp, distance_lp, support_value
from diffsmf.utils import descending_order, is_int

__all__ = ["ConstrainedZonotope", "as_constrained_zonotope", "distance_lp"]

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.interval import Interval
    from diffsmf.sets.strip import Strip
    from diffsmf.sets.zonotope import Zonotope


_EPS = torch.finfo(torch.float64).eps


#: Weight of the constraint rows in the lifted generator-reduction score (the detached choice
#: of the boxed generators only; any weight is an outer bound). 3 was measured tighter than 1
#: on the linear benchmark of docs/constrained_zonotopes.md (caps (12, 3): 1.51 -> 1.35 of
#: the exact widths, (20, 4): 1.22 -> 1.20, (40, 6): 1.13 -> 1.11).
CONSTRAINT_WEIGHT = 3.0


class ConstrainedZonotope(ConvexSet):
    """Constrained zonotope ``{c + G xi : A xi = b, xi in [-1, 1]^m}`` (Scott 2016 Def. 3).

    Args:
        center: ``[..., n]``.
        generators: ``[..., n, m]`` (m >= 0).
        A: ``[..., k, m]`` constraint matrix (k >= 0); ``None`` = no constraints (a zonotope).
        b: ``[..., k]``; ``None`` together with ``A``. Batch dims of all four broadcast.

    Raises:
        ValueError: naming the argument on NaN/inf or a shape mismatch.

    ``volume()`` is the volume of the interval hull (a documented proxy: an upper bound of the
    true volume, 0 for an empty or flat set). The set may be empty: `is_empty`
    certifies emptiness, `interval_hull` then has crossed bounds (``lower > upper``).
    """

    _fields: ClassVar[tuple[str, ...]] = ("_c", "generators", "A", "b")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2, 2, 1)
    generators: Tensor
    A: Tensor
    b: Tensor

    def __init__(self, center: Any, generators: Any, A: Any = None, b: Any = None) -> None:
        c = check_finite("center", as_tensor("center", center, min_dim=1, field=True))
        G = check_finite(
            "generators", as_tensor("generators", generators, like=c, min_dim=2, field=True))
        n, m = c.shape[-1], G.shape[-1]
        if G.shape[-2] != n:
            raise ValueError(
                f"generators: expected shape [..., {n}, m] to match center [..., {n}], "
                f"got {tuple(G.shape)}"
            )
        if (A is None) != (b is None):
            raise ValueError("A: give both A and b, or neither")
        if A is None:
            A = c.new_zeros(0, m)
            b = c.new_zeros(0)
        A = check_finite("A", as_tensor("A", A, like=c, min_dim=2, field=True))
        b = check_finite("b", as_tensor("b", b, like=c, min_dim=1, field=True))
        if A.shape[-1] != m:
            raise ValueError(
                f"A: expected shape [..., k, {m}] (m = generators), got {tuple(A.shape)}"
            )
        if b.shape[-1] != A.shape[-2]:
            raise ValueError(
                f"b: expected shape [..., {A.shape[-2]}] to match A, got {tuple(b.shape)}"
            )
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], G.shape[:-2], A.shape[:-2], b.shape[:-1])
        except RuntimeError as exc:
            raise ValueError(
                f"generators/A/b: batch shapes {tuple(G.shape[:-2])}, {tuple(A.shape[:-2])}, "
                f"{tuple(b.shape[:-1])} do not broadcast with center {tuple(c.shape[:-1])}"
            ) from exc
        self._set(
            _c=c.expand(*batch, n),
            generators=G.expand(*batch, n, m),
            A=A.expand(*batch, *A.shape[-2:]),
            b=b.expand(*batch, b.shape[-1]),
        )

    @classmethod
    def _make(cls, c: Tensor, G: Tensor, A: Tensor, b: Tensor) -> ConstrainedZonotope:
        """Internal constructor without validation (broadcasts the batch dims)."""
        batch = torch.broadcast_shapes(c.shape[:-1], G.shape[:-2], A.shape[:-2], b.shape[:-1])
        obj = object.__new__(cls)
        object.__setattr__(obj, "_c", c.expand(*batch, c.shape[-1]))
        object.__setattr__(obj, "generators", G.expand(*batch, *G.shape[-2:]))
        object.__setattr__(obj, "A", A.expand(*batch, *A.shape[-2:]))
        object.__setattr__(obj, "b", b.expand(*batch, b.shape[-1]))
        return obj

    # ------------------------------------------------------------------ structure
    @property
    def center(self) -> Tensor:
        """``c [..., n]`` (not necessarily a point of the set: ``xi = 0`` may violate
        ``A xi = b``)."""
        return self._c

    @property
    def num_generators(self) -> int:
        """m."""
        return self.generators.shape[-1]

    @property
    def num_constraints(self) -> int:
        """k."""
        return self.A.shape[-2]

    def pad_generators(self, m: int) -> ConstrainedZonotope:
        """Append zero generators (and zero constraint columns) up to ``m`` (same set)."""
        k = self.num_generators
        if m < k:
            raise ValueError(f"m: cannot pad {k} generators down to {m}")
        if m == k:
            return self
        G, A = _zero_pad(self.generators, -1, m - k), _zero_pad(self.A, -1, m - k)
        return ConstrainedZonotope._make(self._c, G, A, self.b)

    def pad_constraints(self, k: int) -> ConstrainedZonotope:
        """Append trivial constraints ``0 xi = 0`` up to ``k`` rows (same set)."""
        j = self.num_constraints
        if k < j:
            raise ValueError(f"k: cannot pad {j} constraints down to {k}")
        if k == j:
            return self
        A, b = _zero_pad(self.A, -2, k - j), _zero_pad(self.b, -1, k - j)
        return ConstrainedZonotope._make(self._c, self.generators, A, b)

    def pad(self, m: int, k: int) -> ConstrainedZonotope:
        """`pad_generators` then `pad_constraints` (same set)."""
        return self.pad_generators(m).pad_constraints(k)

    # ------------------------------------------------------------------ conversions
    @classmethod
    def from_set(cls, S: ConvexSet) -> ConstrainedZonotope:
        """Constrained zonotope containing ``S``: exact for Interval, Zonotope, Parallelotope
        and ConstrainedZonotope; outer for an Ellipsoid (the parallelotope ``c + Q^{1/2}
        [-1, 1]^n`` intersected with its interval hull, Scott 2016 eq. 13, inflated by 1e-9
        relative for rounding); outer (interval hull) for any other bounded set.

        Raises ``ValueError`` for an unbounded set (Strip, infinite Interval) or an ``S`` that
        is not a diffsmf set.
        """
        from diffsmf.sets.ellipsoid import Ellipsoid
        from diffsmf.sets.interval import Interval
        from diffsmf.sets.strip import Strip

        if not isinstance(S, ConvexSet):
            raise ValueError(
                f"S: expected a diffsmf set (Interval, Zonotope, Ellipsoid, ...), got "
                f"{type(S).__name__}"
            )
        if isinstance(S, ConstrainedZonotope):
            return S
        if isinstance(S, Strip):
            raise ValueError("S: a strip is unbounded; intersect a bounded set with it instead")
        if isinstance(S, Ellipsoid):
            Q = S.shape
            e, V = torch.linalg.eigh(Q)
            root = (V * e.clamp_min(0).sqrt().unsqueeze(-2)) @ V.mT * (1 + 1e-9)
            P = cls._from_generators(S.center, root)
            r = torch.diagonal(Q, dim1=-2, dim2=-1).clamp_min(0).sqrt() * (1 + 1e-9)
            return P.intersect(cls._from_generators(S.center, torch.diag_embed(r)))
        G = getattr(S, "generators", None)  # Zonotope, Parallelotope (T)
        if G is not None and not isinstance(S, Interval):
            return cls._from_generators(S.center, G)
        box = S if isinstance(S, Interval) else S.interval_hull()
        lo, hi = box.lower, box.upper
        if not (torch.isfinite(lo.detach()).all() and torch.isfinite(hi.detach()).all()):
            raise ValueError("S: unbounded (infinite interval bounds)")
        return cls._from_generators(0.5 * (lo + hi), torch.diag_embed(0.5 * (hi - lo)))

    @classmethod
    def _from_generators(cls, c: Tensor, G: Tensor) -> ConstrainedZonotope:
        return cls._make(
            c, G, G.new_zeros(*G.shape[:-2], 0, G.shape[-1]), G.new_zeros(*G.shape[:-2], 0)
        )

    def to_zonotope(self) -> Zonotope:
        """Outer zonotope: every constraint eliminated (Scott 2016 Prop. 5, see
        `reduce_constraints`)."""
        from diffsmf.sets.zonotope import Zonotope

        Z = self.reduce_constraints(0)
        return Zonotope._make(Z._c, Z.generators)

    def to_constrained_zonotope(self) -> ConstrainedZonotope:
        return self

    # ------------------------------------------------------------------ support, hull, LPs
    def support(self, d: Tensor, iters: int = LP_ITERS) -> Tensor:
        """Certified upper bound of ``h(d) = max_{x in Z} d.x``; ``d [..., n]`` -> ``[...]``.

        The LP ``d'c + max {d'G xi : A xi = b, |xi| <= 1}`` is solved by a fixed number of
        interior-point iterations and bounded by its dual (weak duality, any multiplier gives
        an upper bound; `diffsmf.sets.czono_lp`), plus float64 rounding margins: the
        value is an outer bound even when the solver stopped early. Exact (to ~1e-12 relative)
        at convergence. ``-inf``-like (very negative) for an empty set. Differentiable: the
        gradient is the LP's envelope gradient (Lagrangian at the primal-dual solution).
        """
        d = as_tensor("d", d, like=self._c, min_dim=1)
        if d.shape[-1] != self.dim:
            raise ValueError(f"d: expected [..., {self.dim}], got {tuple(d.shape)}")
        c, G, A, b = self._c, self.generators, self.A, self.b
        return support_value(d, c, G, A, b, iters)

    def outer_polygon_2d(self, k: int = 64, iters: int = LP_ITERS) -> Tensor:
        """Vertices ``[..., k, 2]`` (counter-clockwise) of the outer polygon of a 2-D set.

        The polygon is ``{x : d_i.x <= h(d_i), i < k}`` with ``d_i = (cos, sin)(2 pi i / k)``
        and ``h`` the certified support (`support`), so it contains the set and touches
        it in the ``k`` directions; vertex ``i`` is where the support lines ``i`` and ``i + 1``
        meet. For plots and area measurements (`diffsmf.plot.polygon_2d`; the CZSMF
        areas in docs/constrained_zonotopes.md): the vertices are computed in float64 without
        outward rounding. An empty set (crossed support values) gives a polygon with no
        meaning; check `is_empty` first.
        """
        if self.dim != 2:
            raise ValueError(f"outer_polygon_2d: needs a 2-D set, got dim {self.dim}")
        k = check_count("k", k)
        if k < 3:
            raise ValueError(f"k: at least 3 directions bound a polygon, got {k}")
        t = torch.arange(k, dtype=self.dtype, device=self.device) * (2 * math.pi / k)
        D = torch.stack([t.cos(), t.sin()], -1)  # [k, 2]
        h = self.support(D.reshape(k, *([1] * len(self.batch_shape)), 2), iters)  # [k, ...]
        h = h.movedim(0, -1)  # [..., k]
        D2, h2 = D.roll(-1, 0), h.roll(-1, -1)
        det = D[:, 0] * D2[:, 1] - D[:, 1] * D2[:, 0]  # sin(2 pi / k) > 0
        vx = (h * D2[:, 1] - h2 * D[:, 1]) / det  # Cramer's rule for the two support lines
        vy = (D[:, 0] * h2 - D2[:, 0] * h) / det
        return torch.stack([vx, vy], -1)

    def outer_polygon_area(self, k: int = 64, iters: int = LP_ITERS) -> Tensor:
        """Area ``[...]`` of `outer_polygon_2d` (shoelace formula): an upper bound of a
        2-D set's area, within a few per cent of it at ``k = 64`` (the CZSMF areas in
        docs/constrained_zonotopes.md). ``volume()`` stays the interval-hull proxy."""
        V = self.outer_polygon_2d(k, iters)
        x, y = V[..., 0], V[..., 1]
        return 0.5 * (x * y.roll(-1, -1) - x.roll(-1, -1) * y).sum(-1).abs()

    def interval_hull(self, iters: int = LP_ITERS) -> Interval:
        """Certified outer box from ``2 n`` support LPs (batched) -> Interval ``[..., n]``.

        For an empty set the bounds may cross (``lower > upper``), which certifies emptiness.
        Differentiable w.r.t. every field (envelope gradients).
        """
        from diffsmf.sets.interval import Interval

        n = self.dim
        eye = torch.eye(n, dtype=self.dtype, device=self.device)
        D = torch.cat([eye, -eye]).reshape(2 * n, *([1] * len(self.batch_shape)), n)
        h = support_value(D, self._c, self.generators, self.A, self.b, iters)  # [2n, ...]
        h = h.movedim(0, -1)
        return Interval._make(-h[..., n:], h[..., :n])

    def is_empty(self, iters: int = LP_ITERS) -> Tensor:
        """Certified emptiness -> bool ``[...]``: True only when a Farkas certificate was found
        (``lam'b + ||A'lam||_1 < 0`` for some ``lam``, i.e. ``A xi = b`` has no solution in
        the box). False means "not proved empty"."""
        with torch.no_grad():
            if self.num_constraints == 0:
                return torch.zeros(self.batch_shape, dtype=torch.bool, device=self.device)
            g = self.A.new_zeros(*self.batch_shape, self.num_generators)
            bound, _, _, _ = box_lp(g, self.A, self.b, iters, None)  # all iterations
            return bound < 0

    def contains(self, x: Tensor, atol: float = 1e-9, iters: int = LP_ITERS) -> Tensor:
        """Membership of ``x [..., n]`` up to ``atol`` (broadcast against the batch) -> bool
        ``[...]``: False only where ``x`` is *certified farther than* ``atol`` from the set.

        The tolerance is part of the meaning. ``x`` belongs to the set enlarged by ``atol``
        when some ``|xi|_inf <= 1`` has ``||c + G xi - x||_inf <= atol`` and
        ``||A xi - b||_inf <= atol``, i.e. when the constrained zonotope
        ``[G, atol I; A, 0 | 0, atol I] (xi, s) = [x - c; b]``, ``|(xi, s)|_inf <= 1``, is not
        empty. ``contains`` is False only when a Farkas certificate of that LP (weak duality:
        the certified dual bound of `box_lp` is negative) proves it
        empty. So:

        - every point of the set (and every point within ``atol`` of it) gives True, whatever
          the interior-point iterate did (a feasible LP has no negative dual bound: no
          certificate of emptiness exists), which is what a containment check of a guaranteed
          filter needs: no false alarm on states on the boundary of a tight set;
        - a point farther than ``atol`` gives False once the dual iterate finds a certificate;
          checked against HiGHS for points at distance ``>= 10 atol`` (docs and tests), a
          point between ``atol`` and that may be reported either way.

        ``atol = 0`` is ``~excludes(x)``. For a certificate of membership (a point ``xi``
        found), use `diffsmf.sets.czono_lp.certify_feasible` on
        `_membership_lp`.
        """
        x = as_tensor("x", x, like=self._c, min_dim=1)
        if x.shape[-1] != self.dim:
            raise ValueError(f"x: expected [..., {self.dim}], got {tuple(x.shape)}")
        with torch.no_grad():
            L, r = self._membership_lp(x.detach())
            if atol > 0:  # the slack generators atol I of every residual row
                K = L.shape[-2]
                eye = torch.eye(K, dtype=L.dtype, device=L.device) * atol
                L = torch.cat([L, eye.expand(*L.shape[:-2], K, K)], -1)
            bound, _, _, _ = box_lp(torch.zeros_like(L[..., 0, :]), L, r, iters, None)
            return ~(bound < 0)

    def excludes(self, x: Tensor, iters: int = LP_ITERS) -> Tensor:
        """Certified non-membership of ``x [..., n]`` -> bool ``[...]`` (a Farkas certificate
        of the membership LP; False means "not proved outside")."""
        x = as_tensor("x", x, like=self._c, min_dim=1)
        with torch.no_grad():
            L, r = self._membership_lp(x.detach())
            bound, _, _, _ = box_lp(torch.zeros_like(L[..., 0, :]), L, r, iters, None)
            return bound < 0

    def _membership_lp(self, x: Tensor) -> tuple[Tensor, Tensor]:
        batch = torch.broadcast_shapes(self.batch_shape, x.shape[:-1])
        n, m, k = self.dim, self.num_generators, self.num_constraints
        G = self.generators.detach().expand(*batch, n, m)
        A = self.A.detach().expand(*batch, k, m)
        L = torch.cat([G, A], -2)
        r = torch.cat(
            [(x - self._c.detach()).expand(*batch, n), self.b.detach().expand(*batch, k)], -1
        )
        return L, r

    def volume(self) -> Tensor:
        """Volume proxy: the volume of the interval hull (an upper bound of the true volume;
        0 for a certified-empty set) -> ``[...]``. Differentiable."""
        box = self.interval_hull()
        return (box.upper - box.lower).clamp_min(0).prod(-1)

    # ------------------------------------------------------------------ exact operations
    def linear_map(self, M: Tensor, d: Tensor | None = None) -> ConstrainedZonotope:
        """``{M x + d}`` (Scott 2016 eq. 11): center ``M c + d``, generators ``M G``, same
        constraints. ``M [..., p, n]``, ``d [..., p]``."""
        M = as_tensor("A", M, like=self._c, min_dim=2)
        if M.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., p, {self.dim}], got {tuple(M.shape)}")
        c = (M @ self._c.unsqueeze(-1)).squeeze(-1)
        if d is not None:
            c = c + as_offset(d, self._c, M.shape[-2])
        return ConstrainedZonotope._make(c, M @ self.generators, self.A, self.b)

    def translate(self, d: Tensor) -> ConstrainedZonotope:
        """``{x + d}``, ``d [..., n]``."""
        return ConstrainedZonotope._make(
            self._c + as_offset(d, self._c, self.dim), self.generators, self.A, self.b
        )

    def minkowski_sum(self, other: ConvexSet | Tensor) -> ConstrainedZonotope:
        """Exact Minkowski sum (Scott 2016 eq. 12): ``[G1, G2]``, ``blkdiag(A1, A2)``,
        ``[b1; b2]``. ``other``: a ConstrainedZonotope, Zonotope, Parallelotope, Interval or a
        point tensor (an Ellipsoid is first covered, `from_set`)."""
        if isinstance(other, Tensor):
            return self.translate(other)
        o = ConstrainedZonotope.from_set(other)
        if o.dim != self.dim:
            raise ValueError(f"other: dimension {o.dim} != {self.dim}")
        batch = torch.broadcast_shapes(self.batch_shape, o.batch_shape)
        n, m1, m2, k1, k2 = (
            self.dim,
            self.num_generators,
            o.num_generators,
            self.num_constraints,
            o.num_constraints,
        )
        G = torch.cat(
            [self.generators.expand(*batch, n, m1), o.generators.expand(*batch, n, m2)], -1
        )
        A1 = torch.cat([self.A.expand(*batch, k1, m1), self.A.new_zeros(*batch, k1, m2)], -1)
        A2 = torch.cat([o.A.new_zeros(*batch, k2, m1), o.A.expand(*batch, k2, m2)], -1)
        b = torch.cat([self.b.expand(*batch, k1), o.b.expand(*batch, k2)], -1)
        return ConstrainedZonotope._make(self._c + o.center, G, torch.cat([A1, A2], -2), b)

    def intersect(self, other: ConvexSet, R: Tensor | None = None) -> ConstrainedZonotope:
        """Generalised intersection ``Z cap_R Y = {z in Z : R z in Y}`` (Scott 2016 eq. 13):
        ``{c_Z, [G_Z, 0], [[A_Z, 0], [0, A_Y], [R G_Z, -G_Y]], [b_Z; b_Y; c_Y - R c_Z]}``.
        ``R [..., p, n]`` (default identity); ``other`` is converted by `from_set`."""
        Y = ConstrainedZonotope.from_set(other)
        c, G = self._c, self.generators
        if R is None:
            if Y.dim != self.dim:
                raise ValueError(f"other: dimension {Y.dim} != {self.dim}")
            RG, Rc = G, c
        else:
            R = as_tensor("R", R, like=c, min_dim=2)
            if R.shape[-1] != self.dim or R.shape[-2] != Y.dim:
                raise ValueError(f"R: expected [..., {Y.dim}, {self.dim}], got {tuple(R.shape)}")
            RG, Rc = R @ G, (R @ c.unsqueeze(-1)).squeeze(-1)
        batch = torch.broadcast_shapes(self.batch_shape, Y.batch_shape, RG.shape[:-2])
        p = Y.dim
        m1, m2, k1, k2 = (
            self.num_generators,
            Y.num_generators,
            self.num_constraints,
            Y.num_constraints,
        )
        z = G.new_zeros
        Gn = torch.cat([G.expand(*batch, self.dim, m1), z(*batch, self.dim, m2)], -1)
        rows = [
            torch.cat([self.A.expand(*batch, k1, m1), z(*batch, k1, m2)], -1),
            torch.cat([z(*batch, k2, m1), Y.A.expand(*batch, k2, m2)], -1),
            torch.cat([RG.expand(*batch, p, m1), -Y.generators.expand(*batch, p, m2)], -1),
        ]
        bn = torch.cat(
            [self.b.expand(*batch, k1), Y.b.expand(*batch, k2), (Y.center - Rc).expand(*batch, p)],
            -1,
        )
        return ConstrainedZonotope._make(c.expand(*batch, self.dim), Gn, torch.cat(rows, -2), bn)

    def intersect_strip(self, strip: Strip) -> ConstrainedZonotope:
        """Exact ``Z cap {x : |a.x - y| <= sigma}`` (Scott 2016 eq. 13 with ``R = a'`` and the
        1-D zonotope ``Y = y + sigma [-1, 1]``): one new generator (zero in x) and one new
        constraint ``a'G xi - sigma xi_new = y - a'c``. Batched over the batch dims of Z and
        the strip."""
        a, y, sig = strip_fields(strip, self)
        return self._intersect_strips(a.unsqueeze(-2), y.unsqueeze(-1), sig.unsqueeze(-1))

    def intersect_strips(
        self, normal: Tensor, offset: Tensor, halfwidth: Tensor
    ) -> ConstrainedZonotope:
        """Exact intersection with ``q`` strips at once: ``normal [..., q, n]``, ``offset`` and
        ``halfwidth [..., q]`` (``q`` generators and ``q`` constraints are added, Scott 2016
        eq. 13 with ``R = normal``)."""
        a = as_tensor("normal", normal, like=self._c, min_dim=2)
        y = as_tensor("offset", offset, like=self._c, min_dim=1)
        s = as_tensor("halfwidth", halfwidth, like=self._c, min_dim=1)
        if a.shape[-1] != self.dim:
            raise ValueError(f"normal: expected [..., q, {self.dim}], got {tuple(a.shape)}")
        if (s.detach() < 0).any():
            raise ValueError("halfwidth: must be >= 0")
        return self._intersect_strips(a, y, s)

    def _intersect_strips(self, a: Tensor, y: Tensor, sig: Tensor) -> ConstrainedZonotope:
        q = a.shape[-2]
        c, G = self._c, self.generators
        aG = a @ G  # [..., q, m]
        ac = (a @ c.unsqueeze(-1)).squeeze(-1)  # [..., q]
        batch = torch.broadcast_shapes(
            self.batch_shape, aG.shape[:-2], y.shape[:-1], sig.shape[:-1]
        )
        n, m, k = self.dim, self.num_generators, self.num_constraints
        Gn = torch.cat([G.expand(*batch, n, m), G.new_zeros(*batch, n, q)], -1)
        top = torch.cat([self.A.expand(*batch, k, m), G.new_zeros(*batch, k, q)], -1)
        bot = torch.cat([aG.expand(*batch, q, m), -torch.diag_embed(sig.expand(*batch, q))], -1)
        bn = torch.cat([self.b.expand(*batch, k), (y - ac).expand(*batch, q)], -1)
        return ConstrainedZonotope._make(c.expand(*batch, n), Gn, torch.cat([top, bot], -2), bn)

    def intersect_halfspace(self, normal: Tensor, offset: Tensor) -> ConstrainedZonotope:
        """Exact ``Z cap {x : normal.x <= offset}``; ``normal [..., n]``, ``offset [...]``.

        With ``l = normal.c - ||G'normal||_1`` (a lower bound of ``normal.x`` on Z, ignoring
        the constraints) the half-space meets Z exactly where the strip
        ``l <= normal.x <= offset`` does; that strip is intersected exactly (one generator,
        one constraint). If ``offset < l`` the result is the (empty) intersection with the
        hyperplane ``normal.x = (l + offset) / 2``, which misses Z.
        """
        a = as_tensor("normal", normal, like=self._c, min_dim=1)
        d = as_tensor("offset", offset, like=self._c)
        if a.shape[-1] != self.dim:
            raise ValueError(f"normal: expected [..., {self.dim}], got {tuple(a.shape)}")
        lo = (a * self._c).sum(-1) - (a.unsqueeze(-1) * self.generators).sum(-2).abs().sum(-1)
        lo = (
            lo
            - 4
            * (self.num_generators + self.dim)
            * _EPS
            * (
                (a * self._c).abs().sum(-1)
                + (a.unsqueeze(-1) * self.generators).abs().sum((-2, -1))
            ).detach()
        )
        half = ((d - lo) / 2).clamp_min(0)
        mid = (d + lo) / 2
        return self._intersect_strips(a.unsqueeze(-2), mid.unsqueeze(-1), half.unsqueeze(-1))

    # ------------------------------------------------------------------ sampling
    def _interior_xi(self, iters: int = LP_ITERS) -> tuple[Tensor, Tensor]:
        """A point ``xi [..., m]`` of ``{A xi = b} cap [-1, 1]^m`` near its analytic centre
        (interior-point iterate with zero objective, then projected onto ``A xi = b``) and
        ``found [...]``: False where the set is certified empty (the LP's Farkas bound, as
        `is_empty`) or the projected point left the box by more than 1e-9."""
        A, b = self.A.detach(), self.b.detach()
        g = A.new_zeros(*self.batch_shape, self.num_generators)
        bound, _, _, xi = box_lp(g, A, b, iters, None)
        if self.num_constraints:
            r = b - (A * xi.unsqueeze(-2)).sum(-1)
            xi = xi + (torch.linalg.pinv(A) @ r.unsqueeze(-1)).squeeze(-1)
        found = (bound >= 0) & (xi.abs() <= 1 + 1e-9).all(-1)
        return xi, found

    def _hit_and_run(
        self, k: int, steps: int, generator: torch.Generator | None, last_to_boundary: bool
    ) -> Tensor:
        m = self.num_generators
        with torch.no_grad():
            xi0, found = self._interior_xi()
            xi = xi0.unsqueeze(-2).expand(*self.batch_shape, k, m)
            A = self.A.detach()
            eye = torch.eye(m, dtype=self.dtype, device=self.device)
            P = (
                eye - torch.linalg.pinv(A) @ A
                if self.num_constraints
                else eye.expand(*self.batch_shape, m, m)
            )
            for s in range(steps):
                r = torch.randn(
                    (*self.batch_shape, k, m),
                    dtype=self.dtype,
                    device=self.device,
                    generator=generator,
                )
                v = r @ P.mT  # [..., k, m], in the null space of A
                big = torch.full_like(v, float("inf"))
                tp = torch.where(
                    v > 1e-300,
                    (1 - xi) / v.clamp_min(1e-300),
                    torch.where(v < -1e-300, (-1 - xi) / v.clamp_max(-1e-300), big),
                )
                tm = torch.where(
                    v > 1e-300,
                    (-1 - xi) / v.clamp_min(1e-300),
                    torch.where(v < -1e-300, (1 - xi) / v.clamp_max(-1e-300), -big),
                )
                t_hi = tp.amin(-1).clamp_min(0)
                t_lo = tm.amax(-1).clamp_max(0)
                t_hi = torch.where(torch.isfinite(t_hi), t_hi, torch.zeros_like(t_hi))
                t_lo = torch.where(torch.isfinite(t_lo), t_lo, torch.zeros_like(t_lo))
                u = torch.rand(
                    (*self.batch_shape, k),
                    dtype=self.dtype,
                    device=self.device,
                    generator=generator,
                )
                if last_to_boundary and s == steps - 1:
                    t = torch.where(u < 0.5, t_lo, t_hi)
                else:
                    t = t_lo + u * (t_hi - t_lo)
                xi = (xi + t.unsqueeze(-1) * v).clamp(-1, 1)
            xi = torch.where(found[..., None, None], xi, torch.full_like(xi, float("nan")))
        return self._c.unsqueeze(-2) + xi @ self.generators.mT

    def sample(self, k: int, generator: torch.Generator | None = None, steps: int = 20) -> Tensor:
        """``k`` points of the set by ``steps`` hit-and-run moves in the ``xi`` polytope from an
        interior point -> ``[..., k, n]`` (approximately uniform in ``xi``; inside up to the
        ~1e-12 residual of ``A xi = b``). An element whose set is empty (certified as by
        `is_empty`, or no point of ``A xi = b`` found in the box) gets NaN points, never
        points outside it. The points carry gradients w.r.t. center and generators."""
        k, steps = check_count("k", k), check_count("steps", steps)
        return self._hit_and_run(k, steps, generator, last_to_boundary=False)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` boundary points (the last hit-and-run move goes to the end of its chord)."""
        k = check_count("k", k)
        return self._hit_and_run(k, 20, generator, last_to_boundary=True)

    # ------------------------------------------------------------------ reduction
    def propagate(self, sweeps: int = PROPAGATION_SWEEPS) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Interval constraint propagation on ``xi`` (Scott 2016 Appendix A) -> ``(E_lo,
        E_hi, R_lo, R_hi)``, each ``[..., m]`` (detached).

        ``E`` contains every feasible ``xi`` (outward-rounded; ``E_lo > E_hi`` certifies
        emptiness); ``R_j`` is the range of ``xi_j`` implied by the constraints alone (each
        row solved for ``xi_j`` with the other coordinates in ``E``), used by the
        elimination heuristic.
        """
        with torch.no_grad():
            return _propagate(self.A.detach(), self.b.detach(), sweeps)

    def rescale(self, sweeps: int = PROPAGATION_SWEEPS) -> ConstrainedZonotope:
        """The same set with ``xi = mid(E) + diag(rad(E)) eta``, ``E`` from `propagate`
        (exact: ``E`` contains every feasible ``xi``): shorter generators for the reductions.
        ``E`` is chosen without gradient."""
        if self.num_constraints == 0:
            return self
        lo, hi, _, _ = self.propagate(sweeps)
        mid, rad = 0.5 * (lo + hi), (0.5 * (hi - lo)).clamp_min(0)
        c = self._c + (self.generators * mid.unsqueeze(-2)).sum(-1)
        b = self.b - (self.A * mid.unsqueeze(-2)).sum(-1)
        return ConstrainedZonotope._make(
            c, self.generators * rad.unsqueeze(-2), self.A * rad.unsqueeze(-2), b
        )

    def reduce_constraints(self, k: int, heuristic: str = "lp") -> ConstrainedZonotope:
        """Outer approximation with ``k`` constraints, eliminating one constraint and one
        generator at a time (Scott 2016 sec. 4.2, Prop. 5).

        For the pivot ``a_ij`` the constraint row i is solved for ``xi_j``:
        ``c + G_j b_i / a_ij``, ``G - G_j A_i / a_ij``, ``A - A_j A_i / a_ij``,
        ``b - A_j b_i / a_ij``, then row i and column j are deleted; only ``|xi_j| <= 1`` is
        lost, so the result contains the set. The generator j minimises the Hausdorff estimate
        of Scott 2016 Appendix A: ``r_j / sqrt(s_j)`` with ``r_j = max(0, max|R_j| - 1)``
        (`propagate`) and ``s_j = P_jj - P_j' A' (A P A')^-1 A P_j``,
        ``P = (G'G + I)^-1``, i.e. the 2-norm of ``[G d; d]`` for the least-norm ``d`` with
        ``A d = 0``, ``d_j = r_j`` (eq. A.7, 2-norm of the stacked vector instead of the sum of
        the two norms); the row i is the one of largest ``|a_ij|``. Columns without a pivot
        (``|a_ij| <= 1e-10 max|A_i|`` in every row) are never chosen. ``heuristic``: where
        ``R_j`` comes from (``"propagation"``: interval propagation, as published; ``"lp"``:
        exact LP ranges), or ``"hull"``: the `HULL_CANDIDATES` best estimates (with
        propagated ``R_j``) are each eliminated and the one whose result has the smallest
        interval hull (sum over axes of width / zonotope width, ``2 n`` LPs per candidate,
        one batched solve) wins. Choices are detached.
        """
        check_count("k", k)
        if heuristic not in ("hull", "lp", "propagation"):
            raise ValueError(f"heuristic: unknown {heuristic!r} (hull | lp | propagation)")
        return self._reduce_constraints(k, heuristic)[0]

    def _reduce_constraints(
        self, k: int, heuristic: str = "lp"
    ) -> tuple[ConstrainedZonotope, tuple[Tensor, Tensor] | None]:
        """`reduce_constraints` -> ``(Z, duals)``; with ``heuristic="hull"`` and at least
        one elimination, ``duals = (lam [2n, ..., k], xi [2n, ..., m])`` are the LP solutions
        of the ``2n`` hull directions of the result, already computed by the ranking (pass
        them to `_hull_from_duals`: no second solve); else ``None``."""
        Z, duals = self, None
        while Z.num_constraints > k:
            Z, duals = Z._eliminate_one(heuristic)
        return Z, duals

    def _eliminate_one(
        self, heuristic: str = "lp"
    ) -> tuple[ConstrainedZonotope, tuple[Tensor, Tensor] | None]:
        c, G, A, b = self._c, self.generators, self.A, self.b
        with torch.no_grad():
            i, j, duals = _elimination_choice(G.detach(), A.detach(), b.detach(), heuristic)
        return ConstrainedZonotope._make(*_eliminate(c, G, A, b, i, j)), duals

    def _hull_from_duals(self, lam: Tensor, xi: Tensor) -> Interval:
        """Certified interval hull ``[..., n]`` from given LP solutions of its ``2n`` support
        LPs (``lam [2n, ..., k]``, ``xi [2n, ..., m]``, directions ``e_1..e_n, -e_1..-e_n``):
        weak duality makes ``phi(lam)`` an upper bound whatever ``lam`` is, so no solve is
        needed; same envelope gradients as `interval_hull`."""
        from diffsmf.sets.interval import Interval

        n = self.dim
        eye = torch.eye(n, dtype=self.dtype, device=self.device)
        D = torch.cat([eye, -eye]).reshape(2 * n, *([1] * len(self.batch_shape)), n)
        h = support_value(D, self._c, self.generators, self.A, self.b, duals=(lam, xi))
        h = h.movedim(0, -1)
        return Interval._make(-h[..., n:], h[..., :n])

    def reduce_generators(
        self, q: int, method: str = "girard", box_radius: Tensor | None = None
    ) -> ConstrainedZonotope:
        """Outer approximation with at most ``q`` generators through the lifted zonotope
        (Scott 2016 sec. 5): ``Z = {x : [x; 0] in {[c; -b] + [G; A] xi}}``, and any outer
        reduction of the lifted zonotope gives an outer constrained zonotope.

        The ``q - n - k`` lifted generators ``[g_j; a_j]`` with the largest score are kept
        (``method="girard"``: ``||.||_1 - ||.||_inf``, Girard 2005; ``"combastel"``: the 2-norm,
        Combastel 2003; the constraint rows weighted by `CONSTRAINT_WEIGHT`) and the
        others replaced by the box of their sum, i.e. ``n`` axis generators in x and ``k``
        slack generators, one per constraint row.
        ``box_radius [..., n]`` (>= 0, optional) adds the box ``[-r, r]`` exactly, merged into
        the n axis generators (``Z (+) box`` with no extra columns). Needs ``q >= n + k``.
        The choice of the kept generators is made without gradient.
        """
        n, m, k = self.dim, self.num_generators, self.num_constraints
        if not is_int(q) or q < n + k:
            raise ValueError(f"q: must be an integer >= n + k = {n + k}, got {q!r}")
        if method not in ("girard", "combastel"):
            raise ValueError(f"method: unknown reduction {method!r} (girard | combastel)")
        c, G, A, b = self._c, self.generators, self.A, self.b
        batch = self.batch_shape
        extra = 0 if box_radius is None else n
        if m + extra <= q:  # nothing to reduce
            if box_radius is None:
                return self
            return self._append_box(box_radius)
        keep = q - n - k
        L = torch.cat([G, A], -2)  # lifted [..., n + k, m]
        with torch.no_grad():
            La = L.detach().abs()
            La = torch.cat([La[..., :n, :], CONSTRAINT_WEIGHT * La[..., n:, :]], -2)
            score = La.sum(-2) - La.amax(-2) if method == "girard" else La.square().sum(-2)
            order = descending_order(score)
        Ls = torch.gather(L, -1, order.unsqueeze(-2).expand(*batch, n + k, m))
        kept, dropped = Ls[..., :keep], Ls[..., keep:]
        s = dropped.abs().sum(-1)  # box of the dropped lifted generators [..., n + k]
        sx = s[..., :n]
        if box_radius is not None:
            sx = sx + box_radius
        Gn = torch.cat([kept[..., :n, :], torch.diag_embed(sx), G.new_zeros(*batch, n, k)], -1)
        An = torch.cat(
            [kept[..., n:, :], A.new_zeros(*batch, k, n), torch.diag_embed(s[..., n:])], -1
        )
        return ConstrainedZonotope._make(c, Gn, An, b)

    def _append_box(self, r: Tensor) -> ConstrainedZonotope:
        batch = torch.broadcast_shapes(self.batch_shape, r.shape[:-1])
        n, m, k = self.dim, self.num_generators, self.num_constraints
        G = torch.cat(
            [self.generators.expand(*batch, n, m), torch.diag_embed(r.expand(*batch, n))], -1
        )
        A = torch.cat([self.A.expand(*batch, k, m), self.A.new_zeros(*batch, k, n)], -1)
        return ConstrainedZonotope._make(self._c, G, A, self.b)

    def reduce(
        self,
        max_generators: int,
        max_constraints: int,
        method: str = "girard",
        rescale: bool = True,
    ) -> ConstrainedZonotope:
        """Outer approximation with at most ``max_constraints`` constraints (Scott 2016 sec.
        4.2) and then at most ``max_generators`` generators (sec. 5); ``rescale`` first
        applies the exact `rescale`."""
        Z = self.rescale() if rescale else self
        Z = Z.reduce_constraints(max_constraints)
        if Z.num_generators > max_generators:
            Z = Z.reduce_generators(max_generators, method)
        return Z


# ---------------------------------------------------------------------- helpers
def _zero_pad(t: Tensor, dim: int, count: int) -> Tensor:
    """``t`` with ``count`` zeros appended along ``dim``."""
    shape = list(t.shape)
    shape[dim] = count
    return torch.cat([t, t.new_zeros(shape)], dim)


def as_constrained_zonotope(S: ConvexSet) -> ConstrainedZonotope:
    """Same as `ConstrainedZonotope.from_set`."""
    return ConstrainedZonotope.from_set(S)
