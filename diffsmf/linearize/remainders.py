"""Guaranteed remainder bounds of a linearisation over a set.

For ``fn : R^n -> R^k``, a set ``S`` (batch ``[...]``), an expansion point ``c [..., n]`` and
any slope matrix ``J [..., k, n]`` (autograd or Stirling), every function here returns an
:class:`~diffsmf.sets.Interval` ``[..., k]`` that contains

    r(x) = fn(x) - fn(c) - J (x - c)      for every x in S

(in exact arithmetic of the computed float data; evaluation of ``fn`` in float64 at a few
points is padded by a small multiple of the rounding unit). All are batched over the set's
batch dims and differentiable w.r.t. the set's fields, ``c``, ``J`` and parameters closed over
by ``fn``. ``fn`` must be batch-elementwise (see :mod:`diffsmf.linearize.jacobians`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.linearize.jacobians import jacobian
from diffsmf.linearize.jets import interval_hessian, interval_jacobian
from diffsmf.sets.base import ConvexSet
from diffsmf.sets.interval import Interval, interval_eval

__all__ = [
    "MAX_VERTICES",
    "dc_remainder",
    "hessian_eig_lower_bound",
    "lagrange_remainder",
    "parameter_deviation",
]

Fn = Callable[[Tensor], Tensor]

#: Above this many extreme points per set, :func:`dc_remainder` falls back to the Lagrange bound.
MAX_VERTICES = 4096
#: Tangent planes at every vertex (not only at ``c``) while the vertex count is at most this.
_MAX_TANGENTS = 64
#: Padding of float evaluations, in units of eps times the magnitudes involved.
_PAD_ULPS = 64.0


def _eps(t: Tensor) -> float:
    return torch.finfo(t.dtype).eps


def _check(S: ConvexSet, c: Tensor, J: Tensor | None) -> tuple[Tensor, Tensor | None]:
    if not isinstance(S, ConvexSet):
        raise ValueError("S: expected a diffsmf set")
    c = torch.as_tensor(c, dtype=S.dtype, device=S.device)
    if c.shape[-1:] != (S.dim,):
        raise ValueError(f"c: expected shape [..., {S.dim}], got {tuple(c.shape)}")
    if J is not None:
        J = torch.as_tensor(J, dtype=S.dtype, device=S.device)
        if J.dim() < 2 or J.shape[-1] != S.dim:
            raise ValueError(f"J: expected shape [..., k, {S.dim}], got {tuple(J.shape)}")
    return c, J


def _padded(lo: Tensor, hi: Tensor, scale: Tensor) -> Interval:
    """``[lo - tol, hi + tol]`` with ``tol = PAD * eps * scale`` (detached) + tiny."""
    tol = (_PAD_ULPS * _eps(lo)) * scale.detach() + torch.finfo(lo.dtype).tiny
    return Interval(lo - tol, hi + tol)


def _hull_with(S: ConvexSet, c: Tensor) -> Interval:
    """Interval hull of ``S`` and ``c`` (so the segments [c, x] lie inside), padded outward."""
    box = S.interval_hull()
    lo = torch.minimum(box.lower, c)
    hi = torch.maximum(box.upper, c)
    scale = lo.abs() + hi.abs()
    return _padded(lo, hi, scale)


def _linear_range(S: ConvexSet, D: Tensor, c: Tensor) -> Interval:
    """Exact range of ``D (x - c)`` over ``S`` via the support function -> ``[..., k]``."""
    Dk = D.movedim(-2, 0)  # [k, ..., n] so the batch dims align with S's
    Dc = (D * c.unsqueeze(-2)).sum(-1)  # [..., k]
    up = S.support(Dk).movedim(0, -1) - Dc
    lo = -S.support(-Dk).movedim(0, -1) - Dc
    box = S.interval_hull()
    mag = box.lower.abs() + box.upper.abs() + c.abs()
    scale = (D.abs() * mag.unsqueeze(-2)).sum(-1)
    return _padded(lo, up, scale)


def _quad_form(H: Interval, d: Interval) -> Interval:
    """Enclosure of ``d' H d`` for ``H [..., k, n, n]``, ``d [..., n]`` -> ``[..., k]``.

    Diagonal terms use the exact square ``d_j^2``; symmetric off-diagonal pairs are kept as
    they are (both copies hold the same interval).
    """
    n = d.shape[-1]
    dd = d.unsqueeze(-1) * d.unsqueeze(-2)  # [..., n, n]
    sq = d.square()
    diag = Interval(torch.diag_embed(sq.lower), torch.diag_embed(sq.upper))
    eye = torch.eye(n, dtype=torch.bool, device=d.lower.device)
    dd = torch.where(eye, diag, dd)
    return (H * dd.unsqueeze(-3)).sum((-2, -1))


def lagrange_remainder(fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
    """Lagrange remainder bound with the interval Hessian -> Interval ``[..., k]``.

    Seed 001 eq. 26-28: ``r(x) = 1/2 (x-c)' H(xi) (x-c)`` with ``H`` enclosed by the interval
    Hessian over the interval hull of ``S`` and ``c``; the quadratic form is bounded in
    interval arithmetic over ``x - c`` in the hull. If ``J`` differs from the exact Jacobian
    at ``c`` (e.g. Stirling slopes), the exact range of ``(J_exact(c) - J)(x - c)`` over ``S``
    (support function) is added. ``J=None`` means the exact Jacobian.
    """
    c, J = _check(S, c, J)
    box = _hull_with(S, c)
    H = interval_hessian(fn, box)  # [..., k, n, n]
    d = box - c  # [..., n] (outward rounded)
    R = _quad_form(H, d) * 0.5
    if J is None:
        return R
    D = jacobian(fn, c) - J
    if bool((D.detach() == 0).all()):
        return R
    return R + _linear_range(S, D, c)


def hessian_eig_lower_bound(H: Interval) -> Tensor:
    """Lower bound of lambda_min over every symmetric matrix in ``H [..., n, n]`` -> ``[...]``.

    Max of two valid bounds: Gershgorin on the interval matrix (``min_j lower(H_jj) -
    sum_{l != j} max|H_jl|``) and the midpoint-radius bound ``lambda_min(H_c) - rho(H_r)``
    (Weyl; ``rho`` of the non-negative symmetric radius matrix is its largest eigenvalue).
    Padded by the float error of the eigenvalue solver.
    """
    lo, hi = H.lower, H.upper
    finite = torch.isfinite(lo) & torch.isfinite(hi)
    ok = finite.all(-1).all(-1)
    lo = torch.where(finite, lo, torch.zeros_like(lo))
    hi = torch.where(finite, hi, torch.zeros_like(hi))
    n = lo.shape[-1]
    eye = torch.eye(n, dtype=torch.bool, device=lo.device)
    mag = torch.maximum(lo.abs(), hi.abs())
    off = torch.where(eye, torch.zeros_like(mag), mag).sum(-1)
    gersh = (torch.diagonal(lo, dim1=-2, dim2=-1) - off).amin(-1)
    Hc = 0.5 * (lo + hi)
    Hr = 0.5 * (hi - lo)
    Hc = 0.5 * (Hc + Hc.mT)
    Hr = 0.5 * (Hr + Hr.mT)
    weyl = torch.linalg.eigvalsh(Hc)[..., 0] - torch.linalg.eigvalsh(Hr)[..., -1]
    norm = (Hc.abs() + Hr.abs()).sum((-2, -1)).detach()
    lam = torch.maximum(gersh, weyl) - (8 * n + 16) * _eps(lo) * norm
    return torch.where(ok, lam, torch.full_like(lam, -torch.inf))


def _extreme_points(S: ConvexSet, max_vertices: int) -> Tensor | None:
    """Points whose convex hull is ``S`` (all vertices included) -> ``[..., N, n]`` or None."""
    if isinstance(S, Interval):
        return S.vertices() if 2**S.dim <= max_vertices else None
    G = getattr(S, "generators", None)  # Parallelotope (T) and Zonotope
    if G is None:
        return None  # Ellipsoid: not a polytope
    m = G.shape[-1]
    if 2**m > max_vertices:
        return None
    s = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=m)), dtype=G.dtype,
                     device=G.device)  # [2^m, m]
    return S.center.unsqueeze(-2) + s @ G.mT


def _front(V: Tensor) -> Tensor:
    """``[..., N, n] -> [N, ..., n]`` (the point index leads, so closures broadcast)."""
    return V.movedim(-2, 0)


def dc_remainder(
    fn: Fn,
    S: ConvexSet,
    c: Tensor,
    J: Tensor | None = None,
    *,
    max_vertices: int = MAX_VERTICES,
    with_lagrange: bool = False,
) -> Interval:
    """Difference-of-convex remainder bound at the set's vertices -> Interval ``[..., k]``.

    Seed 000 eq. 14-18 with the erratum (seeds/README.md): per output i, ``r_i = g1 - g2``
    with ``g1 = r_i + alpha_i |x - c|^2`` and ``g2 = alpha_i |x - c|^2``, where
    ``alpha_i = max(0, -lambda_min / 2)`` uses a guaranteed lower bound of the smallest
    eigenvalue of the interval Hessian of ``fn_i`` over the hull of ``S`` and ``c``
    (:func:`hessian_eig_lower_bound`), so ``g1`` is convex there. Then

    * upper (eq. 15, tangent of g2 at c is 0): ``r <= g1 <= max_v g1(v)`` over the vertices;
    * lower (eq. 16): for a tangent point p (``c`` and, for few vertices, every vertex)
      ``r >= g1(p) + grad g1(p).(x - p) - alpha |x - c|^2``, a concave function whose minimum
      over the polytope is attained at a vertex; the best tangent point is kept. Gradients
      are exact (autograd), never Stirling slopes.

    ``S``: Interval, Parallelotope or Zonotope (extreme points ``c + G s``, s in {-1,1}^m).
    With more than ``max_vertices`` extreme points, or an Ellipsoid, this falls back to
    :func:`lagrange_remainder` (documented deviation). A second lower bound comes from the
    same split applied to ``-r`` (``beta_i`` from an upper bound of lambda_max):
    ``r >= min_v (r(v) - beta_i |v - c|^2)``; the larger lower bound is kept.
    ``with_lagrange=True`` also intersects the result with the Lagrange bound (same interval
    Hessian, so almost free): still guaranteed, never looser.
    """
    c, J = _check(S, c, J)
    V = _extreme_points(S, max_vertices)
    if V is None:
        return lagrange_remainder(fn, S, c, J)
    box = _hull_with(S, c)
    H = interval_hessian(fn, box)  # [..., k, n, n]
    alpha = (-hessian_eig_lower_bound(H)).clamp(min=0) * 0.5  # [..., k]: r + alpha|x-c|^2 cvx
    beta = (-hessian_eig_lower_bound(-H)).clamp(min=0) * 0.5  # -r + beta|x-c|^2 convex
    Vf = _front(V)  # [N, ..., n]
    fc = fn(c)  # [..., k]
    Jc = jacobian(fn, c)  # [..., k, n]
    J = Jc if J is None else J
    dv = Vf - c  # [N, ..., n]
    sqv = (dv * dv).sum(-1).unsqueeze(-1)  # [N, ..., 1]
    fv = fn(Vf)  # [N, ..., k]
    Jdv = (J * dv.unsqueeze(-2)).sum(-1)  # [N, ..., k]
    rv = fv - fc - Jdv  # remainder at the vertices
    g1v = rv + alpha * sqv
    mag = fv.abs() + fc.abs() + (J.abs() * dv.abs().unsqueeze(-2)).sum(-1)
    mag = mag + (alpha + beta.where(torch.isfinite(beta), alpha)) * sqv
    upper = g1v.amax(0)
    # tangent plane of g1 at c: g1(c) = 0, grad g1(c) = Jc - J
    lower = (((Jc - J) * dv.unsqueeze(-2)).sum(-1) - alpha * sqv).amin(0)
    lower = torch.maximum(lower, (rv - beta * sqv).amin(0))  # the split of -r
    grad_mag = (Jc - J).abs()
    if V.shape[-2] <= _MAX_TANGENTS:  # tangent planes at every vertex p: [Np, Nv, ..., k]
        grad_v = jacobian(fn, Vf) - J + 2 * alpha.unsqueeze(-1) * dv.unsqueeze(-2)
        diff = Vf.unsqueeze(0) - Vf.unsqueeze(1)  # [p, v] -> v - p
        tang = g1v.unsqueeze(1) + (grad_v.unsqueeze(1) * diff.unsqueeze(-2)).sum(-1)
        lower = torch.maximum(lower, (tang - alpha * sqv.unsqueeze(0)).amin(1).amax(0))
        grad_mag = grad_mag + grad_v.abs().amax(0)
    scale = mag.amax(0) + 2 * (grad_mag * dv.abs().amax(0).unsqueeze(-2)).sum(-1)
    bad = ~(torch.isfinite(alpha) & torch.isfinite(beta))
    lower = torch.where(bad, torch.full_like(lower, -torch.inf), lower)
    upper = torch.where(bad, torch.full_like(upper, torch.inf), upper)
    scale = torch.where(bad, torch.zeros_like(scale), scale)
    out = _padded(lower, upper, scale)
    if with_lagrange:
        lag = _quad_form(H, box - c) * 0.5
        if not bool(((Jc - J).detach() == 0).all()):
            lag = lag + _linear_range(S, Jc - J, c)
        out = out.intersect(lag)
    return out


def parameter_deviation(
    f: Callable[..., Tensor],
    S: ConvexSet,
    params: Interval,
    theta_nom: Tensor | None = None,
    u: Tensor | None = None,
) -> Interval:
    """Enclosure of ``f(x, u, theta) - f(x, u, theta_nom)`` for x in S, theta in params.

    Seed 001 eq. 18-21 (there evaluated at the estimate only, which is not guaranteed for the
    other x in S). Here two guaranteed enclosures over the box hull of S are intersected:
    the simple interval extension ``F(X, u, Theta) - F(X, u, theta_nom)`` (eq. 20) and the
    mean-value form ``sum_j [df/dtheta_j](X, Theta) (Theta_j - theta_nom_j)`` with the
    interval Jacobian w.r.t. theta (exact range when f is affine in theta). -> ``[..., n]``.
    """
    if not isinstance(params, Interval):
        raise ValueError("params: expected an Interval of parameters [q]")
    box = S.interval_hull()
    box = _padded(box.lower, box.upper, box.lower.abs() + box.upper.abs())
    q = params.shape[-1]
    th_nom = params.center if theta_nom is None else torch.as_tensor(theta_nom, dtype=S.dtype)
    theta_box = params.hull(Interval(th_nom, th_nom))  # theta_nom may lie outside params
    n = S.dim
    nat = interval_eval(lambda x, th: f(x, u, th), box, params) - interval_eval(
        lambda x: f(x, u, th_nom), box
    )
    batch = torch.broadcast_shapes(box.shape[:-1], theta_box.shape[:-1])
    zlo = torch.cat([box.lower.expand(*batch, n), theta_box.lower.expand(*batch, q)], -1)
    zhi = torch.cat([box.upper.expand(*batch, n), theta_box.upper.expand(*batch, q)], -1)
    Jz = interval_jacobian(lambda z: f(z[..., :n], u, z[..., n:]), Interval(zlo, zhi))
    Jth = Jz[..., n:]  # [..., n, q]
    mv = (Jth * (params - th_nom).unsqueeze(-2)).sum(-1)
    return nat.intersect(mv)
