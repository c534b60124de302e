"""Constraint elimination of constrained zonotopes (Scott et al. 2016, sec. 4.2 and Appendix A):
the exact elimination of one constraint, interval propagation of the generator coefficients,
the LP ranges, and the choice of the pair to eliminate by Scott's score or by the hull of the
result.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.sets.czono_lp import LP_ITERS, LP_TOL, box_lp

__all__ = ["HULL_CANDIDATES", "HULL_ITERS", "HULL_TOL", "PROPAGATION_SWEEPS"]

#: Sweeps of interval constraint propagation (Scott 2016 Appendix A) in reductions.
PROPAGATION_SWEEPS = 3


def _eliminate(
    c: Tensor, G: Tensor, A: Tensor, b: Tensor, i: Tensor, j: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Scott 2016 Prop. 5: constraint row ``i`` solved for ``xi_j`` and both deleted, for
    ``i, j [...]`` (the batch: ``c [..., n]``, ``G [..., n, m]``, ``A [..., k, m]``,
    ``b [..., k]`` broadcast to it) -> the fields with ``m - 1`` generators, ``k - 1`` rows."""
    batch = i.shape
    n, k, m = G.shape[-2], A.shape[-2], A.shape[-1]
    c, G = c.expand(*batch, n), G.expand(*batch, n, m)
    A, b = A.expand(*batch, k, m), b.expand(*batch, k)
    ar = torch.gather(A, -2, i.reshape(*batch, 1, 1).expand(*batch, 1, m)).squeeze(-2)  # A_i
    bi = torch.gather(b, -1, i.reshape(*batch, 1)).squeeze(-1)
    a = torch.gather(ar, -1, j.reshape(*batch, 1)).squeeze(-1)
    ok = a.detach().abs() > 0
    a = torch.where(ok, a, torch.ones_like(a))
    gj = torch.gather(G, -1, j.reshape(*batch, 1, 1).expand(*batch, n, 1)).squeeze(-1)
    aj = torch.gather(A, -1, j.reshape(*batch, 1, 1).expand(*batch, k, 1)).squeeze(-1)
    gj = torch.where(ok.unsqueeze(-1), gj, torch.zeros_like(gj))
    aj = torch.where(ok.unsqueeze(-1), aj, torch.zeros_like(aj))
    # Scott 2016 Prop. 5: Lambda_G = G E_ji / a_ij, Lambda_A = A E_ji / a_ij
    cn = c + gj * (bi / a).unsqueeze(-1)
    Gn = G - gj.unsqueeze(-1) * (ar / a.unsqueeze(-1)).unsqueeze(-2)
    An = A - aj.unsqueeze(-1) * (ar / a.unsqueeze(-1)).unsqueeze(-2)
    bn = b - aj * (bi / a).unsqueeze(-1)
    keep_c = _drop_index(j, m)  # [..., m-1]
    keep_r = _drop_index(i, k)  # [..., k-1]
    Gn = torch.gather(Gn, -1, keep_c.unsqueeze(-2).expand(*batch, n, m - 1))
    An = torch.gather(An, -1, keep_c.unsqueeze(-2).expand(*batch, k, m - 1))
    An = torch.gather(An, -2, keep_r.unsqueeze(-1).expand(*batch, k - 1, m - 1))
    bn = torch.gather(bn, -1, keep_r)
    return cn, Gn, An, bn


def _drop_index(i: Tensor, size: int) -> Tensor:
    """Indices ``[..., size - 1]`` of ``range(size)`` without ``i [...]`` (in order)."""
    ar = torch.arange(size - 1, device=i.device)
    return ar + (ar >= i.unsqueeze(-1)).long()


