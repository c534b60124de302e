"""Inclusion rules, one per ATen operation, and the registry that maps ops to rules.

A rule receives the evaluated arguments of one node of a captured model program and returns
its enclosure. A tensor argument is a `Jet` (it depends on the
inputs enclosed), a plain ``Tensor`` (a constant of the program, or a point input such as
``u``) or a `BoolBox` (a comparison of enclosed values). Every argument carries extra
*leading* dims that the captured graph does not know about (the caller's batch dims, and the
tangent dims of gradients and Hessians); a rule applies the op's shape and dim arguments to
the *trailing* dims only, so one rule serves values, gradients and Hessians alike. ``ctx`` gives
the captured rank of each argument and of the result.

Rules never raise for numerical reasons. Where a box reaches outside an op's domain (``sqrt``,
``log`` or a real power of a box reaching below 0, ``asin`` outside ``[-1, 1]``), only its part
inside the domain is enclosed: the true states lie there (the model is evaluated on them). The
value of ``log`` at 0 is then ``-inf`` (the filters flag the trajectory's set as unbounded).
Where no such bound exists (a box across a pole of ``tan``) the enclosure of that element is
NaN, which the filters flag as a domain event for that trajectory.

Register a rule for a further op with `register` (see the "Writing models" docs page).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval import arith
from diffsmf.interval.arith import Stacked, is_number
from diffsmf.interval.box import Interval
from diffsmf.interval.errors import EngineError
from diffsmf.interval.jet import EXACT_SUMS, Jet, chain, hadd, hull, move, mul, nonsmooth, point
from diffsmf.interval.rounding import down, up
from diffsmf.utils import broadcast_shapes

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


# ----------------------------------------------------------------------------- moving values
def _moving(fn: Callable[..., Tensor]) -> Callable[..., Any]:
    """Rule of a single-input op that only moves values: ``fn(t, prefix, *args)``."""

    def rule(ctx: Ctx, x: Any, *args: Any, **kwargs: Any) -> Any:
        return _map_piece(x, ctx.rank(0), lambda t, p: fn(t, p, ctx, *args, **kwargs))

    return rule


def _sized(op: Callable[..., Tensor]) -> Callable[..., Any]:
    def fn(t: Tensor, p: int, ctx: Ctx, size: Sequence[int], *a: Any, **k: Any) -> Tensor:
        own = ctx.shapes[0] if ctx.shapes else None
        if own is not None and tuple(t.shape[p:]) != tuple(own):  # lazily broadcast parts
            t = t.expand(*t.shape[:p], *own)
        return op(t, [*t.shape[:p], *size])

    return _moving(fn)


register(aten.view, aten._unsafe_view, aten.view_copy, aten.reshape, aten._reshape_copy,
         category="moving")(_sized(lambda t, s: t.reshape(s)))
register(aten.expand, aten.expand_copy, category="moving")(_sized(lambda t, s: t.expand(s)))


@register(aten.permute, aten.permute_copy, category="moving")
def _permute(ctx: Ctx, x: Any, dims: Sequence[int]) -> Any:
    r = ctx.rank(0)

    def fn(t: Tensor, p: int) -> Tensor:
        return t.permute(*range(p), *[p + d % r for d in dims])

    return _map_piece(x, r, fn)


@register(aten.repeat, category="moving")
def _repeat(ctx: Ctx, x: Any, repeats: Sequence[int]) -> Any:
    return _map_piece(x, ctx.rank(0), lambda t, p: t.repeat(*([1] * p), *repeats))


def _dim_op(op: Callable[..., Tensor], dim_pos: int = 0, rank_of: str = "in") -> Callable:
    """Rule of a value-moving op whose ``dim`` argument is rewritten as a negative index."""

    def rule(ctx: Ctx, x: Any, *args: Any, **kwargs: Any) -> Any:
        r = ctx.out_rank if rank_of == "out" else ctx.rank(0)
        args = list(args)
        if dim_pos < len(args):
            d = args[dim_pos]
            args[dim_pos] = [_neg_dim(e, r) for e in d] if isinstance(d, (list, tuple)) else (
                _neg_dim(d, r))
        return _map_piece(x, ctx.rank(0), lambda t, p: op(t, *args, **kwargs))

    return rule


for _op in (aten.select, aten.select_copy):
    register(_op, category="moving")(_dim_op(lambda t, d, i: aten.select.int(t, d, i)))
for _op in (aten.slice, aten.slice_copy):
    register(_op, category="moving")(_dim_op(
        lambda t, d=0, s=None, e=None, st=1: aten.slice.Tensor(t, d, s, e, st)))
register(aten.squeeze, aten.squeeze_copy, category="moving")(
    lambda ctx, x, dim=None: _map_piece(
        x, ctx.rank(0),
        lambda t, p: t.squeeze(tuple(range(p, t.dim()))) if dim is None else t.squeeze(
            tuple(_neg_dim(e, ctx.rank(0)) for e in (dim if isinstance(dim, (list, tuple))
                                                      else [dim])))))
register(aten.unsqueeze, aten.unsqueeze_copy, category="moving")(
    _dim_op(lambda t, d: t.unsqueeze(d), rank_of="out"))
register(aten.flip, category="moving")(_dim_op(lambda t, d: t.flip(d)))
register(aten.roll, category="moving")(
    lambda ctx, x, shifts, dims=(): _map_piece(
        x, ctx.rank(0), lambda t, p: t.roll(shifts, [_neg_dim(d, ctx.rank(0)) for d in dims])
        if dims else t.flatten(p).roll(shifts, -1).reshape(t.shape)))
register(aten.index_select, category="moving")(
    _dim_op(lambda t, d, idx: t.index_select(d, idx)))
register(aten.alias, aten.clone, aten.lift_fresh_copy, aten.alias_copy, aten.contiguous,
         category="moving")(lambda ctx, x, *a, **k: x)


@register(aten.gather, category="moving")
def _gather(ctx: Ctx, x: Any, dim: int, index: Tensor, **kw: Any) -> Any:
    r = ctx.rank(0)
    d = _neg_dim(dim, r)

    def fn(t: Tensor, p: int) -> Tensor:
        idx = index.expand(*t.shape[:p], *index.shape[index.dim() - r:])
        return t.gather(d, idx)

    return _map_piece(x, r, fn)


@register(aten.index, category="moving")
def _index(ctx: Ctx, x: Any, indices: Sequence[Tensor | None]) -> Any:
    if any(isinstance(i, (Jet, BoolBox)) for i in indices):
        raise _unsupported(ctx, "indexing with state-dependent indices")

    def fn(t: Tensor, p: int) -> Tensor:
        return t[(slice(None),) * p + tuple(slice(None) if i is None else i for i in indices)]

    return _map_piece(x, ctx.rank(0), fn)


@register(aten.constant_pad_nd, category="moving")
def _pad(ctx: Ctx, x: Any, pad: Sequence[int], value: float = 0.0) -> Any:
    if isinstance(x, Jet):
        fp = torch.nn.functional.pad
        val = Interval._make(fp(x.val.lower, pad, value=value), fp(x.val.upper, pad, value=value))
        return x.like(val, move(x.grad, lambda t: fp(t, pad)), move(x.hess, lambda t: fp(t, pad)))
    return torch.nn.functional.pad(x, pad, value=value)


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


def _broadcast_except(parts: list[Tensor], d: int) -> list[Tensor]:
    """Broadcast tensors to one shape except along the (negative) dim ``d`` (for cat)."""
    nd = max(t.dim() for t in parts)
    parts = [t.reshape((1,) * (nd - t.dim()) + tuple(t.shape)) for t in parts]
    shapes = [list(t.shape) for t in parts]
    for sh in shapes:
        sh[d] = 1
    full = list(broadcast_shapes(*shapes))
    out = []
    for t in parts:
        full[d] = t.shape[d]
        out.append(t.expand(full))
    return out


def _join(op: Callable[..., Tensor], parts: list[Tensor], d: int) -> Tensor:
    """``op(parts, d)`` (torch.cat or torch.stack) after broadcasting the parts to one shape
    except along ``d`` for cat (only the parts that differ are expanded)."""
    if op is torch.stack:
        s0 = parts[0].shape
        if all(t.shape == s0 for t in parts):
            return op(parts, d)
        shape = broadcast_shapes(*[t.shape for t in parts])
        return op([t if t.shape == shape else t.expand(shape) for t in parts], d)
    if all(t.shape[:d] + t.shape[d + 1:] == parts[0].shape[:d] + parts[0].shape[d + 1:]
           for t in parts[1:]) and len({t.dim() for t in parts}) == 1:
        return op(parts, d)
    return op(_broadcast_except(parts, d), d)


def _join_jets(op: Callable[..., Tensor], tensors: Sequence[Any], d: int) -> Any:
    """cat / stack of jets and constants along the (negative) dim ``d``."""
    items = _common(tensors, stacked_zeros=True)
    if not any(isinstance(t, Jet) for t in items):
        return _join(op, [torch.as_tensor(t) for t in items], d)

    def join_iv(ivs: list[Interval | None]) -> Interval | None:
        if ivs[0] is None:
            return None
        if any(isinstance(i, Stacked) for i in ivs) and all(
                isinstance(i, Stacked) or i.lower is i.upper for i in ivs):
            r = max(i.both.dim() - 1 if isinstance(i, Stacked) else i.lower.dim()
                    for i in ivs)  # stacked: one join (points expanded)
            parts = [i.both if isinstance(i, Stacked) else i.lower.expand(2, *i.lower.shape)
                     for i in ivs]
            parts = [t.reshape(2, *([1] * (r + 1 - t.dim())), *t.shape[1:]) if t.dim() <= r
                     else t for t in parts]
            return ivs[0]._pair(_join(op, parts, d)) if isinstance(ivs[0], Stacked) else \
                Interval._pair(_join(op, parts, d))
        lo = _join(op, [i.lower for i in ivs], d)
        if all(i.lower is i.upper for i in ivs):
            return point(lo)
        return Interval._make(lo, _join(op, [i.upper for i in ivs], d))

    j0 = items[0]
    return j0.like(join_iv([j.val for j in items]), join_iv([j.grad for j in items]),
                   join_iv([j.hess for j in items]))


@register(aten.cat, aten.concat, category="moving")
def _cat(ctx: Ctx, tensors: Sequence[Any], dim: int = 0) -> Any:
    return _join_jets(torch.cat, tensors, _neg_dim(dim, ctx.out_rank))


@register(aten.stack, category="moving")
def _stack(ctx: Ctx, tensors: Sequence[Any], dim: int = 0) -> Any:
    return _join_jets(torch.stack, tensors, _neg_dim(dim, ctx.out_rank))


@register(aten.split_with_sizes, aten.split, aten.split_with_sizes_copy, category="moving")
def _split(ctx: Ctx, x: Any, sizes: Any, dim: int = 0) -> list[Any]:
    r = ctx.rank(0)
    d = _neg_dim(dim, r)
    total = None
    if isinstance(sizes, int):  # split.Tensor: chunks of this size
        first = x.val.lower if isinstance(x, Jet) else x
        total = first.shape[d]
        sizes = [min(sizes, total - s) for s in range(0, total, sizes)]
    out, start = [], 0
    for s in sizes:
        out.append(_map_piece(x, r, lambda t, p, a=start, b=s: t.narrow(d, a, b)))
        start += s
    return out


@register(aten.unbind, category="moving")
def _unbind(ctx: Ctx, x: Any, dim: int = 0) -> list[Any]:
    r = ctx.rank(0)
    d = _neg_dim(dim, r)
    first = x.val.lower if isinstance(x, Jet) else x
    return [_map_piece(x, r, lambda t, p, i=i: t.select(d, i)) for i in range(first.shape[d])]


@register(aten._to_copy, aten.to, category="moving")
def _to_copy(ctx: Ctx, x: Any, *args: Any, dtype: Any = None, **kwargs: Any) -> Any:
    ref = x.val.lower if isinstance(x, Jet) else x
    if isinstance(x, (Jet, BoolBox)) and dtype is not None and dtype != ref.dtype:
        raise _unsupported(ctx, f"a cast of the state to {dtype} (keep the model in float64)")
    if isinstance(x, Tensor):
        return x.to(dtype=dtype) if dtype is not None else x
    return x


@register(aten.detach, category="moving")
def _detach(ctx: Ctx, x: Any) -> Any:
    if isinstance(x, Jet):
        raise _unsupported(ctx, ".detach() of the state (its derivative would be lost)")
    return x.detach() if isinstance(x, Tensor) else x


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


@register(aten.pow, category="elementwise")
def _pow(ctx: Ctx, a: Any, p: Any) -> Any:
    if not _is_jet(a) and not _is_jet(p):
        return torch.pow(a, p)
    if _is_jet(p) or (isinstance(p, Tensor) and p.numel() != 1):
        if not _is_jet(a):  # base ** jet = exp(jet * log(base))
            base = torch.as_tensor(a, dtype=p.val.lower.dtype)
            return _exp(ctx, mul(p, torch.log(base)))
        return _exp(ctx, mul(p if _is_jet(p) else p, _log(ctx, a)))
    pv = float(p.item() if isinstance(p, Tensor) else p)
    return _pow_scalar(a, pv)


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


# ----------------------------------------------------------------------------- elementwise
def _unary(fn: Callable[[Jet], Jet], torch_fn: Callable[..., Tensor]) -> Callable:
    def rule(ctx: Ctx, a: Any, *args: Any, **kwargs: Any) -> Any:
        if not _is_jet(a):
            return torch_fn(a, *args, **kwargs)
        return fn(a, *args, **kwargs)

    return rule


def _o(a: Jet, k: int) -> bool:
    return a.order >= k


def _exp_j(a: Jet) -> Jet:
    v = a.val.exp()
    return chain(a, v, v, v)


def _domain(a: Jet, low: float, strict: bool) -> tuple[Interval, Tensor]:
    """The argument clamped into ``[low, inf)`` and the mask of elements that left it.

    Clamping is sound: the true states are in the model's domain (the model is evaluated on
    them), so only the part of the set inside it must be enclosed; the function is enclosed by
    its continuous extension ``phi(max(x, low))``, whose derivative enclosure is unbounded where
    ``phi'`` is at ``low`` (sqrt, asin), and the filters then use a bound of lower order."""
    lo = a.val.lower
    bad = (lo <= low) if strict else (lo < low)
    cl = Interval._make(lo.clamp_min(low), a.val.upper.clamp_min(low))
    return cl, bad


