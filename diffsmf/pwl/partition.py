"""Simplicial partitions of a domain in R^n: construction, point location, stellar splitting.

A partition is a pair ``vertices [nv, n]`` (float64) and ``simplices [M, n+1]`` (vertex
indices, long). It is *conforming*: two simplices meet in a common face or not at all, which is
what makes the nodal ("hat") basis continuous. Constructions here:

* :func:`kuhn_simplices` / :func:`grid_partition` -- Kuhn (Freudenthal) triangulation of a
  regular grid of boxes (every cell cut into n! simplices along the same coordinate orders),
* :func:`cone_partition` -- seed 004 sec. 3.1.2 Step 2: the point p connected to the domain's
  vertices, in n-D the cone from p over the Kuhn triangulation of the box's 2n facets,
* :class:`Refiner` -- seed 004 sec. 3.1.2 Step 3: split the region containing p by connecting p
  to its vertices (stellar subdivision; a point on a face splits every simplex sharing that face,
  so conformity is kept),
* :class:`PointLocator` -- batched point location with a uniform grid of bins.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

__all__ = [
    "PointLocator",
    "Refiner",
    "barycentric_matrices",
    "check_conforming",
    "cone_partition",
    "grid_partition",
    "kuhn_simplices",
    "simplex_domain",
    "simplex_volumes",
]

_F64 = torch.float64


def barycentric_matrices(vertices: Tensor, simplices: Tensor) -> Tensor:
    """Matrices ``Bm [M, n+1, n+1]`` with ``lambda = Bm @ [x; 1]`` the barycentric coordinates.

    vertices [nv, n], simplices [M, n+1]. Row j of ``Bm`` is the affine function that is 1 at
    vertex j of the simplex and 0 at its other vertices (the simplex's hat pieces).
    """
    V = vertices[simplices]  # [M, n+1, n]
    ones = torch.ones(V.shape[:-1] + (1,), dtype=V.dtype, device=V.device)
    T = torch.cat([V, ones], -1).transpose(-1, -2)  # [M, n+1, n+1], columns [v_j; 1]
    return torch.linalg.inv(T)


def simplex_volumes(vertices: Tensor, simplices: Tensor) -> Tensor:
    """Unsigned volumes ``[M]`` of the simplices."""
    V = vertices[simplices]
    E = V[:, 1:] - V[:, :1]
    return torch.linalg.det(E).abs() / math.factorial(vertices.shape[-1])


def kuhn_simplices(n: int) -> Tensor:
    """Kuhn triangulation of the unit n-cube: ``[n!, n+1]`` corner indices (bit i = coordinate i).

    Simplex for permutation pi: 0, e_pi1, e_pi1 + e_pi2, ..., 1 (a monotone path of corners).
    """
    rows = []
    for perm in itertools.permutations(range(n)):
        idx, path = 0, [0]
        for d in perm:
            idx |= 1 << d
            path.append(idx)
        rows.append(path)
    return torch.tensor(rows, dtype=torch.long).reshape(-1, n + 1)


def _corners(lower: Tensor, upper: Tensor) -> Tensor:
    """The 2^n corners ``[2^n, n]`` of the box, corner k has coordinate i at upper iff bit i."""
    n = lower.shape[0]
    bits = (torch.arange(2**n)[:, None] >> torch.arange(n)[None, :]) & 1
    return torch.where(bits.bool(), upper, lower)


def grid_partition(lower: Tensor, upper: Tensor, cells: int | list[int]) -> tuple[Tensor, Tensor]:
    """Kuhn (Freudenthal) triangulation of a regular grid of ``cells`` boxes per dimension.

    Returns ``vertices [prod(cells+1), n]`` and ``simplices [prod(cells) n!, n+1]``. Every cell
    uses the same coordinate-order paths, so neighbouring cells agree on shared faces.
    """
    lower, upper = torch.as_tensor(lower, dtype=_F64), torch.as_tensor(upper, dtype=_F64)
    n = lower.shape[0]
    g = [cells] * n if isinstance(cells, int) else list(cells)
    if len(g) != n or min(g) < 1:
        raise ValueError(f"cells: need {n} positive counts, got {cells}")
    axes = [torch.linspace(float(lower[i]), float(upper[i]), g[i] + 1, dtype=_F64)
            for i in range(n)]
    mesh = torch.meshgrid(*axes, indexing="ij")
    vertices = torch.stack([m.reshape(-1) for m in mesh], -1)
    strides = torch.tensor([math.prod(gi + 1 for gi in g[i + 1 :]) for i in range(n)])
    base = torch.stack(
        torch.meshgrid(*[torch.arange(gi) for gi in g], indexing="ij"), -1
    ).reshape(-1, n)  # [cells, n] lower-corner multi-index
    ks = kuhn_simplices(n)  # [n!, n+1] corner bitmasks
    bits = (ks[..., None] >> torch.arange(n)) & 1  # [n!, n+1, n]
    offs = (bits * strides).sum(-1)  # [n!, n+1]
    simplices = ((base * strides).sum(-1)[:, None, None] + offs[None]).reshape(-1, n + 1)
    return vertices, simplices


def cone_partition(
    lower: Tensor, upper: Tensor, apex: Tensor, tol: float = 1e-12
) -> tuple[Tensor, Tensor]:
    """Seed 004 sec. 3.1.2 Step 2: connect ``apex`` to the vertices of the box domain.

    In n-D: the cone from ``apex`` over the Kuhn triangulation of each of the 2n facets (the
    restriction of the cube's Kuhn triangulation to its boundary, so facets agree on shared
    faces). 2n (n-1)! simplices. An apex on the boundary makes the cones over the facets that
    contain it flat: they are dropped (the rest still tile the box). An apex at a corner reuses
    that corner. Returns ``vertices [2^n (+1), n]`` and ``simplices [M, n+1]``.
    """
    n = lower.shape[0]
    corners = _corners(lower, upper)
    width = upper - lower
    d_corner = ((corners - apex) / width).abs().amax(-1)
    if bool((d_corner <= tol).any()):
        apex_idx = int(d_corner.argmin())
        vertices = corners
    else:
        apex_idx = 2**n
        vertices = torch.cat([corners, apex[None]], 0)
    rows = []
    for d in range(n):
        others = [i for i in range(n) if i != d]
        for side in (0, 1):
            for perm in itertools.permutations(others):
                idx = side << d
                path = [idx]
                for i in perm:
                    idx |= 1 << i
                    path.append(idx)
                rows.append(path + [apex_idx])
    simplices = torch.tensor(rows, dtype=torch.long).reshape(-1, n + 1)
    vol = simplex_volumes(vertices, simplices)
    keep = vol > tol * float(width.prod())
    return vertices, simplices[keep]


def simplex_domain(lower: Tensor, upper: Tensor, margin: float = 1e-6) -> Tensor:
    """Vertices ``[n+1, n]`` of a simplex containing the box (used when n is large).

    The corner simplex {x >= l', sum_i (x_i - l'_i) / w'_i <= n} of the box enlarged by
    ``margin`` of its width contains the box (its far corner gives sum = n). A box domain needs
    2n (n-1)! simplices, which is too many beyond n = 5.
    """
    w = (upper - lower).clamp_min(1e-12)
    lo = lower - margin * w
    w2 = w * (1 + 2 * margin)
    n = lower.shape[0]
    return torch.cat([lo[None], lo[None] + n * torch.diag(w2)], 0)


def check_conforming(vertices: Tensor, simplices: Tensor, atol: float = 1e-9) -> None:
    """Raise ``AssertionError`` unless the partition is a conforming triangulation of its hull.

    Checks: positive volumes; every (n-1)-face is shared by at most two simplices; faces with
    one simplex lie on the boundary of the convex hull of the vertices; total volume equals the
    hull's volume (scipy ConvexHull, independent).
    """
    from scipy.spatial import ConvexHull

    n = vertices.shape[-1]
    vol = simplex_volumes(vertices, simplices)
    assert bool((vol > 0).all()), "degenerate simplex"
    if n == 1:  # scipy's hull needs 2-D; the hull of points on a line is [min, max]
        lo, hi = vertices.min(), vertices.max()
        hv = float(hi - lo)
        eq = torch.tensor([[-1.0, float(lo)], [1.0, -float(hi)]], dtype=vertices.dtype)
    else:
        hull = ConvexHull(vertices.numpy())
        hv = hull.volume
        eq = torch.as_tensor(hull.equations)  # [F, n+1]: a.x + b <= 0 inside
    assert abs(float(vol.sum()) - hv) <= atol * max(1.0, hv), "volume mismatch"
    faces = torch.cat([torch.cat([simplices[:, :j], simplices[:, j + 1 :]], 1)
                       for j in range(n + 1)])
    faces = faces.sort(-1).values
    uniq, counts = torch.unique(faces, dim=0, return_counts=True)
    assert int(counts.max()) <= 2, "a face is shared by more than two simplices"
    bnd = uniq[counts == 1]
    if len(bnd):
        pts = vertices[bnd]  # [f, n, n]
        on = (pts @ eq[:, :n].T + eq[:, n]).abs().amax(1) <= atol * 10  # [f, F]
        assert bool(on.any(-1).all()), "a face with one simplex is inside the domain (hole)"


class PointLocator:
    """Batched point location: a uniform grid of bins over the bounding box, each bin listing
    the simplices whose bounding boxes meet it; a query tests only its bin's candidates.

    ``locate(x [N, n]) -> (simplex [N], lam [N, n+1])`` returns the candidate with the largest
    minimum barycentric coordinate (the containing simplex for points of the domain; for points
    outside, a nearby boundary simplex with some negative coordinates).
    """

    def __init__(self, vertices: Tensor, simplices: Tensor, bary: Tensor, per_bin: float = 1.0):
        n = vertices.shape[-1]
        M = simplices.shape[0]
        self.bary = bary
        self.lo = vertices.amin(0)
        self.hi = vertices.amax(0)
        width = (self.hi - self.lo).clamp_min(1e-300)
        g = max(1, int(round((M / per_bin) ** (1.0 / n))))
        g = min(g, max(1, int(2e6 ** (1.0 / n))))
        self.g = g
        self.cell = width / g
        V = vertices[simplices]
        pad = 1e-9 * width
        smin = ((V.amin(1) - pad - self.lo) / self.cell).floor().clamp(0, g - 1).long()
        smax = ((V.amax(1) + pad - self.lo) / self.cell).floor().clamp(0, g - 1).long()
        nbins = g**n
        self.strides = torch.tensor([g ** (n - 1 - i) for i in range(n)])
        # enumerate (bin, simplex) pairs: each simplex's range of bins, decoded in mixed radix
        span = smax - smin + 1  # [M, n]
        cnt = span.prod(-1)
        sid = torch.repeat_interleave(torch.arange(M), cnt)
        local = torch.arange(int(cnt.sum())) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt,
                                                                       cnt)
        flat = torch.zeros_like(local)
        for d in range(n - 1, -1, -1):
            sp = span[sid, d]
            flat = flat + (smin[sid, d] + local % sp) * self.strides[d]
            local = local // sp
        order = torch.argsort(flat, stable=True)
        pb, ps = flat[order], sid[order]
        counts = torch.bincount(pb, minlength=nbins)
        C = int(counts.max())
        start = torch.cumsum(counts, 0) - counts
        slot = torch.arange(pb.shape[0]) - start[pb]  # pb is sorted
        table = torch.full((nbins, C), M, dtype=torch.long)
        table[pb, slot] = ps
        self.table = table  # [bins, C], M = padding
        # padding row: a "simplex" whose barycentric coordinates are all -inf
        padrow = torch.full((1, n + 1, n + 1), 0.0, dtype=bary.dtype)
        padrow[0, :, n] = -math.inf
        self.bary_pad = torch.cat([bary, padrow], 0)

    def locate(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N, n] -> (simplex index [N] long, barycentric coords [N, n+1]); no gradient."""
        x = x.detach()
        n1 = self.bary.shape[-1]
        chunk = max(1, 4_000_000 // (self.table.shape[1] * n1 * n1))  # ~32 MB of float64
        out_s, out_l = [], []
        for i in range(0, x.shape[0], chunk):
            xc = x[i : i + chunk]
            b = ((xc - self.lo) / self.cell).floor().clamp(0, self.g - 1).long()
            cand = self.table[(b * self.strides).sum(-1)]  # [c, C]
            Bm = self.bary_pad[cand]  # [c, C, n+1, n+1]
            lam = Bm[..., :-1] @ xc[:, None, :, None]
            lam = lam.squeeze(-1) + Bm[..., -1]  # [c, C, n+1]
            best = lam.amin(-1).argmax(-1)  # [c]
            ar = torch.arange(xc.shape[0])
            out_s.append(cand[ar, best])
            out_l.append(lam[ar, best])
        if not out_s:
            n1 = self.bary.shape[-1]
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, n1, dtype=x.dtype)
        return torch.cat(out_s), torch.cat(out_l)


class Refiner:
    """Mutable partition under refinement (seed 004 sec. 3.1.2 Step 3), stored with spare
    capacity: ``V [nv, n]``, ``S [M, n+1]`` with a liveness mask, and the barycentric matrices.

    ``split(p, s)`` inserts a new vertex for the max-error sample ``p`` of simplex ``s``:

    * ``rule="interior"`` (default) and p well inside s (every barycentric coordinate at least
      ``snap``): p is connected to the vertices of s (seed 004 Step 3, n+1 children);
    * ``rule="paper"``: always connect p to the vertices of s (of the face of s containing p
      when p lies on one), seed 004 literally; kept for comparison;
    * otherwise (p near a face of s, where connecting it would create slivers, or
      ``rule="edge"``): the longest edge of s is cut at p's projection, clipped to
      ``[edge_clip, 1 - edge_clip]`` of the edge (default: the midpoint), and every simplex
      sharing that edge is split in two (stellar subdivision of the edge).

    Both are stellar subdivisions of a face, applied to every live simplex containing the face,
    so the partition stays conforming. The edge rule is a deviation from seed 004: with interior
    splits only, no edge is ever shortened, the model is linear along the original long edges
    and the loop stalls on slivers (measured: 10x more vertices, see docs/pwl.md).
    ``last_face``/``last_weights`` give the new vertex as a convex combination of a face.
    """

    def __init__(self, vertices: Tensor, simplices: Tensor, snap: float = 0.2,
                 rule: str = "interior", edge_clip: float = 0.5):
        if rule not in ("interior", "edge", "paper"):
            raise ValueError(f"rule: expected 'interior', 'edge' or 'paper', got {rule!r}")
        self.n = vertices.shape[-1]
        self.snap = snap
        self.rule = rule
        self.edge_clip = edge_clip
        self.scale = (vertices.amax(0) - vertices.amin(0)).clamp_min(1e-300)
        self.V = vertices.clone()
        self.S = simplices.clone()
        self.alive = torch.ones(simplices.shape[0], dtype=torch.bool)
        self.B = barycentric_matrices(self.V, self.S)

    @property
    def n_simplices(self) -> int:
        return int(self.alive.sum())

    def lam(self, x: Tensor, s: Tensor) -> Tensor:
        """Barycentric coordinates ``[N, n+1]`` of x [N, n] in simplices s [N]."""
        Bm = self.B[s]
        return (Bm[..., :-1] @ x[..., None]).squeeze(-1) + Bm[..., -1]

    def split(self, p: Tensor, s: int) -> tuple[Tensor, Tensor] | None:
        """Insert point p [n] lying in simplex s. Returns (removed ids, new ids) or None when p
        is at a vertex already (never, with the edge rule), in which case nothing changes."""
        lam = self.lam(p[None], torch.tensor([s]))[0]
        if self.rule == "paper":  # seed 004 literally: connect p to the vertices of its face
            face_pos = (lam > 1e-9).nonzero().flatten()
            if face_pos.numel() < 2:
                return None  # p is a vertex already
            face = self.S[s, face_pos]
            w = lam[face_pos] / lam[face_pos].sum()
            q = w @ self.V[face]
            self.last_face, self.last_weights = face, w
        elif self.rule == "interior" and bool((lam >= self.snap).all()):
            face, q = self.S[s], p  # seed 004: connect p to the region's vertices
            self.last_face, self.last_weights = face, lam
        else:  # longest edge of s, cut at p's projection (clipped to the middle third)
            Vs = self.V[self.S[s]] / self.scale  # [n+1, n]
            d = torch.cdist(Vs, Vs)
            k = int(d.argmax())
            a, b = k // d.shape[0], k % d.shape[0]
            va, vb = self.V[self.S[s, a]], self.V[self.S[s, b]]
            t = float(((p - va) / self.scale) @ ((vb - va) / self.scale)) / float(d[a, b]) ** 2
            t = min(max(t, self.edge_clip), 1 - self.edge_clip)
            face = self.S[s, [a, b]]
            q = va + t * (vb - va)
            self.last_face = face
            self.last_weights = torch.tensor([1 - t, t], dtype=self.V.dtype)
        live = self.alive.nonzero().flatten()
        has = (self.S[live][:, :, None] == face[None, None, :]).any(1).all(-1)
        affected = live[has]
        new_v = self.V.shape[0]
        self.V = torch.cat([self.V, q[None]], 0)
        rows = []
        St = self.S[affected]  # [a, n+1]
        for f in face.tolist():
            pos = St == f  # [a, n+1], exactly one True per row
            rows.append(torch.where(pos, torch.full_like(St, new_v), St))
        children = torch.cat(rows, 0)
        first = self.S.shape[0]
        self.S = torch.cat([self.S, children], 0)
        self.B = torch.cat([self.B, barycentric_matrices(self.V, children)], 0)
        self.alive = torch.cat([self.alive, torch.ones(children.shape[0], dtype=torch.bool)])
        self.alive[affected] = False
        return affected, torch.arange(first, first + children.shape[0])

    def relocate(self, x: Tensor, candidates: Tensor) -> Tensor:
        """Best simplex among ``candidates [k]`` for each point of x [N, n] (max of min lam)."""
        Bm = self.B[candidates]  # [k, n+1, n+1]
        lam = torch.einsum("kij,nj->nki", Bm[..., :-1], x) + Bm[None, :, :, -1]
        return candidates[lam.amin(-1).argmax(-1)]

    def compact(self) -> tuple[Tensor, Tensor, Tensor]:
        """Live partition: (vertices [nv, n], simplices [M, n+1], old->new simplex map)."""
        live = self.alive.nonzero().flatten()
        remap = torch.full((self.S.shape[0],), -1, dtype=torch.long)
        remap[live] = torch.arange(live.numel())
        return self.V, self.S[live], remap
