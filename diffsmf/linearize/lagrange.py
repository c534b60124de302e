"""Remainder bounds from interval derivatives over the hull of a set: the Lagrange form with the
interval Hessian (Song et al. 2017, eq. 26-28), the mean-value form with the interval Jacobian,
and the parameter deviation (Song et al. 2017, eq. 18-21).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.interval.box import Interval
from diffsmf.interval.engine import enclose_dynamics
from diffsmf.linearize.bound_parts import (
    Fn,
    _affine_remainder,
    _check,
    _hull_with,
    _known_affine,
    _lagrange,
    _lower_order,
    _padded,
    _remember,
)
from diffsmf.linearize.jacobians import jacobian
from diffsmf.linearize.jets import jet_eval

__all__ = ["lagrange_remainder", "mean_value_remainder", "parameter_deviation"]

def lagrange_remainder(fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
    """Lagrange remainder bound with the interval Hessian -> Interval ``[..., k]``.

    Song et al. 2017, eq. 26-28: ``r(x) = 1/2 (x-c)' H(xi) (x-c)`` with ``H`` enclosed by the
    interval Hessian over the interval hull of ``S`` and ``c``; the quadratic form is bounded in
    interval arithmetic over ``x - c`` in the hull. If ``J`` differs from the exact Jacobian
    at ``c`` (e.g. Stirling slopes), the exact range of ``(J_exact(c) - J)(x - c)`` over ``S``
    (support function) is added. ``J=None`` means the exact Jacobian.
    """
    c, J = _check(S, c, J)
    if _known_affine(fn):
        return _affine_remainder(fn, S, c, J)
    box = _hull_with(S, c)
    jet = jet_eval(fn, box, order=2)  # value and Hessian enclosures over the hull
    if _remember(fn, jet):
        return _affine_remainder(fn, S, c, J)
    D = None if J is None else jacobian(fn, c) - J
    return _lower_order(fn, jet, box, S, c, J, _lagrange(jet, box, S, c, J, D))


def parameter_deviation(
    f: Callable[..., Tensor],
    S: ConvexSet,
    params: Interval,
    theta_nom: Tensor | None = None,
    u: Tensor | None = None,
) -> Interval:
    """Enclosure of ``f(x, u, theta) - f(x, u, theta_nom)`` for x in S, theta in params.

    Song et al. 2017, eq. 18-21 (there evaluated at the estimate only, which is not guaranteed for
    the other x in S). Here two guaranteed enclosures over the box hull of S are intersected:
    the simple interval extension ``F(X, u, Theta) - F(X, u, theta_nom)`` (eq. 20) and the
    mean-value form ``sum_j [df/dtheta_j](X, Theta) (Theta_j - theta_nom_j)`` with the
    interval Jacobian w.r.t. theta (exact range when f is affine in theta). -> ``[..., n]``.
    """
    if not isinstance(params, Interval):
        raise ValueError("params: expected an Interval of parameters [q]")
    box = S.interval_hull()
    box = _padded(box.lower, box.upper, box.lower.abs() + box.upper.abs())
    q = params.shape[-1]
    th_nom = params.center if theta_nom is None else torch.as_tensor(theta_nom, dtype=S.dtype)
    theta_box = params.hull(Interval(th_nom, th_nom))  # theta_nom may lie outside params
    n = S.dim
    batch = torch.broadcast_shapes(box.shape[:-1], theta_box.shape[:-1])
    theta_box = Interval._make(theta_box.lower.expand(*batch, q), theta_box.upper.expand(*batch, q))
    box = Interval._make(box.lower.expand(*batch, n), box.upper.expand(*batch, n))
    both = enclose_dynamics(f, box, theta_box, u, order=1)  # over X and the theta hull
    th_pt = torch.as_tensor(th_nom, dtype=S.dtype).expand(*batch, q)
    nominal = enclose_dynamics(f, box, Interval._make(th_pt, th_pt), u, order=0)
    nat = both.val - nominal.val  # eq. 20 (over the hull of params and theta_nom)
    Jth = both.grad[..., n:]  # [..., n, q]
    mv = (Jth * params.__sub__(th_nom).unsqueeze(-2)).sum(-1)
    return nat.intersect(mv)


def mean_value_remainder(fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
    """Vertex-free mean-value remainder bound with the interval Jacobian -> Interval ``[..., k]``.

    ``r(x) = fn(x) - fn(c) - J (x - c) = (J_fn(xi) - J)(x - c)`` for some ``xi`` on the
    segment ``[c, x]`` (mean-value theorem, row by row), so with ``[J_fn]`` the interval
    Jacobian over the hull of ``S`` and ``c`` (first-order interval jets, Song et al. 2017, sec.
    3.2):

        r(x) in ([J_fn] - J) (box - c)

    evaluated in outward-rounded interval arithmetic. Cost and memory are ``O(k n)`` per jet
    operation (no Hessians, no vertices), so it scales to n = 32 and beyond; the bound is of
    second order in the set's width when ``J`` is close to the Jacobian at ``c`` (Stirling or
    autograd slopes), about twice `lagrange_remainder`'s in the quadratic regime.
    ``J=None`` means the autograd Jacobian at ``c``.
    """
    c, J = _check(S, c, J)
    box = _hull_with(S, c)
    jet = jet_eval(fn, box, order=1)
    if J is None:
        J = jacobian(fn, c)
    inf = torch.full_like(jet.val.lower, torch.inf)
    return _lower_order(fn, jet, box, S, c, J, Interval._make(-inf, inf))  # the first-order bound
