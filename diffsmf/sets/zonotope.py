"""Zonotopes ``Z = {c + G xi : ||xi||_inf <= 1}``, batched and differentiable.

``center [..., n]``, ``generators [..., n, m]``. Operations that are exact (linear map,
Minkowski sum, support, volume, 2-D vertices, membership) are exact; the others (order
reduction, outer parallelotope, strip intersection, covering ellipsoid) are *outer* bounds
that provably contain the exact result. Discrete choices (which generators to reduce, which
basis, which lambda candidate) are made on detached values; the chosen formula is then
evaluated with gradients.

References: Kuehn 1998 / Girard 2005 / Combastel 2003 (reduction), Chisci, Garulli, Zappa 1996
(minimal-volume outer parallelotope, Wang et al. 2022, eq. 22), Alamo, Bravo, Camacho 2005
Automatica 41 "Guaranteed state estimation by zonotopes" (strip intersection).
"""

from __future__ import annotations

import functools
import itertools
import math
import warnings
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import (
    ConvexSet,
    as_offset,
    as_tensor,
    as_vector,
    check_count,
    check_finite,
    family,
)
from diffsmf.sets.czono_lp import certify_feasible
from diffsmf.sets.strip import strip_batch, strip_fields
from diffsmf.utils import (
    HIGHS_OPTIONS,
    broadcast_shapes,
    descending_order,
    eager_constant,
    materialize,
    tracing,
)

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.ellipsoid import Ellipsoid
    from diffsmf.sets.interval import Interval
    from diffsmf.sets.strip import Strip

__all__ = ["Zonotope", "MAX_VOLUME_SUBSETS", "MAX_BASES"]

#: Above this many generator n-subsets per set, ``volume()`` returns an upper bound
#: (min of the interval-hull volume and the outer-parallelotope volume) instead of the exact sum.
MAX_VOLUME_SUBSETS = 20_000
#: ``to_parallelotope()`` enumerates at most this many bases per set; beyond, it enumerates the
#: bases formed by the L longest generators (largest L with C(L, n) <= MAX_BASES).
MAX_BASES = 5_000
#: Elements processed per chunk (batch x subsets x n x m) in the subset enumerations.
_CHUNK_ELEMS = 4_000_000
#: Bases whose |det T| is within this relative distance of the least one tie; the first in
#: lexicographic order wins (a deterministic choice, independent of rounding).
BASIS_TIE_RTOL = 1e-9
_EPS = torch.finfo(torch.float64).eps


def _combinations_list(m: int, r: int) -> Tensor:
    if r > m:
        return torch.zeros(0, r, dtype=torch.long)
    if r == 0:
        return torch.zeros(1, 0, dtype=torch.long)
    flat = list(itertools.chain.from_iterable(itertools.combinations(range(m), r)))
    return torch.tensor(flat, dtype=torch.long).reshape(-1, r)


_combinations_cpu = functools.lru_cache(maxsize=64)(_combinations_list)


def _combinations(m: int, r: int, device: torch.device | None = None) -> Tensor:
    """All r-subsets of range(m) as ``[C(m, r), r]`` long tensor (lexicographic, cached;
    while ``torch.compile`` traces, built directly: a graph constant, no cache)."""
    if tracing():
        return _combinations_list(m, r).to(device)
    return _combinations_cpu(m, r).to(device)


