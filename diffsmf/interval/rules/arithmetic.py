"""Rules of the arithmetic ops: sums, products, quotients and powers of jets (Moore arithmetic
on values, product and chain rules on derivatives).
"""

from __future__ import annotations

from typing import Any

import torch

from diffsmf.interval import arith
from diffsmf.interval.arith import is_number
from diffsmf.interval.box import Interval
from diffsmf.interval.jet import EXACT_SUMS, Jet, chain, mul, point
from diffsmf.interval.rules.base import (
    BoolBox,
    Ctx,
    _is_jet,
    _lift,
    _ref,
    _unsupported,
    aten,
    register,
)

__all__ = []

# ----------------------------------------------------------------------------- arithmetic
def _linear_combo(a: Any, b: Any, sa: float, sb: float) -> Any:
    """``sa * a + sb * b`` for jets / tensors / numbers (sa, sb Python numbers)."""
    ref = _ref([a, b])
    if ref is None:
        return sa * a + sb * b
    if sa in (1, -1) and sb in (1, -1):  # a number added to a jet: a shift of its value
        if not _is_jet(a) and is_number(a):
            return _plus_const(b, sb, sa * a)
        if not _is_jet(b) and is_number(b):
            return _plus_const(a, sa, sb * b)
    A, B = _lift(a, ref), _lift(b, ref)

    def comb(x: Interval | None, y: Interval | None, exact_zero: bool) -> Interval | None:
        if x is None or y is None:
            return _times(y, sb) if x is None else _times(x, sa)
        if sa == 1 and sb == -1:
            return arith.sub(x, y, exact_zero)
        return arith.add(_times(x, sa), _times(y, sb), exact_zero)

    # a zero value sum stays exact; derivative sums as `diffsmf.interval.jet.EXACT_SUMS` says
    return ref.like(comb(A.val, B.val, True), comb(A.grad, B.grad, EXACT_SUMS),
                    comb(A.hess, B.hess, EXACT_SUMS))


def _times(x: Interval | None, s: float) -> Interval | None:
    """``s * x`` (``None`` stays None; ``s = +-1`` exact)."""
    if x is None or s == 1:
        return x
    return arith.neg(x) if s == -1 else arith.scale(x, float(s))


def _plus_const(j: Jet, s: float, c: float) -> Jet:
    """``s * j + c`` for ``s = +-1`` and a Python number ``c``."""
    if s == -1 and c != 0:
        val = arith.rshift(j.val, float(c))
    else:
        val = _times(j.val, s)
        if c != 0:
            val = arith.shift(val, float(c))
    return j.like(val, _times(j.grad, s), _times(j.hess, s))


@register(aten.add, category="arithmetic")
def _add(ctx: Ctx, a: Any, b: Any, alpha: float = 1) -> Any:
    return _linear_combo(a, b, 1, alpha)


@register(aten.sub, category="arithmetic")
def _sub(ctx: Ctx, a: Any, b: Any, alpha: float = 1) -> Any:
    return _linear_combo(a, b, 1, -alpha)


@register(aten.rsub, category="arithmetic")
def _rsub(ctx: Ctx, a: Any, b: Any, alpha: float = 1) -> Any:
    return _linear_combo(b, a, 1, -alpha)


@register(aten.neg, category="arithmetic")
def _neg(ctx: Ctx, a: Any) -> Any:
    if not isinstance(a, Jet):
        return -a
    return a.like(arith.neg(a.val), _times(a.grad, -1), _times(a.hess, -1))


@register(aten.mul, category="arithmetic")
def _mul(ctx: Ctx, a: Any, b: Any) -> Any:
    if isinstance(a, BoolBox) or isinstance(b, BoolBox):
        raise _unsupported(ctx, "arithmetic on a comparison of the state")
    if not _is_jet(a) and not _is_jet(b):
        return a * b
    return mul(a, b)


@register(aten.div, category="arithmetic")
def _div(ctx: Ctx, a: Any, b: Any, rounding_mode: str | None = None) -> Any:
    if rounding_mode is not None and (_is_jet(a) or _is_jet(b)):
        raise _unsupported(ctx, f"division with rounding_mode={rounding_mode!r} of the state")
    if not _is_jet(b):
        if not _is_jet(a):
            return torch.div(a, b, rounding_mode=rounding_mode)
        r = 1.0 / b if isinstance(b, (int, float)) else None
        if r is not None and r * b == 1.0:  # exact reciprocal (powers of two)
            return mul(a, r)
        return mul(a, _recip_jet(_lift(b, a)))
    return mul(a, _recip_jet(b)) if _is_jet(a) or not isinstance(a, (int, float)) or a != 1 \
        else _recip_jet(b)


def _recip_jet(b: Jet) -> Jet:
    v = b.val.reciprocal()
    d1 = -v.square() if b.order >= 1 else None
    d2 = (v**3) * 2.0 if b.order >= 2 else None
    return chain(b, v, d1, d2)


@register(aten.reciprocal, category="elementwise")
def _reciprocal(ctx: Ctx, a: Any) -> Any:
    return _recip_jet(a) if _is_jet(a) else torch.reciprocal(a)


def _pow_scalar(a: Jet, pv: float) -> Jet:
    if pv == 0:
        return a.like(point(torch.ones_like(a.val.lower)), None, None)
    if pv == 1:
        return a
    if pv == 2:
        return mul(a, a)
    x = a.val
    if pv != int(pv):  # a real power is defined for x >= 0: its part of the box (see _domain)
        x = Interval._make(x.lower.clamp_min(0.0), x.upper.clamp_min(0.0))
    v = _rpow(x, pv)
    d1 = _rpow(x, pv - 1) * pv if a.order >= 1 else None
    d2 = _rpow(x, pv - 2) * (pv * (pv - 1)) if a.order >= 2 else None
    return chain(a, v, d1, d2)


def _rpow(x: Interval, q: float) -> Interval:
    """``x ** q``; a negative real ``q`` as ``1 / x ** -q`` (``inf`` at 0, never an error)."""
    if q == 0:
        return point(torch.ones_like(x.lower))
    if q < 0 and q != int(q):
        return (x ** (-q)).reciprocal()
    return x**q