# The derivatives of log, sqrt and rsqrt are quotients of non-negative numbers on the clamped
# domain (`_domain`), enclosed by `arith.quotient_nonneg` (the range from the end points)
# instead of the general interval reciprocal, which also covers intervals that cross 0.
def _log_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    r = arith.quotient_nonneg(1.0, x)
    return chain(a, x.log(), r, -r.square())


def _log1p_j(a: Jet) -> Jet:
    x, bad = _domain(a, -1.0, strict=False)
    # x + 1 >= 0 for x >= -1; the clamp keeps a sum rounded below 0 out of the quotient
    r = arith.quotient_nonneg(1.0, arith.clamp(x + 1.0, min=0.0))
    return chain(a, x.log1p(), r, -r.square())


def _sqrt_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    v = arith.monotone(x, torch.sqrt, 1, clamp_min=0.0)  # x >= 0: `Interval.sqrt` unchecked
    # sqrt' = 1 / (2 sqrt x), sqrt'' = -1 / (4 sqrt x) / x: falling magnitudes on x >= 0
    d1 = arith.quotient_nonneg(0.5, v) if _o(a, 1) else None
    d2 = -arith.quotient_nonneg(arith.quotient_nonneg(0.25, v), x) if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _rsqrt_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    v = arith.quotient_nonneg(1.0, arith.monotone(x, torch.sqrt, 1, clamp_min=0.0))
    r = arith.quotient_nonneg(1.0, x)
    d1 = v * r * (-0.5) if _o(a, 1) else None
    d2 = v * r.square() * 0.75 if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _expm1_j(a: Jet) -> Jet:
    e = a.val.exp()
    return chain(a, a.val.expm1(), e, e)


