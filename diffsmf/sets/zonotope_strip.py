"""The weights of a zonotope-strip intersection (Alamo et al. 2005, Property 2): the one that
minimises the zonotope's volume (the volume criterion of sec. 5), Bravo et al. 2006's choice
among the generators by ``det(T T')``, and the vertex of the zonotope farthest along a direction
in the 1-norm of its generator coefficients.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.sets.combinatorics import (
    MAX_VOLUME_SUBSETS,
    _cofactor_normals,
    _combinations,
    _cross_normal,
    _planar_pair_area,
    _sum_abs_det,
)
from diffsmf.utils import tracing

__all__ = []

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
    if method == "bravo":
        return _bravo_lambda(G, p, sig, Gp)
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


def _bravo_lambda(G: Tensor, p: Tensor, sig: Tensor, Gp: Tensor) -> Tensor:
    """Bravo, Alamo & Camacho 2006, Property 1: of ``lambda = 0`` (Z itself) and ``lambda_j =
    g_j / (p.g_j)`` (the strip replaces generator j: ``T_i = g_i - (p.g_i / p.g_j) g_j``,
    ``T_j = sigma g_j / (p.g_j)``), the one whose generator matrix ``T`` has the least
    ``det(T T')`` -> ``lambda [..., n]``.

    Every candidate is a member of the Alamo et al. 2005 family, so each is an outer bound of
    ``Z cap S``. A generator nearly orthogonal to ``p`` (``|p.g_j| <= 1e-10 |p| |g_j|``, a
    zero padding column among them) is no candidate; ties keep the first (``lambda = 0``, then
    the lowest j), as CORA's VolMin-B does. The choice is detached; lambda is differentiable
    in ``G`` and ``p`` through the chosen candidate.
    """
    n = G.shape[-2]
    with torch.no_grad():
        scale = p.detach().norm(dim=-1, keepdim=True) * G.detach().norm(dim=-2)
        ok = Gp.detach().abs() > 1e-10 * scale  # [..., m]
    safe = torch.where(ok, Gp, torch.ones_like(Gp))
    lam_g = (G / safe.unsqueeze(-2)).transpose(-1, -2)  # [..., m, n]
    cands = torch.cat([torch.zeros_like(lam_g[..., :1, :]), lam_g], -2)  # [..., 1 + m, n]
    with torch.no_grad():
        logdet = _bravo_logdets(G.detach(), p.detach(), sig.detach(), lam_g.detach())
        bad = torch.cat([torch.zeros_like(ok[..., :1]), ~ok], -1)
        logdet = torch.where(bad | torch.isnan(logdet), torch.full_like(logdet, torch.inf),
                             logdet)
        k = logdet.argmin(-1)  # the first of equal minima
    return torch.gather(cands, -2, k.reshape(*k.shape, 1, 1).expand(*k.shape, 1, n)).squeeze(-2)


def _bravo_logdets(G: Tensor, p: Tensor, sig: Tensor, lam_g: Tensor) -> Tensor:
    """``log det(T T')`` ``[..., 1 + m]`` of Bravo's candidates: ``G G'`` for lambda = 0, and for
    ``lambda_j`` (with ``p.lambda_j = 1``) the same determinant without cancellation: the
    unimodular map ``Q = I - (lambda_j - p / |p|^2) p'`` keeps the hyperplane ``p'x = 0``
    (where the columns ``C = (I - lambda_j p') G`` lie) and sends ``sigma lambda_j`` to ``sigma
    p / |p|^2``, so ``det(T T') = sigma^2 / |p|^2 det(C_U C_U')`` with ``C_U = U' C`` in an
    orthonormal basis ``U`` of the hyperplane. Each Gram determinant is taken from a QR
    factorisation of the generator matrix (``det(C C') = prod r_ii^2``), never from ``C C'``
    itself, whose condition number is the square of C's: a large candidate (a generator nearly
    orthogonal to ``p``) would lose every digit of it."""
    n = G.shape[-2]
    ld0 = _gram_logdet(G)
    if n == 1:  # the hyperplane is {0}: det(T T') = sigma^2 / p^2
        ldj = (sig * sig / (p * p).sum(-1)).log().unsqueeze(-1).expand(lam_g.shape[:-1])
        return torch.cat([ld0.unsqueeze(-1), ldj], -1)
    Q = torch.linalg.qr(p.unsqueeze(-1), mode="complete").Q  # [..., n, n]
    U = Q[..., 1:]  # orthonormal basis of p'x = 0, [..., n, n-1]
    UG = U.transpose(-1, -2) @ G  # [..., n-1, m]
    Ul = lam_g @ U  # U' lambda_j as rows [..., m, n-1]
    Gp = (p.unsqueeze(-1) * G).sum(-2)  # [..., m]
    ld_fast, regular = _rank_one_logdets(UG, Ul, Gp)
    if tracing():  # one graph: the QR of every candidate, kept where K is singular
        ld_fast = torch.where(regular.unsqueeze(-1), ld_fast, _candidate_logdets(UG, Ul, Gp))
    elif not bool(regular.all()):  # eagerly, only for those elements (a diverged one, ...)
        bad = ~regular
        ld_fast = ld_fast.clone()
        ld_fast[bad] = _candidate_logdets(UG[bad], Ul[bad], Gp[bad])
    ldj = ld_fast + (sig * sig / (p * p).sum(-1)).log().unsqueeze(-1)
    return torch.cat([ld0.unsqueeze(-1), ldj], -1)


def _candidate_logdets(UG: Tensor, Ul: Tensor, Gp: Tensor) -> Tensor:
    """``log det(C_j C_j')`` ``[..., m]`` from the QR of each ``C_j = UG - u_j v'``
    (`_rank_one_logdets`' fallback where ``K`` is singular)."""
    C = UG.unsqueeze(-3) - Ul.unsqueeze(-1) * Gp.unsqueeze(-2).unsqueeze(-2)  # [..., m, k, m]
    return _gram_logdet(C)


def _rank_one_logdets(UG: Tensor, Ul: Tensor, Gp: Tensor) -> tuple[Tensor, Tensor]:
    """``log det(C_j C_j')`` ``[..., m]`` for ``C_j = B - u_j v'`` (``B = UG [..., k, m]``,
    ``u_j`` the rows of ``Ul [..., m, k]``, ``v = Gp [..., m]``), all from one QR: with
    ``B_perp = B (I - v v'/|v|^2)``, ``C_j = B_perp + z_j v'/|v|`` and ``B_perp v = 0``, so
    ``C_j C_j' = K + z_j z_j'`` with ``K = B_perp B_perp'`` and ``z_j = B v/|v| - |v| u_j``;
    ``log det = log det K + log(1 + |R^-T z_j|^2)`` with ``B_perp' = Q R``. ``O(m k^2)``
    instead of a QR per candidate; a large ``u_j`` enters only through the rank-one factor.
    Returns also ``regular [...]``: False where ``K`` is (nearly) singular, where the formula
    does not hold and the caller takes the QR of each ``C_j``."""
    vn = Gp.norm(dim=-1, keepdim=True)  # [..., 1]
    vh = Gp / vn.clamp_min(torch.finfo(Gp.dtype).tiny)
    Bv = (UG * vh.unsqueeze(-2)).sum(-1)  # B v / |v|, [..., k]
    Bp = UG - Bv.unsqueeze(-1) * vh.unsqueeze(-2)
    R = torch.linalg.qr(Bp.transpose(-1, -2), mode="r").R  # [..., k, k]
    d = torch.diagonal(R, dim1=-2, dim2=-1).abs()
    regular = (d.amin(-1) > 1e-10 * d.amax(-1)) & (vn.squeeze(-1) > 0)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    Rs = torch.where(regular.unsqueeze(-1).unsqueeze(-1), R, eye)
    z = Bv.unsqueeze(-2) - vn.unsqueeze(-1) * Ul  # [..., m, k]
    w = torch.linalg.solve_triangular(Rs.transpose(-1, -2), z.transpose(-1, -2), upper=False)
    ldK = 2.0 * torch.where(regular.unsqueeze(-1), d, torch.ones_like(d)).log().sum(-1)
    return ldK.unsqueeze(-1) + torch.log1p((w * w).sum(-2)), regular


def _gram_logdet(M: Tensor) -> Tensor:
    """``log det(M M')`` ``[...]`` of ``M [..., k, m]`` from the R of ``M' = Q R`` (-inf where
    the rows of M are dependent, i.e. ``m < k`` or a zero ``r_ii``)."""
    k, m = M.shape[-2], M.shape[-1]
    if m < k:
        return torch.full(M.shape[:-2], -torch.inf, dtype=M.dtype, device=M.device)
    R = torch.linalg.qr(M.transpose(-1, -2), mode="r").R  # [..., k, k]
    return 2.0 * torch.diagonal(R, dim1=-2, dim2=-1).abs().log().sum(-1)


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
