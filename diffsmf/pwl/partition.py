"""Simplicial partitions of a domain in R^n: construction, point location, stellar splitting.

A partition is a pair ``vertices [nv, n]`` (float64) and ``simplices [M, n+1]`` (vertex
indices, long). It is *conforming*: two simplices meet in a common face or not at all, which is
what makes the nodal ("hat") basis continuous. Constructions here:

* `kuhn_simplices` / `grid_partition` -- Kuhn (Freudenthal) triangulation of a
  regular grid of boxes (every cell cut into n! simplices along the same coordinate orders),
* `cone_partition` -- Wang et al. 2009, sec. 3.1.2 Step 2: the point p connected to the
domain's
  vertices, in n-D the cone from p over the Kuhn triangulation of the box's 2n facets,
* `Refiner` -- Wang et al. 2009, sec. 3.1.2 Step 3: split the region containing p by
connecting p
  to its vertices (stellar subdivision; a point on a face splits every simplex sharing that face,
  so conformity is kept),
* `BisectionRefiner` -- conforming longest-edge (Rivara) bisection, the default
  refinement of `fit_scplnn` (no slivers),
* `PointLocator` -- batched point location with a uniform grid of bins.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

__all__ = [
    "BisectionRefiner",
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
    """Wang et al. 2009, sec. 3.1.2 Step 2: connect ``apex`` to the vertices of the box domain.

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


def face_neighbours(simplices: Tensor) -> Tensor:
    """``[M, n+1]``: the simplex across the face opposite local vertex j (-1 on the boundary)
    of a conforming partition (faces matched by sorting their vertex lists)."""
    M, n1 = simplices.shape
    faces = torch.cat([torch.cat([simplices[:, :j], simplices[:, j + 1:]], 1)
                       for j in range(n1)]).sort(-1).values  # [(n+1) M, n], row j*M + m
    import numpy as np

    owner = torch.arange(M).repeat(n1)
    F = faces.numpy()
    order = torch.from_numpy(np.lexsort(F.T[::-1]))  # rows sorted lexicographically
    Fs = faces[order]
    same = (Fs[1:] == Fs[:-1]).all(-1)  # consecutive equal faces: the two sides
    nb = torch.full((n1 * M,), -1, dtype=torch.long)
    a, b = order[:-1][same], order[1:][same]
    nb[a], nb[b] = owner[b], owner[a]
    return nb.reshape(n1, M).T.contiguous()