def _sin_j(a: Jet) -> Jet:
    v = a.val.sin()
    return chain(a, v, a.val.cos() if _o(a, 1) else None, -v)


def _cos_j(a: Jet) -> Jet:
    v = a.val.cos()
    return chain(a, v, -a.val.sin() if _o(a, 1) else None, -v)


def _tan_j(a: Jet) -> Jet:
    # tan is continuous between its poles; a box meeting a pole is a domain exit (NaN)
    lo, hi = a.val.lower, a.val.upper
    k_lo = torch.floor((lo.detach() + math.pi / 2) / math.pi)
    k_hi = torch.floor((hi.detach() + math.pi / 2) / math.pi)
    near = (hi - lo).detach() >= math.pi - 1e-12
    bad = (k_lo != k_hi) | near
    v = Interval._make(down(torch.tan(lo), 4), up(torch.tan(hi), 4))
    v = Interval._make(torch.where(bad, lo, v.lower), torch.where(bad, hi, v.upper))
    s = v.square() + 1.0  # tan' = 1 + tan^2, tan'' = 2 tan (1 + tan^2)
    return _nan_where(chain(a, v, s, v * s * 2.0), bad)


def _asin_like(a: Jet, fn: Callable[[Tensor], Tensor], sign: float) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    (lo < -1.0) | (hi > 1.0)
    x = Interval._make(lo.clamp(-1.0, 1.0), hi.clamp(-1.0, 1.0))
    f_lo, f_hi = fn(x.lower), fn(x.upper)
    v = Interval._make(down(torch.minimum(f_lo, f_hi), 4), up(torch.maximum(f_lo, f_hi), 4))
    q = (1.0 - x.square())  # 1 - x^2 >= 0
    q = Interval._make(q.lower.clamp_min(0.0), q.upper.clamp_min(0.0))
    r = q.sqrt().reciprocal()  # 1 / sqrt(1 - x^2), inf at +-1
    d1 = r * sign if _o(a, 1) else None
    d2 = x * r * q.reciprocal() * sign if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _atan_j(a: Jet) -> Jet:
    d1 = (a.val.square() + 1.0).reciprocal()
    return chain(a, a.val.atan(), d1, a.val * d1.square() * (-2.0) if _o(a, 2) else None)


