"""Adaptive least-squares fitting of SCPLNN models (Wang et al. 2009, sec. 3.1.2).

Step 1: least-squares affine fit; stop if its max sample error is below eps.
Step 2: an initial partition. Default (``rule="rivara"``): the Kuhn triangulation of
the box. Older rules: connect the max-error sample p1 to the domain's vertices
(`cone_partition`); p1 closer than ``snap`` (relative) to a side of the box is first
moved onto it, else the cones over the near facets are slivers that no later split repairs.
Step 3: least-squares fit of the vertex weights (refit of the whole model); every region whose
max sample error exceeds eps is split; repeat until no region exceeds eps. Default: conforming
longest-edge bisection (`BisectionRefiner`) of those regions, with a held-out part of
the samples also marking regions (the error between samples); older rules: split at the
max-error sample by connecting it to the region's vertices (`Refiner`)."""

from __future__ import annotations

import math
import time
import warnings as _warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from diffsmf.pwl._threads import single_thread
from diffsmf.pwl.partition import (
    BisectionRefiner,
    PointLocator,
    Refiner,
    barycentric_matrices,
    cone_partition,
    grid_partition,
    simplex_domain,
)
from diffsmf.pwl.refine import (
    _extend_prior,
    _locate_tracked,
    _longest_edge_midpoint,
    _marked,
    _refine_worst_first,
    _split_candidates,
)
from diffsmf.pwl.scplnn import SCPLNN

__all__ = ["FitReport", "as_xy", "default_max_regions", "domain_box", "fit_partition", "fit_scplnn",
           "fit_weights"]

_F64 = torch.float64


BOX_MAX_DIM = 5  # beyond this a box domain needs > 2n (n-1)! = 1440 initial simplices


@dataclass
class FitReport:
    """Summary of `fit_scplnn`.

    regions: number of simplices; vertices: partition vertices; parameters: fitted weights
    (vertices * outputs); max_error / rms_error ``[p]``: training errors per output; eps ``[p]``;
    converged: max error < eps for every output; rounds: refit rounds; seconds: wall time;
    history: (regions, max scaled error) after each refit; stop_reason: why the loop ended.
    heldout_max_error ``[p]``: max error on ``heldout_samples`` samples that were left out of
    the least squares, of the model fitted without them (an estimate of the error *between*
    samples; None when no samples were held out); the returned model is then refitted on all
    samples and ``max_error`` / ``converged`` refer to all of them. warnings: degenerate or
    conflicting data (duplicate X with different Y, samples in a lower-dimensional subspace).
    """

    regions: int
    vertices: int
    parameters: int
    max_error: Tensor
    rms_error: Tensor
    eps: Tensor
    converged: bool
    rounds: int
    seconds: float
    stop_reason: str
    history: list[tuple[int, float]] = field(default_factory=list)
    bound_max: Tensor | None = None  # [p] max of ``region_bound`` over the regions, if given
    heldout_max_error: Tensor | None = None  # [p] max error on the held-out samples (see below)
    heldout_samples: int = 0
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> str:
        me = ", ".join(f"{v:.4g}" for v in self.max_error.tolist())
        ep = ", ".join(f"{v:.4g}" for v in self.eps.tolist())
        text = (f"SCPLNN fit: {self.regions} regions, {self.vertices} vertices, "
                f"{self.parameters} weights; max training error [{me}] (eps [{ep}]), "
                f"converged={self.converged} ({self.stop_reason}), {self.rounds} rounds, "
                f"{self.seconds:.3f} s")
        if self.heldout_max_error is not None:
            text += ("; held-out max error [" + ", ".join(
                f"{v:.4g}" for v in self.heldout_max_error.tolist())
                + f"] on {self.heldout_samples} samples")
        if self.bound_max is not None:
            text += ("; certified bound [" + ", ".join(f"{v:.4g}" for v in self.bound_max.tolist())
                     + "]")
        for w in self.warnings:
            text += f"\nwarning: {w}"
        return text


def as_xy(X: Any, Y: Any) -> tuple[Tensor, Tensor]:
    """Validate samples: X ``[N, n]`` (or [N]) and Y ``[N, p]`` (or [N]) as float64 tensors."""
    X = torch.as_tensor(X, dtype=_F64)
    Y = torch.as_tensor(Y, dtype=_F64)
    if X.dim() == 1:
        X = X[:, None]
    if Y.dim() == 1:
        Y = Y[:, None]
    if X.dim() != 2 or X.shape[1] < 1:
        raise ValueError(f"X: expected [N, n] with n >= 1, got shape {tuple(X.shape)}")
    if Y.dim() != 2 or Y.shape[0] != X.shape[0]:
        raise ValueError(f"Y: expected [{X.shape[0]}, p], got shape {tuple(Y.shape)}")
    if X.shape[0] < 1:
        raise ValueError("X: need at least one sample")
    if not torch.isfinite(X).all():
        raise ValueError("X: contains NaN or inf")
    if not torch.isfinite(Y).all():
        raise ValueError("Y: contains NaN or inf")
    return X, Y


