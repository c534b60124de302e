"""Rules of the ops that move values without computing (views, indexing, joins, copies) and of
the ops that make constants.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval.arith import Stacked
from diffsmf.interval.box import Interval
from diffsmf.interval.jet import Jet, move, point
from diffsmf.interval.rules.base import (
    BoolBox,
    Ctx,
    _common,
    _map_piece,
    _neg_dim,
    _unsupported,
    aten,
    register,
)
from diffsmf.utils import broadcast_shapes

__all__ = []

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
