"""Exact ranges of a continuous piecewise-linear model and of its gradients over boxes.

A continuous PWL function ``f`` on a conforming simplicial partition is affine on every simplex
``S_k``, so its minimum and maximum over a box ``B`` are attained at vertices of the polytopes
``B ∩ S_k``. A vertex ``v`` of ``B ∩ S_k`` lies in the relative interior of a face ``F`` of the
partition (dimension ``d``, spanned by ``d + 1`` partition vertices) and of a face ``G`` of the
box, and ``aff F ∩ aff G = {v}``. Among the coordinates that ``G`` fixes at a bound, ``d``
already determine the point on ``aff F`` (a nonsingular ``d x d`` system), so every such vertex
is found by enumerating, for every face ``F`` of the partition, every set ``I`` of ``d``
coordinates and every choice of lower/upper bound for them, the point ``x`` of ``aff F`` with
``x_I`` at those bounds, and keeping the points that lie in ``F`` (barycentric weights >= 0)
and in the box. Their values (``F``'s vertex weights mixed by the barycentric weights) give the
exact range; a face with a valid point meets the box, and so does every simplex containing it,
which gives the exact set of pieces that meet the box and the hull of their gradients (the
interval hull of the Clarke generalised Jacobian over the box).

Everything that depends only on the partition (faces, inverses of the ``d x d`` systems) is
tabulated once (`face_tables`); a query is then a few batched tensor products per face
dimension, with no data-dependent shapes (no host synchronisation).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["FaceTables", "box_enclosure", "face_tables"]

#: Relative tolerance of the membership tests (barycentric weights and box bounds, the latter
#: scaled by the domain's width): a point this close to a face or the box is kept, so that
#: rounding never drops a true vertex; it can only widen the result by ``L * TOL * width``.
TOL = 1e-10
#: Two ``d x d`` systems whose Hadamard ratio ``|det| / prod(column norms)`` (columns scaled by
#: the domain's width) is below this are treated as singular (a face parallel to a box face):
#: the points they would give are found from other faces and box faces.
SINGULAR = 1e-12
#: Elements per chunk of the batched query (memory cap).
CHUNK_ELEMS = 4_000_000


@dataclass
class FaceDim:
    """Faces of one dimension d and their point systems (see module docstring).

    faces ``[F, d+1]`` (vertex ids), combos ``[C, d]`` (coordinate sets I), u0 ``[F, n]`` (first
    vertex), D ``[F, n, d]`` (edge vectors from u0), Einv ``[F, C, d, d]`` (inverse of
    ``D[I]``, identity where singular), ok ``[F, C]`` (nonsingular), u0I ``[F, C, d]``, bmin /
    bmax ``[F, n]`` (bounding box of the face, padded by ``(n + 2) TOL`` of the domain width so
    that it holds every point the tolerant membership test keeps).
    """

    faces: Tensor
    combos: Tensor
    u0: Tensor
    D: Tensor
    Einv: Tensor
    ok: Tensor
    u0I: Tensor
    bmin: Tensor
    bmax: Tensor

    @property
    def n_faces(self) -> int:
        return self.faces.shape[0]


@dataclass
class FaceTables:
    """Faces of every dimension 0..n and, per simplex, the ids of its faces ``[M, 2^(n+1)-1]``
    (numbered consecutively over the dimensions, dimension 0 first)."""

    dims: list[FaceDim]
    simplex_faces: Tensor
    width: Tensor
    top_simplex: Tensor  # [M]: simplex id of each n-dimensional face (faces are sorted)


def face_tables(vertices: Tensor, simplices: Tensor) -> FaceTables:
    """Tabulate the faces of a partition (``vertices [nv, n]``, ``simplices [M, n+1]``)."""
    n = vertices.shape[1]
    width = (vertices.amax(0) - vertices.amin(0)).clamp_min(1e-300)
    dims, cols, offset = [], [], 0
    for d in range(n + 1):
        subsets = list(itertools.combinations(range(n + 1), d + 1))
        rows = simplices[:, subsets].sort(-1).values  # [M, s, d+1]
        faces, inv = torch.unique(rows.reshape(-1, d + 1), dim=0, return_inverse=True)
        cols.append(inv.reshape(simplices.shape[0], len(subsets)) + offset)
        offset += faces.shape[0]
        dims.append(_face_dim(vertices, faces, d, width))
    top = torch.empty_like(cols[-1][:, 0])
    top[cols[-1][:, 0] - (offset - dims[-1].n_faces)] = torch.arange(
        simplices.shape[0], device=top.device)
    return FaceTables(dims=dims, simplex_faces=torch.cat(cols, 1), width=width,
                      top_simplex=top)


def _face_dim(vertices: Tensor, faces: Tensor, d: int, width: Tensor) -> FaceDim:
    n = vertices.shape[1]
    P = vertices[faces]  # [F, d+1, n]
    u0 = P[:, 0]
    D = (P[:, 1:] - u0[:, None]).transpose(-1, -2)  # [F, n, d]
    dev = vertices.device
    combos = torch.tensor(list(itertools.combinations(range(n), d)), dtype=torch.long,
                          device=dev)
    combos = combos.reshape(-1, d) if d else torch.zeros(1, 0, dtype=torch.long, device=dev)
    E = D[:, combos]  # [F, C, d, d]: rows I of the edge matrix
    Es = E / width[combos][None, :, :, None]
    norms = (D / width[:, None]).norm(dim=-2)  # [F, d] scaled edge lengths
    if d == 0:
        ok = torch.ones(E.shape[:2], dtype=torch.bool, device=dev)
    else:
        ratio = torch.linalg.det(Es).abs() / norms.prod(-1)[:, None]
        ok = ratio > SINGULAR
    eye = torch.eye(d, dtype=E.dtype, device=dev).expand_as(E)
    Einv = torch.linalg.inv(torch.where(ok[..., None, None], E, eye))
    pad = (n + 2) * TOL * width
    return FaceDim(faces=faces, combos=combos, u0=u0, D=D, Einv=Einv.contiguous(), ok=ok,
                   u0I=u0[:, combos], bmin=P.amin(1) - pad, bmax=P.amax(1) + pad)


def _per_box_elems(tables: FaceTables, p: int) -> int:
    n = tables.width.shape[0]
    tot = 0
    for d, fd in enumerate(tables.dims):
        tot += fd.n_faces * fd.combos.shape[0] * (2**d) * (n + p + 2 * d + 2)
    return tot + tables.simplex_faces.numel() + tables.simplex_faces.shape[0] * p * n


def box_enclosure(tables: FaceTables, weight: Tensor, A: Tensor, lo: Tensor, hi: Tensor,
                  sparse: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Exact range and gradient hull over boxes ``lo, hi [B, n]`` (inside the domain or not).

    Args:
        tables: `face_tables` of the partition.
        weight: vertex values ``[nv, p]``.
        A: slopes of the pieces ``[M, p, n]``.
        sparse: only the (box, face) pairs whose bounding boxes overlap are evaluated (one
            data-dependent ``nonzero``: a host synchronisation on a GPU); False evaluates every
            pair (fixed shapes: traceable, compilable). Same result.

    Returns:
        ``val_lo, val_hi [B, p]`` (min / max of the model over box ∩ domain; +inf / -inf where
        the box misses the domain), ``jac_lo, jac_hi [B, p, n]`` (entrywise min / max of the
        slopes of the pieces that meet the box; +inf / -inf where none does) and ``corners
        [B]``: whether every corner of the box lies in the domain (for a convex domain: the box
        is inside it).
    """
    per = 1 if sparse else _per_box_elems(tables, weight.shape[1])
    step = max(1, CHUNK_ELEMS // per)
    outs = [_chunk(tables, weight, A, lo[i:i + step], hi[i:i + step], sparse)
            for i in range(0, lo.shape[0], step)]
    return tuple(torch.cat(parts) for parts in zip(*outs))  # type: ignore[return-value]


def _pairs(fd: FaceDim, lo: Tensor, hi: Tensor, sparse: bool) -> tuple[Tensor, Tensor]:
    """(box ids, face ids) ``[K]`` of the pairs to evaluate."""
    B, F = lo.shape[0], fd.n_faces
    if not sparse:
        return (torch.arange(B, device=lo.device).repeat_interleave(F),
                torch.arange(F, device=lo.device).repeat(B))
    over = ((fd.bmin[None] <= hi[:, None]) & (fd.bmax[None] >= lo[:, None])).all(-1)
    ib, jf = over.nonzero(as_tuple=True)
    return ib, jf


def _chunk(tables: FaceTables, weight: Tensor, A: Tensor, lo: Tensor, hi: Tensor,
           sparse: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    B, n = lo.shape
    p = weight.shape[1]
    tx = TOL * tables.width
    inf = torch.full((), torch.inf, dtype=lo.dtype, device=lo.device)
    vmin = inf.expand(B, p).clone()
    vmax = -vmin
    valid_faces = []
    corners = torch.ones(B, dtype=torch.bool, device=lo.device)
    for d, fd in enumerate(tables.dims):
        ib, jf = _pairs(fd, lo - tx, hi + tx, sparse)
        val, valid = _candidates(fd, weight, lo, hi, tx, d, ib, jf)  # [K, C, 2^d, p], [K, C, 2^d]
        idx = ib[:, None].expand(-1, p)
        vmin = vmin.scatter_reduce(0, idx, torch.where(valid[..., None], val, inf).amin((1, 2)),
                                   "amin")
        vmax = vmax.scatter_reduce(0, idx, torch.where(valid[..., None], val, -inf).amax((1, 2)),
                                   "amax")
        fv = torch.zeros(B, fd.n_faces, dtype=torch.bool, device=lo.device)
        valid_faces.append(fv.index_put((ib, jf), valid.flatten(1).any(-1)))
        if d == n:  # simplices; one combo (all coordinates): its 2^n points are the corners
            hits = torch.zeros(B, 2**n, dtype=lo.dtype, device=lo.device)
            corners = hits.index_add(0, ib, valid[:, 0].to(lo.dtype)).gt(0).all(-1)
            simplex_pairs = (ib, tables.top_simplex[jf])
    jlo, jhi = _slope_hull(torch.cat(valid_faces, 1), tables.simplex_faces, A, *simplex_pairs)
    return vmin, vmax, jlo, jhi, corners


def _slope_hull(valid_faces: Tensor, simplex_faces: Tensor, A: Tensor, ib: Tensor, jf: Tensor
                ) -> tuple[Tensor, Tensor]:
    """Entrywise min / max ``[B, p, n]`` of the slopes ``A [M, p, n]`` of the simplices that
    meet each box: among the pairs (box ``ib``, simplex ``jf``) ``[K]``, those with a face that
    has a kept point (``valid_faces [B, total faces]``)."""
    B, (M, p, n) = valid_faces.shape[0], A.shape
    meet = valid_faces[ib[:, None], simplex_faces[jf]].any(-1)  # [K]
    Ak = A.reshape(M, p * n)[jf]
    idx = ib[:, None].expand(-1, p * n)
    full = torch.full((B, p * n), torch.inf, dtype=A.dtype, device=A.device)
    inf = full[:1, :1].squeeze()
    jlo = full.scatter_reduce(0, idx, torch.where(meet[:, None], Ak, inf), "amin")
    jhi = (-full).scatter_reduce(0, idx, torch.where(meet[:, None], Ak, -inf), "amax")
    return jlo.reshape(B, p, n), jhi.reshape(B, p, n)


def _candidates(fd: FaceDim, weight: Tensor, lo: Tensor, hi: Tensor, tx: Tensor, d: int,
                ib: Tensor, jf: Tensor) -> tuple[Tensor, Tensor]:
    """For pairs (box ``ib``, face ``jf``) ``[K]``: the points of ``aff F`` with ``d``
    coordinates at the box's bounds, their values ``[K, C, 2^d, p]`` and validity
    ``[K, C, 2^d]`` (nonsingular system, in F and in the box up to the tolerances)."""
    W = weight[fd.faces[jf]]  # [K, d+1, p]
    lo3, hi3 = lo[ib][:, None, None], hi[ib][:, None, None]  # [K, 1, 1, n]
    u0 = fd.u0[jf][:, None, None]  # [K, 1, 1, n]
    if d == 0:
        inside = ((u0 >= lo3 - tx) & (u0 <= hi3 + tx)).all(-1)  # [K, 1, 1]
        return W[:, None, None, 0], inside
    bits = ((torch.arange(2**d, device=lo.device)[:, None] >> torch.arange(
        d, device=lo.device)[None]) & 1).bool()  # [2^d, d]
    combos = fd.combos
    c = torch.where(bits, hi[ib][:, combos][:, :, None], lo[ib][:, combos][:, :, None])
    rhs = c - fd.u0I[jf][:, :, None]  # [K, C, 2^d, d]
    Einv = fd.Einv[jf][:, :, None]  # [K, C, 1, d, d]
    t = sum(Einv[..., j] * rhs[..., j, None] for j in range(d))  # [K, C, 2^d, d]
    D = fd.D[jf][:, None, None]  # [K, 1, 1, n, d]
    x = u0 + sum(D[..., j] * t[..., j, None] for j in range(d))  # [K, C, 2^d, n]
    W0 = W[:, None, None, 0]  # [K, 1, 1, p]
    DW = (W[:, 1:] - W[:, :1])[:, None, None]  # [K, 1, 1, d, p]
    val = W0 + sum(DW[..., j, :] * t[..., j, None] for j in range(d))
    valid = ((t >= -TOL).all(-1) & (t.sum(-1) <= 1 + TOL)
             & ((x >= lo3 - tx) & (x <= hi3 + tx)).all(-1) & fd.ok[jf][:, :, None])
    return val, valid