def _sinh_j(a: Jet) -> Jet:
    v = a.val.sinh()
    return chain(a, v, a.val.cosh(), v)


def _cosh_j(a: Jet) -> Jet:
    v = a.val.cosh()
    return chain(a, v, a.val.sinh(), v)


def _tanh_j(a: Jet) -> Jet:
    v = a.val.tanh()
    d1 = 1.0 - v.square()
    return chain(a, v, d1, v * d1 * (-2.0) if _o(a, 2) else None)


def _sigmoid_j(a: Jet) -> Jet:
    v = a.val.sigmoid()
    d1 = v * (1.0 - v)
    return chain(a, v, d1, d1 * (1.0 - v * 2.0) if _o(a, 2) else None)


def _softplus_j(a: Jet, beta: float = 1.0, threshold: float = 20.0) -> Jet:
    # beta * softplus is the smooth log(1 + exp(beta x)); torch's threshold switches to x only
    # where it agrees with it to rounding (documented), so the smooth function is enclosed
    x = a.val * beta if beta != 1 else a.val
    v = x.softplus()
    s = x.sigmoid()
    if beta != 1:
        v = v / beta
    d2 = s * (1.0 - s) * beta if _o(a, 2) else None
    pad = math.exp(-threshold) if threshold * beta < 40 else 0.0
    v = Interval._make(v.lower - pad, v.upper + pad)
    return chain(a, v, s, d2)