def domain_box(X: Tensor, domain: Any) -> tuple[Tensor, Tensor]:
    """Box ``(lower [n], upper [n])``: the given one (checked to contain X) or X's bounding box
    (a zero-width axis is widened by 0.5 on each side)."""
    if domain is None or isinstance(domain, str):
        lo, hi = X.amin(0), X.amax(0)
        flat = hi - lo <= 1e-12 * (1 + hi.abs())
        return torch.where(flat, lo - 0.5, lo), torch.where(flat, hi + 0.5, hi)
    lo, hi = (domain.lower, domain.upper) if hasattr(domain, "lower") else domain
    lo = torch.as_tensor(lo, dtype=_F64).reshape(-1)
    hi = torch.as_tensor(hi, dtype=_F64).reshape(-1)
    if lo.shape != (X.shape[1],) or hi.shape != lo.shape or not bool((hi > lo).all()):
        raise ValueError(f"domain: expected lower < upper, each of shape [{X.shape[1]}]")
    if bool(((X < lo) | (X > hi)).any()):
        raise ValueError("X: some samples lie outside the given domain")
    return lo, hi


def fit_weights(vertices: Tensor, idx: Tensor, lam: Tensor, Y: Tensor, ridge: float = 0.0,
                prior: Tensor | None = None) -> Tensor:
    """Least-squares vertex weights ``[nv, p]`` for the nodal basis (sec. 3.1.1: "weights by
    least squares").

    Sample i has basis values ``lam [N, n+1]`` at vertices ``idx [N, n+1]`` of ``vertices
    [nv, n]``. Solves the normal equations ``(Phi'Phi + a I) W = Phi'Y + a prior`` (Phi sparse,
    n+1 nonzeros per row, ``a = ridge * mean diag(Phi'Phi)``) by Cholesky with one step of
    iterative refinement; dense up to 1000 vertices, scipy sparse beyond (a sparse LU for
    n <= 3, Jacobi-preconditioned conjugate gradients warm-started at ``prior`` for n >= 4,
    where LU factors fill in). In the adaptive loop
    ``prior`` is the previous model's value at each vertex, so a vertex with too few samples in
    its star keeps the value the coarser model gave it instead of extrapolating noise (a
    documented regularisation; ``ridge = 0`` is plain least squares, minimum-norm if rank
    deficient).
    """
    nv = vertices.shape[0]
    p = Y.shape[1]
    n1 = idx.shape[1]
    rows = idx[:, :, None].expand(-1, n1, n1).reshape(-1)
    cols = idx[:, None, :].expand(-1, n1, n1).reshape(-1)
    vals = (lam[:, :, None] * lam[:, None, :]).reshape(-1)
    rhs = torch.zeros(nv, p, dtype=_F64).index_add_(
        0, idx.reshape(-1), (lam[..., None] * Y[:, None, :]).reshape(-1, p))
    if ridge > 0:
        diag = torch.zeros(nv, dtype=_F64).index_add_(0, idx.reshape(-1), lam.reshape(-1) ** 2)
        a = ridge * float(diag.sum()) / max(1, int((diag > 0).sum()))
        ar = torch.arange(nv)
        rows, cols = torch.cat([rows, ar]), torch.cat([cols, ar])
        vals = torch.cat([vals, torch.full((nv,), a, dtype=_F64)])
        if prior is not None:
            rhs = rhs + a * prior
    if nv <= 1000:
        G = torch.zeros(nv, nv, dtype=_F64)
        G.index_put_((rows, cols), vals, accumulate=True)
        L, info = torch.linalg.cholesky_ex(G)
        if int(info) == 0:
            W = torch.cholesky_solve(rhs, L)
            W = W + torch.cholesky_solve(rhs - G @ W, L)  # iterative refinement
        else:  # rank deficient (too few samples): minimum-norm least squares
            W = torch.linalg.lstsq(G, rhs, driver="gelsd").solution
        return W
    import numpy as np
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    Gs = sp.csc_matrix((vals.numpy(), (rows.numpy(), cols.numpy())), shape=(nv, nv))
    b = rhs.numpy()
    if n1 > 4 and ridge > 0:  # n >= 4: direct factors fill in; Jacobi-preconditioned CG
        d = Gs.diagonal()
        Minv = sp.diags(1.0 / np.where(d > 0, d, 1.0))
        x0 = None if prior is None else prior.numpy()
        cols_out = []
        for j in range(p):
            xj, info = spla.cg(Gs, b[:, j], x0=None if x0 is None else x0[:, j], rtol=1e-12,
                               atol=0.0, maxiter=20 * nv, M=Minv)
            cols_out.append(xj)
        return torch.from_numpy(np.stack(cols_out, 1))
    try:
        solve = spla.factorized(Gs)
        W = np.stack([solve(b[:, j]) for j in range(p)], 1)
        W = W + np.stack([solve((b - Gs @ W)[:, j]) for j in range(p)], 1)
    except RuntimeError:  # singular: least squares
        W = np.stack([spla.lsqr(Gs, b[:, j], atol=1e-14, btol=1e-14)[0] for j in range(p)], 1)
    return torch.from_numpy(W)


