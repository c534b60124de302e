"""Rules of reductions (sum, mean, cumsum, prod, amax, norms) and of matrix products.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval.box import Interval
from diffsmf.interval.jet import hadd, mul, point
from diffsmf.interval.rounding import down, up
from diffsmf.interval.rules.arithmetic import _div, _linear_combo, _pow_scalar
from diffsmf.interval.rules.base import Ctx, _is_jet, _map_piece, _neg_dim, aten, register
from diffsmf.interval.rules.elementwise import _sqrt_j
from diffsmf.interval.rules.nonsmooth import _abs_j

__all__ = []

# ----------------------------------------------------------------------------- reductions
def _dims(ctx: Ctx, dim: Any) -> list[int]:
    r = ctx.rank(0)
    if dim is None or (isinstance(dim, (list, tuple)) and len(dim) == 0):
        return list(range(-r, 0))
    dims = dim if isinstance(dim, (list, tuple)) else [dim]
    return [_neg_dim(d, r) for d in dims]


@register(aten.sum, category="reduction")
def _sum(ctx: Ctx, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None) -> Any:
    dims = _dims(ctx, dim)
    if not _is_jet(x):
        return x.sum(dims, keepdim=keepdim) if dims else x
    if not dims:
        return x

    def s(t: Interval | None) -> Interval | None:
        return None if t is None else t.sum(dims, keepdim)

    return x.like(s(x.val), s(x.grad), s(x.hess))


@register(aten.mean, category="reduction")
def _mean(ctx: Ctx, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None) -> Any:
    dims = _dims(ctx, dim)
    if not _is_jet(x):
        return x.mean(dims, keepdim=keepdim)
    count = math.prod(x.shape[d] for d in dims)
    return _div(ctx, _sum(ctx, x, dim, keepdim), float(count))


@register(aten.cumsum, category="reduction")
def _cumsum(ctx: Ctx, x: Any, dim: int, *, dtype: Any = None) -> Any:
    d = _neg_dim(dim, ctx.rank(0))
    if not _is_jet(x):
        return x.cumsum(d)
    k = x.shape[d]

    def cs(t: Interval | None) -> Interval | None:
        if t is None:
            return None
        g = (k + 4) * torch.finfo(t.lower.dtype).eps
        tiny = k * torch.finfo(t.lower.dtype).tiny
        lo = t.lower.cumsum(d) - (g * t.lower.detach().abs().cumsum(d) + tiny)
        hi = t.upper.cumsum(d) + (g * t.upper.detach().abs().cumsum(d) + tiny)
        return Interval._make(down(lo), up(hi))

    return x.like(cs(x.val), cs(x.grad), cs(x.hess))


@register(aten.prod, category="reduction")
def _prod(ctx: Ctx, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None) -> Any:
    if not _is_jet(x):
        return x.prod(dim, keepdim=keepdim) if dim is not None else x.prod()
    if dim is None:
        flat = _map_piece(x, ctx.rank(0), lambda t, p: t.flatten(p) if t.dim() > p else
                          t.unsqueeze(-1))
        return _prod(Ctx((1,), 0, ctx.name), flat, 0, False)
    d = _neg_dim(dim, ctx.rank(0))
    k = x.shape[d]
    out = _map_piece(x, ctx.rank(0), lambda t, p: t.select(d, 0))
    for i in range(1, k):
        out = mul(out, _map_piece(x, ctx.rank(0), lambda t, p, i=i: t.select(d, i)))
    if keepdim:
        out = _map_piece(out, ctx.rank(0) - 1, lambda t, p: t.unsqueeze(d))
    return out


@register(aten.amax, aten.amin, category="reduction")
def _amax(ctx: Ctx, x: Any, dim: Any = (), keepdim: bool = False) -> Any:
    is_max = "amax" in ctx.name
    dims = _dims(ctx, dim)
    if not _is_jet(x):
        return x.amax(dims, keepdim) if is_max else x.amin(dims, keepdim)
    # the value range is exact; derivatives: hull over the entries that can be extreme
    lo, hi = x.val.lower, x.val.upper
    if is_max:
        v = Interval._make(lo.amax(dims, keepdim=True), hi.amax(dims, keepdim=True))
        cand = hi >= v.lower
    else:
        v = Interval._make(lo.amin(dims, keepdim=True), hi.amin(dims, keepdim=True))
        cand = lo <= v.upper
    single = cand.sum(dims, keepdim=True) == 1

    def red(t: Interval | None, k: int) -> Interval | None:
        if t is None:
            return None
        c = cand[(None,) * k] if k else cand
        inf = torch.full_like(t.lower, torch.inf)
        dd = [d for d in dims]
        lo_ = torch.where(c, t.lower, inf).amin(dd, keepdim=True)
        hi_ = torch.where(c, t.upper, -inf).amax(dd, keepdim=True)
        return Interval._make(lo_, hi_)

    grad = red(x.grad, 1)
    hess = red(x.hess, 2)
    if hess is not None or (x.order >= 2 and grad is not None):
        if hess is None:
            hess = point(torch.zeros((x.n, x.n, *v.lower.shape), dtype=lo.dtype,
                                     device=lo.device))
        inf = torch.full_like(hess.lower, torch.inf)
        s = single[(None, None)]
        hess = Interval._make(torch.where(s, hess.lower, -inf), torch.where(s, hess.upper, inf))
    out = x.like(v, grad, hess)
    if not keepdim:
        out = _map_piece(out, ctx.rank(0), lambda t, p: t.squeeze(dims))
    return out


@register(aten.linalg_vector_norm, category="reduction")
def _vnorm(ctx: Ctx, x: Any, ord: float = 2, dim: Any = None, keepdim: bool = False,
           *, dtype: Any = None) -> Any:
    if not _is_jet(x):
        return torch.linalg.vector_norm(x, ord, dim, keepdim)
    if ord == 2:
        return _sqrt_j(_sum(ctx, mul(x, x), dim, keepdim))
    if ord == 1:
        return _sum(ctx, _abs_j(x), dim, keepdim)
    if ord == math.inf:
        return _amax(Ctx(ctx.ranks, ctx.out_rank, "amax"), _abs_j(x), dim or (), keepdim)
    p = float(ord)
    return _pow_scalar(_sum(ctx, _pow_scalar(_abs_j(x), p), dim, keepdim), 1.0 / p)


# ----------------------------------------------------------------------------- linear algebra
def _matmul_jets(a: Any, b: Any) -> Any:
    """``a @ b`` with torch.matmul semantics on the trailing dims (jets or constants)."""
    if not _is_jet(a) and not _is_jet(b):
        return torch.matmul(a, b)
    if _is_jet(a) and not _is_jet(b):
        B = torch.as_tensor(b, dtype=a.val.lower.dtype)
        mm = lambda t: _iv_matmul(t, B, right=True)  # noqa: E731
        return a.like(mm(a.val), move_iv(a.grad, mm), move_iv(a.hess, mm))
    if _is_jet(b) and not _is_jet(a):
        A = torch.as_tensor(a, dtype=b.val.lower.dtype)
        mm = lambda t: _iv_matmul(t, A, right=False)  # noqa: E731
        return b.like(mm(b.val), move_iv(b.grad, mm), move_iv(b.hess, mm))
    # both depend on x: product rule with interval matrix products
    grad = hadd(None if a.grad is None else a.grad.__matmul__(_t(b.val, 1)),
                None if b.grad is None else _t(a.val, 1).__matmul__(b.grad))
    hess = None
    if a.order >= 2:
        cross = None
        if a.grad is not None and b.grad is not None:
            ga = Interval._make(a.grad.lower.unsqueeze(1), a.grad.upper.unsqueeze(1))
            gb = Interval._make(b.grad.lower.unsqueeze(0), b.grad.upper.unsqueeze(0))
            o = ga.__matmul__(gb)
            cross = o + Interval._make(o.lower.transpose(0, 1), o.upper.transpose(0, 1))
        hess = hadd(None if a.hess is None else a.hess.__matmul__(_t(b.val, 2)),
                    None if b.hess is None else _t(a.val, 2).__matmul__(b.hess), cross)
    return a.like(a.val.__matmul__(b.val), grad, hess)


def move_iv(t: Interval | None, fn: Callable[[Interval], Interval]) -> Interval | None:
    return None if t is None else fn(t)


def _iv_matmul(t: Interval, M: Tensor, right: bool) -> Interval:
    """``t @ M`` (``right``) or ``M @ t`` for an interval array and a constant matrix.

    Finite bounds: the midpoint-radius product with its rounding bound. Infinite bounds (a
    derivative that does not exist) are kept apart so that ``0 * inf`` never makes a NaN: a
    result bound is infinite exactly where an infinite bound meets a non-zero coefficient.
    """
    fin = torch.isfinite(t.lower) & torch.isfinite(t.upper)
    if not torch.compiler.is_compiling() and bool(fin.all()):
        # explicit method calls: Dynamo reflects `interval @ tensor` into `tensor @ interval`
        return t.__matmul__(M) if right else t.__rmatmul__(M)
    z = torch.zeros_like(t.lower)
    safe = Interval._make(torch.where(fin, t.lower, z), torch.where(fin, t.upper, z))
    out = safe.__matmul__(M) if right else safe.__rmatmul__(M)
    nz = (M != 0).to(t.lower.dtype)
    lo_inf = torch.isinf(t.lower).to(t.lower.dtype)
    hi_inf = torch.isinf(t.upper).to(t.lower.dtype)
    hit = (lo_inf + hi_inf) @ nz if right else nz @ (lo_inf + hi_inf)
    inf = torch.full_like(out.lower, torch.inf)
    return Interval._make(torch.where(hit > 0, -inf, out.lower),
                          torch.where(hit > 0, inf, out.upper))


def _t(v: Interval, k: int) -> Interval:
    idx = (None,) * k
    return Interval._make(v.lower[idx], v.upper[idx])


@register(aten.mm, aten.bmm, aten.matmul, aten.mv, aten.dot, category="linear algebra")
def _mm(ctx: Ctx, a: Any, b: Any) -> Any:
    return _matmul_jets(a, b)


@register(aten.addmm, category="linear algebra")
def _addmm(ctx: Ctx, bias: Any, a: Any, b: Any, *, beta: float = 1, alpha: float = 1) -> Any:
    return _linear_combo(bias, _matmul_jets(a, b), beta, alpha)