def _erf_j(a: Jet) -> Jet:
    c = 2.0 / math.sqrt(math.pi)
    g = (-a.val.square()).exp() * c
    return chain(a, a.val.erf(), g, a.val * g * (-2.0) if _o(a, 2) else None)


def _gelu_j(a: Jet, approximate: str = "none") -> Jet:
    x = a.val
    if approximate != "none":  # tanh form: 0.5 x (1 + tanh(k (x + 0.044715 x^3)))
        k = math.sqrt(2.0 / math.pi)
        inner = _linear_combo(a, _pow_scalar(a, 3.0), k, k * 0.044715)
        t = _tanh_j(inner)
        return mul(mul(a, 0.5), _linear_combo(t, 1.0, 1, 1))
    phi = (-(x.square()) * 0.5).exp() * (1.0 / math.sqrt(2.0 * math.pi))
    cdf = ((x * (1.0 / math.sqrt(2.0))).erf() + 1.0) * 0.5
    # value: gelu is decreasing below its minimum point xm and increasing above
    xm = -0.7517916243457
    f_lo = torch.nn.functional.gelu(x.lower)
    f_hi = torch.nn.functional.gelu(x.upper)
    fmin = torch.nn.functional.gelu(torch.full_like(x.lower, xm))
    inside = (x.lower < xm) & (x.upper > xm)
    low = torch.where(inside, fmin, torch.minimum(f_lo, f_hi))
    v = Interval._make(down(low, 8), up(torch.maximum(f_lo, f_hi), 8))
    d1 = cdf + x * phi if _o(a, 1) else None
    d2 = phi * (2.0 - x.square()) if _o(a, 2) else None
    return chain(a, v, d1, d2)


