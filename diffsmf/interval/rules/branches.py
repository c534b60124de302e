"""Rules of comparisons, logic and ``where``: a comparison over a box is a `BoolBox` (sure or
maybe), and ``where`` takes the hull of both branches where the condition is undecided.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval.box import Interval
from diffsmf.interval.jet import Jet, hull, point
from diffsmf.interval.rules.base import BoolBox, Ctx, _is_jet, _lift, _ref, aten, register

__all__ = []

# ----------------------------------------------------------------------------- branches
def _cmp(op: Callable[[Tensor, Tensor], Tensor], name: str) -> Callable:
    def rule(ctx: Ctx, a: Any, b: Any) -> Any:
        if not _is_jet(a) and not _is_jet(b):
            return op(torch.as_tensor(a), b) if not isinstance(a, Tensor) else op(a, b)
        ref = _ref([a, b])
        A, B = _lift(a, ref).val, _lift(b, ref).val
        if name in ("gt", "ge"):
            A, B = B, A  # a > b  <=>  b < a
        # now: a < b (lt) or a <= b (le) with A, B swapped accordingly
        strict = name in ("gt", "lt")
        if name in ("lt", "le", "gt", "ge"):
            sure = A.upper < B.lower if strict else A.upper <= B.lower
            maybe = A.lower < B.upper if strict else A.lower <= B.upper
            return BoolBox(sure, maybe, ref.n, ref.order)
        point_eq = (A.lower == A.upper) & (B.lower == B.upper) & (A.lower == B.lower)
        overlap = (A.lower <= B.upper) & (B.lower <= A.upper)
        if name == "eq":
            return BoolBox(point_eq, overlap, ref.n, ref.order)
        return BoolBox(~overlap, ~point_eq, ref.n, ref.order)

    return rule


for _name in ("gt", "ge", "lt", "le", "eq", "ne"):
    register(getattr(aten, _name), category="branch")(_cmp(getattr(torch, _name), _name))


def _as_box(c: Any) -> BoolBox:
    if isinstance(c, BoolBox):
        return c
    t = torch.as_tensor(c, dtype=torch.bool)
    return BoolBox(t, t)


@register(aten.logical_not, aten.bitwise_not, category="branch")
def _not(ctx: Ctx, a: Any) -> Any:
    if not isinstance(a, BoolBox):
        return torch.logical_not(a)
    return BoolBox(~a.maybe, ~a.sure, a.n, a.order)


@register(aten.logical_and, aten.bitwise_and, aten.logical_or, aten.bitwise_or,
          category="branch")
def _andor(ctx: Ctx, a: Any, b: Any) -> Any:
    is_and = "and" in ctx.name
    if not isinstance(a, BoolBox) and not isinstance(b, BoolBox):
        return (a & b) if is_and else (a | b)
    A, B = _as_box(a), _as_box(b)
    n, order = max(A.n, B.n), max(A.order, B.order)
    if is_and:
        return BoolBox(A.sure & B.sure, A.maybe & B.maybe, n, order)
    return BoolBox(A.sure | B.sure, A.maybe | B.maybe, n, order)


@register(aten.where, category="branch")
def _where(ctx: Ctx, cond: Any, a: Any, b: Any) -> Any:
    """``where(c, a, b)``: the branch taken where ``c`` is decided over the box; elsewhere the
    hull of both values, and no derivative (the function may jump where ``c`` switches)."""
    if not isinstance(cond, BoolBox) and not _is_jet(a) and not _is_jet(b):
        return torch.where(cond, a, b)
    box = _as_box(cond)
    ref = _ref([a, b])
    if ref is None:  # constant branches under an undecided condition
        like = torch.as_tensor(a if isinstance(a, Tensor) else b)
        if not like.is_floating_point():
            like = like.to(torch.float64)
        ref = Jet(point(torch.zeros_like(like)), None, None, box.order, box.n)
    A, B = _lift(a, ref), _lift(b, ref)
    undecided = box.maybe & ~box.sure

    def sel(x: Interval | None, y: Interval | None, k: int) -> Interval:
        if x is None:
            x = _zero_tangent(y if y is not None else A.val, ref, k)
        if y is None:
            y = _zero_tangent(x, ref, k)
        s_ = box.sure[(None,) * k] if k else box.sure
        u = undecided[(None,) * k] if k else undecided
        lo = torch.where(s_, x.lower, y.lower)
        hi = torch.where(s_, x.upper, y.upper)
        if k == 0:
            h = hull(x, y)
            return Interval._make(torch.where(u, h.lower, lo), torch.where(u, h.upper, hi))
        inf = torch.full_like(lo, torch.inf)
        return Interval._make(torch.where(u, -inf, lo), torch.where(u, inf, hi))

    val = sel(A.val, B.val, 0)
    grad = sel(A.grad, B.grad, 1) if ref.order >= 1 else None
    hess = sel(A.hess, B.hess, 2) if ref.order >= 2 else None
    return ref.like(val, grad, hess)


def _zero_tangent(like: Interval, ref: Jet, k: int) -> Interval:
    """Zero enclosure with ``k`` tangent dims in front of ``like``'s trailing value shape."""
    shape = like.lower.shape
    if k and shape[:k] == (ref.n,) * k:
        shape = shape[k:]
    z = torch.zeros((ref.n,) * k + tuple(shape), dtype=like.lower.dtype, device=like.lower.device)
    return point(z)
