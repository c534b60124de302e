"""Ellipsoids ``{x : (x - c)' S^-1 (x - c) <= 1}`` (Song et al. 2017, eq. 10-17, Jiang et al. 2016,
eq. 34-36).

Outer bounds (Minkowski sum, intersections, covers) are inflated by the relative factor
``1 + INFLATE`` (``INFLATE = 1e-10``) so that boundary points stay inside despite rounding.
Every weight (Minkowski ``p``, intersection ``rho``) is found batched without gradient and then
made differentiable by one Newton step on the optimality condition evaluated with autograd
(implicit-function theorem), so gradients of the outputs are exact at the optimum.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet, as_tensor, as_vector, check_count, check_finite, where
from diffsmf.sets.ellipsoid_update import _MeasFamily, _minimize_rho
from diffsmf.utils import checking, tracing

__all__ = ["Ellipsoid", "minkowski_weight", "outer_sum_shape"]

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.interval import Interval


INFLATE = 1e-10


def _chol(name: str, S: Tensor) -> Tensor:
    """Cholesky factor; ``ValueError`` naming ``name`` if not positive definite."""
    L, info = torch.linalg.cholesky_ex(S)
    if checking() and bool((info != 0).any()):
        raise ValueError(f"{name}: not symmetric positive definite")
    return L


def unit_ball_volume(n: int) -> float:
    """Volume of the unit n-ball ``pi^(n/2) / Gamma(n/2 + 1)``."""
    return math.exp(0.5 * n * math.log(math.pi) - math.lgamma(0.5 * n + 1.0))


class Ellipsoid(ConvexSet):
    """Batched ellipsoid ``{x : (x - c)' shape^-1 (x - c) <= 1}``.

    Args:
        center: ``[..., n]``.
        shape: ``[..., n, n]`` symmetric positive definite (checked by Cholesky; symmetrised).
    Batch dims broadcast.
    """

    _fields: ClassVar[tuple[str, ...]] = ("center_", "shape")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2)
    center_: Tensor
    shape: Tensor

    def __init__(self, center: Any, shape: Any) -> None:
        c = as_tensor("center", center, min_dim=1, field=True)
        S = as_tensor("shape", shape, like=c, min_dim=2, field=True)
        check_finite("center", c)
        check_finite("shape", S)
        n = c.shape[-1]
        if S.shape[-2:] != (n, n):
            raise ValueError(f"shape: expected [..., {n}, {n}], got {tuple(S.shape)}")
        Sd = S.detach()
        scale = Sd.abs().amax(dim=(-2, -1)).clamp(min=1e-300)
        if checking() and ((Sd - Sd.mT).abs().amax(dim=(-2, -1)) > 1e-8 * scale).any():
            raise ValueError("shape: not symmetric")
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], S.shape[:-2])
        except RuntimeError as exc:
            raise ValueError(
                f"shape: batch shape {tuple(S.shape[:-2])} does not broadcast with center "
                f"{tuple(c.shape[:-1])}"
            ) from exc
        S = linalg.sym(S)
        _chol("shape", S.detach())
        self._set(center_=c.expand(*batch, n), shape=S.expand(*batch, n, n))

    @classmethod
    def _make(cls, center: Tensor, shape: Tensor) -> Ellipsoid:
        """Construct without validation (internal; inputs known valid)."""
        obj = object.__new__(cls)
        batch = torch.broadcast_shapes(center.shape[:-1], shape.shape[:-2])
        n = center.shape[-1]
        object.__setattr__(obj, "center_", center.expand(*batch, n))
        object.__setattr__(obj, "shape", shape.expand(*batch, n, n))
        return obj

    @property
    def center(self) -> Tensor:
        return self.center_

    def cholesky(self) -> Tensor:
        """Lower Cholesky factor ``L`` of the shape, ``[..., n, n]``."""
        return torch.linalg.cholesky(self.shape)

    # ------------------------------------------------------------------ exact quantities
    def volume(self) -> Tensor:
        """``V_n sqrt(det S)`` with ``V_n`` the unit-ball volume -> ``batch_shape``.

        Up to n = 2 from the closed-form determinant (`diffsmf.linalg.det`; 0.4 ms
        instead of 12 ms for the Cholesky factors of 110,000 2 x 2 shapes, one thread: most of
        an ellipsoidal filter's compiled ``forward`` after its loop), equal to the
        Cholesky form to rounding, when every shape is positive definite (``S_11 > 0`` and
        ``det S > 0``); otherwise the Cholesky form, which raises for a shape that is not.
        While traced for ``torch.compile`` (no host check) such elements give NaN.
        """
        if self.dim <= 2:
            S = self.shape
            d = linalg.det(S)
            pd = (S[..., 0, 0] > 0) & (d > 0)
            if tracing():
                vol = torch.sqrt(torch.where(pd, d, torch.full_like(d, torch.nan)))
                return unit_ball_volume(self.dim) * vol
            if bool(pd.all()):
                return unit_ball_volume(self.dim) * torch.sqrt(d)
        return unit_ball_volume(self.dim) * torch.exp(self.log_det_half())

    def log_det_half(self) -> Tensor:
        """``0.5 log det S`` (via Cholesky)."""
        L = self.cholesky()
        return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)

    def log_volume(self) -> Tensor:
        return math.log(unit_ball_volume(self.dim)) + self.log_det_half()

    def mahalanobis2(self, x: Tensor) -> Tensor:
        """``(x - c)' S^-1 (x - c)`` via a triangular solve -> ``[...]`` (x broadcasts).

        A degenerate shape (positive semidefinite, singular: a collapsed direction, as in the
        combined filter's mean set without noise) uses ``S + delta I`` with ``delta = n eps
        (1 + max diag S)``, just above the rounding noise of a singular matrix's zero
        eigenvalues: a point off the ellipsoid's plane by ``t`` gets about ``t^2 / delta``, so
        points within about ``sqrt(delta)`` (1.5e-7 for n = 2, max diag S = 1) of it are
        accepted. A non-degenerate shape is unaffected. A shape that is not even positive
        semidefinite to that tolerance raises.
        """
        x = as_vector("x", x, self.center_, self.dim)
        d = (x - self.center_).unsqueeze(-1)
        L, info = torch.linalg.cholesky_ex(self.shape)
        if not tracing() and bool((info != 0).any()):
            S = self.shape
            eps = torch.finfo(S.dtype).eps
            delta = self.dim * eps * (1.0 + torch.diagonal(S, dim1=-2, dim2=-1).amax(-1))
            eye = torch.eye(self.dim, dtype=S.dtype, device=S.device)
            L_reg, info_reg = torch.linalg.cholesky_ex(S + delta[..., None, None] * eye)
            if bool((info_reg != 0).any()):
                raise ValueError("shape: not positive semidefinite (Cholesky failed)")
            L = torch.where((info != 0)[..., None, None], L_reg, L)
        batch = torch.broadcast_shapes(d.shape[:-2], L.shape[:-2])
        n = self.dim
        z = torch.linalg.solve_triangular(
            L.expand(*batch, n, n), d.expand(*batch, n, 1), upper=False
        )
        return (z * z).sum((-2, -1))

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """``(x - c)' S^-1 (x - c) <= 1 + atol`` -> bool ``[...]``."""
        return self.mahalanobis2(x) <= 1.0 + atol

    def support(self, d: Tensor) -> Tensor:
        """``h(d) = d.c + sqrt(d' S d)`` -> ``[...]``."""
        d = as_vector("d", d, self.center_, self.dim)
        q = (d.unsqueeze(-2) @ self.shape @ d.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        return (d * self.center_).sum(-1) + torch.sqrt(q.clamp(min=0.0))

    def interval_hull(self) -> Interval:
        """``c +- sqrt(diag S)`` (rounded outward)."""
        from diffsmf.sets.interval import Interval

        r = torch.sqrt(torch.diagonal(self.shape, dim1=-2, dim2=-1).clamp(min=0.0))
        return Interval.from_center_radius(self.center_, r)

    # ------------------------------------------------------------------ maps
    def linear_map(self, A: Tensor, b: Tensor | None = None, reg: float = 1e-12) -> Ellipsoid:
        """Image ``{A x + b}`` = Ellipsoid(A c + b, A S A'); ``A [..., k, n]`` any k.

        The image is exact when ``A S A'`` is positive definite (square invertible A, or k <= n
        with full row rank). Otherwise (k > n or rank-deficient A) the image is a degenerate
        ellipsoid; it is replaced by the outer bound ``A S A' + reg * (tr(A S A')/k + 1e-300) I``
        so that the shape stays positive definite (documented deviation).
        """
        A = as_tensor("A", A, like=self.center_, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        c = (A @ self.center_.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            c = c + as_tensor("b", b, like=self.center_)
        S = linalg.sym(A @ self.shape @ A.mT)
        k = A.shape[-2]
        _, info = torch.linalg.cholesky_ex(S.detach())
        if tracing() or bool((info != 0).any()) or k > self.dim:
            eye = torch.eye(k, dtype=S.dtype, device=S.device)
            tr = torch.diagonal(S, dim1=-2, dim2=-1).sum(-1) / k
            jitter = (reg * (tr + 1e-300)).unsqueeze(-1).unsqueeze(-1) * eye
            bad = (info != 0).reshape(info.shape + (1, 1)) | (k > self.dim)
            S = torch.where(bad, S + jitter, S)
        return Ellipsoid._make(c, S)

    def translate(self, b: Tensor) -> Ellipsoid:
        b = as_tensor("b", b, like=self.center_)
        return Ellipsoid._make(self.center_ + b, self.shape)

    # ------------------------------------------------------------------ sampling
    def _unit_ball(self, k: int, generator: torch.Generator | None, boundary: bool) -> Tensor:
        n = self.dim
        shape = (*self.batch_shape, k, n)
        g = torch.randn(shape, generator=generator, dtype=self.dtype, device=self.device)
        u = g / g.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        if boundary:
            return u
        r = torch.rand(shape[:-1], generator=generator, dtype=self.dtype, device=self.device)
        return u * r.pow(1.0 / n).unsqueeze(-1)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` uniform points inside -> ``[*batch_shape, k, n]``."""
        k = check_count("k", k)
        u = self._unit_ball(k, generator, boundary=False)
        L = self.cholesky().unsqueeze(-3)
        return self.center_.unsqueeze(-2) + (L @ u.unsqueeze(-1)).squeeze(-1)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` random boundary points -> ``[*batch_shape, k, n]``.

        Pulled inside by the relative factor ``1 - 1e-13`` so that rounding never puts them
        outside the ellipsoid itself."""
        k = check_count("k", k)
        u = self._unit_ball(k, generator, boundary=True) * (1.0 - 1e-13)
        L = self.cholesky().unsqueeze(-3)
        return self.center_.unsqueeze(-2) + (L @ u.unsqueeze(-1)).squeeze(-1)

    # ------------------------------------------------------------------ covers
    @classmethod
    def from_box(cls, box: Interval, min_radius: float = 1e-12) -> Ellipsoid:
        """Covering ellipsoid ``diag(n r_i^2)`` of a box (Song et al. 2017, eq. 23/29, n-D
        erratum)."""
        return box.to_ellipsoid(min_radius=min_radius)

    @classmethod
    def from_zonotope(cls, Z: Any, method: str = "auto", min_radius: float = 1e-12) -> Ellipsoid:
        """Guaranteed covering ellipsoid of a Zonotope ``c + G [-1, 1]^m`` (or Parallelotope).

        ``method``:
          * ``"generators"``: box cover in generator coordinates, shape ``m G G'``
            (``|xi|_2^2 <= m`` on the cube); needs ``G`` of full row rank.
          * ``"hull"``: ``from_box(Z.interval_hull())`` = ``diag(n r_i^2)``.
          * ``"auto"`` (default): the smaller-volume of the two per batch element
            (``"hull"`` where ``G G'`` is singular).
        """
        from diffsmf.sets.interval import Interval

        if isinstance(Z, Interval):
            return cls.from_box(Z, min_radius)
        if method not in ("auto", "generators", "hull"):
            raise ValueError(f"method: expected 'auto', 'generators' or 'hull', got {method!r}")
        hull = cls.from_box(Z.interval_hull(), min_radius)
        if method == "hull":
            return hull
        G = Z.generators
        m = G.shape[-1]
        Sg = linalg.sym(m * (G @ G.mT)) * (1.0 + INFLATE)
        _, info = torch.linalg.cholesky_ex(Sg.detach())
        ok = info == 0
        if method == "generators":
            if checking() and not bool(ok.all()):
                raise ValueError("Z: generators are not of full row rank; use method='hull'")
            return Ellipsoid._make(Z.center, Sg)
        eye = torch.eye(Z.dim, dtype=Sg.dtype, device=Sg.device)
        Sg_safe = torch.where(ok[..., None, None], Sg, hull.shape.detach() + eye)
        ld_g = torch.linalg.cholesky(Sg_safe.detach()).diagonal(dim1=-2, dim2=-1).log().sum(-1)
        use_g = ok & (ld_g < hull.log_det_half().detach())
        S = torch.where(use_g[..., None, None], Sg_safe, hull.shape)
        return Ellipsoid._make(Z.center, S)

    def to_ellipsoid(self) -> Ellipsoid:
        return self

    # ------------------------------------------------------------------ Minkowski sum
    def minkowski_sum(self, other: Any, method: str = "trace", p: Any = None) -> Ellipsoid:
        """Outer ellipsoid of ``self (+) other``: ``S(p) = (1 + 1/p) S1 + (1 + p) S2``.

        (Song et al. 2017, eq. 14-17 with ``alpha = 1/(1+p)``; Jiang et al. 2016, eq. 34-36 with the
        erratum.) ``method="trace"``: ``p = sqrt(tr S1 / tr S2)``; ``"volume"``: the root of
        ``sum_i 1/(lambda_i + 1/p) = n p^2 / (p + 1)`` (``lambda`` eigenvalues of
        ``S1^-1 S2``); or an explicit ``p > 0`` ``[...]``. An Interval / Zonotope /
        Parallelotope operand is first covered by an ellipsoid (`from_zonotope`); a
        tensor is a translation.
        """
        if isinstance(other, Tensor):
            return self.translate(other)
        E2 = other if isinstance(other, Ellipsoid) else Ellipsoid.from_zonotope(other)
        if E2.dim != self.dim:
            raise ValueError(f"other: dimension {E2.dim} != {self.dim}")
        S1, S2 = self.shape, E2.shape
        if p is None:
            p = minkowski_weight(S1, S2, method)
        else:
            p = as_tensor("p", p, like=S1)
            if checking() and (p.detach() <= 0).any():
                raise ValueError("p: must be > 0")
        pp = p[..., None, None]
        S = linalg.sym((1.0 + 1.0 / pp) * S1 + (1.0 + pp) * S2) * (1.0 + INFLATE)
        return Ellipsoid._make(self.center_ + E2.center_, S)

    # ------------------------------------------------------------------ intersections
    def intersect_measurement(
        self,
        H: Tensor,
        y: Tensor,
        R: Tensor,
        method: str = "volume",
        rho: Any = None,
    ) -> Ellipsoid:
        """Outer ellipsoid of ``E ∩ {x : (y - H x)' R^-1 (y - H x) <= 1}`` (Song et al. 2017, eq.
        36-39).

        ``H [..., m, n]``, ``y [..., m]``, ``R [..., m, m]`` SPD. The family (eq. 10-11 written
        for a degenerate second ellipsoid) is, for ``rho in [0, 1)``,
        ``D = rho H P H' + (1 - rho) R``, ``K = rho P H' D^-1``, ``c+ = c + K e``,
        ``xi = 1 - rho (1 - rho) e' D^-1 e``, ``P+ = xi / (1 - rho) (P - K H P)``
        (``rho = 0`` returns the input). ``method``: ``"volume"`` / ``"trace"`` (1-D search
        over rho), ``"fixed"`` (eq. 13 with ``P_2,max = sigma_max(R)/sigma_min(H H')``), or an
        explicit ``rho``. An empty intersection (max over rho of
        ``rho (1 - rho) e' D^-1 e`` > 1, a concave function) returns the input unchanged.

        One output (``m = 1``, ``n > 1``) with ``method="volume"``: the family's
        minimal-volume member in closed form (Fogel-Huang, `_one_output_update`) instead
        of about 150 evaluations of the bracketing search (two thirds of a compiled
        ESMF step), and emptiness decided exactly.
        """
        H = as_tensor("H", H, like=self.center_, min_dim=2)
        y = as_tensor("y", y, like=self.center_, min_dim=1)
        R = as_tensor("R", R, like=self.center_, min_dim=2)
        if H.shape[-1] != self.dim or R.shape[-1] != H.shape[-2] or y.shape[-1] != H.shape[-2]:
            raise ValueError("H: shapes of H [..., m, n], y [..., m], R [..., m, m] mismatch")
        _chol("R", linalg.sym(R).detach())
        P, c = self.shape, self.center_
        e = y - (H @ c.unsqueeze(-1)).squeeze(-1)
        G = linalg.sym(H @ P @ H.mT)
        if H.shape[-2] == 1 and self.dim > 1 and rho is None and method == "volume":
            return self._one_output_update(_MeasFamily(P, H, G, linalg.sym(R), e))
        square = None
        if H.shape[-2] == self.dim and rho is None:
            # square H: the two-sided update with the measurement ellipsoid (tighter: no
            # cancellation as rho -> 1) wherever H is invertible, else the one-sided family
            square = self._square_measurement(H, y, R)
            two = self.intersect_ellipsoid(square[0], method=method)
            if not tracing() and bool(square[1].all()):
                return two
        fam = _MeasFamily(P, H, G, linalg.sym(R), e)
        empty = fam.empty()
        rho_t = self._pick_rho(fam, method, rho, H, R)
        rho_t = torch.where(empty, torch.zeros_like(rho_t), rho_t)
        c2, P2 = fam.evaluate(rho_t, c)
        out = self._finish(c2, P2, rho_t, empty)
        if square is None:
            return out
        # element by element, branch-free (the same in eager and traced code)
        return where(square[1], two, out)

    def _one_output_update(self, fam: _MeasFamily) -> Ellipsoid:
        """The minimal-volume member of the eq. 36-39 family for one output (``m = 1``): the
        Fogel-Huang closed-form rho (`_fogel_huang_rho`; the family's log-volume is the
        strip's) capped at ``1 - 1e-6`` as the search is for ``m < n``, and the exact emptiness
        test ``|e| > sqrt(H P H') + sqrt(R)`` (the maximum over rho of
        ``rho (1 - rho) e^2 / D(rho)`` is ``e^2 / (sqrt(G) + sqrt(R))^2``)."""
        g, r, e = fam.G[..., 0, 0], fam.R[..., 0, 0], fam.e[..., 0]
        g, r, e = (t.expand(fam.batch) for t in (g, r, e))
        empty = e.detach().abs() > torch.sqrt(g.detach()) + torch.sqrt(r.detach())
        top = 1.0 - max(1e-6, 1e4 * torch.finfo(self.dtype).eps)
        rho_t = _fogel_huang_rho(g, r, e, self.dim).clamp(max=top)
        rho_t = torch.where(empty, torch.zeros_like(rho_t), rho_t)
        c2, P2 = fam.evaluate(rho_t, self.center_)
        return self._finish(c2, P2, rho_t, empty)

    def _square_measurement(
        self, H: Tensor, y: Tensor, R: Tensor
    ) -> tuple[Ellipsoid, Tensor]:
        """For square ``H``: the measurement set as the ellipsoid ``E(H^-1 y, H^-1 R H^-T)``
        and ``ok [...]`` where ``H`` is invertible and that shape positive definite (elsewhere
        the ellipsoid is a placeholder, the unit ball at 0, to be discarded). The two-sided
        update with it has no cancellation as rho -> 1. A singular ``H`` is replaced by the
        identity before solving, so no inf or NaN arises, in the values or in the gradients of
        the discarded branch."""
        eye = torch.eye(self.dim, dtype=H.dtype, device=H.device)
        info = torch.linalg.lu_factor_ex(H.detach()).info
        ok = info == 0
        Hs = torch.where(ok[..., None, None], H, eye)
        Hi_y = torch.linalg.solve_ex(Hs, y.unsqueeze(-1))[0].squeeze(-1)
        X = torch.linalg.solve_ex(Hs, R)[0]
        S2 = linalg.sym(torch.linalg.solve_ex(Hs, X.mT)[0])
        _, info2 = torch.linalg.cholesky_ex(S2.detach())
        ok = ok & (info2 == 0) & torch.isfinite(S2.detach()).all(-1).all(-1)
        ok = ok & torch.isfinite(Hi_y.detach()).all(-1)
        c2 = torch.where(ok[..., None], Hi_y, torch.zeros_like(Hi_y))
        return Ellipsoid._make(c2, torch.where(ok[..., None, None], S2, eye)), ok

    def _finish(self, c2: Tensor, P2: Tensor, rho: Tensor, keep: Tensor) -> Ellipsoid:
        """Inflate for rounding (``INFLATE + 64 n eps / (1 - rho)``: the update cancels as
        rho -> 1) and never return something larger than ``self`` (both are outer bounds)."""
        eps = torch.finfo(P2.dtype).eps
        infl = INFLATE + 64 * self.dim * eps / (1.0 - rho.detach())
        P2 = P2 * (1.0 + infl)[..., None, None]
        keep = keep | (_logdet(P2) >= _logdet(self.shape))
        c2 = torch.where(keep[..., None], self.center_, c2)
        return Ellipsoid._make(c2, torch.where(keep[..., None, None], self.shape, P2))

    def _pick_rho(self, fam: _MeasFamily, method: str, rho: Any, H: Tensor, R: Tensor) -> Tensor:
        if rho is not None:
            r = as_tensor("rho", rho, like=self.center_)
            if checking() and ((r.detach() < 0) | (r.detach() >= 1)).any():
                raise ValueError("rho: must be in [0, 1)")
            return r.expand(fam.batch)
        if method == "fixed":
            # Song et al. 2017, eq. 13: rho = sqrt(s1) / (sqrt(s1) + sqrt(s2)), s = largest singular
            # value
            s1 = torch.linalg.eigvalsh(self.shape)[..., -1]
            HH = torch.linalg.eigvalsh(linalg.sym(H @ H.mT))[..., 0].clamp(min=1e-300)
            s2 = torch.linalg.eigvalsh(linalg.sym(R))[..., -1] / HH
            r = s1.sqrt() / (s1.sqrt() + s2.sqrt())
            top = 1.0 - max(1e-6, 1e4 * torch.finfo(self.dtype).eps)
            return r.clamp(max=top).expand(fam.batch)
        if method not in ("volume", "trace"):
            raise ValueError(f"method: expected 'volume', 'trace' or 'fixed', got {method!r}")
        if method == "volume":
            red, full = fam.red_log_volume, fam.log_volume
        else:
            red, full = fam.red_trace, fam.trace
        eps = torch.finfo(self.dtype).eps
        top = 1.0 - max(1e-9, 100 * eps) if fam.m == self.dim else 1.0 - max(1e-6, 1e4 * eps)
        return _minimize_rho(red, full, fam.batch, self.center_, fam.requires_grad, top)

    def intersect_strip(self, strip: Any, method: str = "volume", rho: Any = None) -> Ellipsoid:
        """Outer ellipsoid of ``E ∩ {x : |a.x - o| <= h}`` (Song et al. 2017, eq. 10-13 / 36-39, m =
        1).

        The strip is first tightened to E's extent along ``a`` (same intersection). Emptiness
        is decided exactly with `intersects_strip`; an empty intersection returns the
        input unchanged (never NaN). ``method="volume"`` uses the Fogel-Huang closed form (root
        of a quadratic in rho, differentiable); ``"trace"`` a 1-D search; ``"fixed"`` eq. 13.
        A strip containing E returns E (rho = 0).
        """
        a, o, h = strip.normal, strip.offset, strip.halfwidth
        if a.shape[-1] != self.dim:
            raise ValueError(f"strip: normal has dim {a.shape[-1]}, set has {self.dim}")
        empty = ~self.intersects_strip(strip)
        P, c = self.shape, self.center_
        Pa = (P @ a.unsqueeze(-1)).squeeze(-1)
        g = (a * Pa).sum(-1)  # a' P a
        mid = (a * c).sum(-1)
        sg = torch.sqrt(g)
        # tightened strip (same intersection), widened by a rounding margin so that no point
        # of the true intersection is cut off
        tol = 8 * torch.finfo(g.dtype).eps * (mid.abs() + sg + o.abs() + h)
        lo = torch.maximum(o - h, mid - sg) - tol
        hi = torch.minimum(o + h, mid + sg) + tol
        hi = torch.maximum(hi, lo)  # empty case: harmless degenerate strip
        o2, h2 = 0.5 * (lo + hi), 0.5 * (hi - lo)
        r = (h2 * h2).clamp(min=1e-24 * g)
        e = o2 - mid
        fam = _MeasFamily(
            P, a.unsqueeze(-2), g[..., None, None], r[..., None, None], e.unsqueeze(-1)
        )
        if rho is not None or method != "volume":
            rho_t = self._pick_rho(fam, method, rho, a.unsqueeze(-2), r[..., None, None])
        else:
            rho_t = _fogel_huang_rho(g, r, e, self.dim)
        full = h2 >= sg * (1.0 - 1e-12)  # strip contains E: no update
        rho_t = torch.where(empty | full, torch.zeros_like(rho_t), rho_t)
        c2, P2 = fam.evaluate(rho_t, c)
        return self._finish(c2, P2, rho_t, empty | full)

    def intersect_ellipsoid(
        self, other: Ellipsoid, method: str = "volume", rho: Any = None
    ) -> Ellipsoid:
        """Outer ellipsoid of ``E1 ∩ E2`` (Song et al. 2017, eq. 10-13; ``H = I``, ``y = c2``, ``R =
        P2``).

        ``rho`` weights E2 (``rho = 0`` gives E1, ``rho -> 1`` gives E2). Erratum: eq. 11's
        ``Psi`` must read ``1 - d' (P1/(1 - rho) + P2/rho)^-1 d`` (consistent with eq. 36), the
        printed ``P1/rho + P2/(1 - rho)`` is not an outer bound. Methods as in
        `intersect_measurement`; an empty intersection returns ``self`` unchanged.
        """
        if not isinstance(other, Ellipsoid):
            raise ValueError("other: expected an Ellipsoid")
        if other.dim != self.dim:
            raise ValueError(f"other: dimension {other.dim} != {self.dim}")
        n = self.dim
        eye = torch.eye(n, dtype=self.dtype, device=self.device)
        P1, P2, c1, c2 = self.shape, other.shape, self.center_, other.center_
        fam = _MeasFamily(P1, eye, P1, P2, c2 - c1)
        empty = fam.empty()
        rho_t = self._pick_rho(fam, method, rho, eye, P2)
        rho_t = torch.where(empty, torch.zeros_like(rho_t), rho_t)
        # same set written from E2's side (rho' = 1 - rho): no cancellation for rho > 1/2
        fam_b = _MeasFamily(P2, eye, P2, P1, c1 - c2)
        ca, Pa = fam.evaluate(torch.clamp(rho_t, max=0.5), c1)
        cb, Pb = fam_b.evaluate(torch.clamp(1.0 - rho_t, max=0.5), c2)
        swap = rho_t > 0.5
        c = torch.where(swap[..., None], cb, ca)
        P = torch.where(swap[..., None, None], Pb, Pa)
        out = self._finish(c, P, torch.minimum(rho_t, 1.0 - rho_t), empty)
        # rho -> 1 limit is E2 itself: keep the smaller of {result, E2} (both outer bounds)
        better = (~empty) & (other.log_det_half() < out.log_det_half())
        return Ellipsoid._make(
            torch.where(better[..., None], other.center_, out.center_),
            torch.where(better[..., None, None], other.shape, out.shape),
        )


# ---------------------------------------------------------------------------- helpers
def _logdet(S: Tensor) -> Tensor:
    """``log det`` of SPD matrices (detached; used for discrete choices only)."""
    L = linalg.cholesky(S.detach()) if S.shape[-1] <= 2 else torch.linalg.cholesky_ex(S.detach())[0]
    return 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)


def _lambdas(S1: Tensor, S2: Tensor) -> Tensor:
    """Eigenvalues of ``S1^-1 S2`` (generalised symmetric problem via Cholesky)."""
    L = linalg.lapack_cholesky(S1)  # NaN where S1 is not PD (no exception for the batch)
    X = torch.linalg.solve_triangular(L, S2, upper=False)
    M = torch.linalg.solve_triangular(L, X.mT, upper=False)
    bad, M = linalg.finite_or_eye(linalg.sym(M))
    lam = torch.linalg.eigvalsh(M).clamp(min=0.0)
    return torch.where(bad.unsqueeze(-1), torch.nan, lam)


def _vol_condition(p: Tensor, lam: Tensor) -> Tensor:
    """``F(p) = sum_i (lambda_i - 1/p^2) / (lambda_i + 1/p)``; increasing, root = min volume."""
    q = (1.0 / p).unsqueeze(-1)
    return ((lam - q * q) / (lam + q)).sum(-1)


def minkowski_weight(S1: Tensor, S2: Tensor, method: str = "trace") -> Tensor:
    """Weight ``p`` of ``S(p) = (1 + 1/p) S1 + (1 + p) S2`` (Jiang et al. 2016, eq. 34-36, erratum).

    ``"trace"``: ``p = sqrt(tr S1 / tr S2)``. ``"scaled-trace"``: the trace rule in the
    coordinates normalised by ``N = diag(S1 + S2)^-1/2``, ``p = sqrt(tr(N S1 N) / tr(N S2 N))``
    (the sum of squared semi-axes relative to the operands' widths, instead of in the states'
    units: invariant under a diagonal change of units, the default of the filters' state-space
    sums). ``"volume"``: unique positive root of
    ``sum_i 1/(lambda_i + 1/p) = n p^2/(p + 1)`` (equivalently ``F(p) = 0`` with ``F``
    increasing), bracketed in ``[1/sqrt(lambda_max), 1/sqrt(lambda_min)]`` and solved by
    bisection in log p, then one differentiable Newton step (implicit function theorem).
    """
    if method == "trace":
        t1 = torch.diagonal(S1, dim1=-2, dim2=-1).sum(-1)
        t2 = torch.diagonal(S2, dim1=-2, dim2=-1).sum(-1)
        return torch.sqrt(t1 / t2)
    if method == "scaled-trace":
        d1 = torch.diagonal(S1, dim1=-2, dim2=-1)
        d2 = torch.diagonal(S2, dim1=-2, dim2=-1)
        tot = d1 + d2
        ok = (tot > 0) & torch.isfinite(tot)
        inv = 1.0 / torch.where(ok, tot, torch.ones_like(tot))
        return torch.sqrt((d1 * inv).sum(-1) / (d2 * inv).sum(-1))
    if method != "volume":
        raise ValueError(f"method: expected 'trace', 'scaled-trace' or 'volume', got {method!r}")
    lam = _lambdas(S1, S2)
    ld = lam.detach().clamp(min=1e-300)
    lo = torch.log(1.0 / ld[..., -1].sqrt())
    hi = torch.log(1.0 / ld[..., 0].sqrt())
    for _ in range(32):  # bisection on the increasing function F(exp(t))
        mid = 0.5 * (lo + hi)
        pos = _vol_condition(mid.exp(), ld) > 0
        hi = torch.where(pos, mid, hi)
        lo = torch.where(pos, lo, mid)
    p0 = (0.5 * (lo + hi)).exp()
    p0 = (p0 - _vol_condition(p0, ld) / _vol_condition_dp(p0, ld)).detach()  # Newton polish
    # differentiable Newton step: p = p0 - F(p0)/F'(p0), F' analytic (implicit function)
    return p0 - _vol_condition(p0, lam) / _vol_condition_dp(p0, lam)


def _vol_condition_dp(p: Tensor, lam: Tensor) -> Tensor:
    """``dF/dp`` of `_vol_condition` (positive)."""
    q = (1.0 / p).unsqueeze(-1)
    return (((2 * q**3) * (lam + q) + (lam - q * q) * q * q) / (lam + q) ** 2).sum(-1)


def _fogel_huang_rho(g: Tensor, r: Tensor, e: Tensor, n: int) -> Tensor:
    """Minimal-volume rho for a strip (Fogel & Huang 1982), batched closed form.

    ``log det P+(rho) = n log N - (n + 1) log D - (n - 1) log(1 - rho) + const`` with
    ``D = rho g + (1 - rho) r``, ``N = D - e^2 rho (1 - rho)``; its stationarity condition
    reduces to ``a rho^2 + b rho + c = 0`` (the cubic terms cancel). Candidates 0 and the roots
    in (0, 1) are compared by the objective.
    """
    e2 = e * e
    qa = n * (g - r) ** 2 - e2 * (g + n * r)
    qb = e2 * (g + 2 * n * r) - g * g + 2 * g * n * r + g * r - 2 * n * r * r
    qc = r * (n * r - g - n * e2)
    disc = (qb * qb - 4 * qa * qc).clamp(min=0.0)
    sq = torch.sqrt(disc)
    sgn = torch.where(qb >= 0, torch.ones_like(qb), -torch.ones_like(qb))
    qq = -0.5 * (qb + sgn * sq)
    safe_a = torch.where(qa.abs() > 0, qa, torch.ones_like(qa))
    safe_q = torch.where(qq.abs() > 0, qq, torch.ones_like(qq))
    r1 = torch.where(qa.abs() > 0, qq / safe_a, -qc / torch.where(qb != 0, qb, 1.0))
    r2 = torch.where(qq.abs() > 0, qc / safe_q, r1)
    cand = torch.stack([torch.zeros_like(g), r1, r2], -1)
    cand = torch.where((cand > 0) & (cand < 1), cand, torch.zeros_like(cand))
    cand = cand.clamp(max=1.0 - 1e-9)

    def obj(rho: Tensor) -> Tensor:
        gg, rr, ee = g.unsqueeze(-1), r.unsqueeze(-1), e2.unsqueeze(-1)
        D = rho * gg + (1 - rho) * rr
        N = (D - ee * rho * (1 - rho)).clamp(min=1e-300)
        return n * torch.log(N) - (n + 1) * torch.log(D) - (n - 1) * torch.log1p(-rho)

    idx = obj(cand.detach()).argmin(-1, keepdim=True)
    return torch.gather(cand, -1, idx).squeeze(-1)


def outer_sum_shape(S1: Tensor, S2: Tensor, method: str = "trace") -> Tensor:
    """Shape of the outer ellipsoid of ``F(0, S1) + F(0, S2)`` (Jiang et al. 2016, eq. 34-36,
    erratum).

    ``S(p) = (1 + 1/p) S1 + (1 + p) S2`` times ``1 + INFLATE`` (this module's rounding margin),
    with p from `minkowski_weight`
    (``"trace"``: ``sqrt(tr S1 / tr S2)``; ``"scaled-trace"``: the same in the coordinates
    normalised by ``diag(S1 + S2)``; ``"volume"``: the erratum's root, differentiable).
    Unlike ``Ellipsoid.minkowski_sum`` the operands may be positive *semi*definite (degenerate
    or zero ellipsoids, e.g. ``Gamma D Gamma'`` or a collapsed mean set): ``S2 = 0`` gives
    ``S1`` exactly (``S1 = 0`` gives ``S2``), and where the volume rule is undefined (``S1``
    singular) the trace weight is used. Any ``p > 0`` gives an outer bound (eq. 25-33), so the
    guarantee never depends on the weight.
    """
    if method not in ("trace", "scaled-trace", "volume"):
        raise ValueError(f"weight: expected 'trace', 'scaled-trace' or 'volume', got {method!r}")
    t1 = torch.diagonal(S1, dim1=-2, dim2=-1).sum(-1)
    t2 = torch.diagonal(S2, dim1=-2, dim2=-1).sum(-1)
    zero1, zero2 = (t1 <= 0).unsqueeze(-1).unsqueeze(-1), (t2 <= 0).unsqueeze(-1).unsqueeze(-1)
    eye = torch.eye(S1.shape[-1], dtype=S1.dtype, device=S1.device)
    S1s = torch.where(zero1, eye, S1)  # placeholders keep the unused branches finite
    S2s = torch.where(zero2, eye, S2)  # (also their gradients: no 0/0 in sqrt's backward)
    p = minkowski_weight(S1s, S2s, "scaled-trace" if method == "scaled-trace" else "trace")
    if method == "volume":
        pd = torch.linalg.cholesky_ex(S1s.detach())[1] == 0
        pd_m = pd.unsqueeze(-1).unsqueeze(-1)
        pv = minkowski_weight(torch.where(pd_m, S1s, eye), torch.where(pd_m, S2s, eye), "volume")
        p = torch.where(pd, pv, p)
    p = p.unsqueeze(-1).unsqueeze(-1)
    S = ((1.0 + 1.0 / p) * S1s + (1.0 + p) * S2s) * (1.0 + INFLATE)
    return linalg.sym(torch.where(zero2, S1, torch.where(zero1, S2, S)))
