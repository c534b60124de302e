"""Point linearisations: autograd Jacobian / Hessian and the Stirling central difference.

``fn`` is a plain torch function ``fn(x [..., n]) -> [..., k]`` that treats the leading dims
as batch dims (output element ``b`` depends only on input element ``b``), as every
`System` function does. It may close over batched tensors (inputs
``u [B, p]``, parameters), so batching is never done by ``vmap`` over the batch: row i of
every Jacobian is the gradient of the summed output component i (the batch elements do not
interact).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.utils import broadcast_shapes, eager_constant, tracing

__all__ = [
    "hessian", "jacobian", "stirling_jacobian", "stirling_value_jacobian", "value_and_jacobian",
]

Fn = Callable[[Tensor], Tensor]


def _check_x(x: Tensor) -> Tensor:
    if not isinstance(x, Tensor) or x.dim() < 1:
        raise ValueError("x: expected a tensor of shape [..., n]")
    if not x.is_floating_point():
        x = x.to(torch.float64)
    return x


def jacobian(fn: Fn, x: Tensor) -> Tensor:
    """Autograd Jacobian ``d fn / d x`` at ``x [..., n]`` -> ``[..., k, n]``.

    Song et al. 2017, eq. 25 (``A = df/dx`` at the estimate; also the EKF and the DC tangent
    planes).

    One forward pass and one reverse pass per output component (the batch elements do not
    interact, so the gradient of the summed output component i is row i of every Jacobian).
    Plain ``torch.autograd.grad``: for the small ``k`` of state-space models this is faster
    than a ``vmap`` over cotangents, whose Python overhead dominated the filters' step time.
    Differentiable when grad mode is on (usable inside a loss, and twice: `hessian`
    nests it); under ``torch.no_grad`` the result is detached. If ``fn`` broadcasts ``x``
    against a larger batch (closure over batched tensors), ``x`` is first expanded to the
    output batch shape.
    """
    return value_and_jacobian(fn, x)[1]


def value_and_jacobian(fn: Fn, x: Tensor, *, points: bool = False) -> tuple[Tensor, Tensor]:
    """``(fn(x) [..., k], jacobian(fn, x) [..., k, n])`` from the same passes.

    The value is ``fn`` at ``x`` expanded to the output batch shape (detached under
    ``torch.no_grad``). ``points=True`` declares the leading dim of ``x`` a dim of stacked
    points (vertices, stencils) that ``fn``'s closures broadcast against, as the remainder
    bounds and `stirling_jacobian` stack them: then ``x`` is replicated ``r >= k`` times in
    a further leading dim, copy ``i`` feeding output component ``i``, and one reverse pass
    of ``sum_i y[i, ..., i]`` gives every row (one forward pass of ``r`` copies and one
    reverse pass instead of one forward and ``k`` reverse passes; the same values).
    """
    x = _check_x(x)
    if tracing():
        return _jacobian_forward(fn, x)
    if points and x.dim() >= 2:
        return _stacked(fn, x)
    graph = torch.is_grad_enabled()
    with torch.enable_grad():
        base = x if x.requires_grad else x.detach().requires_grad_()
        y = fn(base)
        if not isinstance(y, Tensor) or y.dim() < 1:
            raise ValueError("fn: must return a tensor of shape [..., k]")
        batch = broadcast_shapes(x.shape[:-1], y.shape[:-1])
        wrt = base
        if batch != x.shape[:-1] or batch != y.shape[:-1]:
            wrt = base.expand(*batch, x.shape[-1])
            y = fn(wrt).expand(*batch, y.shape[-1])
        k = y.shape[-1]
        val = y if graph else y.detach()
        if not y.requires_grad:  # fn does not depend on x (nor on anything with a gradient)
            return val, torch.zeros((*batch, k, x.shape[-1]), dtype=y.dtype, device=y.device)
        rows = []
        for i in range(k):
            (g,) = torch.autograd.grad(
                y[..., i].sum(), wrt, retain_graph=graph or i < k - 1, create_graph=graph,
                allow_unused=True,
            )
            rows.append(torch.zeros_like(wrt) if g is None else g)
    return val, torch.stack(rows, -2)


def _stacked(fn: Fn, x: Tensor) -> tuple[Tensor, Tensor]:
    """`value_and_jacobian` with ``points=True`` (``x [P, ..., n]``, eager)."""
    graph = torch.is_grad_enabled()
    n = x.shape[-1]
    with torch.enable_grad():
        base = x if x.requires_grad else x.detach().requires_grad_()
        r = n  # copies; the common k = n (state maps) needs a single evaluation
        wrt = base.expand(r, *x.shape)
        y = fn(wrt)
        if not isinstance(y, Tensor) or y.dim() < 2:
            raise ValueError("fn: must return a tensor of shape [..., k] (batch dims kept)")
        k = y.shape[-1]
        batch = broadcast_shapes(x.shape[:-1], y.shape[1:-1])
        if k > r or batch != x.shape[:-1] or y.shape[:-1] != (r, *batch):
            r = max(k, 1)
            wrt = base.expand(r, *batch, n)
            y = fn(wrt).expand(r, *batch, k)
        val = y[0]  # carries the graph only while grad mode records it (the caller's mode)
        if not y.requires_grad:  # fn does not depend on x (nor on anything with a gradient)
            return val, torch.zeros((*batch, k, n), dtype=y.dtype, device=y.device)
        (g,) = torch.autograd.grad(
            (y if r == k else y[:k]).diagonal(0, 0, -1).sum(), wrt, retain_graph=graph,
            create_graph=graph, allow_unused=True,
        )
    if g is None:
        return val, torch.zeros((*batch, k, n), dtype=y.dtype, device=y.device)
    return val, (g if r == k else g[:k]).movedim(0, -2)


def _jacobian_forward(fn: Fn, x: Tensor) -> tuple[Tensor, Tensor]:
    """``fn(x)`` and the forward-mode Jacobian ``[..., k, n]``: one ``torch.func.jvp`` per
    basis direction, vectorised by ``vmap`` over the n directions (not over the batch, so
    closures over batched tensors broadcast as usual). Used while ``torch.compile`` traces a
    filter step (``autograd.grad`` would break the graph); the values equal the reverse-mode
    ones up to rounding, and the result stays differentiable (reverse-over-forward).
    """
    n = x.shape[-1]
    y0 = fn(x)
    batch = torch.broadcast_shapes(x.shape[:-1], y0.shape[:-1])
    y0 = y0.expand(*batch, y0.shape[-1])
    xb = x.expand(*batch, n)
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    E = eye.reshape(n, *([1] * len(batch)), n).expand(n, *batch, n)

    def column(t: Tensor) -> Tensor:
        return torch.func.jvp(fn, (xb,), (t,))[1]

    cols = torch.func.vmap(column)(E)  # [n, *batch, k]
    return y0, cols.movedim(0, -1)


def hessian(fn: Fn, x: Tensor) -> Tensor:
    """Autograd Hessian of each output of ``fn`` at ``x [..., n]`` -> ``[..., k, n, n]``.

    Song et al. 2017, eq. 26-28 (``N_es``, here at a point; the guaranteed version over a box is
    `diffsmf.linearize.interval_hessian`).
    """
    x = _check_x(x)
    n = x.shape[-1]

    def jac_flat(z: Tensor) -> Tensor:
        J = jacobian(fn, z)
        return J.reshape(*J.shape[:-2], -1)  # [..., k*n]

    H = jacobian(jac_flat, x)  # [..., k*n, n]
    return H.reshape(*H.shape[:-2], -1, n, n)


def stirling_jacobian(fn: Fn, x: Tensor, h: Tensor | float) -> Tensor:
    """Stirling (central-difference) slope matrix at ``x [..., n]`` -> ``[..., k, n]``.

    Wang et al. 2022, eq. 12-13: column j is ``(fn(x + h_j e_j) - fn(x - h_j e_j)) / (2 h_j)``.
    ``h`` is a positive finite scalar or a tensor broadcastable to ``[..., n]``
    (per-coordinate steps); the result is differentiable in ``h`` and ``x``. Exact for
    quadratic ``fn``.
    The 2n stencil points are stacked in a new *leading* dim so that closures over batched
    tensors broadcast correctly.
    """
    x = _check_x(x)
    h = torch.as_tensor(h, dtype=x.dtype, device=x.device)
    hd = h.detach()
    if not tracing() and not bool(((hd > 0) & (hd < math.inf)).all()):  # NaN, inf, <= 0
        raise ValueError("h: the Stirling step must be positive and finite")
    n = x.shape[-1]
    try:
        shape = torch.broadcast_shapes(h.shape, x.shape)
        hx = h if h.shape == shape else torch.broadcast_to(h, shape)  # [..., n]
    except RuntimeError as exc:
        msg = f"h: shape {tuple(h.shape)} does not broadcast to x {tuple(x.shape)}"
        raise ValueError(msg) from exc
    y0 = fn(x)  # one plain evaluation tells the output batch shape (closures over batches)
    batch = torch.broadcast_shapes(hx.shape[:-1], y0.shape[:-1])
    if hx.shape[:-1] != batch:
        hx = hx.expand(*batch, n)
    if x.shape[:-1] != batch:
        x = x.expand(*batch, n)
    plus, minus = fn(_stencil_points(x, hx, center=False)).split(n)  # [n, ..., k] each
    return _central_slopes(plus, minus, hx)


def stirling_value_jacobian(fn: Fn, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """``(fn(x) [..., k], stirling_jacobian(fn, x, h) [..., k, n])`` from one call of ``fn``
    on the 2n + 1 points ``x``, ``x + h_j e_j``, ``x - h_j e_j`` (stacked in a leading dim).

    The filters' form of `stirling_jacobian` (Wang et al. 2022, eq. 12-13, and the model at
    the centre, eq. 20): ``x`` must already carry every batch dim of the tensors that ``fn``
    closes over (the filters' centres ``[B, n]`` do), and ``h [..., n]`` (broadcastable to
    ``x``) must be positive; neither is checked. The same values as the two separate calls.
    """
    n = x.shape[-1]
    fc, plus, minus = fn(_stencil_points(x, h, center=True)).split([1, n, n])  # [2n + 1, ..., k]
    return fc.squeeze(0), _central_slopes(plus, minus, h)


#: Stencil sign tables of `_stencil_points`, per (n, batch dims, center, dtype, device).
_STENCILS: dict[tuple, Tensor] = {}


def _stencil_points(x: Tensor, h: Tensor, center: bool) -> Tensor:
    """The Stirling points ``[(1 +) 2n, ..., n]``: (``x``,) ``x + h_j e_j`` for j < n, then
    ``x - h_j e_j``, as ``x + E h`` with a constant sign table ``E`` (entries 0, +1, -1: the
    same values as adding ``+-h_j`` to coordinate j alone; ``h`` finite, ``[..., n]``
    broadcastable to ``x``)."""
    n, nb = x.shape[-1], x.dim() - 1

    def make() -> Tensor:
        with torch.no_grad():
            eye = torch.eye(n, dtype=x.dtype, device=x.device)
            rows = [eye, -eye] if not center else [eye.new_zeros(1, n), eye, -eye]
            return torch.cat(rows).reshape(-1, *([1] * nb), n)

    return x + eager_constant(_STENCILS, (n, nb, center, x.dtype, x.device), make) * h


def _central_slopes(plus: Tensor, minus: Tensor, hx: Tensor) -> Tensor:
    """``(plus - minus) / (2 h)`` with the stencil dim ``[n, ..., k]`` moved last ->
    ``[..., k, n]`` (``hx [..., n]``, whose batch dims those of ``plus`` end with)."""
    return (plus - minus).movedim(0, -1) / (2 * hx).unsqueeze(-2)