for _op, _rule, _fn in (
    (aten.exp, _exp_j, torch.exp), (aten.log, _log_j, torch.log),
    (aten.log1p, _log1p_j, torch.log1p), (aten.expm1, _expm1_j, torch.expm1),
    (aten.sqrt, _sqrt_j, torch.sqrt), (aten.rsqrt, _rsqrt_j, torch.rsqrt),
    (aten.sin, _sin_j, torch.sin), (aten.cos, _cos_j, torch.cos), (aten.tan, _tan_j, torch.tan),
    (aten.asin, lambda a: _asin_like(a, torch.asin, 1.0), torch.asin),
    (aten.acos, lambda a: _asin_like(a, torch.acos, -1.0), torch.acos),
    (aten.atan, _atan_j, torch.atan), (aten.sinh, _sinh_j, torch.sinh),
    (aten.cosh, _cosh_j, torch.cosh), (aten.tanh, _tanh_j, torch.tanh),
    (aten.sigmoid, _sigmoid_j, torch.sigmoid), (aten.erf, _erf_j, torch.erf),
):
    register(_op, category="elementwise")(_unary(_rule, _fn))
register(aten.softplus, category="activation")(
    _unary(_softplus_j, torch.nn.functional.softplus))
register(aten.gelu, category="activation")(
    _unary(_gelu_j, lambda x, approximate="none": torch.nn.functional.gelu(
        x, approximate=approximate)))


def _exp(ctx: Ctx, a: Any) -> Any:
    return _exp_j(a) if _is_jet(a) else torch.exp(a)


def _log(ctx: Ctx, a: Any) -> Any:
    return _log_j(a) if _is_jet(a) else torch.log(a)


# ----------------------------------------------------------------------------- non-smooth
def _piecewise(a: Jet, v: Interval, d1_lo: Tensor, d1_hi: Tensor, kink: Tensor,
               d2: Interval | None = None) -> Jet:
    """A continuous piecewise function: slope hull ``[d1_lo, d1_hi]`` (its Clarke derivative),
    second derivative ``d2`` (default 0) except ``[-inf, inf]`` where a kink lies in the box."""
    d1 = Interval._make(d1_lo, d1_hi)
    if a.order >= 2:
        base = d2 if d2 is not None else point(torch.zeros_like(v.lower))
        inf = torch.full_like(v.lower, torch.inf)
        d2 = Interval._make(torch.where(kink, -inf, base.lower), torch.where(kink, inf, base.upper))
    return chain(a, v, d1, d2)