def fit_partition(
    X: Any, Y: Any, vertices: Tensor, simplices: Tensor, ridge: float = 0.0,
    outside: str = "error",
) -> SCPLNN:
    """Least-squares SCPLNN on a given conforming partition (no splitting).

    X ``[N, n]``, Y ``[N, p]``; vertices ``[nv, n]``, simplices ``[M, n+1]`` tiling a box.
    With ``ridge=0`` and enough samples (each vertex's star sampled) the solution is the exact
    least-squares one; a continuous PWL function on that partition is recovered exactly.
    """
    X, Y = as_xy(X, Y)
    model = SCPLNN(vertices, simplices, torch.zeros(vertices.shape[0], Y.shape[1]),
                   outside=outside)
    s, inside = model.locate(X)
    if not bool(inside.all()):
        raise ValueError("X: some samples lie outside the partition")
    Bm = model.bary[s]
    lam = (Bm[..., :-1] @ X[..., None]).squeeze(-1) + Bm[..., -1]
    W = fit_weights(model.vertices, model.simplices[s], lam, Y, ridge)
    with torch.no_grad():
        model.weight.copy_(W)
    return model


def _eps_tensor(eps: Any, p: int) -> Tensor:
    try:
        e = torch.as_tensor(eps, dtype=_F64).reshape(-1)
    except (TypeError, ValueError, RuntimeError):  # a string, None, a ragged list: named below
        e = torch.full((0,), float("nan"), dtype=_F64)
    if e.numel() == 1:
        e = e.expand(p).clone()
    if e.shape != (p,) or not bool((e > 0).all()) or not torch.isfinite(e).all():
        raise ValueError(
            f"eps: expected a positive number or one per output ({p} output"
            f"{'s' if p != 1 else ''}), got {eps}"
        )
    return e


