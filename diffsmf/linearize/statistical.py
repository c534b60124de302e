"""Statistical linearisation over an ellipsoid on 4N+1 axis points (Jiang et al. 2016, eq. 48-55).

The affine map ``fn(x) ~ A x + b`` is fitted by weighted least squares to the values of ``fn`` at
points spread evenly on the axes of the ellipsoid ``F(c, S) = {x : (x-c)' S^-1 (x-c) <= 1}``
(Morrell & Stirling 1991, the method Jiang et al. 2016 cites as [19]). With the default levels
``(0.5, 1.0)`` each axis carries the points ``c +- 0.5 a_i`` and ``c +- a_i`` (``a_i`` the i-th
semi-axis), which together with the centre give the paper's 4N+1 points.

The fit is exact (up to rounding) for affine ``fn``. It carries no bound on the linearisation
error: it is the paper's approximation, not a guaranteed enclosure.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.utils import tracing

__all__ = ["axis_points", "check_levels", "statistical_linearization"]

_AXES = ("principal", "symmetric")


class _SqrtmPSD(torch.autograd.Function):
    """Symmetric square root of a PSD matrix with a Sylvester-equation backward.

    The backward solves ``X dX + dX X = dS`` in the eigenbasis, dividing by
    ``sqrt(l_i) + sqrt(l_j)``: finite for repeated eigenvalues (unlike ``eigh``'s backward).
    """

    @staticmethod
    def forward(ctx, S: Tensor) -> Tensor:  # type: ignore[override]
        evals, V = linalg.eigh(S)  # closed form for n <= 2
        s = _axis_lengths(evals)
        ctx.save_for_backward(s, V)
        return linalg.matmul(V * s.unsqueeze(-2), V.mT)

    @staticmethod
    def backward(ctx, G: Tensor) -> Tensor:  # type: ignore[override]
        s, V = ctx.saved_tensors
        mm = linalg.matmul
        Gs = mm(mm(V.mT, 0.5 * (G + G.mT)), V)
        denom = (s.unsqueeze(-1) + s.unsqueeze(-2)).clamp_min(torch.finfo(s.dtype).tiny)
        return mm(mm(V, Gs / denom), V.mT)


class _EighSafe(torch.autograd.Function):
    """``eigh`` whose backward drops the eigenvector terms of (numerically) repeated eigenvalues.

    The standard backward ``V (diag(gl) + F o (V' gV)) V'`` with ``F_ij = 1/(l_j - l_i)``
    divides by zero when eigenvalues repeat (e.g. an x/y-symmetric ellipsoid), where the
    principal axes are not differentiable at all (any basis of the eigenspace is a valid
    choice). There ``F_ij`` is set to 0, i.e. the chosen basis is held fixed; elsewhere the
    gradient is exact.
    """

    @staticmethod
    def forward(ctx, S: Tensor) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        evals, V = linalg.eigh(S)  # closed form for n <= 2
        ctx.save_for_backward(evals, V)
        return evals, V

    @staticmethod
    def backward(ctx, gl: Tensor, gV: Tensor) -> Tensor:  # type: ignore[override]
        evals, V = ctx.saved_tensors
        gap = evals.unsqueeze(-2) - evals.unsqueeze(-1)  # l_j - l_i
        tol = 1e-10 * evals.abs().amax(-1, keepdim=True).unsqueeze(-1).clamp_min(1e-300)
        F = torch.where(gap.abs() > tol, 1.0 / torch.where(gap == 0, 1.0, gap), 0.0)
        mm = linalg.matmul
        inner = F * mm(V.mT, gV) if gV is not None else torch.zeros_like(V)
        if gl is not None:
            inner = inner + torch.diag_embed(gl)
        g = mm(mm(V, inner), V.mT)
        return 0.5 * (g + g.mT)


#: Shortest semi-axis used by the fit, relative to the longest (see `_axis_lengths`).
AXIS_FLOOR = 1e-12


def _axis_lengths(evals: Tensor) -> Tensor:
    """Semi-axis lengths ``sqrt(l_i)`` ``[..., n]``, raised to ``AXIS_FLOOR`` times the longest.

    A degenerate ellipsoid (a collapsed direction, e.g. after an exact measurement: V = {0})
    has a zero semi-axis; the fit's ``A = G M^-1`` would then be 0 / 0. On such an axis the
    points are spread by the floor instead, which gives the slope of ``fn`` there (any finite
    slope would do: ``A`` only acts on the ellipsoid's range). Lengths above the floor, i.e.
    every non-degenerate ellipsoid, are unchanged bit for bit. An all-zero shape gets the
    smallest normal number's square root, so ``A`` stays finite.
    """
    s = evals.clamp_min(0).sqrt()
    tiny = torch.finfo(s.dtype).tiny ** 0.5
    floor = (AXIS_FLOOR * s.amax(-1, keepdim=True)).clamp_min(tiny)
    return torch.where(s > floor, s, floor)


def _axes_matrix(shape: Tensor, axes: str) -> Tensor:
    """Matrix M ``[..., n, n]`` whose columns are the semi-axes used (``S = M M'``, up to the
    floor of `_axis_lengths` on degenerate axes)."""
    if axes == "principal":  # principal semi-axes sqrt(l_i) v_i (Morrell & Stirling)
        evals, V = _EighSafe.apply(shape)
        return V * _axis_lengths(evals).unsqueeze(-2)
    return _SqrtmPSD.apply(shape)  # columns of S^(1/2): boundary points, smooth in S


def _unit_points(n: int, levels: Sequence[float], like: Tensor) -> Tensor:
    """Axis coordinates ``z [K, n]``: 0, then for each axis i and level t: +t e_i, -t e_i."""
    eye = torch.eye(n, dtype=like.dtype, device=like.device)
    rows = [torch.zeros(1, n, dtype=like.dtype, device=like.device)]
    for i in range(n):
        for t in levels:
            rows.append(torch.stack([t * eye[i], -t * eye[i]]))
    return torch.cat(rows, 0)


def check_levels(levels: Sequence[float]) -> tuple[float, ...]:
    lv = tuple(float(t) for t in levels)
    if len(lv) == 0 or any(not (t > 0) for t in lv):
        raise ValueError(f"levels: need at least one positive level, got {levels!r}")
    return lv


def axis_points(
    center: Tensor, shape: Tensor, levels: Sequence[float] = (0.5, 1.0), axes: str = "principal"
) -> tuple[Tensor, Tensor, Tensor]:
    """Points spread evenly on the ellipsoid's axes (Jiang et al. 2016, sec. 2.2, fig. 2).

    Args:
        center: ``[..., n]``; shape: ``[..., n, n]`` symmetric positive definite.
        levels: fractions of each semi-axis where points are placed (both signs); the default
            ``(0.5, 1.0)`` gives the paper's 4N+1 points. ``K = 2 * len(levels) * n + 1``.
        axes: ``"principal"`` (eigenvectors scaled by sqrt(eigenvalues), the paper's choice;
            not differentiable where ``shape`` has repeated eigenvalues, where the backward
            holds the eigenbasis fixed instead of returning NaN, see `_EighSafe`) or
            ``"symmetric"`` (columns of ``shape^(1/2)``; equal to the principal axes for
            axis-aligned ellipsoids, smooth everywhere).

    Returns:
        ``points [K, ..., n]`` (the point index leads, so that tensors closed over by a user's
        function, e.g. inputs ``u [B, p]``, broadcast against it), ``z [K, n]`` (coordinates:
        ``points[i] = center + M z_i``) and ``M [..., n, n]`` (columns = semi-axes,
        ``shape = M M'``).
    """
    if axes not in _AXES:
        raise ValueError(f"axes: expected one of {_AXES}, got {axes!r}")
    lv = check_levels(levels)
    if center.dim() < 1 or shape.shape[-2:] != (center.shape[-1], center.shape[-1]):
        raise ValueError(
            f"shape: expected [..., n, n] with n = {center.shape[-1]}, got {tuple(shape.shape)}"
        )
    M = _axes_matrix(shape, axes)
    z = _unit_points(center.shape[-1], lv, center)
    points = center + linalg.matmul(z, M.mT).movedim(-2, 0)  # [K, ..., n]
    return points, z, M


def _weight_vector(weights: Tensor | Sequence[float] | None, K: int, nlev: int, like: Tensor):
    """Per-point weights ``[K]`` from None (uniform), ``[K]`` or ``[1 + len(levels)]``."""
    if weights is None:
        return torch.ones(K, dtype=like.dtype, device=like.device)
    w = torch.as_tensor(weights, dtype=like.dtype, device=like.device)
    if w.dim() != 1 or w.shape[0] not in (K, 1 + nlev):
        raise ValueError(f"weights: expected shape [{K}] or [{1 + nlev}], got {tuple(w.shape)}")
    if not tracing() and (torch.isnan(w).any() or (w < 0).any()):
        raise ValueError("weights: must be non-negative and not NaN")
    if w.shape[0] == 1 + nlev and K != 1 + nlev:  # centre weight, then one weight per level
        n = (K - 1) // (2 * nlev)
        w = torch.cat([w[:1], w[1:].repeat_interleave(2).repeat(n)])
    return w


def _symmetric_weights(weights: Tensor | Sequence[float] | None, K: int, nlev: int) -> bool:
    """True when each pair ``c +- t a_i`` carries one weight (None or ``[1 + len(levels)]``
    weights): then the normal matrix of the fit is diagonal. Decided from shapes only."""
    if weights is None:
        return True
    size = weights.shape[0] if isinstance(weights, Tensor) and weights.dim() == 1 else len(weights)
    return size == 1 + nlev


def statistical_linearization(
    fn: Callable[[Tensor], Tensor],
    center: Tensor,
    shape: Tensor,
    *,
    levels: Sequence[float] = (0.5, 1.0),
    weights: Tensor | Sequence[float] | None = None,
    axes: str = "principal",
) -> tuple[Tensor, Tensor]:
    """Weighted least-squares affine fit ``fn(x) ~ A x + b`` over ``F(center, shape)``.

    Jiang et al. 2016, eq. 50-55 (eq. 54 for the state map, eq. 55 for the measurement map):
    minimise ``sum_i l_i |fn(x_i) - A x_i - b|^2`` over the axis points of `axis_points`. The
    fit is done in the axis coordinates ``z`` (``x = c + M z``), whose normal matrix does not depend
    on the ellipsoid's scale, then mapped back with ``torch.linalg.solve`` (no inverse).

    Args:
        fn: ``fn(x [K, ..., n]) -> [K, ..., k]`` (batched torch function).
        center: ``[..., n]``; shape: ``[..., n, n]`` positive definite.
        levels: see `axis_points`.
        axes: see `axis_points`.
        weights: point weights ``l_i``: ``None`` (all 1), ``[K]`` (one per point, in the order
            of `axis_points`) or ``[1 + len(levels)]`` (centre, then one per level).

    Returns:
        ``A [..., k, n]``, ``b [..., k]``.
    """
    points, z, M = axis_points(center, shape, levels, axes)
    K, n = z.shape
    w = _weight_vector(weights, K, len(tuple(levels)), z)
    Z1 = torch.cat([z, torch.ones(K, 1, dtype=z.dtype, device=z.device)], -1)  # [K, n+1]
    wZ1 = w.unsqueeze(-1) * Z1
    symmetric = _symmetric_weights(weights, K, len(tuple(levels)))
    if not tracing() or not symmetric:
        normal = Z1.mT @ wZ1  # eq. 54: F L F'
        if not tracing() and bool(torch.linalg.cholesky_ex(normal)[1] != 0):
            raise ValueError("weights: the weighted points do not determine an affine fit")
    Y = fn(points)  # [K, ..., k]
    if Y.dim() != points.dim() or Y.shape[0] != K:
        raise ValueError(f"fn: expected output [{K}, ..., k], got {tuple(Y.shape)}")
    rhs = linalg.matmul(wZ1.mT, Y.movedim(0, -2))  # F L beta' [..., n+1, k]
    if symmetric:
        # +-t point pairs with equal weights: the normal matrix is diagonal (exactly, up to
        # the rounding of its zero entries), so the fit is a division by its diagonal
        # (no LAPACK call, and no matrix product while tracing)
        theta = rhs / (wZ1 * Z1).sum(0).unsqueeze(-1)  # eq. 54: [..., n+1, k]
    else:
        theta = torch.linalg.solve(normal, rhs)  # eq. 54: [..., n+1, k]
    G, g0 = theta[..., :n, :].mT, theta[..., n, :]  # fn(c + M z) ~ G z + g0
    A = linalg.solve(M.mT, G.mT).mT  # A = G M^-1 (closed form for n <= 2)
    b = g0 - linalg.matmul(A, center.unsqueeze(-1)).squeeze(-1)
    return A, b
