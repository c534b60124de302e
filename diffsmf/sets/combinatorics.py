"""Subsets of generators and the determinants, normals and planar areas built from them: the
combinatorics that the zonotope's volume, its outer parallelotope, Alamo's strip weight and the
containment test share.
"""

from __future__ import annotations

import functools
import itertools
import math

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.utils import (
    tracing,
)

__all__ = ["MAX_VOLUME_SUBSETS", "PAIR_TABLE_MAX_M"]

#: Above this many generator n-subsets per set, ``volume()`` returns an upper bound
#: (min of the interval-hull volume and the outer-parallelotope volume) instead of the exact sum.
MAX_VOLUME_SUBSETS = 20_000


#: Elements processed per chunk (batch x subsets x n x m) in the subset enumerations.
_CHUNK_ELEMS = 4_000_000


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