def _slopes(lo: Tensor, hi: Tensor, x0: float, left: float, right: float) -> tuple[Tensor, ...]:
    """Slope hull of a function with slope ``left`` below ``x0`` and ``right`` above."""
    below = hi <= x0
    above = lo >= x0
    sl = torch.full_like(lo, left)
    sr = torch.full_like(lo, right)
    smin = torch.minimum(sl, sr)
    smax = torch.maximum(sl, sr)
    d_lo = torch.where(below, sl, torch.where(above, sr, smin))
    d_hi = torch.where(below, sl, torch.where(above, sr, smax))
    return d_lo, d_hi, (lo < x0) & (hi > x0)


def _relu_j(a: Jet) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, 0.0, 1.0)
    return _piecewise(a, a.val.relu(), d_lo, d_hi, kink)


def _leaky_j(a: Jet, slope: float = 0.01) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, slope, 1.0)
    f = lambda t: torch.where(t >= 0, t, t * slope)  # noqa: E731 - monotone for slope >= 0
    v = Interval._make(down(torch.minimum(f(lo), f(hi))), up(torch.maximum(f(lo), f(hi))))
    return _piecewise(a, v, d_lo, d_hi, kink)


def _elu_j(a: Jet, alpha: float = 1.0, scale: float = 1.0, input_scale: float = 1.0) -> Jet:
    """ELU, ``alpha >= 0``: ``x`` above 0, ``alpha (e^x - 1)`` below (increasing)."""
    if alpha < 0:
        raise EngineError("elu: alpha < 0 is not supported")
    if input_scale != 1.0:
        a = mul(a, input_scale)
    x = a.val
    lo, hi = x.lower, x.upper
    neg = x.expm1() * alpha
    v = Interval._make(torch.where(lo >= 0, lo, neg.lower), torch.where(hi >= 0, hi, neg.upper))
    en = Interval._make(lo.clamp_max(0.0), hi.clamp_max(0.0)).exp() * alpha  # slopes below 0
    one = torch.ones_like(lo)
    d_lo = torch.where(lo >= 0, one, torch.where(hi > 0, torch.minimum(en.lower, one), en.lower))
    d_hi = torch.where(lo >= 0, one, torch.where(hi > 0, torch.maximum(en.upper, one), en.upper))
    zero = torch.zeros_like(lo)
    d2 = Interval._make(torch.where(hi <= 0, en.lower, zero), torch.where(hi <= 0, en.upper, zero))
    out = _piecewise(a, v, d_lo, d_hi, (lo < 0) & (hi > 0), d2)
    return mul(out, scale) if scale != 1.0 else out


def _clamp_j(a: Jet, lo_b: Any = None, hi_b: Any = None) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    ones = torch.ones_like(lo)
    zeros = torch.zeros_like(lo)
    mn = -math.inf if lo_b is None else lo_b
    mx = math.inf if hi_b is None else hi_b
    mn_t = torch.as_tensor(mn, dtype=lo.dtype, device=lo.device)
    mx_t = torch.as_tensor(mx, dtype=lo.dtype, device=lo.device)
    v = Interval._make(torch.clamp(lo, mn_t, mx_t), torch.clamp(hi, mn_t, mx_t))
    inside = (lo >= mn_t) & (hi <= mx_t)
    outside = (hi <= mn_t) | (lo >= mx_t)
    d_lo = torch.where(inside, ones, zeros)
    d_hi = torch.where(outside, zeros, ones)
    kink = ((lo < mn_t) & (hi > mn_t)) | ((lo < mx_t) & (hi > mx_t))
    return _piecewise(a, v, d_lo, d_hi, kink)


def _abs_j(a: Jet) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, -1.0, 1.0)
    return _piecewise(a, a.val.abs(), d_lo, d_hi, kink)


register(aten.relu, category="non-smooth")(_unary(_relu_j, torch.relu))
register(aten.leaky_relu, category="non-smooth")(
    _unary(_leaky_j, torch.nn.functional.leaky_relu))
register(aten.elu, category="non-smooth")(_unary(
    _elu_j, lambda x, alpha=1.0, scale=1.0, input_scale=1.0: aten.elu(x, alpha, scale,
                                                                      input_scale)))
