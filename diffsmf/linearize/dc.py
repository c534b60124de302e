"""The difference-of-convex remainder bound at a set's vertices (Wang et al. 2022, eq. 14-18, with
the erratum): guaranteed curvature bounds of an interval Hessian, the convexifying quadratics,
the vertices of a set and the table of tangent-plane bounds.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.interval.box import Interval
from diffsmf.linearize.bound_parts import (
    Fn,
    _abs_max,
    _abs_sum,
    _affine_remainder,
    _check,
    _eps,
    _hull_with,
    _known_affine,
    _lagrange,
    _lower_order,
    _nograd,
    _padded,
    _remember,
)
from diffsmf.linearize.jacobians import jacobian, value_and_jacobian
from diffsmf.linearize.jets import jet_eval
from diffsmf.utils import broadcast_shapes, eager_constant, materialize, tracing

__all__ = [
    "MAX_TANGENTS",
    "MAX_VERTICES",
    "dc_remainder",
    "diagonal_shift",
    "hessian_eig_lower_bound",
]

#: Above this many sign combinations, `dc_remainder` uses the corners of the interval hull.
MAX_VERTICES = 256


#: Tangent planes at every vertex (not only at ``c``) while the vertex count is at most this.
MAX_TANGENTS = 64


#: Elements per chunk of the tangent-plane evaluation.
_TANGENT_ELEMS = 4_000_000


#: `_dc_bounds` evaluates its table as matrix products (`_dc_bounds_gemm`) from this many
#: (tangent point, vertex) pairs on: eagerly 1.0-4.2x faster from 32 x 33 pairs on (n = 2-6,
#: batch 1-1,000, one thread), slower for fewer pairs or a single tangent point.
_GEMM_MIN_PAIRS = 1 << 10


#: Table entries per chunk of `_dc_bounds_gemm` (8 MB in float64: 1.7-2x faster than 4M at
#: n = 5-6, batch 100-1,000).
_GEMM_CHUNK_ELEMS = 1 << 20


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
    lam = _curvature(torch.where(finite, lo, 0.0), torch.where(finite, hi, 0.0))[0][0]
    return torch.where(ok, lam, -torch.inf)


def _curvature(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """`hessian_eig_lower_bound` and `diagonal_shift` of the interval matrices ``[lo, hi]``
    and ``[-hi, -lo]`` (``[..., n, n]``) at once -> ``(lam [2, ...], w [2, ..., n])``.

    The two share their off-diagonal magnitudes, radius matrix and norm; the midpoint of the
    second is minus the first's, so its ``lambda_min`` is minus the first's ``lambda_max``
    (one eigenvalue call for the midpoint and the radius matrix together; for n <= 2 the
    closed form gives exactly ``-lambda_max``, above that any difference is within the
    solver's error that the ``(8 n + 16) eps`` padding covers). Non-finite entries give a
    non-finite ``lam`` / ``w``.
    """
    n = lo.shape[-1]
    mag = torch.maximum(lo.abs(), hi.abs()).masked_fill(_eye(n, lo.device), 0.0)
    off = linalg.small_reduce(mag, "sum")  # [..., n]
    diag = torch.stack([torch.diagonal(lo, dim1=-2, dim2=-1),
                        -torch.diagonal(hi, dim1=-2, dim2=-1)])  # [2, ..., n]
    gersh = linalg.small_reduce(diag - off, "amin")  # [2, ...]
    Hcr = torch.stack([lo + hi, hi - lo]) * 0.5  # [2, ..., n, n]: midpoint, radius
    if n == 2:
        weyl, norm = _weyl2(Hcr)
    else:
        Hcr = 0.5 * (Hcr + Hcr.mT)
        ev = linalg.eigvalsh(Hcr)  # [2, ..., n]
        weyl = torch.stack([ev[0, ..., 0], -ev[0, ..., -1]]) - ev[1, ..., -1]
        A = Hcr.abs()
        norm = _nograd((A[0] + A[1]).sum((-2, -1)))
    tol = (8 * n + 16) * _eps(lo)
    lam = torch.maximum(gersh, weyl) - tol * norm
    w = (off - diag + tol * _nograd(diag.abs() + off)).clamp(min=0) * 0.5
    return lam, w


def _weyl2(Hcr: Tensor) -> tuple[Tensor, Tensor]:
    """The Weyl bounds ``[lambda_min(H_c) - rho(H_r), -lambda_max(H_c) - rho(H_r)]``
    ``[2, ...]`` and a norm (the sum of ``|entries|`` of both) of 2 x 2 ``Hcr [2, ..., 2, 2]``
    (midpoint, radius), with `linalg.eigvalsh`'s closed form on the symmetric parts
    (``(a + d) / 2 -+ sqrt(((a - d) / 2)^2 + b^2)``, the same floats)."""
    a, b01, b10, d = Hcr.flatten(-2).unbind(-1)  # [2, ...] each
    b = 0.5 * (b01 + b10)
    m, h = 0.5 * (a + d), 0.5 * (a - d)
    r = torch.sqrt(h * h + b * b + torch.finfo(a.dtype).tiny)  # [2, ...]
    # [m - r, -m - r] (exactly -(m + r)) of the midpoint, minus rho(H_r) = m + r of the radius
    (m0, m1), (r0, r1) = m.unbind(0), r.unbind(0)
    weyl = torch.addcmul(-r0, m0, _pm1(m)) - (m1 + r1)
    return weyl, _nograd(Hcr.abs().sum((0, -2, -1)))


def _pm1(like: Tensor) -> Tensor:
    """``[1, -1]`` shaped ``[2, 1, .., 1]`` against ``[2, *like.shape[1:]]`` (cached like
    `_form_signs`)."""
    return eager_constant(
        _SIGNS, ("pm1", like.dtype, like.device, like.dim()),
        lambda: torch.tensor([1.0, -1.0], dtype=like.dtype, device=like.device).reshape(
            2, *([1] * (like.dim() - 1))))


_EYES: dict = {}


def _one(like: Tensor) -> Tensor:
    """A 0-dim 1 like ``like`` (cached in eager mode: a constant, not an op per call)."""
    return eager_constant(_SIGNS, ("one", like.dtype, like.device),
                          lambda: torch.ones((), dtype=like.dtype, device=like.device))


def _eye(n: int, device: torch.device) -> Tensor:
    """Boolean identity ``[n, n]`` (cached in eager mode: a constant, not an op per call)."""
    return eager_constant(_EYES, (n, device),
                          lambda: torch.eye(n, dtype=torch.bool, device=device))


def _extreme_points(S: ConvexSet, max_vertices: int) -> tuple[Tensor, bool]:
    """Points whose convex hull contains ``S`` -> (``[..., N, n]``, exact).

    ``exact`` is True when the hull of the points is ``S`` itself (box corners, parallelotope
    vertices, 2-D zonotope vertices, or ``c + G s`` over all sign vectors s); otherwise the
    corners of the interval hull of ``S`` (a containing box) are returned: max/min of the
    convex / concave parts over that box still bound those over ``S``.
    """
    n = S.dim
    G = getattr(S, "generators", None)  # Parallelotope (T) and Zonotope
    if isinstance(S, Interval):
        if 2**n <= max_vertices:
            return S.vertices(), True
    elif G is not None:
        m = G.shape[-1]
        if n == 2 and hasattr(S, "vertices_2d"):
            return S.vertices_2d(), True  # 2m vertices of a planar zonotope
        if 2**m <= max_vertices:
            s = _sign_vectors(m, G)  # [2^m, m]
            return S.center.unsqueeze(-2) + linalg.traced_matmul(s, G.mT), True
    if 2**n > max_vertices:
        raise ValueError(f"max_vertices: {max_vertices} < 2^{n} box corners")
    return S.interval_hull().vertices(), False


def _sign_vectors(m: int, like: Tensor) -> Tensor:
    """Every sign vector of length ``m`` ``[2^m, m]`` (-1 first) in ``like``'s dtype and
    device (cached in eager mode: a constant, not a tensor built from Python per call)."""
    return eager_constant(
        _SIGNS, ("signs", m, like.dtype, like.device),
        lambda: torch.tensor(list(itertools.product((-1.0, 1.0), repeat=m)), dtype=like.dtype,
                             device=like.device))


def _front(V: Tensor) -> Tensor:
    """``[..., N, n] -> [N, ..., n]`` (the point index leads, so closures broadcast)."""
    return V.movedim(-2, 0)


def diagonal_shift(H: Interval) -> Tensor:
    """Weights ``w [..., n] >= 0`` with ``M + 2 diag(w)`` PSD for every symmetric M in ``H``.

    Row-wise Gershgorin: ``2 w_j >= -(lower(H_jj) - sum_{l != j} max|H_jl|)`` makes every
    member diagonally dominant with a non-negative diagonal. Padded for rounding; inf where
    ``H`` is unbounded.
    """
    w = _curvature(H.lower, H.upper)[1][0]
    return torch.where(torch.isnan(w), torch.inf, w)


#: Half-widths below this are not used to normalise the DC split (a flat direction of the box,
#: where every vertex has ``x_j = c_j`` and the weight of that coordinate does not matter).
_MIN_SCALE = 1e-150


def _convexifying_weights(
    H: Interval, box: Interval, finite: bool = False
) -> tuple[Tensor, Tensor]:
    """Weights ``W [4, ..., k, n]`` of the four quadratics ``q = sum_j W_j (x_j - c_j)^2`` of
    the DC split: ball and diagonal shift for ``r`` and for ``-r`` (``H [..., k, n, n]`` is
    the interval Hessian of ``r``; that of ``-r`` is ``-H``), and ``bad [4, ..., k]``: True
    where a form does not exist (an unbounded Hessian; there ``W`` is 0, not to be used).

    Scale-covariant: both forms are computed for the Hessian in the coordinates normalised by
    the box's half-widths ``s`` (``x~ = x / s``, Hessian ``diag(s) M diag(s)``) and mapped
    back, ``W_j = w~_j / s_j^2``. The ball is then ``alpha~ |diag(s)^-1 (x - c)|^2``, the
    ellipsoid of the box's proportions, rather than Wang et al. 2022's Euclidean
    ``alpha |x - c|^2``, whose single curvature couples states of different units (a state
    in kelvin inflated the remainder of one in mol/L); for a cube the two are the same. A
    change of units ``x' = D x`` (D diagonal) gives the same quadratics, so the same bounds.
    Validity: ``M~ + 2 diag(w~) >= 0`` implies ``M + 2 diag(w~ / s^2) >= 0`` (congruence).
    ``finite=True`` declares every bound of ``H`` finite (the caller checked): no masks.
    """
    s = box.radius
    # a flat or non-finite width (a diverged element) normalises by 1: no inf reaches the
    # weights or, through them, the gradients of the other elements
    s = torch.where((s > _MIN_SCALE) & (s < torch.inf), s, _one(s))  # [..., n]
    n = s.shape[-1]
    lead = s.shape[:-1]
    ss = s.reshape(*lead, 1, n, 1) * s.reshape(*lead, 1, 1, n)  # [..., 1, n, n]
    unbounded = None
    if finite:
        lo, hi = H.lower * ss, H.upper * ss
    else:
        hinf = ~((H.upper - H.lower) < torch.inf)  # an infinite bound (or NaN): hi - lo >= 0
        unbounded = hinf.flatten(-2).any(-1)  # [..., k]: no convexification
        lo = H.lower.masked_fill(hinf, 0.0) * ss
        hi = H.upper.masked_fill(hinf, 0.0) * ss
    lam, diag = _curvature(lo, hi)  # [2, ..., k] (r and -r), [2, ..., k, n]
    ball = (lam.clamp(max=0) * -0.5).unsqueeze(-1).expand_as(diag)  # alpha~, beta~
    W = torch.stack([ball, diag], 1).flatten(0, 1)  # [4, ..., k, n], scaled
    # a non-finite weight (an unbounded or overflowing Hessian) marks the form bad; only
    # finite weights are mapped back, so no inf * 0 reaches the gradients
    drop = ~(W < torch.inf)  # W >= 0 or NaN
    if unbounded is not None:
        drop = drop | unbounded.unsqueeze(-1)
    Wf = W.masked_fill(drop, 0.0) * (1.0 / (s * s)).unsqueeze(-2)
    return Wf, linalg.small_reduce(drop, "any")


def _dc_bounds(
    rP: Tensor, gP: Tensor, dP: Tensor, W: Tensor, bad: Tensor
) -> tuple[Tensor, Tensor]:
    """Wang et al. 2022, eq. 15-16 for the four forms (ball and diagonal for ``r``, then for
    ``-r``), the tightest of those that exist -> ``(lower, upper)`` ``[..., k]``.

    ``rP [1 + N, ..., k]``: ``r`` at ``c`` (0) and the vertices; ``gP [P, ..., k, n]``: the
    gradient of ``r`` at the tangent points (``c``, then the vertices when ``P > 1``);
    ``dP [1 + N, ..., n]``: ``x - c`` at ``c`` (0) and the vertices; ``W [4, ..., k, n]``;
    ``bad [4, ..., k]``: the forms that do not exist.

    * eq. 15 (``r + q`` convex, its tangent at ``c`` is 0): ``r <= max_v (r(v) + q(v))``;
    * eq. 16: ``r + q`` lies above its tangent plane at ``p`` and ``q`` is quadratic, so
      ``r(x) >= r(p) + grad r(p).(x - p) - sum_j W_j (x_j - p_j)^2`` (the tangent plane
      minus ``q``, rewritten: no ``p x v x n`` tensor), a concave function of ``x`` whose
      minimum over the polytope is at a vertex. The best tangent point is kept.

    The forms of ``-r`` give the upper bound ``min_p max_v (L + Q)`` and the lower bound
    ``min_v (r(v) - q(v))`` the same way. Rounding: the terms are at most ``|r(p)|``,
    ``2 |grad r(p)| |x - c|`` and ``4 W |x - c|^2`` in magnitude, which the caller's padding
    covers. The tangent points go in chunks (memory ``chunk x N x 4 x batch x k``). From
    `_GEMM_MIN_PAIRS` (tangent point, vertex) pairs, the table is `_dc_bounds_gemm`'s matrix
    products instead.
    """
    P = gP.shape[0]
    dv = dP[1:]  # [N, ..., n]
    rv = rP[1:]
    if P * dv.shape[0] >= _GEMM_MIN_PAIRS:
        return _dc_bounds_gemm(rP, gP, dP, W, bad)
    neg = _form_signs(rv)  # -1 for the forms of r, +1 for those of -r: [4, 1.., 1]
    step = max(1, _TANGENT_ELEMS // max(1, 4 * dv.shape[0] * rv[0].numel()))
    M = V4 = None
    for p0 in range(0, P, step):
        sl = slice(p0, min(p0 + step, P))  # the tangent points only (dP has all 1 + N)
        dPs, gPs, rPs = (dP, gP, rP) if P == 1 + dv.shape[0] and step >= P else (
            dP[sl], gP[sl], rP[sl])  # (no slicing ops when one chunk holds every point)
        diff = materialize(dv.unsqueeze(0) - dPs.unsqueeze(1))  # [p, N, ..., n]: x_v - p
        # the tangent plane of r at p, at the vertices: [p, N, ..., k]
        L = materialize(
            linalg.small_dot(gPs.unsqueeze(1), diff.unsqueeze(-2)) + rPs.unsqueeze(1)
        )
        # Q = sum_j W_j (x_vj - p_j)^2 for the four forms: [p, N, 4, ..., k]
        Q = linalg.small_dot(W, materialize(diff * diff).unsqueeze(-2).unsqueeze(2))
        if V4 is None:  # eq. 15 with q at the vertices (p = c): max_v (q(v) +- r(v))
            V4 = torch.addcmul(Q[0], rv.unsqueeze(1), neg, value=-1.0).amax(0)  # [4, ..., k]
        # Q - L (forms of r) and Q + L (forms of -r), in place: -max_v is the tangent
        # bound's min_v for r, max_v the upper bound for -r
        m = Q.addcmul_(L.unsqueeze(2), neg).amax(1).amin(0)  # [4, ..., k]
        M = m if M is None else torch.minimum(M, m)
    return _tightest_forms(V4, M, bad)


def _tightest_forms(V4: Tensor, M: Tensor, bad: Tensor) -> tuple[Tensor, Tensor]:
    """The bounds of `_dc_bounds` from ``V4`` (eq. 15) and ``M`` (eq. 16), ``[4, ..., k]``
    each, the forms that do not exist (``bad``) dropped -> ``(lower, upper)`` ``[..., k]``."""
    # forms of r: upper V4 (eq. 15), lower -M (eq. 16); forms of -r: upper M, lower -V4
    pos = _form_signs(V4, positive=True)  # neg < 0
    upper = torch.where(pos, V4, M).masked_fill(bad, torch.inf).amin(0)
    lower = torch.where(pos, M, V4).masked_fill(bad, torch.inf).amin(0).neg()
    return lower, upper


def _dc_bounds_gemm(
    rP: Tensor, gP: Tensor, dP: Tensor, W: Tensor, bad: Tensor
) -> tuple[Tensor, Tensor]:
    """`_dc_bounds` (same arguments, same bounds up to rounding) with the table of every
    tangent point p, vertex v and form as one matrix product per batch element.

    Expanded about ``c`` (``x`` = ``x_v - c``, ``p`` = ``p - c``), the quantity maximised
    over the vertices, ``q(v) + sgn (r(p) + g.(x - p))`` with ``q = sum_j W_j (x_j - p_j)^2``
    and ``sgn = -1`` for the forms of r, +1 for those of -r (`_dc_bounds`' ``Q -+ L``), is
    ``[x^2, x, 1] . [W, -2 W p + sgn g, sum_j W_j p_j^2 + sgn (r(p) - g.p)]``: the vertices'
    features ``[N, 2n + 1]`` times the coefficients of each (tangent point, form, output)
    ``[2n + 1, P 4 k]``. Rounding: the ``2n + 1`` terms and the coefficients' own sums are
    at most ``W mag^2``, ``2 W mag^2``, ``|g| mag``, ``W mag^2``, ``|r(p)|`` and ``|g| mag``
    in magnitude (``|x|, |p| <= mag``), so the error is within about ``(3n + 4) eps`` times
    their sum, inside `dc_remainder`'s padding of `_PAD_ULPS` eps times its scale. Also
    while traced (an extern matrix product: a faster compiled step at the same compile
    time).
    """
    P, N = gP.shape[0], dP.shape[0] - 1
    k, n = gP.shape[-2], gP.shape[-1]
    batch = broadcast_shapes(dP.shape[1:-1], gP.shape[1:-2], W.shape[1:-2])
    b = math.prod(batch)

    def front(t: Tensor, lead: int, inner: tuple[int, ...]) -> Tensor:  # [b, lead, *inner]
        if len(batch) != 1 or t.shape[1:-len(inner)] != batch:
            t = t.expand(lead, *batch, *inner).reshape(lead, b, *inner)
        return t.transpose(0, 1)

    d, g = front(dP, 1 + N, (n,)), front(gP, P, (k, n))  # [b, 1 + N, n], [b, P, k, n]
    r, w = front(rP, 1 + N, (k,)), front(W, 4, (k, n))  # [b, 1 + N, k], [b, 4, k, n]
    rows = max(1, _GEMM_CHUNK_ELEMS // (N * P * 4 * k))  # batch elements per chunk of the table
    if tracing():  # the chunks are unrolled in the graph: at most P of them, as `_dc_bounds`
        rows = max(rows, -(-b // P))
    if b <= rows:
        V4, M = _gemm_chunk(d, g, r, w)
    else:
        parts = [_gemm_chunk(d[s : s + rows], g[s : s + rows], r[s : s + rows],
                             w[s : s + rows]) for s in range(0, b, rows)]
        V4, M = (torch.cat(t) for t in zip(*parts))
    V4, M = (t.transpose(0, 1) for t in (V4, M))  # [4, b, k]
    if len(batch) != 1:
        V4, M = (t.reshape(4, *batch, k) for t in (V4, M))
    return _tightest_forms(V4, M, bad)


def _gemm_chunk(d: Tensor, g: Tensor, r: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """`_dc_bounds_gemm` on ``b`` batch elements: ``d [b, 1 + N, n]`` (``x - c`` at ``c`` and
    the vertices), ``g [b, P, k, n]``, ``r [b, 1 + N, k]``, ``w [b, 4, k, n]`` -> ``(V4, M)``
    ``[b, 4, k]`` each (eq. 15 and eq. 16's ``min_p max_v``)."""
    b, P, k, n = g.shape
    N = d.shape[1] - 1
    sgn = _form_signs(w, rank=2)  # [4, 1]: against [b, P, 4, k]
    x, p = d[:, 1:], d[:, :P].unsqueeze(-2)  # [b, N, n], [b, P, 1, n]
    wp = w.unsqueeze(1) * p.unsqueeze(-2)  # [b, P, 4, k, n]
    lin = torch.addcmul(wp * -2.0, sgn.unsqueeze(-1), g.unsqueeze(2))
    rc = (r[:, :P] - (g * p).sum(-1)).unsqueeze(2)  # [b, P, 1, k]: r(p) - g.p
    const = torch.addcmul((wp * p.unsqueeze(-2)).sum(-1), sgn, rc)  # [b, P, 4, k]
    coef = torch.cat([w.unsqueeze(1).expand(b, P, 4, k, n), lin, const.unsqueeze(-1)], -1)
    x2 = x * x
    feats = torch.cat([x2, x, torch.ones_like(x[..., :1])], -1)  # [b, N, 2n + 1]
    table = torch.bmm(feats, coef.reshape(b, P * 4 * k, 2 * n + 1).mT)  # [b, N, P 4 k]
    M = table.amax(1).reshape(b, P, 4, k).amin(1)  # [b, 4, k]
    # eq. 15 (p = c): max_v (q(v) - sgn r(v)), q(v) = sum_j W_j x_vj^2
    q = torch.bmm(x2, w.reshape(b, 4 * k, n).mT).reshape(b, N, 4, k)
    V4 = torch.addcmul(q, r[:, 1:].unsqueeze(2), sgn, value=-1.0).amax(1)  # [b, 4, k]
    return V4, M


_SIGNS: dict = {}


def _form_signs(like: Tensor, positive: bool = False, rank: int | None = None) -> Tensor:
    """``[-1, -1, 1, 1]`` shaped ``[4, 1, .., 1]`` against ``[4, *like.shape[1:]]`` (``rank``
    dims, ``like``'s rank by default; cached per dtype, device and rank in eager mode: a
    constant, not an op per call); ``positive``: the boolean ``[True, True, False, False]``
    (the signs < 0) instead."""
    rank = like.dim() if rank is None else rank

    def make() -> Tensor:
        t = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=like.dtype, device=like.device)
        t = t.reshape(4, *([1] * (rank - 1)))
        return t < 0 if positive else t

    return eager_constant(_SIGNS, (like.dtype, like.device, rank, positive), make)


def dc_remainder(
    fn: Fn,
    S: ConvexSet,
    c: Tensor,
    J: Tensor | None = None,
    *,
    max_vertices: int = MAX_VERTICES,
    max_tangents: int = MAX_TANGENTS,
    with_lagrange: bool = False,
) -> Interval:
    """Difference-of-convex remainder bound at the set's vertices -> Interval ``[..., k]``.

    Wang et al. 2022, eq. 14-18 with the erratum (docs/errata.md): per output i, ``r_i = g1 - g2``
    with ``g1 = r_i + q`` convex and ``g2 = q`` a convex quadratic centred at ``c``. The
    paper's ``q = alpha_i |x - c|^2`` uses ``alpha_i = max(0, -lambda_min / 2)`` from a
    guaranteed lower bound of the smallest eigenvalue of the interval Hessian of ``fn_i`` over
    the hull of ``S`` and ``c`` (`hessian_eig_lower_bound`); a second, diagonal
    ``q = sum_j w_ij (x_j - c_j)^2`` (`diagonal_shift`, tighter when the curvature lies
    along few axes) is also used and the tighter bound kept. Deviation (scale invariance):
    both are computed in the coordinates normalised by the hull's half-widths, so the ball is
    ``alpha_i |diag(s)^-1 (x - c)|^2`` (`_convexifying_weights`; the paper's ball for a
    cube) and the bound does not depend on the units of the states. Then

    * upper (eq. 15, tangent of g2 at c is 0): ``r <= g1 <= max_v g1(v)`` over the vertices;
    * lower (eq. 16): for a tangent point p (``c`` and, for few vertices, every vertex)
      ``r >= g1(p) + grad g1(p).(x - p) - q(x)``, a concave function whose minimum over the
      polytope is attained at a vertex. Gradients are exact (autograd), never Stirling slopes.

    The same construction applied to ``-r`` (convexifying ``-H``) gives a second lower and upper
    bound; the intersection is returned. Vertices: box corners, parallelotope vertices, the 2m
    vertices of a planar zonotope, or ``c + G s`` over all sign vectors (at most
    ``max_vertices``). For an Ellipsoid or a zonotope with more sign vectors, the corners of
    the interval hull (a containing box) are used instead, and the result is always intersected
    with the Lagrange bound (documented deviation: the paper only treats parallelotopes).
    Tangent planes are taken at every vertex while there are at most ``max_tangents``
    vertices, at ``c`` only above. ``with_lagrange=True`` also intersects with the Lagrange
    bound (same interval Hessian).
    """
    c, J = _check(S, c, J)
    if _known_affine(fn):
        return _affine_remainder(fn, S, c, J)
    V, exact = _extreme_points(S, max_vertices)
    with_lagrange = with_lagrange or not exact
    box = _hull_with(S, c)
    jet = jet_eval(fn, box, order=2)
    if _remember(fn, jet):  # same result as every later call (which skips the jets)
        return _affine_remainder(fn, S, c, J)
    H = jet.hess  # [..., k, n, n]
    # eagerly, one host read: the sum of |bounds| is 0 for a zero Hessian, finite for a
    # finite one (an overflowing sum only takes the general, masked path)
    mass = None if tracing() else _abs_sum(H)
    if mass == 0.0:
        # fn is affine on the hull: r(x) = (J_exact - J)(x - c) exactly, no vertices needed
        R = _lagrange(jet, box, S, c, J, None if J is None else jacobian(fn, c) - J)
        return _lower_order(fn, jet, box, S, c, J, R)
    # the four convexifications at once (leading dim 4): r + q convex with q the ball
    # (alpha |x - c|^2) or the diagonal shift, and -r + q convex with the same two forms
    W, bad = _convexifying_weights(  # [4, ..., k, n], [4, ..., k]
        H, box, mass is not None and mass < math.inf)
    W = materialize(W)
    Vf = _front(V)  # [N, ..., n]
    tangents = V.shape[-2] <= max_tangents  # tangent planes at the vertices too
    c0 = c if c.shape == Vf.shape[1:] else torch.broadcast_to(c, Vf.shape[1:])
    pts = torch.cat([c0.unsqueeze(0), Vf])  # [1 + N, ..., n]
    if tangents:  # one batched autograd call: values and gradients at c and the vertices
        fall, Jall = value_and_jacobian(fn, pts, points=True)  # [1 + N, ..., k (, n)]
    else:
        fall, Jall = fn(pts), jacobian(fn, c).unsqueeze(0)
    Jc = Jall[0]  # [..., k, n]
    J = materialize(Jc if J is None else J)
    dP = materialize(pts - c)  # [1 + N, ..., n]: exactly 0 at c
    # r at c (exactly 0) and the vertices
    rP = fall - fall[0] - linalg.small_dot(J, dP.unsqueeze(-2))
    gP = materialize(Jall - J)  # [P, ..., k, n]: gradients of r at the tangent points
    lower, upper = _dc_bounds(rP, gP, dP, W, bad)  # [..., k]
    # rounding scale: magnitudes of every term summed above (|r| at the points, the tangent
    # planes' slopes and the quadratics over the hull, c included: box - c covers x - c).
    # The tangent bound is evaluated as r(p) + g.(x_v - p) - sum_j W_j (x_vj - p_j)^2, not as
    # the paper's tangent of r + q minus q: the same number in exact arithmetic, other last
    # bits in floats. Each term is at most 2 |g| mag or 4 W mag^2 (|x_v - p| <= 2 mag), the
    # error of the evaluation at most (n + 3) eps times their sum ((3n + 4) eps for the
    # expanded form of `_dc_bounds_gemm`, whose terms are bounded by the same magnitudes),
    # well inside the padding of _PAD_ULPS eps times this scale (4 |g| mag + 4 W mag^2 +
    # 2 max|f| + ...).
    jv = _abs_max(jet.val)  # rounding of fn at interior points
    dl, du = box.lower - c, box.upper - c
    mag = torch.maximum(du, dl.neg())  # [..., n] >= |x - c| on the hull
    mag2 = mag.unsqueeze(-2)
    G = gP.abs().amax(0) + J.abs() + W.amax(0) * mag2  # [..., k, n]
    scale = fall.abs().amax(0) * 2.0 + jv + linalg.small_dot(G, mag2) * 4.0
    out = _padded(lower, upper, scale)
    if with_lagrange:
        out = out.intersect(_lagrange(jet, box, S, c, J, Jc - J))
    return _lower_order(fn, jet, box, S, c, J, out, jv, (dl, du, mag))
