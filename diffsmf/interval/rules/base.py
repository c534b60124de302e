"""The rule registry (`register`, `RULES`) and what every rule is written with: the node's
context (`Ctx`), comparisons over a box (`BoolBox`) and the helpers that lift, map and select
jets.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval import arith
from diffsmf.interval.arith import Stacked
from diffsmf.interval.box import Interval
from diffsmf.interval.errors import EngineError
from diffsmf.interval.jet import Jet, move, nonsmooth, point

__all__ = ["CATEGORIES", "RULES", "BoolBox", "Ctx", "register", "supported_ops"]

aten = torch.ops.aten

#: op packet -> rule(ctx, *args, **kwargs)
RULES: dict[Any, Callable[..., Any]] = {}
#: op name -> category (for the generated docs table)
CATEGORIES: dict[str, str] = {}


@dataclass(frozen=True)
class Ctx:
    """What a rule knows of its node: the captured ranks of its args and of its result."""

    ranks: tuple[int | None, ...]
    out_rank: int
    name: str
    shapes: tuple[tuple[int, ...] | None, ...] = ()

    def rank(self, i: int = 0) -> int:
        r = self.ranks[i]
        return self.out_rank if r is None else r


@dataclass
class BoolBox:
    """A comparison over a box: ``sure`` (true for every point) and ``maybe`` (true for some),
    with the differentiation variables ``n`` and ``order`` of the jets compared."""

    sure: Tensor
    maybe: Tensor
    n: int = 0
    order: int = 0


def register(*ops: Any, category: str = "other") -> Callable[[Callable], Callable]:
    """Decorator: register ``rule(ctx, *args, **kwargs)`` for ATen op packets ``ops``."""

    def deco(rule: Callable) -> Callable:
        for op in ops:
            RULES[op] = rule
            CATEGORIES[str(op).removeprefix("aten.")] = category
        return rule

    return deco


def supported_ops() -> dict[str, list[str]]:
    """Category -> sorted op names that have a rule (for the docs)."""
    out: dict[str, list[str]] = {}
    for name, cat in CATEGORIES.items():
        out.setdefault(cat, []).append(name)
    return {k: sorted(v) for k, v in sorted(out.items())}


# ----------------------------------------------------------------------------- helpers
def _is_jet(x: Any) -> bool:
    return isinstance(x, Jet)


def _ref(args: Sequence[Any]) -> Jet | None:
    for a in args:
        if isinstance(a, Jet):
            return a
        if isinstance(a, (list, tuple)):
            r = _ref(a)
            if r is not None:
                return r
    return None


def _lift(x: Any, ref: Jet) -> Jet:
    """A constant (tensor or number) as a jet with zero derivatives."""
    if isinstance(x, Jet):
        return x
    t = torch.as_tensor(x, dtype=ref.val.lower.dtype, device=ref.val.lower.device)
    return ref.like(point(t), None, None)


def _map_piece(x: Any, rank: int, fn: Callable[[Tensor, int], Tensor]) -> Any:
    """Apply ``fn(t, prefix)`` to every tensor of a jet / tensor / BoolBox (value-moving op)."""

    def g(t: Tensor) -> Tensor:
        return fn(t, t.dim() - rank)

    if isinstance(x, Jet):
        return x.like(move(x.val, g), move(x.grad, g), move(x.hess, g))
    if isinstance(x, BoolBox):
        return BoolBox(g(x.sure), g(x.maybe), x.n, x.order)
    if isinstance(x, Tensor):
        return g(x)
    return x


def _neg_dim(d: int, rank: int) -> int:
    """A captured dim as a negative index (independent of extra leading dims)."""
    return (d % rank) - rank if rank > 0 else d


def _zeros_grad(j: Jet, tangent: int) -> Interval | None:
    """Materialised zero derivative enclosure of ``j`` (for ops that need all parts)."""
    if j.order < tangent:
        return None
    shape = (j.n,) * tangent + tuple(j.shape)
    like = arith.tensor_of(j.val)
    return point(torch.zeros(shape, dtype=like.dtype, device=like.device))


def _nan_where(j: Jet, bad: Tensor) -> Jet:
    """NaN enclosures for the elements flagged ``bad`` (a domain exit)."""
    if not isinstance(bad, Tensor):
        return j
    nan = torch.tensor(math.nan, dtype=j.val.lower.dtype, device=j.val.lower.device)

    def f(t: Interval | None) -> Interval | None:
        if t is None:
            return None
        return Interval._make(torch.where(bad, nan, t.lower), torch.where(bad, nan, t.upper))

    return j.like(f(j.val), f(j.grad), f(j.hess))


def _common(items: Sequence[Any], stacked_zeros: bool = False) -> list[Any]:
    """Lift tensors to jets and broadcast every part to common leading dims (for cat/stack).

    ``stacked_zeros``: where the other parts are stacked, a missing derivative is made as
    stacked zeros (one op; see `_pair_zeros`)."""
    ref = _ref(items)
    if ref is None:
        return list(items)
    jets = [_lift(t, ref) for t in items]
    need_g = [j.grad for j in jets if j.grad is not None]
    need_h = [j.hess for j in jets if j.hess is not None]
    out = []
    for j in jets:
        g = j.grad if j.grad is not None or not need_g else _zeros_like_part(j, 1, need_g,
                                                                            stacked_zeros)
        h = j.hess if j.hess is not None or not need_h else _zeros_like_part(j, 2, need_h,
                                                                            stacked_zeros)
        out.append(j.like(j.val, g, h))
    return out


def _zeros_like_part(j: Jet, tangent: int, others: list, stacked: bool) -> Interval | None:
    """Zero derivative enclosure of ``j`` (stacked when ``stacked`` and another part is)."""
    if j.order < tangent:
        return None
    if not stacked or not any(isinstance(o, Stacked) for o in others):
        return _zeros_grad(j, tangent)
    like = arith.tensor_of(j.val)
    z = torch.zeros((2, *((j.n,) * tangent), *j.shape), dtype=like.dtype, device=like.device)
    return Interval._pair(z)


def _select(mask: Tensor, a: Jet, b: Jet | Interval, undefined_derivative: bool = False) -> Jet:
    """Elementwise choice between two jets (``b`` may be a constant interval)."""
    if isinstance(b, Interval):
        b = a.like(b, None, None)
    A, B = _common([a, b])

    def sel(x: Interval | None, y: Interval | None, k: int) -> Interval | None:
        if x is None and y is None:
            return None
        x = x if x is not None else point(torch.zeros_like(y.lower))
        y = y if y is not None else point(torch.zeros_like(x.lower))
        m = mask[(None,) * k] if k else mask
        if undefined_derivative and k:
            y = nonsmooth(y)
        return Interval._make(torch.where(m, x.lower, y.lower), torch.where(m, x.upper, y.upper))

    grad = sel(A.grad, B.grad if B.grad is not None or not undefined_derivative else
               (_zeros_grad(B, 1)), 1)
    hess = sel(A.hess, B.hess if B.hess is not None or not undefined_derivative else
               _zeros_grad(B, 2), 2) if a.order >= 2 else None
    return a.like(sel(A.val, B.val, 0), grad, hess)


def _unsupported(ctx: Ctx, what: str) -> Exception:
    return EngineError(f"{what} (operation {ctx.name}) is not supported")