def _propagate(A: Tensor, b: Tensor, sweeps: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Scott 2016 Appendix A interval propagation (Jacobi sweeps, outward rounded)."""
    k, m = A.shape[-2], A.shape[-1]
    lo = torch.full(A.shape[:-2] + (m,), -1.0, dtype=A.dtype, device=A.device)
    hi = -lo
    Rlo = torch.full_like(lo, -float("inf"))
    Rhi = torch.full_like(lo, float("inf"))
    if k == 0:
        return lo, hi, Rlo, Rhi
    Aa = A.abs()
    valid = Aa > 1e-10 * Aa.amax(-1, keepdim=True)
    safe = torch.where(valid, A, torch.ones_like(A))
    for _ in range(sweeps):
        mid, rad = 0.5 * (lo + hi), (0.5 * (hi - lo)).clamp_min(0)
        rm = (A * mid.unsqueeze(-2)).sum(-1, keepdim=True)  # [..., k, 1]
        rr = (Aa * rad.unsqueeze(-2)).sum(-1, keepdim=True)
        em = rm - A * mid.unsqueeze(-2)  # row sums without column j [..., k, m]
        er = (rr - Aa * rad.unsqueeze(-2)).clamp_min(0)
        t = (b.unsqueeze(-1) - em) / safe
        w = er / safe.abs()
        w = (
            w
            + 1e-12 * (t.abs() + w + (b.abs().unsqueeze(-1) + rm.abs() + rr) / safe.abs())
            + 1e-300
        )
        inf = torch.full_like(t, float("inf"))
        l_ij = torch.where(valid, t - w, -inf)
        h_ij = torch.where(valid, t + w, inf)
        Rlo = torch.maximum(Rlo, l_ij.amax(-2))
        Rhi = torch.minimum(Rhi, h_ij.amin(-2))
        lo = torch.maximum(lo, Rlo)
        hi = torch.minimum(hi, Rhi)
    return lo, hi, Rlo, Rhi


def _lp_ranges(A: Tensor, b: Tensor, big: float = 1e3, iters: int = 12) -> tuple[Tensor, Tensor]:
    """Range ``[..., m]`` of each ``xi_j`` over ``{A xi = b, |xi_k| <= 1 (k != j)}`` (its own
    bound relaxed to ``|xi_j| <= big``), by ``2 m`` batched LPs (`box_lp`): the exact
    version of Scott 2016's propagated ``R_j`` (Appendix A)."""
    m = A.shape[-1]
    eye = torch.eye(m, dtype=A.dtype, device=A.device)
    scale = 1 + (big - 1) * eye  # row j: column j scaled by big (xi_j = big eta_j)
    Aj = A.unsqueeze(-3) * scale.unsqueeze(-2)  # [..., m, k, m]
    g = torch.stack([big * eye, -big * eye])  # [2, m, m]
    g = g.reshape(2, *([1] * (A.dim() - 2)), m, m)
    up, _, _, _ = box_lp(g, Aj.unsqueeze(0), b.unsqueeze(-2).unsqueeze(0), iters)  # [2, ..., m]
    return -up[1], up[0]


def _pivot_row(A: Tensor, j: Tensor) -> Tensor:
    """Row ``[...]`` of the largest pivot ``|a_ij|`` in column ``j [...]`` of ``A [..., k, m]``
    (entries ``<= 1e-10 max|A_i|`` are not pivots)."""
    k = A.shape[-2]
    Aa = A.abs()
    pivot = Aa > 1e-10 * Aa.amax(-1, keepdim=True).clamp_min(1e-300)
    Ap = torch.where(pivot, Aa, torch.zeros_like(Aa))
    col = torch.gather(Ap, -1, j.reshape(*j.shape, 1, 1).expand(*j.shape, k, 1)).squeeze(-1)
    return col.argmax(-1)


def _hull_choice(
    G: Tensor, A: Tensor, b: Tensor, cand: Tensor, valid: Tensor
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """Exact ``"hull"`` ranking of the candidates ``cand [..., K]`` (``valid [..., K]``: has a
    pivot): each candidate is eliminated (`_eliminate`, Prop. 5), the ``2 n`` hull LPs
    of all ``K`` results are solved in one batched `box_lp` (``[2n, ..., K]``), and the
    candidate with the smallest sum over axes of ``width / (zonotope width 2 sum_j |G_ij|)``
    wins. -> ``(i, j, (lam, xi))``, the LP solutions of the winner (its certified hull,
    `ConstrainedZonotope._hull_from_duals`). Detached."""
    n = G.shape[-2]
    i = _pivot_row(A.unsqueeze(-3).expand(*cand.shape, *A.shape[-2:]), cand)  # [..., K]
    zc = G.new_zeros(*G.shape[:-1])
    _, Gk, Ak, bk = _eliminate(
        zc.unsqueeze(-2), G.unsqueeze(-3), A.unsqueeze(-3), b.unsqueeze(-2), i, cand
    )  # [..., K, n, m-1], [..., K, k-1, m-1], [..., K, k-1]
    g = torch.cat([Gk, -Gk], -2).movedim(-2, 0)  # [2n, ..., K, m-1]
    up, lam, xi, _ = box_lp(g, Ak.unsqueeze(0), bk.unsqueeze(0), HULL_ITERS, HULL_TOL)
    width = up[:n] + up[n:]  # [n, ..., K]: the centre terms cancel
    width = torch.where(valid, width, torch.full_like(width, float("inf")))
    # per-axis scale: the width of the zonotope without constraints (no LP; measured on the
    # linear benchmark as tight as the current set's LP width)
    ref = (2 * G.abs().sum(-1)).movedim(-1, 0).unsqueeze(-1).clamp_min(1e-300)
    score = (width / ref).nan_to_num(nan=float("inf")).sum(0)  # [..., K]
    best = score.argmin(-1, keepdim=True)  # [..., 1]
    j = torch.gather(cand, -1, best).squeeze(-1)
    ib = torch.gather(i, -1, best).squeeze(-1)

    def pick(t: Tensor) -> Tensor:  # [2n, ..., K, p] -> [2n, ..., p]
        idx = best.expand(2 * n, *best.shape).unsqueeze(-1).expand(*t.shape[:-2], 1, t.shape[-1])
        return torch.gather(t, -2, idx).squeeze(-2)

    return ib, j, (pick(lam), pick(xi))


#: Candidates (best Scott 2016 Appendix A scores) re-ranked by the exact hull in ``"hull"``.
HULL_CANDIDATES = 4


#: Interior-point iterations (at most) and early-stop tolerance of the ``"hull"`` ranking
#: LPs. The winner's LP solutions certify the hull of the result (no second solve), so they
#: are solved as accurately as `ConstrainedZonotope.interval_hull`.
HULL_ITERS = LP_ITERS


HULL_TOL = LP_TOL


def _scott_score(G: Tensor, A: Tensor, b: Tensor, Rlo: Tensor, Rhi: Tensor) -> Tensor:
    """Scott 2016 Appendix A estimate ``r_j / sqrt(s_j)`` ``[..., m]`` (``inf`` for columns
    without a pivot), see `ConstrainedZonotope.reduce_constraints`."""
    k, m = A.shape[-2], A.shape[-1]
    r = (torch.maximum(Rlo.abs(), Rhi.abs()) - 1).clamp_min(0)  # eq. A.6
    r = torch.where(torch.isfinite(r), r, torch.full_like(r, 1e300))
    eye = torch.eye(m, dtype=G.dtype, device=G.device)
    Q = G.mT @ G + eye
    P = torch.cholesky_inverse(torch.linalg.cholesky(Q))
    AP = A @ P  # [..., k, m]
    S = AP @ A.mT
    tr = torch.diagonal(S, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)
    S = S + (1e-12 * tr / k).reshape(*tr.shape, 1, 1) * torch.eye(k, dtype=G.dtype, device=G.device)
    X = torch.linalg.solve(S, AP)  # S^-1 A P  [..., k, m]
    s = torch.diagonal(P, dim1=-2, dim2=-1) - (AP * X).sum(-2)  # eq. A.7 Schur complement
    score = r / s.clamp_min(1e-300).sqrt()
    score = torch.where(r == 0, torch.zeros_like(score), score)
    Aa = A.abs()
    pivot = Aa > 1e-10 * Aa.amax(-1, keepdim=True).clamp_min(1e-300)  # [..., k, m]
    return torch.where(pivot.any(-2), score, torch.full_like(score, float("inf")))


def _elimination_choice(
    G: Tensor, A: Tensor, b: Tensor, heuristic: str = "lp"
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor] | None]:
    """Row i and column j ``[...]`` of the next elimination (Scott 2016 Appendix A), and for
    ``"hull"`` the LP solutions of the result's hull (`_hull_choice`, else ``None``)."""
    m = A.shape[-1]
    if heuristic == "hull":
        pre = _scott_score(G, A, b, *_propagate(A, b, PROPAGATION_SWEEPS)[2:])
        K = min(HULL_CANDIDATES, m)
        cand = pre.topk(K, dim=-1, largest=False).indices  # [..., K]
        valid = torch.isfinite(torch.gather(pre, -1, cand))
        return _hull_choice(G, A, b, cand, valid)
    if heuristic == "lp":
        Rlo, Rhi = _lp_ranges(A, b)
    else:
        _, _, Rlo, Rhi = _propagate(A, b, PROPAGATION_SWEEPS)
    score = _scott_score(G, A, b, Rlo, Rhi)
    j = score.argmin(-1)  # [...]
    return _pivot_row(A, j), j, None
