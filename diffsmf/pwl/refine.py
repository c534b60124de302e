"""The steps of the refinement loops of `diffsmf.pwl.fit` (Wang et al. 2009, sec. 3.1.2 Step 3):
locating the samples in the live simplices, extending the vertex weights to new vertices,
marking the regions to split and bisecting them worst first.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from diffsmf.pwl.partition import BisectionRefiner, Refiner

__all__: list[str] = []

_F64 = torch.float64


def _marked(ref: BisectionRefiner, sid: Tensor, lam: Tensor, idx: Tensor, bad: Tensor,
            rscore: Tensor | None, level: float) -> set[int]:
    """The regions to bisect: those holding a ``bad`` sample (local ids), every region sharing
    the face a bad sample lies on (global ids, as ``-1 - id``), and those whose region bound
    is at ``level`` or above."""
    marked = set(sid[bad].tolist())
    onface = bad & (lam.amin(-1) < 1e-9)
    if bool(onface.any()):  # a sample on a face: every region sharing the face
        for row, lm in zip(idx[onface].tolist(), lam[onface].tolist()):
            marked.update(-1 - g for g in ref.containing(
                [v for v, w in zip(row, lm) if w > 1e-9]))
    if rscore is not None:
        marked.update((rscore >= level).nonzero().flatten().tolist())
    return marked


def _refine_worst_first(ref: BisectionRefiner, marked: set[int], sid: Tensor, score: Tensor,
                        rscore: Tensor | None, max_regions: int) -> int:
    """Bisect the ``marked`` regions (`_marked`'s ids), the worst error first, until
    ``max_regions`` -> the number of regions added."""
    live = ref.live
    glob = [(-1 - m) if m < 0 else int(live[m]) for m in marked]
    pr = torch.zeros(ref.M, dtype=_F64)
    reg_score = torch.zeros(live.shape[0], dtype=_F64).scatter_reduce(0, sid, score, "amax")
    pr[live] = reg_score
    if rscore is not None:
        pr[live] = torch.maximum(pr[live], rscore)
    glob.sort(key=lambda g: -float(pr[g]) if g < pr.shape[0] else 0.0)
    added = 0
    for g in glob:
        added += ref.refine(g)
        if ref.n_simplices >= max_regions:
            break
    return added


def _locate_tracked(ref: BisectionRefiner, Xn: Any, gs: Any) -> tuple[Tensor, Tensor]:
    """Samples' live simplices (local ids ``[N]``) and barycentric coordinates ``[N, n+1]``,
    updating ``gs`` (global ids, numpy, in place) by descending the bisections."""
    import numpy as np

    gs[:] = ref.descend(Xn, gs)
    live = ref.live.numpy()
    remap = np.full(ref.M, -1, dtype=np.int64)
    remap[live] = np.arange(len(live))
    B = ref.bary(gs)
    lam = np.einsum("kij,kj->ki", B[:, :, :-1], Xn) + B[:, :, -1]
    lam = np.clip(lam, 0.0, None)
    lam /= lam.sum(-1, keepdims=True)
    return torch.from_numpy(remap[gs]), torch.from_numpy(lam)


def _extend_prior(prior: Tensor, parents: list[tuple[int, int]]) -> Tensor:
    """Values ``[nv, p]`` at all vertices: new vertex k is the midpoint of edge ``parents[k]``,
    so the current (continuous, edge-linear) model there is the mean of its endpoints'."""
    k0, nv = prior.shape[0], len(parents)
    if k0 >= nv:
        return prior
    import numpy as np

    P = np.empty((nv, prior.shape[1]))
    P[:k0] = prior.numpy()
    for k in range(k0, nv):  # parents precede children
        a, b = parents[k]
        P[k] = 0.5 * (P[a] + P[b])
    return torch.from_numpy(P)


def _longest_edge_midpoint(ref: Refiner, s: int) -> Tensor:
    """Midpoint ``[n]`` of the longest edge of live simplex s (in the Refiner's scaled metric),
    so that `Refiner.split` bisects that edge (conforming newest-edge refinement)."""
    Vs = ref.V[ref.S[s]]
    d = torch.cdist(Vs / ref.scale, Vs / ref.scale)
    k = int(d.argmax())
    return 0.5 * (Vs[k // d.shape[0]] + Vs[k % d.shape[0]])


def _split_candidates(assign: Tensor, score: Tensor, cap: int, level: float) -> Tensor:
    """Max-error sample of each region whose max error (in units of eps) is at least ``level``,
    sorted by decreasing error. Returns sample indices."""
    reg_max = torch.zeros(cap, dtype=_F64).scatter_reduce(0, assign, score, "amax")
    is_best = (score == reg_max[assign]) & (score >= level)
    pts = is_best.nonzero().flatten()
    # one per region (first index), then by decreasing error
    _, first = _first_per_group(assign[pts])
    pts = pts[first]
    return pts[torch.argsort(score[pts], descending=True)]


def _first_per_group(g: Tensor) -> tuple[Tensor, Tensor]:
    """For group labels g [k]: unique labels and the index of each label's first occurrence."""
    uniq, inv = torch.unique(g, return_inverse=True)
    first = torch.full((uniq.numel(),), g.numel(), dtype=torch.long).scatter_reduce(
        0, inv, torch.arange(g.numel()), "amin")
    return uniq, first
