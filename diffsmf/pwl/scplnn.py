"""The SCPLNN model: a continuous piecewise-linear function on a simplicial partition.

Wang et al. 2009, sec. 3.1.1 writes the model as a weighted sum of max-min basis functions (eq.
11-15), one per region, whose weights are fitted by least squares. We store the same space of
functions in the *nodal* (hat) basis: one weight vector per partition vertex, ``f(x) = sum_j
lam_j(x) W[v_j]`` with ``lam`` the barycentric coordinates of x in the simplex containing it. Both
bases span exactly the continuous functions that are affine on every simplex of the partition (the
nodal basis has one function per vertex, the dimension of that space); the hat function of a
vertex whose star is convex is itself a max-min function ``max(0, min_s lam_v^s(x))`` (eq. 12
with a = 0), see `SCPLNN.maxmin_basis`, and every fitted model can be exported in the
max-min (lattice) form of eq. 12 with `SCPLNN.lattice_eval`. The nodal basis is used for
fitting because its least-squares matrix is sparse (n+1 nonzeros per sample).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from diffsmf.pwl._threads import single_thread
from diffsmf.pwl.partition import PointLocator, barycentric_matrices

__all__ = ["SCPLNN", "Regions"]

_OUTSIDE = ("error", "clamp", "extrapolate")
_F64 = torch.float64


def _tracing() -> bool:
    """Inside torch.compile or a torch.func transform (vmap, grad, jacrev, ...)."""
    from torch._C._functorch import peek_interpreter_stack

    return bool(torch.compiler.is_compiling()) or peek_interpreter_stack() is not None


class Regions(NamedTuple):
    """Regions of an SCPLNN: simplex ``vertices [M, n+1, n]`` and affine maps ``A [M, p, n]``,
    ``b [M, p]`` with ``f(x) = A_k x + b_k`` on simplex k."""

    vertices: Tensor
    A: Tensor
    b: Tensor


class SCPLNN(nn.Module):
    """Continuous piecewise-linear model ``R^n -> R^p`` on a conforming simplicial partition.

    Args:
        vertices: ``[nv, n]`` partition vertices (buffer).
        simplices: ``[M, n+1]`` vertex indices of each simplex (buffer).
        weight: ``[nv, p]`` value of the model at each vertex (``nn.Parameter``); zeros if None.
        n_outputs: p when ``weight`` is None.
        outside: what ``forward`` does with points outside the domain: ``"error"`` (ValueError),
            ``"clamp"`` (evaluate at the nearest domain point: box clamp for box domains,
            clipped barycentric coordinates otherwise; keeps continuity and the Lipschitz
            bound), ``"extrapolate"`` (extend the affine piece of the nearest boundary simplex;
            may be discontinuous outside the domain).
        box_domain: whether the partition tiles the box ``[vertices.min, vertices.max]``.
        atol: relative tolerance (in barycentric coordinates) for "inside the domain".
    """

    #: a model fitted to samples: a filter on it bounds the fit, not the plant, unless its
    #: certified error is added (`diffsmf.pwl.as_system`; `diffsmf.systems.model.uncertified_fit`)
    fitted_model = True

    def __init__(
        self,
        vertices: Tensor,
        simplices: Tensor,
        weight: Tensor | None = None,
        n_outputs: int = 1,
        outside: str = "error",
        box_domain: bool = True,
        atol: float = 1e-9,
        input_names: list[str] | None = None,
        output_names: list[str] | None = None,
    ):
        super().__init__()
        vertices = torch.as_tensor(vertices, dtype=_F64)
        simplices = torch.as_tensor(simplices, dtype=torch.long)
        if vertices.dim() != 2:
            raise ValueError(f"vertices: expected [nv, n], got shape {tuple(vertices.shape)}")
        n = vertices.shape[1]
        if simplices.dim() != 2 or simplices.shape[1] != n + 1:
            raise ValueError(f"simplices: expected [M, {n + 1}], got {tuple(simplices.shape)}")
        if simplices.numel() and (simplices.min() < 0 or simplices.max() >= vertices.shape[0]):
            raise ValueError("simplices: vertex index out of range")
        if not torch.isfinite(vertices).all():
            raise ValueError("vertices: contains NaN or inf")
        if weight is None:
            weight = torch.zeros(vertices.shape[0], n_outputs, dtype=_F64)
        weight = torch.as_tensor(weight, dtype=_F64)
        if weight.dim() == 1:
            weight = weight[:, None]
        if weight.shape[0] != vertices.shape[0]:
            raise ValueError(
                f"weight: expected [{vertices.shape[0]}, p], got {tuple(weight.shape)}")
        if not bool(torch.isfinite(weight.detach()).all()):
            raise ValueError("weight: contains NaN or inf")
        if outside not in _OUTSIDE:
            raise ValueError(f"outside: must be one of {_OUTSIDE}, got {outside!r}")
        self.register_buffer("vertices", vertices.clone())
        self.register_buffer("simplices", simplices.clone())
        self.register_buffer("box_domain", torch.tensor(bool(box_domain)))
        self._box = bool(box_domain)  # Python copy: no tensor-to-bool inside forward
        self.weight = nn.Parameter(weight.clone())
        self.outside = outside
        self.atol = atol
        self.input_names = input_names
        self.output_names = output_names
        self._cache: dict[str, Any] = {}

    # ------------------------------------------------------------------ structure
    @property
    def n_inputs(self) -> int:
        return self.vertices.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.weight.shape[1]

    @property
    def n_regions(self) -> int:
        return self.simplices.shape[0]

    @property
    def lower(self) -> Tensor:
        """Lower corner ``[n]`` of the bounding box of the domain."""
        return self.vertices.amin(0)

    @property
    def upper(self) -> Tensor:
        return self.vertices.amax(0)

    def n_parameters(self) -> int:
        """Number of fitted weights (nv * p)."""
        return self.weight.numel()

    def _key(self) -> tuple:
        return (self.vertices.data_ptr(), self.vertices._version, self.simplices.data_ptr(),
                self.simplices._version, tuple(self.simplices.shape))

    def _get(self, name: str) -> Any:
        if torch.compiler.is_compiling():  # no data_ptr / cache checks inside a graph
            if name not in self._cache:
                raise RuntimeError("SCPLNN: evaluate the model once (or call prepare(); "
                                   "prepare(enclosure=True) for interval_enclosure) before "
                                   "torch.compile, so that its tables are built")
            return self._cache[name]
        if self._cache.get("key") != self._key():
            self._cache = {"key": self._key()}
        if name not in self._cache:
            if name == "bary":
                self._cache[name] = barycentric_matrices(self.vertices, self.simplices)
            elif name == "encl":
                from diffsmf.pwl.enclosure import face_tables

                self._cache[name] = face_tables(self.vertices, self.simplices)
            elif name == "locator":
                with single_thread():
                    self._cache[name] = PointLocator(self.vertices, self.simplices,
                                                     self._get("bary"))
        return self._cache[name]

    def prepare(self, enclosure: bool = False) -> SCPLNN:
        """Build the barycentric matrices and the point locator now (they are otherwise built
        on first use); needed once before ``torch.compile``. ``enclosure=True`` also builds the
        face tables of `interval_enclosure` (needed before compiling it). Returns self."""
        self._get("locator")
        if enclosure:
            self._get("encl")
        return self

    @property
    def bary(self) -> Tensor:
        """Barycentric matrices ``[M, n+1, n+1]``: ``lam = bary[k] @ [x; 1]`` on simplex k."""
        return self._get("bary")

    # ------------------------------------------------------------------ evaluation
    def locate(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Simplex index ``[N]`` and a boolean ``inside [N]`` for points x [N, n] (no grad)."""
        with single_thread():
            s, lam = self._get("locator").locate(x)
        return s, lam.amin(-1) >= -self.atol

    def _prepare(self, x: Tensor, outside: str, traced: bool = False) -> tuple[Tensor, Tensor]:
        """Apply the outside policy; return (points to evaluate [N, n], simplex ids [N])."""
        if self._box and outside == "clamp":
            x = torch.maximum(torch.minimum(x, self.upper), self.lower)
        if traced:  # no data-dependent check inside vmap / jacrev / torch.compile
            s, _ = self._get("locator").locate(x, padded=True)
            return x, s
        with single_thread():  # a loop of small ops: thread hand-offs cost more than the work
            s, lam = self._get("locator").locate(x)
        inside = lam.amin(-1) >= -self.atol
        if outside == "error" and not bool(inside.all()):
            bad = x[~inside][0].tolist()
            raise ValueError(
                f"x: {int((~inside).sum())} point(s) outside the model's domain, e.g. {bad}; "
                "use outside='clamp' or 'extrapolate'"
            )
        return x, s

    def forward(self, x: Tensor, outside: str | None = None) -> Tensor:
        """Evaluate the model: x ``[..., n]`` -> ``[..., p]``; differentiable in x and weight.
        A model with one input also takes x ``[...]`` (scalar inputs, as ``fit_scplnn`` accepts
        a 1-D X) and returns ``[..., p]``.

        f(x) = sum_j lam_j(x) W[v_j] on the simplex containing x (nodal form of eq. 11).

        Works under ``torch.func.vmap`` / ``jacrev`` / ``grad`` and ``torch.compile(fullgraph=
        True)`` (call the model once, or `prepare`, before compiling): point location is
        a fixed-shape gather, and inside those transforms the data-dependent checks are
        skipped (NaN in x is not reported and ``outside="error"`` returns the extrapolated
        value instead of raising).

        A first-order interval jet x (``diffsmf.linearize.jets.Jet``, what the guaranteed
        ``remainder="mean-value"`` evaluates a model on) gives the jet of the model from
        `interval_enclosure` (chain rule with the gradient hull; NaN bounds where the box
        leaves the domain, unless ``outside="clamp"``); a second-order jet raises ``JetError``.
        """
        outside = outside or self.outside
        if outside not in _OUTSIDE:
            raise ValueError(f"outside: must be one of {_OUTSIDE}, got {outside!r}")
        traced = _tracing()
        x = torch.as_tensor(x, dtype=self.weight.dtype)
        if self.n_inputs == 1 and (x.dim() == 0 or x.shape[-1] != 1):
            x = x[..., None]  # scalar inputs
        if x.shape[-1:] != (self.n_inputs,):
            raise ValueError(f"x: expected [..., {self.n_inputs}], got {tuple(x.shape)}")
        if not traced and not torch.isfinite(x.detach()).all():
            raise ValueError("x: contains NaN or inf")
        batch = x.shape[:-1]
        xf = x.reshape(-1, self.n_inputs)
        xe, s = self._prepare(xf, outside, traced)
        Bm = self.bary[s]  # [N, n+1, n+1]
        lam = (Bm[..., :-1] @ xe[..., None]).squeeze(-1) + Bm[..., -1]
        if outside == "clamp" and not self._box:
            lam = lam.clamp_min(0)
            lam = lam / lam.sum(-1, keepdim=True)
        W = self.weight[self.simplices[s]]  # [N, n+1, p]
        y = (lam[..., None] * W).sum(-2)
        return y.reshape(batch + (self.n_outputs,))

    def piece_eval(self, x: Tensor, simplex: Tensor) -> Tensor:
        """Affine piece of simplex ``simplex [N]`` evaluated at x [N, n] -> [N, p] (any x)."""
        Bm = self.bary[simplex]
        lam = (Bm[..., :-1] @ x[..., None]).squeeze(-1) + Bm[..., -1]
        return (lam[..., None] * self.weight[self.simplices[simplex]]).sum(-2)

    def regions(self) -> Regions:
        """Vertices ``[M, n+1, n]`` and affine maps ``A [M, p, n]``, ``b [M, p]`` per simplex.

        [A_k | b_k] = W_k^T bary_k with W_k [n+1, p] the vertex values of simplex k.
        """
        Ab = self.weight[self.simplices].transpose(-1, -2) @ self.bary  # [M, p, n+1]
        return Regions(self.vertices[self.simplices], Ab[..., :-1], Ab[..., -1])

    def lipschitz_bound(self) -> Tensor:
        """A Lipschitz constant in the 2-norm: ``max_k ||A_k||_2`` (spectral norm of the p x n
        slope of each piece). Valid on the convex domain because the model is continuous and
        affine on each simplex (any segment crosses finitely many pieces); also valid with
        ``outside='clamp'`` (clamping is 1-Lipschitz), not with ``'extrapolate'``."""
        A = self.regions().A
        return torch.linalg.matrix_norm(A, ord=2).amax()

    # ------------------------------------------------------------------ interval evaluation
    def interval_eval(self, box: Any, margin: float = 1e-9) -> Any:
        """Guaranteed range of the model over boxes: ``Interval [..., p]`` containing f(x) for
        every x in the box ``[..., n]`` (an ``Interval`` or a ``(lower, upper)`` pair).

        For each simplex that may meet the box (bounding boxes overlap and no barycentric
        coordinate is negative on the whole box), the affine piece is bounded over the box
        intersected with the simplex's bounding box, and also by the simplex's vertex values
        (the exact range of an affine function on a simplex); the tighter of the two is taken,
        then the union over the candidate simplices. This is a valid bound (exact when the box
        contains whole simplices), widened outward by ``margin * (1 + max |W|)`` to cover the
        rounding of `forward`. Outside the domain: ``outside='clamp'`` clamps the box,
        otherwise ValueError.
        """
        from diffsmf.sets.interval import Interval

        lo, hi = (box.lower, box.upper) if hasattr(box, "lower") else box
        lo = torch.as_tensor(lo, dtype=_F64)
        hi = torch.as_tensor(hi, dtype=_F64)
        lo, hi = torch.broadcast_tensors(lo, hi)
        if lo.shape[-1:] != (self.n_inputs,):
            raise ValueError(f"box: expected [..., {self.n_inputs}], got {tuple(lo.shape)}")
        if not (torch.isfinite(lo).all() and torch.isfinite(hi).all()) or bool((lo > hi).any()):
            raise ValueError("box: bounds must be finite with lower <= upper")
        if not bool(self.box_domain):
            raise ValueError("box: interval_eval needs a box domain (fit with a box domain)")
        tol = self.atol * (self.upper - self.lower)
        if bool(((lo < self.lower - tol) | (hi > self.upper + tol)).any()):
            if self.outside != "clamp":
                raise ValueError("box: extends outside the model's domain; use outside='clamp'")
        lo = torch.maximum(torch.minimum(lo, self.upper), self.lower)
        hi = torch.maximum(torch.minimum(hi, self.upper), self.lower)
        batch = lo.shape[:-1]
        l2, h2 = lo.reshape(-1, self.n_inputs), hi.reshape(-1, self.n_inputs)
        outs_lo, outs_hi = [], []
        M = max(self.n_regions, 1)
        step = max(1, 2_000_000 // (M * (self.n_inputs + 1 + self.n_outputs)))
        for i in range(0, l2.shape[0], step):
            a, b = self._interval_chunk(l2[i : i + step], h2[i : i + step])
            outs_lo.append(a)
            outs_hi.append(b)
        pad = margin * (1 + self.weight.detach().abs().max())
        ylo = torch.cat(outs_lo).reshape(batch + (self.n_outputs,)) - pad
        yhi = torch.cat(outs_hi).reshape(batch + (self.n_outputs,)) + pad
        return Interval(ylo, yhi)

    def _interval_chunk(self, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
        """lo, hi [B, n] -> range bounds [B, p] (see `interval_eval`)."""
        V = self.vertices[self.simplices]  # [M, n+1, n]
        smin, smax = V.amin(1), V.amax(1)
        bl = torch.maximum(lo[:, None], smin[None])  # box ∩ bbox(simplex) [B, M, n]
        bh = torch.minimum(hi[:, None], smax[None])
        meet = (bl <= bh).all(-1)
        Bm = self.bary  # lam_j(x) = Bm[:, j, :n] x + Bm[:, j, n]
        lam_max = (torch.maximum(Bm[None, :, :, :-1] * bl[:, :, None], Bm[None, :, :, :-1]
                   * bh[:, :, None])).sum(-1) + Bm[None, :, :, -1]  # [B, M, n+1]
        meet = meet & (lam_max >= -1e-12).all(-1)
        R = self.regions()
        A, b = R.A, R.b  # [M, p, n], [M, p]
        Al, Ah = A[None] * bl[:, :, None], A[None] * bh[:, :, None]  # [B, M, p, n]
        f_lo = torch.minimum(Al, Ah).sum(-1) + b[None]
        f_hi = torch.maximum(Al, Ah).sum(-1) + b[None]
        Wv = self.weight[self.simplices]  # [M, n+1, p]
        f_lo = torch.maximum(f_lo, Wv.amin(1)[None])
        f_hi = torch.minimum(f_hi, Wv.amax(1)[None])
        big = torch.tensor(math.inf, dtype=f_lo.dtype)
        f_lo = torch.where(meet[..., None], f_lo, big)
        f_hi = torch.where(meet[..., None], f_hi, -big)
        return f_lo.amin(1), f_hi.amax(1)

    def interval_enclosure(
        self, lo: Tensor, hi: Tensor, outside: str | None = None, margin: float = 1e-10,
        check: bool = True,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Exact range of the model and hull of its gradients over boxes.

        The extension point of the guaranteed remainders: any model with this method is
        bounded over a box by these enclosures (first-order, mean-value remainder).

        Args:
            lo, hi: box bounds ``[..., n]`` (any leading batch dims, broadcast together).
            outside: policy for boxes that leave the domain (default: the model's
                ``outside``). ``"clamp"``: the range and gradients of the clamped model
                ``x -> f(clamp(x))`` (box domains); the gradient hull of a coordinate along
                which the box leaves the domain also holds 0. ``"error"`` / ``"extrapolate"``:
                NaN bounds for that element (a domain exit; no ValueError, so that a filter
                step needs no host synchronisation). A non-box domain gives NaN for every box
                not inside it, whatever the policy.
            margin: outward padding, relative: the value bounds move by ``margin (1 + max|W|)``
                and the gradient bounds by ``margin (1 + max|A|)`` (rounding of ``forward`` and
                of autograd); 0 gives the computed extremes themselves.
            check: raise ValueError (naming ``lo`` / ``hi``) for NaN bounds or ``lo > hi``
                outside tracing (one host synchronisation); with ``check=False`` such elements
                get NaN bounds.

        Returns:
            ``(val_lo, val_hi [..., p], jac_lo, jac_hi [..., p, n])``: ``val_lo = min`` and
            ``val_hi = max`` of the model over the box (exact up to rounding), and the
            entrywise min / max of the slopes ``A_k`` of every piece whose simplex meets the
            box, touching included (the interval hull of the Clarke generalised Jacobian over
            the box; the autograd gradient at any point of the box lies in it).
            Differentiable in ``lo``, ``hi`` (value bounds) and ``weight`` (all four).

        Algorithm (exact, diffsmf.pwl.enclosure): the extremes of a continuous PWL function
        over a box are attained at vertices of ``box ∩ simplex``; every such vertex is the
        point of a partition face F (dimension d) with d coordinates at box bounds. All faces,
        coordinate sets and bound choices are enumerated in batched tensor code, points outside
        F or the box (relative tolerance 1e-10) dropped; a face with a kept point meets the box
        and so does every simplex containing it. Cost per box: about ``sum_d F_d C(n, d) 2^d``
        candidate points (2-D: ``nv + 4 edges + 4 M``), so meant for models up to a few
        thousand regions in low dimension. Before ``torch.compile``: call it once, or
        ``prepare(enclosure=True)`` (the face tables are cached).
        """
        from diffsmf.pwl.enclosure import box_enclosure

        outside = outside or self.outside
        if outside not in _OUTSIDE:
            raise ValueError(f"outside: must be one of {_OUTSIDE}, got {outside!r}")
        lo = torch.as_tensor(lo, dtype=_F64)
        hi = torch.as_tensor(hi, dtype=_F64)
        lo, hi = torch.broadcast_tensors(lo, hi)
        n, p = self.n_inputs, self.n_outputs
        if lo.shape[-1:] != (n,):
            raise ValueError(f"lo: expected [..., {n}], got {tuple(lo.shape)}")
        bad = ~(lo <= hi).all(-1)  # NaN or lo > hi
        if check and not _tracing() and bool(bad.any()):
            raise ValueError("lo, hi: bounds must not be NaN and lower <= upper elementwise")
        batch = lo.shape[:-1]
        lo2, hi2 = lo.reshape(-1, n), hi.reshape(-1, n)
        L, U = self.lower, self.upper
        tol = self.atol * (U - L)
        exits = (lo2 < L - tol) | (hi2 > U + tol)  # [N, n]
        lc = torch.minimum(torch.maximum(lo2, L), U)
        hc = torch.minimum(torch.maximum(hi2, L), U)
        A = self.regions().A
        sparse = lc.device.type == "cpu" and not _tracing()
        vl, vh, jl, jh, corners = box_enclosure(self._get("encl"), self.weight, A, lc, hc, sparse)
        leave = exits.any(-1)
        if self._box and outside == "clamp":
            e3 = exits[:, None, :]
            jl = torch.where(e3, jl.clamp_max(0.0), jl)
            jh = torch.where(e3, jh.clamp_min(0.0), jh)
            nan = bad.reshape(-1)
        else:
            nan = bad.reshape(-1) | leave | ~corners
        nan = nan | ~torch.isfinite(vl).all(-1)
        pad_v = margin * (1 + self.weight.detach().abs().max())
        pad_j = margin * (1 + A.detach().abs().max())
        vl = torch.where(nan[:, None], torch.nan, vl - pad_v).reshape(batch + (p,))
        vh = torch.where(nan[:, None], torch.nan, vh + pad_v).reshape(batch + (p,))
        jl = torch.where(nan[:, None, None], torch.nan, jl - pad_j).reshape(batch + (p, n))
        jh = torch.where(nan[:, None, None], torch.nan, jh + pad_j).reshape(batch + (p, n))
        return vl, vh, jl, jh

    # ------------------------------------------------------------------ max-min forms (eq. 12)
    def maxmin_basis(self, x: Tensor) -> Tensor:
        """Hat basis written in the max-min form of eq. 12: ``phi_v(x) = max(0, min_{s in
        star(v)} lam_v^s(x))`` for each vertex v, x [N, n] -> [N, nv].

        Equal to the nodal basis when every vertex star is convex (e.g. Kuhn grids); raises
        ValueError otherwise. Evaluated without point location (pure max/min of affine maps).
        """
        nv, n = self.vertices.shape[0], self.n_inputs
        Bm = self.bary  # [M, n+1, n+1]
        xa = torch.cat([x, torch.ones_like(x[..., :1])], -1)
        lam = torch.einsum("mjk,nk->nmj", Bm, xa)  # [N, M, n+1] affine extensions
        # check convex stars: every star vertex w has lam_v^s(w) >= 0 for all s in star(v)
        lam_vert = torch.einsum("mjk,vk->vmj", Bm, torch.cat(
            [self.vertices, torch.ones(nv, 1, dtype=_F64)], -1))  # [nv, M, n+1]
        M = self.n_regions
        nbr = torch.zeros(nv, nv, dtype=torch.bool)  # vertices sharing a simplex
        for j in range(n + 1):
            for k in range(n + 1):
                nbr[self.simplices[:, j], self.simplices[:, k]] = True
        inf = torch.tensor(math.inf, dtype=_F64)
        phi = torch.full((x.shape[0], nv), inf, dtype=_F64)
        for j in range(n + 1):
            v = self.simplices[:, j]  # simplex m contributes lam_j^m to vertex v = S[m, j]
            bad = nbr[v] & (lam_vert[:, :, j].T < -1e-9)  # [M, nv]
            if bool(bad.any()):
                raise ValueError("maxmin_basis: some vertex star is not convex")
            phi = phi.scatter_reduce(1, v.expand(x.shape[0], M), lam[:, :, j], "amin")
        return phi.clamp_min(0)

    def lattice_eval(self, x: Tensor) -> Tensor:
        """The model in max-min (lattice) form, eq. 12 generalised: ``f_o(x) = max_k min_{j in
        J_k} l_j(x)`` with l_k the affine piece of simplex k and ``J_k = {j : l_j >= l_k on
        simplex k}`` (Tarela-Martinez lattice representation, valid for every continuous PWL
        function on a convex domain). x [N, n] -> [N, p]. O(N M^2): for checks on small models.
        """
        R = self.regions()
        outs = []
        for o in range(self.n_outputs):
            a, b = R.A[:, o], R.b[:, o]  # [M, n], [M]
            at_verts = torch.einsum("jn,kvn->kvj", a, R.vertices) + b  # [k, n+1, j]: l_j(v of k)
            lk = torch.einsum("kvn,kn->kv", R.vertices, a) + b[:, None]  # [k, n+1]
            scale = 1e-9 * (1 + at_verts.abs().amax())
            J = (at_verts >= lk[..., None] - scale).all(1)  # [k, j]
            lx = x @ a.T + b  # [N, j]
            inf = torch.tensor(math.inf, dtype=_F64)
            mins = torch.where(J[None], lx[:, None, :], inf).amin(-1)  # [N, k]
            outs.append(mins.amax(-1))
        return torch.stack(outs, -1)

    # ------------------------------------------------------------------ persistence
    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing, unexp,
                              err):
        # resize to the saved partition so a model with another number of regions loads it
        for name in ("vertices", "simplices"):
            key = prefix + name
            if key in state_dict:
                setattr(self, name, torch.empty_like(state_dict[key]))
        key = prefix + "weight"
        if key in state_dict:
            self.weight = nn.Parameter(torch.empty_like(state_dict[key]))
        self._cache = {}
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing, unexp,
                                      err)
        self._box = bool(self.box_domain)

    @classmethod
    def from_state_dict(cls, state_dict: dict[str, Tensor], **kwargs: Any) -> SCPLNN:
        """Build a model from a ``state_dict`` (any number of regions)."""
        m = cls(state_dict["vertices"], state_dict["simplices"], state_dict["weight"],
                box_domain=bool(state_dict.get("box_domain", True)), **kwargs)
        return m

    def save(self, path: str | Path) -> None:
        """``torch.save`` of the state dict plus the outside policy and names."""
        torch.save({"state_dict": self.state_dict(), "outside": self.outside,
                    "input_names": self.input_names, "output_names": self.output_names}, path)

    @classmethod
    def load(cls, path: str | Path) -> SCPLNN:
        d = torch.load(path, weights_only=True)
        return cls.from_state_dict(d["state_dict"], outside=d["outside"],
                                   input_names=d["input_names"], output_names=d["output_names"])

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict: partition, vertex weights and each region's affine piece."""
        R = self.regions()
        return {
            "format": "diffsmf.scplnn",
            "version": 1,
            "n_inputs": self.n_inputs,
            "n_outputs": self.n_outputs,
            "input_names": self.input_names,
            "output_names": self.output_names,
            "outside": self.outside,
            "box_domain": bool(self.box_domain),
            "domain": {"lower": self.lower.tolist(), "upper": self.upper.tolist()},
            "vertices": self.vertices.tolist(),
            "simplices": self.simplices.tolist(),
            "weights": self.weight.detach().tolist(),
            "regions": [
                {"vertices": s, "A": A, "b": b}
                for s, A, b in zip(self.simplices.tolist(), R.A.detach().tolist(),
                                   R.b.detach().tolist())
            ],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any] | str | Path) -> SCPLNN:
        """Inverse of `to_json` (a dict, a JSON string or a path to a .json file).

        Validated on load; a ValueError names the field: truncated / invalid JSON, a wrong
        ``format``, ``vertices`` / ``weights`` that are not finite numbers (NaN, null, strings),
        ``simplices`` that are not vertex indices or are degenerate, ``domain`` with
        upper < lower or not the vertices' bounding box, ``regions`` whose affine maps disagree
        with the weights, an unknown ``outside`` policy.
        """
        if isinstance(data, Path) or (isinstance(data, str) and not data.lstrip().startswith("{")):
            path = Path(data)
            if not path.exists():
                raise FileNotFoundError(2, "no such model file", str(path))
            data = path.read_text()
        if isinstance(data, str):
            try:
                data = json.loads(data)
            except json.JSONDecodeError as exc:
                raise ValueError(f"data: not valid JSON (truncated?): {exc}") from None
        if not isinstance(data, dict) or data.get("format") != "diffsmf.scplnn":
            raise ValueError("format: not a diffsmf.scplnn JSON model")

        def _num(name: str, dims: int) -> Tensor:
            if name not in data:
                raise ValueError(f"{name}: missing from the model JSON")
            try:
                t = torch.tensor(data[name], dtype=_F64)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise ValueError(f"{name}: expected a {dims}-D array of numbers ({exc})"
                                 ) from None
            if t.dim() != dims:
                raise ValueError(f"{name}: expected a {dims}-D array, got shape "
                                 f"{tuple(t.shape)}")
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name}: contains NaN or inf")
            return t

        V = _num("vertices", 2)
        W = _num("weights", 2)
        Sf = _num("simplices", 2)
        if bool((Sf != Sf.round()).any()):
            raise ValueError("simplices: expected integer vertex indices")
        S = Sf.long()
        nv, n = V.shape
        if S.shape[1] != n + 1 or (S.numel() and (int(S.min()) < 0 or int(S.max()) >= nv)):
            raise ValueError(f"simplices: expected [M, {n + 1}] indices in [0, {nv})")
        if W.shape[0] != nv:
            raise ValueError(f"weights: expected [{nv}, p], got {tuple(W.shape)}")
        vol = torch.linalg.det(V[S][:, 1:] - V[S][:, :1]).abs() if n > 0 else None
        scale = float((V.amax(0) - V.amin(0)).prod())
        if vol is not None and bool((vol <= 1e-14 * max(scale, 1e-300)).any()):
            raise ValueError(f"simplices: {int((vol <= 1e-14 * scale).sum())} degenerate "
                             "(zero-volume) simplices")
        dom = data.get("domain")
        if dom is not None:
            try:
                lo = torch.tensor(dom["lower"], dtype=_F64)
                hi = torch.tensor(dom["upper"], dtype=_F64)
            except (TypeError, ValueError, KeyError, RuntimeError) as exc:
                raise ValueError(f"domain: expected lower and upper lists of numbers ({exc})"
                                 ) from None
            if lo.shape != (n,) or hi.shape != (n,) or not bool(torch.isfinite(lo).all()
                                                                 and torch.isfinite(hi).all()):
                raise ValueError(f"domain: expected finite lower and upper of length {n}")
            if bool((hi < lo).any()):
                raise ValueError("domain: upper < lower")
            tol = 1e-9 * (1 + (V.amax(0) - V.amin(0)).abs().max())
            if bool(((lo - V.amin(0)).abs() > tol).any() or ((hi - V.amax(0)).abs() > tol).any()):
                raise ValueError("domain: lower/upper are not the bounding box of the vertices")
        outside = data.get("outside", "error")
        if outside not in _OUTSIDE:
            raise ValueError(f"outside: must be one of {_OUTSIDE}, got {outside!r}")
        box = data.get("box_domain", True)
        if not isinstance(box, bool):
            raise ValueError(f"box_domain: expected true or false, got {box!r}")
        model = cls(V, S, W, outside=outside, box_domain=box,
                    input_names=data.get("input_names"), output_names=data.get("output_names"))
        regs = data.get("regions")
        if regs is not None:
            try:
                A = torch.tensor([r["A"] for r in regs], dtype=_F64)
                b = torch.tensor([r["b"] for r in regs], dtype=_F64)
            except (TypeError, ValueError, KeyError, RuntimeError) as exc:
                raise ValueError(f"regions: expected a list of {{A, b}} pieces ({exc})") from None
            with torch.no_grad():
                R = model.regions()
            if A.shape != R.A.shape or b.shape != R.b.shape:
                raise ValueError(f"regions: expected {R.A.shape[0]} pieces of shape "
                                 f"{tuple(R.A.shape[1:])}")
            big = 1 + float(W.abs().max()) * (1 + float(V.abs().max()))
            finite = bool(torch.isfinite(A).all() and torch.isfinite(b).all())
            if not finite or float((A - R.A).abs().max()) > 1e-6 * big or float(
                    (b - R.b).abs().max()) > 1e-6 * big:
                raise ValueError("regions: the affine pieces disagree with weights and vertices")
        return model

    def extra_repr(self) -> str:
        return (f"n_inputs={self.n_inputs}, n_outputs={self.n_outputs}, "
                f"regions={self.n_regions}, vertices={self.vertices.shape[0]}, "
                f"outside={self.outside!r}")