register(aten.abs, category="non-smooth")(_unary(_abs_j, torch.abs))
register(aten.clamp, category="non-smooth")(_unary(_clamp_j, torch.clamp))
register(aten.clamp_min, category="non-smooth")(
    _unary(lambda a, m: _clamp_j(a, m, None), torch.clamp_min))
register(aten.clamp_max, category="non-smooth")(
    _unary(lambda a, m: _clamp_j(a, None, m), torch.clamp_max))
register(aten.hardtanh, category="non-smooth")(
    _unary(lambda a, mn=-1.0, mx=1.0: _clamp_j(a, mn, mx), torch.nn.functional.hardtanh))


@register(aten.maximum, aten.minimum, aten.fmax, aten.fmin, category="non-smooth")
def _maxmin(ctx: Ctx, a: Any, b: Any) -> Any:
    is_max = "max" in ctx.name
    if not _is_jet(a) and not _is_jet(b):
        return torch.maximum(a, b) if is_max else torch.minimum(a, b)
    # max(a, b) = b + relu(a - b); min(a, b) = a - relu(a - b)
    d = _linear_combo(a, b, 1, -1)
    r = _relu_j(d)
    return _linear_combo(b, r, 1, 1) if is_max else _linear_combo(a, r, 1, -1)


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


# ----------------------------------------------------------------------------- angles
@register(aten.atan2, category="elementwise")
def _atan2(ctx: Ctx, y: Any, x: Any) -> Any:
    """``atan2(y, x)``: on the right half-plane ``atan(y/x)``, above/below the x axis
    ``+-pi/2 - atan(x/y)``; a box meeting the branch cut (``x <= 0``, ``y = 0``) gets the hull
    ``[-pi, pi]`` and no derivative (the function jumps by ``2 pi`` there)."""
    if not _is_jet(y) and not _is_jet(x):
        return torch.atan2(y, x)
    ref = _ref([y, x])
    Y, X = _common([_lift(y, ref), _lift(x, ref)])
    xpos = X.val.lower > 0
    ypos = Y.val.lower > 0
    yneg = Y.val.upper < 0
    ok = xpos | ypos | yneg
    one = point(torch.ones_like(X.val.lower))
    safe_x = _select(xpos, X, one)
    safe_y = _select(ypos | yneg, Y, one)
    right = _atan_j(mul(Y, _recip_jet(safe_x)))
    side = _atan_j(mul(X, _recip_jet(safe_y)))
    half = math.pi / 2
    hp = Interval._make(torch.full_like(X.val.lower, math.nextafter(half, 0)),
                        torch.full_like(X.val.lower, math.nextafter(half, 4)))
    upper = _linear_combo(ref.like(hp, None, None), side, 1, -1)
    lower = _linear_combo(ref.like(-hp, None, None), side, 1, -1)
    out = _select(xpos, right, _select(ypos, upper, lower))
    pi = math.nextafter(math.pi, 4)
    cut = ref.like(Interval._make(torch.full_like(X.val.lower, -pi),
                                  torch.full_like(X.val.lower, pi)), None, None)
    return _select(ok, out, cut, undefined_derivative=True)


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


register(aten.scalar_tensor, category="constant")(lambda ctx, *a, **k: aten.scalar_tensor(*a, **k))


def _like_value(x: Any) -> Tensor:
    if isinstance(x, Jet):
        return x.val.lower
    if isinstance(x, BoolBox):
        return x.sure
    return x


@register(aten.full_like, category="constant")
def _full_like(ctx: Ctx, x: Any, value: Any, **kwargs: Any) -> Tensor:
    return aten.full_like(_like_value(x).detach(), value, **kwargs)


@register(aten.zeros_like, aten.empty_like, category="constant")
def _zeros_like(ctx: Ctx, x: Any, **kwargs: Any) -> Tensor:
    return aten.zeros_like(_like_value(x).detach(), **kwargs)


@register(aten.ones_like, category="constant")
def _ones_like(ctx: Ctx, x: Any, **kwargs: Any) -> Tensor:
    return aten.ones_like(_like_value(x).detach(), **kwargs)