class PointLocator:
    """Batched point location on a conforming partition.

    Two modes, chosen from the size of the bin table:

    * ``"bins"`` (small n): a uniform grid of bins over the bounding box, each bin listing the
      simplices whose bounding boxes meet it; a query tests only its bin's candidates.
    * ``"walk"`` (n >= 4, or a bin table of more than 4 million entries, where vertex stars
      have hundreds of simplices and bounding boxes overlap many bins): each bin keeps one
      simplex (the one containing its centre) and a query walks from it to the neighbour
      across the face of its most negative barycentric coordinate until none is negative.

    ``locate(x [N, n]) -> (simplex [N], lam [N, n+1])`` returns the containing simplex for
    points of the domain (the candidate with the largest minimum barycentric coordinate); for
    points outside, a nearby boundary simplex with some negative coordinates.
    """

    def __init__(self, vertices: Tensor, simplices: Tensor, bary: Tensor, per_bin: float = 1.0,
                 mode: str | None = None):
        n = vertices.shape[-1]
        M = simplices.shape[0]
        self.bary = bary
        self.lo = vertices.amin(0)
        self.hi = vertices.amax(0)
        width = (self.hi - self.lo).clamp_min(1e-300)
        self.width = width
        V = vertices[simplices]
        pad = 1e-9 * width
        padrow = torch.full((1, n + 1, n + 1), 0.0, dtype=bary.dtype)
        padrow[0, :, n] = -math.inf  # padding "simplex": all coordinates -inf
        self.bary_pad = torch.cat([bary, padrow], 0)
        self.neighbours: Tensor | None = None
        self.walk_steps = 0  # most steps an eager walk has needed (sets the traced walk length)
        g = max(1, int(round((M / per_bin) ** (1.0 / n))))
        g = min(g, max(1, int(2e6 ** (1.0 / n))))
        cell = width / g
        smin = ((V.amin(1) - pad - self.lo) / cell).floor().clamp(0, g - 1).long()
        smax = ((V.amax(1) + pad - self.lo) / cell).floor().clamp(0, g - 1).long()
        span = smax - smin + 1  # [M, n]
        cnt = span.prod(-1)
        if mode is None:
            mode = "walk" if (n >= 4 or int(cnt.sum()) > 4_000_000) and M > 1 else "bins"
        if mode not in ("bins", "walk"):
            raise ValueError(f"mode: expected 'bins' or 'walk', got {mode!r}")
        self.mode = mode
        if mode == "walk":
            self._init_walk(vertices, simplices, V)
            return
        self.g = g
        self.cell = cell
        nbins = g**n
        self.strides = torch.tensor([g ** (n - 1 - i) for i in range(n)])
        # enumerate (bin, simplex) pairs: each simplex's range of bins, decoded in mixed radix
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
        self.counts = counts  # [bins] candidates per bin

    def _init_walk(self, vertices: Tensor, simplices: Tensor, V: Tensor) -> None:
        n, M = vertices.shape[-1], simplices.shape[0]
        self.neighbours = face_neighbours(simplices)
        g = max(1, min(int(round((M / 8) ** (1.0 / n))), int(1e5 ** (1.0 / n))))
        self.g = g
        self.cell = self.width / g
        self.strides = torch.tensor([g ** (n - 1 - i) for i in range(n)])
        nbins = g**n
        # a first guess per bin (a simplex whose centroid falls in it), then the simplex
        # containing the bin's centre, found by walking
        cb = ((V.mean(1) - self.lo) / self.cell).floor().clamp(0, g - 1).long()
        guess = torch.full((nbins,), M, dtype=torch.long).scatter_reduce(
            0, (cb * self.strides).sum(-1), torch.arange(M), "amin")
        guess = torch.where(guess == M, 0, guess)
        idx = torch.stack(torch.meshgrid(*[torch.arange(g)] * n, indexing="ij"), -1)
        centres = self.lo + (idx.reshape(-1, n).to(V.dtype) + 0.5) * self.cell
        rep, _ = self._walk_from(centres, guess)
        self.table = rep[:, None]  # [bins, 1]
        self.counts = torch.ones(nbins, dtype=torch.long)
        # probe walks from the bins' simplices to every simplex's centroid and to points near
        # its vertices: sets ``walk_steps`` (the traced walk's length) from the partition itself
        self.walk_steps = 0
        probes = torch.cat([V.mean(1), (0.9 * V + 0.1 * V.mean(1, keepdim=True)).reshape(-1, n)])
        self._walk_from(probes, self.table[self._bin(probes), 0])

    def _walk_from(self, x: Tensor, start: Tensor) -> tuple[Tensor, Tensor]:
        """Visibility walk (batched): step to the neighbour across the face of the most negative
        barycentric coordinate until none is negative or that face is on the boundary."""
        assert self.neighbours is not None
        xa = torch.cat([x, torch.ones_like(x[:, :1])], 1)
        out_l = torch.empty(x.shape[0], x.shape[1] + 1, dtype=x.dtype)
        todo = torch.arange(x.shape[0])
        cur = start.clone()
        steps = 0
        while todo.numel():
            lam = (self.bary[cur[todo]] @ xa[todo, :, None]).squeeze(-1)  # [k, n+1]
            mn, j = lam.min(-1)
            nxt = self.neighbours[cur[todo], j]
            done = (mn >= -1e-12) | (nxt < 0)
            if steps > 20 * self.bary.shape[0]:  # cannot happen on a conforming partition
                done[:] = True
            out_l[todo[done]] = lam[done]
            cur[todo[~done]] = nxt[~done]
            todo = todo[~done]
            steps += 1
        self.walk_steps = max(self.walk_steps, steps)
        return cur, out_l

    def _walk_fixed(self, x: Tensor, start: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        """The walk with a fixed number of steps (settled points stay): no data-dependent
        control flow, for vmap / torch.compile."""
        assert self.neighbours is not None
        xa = torch.cat([x, torch.ones_like(x[:, :1])], 1)
        cur = start
        for _ in range(steps):
            lam = (self.bary[cur] @ xa[..., None]).squeeze(-1)
            mn, j = lam.min(-1)
            nxt = torch.gather(self.neighbours[cur], -1, j[..., None]).squeeze(-1)
            cur = torch.where((mn >= -1e-12) | (nxt < 0), cur, nxt)
        lam = (self.bary[cur] @ xa[..., None]).squeeze(-1)
        return cur, lam

    def _bin(self, x: Tensor) -> Tensor:
        b = ((x - self.lo) / self.cell).floor().clamp(0, self.g - 1).long()
        return (b * self.strides).sum(-1)

    def locate(self, x: Tensor, padded: bool = False) -> tuple[Tensor, Tensor]:
        """x [N, n] -> (simplex index [N] long, barycentric coords [N, n+1]); no gradient.

        Bins mode: queries are sorted by their bin's candidate count and processed in chunks
        padded only to the chunk's largest count. ``padded=True`` (for ``vmap`` /
        ``torch.compile``): fixed shapes and no data-dependent control flow -- every query
        against its bin's full padded candidate row, or in walk mode a walk of a fixed number
        of steps (twice the most any eager walk on this partition needed, plus 8; at
        construction every simplex's centroid and points near each of its vertices are walked
        to from their bins)."""
        x = x.detach()
        flat = self._bin(x)
        if self.mode == "walk":
            if padded:
                return self._walk_fixed(x, self.table[flat, 0], 2 * self.walk_steps + 8)
            return self._walk_from(x, self.table[flat, 0])
        if padded:
            cand = self.table[flat]  # [N, C]
            Bm = self.bary_pad[cand]
            lam = (Bm[..., :-1] @ x[..., None, :, None]).squeeze(-1) + Bm[..., -1]
            best = lam.amin(-1).argmax(-1, keepdim=True)  # [N, 1]
            s = torch.gather(cand, -1, best).squeeze(-1)
            lam = torch.gather(lam, -2, best[..., None].expand(best.shape + lam.shape[-1:]))
            return s, lam.squeeze(-2)
        n1 = self.bary.shape[-1]
        out_s = torch.empty(x.shape[0], dtype=torch.long)
        out_l = torch.empty(x.shape[0], n1, dtype=x.dtype)
        if x.shape[0] == 0:
            return out_s, out_l
        cnt = self.counts[flat]
        order = torch.argsort(cnt)
        cs = cnt[order].tolist()
        budget = 4_000_000 // (n1 * n1)
        i, N = 0, x.shape[0]
        while i < N:
            j, hi = i + 1, N
            while hi > j:  # largest j with (j - i) * cs[j - 1] <= budget (cs ascending)
                mid = (j + hi + 1) // 2
                if (mid - i) * max(1, cs[mid - 1]) <= budget:
                    j = mid
                else:
                    hi = mid - 1
            sel = order[i:j]
            cand = self.table[flat[sel], : max(1, cs[j - 1])]
            Bm = self.bary_pad[cand]
            lam = (Bm[..., :-1] @ x[sel][:, None, :, None]).squeeze(-1) + Bm[..., -1]
            best = lam.amin(-1).argmax(-1)
            ar = torch.arange(sel.shape[0])
            out_s[sel] = cand[ar, best]
            out_l[sel] = lam[ar, best]
            i = j
        return out_s, out_l


class Refiner:
    """Mutable partition under refinement (Wang et al. 2009, sec. 3.1.2 Step 3), stored with spare
    capacity: ``V [nv, n]``, ``S [M, n+1]`` with a liveness mask, and the barycentric matrices.

    ``split(p, s)`` inserts a new vertex for the max-error sample ``p`` of simplex ``s``:

    * ``rule="interior"`` (default) and p well inside s (every barycentric coordinate at least
      ``snap``): p is connected to the vertices of s (Wang et al. 2009 Step 3, n+1 children);
    * ``rule="paper"``: always connect p to the vertices of s (of the face of s containing p
      when p lies on one), Wang et al. 2009 literally; kept for comparison;
    * otherwise (p near a face of s, where connecting it would create slivers, or
      ``rule="edge"``): the longest edge of s is cut at p's projection, clipped to
      ``[edge_clip, 1 - edge_clip]`` of the edge (default: the midpoint), and every simplex
      sharing that edge is split in two (stellar subdivision of the edge).

    Both are stellar subdivisions of a face, applied to every live simplex containing the face,
    so the partition stays conforming. The edge rule is a deviation from Wang et al. 2009: with
    interior splits only, no edge is ever shortened, the model is linear along the original long
    edges and the loop stalls on slivers (measured: 10x more vertices, see docs/pwl.md).
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
        if self.rule == "paper":  # Wang et al. 2009 literally: connect p to the vertices of its
                                  # face
            face_pos = (lam > 1e-9).nonzero().flatten()
            if face_pos.numel() < 2:
                return None  # p is a vertex already
            face = self.S[s, face_pos]
            w = lam[face_pos] / lam[face_pos].sum()
            q = w @ self.V[face]
            self.last_face, self.last_weights = face, w
        elif self.rule == "interior" and bool((lam >= self.snap).all()):
            face, q = self.S[s], p  # Wang et al. 2009: connect p to the region's vertices
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


class BisectionRefiner:
    """Conforming longest-edge bisection of a simplicial partition (Rivara 1984; the
    longest-edge propagation path, LEPP, of Rivara 1997; in n-D the same closure).

    ``refine(s)`` bisects simplex ``s`` at the midpoint of its longest edge ``e``. Every live
    simplex containing ``e`` is bisected with it (the partition stays conforming); a neighbour
    whose own longest edge is not ``e`` is refined first, recursively along the path of
    strictly longer edges, so that every simplex is only ever cut across its longest edge.
    This keeps the minimum angle bounded below (in 2-D at least half the initial one) instead
    of producing the slivers that inserting samples as vertices creates; on a Kuhn
    triangulation it generates the shape-regular family of Maubach / Kossaczky bisection.

    Edge lengths are measured after scaling each axis by ``scale``; ties (equal lengths, common
    on Kuhn meshes) are broken consistently by vertex age (the edge whose newer endpoint is
    older wins, as in newest-vertex bisection), which makes "longest" a strict total order and
    the recursion finite.

    Bookkeeping is numpy + Python sets (one set of live simplices per vertex), with arrays that
    grow by doubling, so a bisection costs O(number of simplices sharing the edge), not O(M).
    ``parents[k]`` gives the two endpoints of the edge whose midpoint is vertex k (or -1).
    """

    def __init__(self, vertices: Tensor, simplices: Tensor, scale: Tensor | None = None,
                 min_edge: float = 1e-9):
        import numpy as np

        self._np = np
        V = vertices.detach().to(_F64).numpy()
        S = simplices.detach().numpy().astype(np.int64)
        self.n = V.shape[1]
        sc = (V.max(0) - V.min(0)) if scale is None else scale.detach().numpy()
        self.scale = np.where(sc > 0, sc, 1.0)
        self.min_edge2 = float(min_edge) ** 2
        self._V = np.empty((max(16, 2 * V.shape[0]), self.n))
        self._V[: V.shape[0]] = V
        self.nv = V.shape[0]
        cap = max(16, 2 * S.shape[0])
        self._S = np.empty((cap, self.n + 1), dtype=np.int64)
        self._S[: S.shape[0]] = S
        self.M = S.shape[0]
        self._alive = np.zeros(cap, dtype=bool)
        self._alive[: self.M] = True
        self._long = np.empty((cap, 2), dtype=np.int64)  # longest edge (a, b) of each simplex
        self._long2 = np.empty(cap)  # its squared (scaled) length
        self._child = np.full((cap, 2), -1, dtype=np.int64)  # (half with b, half with a)
        self._cutpos = np.zeros((cap, 2), dtype=np.int64)  # positions of (a, b) in the row
        self._B = np.empty((cap, self.n + 1, self.n + 1))  # barycentric matrices (lazy)
        self._hasB = np.zeros(cap, dtype=bool)
        self.parents = [(-1, -1)] * self.nv
        self.star: list[set[int]] = [set() for _ in range(self.nv)]
        for s, row in enumerate(S.tolist()):
            for v in row:
                self.star[v].add(s)
        iu = np.triu_indices(self.n + 1, 1)
        self._iu = (iu[0], iu[1])
        self._set_longest(np.arange(self.M))

    # ------------------------------------------------------------------ views
    @property
    def V(self) -> Tensor:
        """Vertices ``[nv, n]`` (a copy as a torch tensor)."""
        return torch.from_numpy(self._V[: self.nv].copy())

    @property
    def live(self) -> Tensor:
        """Ids of the live simplices ``[M_live]``."""
        return torch.from_numpy(self._alive[: self.M].nonzero()[0])

    @property
    def S(self) -> Tensor:
        """Live simplices ``[M_live, n+1]`` (vertex ids)."""
        return torch.from_numpy(self._S[: self.M][self._alive[: self.M]].copy())

    @property
    def n_simplices(self) -> int:
        return int(self._alive[: self.M].sum())

    def longest2(self, ids: Tensor) -> Tensor:
        """Squared scaled length of the longest edge of simplices ``ids`` (global ids)."""
        return torch.from_numpy(self._long2[ids.numpy()].copy())

    # ------------------------------------------------------------------ refinement
    def _set_longest(self, ids) -> None:
        np = self._np
        if len(ids) == 0:
            return
        S = self._S[ids]  # [k, n+1]
        a, b = S[:, self._iu[0]], S[:, self._iu[1]]  # [k, E]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        d = (self._V[hi] - self._V[lo]) / self.scale
        L2 = np.round((d * d).sum(-1), 10)  # quantised: equal lengths tie exactly
        # strict total order: longer first, then the edge whose newer endpoint is older
        top = L2 == L2.max(1, keepdims=True)
        key = np.where(top, -(hi.astype(np.float64) * (self.nv + 2) + lo), -np.inf)
        k = key.argmax(1)
        r = np.arange(len(ids))
        self._long[ids, 0], self._long[ids, 1] = lo[r, k], hi[r, k]
        self._long2[ids] = L2[r, k]

    def _grow(self) -> None:
        np = self._np
        if self.nv + 1 > self._V.shape[0]:
            self._V = np.concatenate([self._V, np.empty_like(self._V)])
        need = self.M + 4096
        if need > self._S.shape[0]:
            extra = max(need, 2 * self._S.shape[0]) - self._S.shape[0]
            self._S = np.concatenate([self._S, np.empty((extra, self.n + 1), dtype=np.int64)])
            self._alive = np.concatenate([self._alive, np.zeros(extra, dtype=bool)])
            self._long = np.concatenate([self._long, np.empty((extra, 2), dtype=np.int64)])
            self._long2 = np.concatenate([self._long2, np.empty(extra)])
            self._child = np.concatenate([self._child, np.full((extra, 2), -1, dtype=np.int64)])
            self._cutpos = np.concatenate([self._cutpos, np.zeros((extra, 2), dtype=np.int64)])
            self._B = np.concatenate([self._B, np.empty((extra,) + self._B.shape[1:])])
            self._hasB = np.concatenate([self._hasB, np.zeros(extra, dtype=bool)])

    def _bisect_edge(self, a: int, b: int, shared: set[int]) -> None:
        """Insert the midpoint of edge (a, b) and split every simplex in ``shared`` in two."""
        np = self._np
        self._grow()
        m = self.nv
        self._V[m] = 0.5 * (self._V[a] + self._V[b])
        self.nv += 1
        self.parents.append((a, b))
        self.star.append(set())
        ts = np.fromiter(shared, dtype=np.int64, count=len(shared))
        St = self._S[ts]
        k = len(ts)
        c1 = np.where(St == a, m, St)  # the half containing b
        c2 = np.where(St == b, m, St)  # the half containing a
        first = self.M
        ids = np.arange(first, first + 2 * k)
        self._S[first : first + 2 * k] = np.concatenate([c1, c2])
        self._alive[first : first + 2 * k] = True
        self._alive[ts] = False
        self._child[ts, 0] = ids[:k]
        self._child[ts, 1] = ids[k:]
        self._cutpos[ts, 0] = (St == a).argmax(1)
        self._cutpos[ts, 1] = (St == b).argmax(1)
        self.M += 2 * k
        for t, row in zip(ts.tolist(), St.tolist()):
            for v in row:
                self.star[v].discard(t)
        for s, row in zip(ids.tolist(), self._S[first : first + 2 * k].tolist()):
            for v in row:
                self.star[v].add(s)
        self._set_longest(ids)

    def bary(self, ids):
        """Barycentric matrices ``[k, n+1, n+1]`` (numpy) of simplices ``ids`` (any, live or
        dead), computed once and cached."""
        np = self._np
        need = ids[~self._hasB[ids]]
        if len(need):
            need = np.unique(need)
            Vs = self._V[self._S[need]]  # [k, n+1, n]
            T = np.concatenate([Vs, np.ones(Vs.shape[:-1] + (1,))], -1).transpose(0, 2, 1)
            self._B[need] = np.linalg.inv(T)
            self._hasB[need] = True
        return self._B[ids]

    def descend(self, x, s):
        """Current simplex of points x ``[k, n]`` (numpy) that lay in simplices s ``[k]``:
        follow each bisection down to a live simplex (a point goes to the half on the side of
        the cut edge's endpoint with the larger barycentric coordinate). Returns ``[k]``."""
        np = self._np
        s = s.copy()
        xa = np.concatenate([x, np.ones((x.shape[0], 1))], 1)
        while True:
            dead = (~self._alive[s]).nonzero()[0]
            if len(dead) == 0:
                return s
            t = s[dead]
            lam = np.einsum("kij,kj->ki", self.bary(t), xa[dead])
            r = np.arange(len(t))
            go_b = lam[r, self._cutpos[t, 0]] <= lam[r, self._cutpos[t, 1]]
            s[dead] = np.where(go_b, self._child[t, 0], self._child[t, 1])

    def can_refine(self, s: int) -> bool:
        """Whether simplex s is live and its longest edge is above ``min_edge`` (relative)."""
        return bool(self._alive[s]) and self._long2[s] > self.min_edge2

    def refine(self, s: int) -> int:
        """Bisect live simplex s (and, for conformity, its longest-edge neighbourhood).
        Returns the number of new vertices (0 if s was dead or below ``min_edge``)."""
        if not self.can_refine(s):
            return 0
        before = self.nv
        stack = [s]
        while stack:
            t = stack[-1]
            if not self._alive[t]:
                stack.pop()
                continue
            a, b = int(self._long[t, 0]), int(self._long[t, 1])
            shared = self.star[a] & self.star[b]
            nxt = next((u for u in shared if int(self._long[u, 0]) != a
                        or int(self._long[u, 1]) != b), None)
            if nxt is None:
                self._bisect_edge(a, b, shared)
                stack.pop()
            else:
                stack.append(nxt)  # its longest edge is strictly longer: refine it first
        return self.nv - before

    def containing(self, face: list[int]) -> set[int]:
        """Live simplices containing all vertices of ``face``."""
        out = set(self.star[face[0]])
        for v in face[1:]:
            out &= self.star[v]
        return out
