"""Products whose gradients stay finite where an operand is infinite: ``times`` and ``mm``
are the plain products in value, and their backward passes take the finite part of the other
operand (an unbounded interval end must not send ``inf * 0 = NaN`` into the gradients of the
finite ones).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

__all__ = ["mm", "times"]

def _finite_part(t: Tensor) -> Tensor:
    """``t`` with its infinite and NaN entries 0 (the operand of a product's gradient)."""
    return torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0)


class _SavesInputs(torch.autograd.Function):
    """An autograd Function whose backward reads its inputs (``ctx.saved_tensors``)."""

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:  # noqa: D102
        ctx.save_for_backward(*inputs)


class _FiniteGradMul(_SavesInputs):
    """``x * y`` whose gradients are those of the finite parts: ``g * y`` with the infinite
    and NaN entries of ``y`` taken as 0 (and the same for ``x``). An unbounded enclosure (the
    Hessian of a ReLU network at a kink, a set that diverged) is never used with a gradient
    by the remainders, which mask it; its gradient is 0, and the plain product's backward
    would turn that 0 into ``0 * inf = NaN`` in the gradients of the model's parameters.
    The values are the plain product's, bit for bit."""

    @staticmethod
    def forward(x: Tensor, y: Tensor) -> Tensor:  # noqa: D102
        return x * y

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None]:  # noqa: D102
        x, y = ctx.saved_tensors
        gx = _reduce_to(g * _finite_part(y), x) if ctx.needs_input_grad[0] else None
        gy = _reduce_to(g * _finite_part(x), y) if ctx.needs_input_grad[1] else None
        return gx, gy


class _FiniteGradSquare(_SavesInputs):
    """``x * x`` with the gradient ``2 g x`` of the finite part of ``x`` (`_FiniteGradMul`;
    a Function of one input: Dynamo does not trace one applied to the same tensor twice)."""

    @staticmethod
    def forward(x: Tensor) -> Tensor:  # noqa: D102
        return x * x

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> Tensor:  # noqa: D102
        (x,) = ctx.saved_tensors
        return 2.0 * g * _finite_part(x)


class _FiniteGradMatmul(_SavesInputs):
    """``x @ y`` (``torch.matmul``) with the gradients of `_FiniteGradMul` (the operands'
    finite parts)."""

    @staticmethod
    def forward(x: Tensor, y: Tensor) -> Tensor:  # noqa: D102
        return x @ y

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None]:  # noqa: D102
        x, y = ctx.saved_tensors
        xs, ys = x, y
        if x.dim() == 1:  # a vector on the left is a row, on the right a column
            xs, g = x.unsqueeze(0), g.unsqueeze(-2)
        if y.dim() == 1:
            ys, g = y.unsqueeze(-1), g.unsqueeze(-1)
        gx = gy = None
        if ctx.needs_input_grad[0]:
            gx = _reduce_to(g @ _finite_part(ys).mT, xs).reshape(x.shape)
        if ctx.needs_input_grad[1]:
            gy = _reduce_to(_finite_part(xs).mT @ g, ys).reshape(y.shape)
        return gx, gy


def _reduce_to(g: Tensor, like: Tensor) -> Tensor:
    """The gradient ``g`` of a broadcast product summed to ``like``'s shape."""
    if g.shape == like.shape:
        return g
    lead = g.dim() - like.dim()
    dims = [i for i in range(g.dim()) if i < lead or like.shape[i - lead] == 1 != g.shape[i]]
    return g.sum(dims, keepdim=True).reshape(like.shape) if dims else g.reshape(like.shape)


def _needs_safe_grad(x: Tensor, y: Tensor) -> bool:
    return torch.is_grad_enabled() and (x.requires_grad or y.requires_grad)


def times(x: Tensor, y: Tensor) -> Tensor:
    """``x * y`` of bound tensors: the plain product, with `_FiniteGradMul`'s gradients when
    one records a gradient (the same values either way)."""
    if not _needs_safe_grad(x, y):
        return x * y
    return _FiniteGradSquare.apply(x) if x is y else _FiniteGradMul.apply(x, y)


def mm(x: Tensor, y: Tensor) -> Tensor:
    """``x @ y`` of bound tensors, with `_FiniteGradMatmul`'s gradients when one records a
    gradient (the same values either way)."""
    return _FiniteGradMatmul.apply(x, y) if _needs_safe_grad(x, y) else x @ y