def default_max_regions(n: int) -> int:
    """Default region cap for n inputs: ``10,000 * max(1, n! / 2)``. A shape-regular
    triangulation has about n! / 2 simplices per vertex (Kuhn: n! per grid cell), so this caps
    the *vertices* (the fitted parameters) at a few thousand in every dimension."""
    return 10_000 * max(1, math.factorial(n) // 2)


def fit_scplnn(
    X: Any,
    Y: Any,
    eps: Any,
    max_regions: int | None = None,
    domain: Any = None,
    *,
    max_rounds: int = 200,
    ridge: float | None = None,
    snap: float | None = None,
    mark: float = 0.0,
    rule: str = "rivara",
    edge_clip: float = 0.5,
    outside: str = "error",
    progress: bool | None = None,
    vertex_fn: Callable[[Tensor], Tensor] | None = None,
    region_bound: Callable[[Tensor, Tensor], Tensor] | None = None,
    holdout: float = 0.1,
    seed: int = 0,
    degenerate: str = "error",
) -> tuple[SCPLNN, FitReport]:
    """Fit an SCPLNN to samples X ``[N, n]`` (or [N]), Y ``[N, p]`` (or [N]) by adaptive
    splitting (Wang et al. 2009, sec. 3.1.2: least squares, split the regions whose error exceeds
    eps).

    Args:
        eps: target max absolute training error, a number or one per output ``[p]``.
        max_regions: stop splitting once the partition has this many simplices (the last split
            may overshoot by the children of one split); default `default_max_regions`
            (10,000 in 1-D/2-D, growing like n! / 2).
        domain: ``None`` (bounding box of X; for n > 5 a simplex containing it), a box
            ``(lower, upper)`` / Interval containing X, ``"box"`` or ``"simplex"``.
        max_rounds: cap on refit rounds.
        ridge: relative weight pulling each vertex towards the previous round's model (see
            `fit_weights`); matters only for vertices with few samples. Default 0.01 for
            ``rule="rivara"``, 0.1 for the other rules.
        snap: barycentric threshold of the split rule (see `Refiner`); default
            0.5 / (n + 1).
        rule: ``"rivara"`` (default: conforming longest-edge bisection of every region above
            eps, `BisectionRefiner`, starting from the Kuhn
            triangulation of the box; no slivers), ``"interior"`` (Wang et al. 2009: connect the
            sample to the region's vertices when it is well inside, else cut the longest edge; the
            earlier default), ``"edge"`` (always the longest edge of the sample's
            region) or ``"paper"`` (always connect the sample to the vertices; stalls on
            slivers).
        edge_clip: where the longest edge is cut: the sample's projection clipped to
            ``[edge_clip, 1 - edge_clip]`` (0.5: the midpoint).
        mark: split only regions whose error exceeds ``max(eps, mark * current max error)``
            each round (0: every region above eps, as in Wang et al. 2009).
        outside: policy of the returned model for points outside the domain.
        progress: tqdm progress bar (None: shown only for fits longer than 2 s on a terminal).
        vertex_fn: known function ``[k, n] -> [k, p]``; when given, the vertex weights are its
            values at the vertices (interpolation) instead of least squares (a deviation from
            sec. 3.1.1 for functions known in closed form: no vertex is extrapolated from
            samples that do not pin it down).
        region_bound: ``(simplex vertices [M, n+1, n], weights [M, n+1, p]) -> [M, p]``, an
            upper bound of the error on each whole simplex (e.g. vertex mismatch plus a
            curvature term); when given, every region whose bound is not below eps is also
            split (bisection of its longest edge) and ``converged`` requires it everywhere.

        holdout: fraction of the samples (``rule="rivara"`` only; at least 10 samples, else
            none) left out of the least squares while splitting. A region is also split when a
            held-out sample in it misses eps and the region holds at least n + 1 training
            samples (so the mesh is refined where the error *between* samples is large, not
            where the data are too sparse to pin the pieces down). Once every sample is within
            eps the held-out error of that model is recorded (``report.heldout_max_error``),
            then the model is refitted on all samples and split further if any sample still
            misses eps. 0 disables.
        seed: seed of the held-out draw (the fit is deterministic).
        degenerate: samples in a lower-dimensional affine subspace (collinear 2-D data, a
            constant input): ``"error"`` (ValueError naming X) or ``"warn"`` (fit anyway, the
            model is unconstrained off the subspace; recorded in ``report.warnings``). One
            distinct sample without a ``domain`` is always an error.

    Duplicate X with conflicting Y: eps is unreachable where half the spread of Y at one
    point exceeds eps; those samples are not split on, the fit stops and
    ``report.warnings`` / ``stop_reason`` say so (``converged`` is False).

    Returns ``(model, report)``; ``report.converged`` says whether max error < eps at every
    sample (and the certified bound, when ``region_bound`` is given).
    The loop is made of many small tensor operations, so it runs with one intra-op thread
    (restored afterwards): on a loaded 2-core machine thread hand-offs cost more than the work;
    it also makes the result independent of the caller's thread count.
    """
    if rule not in ("rivara", "interior", "edge", "paper"):
        raise ValueError(f"rule: expected 'rivara', 'interior', 'edge' or 'paper', got {rule!r}")
    if not 0 <= holdout < 1:
        raise ValueError(f"holdout: expected a fraction in [0, 1), got {holdout}")
    if degenerate not in ("error", "warn"):
        raise ValueError(f"degenerate: expected 'error' or 'warn', got {degenerate!r}")
    if ridge is None:
        ridge = 0.01 if rule == "rivara" else 0.1
    opts = _Opts(holdout=holdout if rule == "rivara" else 0.0, seed=seed, degenerate=degenerate)
    with single_thread(blas=True):
        return _fit(X, Y, eps, max_regions, domain, max_rounds, ridge, snap, mark, rule,
                    edge_clip, outside, progress, _Known(vertex_fn, region_bound), opts)


@dataclass
class _Opts:
    holdout: float = 0.0
    seed: int = 0
    degenerate: str = "error"


def _check_samples(X: Tensor, Y: Tensor, e: Tensor, domain: Any, degenerate: str
                   ) -> tuple[list[str], Tensor, Tensor]:
    """Degenerate and conflicting data. Returns (warnings, unreachable [N] bool, mid [N, p],
    group [N]): samples whose duplicates (same X) have a Y spread with half-range >= eps, where
    no model meets eps; the mean of Y at each sample's X (the least-squares value there); the
    index of each sample's distinct X."""
    N, n = X.shape
    warns: list[str] = []
    uniq, inv = torch.unique(X, dim=0, return_inverse=True)
    G = uniq.shape[0]
    if G == 1 and domain is None:
        raise ValueError(f"X: all {N} samples are the same point {uniq[0].tolist()}; a domain "
                         "cannot be inferred from one point (pass domain=(lower, upper))")
    if G >= 2 and n >= 2:
        sv = torch.linalg.svdvals(uniq - uniq.mean(0))
        rank = int((sv > 1e-9 * sv[0]).sum())
        if rank < n:
            msg = (f"X: the samples lie in a {rank}-dimensional affine subspace of R^{n} "
                   "(e.g. collinear points in 2-D, or a constant input); the model is not "
                   "determined off that subspace")
            if degenerate == "error":
                raise ValueError(msg + " (pass degenerate='warn' to fit anyway)")
            warns.append(msg)
    unreachable = torch.zeros(N, dtype=torch.bool)
    mid = Y
    if G < N:
        p = Y.shape[1]
        big = torch.full((G, p), -math.inf, dtype=_F64)
        ymax = big.scatter_reduce(0, inv[:, None].expand(-1, p), Y, "amax")
        ymin = (-big).scatter_reduce(0, inv[:, None].expand(-1, p), Y, "amin")
        half = 0.5 * (ymax - ymin)
        bad_g = (half >= e).any(-1)
        if bool(bad_g.any()):
            unreachable = bad_g[inv]
            cnt = torch.bincount(inv, minlength=G).to(_F64)[:, None]
            mid = (torch.zeros(G, p, dtype=_F64).index_add_(0, inv, Y) / cnt)[inv]
            warns.append(f"eps unreachable at {int(unreachable.sum())} samples: "
                         f"{int(bad_g.sum())} distinct X values carry conflicting Y "
                         f"(half-range of Y up to {float((half / e).amax()):.3g} eps); "
                         "no model can meet eps there")
    return warns, unreachable, mid, inv


@dataclass
class _Known:
    """Optional knowledge of the target: its values at vertices, a per-simplex error bound."""

    vertex_fn: Callable[[Tensor], Tensor] | None = None
    region_bound: Callable[[Tensor, Tensor], Tensor] | None = None

    def weights(self, V: Tensor, p: int) -> Tensor:
        """Vertex values ``[nv, p]`` of the known function."""
        with torch.no_grad():
            W = torch.as_tensor(self.vertex_fn(V), dtype=_F64).reshape(V.shape[0], p)
        if not bool(torch.isfinite(W).all()):
            raise ValueError("vertex_fn: returned NaN or inf")
        return W

    def bound(self, V: Tensor, S: Tensor, W: Tensor) -> Tensor | None:
        """``region_bound`` ``[M, p]`` of simplices S [M, n+1] (None if not given)."""
        if self.region_bound is None:
            return None
        with torch.no_grad():
            return torch.as_tensor(self.region_bound(V[S], W[S]), dtype=_F64).reshape(
                S.shape[0], W.shape[1])


def _fit(X: Any, Y: Any, eps: Any, max_regions: int | None, domain: Any, max_rounds: int,
         ridge: float, snap: float, mark: float, rule: str, edge_clip: float, outside: str,
         progress: bool | None, known: _Known, opts: _Opts
         ) -> tuple[SCPLNN, FitReport]:
    t0 = time.perf_counter()
    X, Y = as_xy(X, Y)
    N, n = X.shape
    p = Y.shape[1]
    e = _eps_tensor(eps, p)
    if max_regions is None:
        max_regions = default_max_regions(n)
    if max_regions < 1:
        raise ValueError(f"max_regions: must be >= 1, got {max_regions}")
    if domain is not None and isinstance(domain, str) and domain not in ("box", "simplex"):
        raise ValueError(f"domain: expected None, 'box', 'simplex' or (lower, upper), got {domain}")
    given = None if isinstance(domain, str) else domain
    warns, unreachable, mid, group = _check_samples(X, Y, e, given, opts.degenerate)
    for w in warns:
        _warnings.warn(f"fit_scplnn: {w}", stacklevel=3)
    lo, hi = domain_box(X, domain)
    snap = 0.5 / (n + 1) if snap is None else float(snap)
    use_box = domain == "box" or (not isinstance(domain, str) and (domain is not None or
                                                                    n <= BOX_MAX_DIM))

    # Step 1: one affine function by least squares
    Xa = torch.cat([X, torch.ones(N, 1, dtype=_F64)], 1)
    coef = torch.linalg.lstsq(Xa, Y, driver="gelsd").solution  # [n+1, p]
    score = ((Y - Xa @ coef).abs() / e).amax(-1)
    history = [(1, float(score.max()))]
    affine_ok = float(score.max()) < 1 and known.vertex_fn is None and known.region_bound is None
    ctx = _Ctx(warnings=warns, unreachable=unreachable, mid=mid, group=group)
    if affine_ok:
        V, S = grid_partition(lo, hi, 1) if use_box else (simplex_domain(lo, hi),
                                                          torch.arange(n + 1)[None])
        return _finish(V, S, coef, None, X, Y, e, t0, 0, "affine fit below eps", history,
                       outside, use_box, ctx=ctx)
    if rule == "rivara":
        return _bisection_loop(X, Y, e, lo, hi, use_box, coef, t0, max_regions, max_rounds,
                               ridge, mark, outside, progress, history, known, opts, ctx)
    if use_box:
        if affine_ok:
            V, S = grid_partition(lo, hi, 1)
            return _finish(V, S, coef, None, X, Y, e, t0, 0, "affine fit below eps", history,
                           outside, True)
        # Step 2: connect the max-error sample to the domain's vertices
        p1 = X[int(score.argmax())]
        u = (p1 - lo) / (hi - lo)  # a p1 near the boundary would make sliver cones: snap it
        u = torch.where(u < snap, 0.0, torch.where(u > 1 - snap, 1.0, u))
        V, S = cone_partition(lo, hi, lo + u * (hi - lo))
        ref = Refiner(V, S, snap=snap, rule=rule, edge_clip=edge_clip)
    else:
        Vd = simplex_domain(lo, hi)
        S0 = torch.arange(n + 1)[None]
        if affine_ok:
            return _finish(Vd, S0, coef, None, X, Y, e, t0, 0, "affine fit below eps", history,
                           outside, False)
        ref = Refiner(Vd, S0, snap=snap, rule=rule, edge_clip=edge_clip)
        ref.split(X[int(score.argmax())], 0)
    assign = ref.relocate(X, ref.alive.nonzero().flatten())
    prior = torch.cat([ref.V, torch.ones(ref.V.shape[0], 1, dtype=_F64)], 1) @ coef
    return _adaptive_loop(ref, assign, prior, X, Y, e, t0, max_regions, max_rounds, ridge, mark,
                          outside, use_box, progress, history, known, ctx)


@dataclass
class _Ctx:
    """Data checks carried to the report: warnings and the unreachable (conflicting) samples."""

    warnings: list[str] = field(default_factory=list)
    unreachable: Tensor | None = None
    mid: Tensor | None = None  # [N, p] mean of Y at each sample's X
    group: Tensor | None = None  # [N] index of each sample's distinct X
    heldout: Tensor | None = None  # [p] held-out max error
    n_heldout: int = 0


def _adaptive_loop(ref: Refiner, assign: Tensor, prior: Tensor, X: Tensor, Y: Tensor,
                   e: Tensor, t0: float, max_regions: int, max_rounds: int, ridge: float,
                   mark: float, outside: str, use_box: bool, progress: bool | None,
                   history: list, known: _Known, ctx: _Ctx) -> tuple[SCPLNN, FitReport]:
    """Step 3 of sec. 3.1.2: refit, split every region above eps at its max-error sample."""
    from tqdm.auto import tqdm

    bar = tqdm(total=None, disable=(not progress) if progress is not None else None,
               delay=0 if progress else 2.0, desc="fit_scplnn", unit="round", leave=False)
    reason, rounds = "max_rounds reached", 0
    W = None
    for _ in range(max_rounds):
        rounds += 1
        V, S_all = ref.V, ref.S
        idx = S_all[assign]
        lam = ref.lam(X, assign)
        if known.vertex_fn is None:
            W = fit_weights(V, idx, lam, Y, ridge, prior)
        else:
            W = known.weights(V, Y.shape[1])
        prior = W
        resid = (lam[..., None] * W[idx]).sum(1) - Y
        score = (resid.abs() / e).amax(-1)  # [N] error in units of eps
        if ctx.unreachable is not None and bool(ctx.unreachable.any()):
            score = torch.where(ctx.unreachable, 0.0, score)  # conflicting duplicates: no split
        live = ref.alive.nonzero().flatten()
        rb = known.bound(V, S_all[live], W)
        rscore = None if rb is None else (rb / e).amax(-1)  # [M] region bound in units of eps
        worst = max(float(score.max()), 0.0 if rscore is None else float(rscore.max()))
        history.append((ref.n_simplices, worst))
        bar.update(1)
        bar.set_postfix(regions=ref.n_simplices, max_err_over_eps=f"{worst:.3g}")
        if worst < 1:
            reason = "max error below eps"
            break
        if ref.n_simplices >= max_regions:
            reason = "max_regions reached"
            break
        level = max(1.0, mark * worst)
        cands = _split_candidates(assign, score, ref.S.shape[0], level)
        bad = None
        if rscore is not None:  # regions whose whole-simplex bound fails: longest-edge midpoint
            bad = live[rscore >= level]
            bad = bad[torch.argsort(rscore[rscore >= level], descending=True)]
            is_bad = torch.zeros(ref.S.shape[0], dtype=torch.bool)
            is_bad[bad] = True
            cands = cands[~is_bad[assign[cands]]]  # bisected anyway: no extra sample split
        jobs = [(q, -1) for q in cands.tolist()]  # sample q: split its region at q
        if bad is not None:
            jobs += [(-1, s) for s in bad.tolist()]
        if not jobs:
            reason = "no splittable region left (max-error samples at vertices)"
            break
        for q, s in jobs:
            s = int(assign[q]) if q >= 0 else s  # a sample's current region (may be a child)
            if not bool(ref.alive[s]):
                continue  # already split this round through a shared face
            out = ref.split(X[q] if q >= 0 else _longest_edge_midpoint(ref, s), s)
            if out is None:
                continue
            removed, children = out
            new_prior = ref.last_weights @ prior[ref.last_face]  # current model at the new vertex
            prior = torch.cat([prior, new_prior[None]], 0)
            moved = torch.isin(assign, removed).nonzero().flatten()
            assign[moved] = ref.relocate(X[moved], children)
            if ref.n_simplices >= max_regions:
                break
    bar.close()
    if W is None or W.shape[0] != ref.V.shape[0]:  # split after the last fit: refit
        W = (fit_weights(ref.V, ref.S[assign], ref.lam(X, assign), Y, ridge, prior)
             if known.vertex_fn is None else known.weights(ref.V, Y.shape[1]))
    V, S, _ = ref.compact()
    return _finish(V, S, None, W, X, Y, e, t0, rounds, reason, history, outside, use_box, known,
                   ctx)


def _bisection_loop(X: Tensor, Y: Tensor, e: Tensor, lo: Tensor, hi: Tensor, use_box: bool,
                    coef: Tensor, t0: float, max_regions: int, max_rounds: int, ridge: float,
                    mark: float, outside: str, progress: bool | None, history: list,
                    known: _Known, opts: _Opts, ctx: _Ctx) -> tuple[SCPLNN, FitReport]:
    """Wang et al. 2009, sec. 3.1.2 Step 3 with conforming longest-edge bisection
    (``rule="rivara"``).

    Start: the Kuhn triangulation of the box (n! simplices) or the enclosing simplex. Each
    round: locate all samples, least-squares vertex weights on the training samples (or
    ``vertex_fn``), then bisect every region holding a sample whose error is >= eps (all
    regions sharing the face the sample lies on, when it lies on one), every region whose
    held-out sample misses eps while it holds >= n + 1 training samples, and every region whose
    ``region_bound`` is >= eps. Phase 1 uses a held-out part of the samples; phase 2 refits on
    all of them (see `fit_scplnn`)."""
    from tqdm.auto import tqdm

    N, n = X.shape
    if use_box:
        V0, S0 = grid_partition(lo, hi, 1)
    else:
        V0, S0 = simplex_domain(lo, hi), torch.arange(n + 1)[None]
    ref = BisectionRefiner(V0, S0, scale=hi - lo, min_edge=1e-7)
    prior = torch.cat([V0, torch.ones(V0.shape[0], 1, dtype=_F64)], 1) @ coef
    train, k_hold = _holdout(N, n, opts, ctx)
    unreach = ctx.unreachable if ctx.unreachable is not None else torch.zeros(N, dtype=torch.bool)
    bar = tqdm(total=None, disable=(not progress) if progress is not None else None,
               delay=0 if progress else 2.0, desc="fit_scplnn", unit="round", leave=False)
    reason, rounds, phase = "max_rounds reached", 0, 1 if k_hold else 2
    W = prior
    Xn = X.numpy()
    gs = PointLocator(V0, S0, barycentric_matrices(V0, S0)).locate(X)[0].numpy()
    while rounds < max_rounds:
        rounds += 1
        V, S = ref.V, ref.S
        # new vertices: the current model there (midpoint of the bisected edge)
        prior = _extend_prior(prior, ref.parents)
        sid, lam = _locate_tracked(ref, Xn, gs)
        idx = S[sid]
        if known.vertex_fn is None:
            W = fit_weights(V, idx[train], lam[train], Y[train], ridge, prior)
        else:
            W = known.weights(V, Y.shape[1])
        prior = W
        resid = (lam[..., None] * W[idx]).sum(1) - Y
        score = (resid.abs() / e).amax(-1)  # [N] in units of eps
        if bool(unreach.any()):  # conflicting duplicates: aim at the mean of their Y
            score = torch.where(unreach, ((resid + Y - ctx.mid).abs() / e).amax(-1), score)
        rb = known.bound(V, S, W)
        rscore = None if rb is None else (rb / e).amax(-1)
        worst = max(float(score.max()), 0.0 if rscore is None else float(rscore.max()))
        history.append((S.shape[0], worst))
        bar.update(1)
        bar.set_postfix(regions=S.shape[0], max_err_over_eps=f"{worst:.3g}", phase=phase)
        level = max(1.0, mark * worst)
        bad = score >= level
        if phase == 1:  # held-out samples count only where the region is resolvable
            cnt = torch.bincount(sid[train], minlength=S.shape[0])
            bad = bad & (train | (cnt[sid] >= n + 1))
        marked_local = _marked(ref, sid, lam, idx, bad, rscore, level)
        if not marked_local:
            if phase == 1:  # phase 1 done: record the held-out error, refit on all samples
                ctx.heldout = resid[~train].abs().amax(0)
                ctx.n_heldout = k_hold
                train = torch.ones(N, dtype=torch.bool)
                phase = 2
                continue
            reason = ("no splittable region left" if worst >= 1 else "max error below eps"
                      if not bool(unreach.any()) else
                      "max error below eps where reachable, eps of the mean Y at duplicates")
            break
        if ref.n_simplices >= max_regions:
            reason = "max_regions reached"
            break
        if _refine_worst_first(ref, marked_local, sid, score, rscore, max_regions) == 0:
            reason = "no splittable region left (regions at the minimum edge length)"
            if phase == 1:
                ctx.heldout = resid[~train].abs().amax(0)
                ctx.n_heldout = k_hold
                train = torch.ones(N, dtype=torch.bool)
                phase = 2
                continue
            break
    bar.close()
    if phase == 1:  # stopped by a cap in phase 1: held-out error now, then refit on all
        ctx.heldout = resid[~train].abs().amax(0)
        ctx.n_heldout = k_hold
    V, S = ref.V, ref.S
    if prior.shape[0] < V.shape[0] or phase == 1:
        prior = _extend_prior(prior, ref.parents)
        if known.vertex_fn is None:
            sid, lam = _locate_tracked(ref, Xn, gs)
            W = fit_weights(V, S[sid], lam, Y, ridge, prior)
        else:
            W = known.weights(V, Y.shape[1])
    return _finish(V, S, None, W, X, Y, e, t0, rounds, reason, history, outside, use_box, known,
                   ctx)


def _holdout(N: int, n: int, opts: _Opts, ctx: _Ctx) -> tuple[Tensor, int]:
    """The training mask ``[N]`` of phase 1 and the number of held-out samples: whole groups of
    duplicates (distinct X values) drawn by ``opts.seed`` up to ``opts.holdout * N`` samples;
    none (all True, 0) when that leaves too few samples on either side."""
    k_hold = int(opts.holdout * N)
    train = torch.ones(N, dtype=torch.bool)
    if k_hold < 10 or N - k_hold < n + 2:
        return train, 0
    grp = ctx.group if ctx.group is not None else torch.arange(N)
    G = int(grp.max()) + 1
    perm = torch.randperm(G, generator=torch.Generator().manual_seed(opts.seed))
    size = torch.bincount(grp, minlength=G)[perm]
    held = perm[: int((torch.cumsum(size, 0) < k_hold).sum()) + 1]
    is_held = torch.zeros(G, dtype=torch.bool)
    is_held[held] = True
    train = ~is_held[grp]
    k_hold = int((~train).sum())
    if k_hold == N or N - k_hold < n + 2:
        train[:] = True
        k_hold = 0
    return train, k_hold


def _finish(V: Tensor, S: Tensor, coef: Tensor | None, W: Tensor | None, X: Tensor, Y: Tensor,
            e: Tensor, t0: float, rounds: int, reason: str, history: list, outside: str,
            box: bool, known: _Known | None = None, ctx: _Ctx | None = None
            ) -> tuple[SCPLNN, FitReport]:
    """Build the model (weights W, or the affine ``coef`` at the vertices) and the report."""
    if W is None:
        W = torch.cat([V, torch.ones(V.shape[0], 1, dtype=_F64)], 1) @ coef
    model = SCPLNN(V, S, W, outside=outside, box_domain=box)
    used = torch.zeros(V.shape[0], dtype=torch.bool)
    used[S.reshape(-1)] = True
    if not bool(used.all()):  # drop vertices left unused (e.g. a snapped corner)
        newid = torch.cumsum(used.long(), 0) - 1
        model = SCPLNN(V[used], newid[S], W[used], outside=outside, box_domain=box)
    with torch.no_grad():
        err = (model(X, outside="clamp") - Y).abs()
    rb = None if known is None else known.bound(model.vertices, model.simplices, model.weight)
    bmax = None if rb is None else rb.amax(0)
    report = FitReport(
        regions=model.n_regions, vertices=model.vertices.shape[0],
        parameters=model.n_parameters(), max_error=err.amax(0), rms_error=err.pow(2).mean(0).sqrt(),
        eps=e, converged=bool((err.amax(0) < e).all()) and (bmax is None or bool((bmax < e).all())),
        rounds=rounds, seconds=time.perf_counter() - t0, stop_reason=reason, history=history,
        bound_max=bmax)
    if ctx is not None:
        report.warnings = list(ctx.warnings)
        report.heldout_max_error = ctx.heldout
        report.heldout_samples = ctx.n_heldout
        if ctx.unreachable is not None and bool(ctx.unreachable.any()):
            report.stop_reason += "; eps unreachable at conflicting duplicate samples"
    return model, report
