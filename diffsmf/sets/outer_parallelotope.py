"""The minimal-volume outer parallelotope of a zonotope (Chisci et al. 1996, eq. 22 of Wang et
al. 2022): the search over bases of n generators, by batched determinants, Laplace minors or
Cramer exchange tables, and the parallelotope of the best basis.
"""

from __future__ import annotations

import functools
import itertools
import math
import warnings

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.sets.combinatorics import _EPS, _chunks, _combinations
from diffsmf.utils import (
    eager_constant,
    materialize,
    tracing,
)

__all__ = ["BASIS_TIE_RTOL", "MAX_BASES", "MINOR_ELEMS"]

#: ``to_parallelotope()`` enumerates at most this many bases per set; beyond, it enumerates the
#: bases formed by the L longest generators (largest L with C(L, n) <= MAX_BASES).
MAX_BASES = 5_000


#: Bases whose |det T| is within this relative distance of the least one tie; the first in
#: lexicographic order wins (a deterministic choice, independent of rounding).
BASIS_TIE_RTOL = 1e-9


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
