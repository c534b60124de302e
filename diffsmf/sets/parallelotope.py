"""Parallelotopes ``P = {c + T eta : ||eta||_inf <= 1}``, T square and invertible (Wang et al.
2022).

``center [..., n]``, ``T [..., n, n]``. Batched and differentiable; linear solves, never
explicit inverses.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import (
    ConvexSet,
    as_offset,
    as_tensor,
    as_vector,
    check_count,
    check_finite,
    strip_batch,
    strip_fields,
)
from diffsmf.linalg import small_sum
from diffsmf.utils import broadcast_shapes, checking

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.ellipsoid import Ellipsoid
    from diffsmf.sets.interval import Interval
    from diffsmf.sets.strip import Strip
    from diffsmf.sets.zonotope import Zonotope

__all__ = ["Parallelotope"]

_EPS = torch.finfo(torch.float64).eps
TIE_RTOL = 1e-12
"""Relative volume tolerance of the tie rule of `Parallelotope.intersect_strip`
(Wang et al. 2022, eq. 38-39): candidates within it of the least volume are tied."""


class Parallelotope(ConvexSet):
    """Parallelotope ``{c + T eta : eta in [-1, 1]^n}`` (Wang et al. 2022 "hyperparallel space").

    Args:
        center: ``[..., n]``.
        T: ``[..., n, n]``, invertible. Batch dims broadcast.

    Raises:
        ValueError: naming ``center`` or ``T`` on NaN/inf, a shape mismatch, or a singular
            ``T`` (smallest singular value <= 1e-13 x largest).
    """

    _fields: ClassVar[tuple[str, ...]] = ("_c", "T")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2)

    def __init__(self, center: Any, T: Any) -> None:
        c = check_finite("center", as_tensor("center", center, min_dim=1, field=True))
        T = check_finite("T", as_tensor("T", T, like=c, min_dim=2, field=True))
        n = c.shape[-1]
        if T.shape[-1] != T.shape[-2]:
            raise ValueError(f"T: must be square, got shape {tuple(T.shape)}")
        if T.shape[-1] != n:
            raise ValueError(f"T: expected [..., {n}, {n}] to match center, got {tuple(T.shape)}")
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], T.shape[:-2])
        except RuntimeError as exc:
            raise ValueError(
                f"T: batch shape {tuple(T.shape[:-2])} does not broadcast with center batch "
                f"shape {tuple(c.shape[:-1])}"
            ) from exc
        if T.numel() > 0 and checking():
            sv = torch.linalg.svdvals(T.detach())
            if (sv[..., -1] <= 1e-13 * sv[..., 0]).any() or (sv[..., 0] == 0).any():
                raise ValueError("T: singular (parallelotope must be full-dimensional)")
        self._set(_c=c.expand(*batch, n), T=T.expand(*batch, n, n))

    @classmethod
    def _make(cls, c: Tensor, T: Tensor) -> Parallelotope:
        """Internal constructor without validation (broadcasts the batch dims)."""
        batch = broadcast_shapes(c.shape[:-1], T.shape[:-2])
        n = c.shape[-1]
        obj = object.__new__(cls)
        object.__setattr__(obj, "_c", _expand(c, (*batch, n)))
        object.__setattr__(obj, "T", _expand(T, (*batch, n, n)))
        return obj

    @property
    def center(self) -> Tensor:
        """``[..., n]``."""
        return self._c

    @property
    def generators(self) -> Tensor:
        """``T`` viewed as zonotope generators ``[..., n, n]``."""
        return self.T

    # ------------------------------------------------------------------ set API
    def volume(self) -> Tensor:
        """``2^n |det T|`` -> ``[...]`` (Wang et al. 2022).

        The determinant in closed form up to n = 3 (`diffsmf.linalg.det`; equal to
        LAPACK's LU to rounding): 45x faster than ``torch.linalg.det`` on 110,000 2 x 2
        matrices (0.2 vs 9 ms, one thread), which was most of a compiled HSNSMF ``forward``'s
        time after its loop. Not used inside a filter step.
        """
        return (2.0**self.dim) * linalg.det(self.T).abs()

    def support(self, d: Tensor) -> Tensor:
        """h(d) = d.c + ||T' d||_1; ``d [..., n]`` -> ``[...]``."""
        d = as_vector("d", d, self._c, self.dim)
        return (d * self._c).sum(-1) + (d.unsqueeze(-1) * self.T).sum(-2).abs().sum(-1)

    def interval_hull(self) -> Interval:
        """Box ``c +- sum_j |T_:,j|`` (exact)."""
        from diffsmf.sets.interval import Interval

        r = self.T.abs().sum(-1)
        return Interval._make(self._c - r, self._c + r)  # lower <= upper (NaN propagates)

    def to_interval(self) -> Interval:
        return self.interval_hull()

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """Exact membership: ``eta = T^-1 (x - c)`` by a solve; ``|eta_i| ||T_:,i|| <=
        ||T_:,i|| + atol`` (``atol`` in distance units along each edge) -> bool ``[...]``."""
        x = as_tensor("x", x, like=self._c, min_dim=1)
        if x.shape[-1] != self.dim:
            raise ValueError(f"x: expected [..., {self.dim}], got {tuple(x.shape)}")
        with torch.no_grad():
            r = (x - self._c).detach()
            batch = torch.broadcast_shapes(r.shape[:-1], self.batch_shape)
            T = self.T.detach().expand(*batch, self.dim, self.dim)
            eta = torch.linalg.solve(T, r.expand(*batch, self.dim).unsqueeze(-1)).squeeze(-1)
            cn = T.norm(dim=-2)
            tol = atol + 1e-10 * cn
            return ((eta.abs() - 1) * cn <= tol).all(-1)

    def vertices(self) -> Tensor:
        """All ``2^n`` vertices ``c + T s``, s in {-1, 1}^n -> ``[..., 2^n, n]``."""
        s = torch.tensor(
            list(itertools.product((-1.0, 1.0), repeat=self.dim)),
            dtype=self.dtype,
            device=self.device,
        )
        return self._c.unsqueeze(-2) + linalg.traced_matmul(s, self.T.transpose(-1, -2))

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> Parallelotope | Zonotope:
        """``{A x + b}``: a Parallelotope ``(A c + b, A T)`` for square ``A [..., n, n]``
        (degenerate if A is singular), else a Zonotope."""
        A = as_tensor("A", A, like=self._c, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        if A.shape[-2] != self.dim:
            return self.to_zonotope().linear_map(A, b)
        c = (A @ self._c.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            c = c + as_offset(b, self._c, self.dim)
        return Parallelotope._make(c, A @ self.T)

    def translate(self, b: Tensor) -> Parallelotope:
        """``{x + b}``, ``b [..., n]``."""
        return Parallelotope._make(self._c + as_offset(b, self._c, self.dim), self.T)

    def minkowski_sum(self, other: ConvexSet | Tensor) -> Zonotope:
        """Exact Minkowski sum as a Zonotope (generators ``[T, G_other]``)."""
        return self.to_zonotope().minkowski_sum(other)

    def to_zonotope(self) -> Zonotope:
        """The same set as a Zonotope with generators ``T``."""
        from diffsmf.sets.zonotope import Zonotope

        return Zonotope._make(self._c, self.T)

    def to_parallelotope(self) -> Parallelotope:
        return self

    def to_ellipsoid(self) -> Ellipsoid:
        """Covering ellipsoid ``shape = n T T' (1 + 1e-12) + 1e-10 tr(n T T') / n I``.

        ``||eta||_2^2 <= n`` on the cube, so ``n T T'`` covers P; the added multiple of I
        (Loewner-larger, hence still a cover) keeps the condition number <= ~1e10 so that a
        nearly flat P (e.g. from a rank-deficient zonotope) still gives a usable ellipsoid.
        """
        from diffsmf.sets.ellipsoid import Ellipsoid

        n = self.dim
        Q = n * (self.T @ self.T.transpose(-1, -2)) * (1 + 1e-12)
        Q = (Q + Q.transpose(-1, -2)) / 2
        tr = torch.diagonal(Q, dim1=-2, dim2=-1).sum(-1)
        eye = torch.eye(n, dtype=Q.dtype, device=Q.device)
        return Ellipsoid(self._c, Q + (1e-10 * tr / n).reshape(*tr.shape, 1, 1) * eye)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` points uniform in P -> ``[..., k, n]``."""
        u = self._rand(check_count("k", k), self.dim, generator)
        return self._c.unsqueeze(-2) + (2 * u - 1) @ self.T.transpose(-1, -2)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` random vertices ``c + T s`` -> ``[..., k, n]``."""
        u = self._rand(check_count("k", k), self.dim, generator)
        s = torch.where(u >= 0.5, 1.0, -1.0).to(self.dtype)
        return self._c.unsqueeze(-2) + s @ self.T.transpose(-1, -2)

    def intersect_strip(self, strip: Strip) -> Parallelotope:
        """Outer parallelotope of ``P cap S`` by Wang et al. 2022, eq. 30-41 (Vicino-Zappa 1996 /
        Chisci et al. 1996), batched over the batch dims of P and S.

        The strip ``|a.x - y| <= sigma`` is normalised to ``|p x - c| <= 1``
        (``p = a / sigma``, ``c = y / sigma``; eq. 23-25). Then

        1. eq. 31-36: tighten the strip to the range of ``p x - c`` over P;
        2. eq. 37: tighten P's own n strips ``|eta_i| <= 1`` against the strip;
        3. eq. 38-41: of the n + 1 tightened strips keep the n whose parallelotope has the
           least volume: replacing strip i by the measurement strip scales the volume by
           ``1 / (p_bar t_bar_i)``, so ``i* = argmax_j p_bar t_bar_j`` with
           ``p_bar t_bar_{n+1} = 1`` (keep P_bar).

        Tie rule (eq. 38-39 are often exact ties: a column clipped on one side only by eq. 37
        gives the same ``p_bar t_bar_j`` whatever j, a column clipped on both sides gives 1,
        the value of keeping P_bar; a symmetric P and strip tie by construction). All n + 1
        candidates contain ``P cap S`` (each is cut out by n of the n + 1 tightened strips),
        so any choice is guaranteed. The rule, with ``TIE_RTOL = 1e-12``:

        a. *tied*: the candidates whose volume is within ``TIE_RTOL`` relative of the least,
           ``p_bar t_bar_j (1 + TIE_RTOL) >= max(1, max_i p_bar t_bar_i)`` (keeping P_bar has
           value 1);
        b. among them, the least interval hull within ``TIE_RTOL`` relative, measured as the
           sum of its half-widths each divided by P_bar's (``sum_i hull_i / hull_i(P_bar)``:
           the same choice whatever the units of the states);
        c. then P_bar (no replacement) before a replacement, then the lowest index j.

        So the choice never depends on float rounding of values equal up to a few ulps (the
        same on every platform and under a 1-ulp perturbation of the inputs), and the volume
        is the least to 1e-12 relative. Step b is measured to tighten the filters markedly
        (docs/filters.md, "Tie rule"). Branch-free (masks and ``where``, a loop over the
        static n, no host sync): compile-ready.

        Guarantee fixes (not in the paper): the tightened bounds get an outward margin of
        16 eps relative to the magnitudes involved, and a tightened edge never shrinks below
        1e-12 of its length (no singular T). The index choice is made without gradient.
        An empty intersection (eq. 31-32: ``eps0+ < -1`` or ``eps0- > 1``) returns the input
        unchanged (never NaN); use `intersects_strip` to flag it.
        """

        a, y, sig = strip_fields(strip, self)
        n = self.dim
        batch = strip_batch(self.batch_shape, a, y, sig)
        xc, T0 = _expand(self._c, (*batch, n)), _expand(self.T, (*batch, n, n))
        # the strip's scalars and everything per element below are kept as [..., 1]
        a = _expand(a, (*batch, n))
        y, sig = _expand(y.unsqueeze(-1), (*batch, 1)), _expand(sig.unsqueeze(-1), (*batch, 1))
        tiny = torch.finfo(T0.dtype).tiny
        p, c = _normalised_strip(a, y, sig, xc, T0)  # eq. 24-25
        # direction convention (eq. before 33): p t_i >= 0 (column i negated where p t_i < 0)
        pt = small_sum(p.unsqueeze(-1) * T0, -2)  # [..., n]
        neg = (pt < 0).unsqueeze(-2)
        T, pt = torch.where(neg, -T0, T0), pt.abs()
        mid = small_sum(p * xc, -1, keepdim=True) - c
        spread = small_sum(pt, -1, keepdim=True)
        eps0p, eps0m = mid + spread, mid - spread  # eq. 31-32
        empty = (eps0p < -1) | (eps0m > 1)
        # double-where: an empty element computes with a harmless full-overlap range so that
        # the unused branch gives no inf/NaN in the backward pass (its output is the input)
        eps0p = eps0p.masked_fill(empty, 1.0)  # masked_fill: torch.where with a scalar is 2 calls
        eps0m = eps0m.masked_fill(empty, -1.0)
        marg = 16 * _EPS * (1 + mid.abs() + spread)  # outward rounding margin
        # step 1, eq. 33-36: tightened strip |p_bar x - c_bar| <= 1
        rp = eps0p.clamp(max=1.0) + marg
        rm = (-eps0m).clamp(max=1.0) + marg
        g = 2 / (rp + rm).clamp_min(tiny)
        p_bar = g * p
        c_bar = g * (c + (rp - rm) / 2)
        # step 2, eq. 37: tighten eta_i in [-r_i-, r_i+]; no tightening where p t_i = 0
        z = ~(pt > 0)  # NaN counts as 0
        ptd = pt.masked_fill(z, 1.0)
        mi = (marg / ptd).unsqueeze(-2)
        num = torch.stack([1 - eps0m, 1 + eps0p], -2)  # [..., 2, 1]
        r2 = (num / ptd.unsqueeze(-2) - 1 + mi).clamp(max=1.0)
        rip, rim = r2.masked_fill(z.unsqueeze(-2), 1.0).unbind(-2)
        half = ((rip + rim) / 2).clamp_min(1e-12)
        T_bar = T * half.unsqueeze(-2)
        xc_bar = xc + small_sum(T * ((rip - rim) / 2).unsqueeze(-2), -1)
        # step 3, eq. 38-39: i* = argmax_j p_bar t_bar_j over j = 1..n+1 (p_bar t_bar_{n+1} = 1)
        pbt = small_sum(p_bar.unsqueeze(-1) * T_bar, -2)  # [..., n]
        istar, replace = _tie_rule(T_bar, pbt, ~empty)  # [..., 1]
        # eq. 41: replace strip i* by the measurement strip; where P_bar is kept (eq. 40),
        # d = 1 and the other columns' factors are 0, so that T_new is T_bar exactly
        col = istar.unsqueeze(-1).expand(*batch, n, 1)
        t_star = torch.gather(T_bar, -1, col)
        d = torch.where(replace, torch.gather(pbt, -1, istar), 1.0)  # p_bar t_bar_i*  [..., 1]
        T_new = T_bar - t_star * ((pbt / d) * replace).unsqueeze(-2)
        T_new = T_new.scatter(-1, col, t_star / d.unsqueeze(-1))  # column i*: t_i* / d
        q = (c_bar - small_sum(p_bar * xc_bar, -1, keepdim=True)) / d
        xc_new = xc_bar + t_star.squeeze(-1) * q
        # empty -> the input unchanged
        T_out = torch.where(empty.unsqueeze(-1), T0, torch.where(neg, -T_new, T_new))
        x_out = torch.where(replace, xc_new, xc_bar)
        x_out = torch.where(empty, xc, x_out)
        return Parallelotope._make(x_out, T_out)

    def intersects_strip(self, strip: Any, atol: float = 0.0) -> Tensor:
        """Exact test that P meets ``strip``: bool ``[...]`` (`ConvexSet.intersects_strip`:
        ``|normal.c - offset| <= ||T' normal||_1 + halfwidth + atol``, the same values)."""
        a = strip.normal
        mid = small_sum(a * self._c, -1)
        rad = (mid + small_sum(small_sum(a.unsqueeze(-1) * self.T, -2).abs(), -1)) - mid
        return (mid - strip.offset).abs() <= rad + strip.halfwidth + atol


def _expand(t: Tensor, shape: tuple[int, ...]) -> Tensor:
    """``t`` expanded to ``shape`` (itself, no call, when it has that shape already)."""
    return t if t.shape == shape else t.expand(shape)


def _normalised_strip(a: Tensor, y: Tensor, sig: Tensor, xc: Tensor, T: Tensor
                      ) -> tuple[Tensor, Tensor]:
    """Wang et al. 2022, eq. 24-25: the strip ``|a.x - y| <= sig`` as ``|p x - c| <= 1``
    (``a [..., n]``, ``y``, ``sig [..., 1]``) -> ``(p [..., n], c [..., 1])``. A zero
    half-width is widened by 1e-15 of the strip's scale over the parallelotope ``(xc, T)``
    (outward, keeps ``p`` finite; no gradient through the widening)."""
    with torch.no_grad():
        scale = small_sum(a.abs() * (xc.abs() + small_sum(T.abs(), -1)), -1, keepdim=True)
        floor = 1e-15 * scale + torch.finfo(T.dtype).tiny
    sig = torch.maximum(sig, floor)
    return a / sig, y / sig


def _tie_rule(T_bar: Tensor, pbt: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
    """Wang et al. 2022, eq. 38-39 with the tie rule of `Parallelotope.intersect_strip`:
    ``(i* [..., 1], replace [..., 1])``, the column ``i*`` whose replacement by the
    measurement strip gives the least volume and whether to replace it at all (False: keep
    P_bar; always False where ``keep [..., 1]`` is False).

    ``T_bar [..., n, n]`` the tightened edges, ``pbt [..., n]`` their ``p_bar t_bar_j``.
    Without gradient (a discrete choice); all candidates at once: candidate i has column i
    ``t_i / pbt_i`` and column j ``t_j - t_i pbt_j / pbt_i``. Where no candidate is tied,
    ``replace`` is False and ``i*`` any index.
    """
    with torch.no_grad():
        # (NaN values, only from a NaN set whose output is NaN anyway, are not special-cased)
        top = pbt.amax(-1, keepdim=True)
        untied = pbt * (1 + TIE_RTOL) < top.clamp_min(1)  # not within TIE_RTOL of the least
        # rows weighted by 1 / (P_bar's hull half-width): the widths relative to P_bar's,
        # so that the choice does not depend on the units of the states
        Ta = T_bar.abs()
        rw = small_sum(Ta, -1, keepdim=True)
        rw = rw.reciprocal().masked_fill(rw == 0, 1.0)  # [..., n, 1]
        colA = small_sum(Ta * rw, -2)  # [..., n]
        # summed hull half-widths of each candidate i (eq. 41), [..., i, row, column j]; a
        # candidate with pbt_i = 0 (inf / NaN here) is untied, its hull replaced by inf
        ratio = pbt.reshape(*pbt.shape[:-1], 1, 1, -1) / pbt.reshape(*pbt.shape, 1, 1)
        U = T_bar.unsqueeze(-3)  # [..., 1, row, column]; its transpose(-1, -3): T_bar[row, i]
        D = U - U.transpose(-1, -3) * ratio  # ratio [..., i, 1, j]: pbt_j / pbt_i
        hull = (D.abs() * rw.unsqueeze(-3)).sum((-1, -2)) + colA / pbt  # [..., n]
        hull = hull.masked_fill(untied, torch.inf)
        hm = hull.amin(-1, keepdim=True) * (1 + TIE_RTOL)
        # the lowest index within TIE_RTOL of the least hull; where none is tied, replace is
        # False and i* is unused
        istar = (hull <= hm).to(torch.uint8).argmax(-1, keepdim=True)
        keep_hull = colA.sum(-1, keepdim=True)
        # keeping P_bar (value 1) is not among the least volumes, or is but has a larger hull
        replace = ((top > 1 + TIE_RTOL) | (hm < keep_hull)) & keep
    return istar, replace
