"""Interval arrays: Moore interval arithmetic with outward rounding (Song et al. 2017, sec. 3).

Functions on interval arrays (objects with ``lower`` and ``upper`` tensors of one shape, the
`IntervalArray` interface that ``diffsmf.Interval`` implements): sums, products, quotients,
powers, monotone and trigonometric functions, reductions and matrix products, each enclosing
the exact real result. Results are built with the class of an operand (``a._make``), so this
module never imports the box set.

Outward rounding (guarantee): after every arithmetic operation the lower bound is moved down
and the upper bound up by at least ``k`` units in the last place (`diffsmf.interval.rounding`:
one ``nextafter`` for correctly rounded IEEE operations ``+ - * / sqrt``, ``eps |x|`` for sums,
a relative offset for library functions, ``k = 2``, and ``x ** p``, ``k = |p| + 1``). Sums and
matrix products add the classical a-priori bound ``gamma_k * sum |terms|``
(``gamma_k = (k + 4) eps``) before rounding. Gradients of ``lower``/``upper`` flow unchanged.

Stacked mode (`Stacked`, `stacking`): while the engine evaluates a captured program eagerly
on a small box, or at any size while traced, non-point results are stored as one tensor
``[2, ...]`` (lower, upper), so that the elementwise operations here treat both bounds in one
op. Eagerly, the products defer their check for ``0 * inf`` to one read of the host per
program run; while traced (or on an accelerator) each takes a branch-free rule instead.

`TORCH_IMPL` maps torch functions to their interval extensions (the ``__torch_function__``
hook of ``Interval``), so that ``diffsmf.interval.box.interval_eval`` evaluates a plain torch
function on interval arrays.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor

from diffsmf.convex import as_tensor
from diffsmf.interval.finite_grad import mm, times
from diffsmf.interval.rounding import (
    down,
    eps,
    finite_inner,
    nan_to_zero,
    outward,
    pair_const,
    pair_signs,
    tiny,
    up,
)
from diffsmf.utils import checking, tracing

__all__ = [
    "IntervalArray", "absolute", "add", "as_interval", "clamp", "div", "is_number", "is_point",
    "matmul", "mm", "monotone", "mul", "power", "quotient_nonneg", "reciprocal", "relu", "rpow",
    "scale", "shift", "square", "sub", "times", "total", "trig",
]

_TWO_PI = 2.0 * math.pi


class IntervalArray:
    """Interface of an interval array: ``lower`` and ``upper`` tensors of one shape.

    ``_make(lower, upper)`` builds one without validation; the arithmetic below returns
    objects of its operands' class.
    """

    __slots__ = ()
    lower: Tensor
    upper: Tensor

    @classmethod
    def _make(cls, lower: Tensor, upper: Tensor) -> Any:
        """Fast constructor without validation (internal)."""
        obj = object.__new__(cls)
        object.__setattr__(obj, "lower", lower)
        object.__setattr__(obj, "upper", upper)
        return obj


    @classmethod
    def _pair(cls, both: Tensor) -> Any:
        """An interval array from its bounds stacked as ``both [2, ...]`` (lower, upper)."""
        return cls._make(both[0], both[1])


class Stacked:
    """Mixin of an interval array stored as one tensor ``both [2, ...]`` (lower, upper).

    The elementwise arithmetic below then treats both bounds in one op (one product, one
    rounding, one move); ``lower`` and ``upper`` are views made on first use. Results of
    other operations are plain arrays (``_make``).
    """

    both: Tensor

    @classmethod
    def _new(cls, both: Tensor) -> Any:
        obj = object.__new__(cls)
        object.__setattr__(obj, "both", both)
        return obj

    @property
    def lower(self) -> Tensor:  # type: ignore[override]
        lo = self.__dict__.get("_lo")
        if lo is None:
            lo = self.both[0]
            object.__setattr__(self, "_lo", lo)
        return lo

    @property
    def upper(self) -> Tensor:  # type: ignore[override]
        hi = self.__dict__.get("_hi")
        if hi is None:
            hi = self.both[1]
            object.__setattr__(self, "_hi", hi)
        return hi


Iv = IntervalArray


def _st(a: Any) -> Tensor | None:
    """The stacked bounds ``[2, ...]`` of ``a``, or None."""
    return a.both if isinstance(a, Stacked) else None


def _lift(both: Tensor, rank: int, outer: int = -1) -> Tensor:
    """Stacked bounds ``[2, *s]`` viewed with at least ``rank`` dims after the first (leading
    singleton dims: broadcasting against tangents that lead); ``outer`` 0 or 1: the bounds dim
    becomes ``[2, 1]`` or ``[1, 2]`` (for the four products), in the same view."""
    k = max(rank - (both.dim() - 1), 0)
    head = (2,) if outer < 0 else ((2, 1) if outer == 0 else (1, 2))
    if k == 0 and outer < 0:
        return both
    return both.reshape(*head, *([1] * k), *both.shape[1:])


class _Mode(threading.local):
    """Per-thread state: ``stack`` (stacked mode: the engine's evaluation of a program;
    every non-point result is stacked, plain operands are stacked on first use) and
    ``checks`` (see `deferred_checks`)."""

    def __init__(self) -> None:  # (instance attributes from the start: Dynamo guards on them)
        self.stack = False
        self.checks: list | None = None


_M = _Mode()


def stacking(on: bool) -> bool:
    """Switch stacked mode; returns the previous state (see `Stacked`)."""
    prev = _M.stack
    _M.stack = on
    return prev


@contextmanager
def deferred_checks(checks: list) -> Iterator[None]:
    """Within: stacked products skip their own NaN check and append their lower bounds to
    ``checks``; `products_ok` then checks them all (one host read). Where it fails, the
    caller evaluates again outside (each product then falls back to the general rule)."""
    prev = _M.checks
    _M.checks = checks
    try:
        yield
    finally:
        _M.checks = prev


def products_ok(checks: list) -> bool:
    """True when no tensor of ``checks`` holds a NaN (two ops and one host read)."""
    if not checks:
        return True
    norms = torch._foreach_norm(checks)  # NaN where a NaN is; inf where an inf is
    return not any(math.isnan(v) for v in torch.stack(norms).tolist())


def _as_stacked(a: Iv) -> Tensor:
    lo, hi = a.lower, a.upper
    if lo.shape != hi.shape:
        lo, hi = torch.broadcast_tensors(lo, hi)
    return torch.stack([lo, hi])


def _stacked_pair(a: Iv, b: Iv, outer: bool = False) -> tuple[Tensor, Tensor] | None:
    """Both operands as ``[2, ...]`` tensors that broadcast together (a point as ``[...]``), or
    None when neither is stacked (outside stacked mode) or one is a plain non-point array."""
    sa, sb = _st(a), _st(b)
    if sa is None and sb is None and not _M.stack:
        return None
    pa, pb = is_point(a), is_point(b)
    if sa is None and not pa:
        if not _M.stack:
            return None
        sa = _as_stacked(a)
    if sb is None and not pb:
        if not _M.stack:
            return None
        sb = _as_stacked(b)
    ta = sa if sa is not None else a.lower
    tb = sb if sb is not None else b.lower
    r = max(ta.dim() - (sa is not None), tb.dim() - (sb is not None))
    both = outer and sa is not None and sb is not None
    if sa is not None:
        ta = _lift(ta, r, 0 if both else -1)
    if sb is not None:
        tb = _lift(tb, r, 1 if both else -1)
    return ta, tb


# ---------------------------------------------------------------------------- primitives
def as_interval(x: Any, like: Iv | None = None) -> Any:
    """Interval, tensor or number -> interval array like ``like`` (points become degenerate
    intervals); ``like`` is needed unless ``x`` is an interval array."""
    if isinstance(x, IntervalArray):
        if like is not None and x.lower.dtype != like.lower.dtype:
            dt = torch.promote_types(x.lower.dtype, like.lower.dtype)
            return x._make(x.lower.to(dt), x.upper.to(dt))
        return x
    if like is None:
        raise TypeError(f"as_interval: no interval array to take the class of ({type(x)})")
    ref = like.lower
    if isinstance(x, Tensor) and x.is_floating_point():
        dt = torch.promote_types(x.dtype, ref.dtype)
        t = x.to(dtype=dt, device=ref.device)
    else:
        t = as_tensor("operand", x, like=ref)
    return like._make(t, t)


def is_point(a: Iv) -> bool:
    """True when ``a`` is a point interval by construction (``lower is upper``): the
    arithmetic then computes its bound once."""
    return not isinstance(a, Stacked) and a.lower is a.upper


def add(a: Iv, b: Iv, exact_zero: bool = True) -> Any:
    """``[a] + [b]`` (Song et al. 2017, sec. 3): ``[a_lo + b_lo, a_hi + b_hi]`` rounded outward.

    A zero sum of floats is exact and kept (``exact_zero``; two ops a bound more), or, with
    ``exact_zero=False``, widened to the smallest subnormal like any other result.
    """
    if is_point(a) and is_point(b):
        s = a.lower + b.lower
        if _M.stack:
            return a._pair(outward(s, absolute=not exact_zero, point=True))
        return a._make(down(s, absolute=not exact_zero), up(s, absolute=not exact_zero))
    st = _stacked_pair(a, b)
    if st is not None:
        return a._pair(outward(st[0] + st[1], absolute=not exact_zero))
    lo, hi = a.lower + b.lower, a.upper + b.upper
    return a._make(down(lo, absolute=not exact_zero), up(hi, absolute=not exact_zero))


def _flip(t: Tensor) -> Tensor:
    """Stacked bounds with lower and upper exchanged."""
    return t.flip(0)


def neg(a: Iv) -> Any:
    """``-[a]`` (exact)."""
    sa = _st(a)
    if sa is not None:
        return a._pair(-_flip(sa))
    if is_point(a):
        n = -a.lower
        return a._make(n, n)
    return a._make(-a.upper, -a.lower)


def sub(a: Iv, b: Iv, exact_zero: bool = True) -> Any:
    """``[a] - [b] = [a_lo - b_hi, a_hi - b_lo]`` rounded outward (see `add`)."""
    if is_point(a) and is_point(b):
        s = a.lower - b.lower
        if _M.stack:
            return a._pair(outward(s, absolute=not exact_zero, point=True))
        return a._make(down(s, absolute=not exact_zero), up(s, absolute=not exact_zero))
    st = _stacked_pair(a, b)
    if st is not None:
        tb = st[1] if is_point(b) else _flip(st[1])
        return a._pair(outward(st[0] - tb, absolute=not exact_zero))
    lo, hi = a.lower - b.upper, a.upper - b.lower
    return a._make(down(lo, absolute=not exact_zero), up(hi, absolute=not exact_zero))


def mul(a: Iv, b: Iv) -> Any:
    """``[a] * [b]`` (Song et al. 2017, sec. 3): the hull of the endpoint products, with
    ``0 * inf := 0``; a NaN operand (an enclosure outside its domain) stays NaN.

    A point operand costs two products, two points one. Eagerly, the products are first
    combined by NaN-propagating min/max; only where that meets a NaN (``0 * inf`` or a NaN
    operand; one host read of the lower bounds' sum: an eager-only shortcut on the CPU that
    saves about ten ops a product) is the general rule taken, which it always is while
    tracing and on an accelerator (no host sync there): `_mul_stacked_general` for stacked
    operands, `_mul_general` for separate bounds.
    """
    pa, pb = is_point(a), is_point(b)
    if pa and pb:
        p = times(a.lower, b.lower)
        return a._pair(outward(p, point=True)) if _M.stack else a._make(down(p), up(p))
    st = _stacked_pair(a, b, outer=True)
    if tracing() or tensor_of(a).device.type != "cpu":
        if st is not None:
            return _mul_stacked_general(a, b, st[0], st[1])
        return _mul_general(a, b)
    if st is not None:
        return _mul_stacked(a, b, st[0], st[1])
    if pa or pb:
        c, x = (a.lower, b) if pa else (b.lower, a)
        u, v = times(c, x.lower), times(c, x.upper)
        lo, hi = torch.minimum(u, v), torch.maximum(u, v)
    else:
        p1, p2 = times(a.lower, b.lower), times(a.lower, b.upper)
        p3, p4 = times(a.upper, b.lower), times(a.upper, b.upper)
        lo = torch.minimum(torch.minimum(p1, p2), torch.minimum(p3, p4))
        hi = torch.maximum(torch.maximum(p1, p2), torch.maximum(p3, p4))
    if math.isnan(lo.sum().item()):  # NaN-ness of lo and hi agree (same products); a sum of
        return _mul_general(a, b)  # -inf and inf (NaN) takes the general rule too
    return a._make(down(lo), up(hi))


def _mul_stacked(a: Iv, b: Iv, ta: Tensor, tb: Tensor) -> Any:
    """`mul` with stacked operands ``[2, ...]`` (a point as ``[...]``), eagerly."""
    if is_point(a) or is_point(b):  # a point times a pair: the two products, sorted
        both = torch.sort(times(ta, tb), dim=0).values
    else:  # [2, 1, ...] * [1, 2, ...]: the four products, the smallest and the largest
        both = torch.sort(times(ta, tb).flatten(0, 1), dim=0).values[::3]
    if _M.checks is not None:
        _M.checks.append(both)
    elif math.isnan(both.sum().item()):  # 0 * inf or a NaN operand: the general rule
        return _mul_general(a, b)
    return a._pair(outward(both))


def mul_sum(x1: Iv, y1: Iv, x2: Iv, y2: Iv) -> Any | None:
    """``[x1] [y1] + [x2] [y2]`` in stacked mode, the two products in one (each rounded
    outward as `mul` rounds it, then the sum as `add` with ``exact_zero=False``: the same
    bounds), or None where it does not apply (the caller then multiplies and adds: operands
    not all stacked, shapes that differ between the terms, or a NaN product while the checks
    are not deferred)."""
    if not _M.stack or tracing():
        return None
    ts = [_st(t) for t in (x1, y1, x2, y2)]
    if any(t is None for t in ts) or ts[0].shape != ts[2].shape or ts[1].shape != ts[3].shape:
        return None
    if ts[0].device.type != "cpu":
        return None
    sx, sy = ts[0].shape[1:], ts[1].shape[1:]
    r = max(len(sx), len(sy))
    # [2, 1, 2 terms, 1.., *sx] * [1, 2, 2 terms, 1.., *sy]: the four products of each term
    X = torch.stack([ts[0], ts[2]], 1).reshape(2, 1, 2, *([1] * (r - len(sx))), *sx)
    Y = torch.stack([ts[1], ts[3]], 1).reshape(1, 2, 2, *([1] * (r - len(sy))), *sy)
    both = torch.sort(times(X, Y).flatten(0, 1), dim=0).values[::3]  # [2, 2 terms, ...]
    if _M.checks is not None:
        _M.checks.append(both)
    elif math.isnan(both.sum().item()):
        return None
    return x1._pair(outward(outward(both).sum(1)))


def _mul_stacked_general(a: Iv, b: Iv, ta: Tensor, tb: Tensor) -> Any:
    """`_mul_general` on stacked operands ``[2, ...]`` (a point as ``[...]``; two stacked
    operands lifted to ``[2, 1, ...]`` and ``[1, 2, ...]``, as `_stacked_pair` gives them)."""
    return a._pair(_products_hull(ta, tb, is_point(a), is_point(b)))


def _mul_general(a: Iv, b: Iv) -> Any:
    """`mul` of separate bounds (any shapes, traceable): the bounds stacked as ``[2, 1, ...]``
    and ``[1, 2, ...]`` for `_products_hull`."""
    al, au, bl, bu = torch.broadcast_tensors(a.lower, a.upper, b.lower, b.upper)
    both = _products_hull(torch.stack([al, au]).unsqueeze(1),
                          torch.stack([bl, bu]).unsqueeze(0), False, False)
    return a._make(both[0], both[1])


def _products_hull(ta: Tensor, tb: Tensor, pa: bool, pb: bool) -> Tensor:
    """The product rule without a host read: the endpoint products of ``ta`` and ``tb``
    (stacked ``[2, 1, ...]`` and ``[1, 2, ...]``, or a point ``[...]`` (``pa`` / ``pb``) and
    a stacked ``[2, ...]``) with ``0 * inf := 0``, their least and greatest, rounded outward
    -> ``[2, ...]``; NaN where an operand is NaN."""
    p = times(ta, tb)
    if not (pa or pb):
        p = p.flatten(0, 1)
    lo, hi = torch.aminmax(torch.nan_to_num(p, nan=0.0, posinf=math.inf, neginf=-math.inf), dim=0)
    both = outward(torch.stack([lo, hi]))
    na = torch.isnan(ta) if pa else torch.isnan(ta).any(0)
    nb = torch.isnan(tb) if pb else torch.isnan(tb).any(1 if not pa else 0)
    if not (pa or pb):
        na, nb = na.squeeze(0), nb.squeeze(0)
    return torch.where(na | nb, math.nan, both)


def scale(a: Iv, s: float) -> Any:
    """``[a] * s`` for a Python number ``s`` (two products instead of four; a point: one).

    ``s = +-2^k`` with ``k >= 0`` is exact but for overflow, where the inner bound is clamped
    to the largest finite float instead of rounded."""
    if s == 0:
        z = torch.zeros_like(a.lower)
        return a._make(z, z)
    exact = abs(s) >= 1.0 and math.frexp(s)[0] in (0.5, -0.5)
    sa = _st(a)
    if sa is None and _M.stack and not is_point(a):
        sa = _as_stacked(a)
    if sa is not None:
        t = sa * s if s > 0 else _flip(sa) * s
        if exact:
            return a._pair(t) if abs(s) == 1.0 else a._pair(finite_inner(t))
        return a._pair(outward(t))
    if is_point(a):
        p = a.lower * s
        if exact:
            return a._make(p, p) if abs(s) == 1.0 else a._make(_finite_lo(p), _finite_hi(p))
        return a._pair(outward(p, point=True)) if _M.stack else a._make(down(p), up(p))
    lo, hi = (a.lower * s, a.upper * s) if s > 0 else (a.upper * s, a.lower * s)
    if exact:
        return a._make(lo, hi) if abs(s) == 1.0 else a._make(_finite_lo(lo), _finite_hi(hi))
    return a._make(down(lo), up(hi))


def _finite_lo(x: Tensor) -> Tensor:
    """A lower bound that overflowed to +inf becomes the largest float (``nextafter``'s rule)."""
    return x.clamp(max=torch.finfo(x.dtype).max)


def _finite_hi(x: Tensor) -> Tensor:
    return x.clamp(min=-torch.finfo(x.dtype).max)


def shift(a: Iv, s: float) -> Any:
    """``[a] + s`` for a Python number ``s``."""
    if s == 0:
        return a
    sa = _st(a)
    if sa is None and _M.stack and not is_point(a):
        sa = _as_stacked(a)
    if sa is not None:
        return a._pair(outward(sa + s, absolute=False))
    if is_point(a):
        p = a.lower + s
        if _M.stack:
            return a._pair(outward(p, absolute=False, point=True))
        return a._make(down(p, absolute=False), up(p, absolute=False))
    return a._make(down(a.lower + s, absolute=False), up(a.upper + s, absolute=False))


def rshift(a: Iv, s: float) -> Any:
    """``s - [a]`` for a Python number ``s``."""
    sa = _st(a)
    if sa is None and _M.stack and not is_point(a):
        sa = _as_stacked(a)
    if sa is not None:
        return a._pair(outward(s - _flip(sa), absolute=False))
    return shift(neg(a), s)


def shape_of(a: Iv) -> torch.Size:
    """The shape of an interval array (without making views of stacked bounds)."""
    return a.both.shape[1:] if isinstance(a, Stacked) else a.lower.shape


def tensor_of(a: Iv) -> Tensor:
    """A tensor of ``a``'s dtype and device (its lower bound, or its stacked bounds)."""
    return a.both if isinstance(a, Stacked) else a.lower


def is_number(x: Any) -> bool:
    """A finite Python int or float (not a bool)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def quotient_nonneg(num: float | Iv, x: Iv) -> Any:
    """``num / [x]`` for ``x >= 0`` and ``num >= 0`` (a number, or an interval array): a
    quotient of non-negative numbers falls with ``x`` and grows with ``num``, so its range is
    ``[num_lo / x_hi, num_hi / x_lo]``, rounded outward, with ``c / 0 = inf`` for ``c > 0``.

    The derivative rules of monotone functions (sqrt, log, rsqrt) call it on arguments
    clamped to their domain: three ops in stacked mode where `reciprocal` takes a dozen to
    cover intervals that meet or cross 0. The caller guarantees the signs (a negative bound
    gives a wrong range, not an error); ``0 / 0`` (``num`` and ``x`` both meeting 0 at the
    same end) and NaN bounds give NaN. Rounding: one ulp, the quotient being one division
    (a number is divided as a constant tensor: torch computes ``c / t`` for a number ``c``
    as a reciprocal and a product, two roundings).
    """
    sx = _st(x)
    if sx is None and _M.stack and not is_point(x):
        sx = _as_stacked(x)
    if sx is not None:
        if isinstance(num, IntervalArray):
            top = num.lower if is_point(num) else _st(num)
            top = _as_stacked(num) if top is None else top
        else:
            top = pair_const(sx, sx.dim(), float(num), float(num))
        return x._pair(outward(top / _flip(sx)))
    if isinstance(num, IntervalArray):
        return x._make(down(num.lower / x.upper), up(num.upper / x.lower))
    top = pair_const(x.upper, x.upper.dim() + 1, float(num), float(num))[0]  # [1, ..., 1]
    return x._make(down(top / x.upper), up(top / x.lower))


def reciprocal(b: Iv) -> Any:
    """Extended reciprocal: [c,d] not containing 0 -> [1/d, 1/c]; [0,d] -> [1/d, inf];
    [c,0] -> [-inf, 1/c]; c < 0 < d (or [0,0]) -> [-inf, inf] (documented extended result)."""
    c, d = b.lower, b.upper
    inf = torch.full_like(c, math.inf)
    one = torch.ones_like(c)
    safe_c = torch.where(c == 0, one, c)
    safe_d = torch.where(d == 0, one, d)
    lo = down(1.0 / safe_d)
    hi = up(1.0 / safe_c)
    pos = c > 0
    neg_ = d < 0
    zero_left = (c == 0) & (d > 0)
    zero_right = (c < 0) & (d == 0)
    lo = torch.where(pos | neg_ | zero_left, lo, -inf)
    hi = torch.where(pos | neg_ | zero_right, hi, inf)
    return b._make(lo, hi)


def div(a: Iv, b: Iv) -> Any:
    # Song et al. 2017, sec. 3: [a] / [b] = [a] * [1/b_hi, 1/b_lo] for 0 not in [b]
    c, d = b.lower, b.upper
    nonzero = (c > 0) | (d < 0)
    one = torch.ones_like(c)
    sc = torch.where(nonzero, c, one)
    sd = torch.where(nonzero, d, one)
    q = torch.stack(torch.broadcast_tensors(a.lower / sc, a.lower / sd, a.upper / sc, a.upper / sd))
    direct = a._make(down(q.amin(0)), up(q.amax(0)))
    if not tracing() and bool(nonzero.all()):
        return direct
    ext = mul(a, reciprocal(b))
    nz = torch.broadcast_to(nonzero, direct.lower.shape)
    return a._make(
        torch.where(nz, direct.lower, ext.lower), torch.where(nz, direct.upper, ext.upper)
    )


def power(x: Iv, p: Any) -> Any:
    """``x ** p``: integer p (even powers exact: [-2, 1]^2 = [0, 4]; negative p via 1/x^|p|),
    or real p for x >= 0 (monotone)."""
    if isinstance(p, IntervalArray) or (isinstance(p, Tensor) and p.numel() != 1):
        return monotone(mul(as_interval(p, x), x.log()), torch.exp, 2, clamp_min=0.0)
    pv = float(p.item() if isinstance(p, Tensor) else p)
    if pv == int(pv):
        pi = int(pv)
        if pi == 0:
            one = torch.ones_like(x.lower)
            return x._make(one, one)
        if pi == 1:
            return x
        if pi < 0:
            return reciprocal(power(x, -pi))
        if pi == 2:
            return square(x)
        k = pi + 1
        lo_p, hi_p = torch.pow(x.lower, pi), torch.pow(x.upper, pi)
        if pi % 2 == 1:
            return x._make(down(lo_p, k), up(hi_p, k))
        lo, hi = x.lower, x.upper
        low = torch.where(lo >= 0, lo_p, torch.where(hi <= 0, hi_p, torch.zeros_like(lo_p)))
        high = torch.maximum(lo_p, hi_p)
        low = torch.where(low > 0, down(low, k), low).clamp(min=0.0)
        return x._make(low, up(high, k))
    check_domain(x, f"power {pv}", strict=pv < 0)
    k = int(abs(pv)) + 2
    lo_p, hi_p = torch.pow(x.lower, pv), torch.pow(x.upper, pv)
    if pv > 0:
        return x._make(down(lo_p, k).clamp(min=0.0), up(hi_p, k))
    return x._make(down(hi_p, k).clamp(min=0.0), up(lo_p, k))


def rpow(base: Any, x: Iv) -> Any:
    """``base ** [x]`` for a positive constant ``base``."""
    b = as_tensor("base", base, like=x.lower)
    if (b.detach() <= 0).any():
        raise ValueError("base: must be > 0 for base ** Interval")
    return monotone(mul(x, as_interval(torch.log(b), x)), torch.exp, 2, clamp_min=0.0)


def check_domain(x: Iv, name: str, strict: bool) -> None:
    """Raise a ValueError where ``x`` reaches below 0 (``<= 0`` when ``strict``), eagerly."""
    if not checking():  # traced or in a filter step: out of the domain the bounds are NaN
        return  # (no host sync), and the filters flag those elements (FilterEvent.DOMAIN)
    bad = (x.lower <= 0) if strict else (x.lower < 0)
    if bool(bad.detach().any()):
        rel = ">" if strict else ">="
        low = float(x.lower.detach().min())
        raise ValueError(f"x: {name} needs lower {rel} 0, its argument reaches {low:.6g} "
                         "(interval leaves the domain)")


def monotone(
    x: Iv,
    fn: Callable[[Tensor], Tensor],
    ulps: int,
    clamp_min: float | None = None,
    clamp_max: float | None = None,
) -> Any:
    """Increasing function: [fn(lo), fn(hi)] rounded outward, clamped to fn's range."""
    sx = _st(x)
    if sx is None and _M.stack and not is_point(x):
        sx = _as_stacked(x)
    if sx is not None:
        both = outward(fn(sx), ulps)
        if clamp_min is not None or clamp_max is not None:
            both = torch.clamp(both, min=clamp_min, max=clamp_max)
        return x._pair(both)
    lo = down(fn(x.lower), ulps)
    hi = up(fn(x.upper), ulps)
    if clamp_min is not None or clamp_max is not None:
        lo = torch.clamp(lo, min=clamp_min, max=clamp_max)
        hi = torch.clamp(hi, min=clamp_min, max=clamp_max)
    return x._make(lo, hi)


def absolute(x: Iv) -> Any:
    """Exact range of ``|x|``."""
    lo, hi = x.lower, x.upper
    mag = torch.maximum(-lo, hi)
    low = torch.where(lo >= 0, lo, torch.where(hi <= 0, -hi, torch.zeros_like(lo)))
    return x._make(low, mag)


def square(x: Iv) -> Any:
    """Exact range of ``x ** 2``: the squares of the smallest and largest ``|x|``."""
    sx = _st(x)
    if sx is not None:
        # [min(-lo, hi), max(-lo, hi)] sorted, the first clamped to <= 0: [-min |x|, max |x|]
        # (min |x| is 0 where the interval meets 0; the square of -min |x| is min |x|^2)
        m = sx * pair_signs(sx, sx.dim())
        # (while traced, no sort: a graph that sorts is compiled with other options)
        m = torch.stack(torch.aminmax(m, dim=0)) if tracing() else torch.sort(m, dim=0).values
        both = m.clamp(max=pair_const(m, m.dim(), 0.0, math.inf))
        return x._pair(outward(times(both, both)).clamp_min(0.0))
    lo, hi = x.lower, x.upper
    if is_point(x):
        p = times(lo, lo)
        return x._make(down(p).clamp_min(0.0), up(p))
    small = torch.maximum(lo, -hi).clamp_min(0.0)  # min |x| (0 where the interval meets 0)
    big = torch.maximum(-lo, hi)  # max |x|
    return x._make(down(times(small, small)).clamp_min(0.0), up(times(big, big)))


def relu(x: Iv) -> Any:
    sx = _st(x)
    if sx is not None:
        return x._pair(torch.relu(sx))
    return x._make(torch.relu(x.lower), torch.relu(x.upper))


def clamp(x: Iv, min: Any = None, max: Any = None) -> Any:  # noqa: A002
    sx = _st(x)
    if sx is not None and not isinstance(min, Tensor) and not isinstance(max, Tensor):
        return x._pair(torch.clamp(sx, min=min, max=max))
    return x._make(torch.clamp(x.lower, min=min, max=max), torch.clamp(x.upper, min=min, max=max))


def _hits(a: Tensor, b: Tensor, phase: float) -> Tensor:
    """True where some ``phase + 2 pi k`` lies in ``[a, b]`` (generous: never misses one)."""
    a64, b64 = a.detach().double(), b.detach().double()
    slack = 1e-9 + 64 * eps(a) * (1.0 + torch.maximum(a64.abs(), b64.abs()))
    k_lo = torch.ceil((a64 - phase) / _TWO_PI - slack)
    k_hi = torch.floor((b64 - phase) / _TWO_PI + slack)
    return k_lo <= k_hi


def trig(x: Iv, fn: Callable[[Tensor], Tensor], phase_max: float, phase_min: float) -> Any:
    # Song et al. 2017, sec. 3 (simple interval extension): range of sin/cos = endpoint values,
    # widened to +-1 where a maximum/minimum lies inside the interval.
    fa, fb = fn(x.lower), fn(x.upper)
    lo = down(torch.minimum(fa, fb), 2)
    hi = up(torch.maximum(fa, fb), 2)
    wide = (x.upper - x.lower).detach() >= _TWO_PI
    has_max = wide | _hits(x.lower, x.upper, phase_max)
    has_min = wide | _hits(x.lower, x.upper, phase_min)
    one = torch.ones_like(lo)
    hi = torch.where(has_max, one, hi).clamp(max=1.0)
    lo = torch.where(has_min, -one, lo).clamp(min=-1.0)
    return x._make(lo, hi)


def count(shape: torch.Size, dim: Any) -> int:
    """Number of elements over the dims ``dim`` of ``shape``."""
    dims = (dim,) if isinstance(dim, int) else tuple(dim)
    return math.prod([shape[d] for d in dims])  # a list: Dynamo traces it


def total(x: Iv, dim: Any = None, keepdim: bool = False) -> Any:
    """Sum with the a-priori float error bound gamma_k sum|terms| added outward."""
    if dim is None:
        lo_t, hi_t = x.lower.reshape(-1), x.upper.reshape(-1)
        dim_, keep = 0, False
        k = lo_t.numel()
    else:
        lo_t, hi_t, dim_, keep = x.lower, x.upper, dim, keepdim
        k = count(x.lower.shape, dim)
    if k <= 1:
        return x._make(lo_t.sum(dim_, keepdim=keep), hi_t.sum(dim_, keepdim=keep))
    g = (k + 4) * eps(lo_t)
    tn = k * tiny(lo_t)
    lo_s = lo_t.sum(dim_, keepdim=keep)
    hi_s = hi_t.sum(dim_, keepdim=keep)
    lo_err = g * nan_to_zero(lo_t.detach().abs()).sum(dim_, keepdim=keep) + tn
    hi_err = g * nan_to_zero(hi_t.detach().abs()).sum(dim_, keepdim=keep) + tn
    return x._make(down(lo_s - lo_err), up(hi_s + hi_err))


def mid_rad(x: Iv) -> tuple[Tensor, Tensor]:
    """Guaranteed midpoint-radius form: ``[c - r, c + r]`` contains the interval (reals)."""
    c = 0.5 * (x.lower + x.upper)
    r = up(torch.maximum(x.upper - c, c - x.lower))
    return c, r


def matmul(a: Any, b: Any) -> Any:
    """``a @ b`` with an interval array on either side; tensor semantics of ``torch.matmul``."""
    if isinstance(a, IntervalArray) and isinstance(b, IntervalArray):
        return _matmul_ii(a, b)
    if isinstance(a, IntervalArray):
        A = as_tensor("other", b, like=a.lower)
        c, r = mid_rad(a)
        k = A.shape[0] if A.dim() == 1 else A.shape[-2]
        return _mid_rad_out(a, mm(c, A), mm(r, A.abs()), mm(c.abs(), A.abs()), k)
    A = as_tensor("other", a, like=b.lower)
    c, r = mid_rad(b)
    k = A.shape[-1]
    return _mid_rad_out(b, mm(A, c), mm(A.abs(), r), mm(A.abs(), c.abs()), k)


def _mid_rad_out(like: Iv, mc: Tensor, mr: Tensor, mabs: Tensor, k: int) -> Any:
    # point matrix x interval vector/matrix (midpoint-radius form, exact in real arithmetic)
    # plus the dot-product rounding bound gamma_k (|c||A| + r|A|).
    err = (k + 4) * eps(mc) * (mabs + mr) + k * tiny(mc)
    rad = mr + err
    return like._make(down(mc - rad), up(mc + rad))


def _matmul_ii(a: Iv, b: Iv) -> Any:
    # interval matrix product: entrywise exact Moore products summed (Song et al. 2017, sec. 3)
    sq_a, sq_b = a.lower.dim() == 1, b.lower.dim() == 1
    al, au, bl, bu = a.lower, a.upper, b.lower, b.upper
    if sq_a:
        al, au = al.unsqueeze(0), au.unsqueeze(0)
    if sq_b:
        bl, bu = bl.unsqueeze(-1), bu.unsqueeze(-1)
    prod = mul(a._make(al.unsqueeze(-1), au.unsqueeze(-1)),
               a._make(bl.unsqueeze(-3), bu.unsqueeze(-3)))  # [..., m, k, p]
    out = total(prod, -2)
    lo, hi = out.lower, out.upper
    if sq_a:
        lo, hi = lo.squeeze(-2), hi.squeeze(-2)
    if sq_b:
        lo, hi = lo.squeeze(-1), hi.squeeze(-1)
    return a._make(lo, hi)
