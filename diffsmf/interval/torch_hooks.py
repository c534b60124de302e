"""How a torch function reaches interval arithmetic: the table that maps torch functions and
operators on `IntervalArray` arguments to `diffsmf.interval.arith` (`TORCH_IMPL`, read by the
box's ``__torch_function__``) and `wrap_out`, which wraps a function's interval results.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval.arith import (
    IntervalArray,
    Iv,
    add,
    as_interval,
    div,
    matmul,
    mul,
    neg,
    power,
    relu,
    rpow,
    sub,
    total,
)

__all__ = ["TORCH_IMPL", "wrap_out"]

# ---------------------------------------------------------------------------- torch hooks
def _is_iv(x: Any) -> bool:
    return isinstance(x, IntervalArray)


def _binop(op: Callable[[Iv, Iv], Any], swap: bool = False) -> Callable:
    def f(x: Any, y: Any, *args: Any, **kwargs: Any) -> Any:
        if swap:
            x, y = y, x
        like = x if _is_iv(x) else y
        return op(as_interval(x, like), as_interval(y, like))

    return f


def _unary(name: str) -> Callable:
    def f(x: Any, *args: Any, **kwargs: Any) -> Any:
        return getattr(as_interval(x), name)(*args, **kwargs)

    return f


def _stack(tensors: Sequence[Any], dim: int = 0, *, out: Any = None) -> Any:
    like = next(t for t in tensors if _is_iv(t))
    ivs = [as_interval(t, like) for t in tensors]
    return like._make(
        torch.stack([i.lower for i in ivs], dim), torch.stack([i.upper for i in ivs], dim)
    )


def _cat(tensors: Sequence[Any], dim: int = 0, *, out: Any = None) -> Any:
    like = next(t for t in tensors if _is_iv(t))
    ivs = [as_interval(t, like) for t in tensors]
    return like._make(
        torch.cat([i.lower for i in ivs], dim), torch.cat([i.upper for i in ivs], dim)
    )


def _where(cond: Tensor, x: Any, y: Any) -> Any:
    like = x if _is_iv(x) else y
    a, b = as_interval(x, like), as_interval(y, like)
    return like._make(torch.where(cond, a.lower, b.lower), torch.where(cond, a.upper, b.upper))


def _maximum(x: Any, y: Any) -> Any:
    like = x if _is_iv(x) else y
    a, b = as_interval(x, like), as_interval(y, like)
    return like._make(torch.maximum(a.lower, b.lower), torch.maximum(a.upper, b.upper))


def _minimum(x: Any, y: Any) -> Any:
    like = x if _is_iv(x) else y
    a, b = as_interval(x, like), as_interval(y, like)
    return like._make(torch.minimum(a.lower, b.lower), torch.minimum(a.upper, b.upper))


def _like(fn: Callable) -> Callable:
    def f(x: Iv, *args: Any, **kwargs: Any) -> Tensor:
        return fn(x.lower, *args, **kwargs)

    return f


def _pow_fn(x: Any, p: Any) -> Any:
    if _is_iv(x):
        return power(x, p)
    return rpow(x, p)


def _softplus(x: Any, beta: float = 1.0) -> Any:
    iv = as_interval(x)
    if beta == 1.0:
        return iv.softplus()
    return (iv * beta).softplus() / beta


def _sum_fn(x: Iv, dim: Any = None, keepdim: bool = False, **kwargs: Any) -> Any:
    return total(x, dim, keepdim)


def _build_table() -> dict[Any, Callable]:
    T = torch.Tensor
    F = torch.nn.functional
    table: dict[Any, Callable] = {}
    for fns, impl in [
        ((torch.add, T.add, T.__add__, T.__radd__), _binop(add)),
        ((torch.sub, torch.subtract, T.sub, T.__sub__), _binop(sub)),
        ((T.__rsub__, torch.rsub), _binop(sub, swap=True)),
        ((torch.mul, torch.multiply, T.mul, T.__mul__, T.__rmul__), _binop(mul)),
        ((torch.div, torch.divide, torch.true_divide, T.div, T.__truediv__), _binop(div)),
        ((T.__rtruediv__,), _binop(div, swap=True)),
        ((torch.matmul, torch.mm, torch.mv, T.matmul, T.__matmul__), matmul),
        ((T.__rmatmul__,), lambda a, b: matmul(b, a)),
        ((torch.pow, T.pow, T.__pow__), _pow_fn),
        ((T.__rpow__,), lambda a, b: _pow_fn(b, a)),
        ((torch.stack,), _stack),
        ((torch.cat, torch.concat), _cat),
        ((torch.where,), _where),
        ((torch.maximum,), _maximum),
        ((torch.minimum,), _minimum),
        ((torch.sum, T.sum), _sum_fn),
        ((torch.zeros_like,), _like(torch.zeros_like)),
        ((torch.ones_like,), _like(torch.ones_like)),
        ((torch.full_like,), _like(torch.full_like)),
        ((torch.neg, torch.negative, T.neg, T.__neg__), lambda x: neg(as_interval(x))),
        ((F.relu,), lambda x, inplace=False: relu(as_interval(x))),
        ((F.softplus,), lambda x, beta=1.0, threshold=20.0: _softplus(x, beta)),
    ]:
        for fn in fns:
            table[fn] = impl
    for name in [
        "sin",
        "cos",
        "exp",
        "log",
        "sqrt",
        "tanh",
        "abs",
        "square",
        "sigmoid",
        "atan",
        "relu",
        "clamp",
        "reciprocal",
        "mean",
        "log1p",
        "expm1",
        "sinh",
        "cosh",
        "erf",
        "reshape",
        "unsqueeze",
        "squeeze",
        "transpose",
        "permute",
        "movedim",
        "flatten",
        "clone",
    ]:
        if hasattr(torch, name):
            table[getattr(torch, name)] = _unary(name)
        if hasattr(T, name):
            table[getattr(T, name)] = _unary(name)
    table[torch.arctan] = _unary("atan")
    table[torch.clip] = _unary("clamp")
    table[torch.absolute] = _unary("abs")
    return table


#: torch function -> its interval extension (the ``__torch_function__`` hook of ``Interval``).
TORCH_IMPL = _build_table()


def wrap_out(out: Any, cls: type) -> Any:
    """A function's result as interval arrays of class ``cls``: tensors (parts independent of
    the interval arguments) become point intervals; tuples and lists are mapped."""
    if isinstance(out, IntervalArray):
        return out
    if isinstance(out, Tensor):
        return cls._make(out, out)
    if isinstance(out, (tuple, list)):
        return type(out)(wrap_out(o, cls) for o in out)
    return out
