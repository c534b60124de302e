"""Whether points lie in a zonotope: exact facet tests in low dimension and certified LPs (HiGHS
or a batched torch LP) above.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffsmf.sets.combinatorics import MAX_VOLUME_SUBSETS, _chunks, _cofactor_normals, _combinations
from diffsmf.sets.czono_lp import certify_feasible
from diffsmf.utils import (
    HIGHS_OPTIONS,
)

__all__ = ["LP_POINTS_PER_CHUNK"]

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