def _chunks(k: int, per_item: int) -> tuple[range, int]:
    """Chunk starts over ``k`` items of ``per_item`` elements each, and the chunk length."""
    step = max(1, _CHUNK_ELEMS // max(1, per_item))
    return range(0, k, step), step


def _sum_abs_det(G: Tensor, idx: Tensor) -> Tensor:
    """sum over subsets S (rows of ``idx [K, n]``) of |det G[..., :, S]| -> ``[...]``."""
    n = G.shape[-2]
    batch = int(math.prod(G.shape[:-2])) or 1
    starts, step = _chunks(idx.shape[0], batch * n * n)
    total = G.new_zeros(G.shape[:-2])
    for s in starts:
        sub = G[..., idx[s : s + step]]  # [..., n, k, n]
        total = total + linalg.det(sub.movedim(-2, -3)).abs().sum(-1)
    return total


def _angle_sorted(G: Tensor) -> Tensor:
    """2-D generators ``G [..., 2, m]`` flipped to the upper half plane (``b > 0``, or ``b = 0``
    and ``a >= 0``) and sorted by angle in ``[0, pi)`` (the order detached) -> ``[..., 2, m]``."""
    flip = (G[..., 1, :] < 0) | ((G[..., 1, :] == 0) & (G[..., 0, :] < 0))
    G = torch.where(flip.unsqueeze(-2), -G, G)
    order = torch.atan2(G[..., 1, :], G[..., 0, :]).detach().argsort(-1)
    return torch.gather(G, -1, order.unsqueeze(-2).expand_as(G))


def _planar_area(G: Tensor) -> Tensor:
    """``sum_{i<j} |det [g_i, g_j]|`` for 2-D generators ``G [..., 2, m]`` -> ``[...]`` in
    ``O(m log m)``: with the generators angle-sorted in the upper half plane
    (`_angle_sorted`), every ``det [g_i, g_j]`` with ``i < j`` is ``>= 0``, so the sum is
    ``sum_j (b_j A_j - a_j B_j)`` with the prefix sums ``A_j, B_j`` of rows a, b (inclusive:
    the ``i = j`` terms cancel).

    Absolute rounding error a few ``m eps (sum_j |g_j|)^2``, the order of the pair table's
    (`_planar_pair_area`, each ``a_i b_j - b_i a_j`` has error ``eps |g_i| |g_j|``);
    clamped at 0. ``Zonotope.volume`` in 2-D: the pair table's ``m^2`` products were a
    quarter of a compiled MSZM forward at B = 10,000. Same subgradient as the sum
    of ``|det|`` (every term enters with its sign).
    """
    Gs = _angle_sorted(G)
    a, b = Gs[..., 0, :], Gs[..., 1, :]
    return (b * torch.cumsum(a, -1) - a * torch.cumsum(b, -1)).sum(-1).clamp_min(0.0)


#: Up to this many generators a traced 2-D `Zonotope.volume` sums the pair table
#: (`_planar_pair_area`, which Inductor fuses into one loop without a sort); above, the
#: ``O(m log m)`` sorted sum. Compiled with a dynamic batch, the filters' options, one thread:
#: 51 ms for MSZM's 110,000 stacked sets (m = 24), against 65-80 ms for the eager sorted sum
#: at m = 64 0.38 s against 0.47 s (random generators), with no table in memory.
PAIR_TABLE_MAX_M = 64

#: Entries of the pair table per chunk in `_planar_pair_area` (2 MB: stays in cache).
_PAIR_TABLE_ELEMS = 262_144


def _planar_pair_area(G: Tensor) -> Tensor:
    """``sum_{i<j} |det [g_i, g_j]|`` for 2-D generators ``G [..., 2, m]`` -> ``[...]``.

    The same 2 x 2 determinants as `_sum_abs_det` (``a_i b_j - b_i a_j``, rows a and b of
    G), from the ``m x m`` table of all pairs instead of a gather over the C(m, 2) subsets:
    elementwise and vectorised, no index kernel. The table is antisymmetric and its diagonal
    is zero exactly in floating point, so half its absolute sum is the sum over i < j (up to
    the summation order). Chunked over the batch (`_PAIR_TABLE_ELEMS` table entries per
    chunk); exact for every m, so no `MAX_VOLUME_SUBSETS` cap is needed in 2-D.
    """
    a, b = G[..., 0, :], G[..., 1, :]
    batch = G.shape[:-2]
    m = G.shape[-1]
    a, b = a.reshape(-1, m), b.reshape(-1, m)
    if a.shape[0] == 0:
        return G.new_zeros(batch)
    # chunks bound the eager table's memory; traced, Inductor fuses the table into the sum
    rows = a.shape[0] if tracing() else max(1, _PAIR_TABLE_ELEMS // max(1, m * m))
    parts = []
    for s in range(0, a.shape[0], rows):
        ai, bi = a[s : s + rows], b[s : s + rows]
        table = ai.unsqueeze(-1) * bi.unsqueeze(-2) - bi.unsqueeze(-1) * ai.unsqueeze(-2)
        parts.append(table.abs().sum((-1, -2)) * 0.5)
    return torch.cat(parts).reshape(batch)


def _cross_normal(A: Tensor) -> Tensor:
    """Generalised cross product of the n-1 columns of ``A [..., n, n-1]`` -> ``[..., n]``.

    ``q . v = det([A, v])`` for every v (expansion along the last column). Computed with
    elementwise ops only (no per-matrix LAPACK call): a dynamic programme over row subsets,
    ``D(S) = det A[S, :|S|]`` expanded along column ``|S| - 1``; ``n 2^n`` multiply-adds.
    """
    n = A.shape[-2]
    At = A.movedim((-2, -1), (0, 1)).contiguous()  # [n, n-1, ...]: contiguous slices
    cols = [[At[r, j] for j in range(n - 1)] for r in range(n)]
    level: dict[int, Tensor] = {1 << r: cols[r][0] for r in range(n)} if n > 1 else {}
    for j in range(1, n - 1):  # build |S| = j + 1 from |S| = j
        nxt: dict[int, Tensor] = {}
        for S, dS in level.items():
            for r in range(n):
                if S >> r & 1:
                    continue
                T = S | (1 << r)
                pos = bin(T & ((1 << r) - 1)).count("1")  # index of r within sorted T
                sign = 1.0 if (pos + j) % 2 == 0 else -1.0
                if T in nxt:
                    nxt[T] = torch.addcmul(nxt[T], cols[r][j], dS, value=sign)
                else:
                    nxt[T] = cols[r][j] * dS if sign > 0 else -(cols[r][j] * dS)
        level = nxt
    full = (1 << n) - 1
    if n == 1:
        return A.new_ones(*A.shape[:-2], 1)
    out = [level[full ^ (1 << k)] * (1.0 if (k + n - 1) % 2 == 0 else -1.0) for k in range(n)]
    return torch.stack(out, -1)


def _cofactor_normals(G: Tensor, idx: Tensor) -> Tensor:
    """Generalised cross products of the (n-1)-subsets ``idx [K, n-1]`` -> ``[..., K, n]``.

    ``q_T . v = det([G_T, v])`` for every v, so q_T is normal to span(G_T); zero if G_T is
    rank deficient.
    """
    return _cross_normal(G[..., idx].movedim(-2, -3))


class Zonotope(ConvexSet):
    """Zonotope ``{c + G xi : xi in [-1, 1]^m}``.

    Args:
        center: ``[..., n]``.
        generators: ``[..., n, m]`` (m >= 0). Batch dims of both broadcast.

    Raises:
        ValueError: naming ``center`` or ``generators`` on NaN/inf or shape mismatch.
    """

    _fields: ClassVar[tuple[str, ...]] = ("_c", "generators")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2)

    def __init__(self, center: Any, generators: Any) -> None:
        c = check_finite("center", as_tensor("center", center, min_dim=1, field=True))
        G = check_finite(
            "generators", as_tensor("generators", generators, like=c, min_dim=2, field=True))
        if G.shape[-2] != c.shape[-1]:
            raise ValueError(
                f"generators: expected shape [..., {c.shape[-1]}, m] to match center "
                f"[..., {c.shape[-1]}], got {tuple(G.shape)}"
            )
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], G.shape[:-2])
        except RuntimeError as exc:
            raise ValueError(
                f"generators: batch shape {tuple(G.shape[:-2])} does not broadcast with "
                f"center batch shape {tuple(c.shape[:-1])}"
            ) from exc
        c = c.expand(*batch, c.shape[-1])
        G = G.expand(*batch, *G.shape[-2:])
        self._set(_c=c, generators=G)

    # ------------------------------------------------------------------ structure
    @property
    def center(self) -> Tensor:
        """``[..., n]``."""
        return self._c

    @property
    def num_generators(self) -> int:
        """m."""
        return self.generators.shape[-1]

    @property
    def order(self) -> float:
        """m / n."""
        return self.num_generators / self.dim

    @classmethod
    def _make(cls, c: Tensor, G: Tensor) -> Zonotope:
        """Internal constructor without validation (broadcasts the batch dims)."""
        batch = broadcast_shapes(c.shape[:-1], G.shape[:-2])
        obj = object.__new__(cls)
        if c.shape[:-1] != batch:
            c = c.expand(*batch, c.shape[-1])
        if G.shape[:-2] != batch:
            G = G.expand(*batch, *G.shape[-2:])
        object.__setattr__(obj, "_c", c)
        object.__setattr__(obj, "generators", G)
        return obj

    def pad_generators(self, m: int) -> Zonotope:
        """Append zero generators up to ``m`` columns (same set)."""
        k = self.num_generators
        if m < k:
            raise ValueError(f"m: cannot pad {k} generators down to {m}")
        if m == k:
            return self
        zeros = self.generators.new_zeros(*self.generators.shape[:-1], m - k)
        return Zonotope._make(self._c, torch.cat([self.generators, zeros], -1))

    # ------------------------------------------------------------------ set API
    def support(self, d: Tensor) -> Tensor:
        """h(d) = d.c + sum_j |d.g_j|; ``d [..., n]`` -> ``[...]``."""
        d = as_vector("d", d, self._c, self.dim)
        dG = (d.unsqueeze(-1) * self.generators).sum(-2)  # [..., m]
        return (d * self._c).sum(-1) + dG.abs().sum(-1)

    def interval_hull(self) -> Interval:
        """Box ``c +- sum_j |g_j|`` (exact)."""
        from diffsmf.sets.interval import Interval

        r = self.generators.abs().sum(-1)
        return Interval(self._c - r, self._c + r)

    def to_interval(self) -> Interval:
        """Same as `interval_hull`."""
        return self.interval_hull()

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> Zonotope:
        """``{A x + b}``: center ``A c + b``, generators ``A G`` (exact). ``A [..., k, n]``."""
        A = as_tensor("A", A, like=self._c, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        c = (A @ self._c.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            c = c + as_offset(b, self._c, A.shape[-2])
        return Zonotope._make(c, A @ self.generators)

    def translate(self, b: Tensor) -> Zonotope:
        """``{x + b}``, ``b [..., n]``."""
        return Zonotope._make(self._c + as_offset(b, self._c, self.dim), self.generators)

    def minkowski_sum(self, other: ConvexSet | Tensor) -> Zonotope:
        """Exact Minkowski sum with a Zonotope, Interval (box), Parallelotope or a point.

        Generators are concatenated (``[..., n, m1 + m2]``); batch dims broadcast.
        """
        oc, oG = _as_zonotope_fields(other, self)
        if oc.shape[-1] != self.dim:
            raise ValueError(f"other: dimension {oc.shape[-1]} != {self.dim}")
        batch = torch.broadcast_shapes(self.batch_shape, oc.shape[:-1])
        G1 = self.generators.expand(*batch, *self.generators.shape[-2:])
        G2 = oG.expand(*batch, *oG.shape[-2:])
        return Zonotope._make(self._c + oc, torch.cat([G1, G2], -1))

    def to_zonotope(self) -> Zonotope:
        return self

    def volume(self) -> Tensor:
        """Exact volume ``2^n sum_{|S|=n} |det G_S|`` (Gover & Krikorian) -> ``[...]``.

        Batched over the C(m, n) subsets (in 2-D from the angle-sorted generators,
        `_planar_area`, ``O(m log m)``, exact for every m; while traced for
        ``torch.compile`` and up to `PAIR_TABLE_MAX_M` generators from the fused pair
        table, `_planar_pair_area`, the same sum to rounding). If C(m, n) >
        ``MAX_VOLUME_SUBSETS`` (n >= 3) the result is an *upper bound*: min(volume of the
        interval hull, volume of ``to_parallelotope()``).
        Differentiable (|det| has a subgradient at singular subsets).
        """
        n, m = self.dim, self.num_generators
        if m < n:
            return self._c.new_zeros(self.batch_shape) + 0.0 * self.generators.sum((-1, -2))
        if n == 2:
            if tracing() and m <= PAIR_TABLE_MAX_M:  # fused and sort-free under torch.compile
                return 4.0 * _planar_pair_area(self.generators)
            return 4.0 * _planar_area(self.generators)
        if math.comb(m, n) > MAX_VOLUME_SUBSETS:
            box = (2 * self.generators.abs().sum(-1)).prod(-1)
            return torch.minimum(box, self.to_parallelotope().volume())
        idx = _combinations(m, n, self._c.device)
        return (2.0**n) * _sum_abs_det(self.generators, idx)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` points ``c + G xi``, xi uniform in the cube -> ``[..., k, n]`` (inside)."""
        k = check_count("k", k)
        xi = _uniform((*self.batch_shape, k, self.num_generators), self._c, generator)
        return self._c.unsqueeze(-2) + xi @ self.generators.transpose(-1, -2)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` points ``c + G s`` with random sign vectors s (vertex candidates)."""
        k = check_count("k", k)
        u = _uniform((*self.batch_shape, k, self.num_generators), self._c, generator)
        s = torch.where(u >= 0, 1.0, -1.0).to(self._c.dtype)
        return self._c.unsqueeze(-2) + s @ self.generators.transpose(-1, -2)

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """Exact membership of ``x [..., n]`` (broadcast against the batch) -> bool ``[...]``.

        Batched half-space test over all facet normals: the generalised cross products of
        the (n-1)-subsets of generators (in 2-D: the generators rotated by 90 degrees), plus
        the axes and the generators themselves (for degenerate zonotopes). This is exact when
        the zonotope is full-dimensional or n <= 2 (every facet of a full-dimensional
        zonotope is spanned by n-1 generators). For rank-deficient zonotopes in n >= 3 D or
        more than ``MAX_VOLUME_SUBSETS`` facet candidates it falls back to the feasibility LP
        ``x - c = G xi``, ``|xi|_inf <= 1`` for the points no half-space found excludes:
        batched in torch first (`box_lp` and
        `feasible_residual`, as in
        `ConstrainedZonotope.contains`), then scipy HiGHS per point for what torch left
        uncertified; either way True needs a box point whose residual ``|G xi - (x - c)|_inf``
        is at most ``atol`` (not differentiable). Tolerance: ``atol`` in distance units; with
        the LP, a point within about 1e-8 of the boundary may be refused.
        """
        x = as_tensor("x", x, like=self._c, min_dim=1)
        if x.shape[-1] != self.dim:
            raise ValueError(f"x: expected [..., {self.dim}], got {tuple(x.shape)}")
        with torch.no_grad():
            return _zonotope_contains(self._c.detach(), self.generators.detach(), x.detach(), atol)

    # ------------------------------------------------------------------ conversions
    def to_parallelotope(self) -> ConvexSet:
        """Minimal-volume outer parallelotope over generator bases (Chisci et al. 1996).

        Wang et al. 2022, eq. 22: for a basis B of n generators, ``T = B diag(sum_j |(B^-1 G)_ij|)``
        contains Z; pick the basis of least ``|det T|``. Batched over the C(m, n) bases
        (chunked; in 2-D all of them at once from the table of the pair determinants,
        `_outer_parallelogram`); singular bases (|det B| <= 1e-12 x Hadamard bound) are
        skipped. At most
        ``MAX_BASES`` bases per set: beyond, only bases of the L longest generators are
        tried (L largest with C(L, n) <= MAX_BASES) -- still an outer bound, maybe not the
        smallest. A rank-deficient Z (no regular basis) gets 1e-9-scaled axis generators
        appended first. The basis choice is made without gradient; T is differentiable.
        An outward margin covers the rounding of the solve (in 2-D, of the determinants).
        """
        T = _outer_parallelotope(self.generators)
        return family("Parallelotope")._from_tensors((self._c, T))  # T has the batch of c

    def to_ellipsoid(self) -> Ellipsoid:
        """Covering ellipsoid of the outer parallelotope ``c + T[-1,1]^n``
        (`Parallelotope.to_ellipsoid`: ``n T T'`` plus a 1e-10 relative ridge)."""
        return self.to_parallelotope().to_ellipsoid()

    def vertices_2d(self) -> Tensor:
        """Vertices of a 2-D zonotope in counter-clockwise order -> ``[..., 2m, 2]``.

        Generators are flipped to the upper half plane and sorted by angle (detached); the
        vertices are ``c - sum g + 2 * cumsum`` (lower chain) then the mirrored upper chain.
        Duplicate vertices appear for zero or parallel generators.
        """
        if self.dim != 2:
            raise ValueError(f"vertices_2d: needs a 2-D zonotope, got dim {self.dim}")
        Gs = _angle_sorted(self.generators)  # [..., 2, m]
        start = self._c - Gs.sum(-1)  # lowest-angle start (rightmost-bottom)
        steps = 2 * Gs.transpose(-1, -2)  # [..., m, 2]
        lower = start.unsqueeze(-2) + torch.cumsum(steps, -2)  # [..., m, 2]
        first = torch.cat([start.unsqueeze(-2), lower[..., :-1, :]], -2)
        upper = 2 * self._c.unsqueeze(-2) - first  # point reflection through c
        return torch.cat([first, upper], -2)

    # ------------------------------------------------------------------ reduction
    def reduce(self, order: float, method: str = "girard") -> Zonotope:
        """Outer order reduction to at most ``floor(order * n)`` generators.

        Methods (the generators to remove are chosen on detached scores, computed for the
        generators normalised by the interval hull's half-widths, ``diag(r)^-1 G``: the same
        choice whatever the units of the states; equal scores keep the generators' order,
        `diffsmf.utils.descending_order`):
          * ``"girard"`` (Girard 2005): keep the ``N - n`` generators with largest
            ``||g||_1 - ||g||_inf``, box the rest (``diag(sum |g|)``).
          * ``"combastel"`` (Combastel 2003): same with score ``||g||_2``.
          * ``"pca"``: same selection as Girard, the rest are boxed in the frame of their
            principal axes (left singular vectors U: ``U diag(sum |U' g|)``).
          * ``"chisci"`` (Chisci et al. 1996): the rest are replaced by their minimal-volume
            outer parallelotope (`to_parallelotope` of the removed part).
        A zonotope already within the target order is returned unchanged.
        """
        n, m = self.dim, self.num_generators
        if not (isinstance(order, (int, float)) and order >= 1):
            raise ValueError(f"order: must be a number >= 1, got {order!r}")
        if method not in ("girard", "combastel", "pca", "chisci"):
            raise ValueError(f"method: unknown reduction method {method!r}")
        target = int(math.floor(order * n + 1e-9))
        if m <= target:
            return self
        G = self.generators
        with torch.no_grad():
            # scores of the generators in the coordinates normalised by the interval hull's
            # half-widths, so that the choice does not depend on the units of the states
            A = G.abs()
            As = A * _hull_weights(G, A).unsqueeze(-1)  # |diag(1 / r) G|
            if method == "combastel":
                score = As.norm(dim=-2)
            else:
                score = As.sum(-2) - As.amax(-2)
            perm = descending_order(score)  # a stable order (ties by index)
        keep_k = target - n
        Gp = torch.gather(G, -1, perm.unsqueeze(-2).expand_as(G))
        kept, rest = Gp[..., :keep_k], Gp[..., keep_k:]
        # outward margin (4 (m + n) eps, relative) for the rounding of the sums / products
        marg = 1 + 4 * (m + n) * _EPS
        if method in ("girard", "combastel"):
            box = torch.diag_embed(rest.abs().sum(-1) * marg)
        elif method == "pca":  # principal axes of the normalised rest, mapped back
            w = _hull_weights(G).unsqueeze(-1)  # [..., n, 1]
            Uo = torch.linalg.svd((rest * w).detach(), full_matrices=False)[0]  # [..., n, n]
            U = Uo / w  # the frame in the original coordinates, diag(r) Uo
            Ui = Uo.transpose(-1, -2) * w.transpose(-1, -2)  # its inverse, Uo' diag(1 / r)
            box = U * ((Ui @ rest).abs().sum(-1) * marg).unsqueeze(-2)
        else:
            box = _outer_parallelotope(rest)
        return Zonotope._make(self._c, torch.cat([kept, box], -1))

    # ------------------------------------------------------------------ strips
    def intersect_strip(self, strip: Strip, method: str = "fradius") -> Zonotope:
        """Outer bound of ``Z cap S`` by the Alamo-Bravo-Camacho (2005) family.

        For ``S = {x : |p.x - y| <= sigma}`` and any ``lambda in R^n``,
        ``Z(lambda) = (c + lambda (y - p.c), [(I - lambda p') G, sigma lambda])`` contains
        ``Z cap S``. Returns ``m + 1`` generators.

        * ``"fradius"``: ``lambda = G G' p / (p' G G' p + sigma^2)`` (closed-form minimiser of
          the Frobenius norm of the generator matrix).
        * ``"volume"``: ``vol Z(lambda) = 2^n (|1 - p.lambda| V0 + sigma sum_T |q_T.lambda|)``
          (V0 = sum |det G_S|, q_T the cross products of the (n-1)-subsets), a convex
          piecewise-linear function; its minimum is at lambda = 0 or at a vertex on
          ``p.lambda = 1`` (an LP). We evaluate it exactly at the candidates {0, F-radius
          lambda, g_j / (p.g_j), an IRLS solution of the LP (15 steps), the vertices
          through the n + 2 nearly active subsets} and keep the least. Exact in 2-D (the
          vertices are the g_j / (p.g_j)); within 0.7% of the LP optimum in 3-6 D in our
          tests. Vertices are differentiable functions of (G, p); if the (detached) IRLS
          iterate wins, lambda acts as a constant for autograd. Falls back to the F-radius
          lambda when C(m, n) or C(m, n-1) > ``MAX_VOLUME_SUBSETS``.

        If the strip contains Z, lambda = 0 (Z itself, padded). If ``Z cap S`` is empty
        (`intersects_strip`) the input padded with a zero generator is returned.
        """
        if method not in ("fradius", "volume"):
            raise ValueError(f"method: unknown strip method {method!r}")
        p, y, sig = strip_fields(strip, self)
        c, G = self._c, self.generators
        batch = strip_batch(self.batch_shape, p, y, sig)
        c, G = _expand_to(c, (*batch, self.dim)), _expand_to(G, (*batch, *G.shape[-2:]))
        p, y, sig = _expand_to(p, (*batch, self.dim)), _expand_to(y, batch), _expand_to(sig, batch)
        Gp = (p.unsqueeze(-1) * G).sum(-2)  # p'G [..., m]
        r = y - (p * c).sum(-1)  # y - p'c
        lam = _alamo_lambda(c, G, p, y, sig, method, Gp)
        with torch.no_grad():
            dist, rad = r.abs(), Gp.abs().sum(-1)
            inside = dist + rad <= sig
            empty = dist > rad + sig
            zero = (inside | empty).unsqueeze(-1)
        lam = lam.masked_fill(zero, 0.0)  # (torch.where with a scalar is two calls)
        # Alamo 2005 Property: c(lam) = c + lam (y - p'c), G(lam) = [(I - lam p')G, sigma lam]
        cn = c + lam * r.unsqueeze(-1)
        Gn = torch.cat(
            [G - lam.unsqueeze(-1) * Gp.unsqueeze(-2), (sig.unsqueeze(-1) * lam).unsqueeze(-1)], -1
        )
        return Zonotope._make(cn, Gn)

    def intersects_strip(self, strip: Any, atol: float = 0.0) -> Tensor:
        """Exact test that Z meets ``strip``: bool ``[...]`` (`ConvexSet.intersects_strip`:
        ``|normal.c - offset| <= sum_j |normal.g_j| + halfwidth + atol``, the same values)."""
        a = strip.normal
        mid = (a * self._c).sum(-1)
        rad = (mid + (a.unsqueeze(-1) * self.generators).sum(-2).abs().sum(-1)) - mid
        return (mid - strip.offset).abs() <= rad + strip.halfwidth + atol


# ---------------------------------------------------------------------- helpers
def _hull_weights(G: Tensor, A: Tensor | None = None) -> Tensor:
    """``1 / r [..., n]`` for the interval hull half-widths ``r = sum_j |G_ij|`` (``A``:
    ``|G|`` if already at hand), detached: the row weights that make generator scores
    unit-free. A zero row (``r = 0``, where every score term is 0 anyway) gets a finite
    weight, ``1 / tiny``."""
    with torch.no_grad():
        r = (G.abs() if A is None else A).sum(-1)
        return r.clamp_min(torch.finfo(r.dtype).tiny).reciprocal()


def _uniform(shape: tuple[int, ...], like: Tensor, generator: torch.Generator | None) -> Tensor:
    u = torch.rand(shape, dtype=like.dtype, device=like.device, generator=generator)
    return 2 * u - 1


def _as_zonotope_fields(other: Any, ref: Zonotope) -> tuple[Tensor, Tensor]:
    """(center, generators) of a Zonotope / Parallelotope / Interval / point tensor."""
    if isinstance(other, Zonotope):
        return other.center, other.generators
    if isinstance(other, Tensor):
        c = as_tensor("other", other, like=ref.center, min_dim=1)
        return c, c.new_zeros(*c.shape, 0)
    from diffsmf.sets.interval import Interval

    if isinstance(other, family("Parallelotope")):
        return other.center, other.T
    if isinstance(other, Interval):
        lo, up = other.lower, other.upper
        return (lo + up) / 2, torch.diag_embed((up - lo) / 2)
    if hasattr(other, "to_zonotope"):
        z = other.to_zonotope()
        return z.center, z.generators
    raise ValueError(f"other: cannot add a {type(other).__name__} to a Zonotope exactly")


def _outer_parallelotope(G: Tensor) -> Tensor:
    """Chisci 1996 minimal-volume outer parallelotope ``T [..., n, n]`` of ``{G xi}``.

    Elements without a regular basis (rank-deficient G) get axis generators of size
    1e-9 x max|G| appended (outward) and the basis of `_fallback_basis` (the longest
    generator and n - 1 of the axis generators); Chisci's ``T = B diag(sum_j |(B^-1 G)_ij|)``
    contains Z for *any* regular basis B, so this is an outer bound, not the smallest one. The
    other elements get zero columns (no change) and their best basis. One search over G's own
    bases, also while traced (where both branches are computed): a second search over the
    augmented columns cost 15 instead of 6 bases per set at n = 2.
    """
    n, m = G.shape[-2], G.shape[-1]
    if n == 2 and 2 <= m and math.comb(m, 2) <= _max_bases(2):
        return _outer_parallelogram(G)
    eye = torch.eye(n, dtype=G.dtype, device=G.device)
    with torch.no_grad():
        Gd = G.detach()
        if m == 0:
            scale = Gd.new_full((*G.shape[:-2], 1, 1), 1e-150)
        else:
            scale = Gd.abs().amax((-1, -2), keepdim=True).clamp_min(1e-150)
        Gn = materialize(Gd / scale)
        best, ok = _best_basis(Gn)
    if not tracing() and bool(ok.all()):
        return _basis_T(G, best)
    aug = torch.where(ok.reshape(*ok.shape, 1, 1), 0.0 * eye, (1e-9 * scale) * eye)
    Gaug = torch.cat([G, aug.expand(*G.shape[:-2], n, n)], -1)
    with torch.no_grad():
        basis = torch.where(ok.unsqueeze(-1), best, _fallback_basis(Gn))
    return _basis_T(Gaug, basis)


#: Pair-table entries (batch x m x m) per eager chunk of `_outer_parallelogram`.
_PAIR_CHUNK_ELEMS = 2_000_000


def _outer_parallelogram(G: Tensor) -> Tensor:
    """`_outer_parallelotope` in 2-D from the table of all pair determinants -> ``[..., 2, 2]``.

    The same basis and the same ``T`` as the search over the C(m, 2) bases (Chisci 1996), in
    closed form (Cramer's rule): with ``D_kl = det [g_k, g_l]`` and ``S_k = sum_l |D_kl|``, the
    basis ``(i, j)`` has ``B^-1 g_l = (D_lj, D_il) / D_ij``, so ``s = (S_j, S_i) / |D_ij|`` and
    ``|det T| = S_i S_j / |D_ij|``: one ``m x m`` table instead of a solve per basis. The
    choice (least ``|det T|``, ties within `BASIS_TIE_RTOL` to the first pair in lexicographic
    order, regular pairs ``|D_ij| > 1e-12 |g_i|_1 |g_j|_1`` only) is made on the detached table;
    the first near-least entry of the symmetric table in row-major order is that pair. ``s`` is
    padded by the rounding of the table (``|fl(D_kl) - D_kl| <= 2 eps P_kl``, ``P_kl = |a_k
    b_l| + |b_k a_l|``, counted twice) and a relative ``(m + 8) eps``. Elements without a
    regular pair take `_outer_parallelotope`'s fallback. Eager batches are chunked
    (`_PAIR_CHUNK_ELEMS` table entries per chunk).
    """
    m = G.shape[-1]
    batch = G.shape[:-2]
    nb = int(math.prod(batch))
    rows = max(1, _PAIR_CHUNK_ELEMS // (m * m))
    if tracing() or nb <= rows:
        T, ok, all_ok = _pair_T(G)
    else:
        Gf = G.reshape(nb, 2, m)
        parts = [_pair_T(Gf[s : s + rows]) for s in range(0, nb, rows)]
        T = torch.cat([t for t, _, _ in parts]).reshape(*batch, 2, 2)
        ok = torch.cat([k.reshape(-1) for _, k, _ in parts]).reshape(batch)
        all_ok = all(a for _, _, a in parts)
    if all_ok:
        return T
    # no regular pair (all generators parallel or zero): Chisci's T on [G, 1e-9 max|G| I]
    # with the basis of `_fallback_basis` (an outer bound, not the least one)
    with torch.no_grad():
        scale = G.detach().abs().amax((-1, -2), keepdim=True).clamp_min(1e-150)
        basis = _fallback_basis(G.detach() / scale)
    eye = torch.eye(2, dtype=G.dtype, device=G.device)
    Gaug = torch.cat([G, ((1e-9 * scale) * eye).expand(*batch, 2, 2)], -1)
    return torch.where(ok.reshape(*ok.shape, 1, 1), T, _basis_T(Gaug, basis))


def _pair_T(G: Tensor) -> tuple[Tensor, Tensor, bool]:
    """`_outer_parallelogram` on one chunk: ``(T [..., 2, 2], ok [...], all_ok)``: ``ok``
    False where no pair is regular (``T`` is then finite but not a bound), ``all_ok`` whether
    every element is ok (eager; False while traced; when True, ``ok`` is not read and keeps a
    trailing dim of 1)."""
    m = G.shape[-1]
    with torch.no_grad():
        scale = G.abs().amax((-1, -2), keepdim=True).clamp_min(1e-150)
    Gn = G / scale  # the choice and s are invariant to the scale; no over- or underflow
    a, b = Gn.unbind(-2)  # the rows of Gn
    p = a.unsqueeze(-1) * b.unsqueeze(-2)  # p_kl = a_k b_l; b_k a_l is p_lk (the same bits)
    Dabs = (p - p.mT).abs()  # |det [g_k, g_l]|: symmetric, 0 diagonal
    S = Dabs.sum(-1)
    with torch.no_grad():
        nrm = a.abs() + b.abs()  # 1-norms: a norm over dim -2, or hypot, is slow
        regular = Dabs > 1e-12 * (nrm.unsqueeze(-1) * nrm.unsqueeze(-2))
        val = torch.where(regular, S.unsqueeze(-1) * S.unsqueeze(-2) / Dabs, math.inf)
        flat = val.flatten(-2)
        v = flat.amin(-1, keepdim=True)
        k = (flat <= v * (1 + BASIS_TIE_RTOL)).max(-1, keepdim=True).indices  # the first
        ij = torch.cat([k // m, k % m], -1)  # [..., 2], i < j
        fin = v < math.inf  # False for inf and NaN
        all_ok = not tracing() and bool(fin.all())
    # rounding of the table: |fl(D_kl) - D_kl| <= 2 eps P_kl (operands of Gn exact to eps/2)
    pa = p.abs()
    P = pa + pa.mT  # |a_k b_l| + |b_k a_l|
    num = torch.add(S, P.sum(-1), alpha=4 * _EPS).gather(-1, ij.flip(-1))  # (S_j, S_i) + pad
    den = torch.sub(Dabs, P, alpha=4 * _EPS).flatten(-2).gather(-1, k)  # |D_ij| - pad, > 0
    if not all_ok:  # no regular pair: a finite placeholder (no NaN in the gradients)
        den = torch.where(fin, den, 1.0)
    s = num / den * (1 + (m + 8) * _EPS)
    B = torch.gather(G, -1, ij.unsqueeze(-2).expand(*G.shape[:-1], 2))
    return B * s.unsqueeze(-2), fin.squeeze(-1) if not all_ok else fin, all_ok


def _fallback_basis(G: Tensor) -> Tensor:
    """A regular basis ``[..., n]`` of ``[G, I]`` (indices ``m + j`` are the axis columns) for
    any ``G [..., n, m]``: the longest column g of G and the axes ``e_j`` with ``j`` other than
    ``argmax_j |g_j|`` (``det = +-g_j* != 0``), or all n axes where G is zero."""
    n, m = G.shape[-2], G.shape[-1]
    axes = torch.arange(m, m + n, device=G.device).expand(*G.shape[:-2], n)
    if m == 0:
        return axes
    norms = G.abs().sum(-2)  # [..., m]
    k = norms.argmax(-1, keepdim=True)  # [..., 1]
    g = torch.gather(G, -1, k.unsqueeze(-2).expand(*G.shape[:-2], n, 1)).squeeze(-1)
    top = g.abs().argmax(-1, keepdim=True)  # [..., 1]: axis replaced by g
    with_g = torch.where(axes == m + top, k.expand_as(axes), axes)
    return torch.where((norms.amax(-1, keepdim=True) > 0), with_g, axes)


def _basis_T(G: Tensor, basis: Tensor) -> Tensor:
    """Wang et al. 2022, eq. 22 / Chisci 1996: ``T = B diag(sum_j |(B^-1 G)_ij|)``, basis ``[...,
    n]``.

    Guarantee: the solve is refined once (X + B^-1 (G - B X)) and both |X| and |correction|
    are summed, plus a relative margin of 8 n eps.
    """
    n = G.shape[-2]
    B = torch.gather(G, -1, basis.unsqueeze(-2).expand(*G.shape[:-1], n))
    if n <= 2:  # `linalg.solve`'s closed form (fused when compiled)
        X = linalg.solve(B, G)
        R = G - linalg.traced_matmul(B, X)
        X2 = linalg.solve(B, R)
    else:  # one LU for both solves, without the error check's host sync (the basis is regular)
        LU, piv, _ = torch.linalg.lu_factor_ex(B)
        X = torch.linalg.lu_solve(LU, piv, G)
        R = G - linalg.traced_matmul(B, X)
        X2 = torch.linalg.lu_solve(LU, piv, R)
    s = (X + X2).abs().sum(-1) + X2.abs().sum(-1)
    s = s * (1 + 8 * n * _EPS)
    return B * s.unsqueeze(-2)


def _max_bases(n: int) -> int:
    """Bases tried per set: `MAX_BASES` up to n = 8, then a budget falling as n^-3 (each
    basis costs an n x n solve against all generators), at least n + 1 (so the candidates
    always include the pivoted basis and one alternative)."""
    return MAX_BASES if n <= 8 else max(n + 1, MAX_BASES * 512 // n**3)


def _candidate_columns(G: Tensor, L: int) -> Tensor:
    """Indices ``[..., L]`` of the generators tried as bases when all C(m, n) are too many.

    The first n come from greedy column pivoting (the generator with the largest component
    orthogonal to those already picked, i.e. pivoted Gram-Schmidt), so the candidates contain a
    regular basis whenever G has rank n, however the lengths compare; the other L - n are the
    longest remaining generators. Selection only (no gradient), batched, n small steps.
    """
    n, m = G.shape[-2], G.shape[-1]
    with torch.no_grad():
        R = G.detach().clone()  # residuals of the columns
        picked = torch.zeros(G.shape[:-2] + (m,), dtype=torch.bool, device=G.device)
        order = []
        for _ in range(n):
            score = (R * R).sum(-2).masked_fill(picked, -1.0)  # [..., m]
            j = score.argmax(-1)  # [...]
            order.append(j)
            picked = picked | torch.nn.functional.one_hot(j, m).bool()
            q = torch.gather(R, -1, j[..., None, None].expand(*R.shape[:-1], 1))  # [..., n, 1]
            qn = q / (q * q).sum(-2, keepdim=True).sqrt().clamp_min(1e-300)
            R = R - qn * (qn * R).sum(-2, keepdim=True)
        first = torch.stack(order, -1)  # [..., n]
        rest = G.detach().norm(dim=-2).masked_fill(picked, -1.0)
        more = rest.argsort(-1, descending=True)[..., : L - n]
    return torch.cat([first, more], -1)


def _bases(G: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
    """The candidate bases of `_best_basis`: ``(Gc [..., n, L], idx [K, n], cols)``,
    the candidate columns, the index of each basis into them, and the candidates' indices into
    G (None when all ``m`` columns are candidates)."""
    n, m = G.shape[-2], G.shape[-1]
    budget = _max_bases(n)
    if math.comb(m, n) <= budget:
        return G, _combinations(m, n, G.device), None
    L = n
    while math.comb(L + 1, n) <= budget:
        L += 1
    cols = _candidate_columns(G, L)
    Gc = torch.gather(G, -1, cols.unsqueeze(-2).expand(*G.shape[:-2], n, L))
    return Gc, _combinations(L, n, G.device), cols


def _basis_solves(
    Gc: Tensor, sub: Tensor, G: Tensor, eye: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """For the bases ``B [..., k, n, n]`` (columns ``sub [k, n]`` of ``Gc``): ``|det B|``
    ``[..., k]``, ``B^-1 G`` ``[..., k, n, m]`` and the regularity flag ``|det B| > 1e-12 x``
    the Hadamard bound (product of column norms) ``[..., k]``.

    From n = 4 on, one LU factorisation gives both the determinant and the solve (the
    numbers of ``torch.linalg.det`` and ``torch.linalg.solve``, which factorise each on its
    own); a singular basis gives inf / NaN there, never an exception, and is flagged.
    """
    B = materialize(Gc[..., sub].movedim(-2, -3))  # [..., k, n, n]
    norms = Gc.norm(dim=-2)[..., sub].prod(-1)
    if B.shape[-1] <= 3:  # closed-form determinants and solves
        detB = linalg.det(B).abs()
        regular = detB > 1e-12 * norms
        Bs = torch.where(regular.unsqueeze(-1).unsqueeze(-1), B, eye)
        return detB, linalg.solve(Bs, G.unsqueeze(-3).expand(*B.shape[:-1], G.shape[-1])), regular
    LU, piv, _ = torch.linalg.lu_factor_ex(B)
    detB = LU.diagonal(dim1=-2, dim2=-1).prod(-1).abs()
    X = torch.linalg.lu_solve(LU, piv, G.unsqueeze(-3).expand(*B.shape[:-1], G.shape[-1]))
    return detB, X, detB > 1e-12 * norms


def _best_basis(G: Tensor) -> tuple[Tensor, Tensor]:
    """Index ``[..., n]`` of the basis with least |det T| (ties within `BASIS_TIE_RTOL`:
    the first in lexicographic order) and a validity flag ``[...]``."""
    n, m = G.shape[-2], G.shape[-1]
    batch = G.shape[:-2]
    if m < n:
        return torch.zeros(*batch, n, dtype=torch.long, device=G.device), torch.zeros(
            batch, dtype=torch.bool, device=G.device
        )
    Gc, idx, cols = _bases(G)
    if cols is None and n >= 4:
        return _best_basis_cramer(G, idx)
    nb = int(math.prod(batch)) or 1
    starts, step = _chunks(idx.shape[0], nb * n * (m + n))
    best_val = G.new_full(batch, float("inf"))
    best_k = torch.zeros(batch, dtype=torch.long, device=G.device)
    eye = torch.eye(n, dtype=G.dtype, device=G.device)
    for s in starts:
        sub = idx[s : s + step]
        detB, X, regular = _basis_solves(Gc, sub, G, eye)
        # |det T| = |det B| prod_i sum_j |(B^-1 G)_ij| over ALL m generators
        val = detB * X.abs().sum(-1).prod(-1)
        val = torch.where(regular, val, torch.full_like(val, float("inf")))
        # tie rule: the first basis (lexicographic) within BASIS_TIE_RTOL of the least volume,
        # so that rounding (e.g. LAPACK vs closed-form determinants) cannot flip the choice
        v = val.amin(-1, keepdim=True)
        near = val <= v * (1 + BASIS_TIE_RTOL)
        k = near.to(torch.int8).argmax(-1)  # first True
        v = v.squeeze(-1)
        better = v < best_val * (1 - BASIS_TIE_RTOL)
        best_val = torch.where(better, v, best_val)
        best_k = torch.where(better, k + s, best_k)
    basis = idx[best_k]  # [..., n] indices into the candidate columns
    if cols is not None:
        basis = torch.gather(cols, -1, basis)
    return basis, torch.isfinite(best_val)


#: Elements (batch x subsets x n) up to which `_abs_dets` expands every n x n minor of
#: ``G [..., n, m]`` row by row (`_all_minors`) instead of one LU factorisation per subset;
#: eagerly, a larger batch is expanded in chunks of this many elements where that is cheaper
#: than the LUs (`_laplace_pays`).
MINOR_ELEMS = 1 << 18


def _abs_dets(G: Tensor, idx: Tensor) -> Tensor:
    """``|det G[..., :, S]|`` for the subsets ``S`` (rows of ``idx [K, n]``), subsets first:
    ``[K, ...]``. For all ``C(m, n)`` subsets, by Laplace expansion (`_all_minors`; eagerly
    in chunks of the batch, while traced for a small batch only); else one LU factorisation
    of each transposed basis (rows gather faster than columns): the product of ``|U_ii|``,
    the number ``torch.linalg.det`` computes."""
    n, m = G.shape[-2], G.shape[-1]
    nb = int(math.prod(G.shape[:-2])) or 1
    K = idx.shape[0]
    if 2 <= n and K == math.comb(m, n):
        if nb * K * n <= MINOR_ELEMS:
            return _all_minors(G).abs().movedim(-1, 0)
        if not tracing() and _laplace_pays(m, n):  # eagerly in chunks of the batch
            Gf = G.reshape(nb, n, m)
            rows = max(1, MINOR_ELEMS // (K * n))
            M = torch.cat([_all_minors(Gf[s : s + rows]) for s in range(0, nb, rows)])
            return M.abs().mT.reshape(K, *G.shape[:-2])
    return _lu_abs_dets(G, idx)


@functools.lru_cache(maxsize=64)
def _laplace_pays(m: int, n: int) -> bool:
    """Whether the row-by-row expansion of every n x n minor of n x m matrices beats one LU
    per basis for a large batch: its products, ``sum_r r C(m, r)`` over the rows r = 2..n, at
    most 1.1 times the LUs' ``C(m, n) n^2``. Measured at batches of 1,000-30,000, one thread:
    1.2-3.8x faster than the LUs where this holds (work ratios 0.34-1.0, n = 4-8), 0.73-0.95x
    where it fails (ratios 1.3-1.7: n = 6, m = 7; n = 7, m = 9; n = 8, m = 10)."""
    work = sum(r * math.comb(m, r) for r in range(2, n + 1))
    return work <= 1.1 * math.comb(m, n) * n * n


def _lu_abs_dets(G: Tensor, idx: Tensor) -> Tensor:
    """`_abs_dets` by one LU factorisation per subset, chunked over the subsets."""
    n = G.shape[-2]
    nb = int(math.prod(G.shape[:-2])) or 1
    starts, step = _chunks(idx.shape[0], nb * n * n)
    out = []
    for s in starts:
        Bt = G.mT[..., idx[s : s + step], :]  # [..., k, n, n]: the bases transposed
        LU = torch.linalg.lu_factor_ex(Bt)[0]
        out.append(LU.diagonal(dim1=-2, dim2=-1).prod(-1).abs().movedim(-1, 0))
    return out[0] if len(out) == 1 else torch.cat(out)


def _all_minors(G: Tensor) -> Tensor:
    """Every ``n x n`` minor ``det G[..., :, S]`` of ``G [..., n, m]`` over the n-subsets
    ``S`` of its columns in lexicographic order (`_combinations`) -> ``[..., C(m, n)]``.

    Laplace expansion along the last row, one row at a time: the minors of the first ``r``
    rows on the r-subsets ``T`` are ``sum_k (-1)^(r - 1 + k) G[r - 1, T_k] M_(r-1)(T - T_k)``,
    a gather of the previous level and one product with the signs per row (about 25 ops for
    n = 6 where 924 LU factorisations cost a library call). Without pivoting: the error of a
    minor is within about ``n! eps`` of its terms' magnitudes, which moves a volume that
    `_best_basis_cramer` compares by far less than `BASIS_TIE_RTOL` unless the basis is
    nearly singular (such bases have large volumes, and every basis gives a guaranteed
    parallelotope: the choice only affects its size)."""
    M = G[..., 0, :]
    for r, (prev, cols, signs) in enumerate(_minor_plan(G.shape[-1], G.shape[-2], G), start=2):
        terms = M[..., prev] * G[..., r - 1, :][..., cols]  # [..., C(m, r), r]
        M = (terms * signs).sum(-1) if tracing() else terms @ signs  # (fused when traced)
    return M


def _minor_plan(m: int, n: int, like: Tensor) -> list[tuple[Tensor, Tensor, Tensor]]:
    """`_all_minors`' tables per row ``r = 2 .. n``: ``prev [C(m, r), r]`` (the index of
    ``T - T_k`` among the (r-1)-subsets), ``cols [C(m, r), r]`` (``T_k``) and ``signs [r]``
    (``(-1)^(r - 1 + k)``, ``like``'s dtype) -- cached eagerly per (m, n, dtype, device); built
    directly while traced (graph constants)."""
    return eager_constant(_MINOR_PLANS, (m, n, like.dtype, like.device), lambda: [
        (p.to(like.device), c.to(like.device),
         torch.tensor(sg, dtype=like.dtype, device=like.device))
        for p, c, sg in _minor_lists(m, n)])


_MINOR_PLANS: dict = {}


@functools.lru_cache(maxsize=16)
def _minor_lists(m: int, n: int) -> tuple[tuple[Tensor, Tensor, list[float]], ...]:
    """The index lists of `_minor_plan` on the CPU (lexicographic subsets)."""
    out = []
    where_prev = {(j,): j for j in range(m)}
    for r in range(2, n + 1):
        subsets = list(itertools.combinations(range(m), r))
        prev = [[where_prev[S[:k] + S[k + 1:]] for k in range(r)] for S in subsets]
        out.append((torch.tensor(prev, dtype=torch.long), torch.tensor(subsets, dtype=torch.long),
                    [(-1.0) ** (r - 1 + k) for k in range(r)]))
        where_prev = {S: i for i, S in enumerate(subsets)}
    return tuple(out)


def _exchange_table(m: int, n: int, device: torch.device) -> Tensor:
    """``[C(m, n) * n * (m - n + 1)]``, flat: for each n-subset ``S`` of range(m)
    (lexicographic, the order of `_combinations`), each position i and each column j outside
    ``S - s_i`` (ascending; ``j = s_i`` included), the index of the subset ``S - s_i + j``
    (cached eagerly; while traced, built directly: a graph constant)."""
    if tracing():
        return _exchange_list(m, n).to(device)
    return _exchange_cpu(m, n).to(device)


def _exchange_list(m: int, n: int) -> Tensor:
    subsets = list(itertools.combinations(range(m), n))
    where_ = {S: k for k, S in enumerate(subsets)}
    return torch.tensor([
        where_[tuple(sorted(S[:i] + S[i + 1 :] + (j,)))]
        for S in subsets for i in range(n) for j in range(m) if j not in S[:i] + S[i + 1 :]
    ], dtype=torch.long)


_exchange_cpu = functools.lru_cache(maxsize=16)(_exchange_list)


def _cramer_volumes(flat: Tensor, m: int, n: int) -> Tensor:
    """``|det T|`` ``[K, nb]`` of every basis from the table of ``|det|`` ``flat [K, nb]``
    (`_best_basis_cramer`): each basis gathers its ``n (m - n + 1)`` exchanged
    determinants (`_exchange_table`); chunked over the bases."""
    K, r = flat.shape[0], m - n + 1
    table = _exchange_table(m, n, flat.device)
    starts, step = _chunks(K, flat.shape[1] * n * r)
    vals = []
    for s in starts:
        k = min(step, K - s)
        t = table[s * n * r : (s + k) * n * r]
        # (a one-column table gathers 3x faster as a vector)
        dt = flat.view(-1).index_select(0, t) if flat.shape[1] == 1 else flat.index_select(0, t)
        ratio = dt.view(k, n, r, -1) / flat[s : s + k, None, None]
        vals.append(flat[s : s + k] * ratio.sum(2).prod(1))
    return vals[0] if len(vals) == 1 else torch.cat(vals)


def _cramer_volumes_sparse(flat: Tensor, m: int, n: int) -> Tensor:
    """`_cramer_volumes` with the sums over the exchanged determinants as one product by the
    constant 0/1 matrix ``A [K n, K]`` (`_exchange_matrix`): ``|det T_S| = |det B_S| prod_i
    (A |det|)_(S, i) / |det B_S|``, without the ``[K n (m - n + 1), nb]`` gathered table
    (2-4x faster on the CPU). The determinants are absolute values, so the sums have no
    cancellation; dividing the sum instead of each term changes only the last bits, which
    `BASIS_TIE_RTOL` absorbs. Chunked over the batch."""
    K = flat.shape[0]
    A = _exchange_matrix(m, n, flat.dtype, flat.device)
    starts, cols = _chunks(flat.shape[1], K * n)
    vals = []
    for s in starts:
        f = flat[:, s : s + cols] if flat.shape[1] > cols else flat
        sums = torch.sparse.mm(A, f).view(K, n, -1)  # [K, n, nb]: sum_j |det B_(S - s_i + j)|
        vals.append(f * (sums / f.unsqueeze(1)).prod(1))
    return vals[0] if len(vals) == 1 else torch.cat(vals, 1)


_EXCHANGE_MATRICES: dict = {}


def _exchange_matrix(m: int, n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The sparse (CSR) 0/1 matrix ``[C(m, n) n, C(m, n)]`` whose row ``(S, i)`` has a 1 at
    each subset ``S - s_i + j`` of `_exchange_table` (``m - n + 1`` per row); cached per
    (m, n, dtype, device), eager only."""
    def make() -> Tensor:
        K, r = math.comb(m, n), m - n + 1
        table = _exchange_cpu(m, n).view(K * n, r).sort(-1).values.reshape(-1)  # CSR order
        crow = torch.arange(0, K * n * r + 1, r)
        with warnings.catch_warnings():  # (CSR support is marked beta: a warning per process)
            warnings.simplefilter("ignore")
            A = torch.sparse_csr_tensor(crow, table, torch.ones(K * n * r, dtype=dtype),
                                        (K * n, K), check_invariants=True)
        return A.to(device)

    return eager_constant(_EXCHANGE_MATRICES, (m, n, dtype, device), make)


def _best_basis_cramer(G: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
    """`_best_basis` over all ``K = C(m, n)`` bases of ``G [..., n, m]`` (``idx [K, n]``) by
    Cramer's rule: ``(B^-1 G)_ij = det(B with column i replaced by g_j) / det B``, and that
    matrix is the basis ``S - s_i + j``. So ``|det T| = |det B| prod_i sum_j |(B^-1 G)_ij|``
    (Chisci 1996) needs only the K determinants (`_abs_dets`) and no solve (the term at
    ``j = s_i`` is 1). The same choice as the solves up to rounding, which `BASIS_TIE_RTOL`
    absorbs: the first basis within it of the least volume."""
    n, m = G.shape[-2], G.shape[-1]
    K = idx.shape[0]
    d = _abs_dets(G, idx)  # [K, ...]
    norms = G.norm(dim=-2).movedim(-1, 0)[idx].prod(1)  # Hadamard bounds [K, ...]
    regular = d > 1e-12 * norms
    flat = d.reshape(K, -1)  # [K, nb]
    val = (_cramer_volumes_sparse(flat, m, n) if not tracing() and G.device.type == "cpu"
           else _cramer_volumes(flat, m, n)).view(d.shape)
    val = torch.where(regular, val, torch.full_like(val, math.inf))
    v = val.amin(0)
    best = (val <= v * (1 + BASIS_TIE_RTOL)).to(torch.int8).argmax(0)  # the first within
    return idx[best], torch.isfinite(v)


def _expand_to(t: Tensor, shape: tuple[int, ...]) -> Tensor:
    """``t`` expanded to ``shape`` (itself, no call, when it has that shape already)."""
    return t if t.shape == shape else t.expand(shape)


def _alamo_lambda(
    c: Tensor, G: Tensor, p: Tensor, y: Tensor, sig: Tensor, method: str, Gp: Tensor
) -> Tensor:
    """lambda ``[..., n]`` of the Alamo 2005 family (see `Zonotope.intersect_strip`);
    ``Gp = p'G [..., m]``."""
    GGp = (G * Gp.unsqueeze(-2)).sum(-1)  # G G' p [..., n]
    denom = (Gp * Gp).sum(-1) + sig * sig
    # Alamo 2005 (F-radius): lambda* = G G' p / (p' G G' p + sigma^2)
    lam_f = GGp / denom.clamp_min(torch.finfo(G.dtype).tiny).unsqueeze(-1)
    if method == "fradius":
        return lam_f
    n, m = G.shape[-2], G.shape[-1]
    if m < n - 1 or (m >= n and math.comb(m, n) > MAX_VOLUME_SUBSETS):
        return lam_f  # no facets / too many subsets for the exact volume: F-radius lambda
    if math.comb(m, n - 1) > MAX_VOLUME_SUBSETS:
        return lam_f
    safe = torch.where(Gp.abs() > 0, Gp, torch.ones_like(Gp))
    lam_g = (G / safe.unsqueeze(-2)).transpose(-1, -2)  # [..., m, n] : g_j / (p.g_j)
    cands = [torch.zeros_like(lam_f).unsqueeze(-2), lam_f.unsqueeze(-2), lam_g]
    bad = [torch.zeros_like(Gp[..., :2], dtype=torch.bool), Gp.detach().abs() == 0]
    idx1 = _combinations(m, n - 1, G.device)
    with torch.no_grad():
        Gd, pd = G.detach(), p.detach()
        q = _cofactor_normals(
            Gd, idx1
        )  # [..., K, n]: vol(lam) = 2^n (|1-p.lam| V0 + sig |q lam|_1)
        if m < n:
            V0 = Gd.new_zeros(Gd.shape[:-2])
        elif n == 2:  # the same determinants from the pair table, no gather
            V0 = _planar_pair_area(Gd)
        else:
            V0 = _sum_abs_det(Gd, _combinations(m, n, G.device))
    if n >= 2 and idx1.shape[0] >= n - 1:
        lam_v, ok_v = _l1_vertex(G, p, q, idx1)
        cands.append(lam_v)
        bad.append(~ok_v)
    cands_t = torch.cat(cands, -2)  # [..., C, n]
    with torch.no_grad():
        cd = cands_t.detach()
        vol = (1 - (cd * pd.unsqueeze(-2)).sum(-1)).abs() * V0.unsqueeze(-1)
        vol = vol + sig.detach().unsqueeze(-1) * (cd @ q.transpose(-1, -2)).abs().sum(-1)
        vol = torch.where(torch.cat(bad, -1), torch.full_like(vol, float("inf")), vol)
        vol[..., 0] = vol[..., 0] * (1 - 1e-9)  # prefer lambda = 0 on (near) ties
        k = vol.argmin(-1)
    return torch.gather(cands_t, -2, k.reshape(*k.shape, 1, 1).expand(*k.shape, 1, n)).squeeze(-2)


def _l1_vertex(
    G: Tensor, p: Tensor, q: Tensor, idx1: Tensor, iters: int = 15
) -> tuple[Tensor, Tensor]:
    """Candidates for the minimiser of ``sum_T |q_T . lam|`` s.t. ``p . lam = 1`` (the
    volume-optimal lambda on the hyperplane; an LP whose optimum is a vertex where n-1 of the
    ``q_T . lam`` vanish). IRLS (detached, ``iters`` steps, best iterate kept) locates it; the
    s = n + 2 subsets with the smallest ``|q_T . lam|`` are then combined n-1 at a time and each
    vertex ``[q_T; p] lam = e_n`` is solved differentiably in G and p.
    Returns the IRLS iterate ``[..., 1, n]`` (detached) and the vertices ``[..., V, n]``
    concatenated ``[..., 1 + V, n]``, and their regularity flags ``[..., 1 + V]``."""
    n, m = G.shape[-2], G.shape[-1]
    with torch.no_grad():
        pd = p.detach()
        lam = pd / (pd * pd).sum(-1, keepdim=True)
        r = (q @ lam.unsqueeze(-1)).squeeze(-1).abs()
        best, bestf = lam, r.sum(-1)
        eps = r.mean(-1, keepdim=True).clamp_min(1e-300)
        eye = torch.eye(n, dtype=G.dtype, device=G.device)
        for _ in range(iters):
            w = 1 / torch.maximum(r, eps)
            M = q.transpose(-1, -2) @ (w.unsqueeze(-1) * q)
            tr = torch.diagonal(M, dim1=-2, dim2=-1).sum(-1)
            M = M + (1e-12 * tr / n).reshape(*tr.shape, 1, 1) * eye
            z = torch.linalg.solve_ex(M, pd.unsqueeze(-1))[0].squeeze(-1)
            lam = z / (pd * z).sum(-1, keepdim=True)
            r = (q @ lam.unsqueeze(-1)).squeeze(-1).abs()
            f = r.sum(-1)
            better = (f < bestf) & torch.isfinite(lam).all(-1)
            best = torch.where(better.unsqueeze(-1), lam, best)
            bestf = torch.where(better, f, bestf)
            eps = eps * 0.3
        r = (q @ best.unsqueeze(-1)).squeeze(-1).abs()
        k_s = min(q.shape[-2], n + 2)
        near = r.topk(k_s, dim=-1, largest=False).indices  # [..., s]
    cols = idx1[near]  # [..., s, n-1] generator indices of the near-active subsets
    Gx = G.unsqueeze(-3).expand(*cols.shape[:-1], n, m)
    Gsub = torch.gather(Gx, -1, cols.unsqueeze(-2).expand(*cols.shape[:-1], n, n - 1))
    Qs = _cross_normal(Gsub)  # [..., s, n], differentiable
    combo = _combinations(k_s, n - 1, G.device)  # [V, n-1]
    Qa = Qs[..., combo, :]  # [..., V, n-1, n]
    pe = p.expand(*Qs.shape[:-2], n).unsqueeze(-2).unsqueeze(-2)
    A = torch.cat([Qa, pe.expand(*Qa.shape[:-2], 1, n)], -2)  # [..., V, n, n]
    with torch.no_grad():
        Ad = A.detach()
        ok = linalg.det(Ad).abs() > 1e-12 * Ad.norm(dim=-1).prod(-1)
    A = torch.where(ok.unsqueeze(-1).unsqueeze(-1), A, torch.eye(n, dtype=G.dtype, device=G.device))
    e = torch.zeros(n, 1, dtype=G.dtype, device=G.device)
    e[-1] = 1.0
    verts = linalg.solve(A, e.expand(*A.shape[:-1], 1)).squeeze(-1)
    ok = torch.cat([torch.ones_like(ok[..., :1]), ok], -1)
    return torch.cat([best.unsqueeze(-2), verts], -2), ok


def _facet_directions(G: Tensor) -> tuple[Tensor, Tensor | None]:
    """Unit half-space normals ``[..., K, n]`` for the membership test and, in n >= 3 D, a
    flag ``[...]`` for the sets where they are not exact (rank-deficient: LP needed)."""
    n, m = G.shape[-2], G.shape[-1]
    eye = torch.eye(n, dtype=G.dtype, device=G.device)
    dirs = [eye.expand(*G.shape[:-2], n, n), G.transpose(-1, -2)]
    lp_needed = None
    if n == 2:
        dirs.append(torch.stack([-G[..., 1, :], G[..., 0, :]], -1))
    elif n > 2 and m >= n - 1 and math.comb(m, n - 1) <= MAX_VOLUME_SUBSETS:
        # facet normals: cross products of the (n-1)-subsets (zero, hence no constraint,
        # for rank-deficient subsets; all facets of a full-dimensional zonotope are found)
        dirs.append(_cofactor_normals(G, _combinations(m, n - 1, G.device)))
        lp_needed = (
            torch.linalg.matrix_rank(G) < n
            if m >= n
            else torch.ones(G.shape[:-2], dtype=torch.bool, device=G.device)
        )
    elif n > 2:
        lp_needed = torch.ones(G.shape[:-2], dtype=torch.bool, device=G.device)
    D = torch.cat(dirs, -2)  # [..., K, n]
    norm = D.norm(dim=-1, keepdim=True)
    D = torch.where(norm > 0, D / norm.clamp_min(1e-300), torch.zeros_like(D))
    return D, lp_needed


def _zonotope_contains(c: Tensor, G: Tensor, x: Tensor, atol: float) -> Tensor:
    """Exact membership (see `Zonotope.contains`).

    The half-space normals are computed per set (chunked over the flattened set batch to bound
    memory), then every point is tested against its set's half-spaces.
    """
    n, m = G.shape[-2], G.shape[-1]
    batch = torch.broadcast_shapes(c.shape[:-1], x.shape[:-1])
    gb = G.shape[:-2]
    if math.prod(batch) == 0 or math.prod(gb) == 0:
        return torch.zeros(batch, dtype=torch.bool, device=G.device)
    Gf = G.reshape(-1, n, m)
    k_est = n + m + (math.comb(m, n - 1) if n > 2 and m >= n - 1 else m)
    starts, step = _chunks(Gf.shape[0], k_est * n * max(n, 2))
    parts = [_facet_directions(Gf[s : s + step]) for s in starts]
    D = torch.cat([d for d, _ in parts], 0).reshape(*gb, -1, n)
    lp_needed = None if parts[0][1] is None else torch.cat([f for _, f in parts], 0).reshape(gb)
    h = (D @ G).abs().sum(-1)  # [..., K]
    dx = ((x - c).unsqueeze(-2) @ D.transpose(-1, -2)).squeeze(-2)  # [..., K]
    tol = atol + 1e-12 * (h.abs() + (D @ c.unsqueeze(-1)).squeeze(-1).abs())
    ok = (dx.abs() <= h + tol).all(-1)
    if lp_needed is not None:
        # the half-spaces found are valid ones, so a point they exclude is outside; the
        # others are decided by the feasibility LP, batched in torch first (a certificate:
        # the residual of a box point), then by HiGHS for what torch left uncertified
        lp_b = lp_needed.expand(batch) & ok
        if lp_b.any():
            ok = ok.clone()
            idx = lp_b.nonzero()
            cb, Gb, xb = c.expand(*batch, n), G.expand(*batch, n, m), x.expand(*batch, n)
            certified = _torch_lp_contains(cb, Gb, xb, idx, atol)
            for i, cert in zip(idx.tolist(), certified.tolist()):
                ii = tuple(i)
                ok[ii] = cert or _lp_contains(cb[ii], Gb[ii], xb[ii], atol)
    return ok


#: points per chunk of the batched membership LPs (bounds the memory of ``[N, n, m]``)
LP_POINTS_PER_CHUNK = 1024


def _torch_lp_contains(c: Tensor, G: Tensor, x: Tensor, idx: Tensor, atol: float) -> Tensor:
    """Certified ``x in c + G [-1, 1]^m`` (to ``atol``, max-norm) for the points ``idx [N, d]``
    of the batch -> bool ``[N]`` (False: not certified), by
    `certify_feasible` in chunks of ``LP_POINTS_PER_CHUNK``."""
    out = [
        certify_feasible(G[ii], x[ii] - c[ii], atol)  # L [N, n, m], r [N, n]
        for ii in (tuple(idx[s : s + LP_POINTS_PER_CHUNK].T)
                   for s in range(0, idx.shape[0], LP_POINTS_PER_CHUNK))
    ]
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool, device=G.device)


def _lp_contains(c: Tensor, G: Tensor, x: Tensor, atol: float) -> bool:
    """Feasibility LP: min t s.t. |G xi - (x - c)| <= t, |xi| <= 1 (scipy linprog)."""
    import numpy as np
    from scipy.optimize import linprog

    Gn = G.cpu().numpy()
    r = (x - c).cpu().numpy()
    n, m = Gn.shape
    if m == 0:
        return bool(np.abs(r).max(initial=0.0) <= atol)
    cost = np.zeros(m + 1)
    cost[-1] = 1.0
    ones = np.ones((n, 1))
    A = np.block([[Gn, -ones], [-Gn, -ones]])
    b = np.concatenate([r, -r])
    bounds = [(-1.0, 1.0)] * m + [(0, None)]
    res = linprog(cost, A_ub=A, b_ub=b, bounds=bounds, method="highs", options=HIGHS_OPTIONS)
    if res.status != 0:
        return False
    xi = np.clip(res.x[:m], -1.0, 1.0)  # verify HiGHS's point: the residual itself decides
    return bool(np.abs(Gn @ xi - r).max(initial=0.0) <= atol)
