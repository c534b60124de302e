"""ESMF: extended (ellipsoidal) set-membership filter with bounded parameter mismatch, Song et al.
2017.

Prediction (sec. 4.2, eq. 18-35): autograd Jacobian A at the centre with the nominal parameter
(eq. 25); Lagrange remainder by an interval Hessian over the interval hull of the ellipsoid
(eq. 26-28); parameter-deviation box (eq. 18-21); each box covered by the diagonal ellipsoid
``diag(n b_i^2)`` (eq. 23 and 29 with the n-D erratum: ``2 b^2`` covers a box only in 2-D);
virtual process noise ``(Qbar (+) Q) (+) Delta`` and prior ``A P A' (+) Qhat``, each an outer
Minkowski sum (eq. 30-35 = eq. 15-17) with the trace-minimal weight times the learnable
``minkowski_scale`` (1 = the paper's rule).

Update (sec. 4.3, eq. 36-40): intersection of the prior with the linearised observation set
``{x : (y - h(c) - H (x - c))' Rhat^-1 (...) <= 1}``, ``Rhat`` the covering ellipsoid of the
measurement-noise box plus the Lagrange remainder of ``h`` (an ellipsoidal or zonotope V is
used as given, summed with the remainder's ellipsoid).

Deviations (guarantee fixes, also in docs/filters.md): the parameter deviation is bounded over
the whole current box, not only at the centre (eq. 20 evaluates it at ``x_hat`` only, which does
not contain ``f(x, theta) - f(x, theta_m)`` for the other x of the set); remainder and deviation
boxes keep their centres (the paper centres the remainder ellipsoid at 0); the remainder of a
nonlinear ``h`` is folded into ``Rhat``.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import where
from diffsmf.filters.base import (
    FilterState,
    StrictlyPositive,
    register_minkowski_scale,
    scaled_minkowski_sum,
)
from diffsmf.filters.ellipsoidal import EllipsoidalSetFilter
from diffsmf.filters.prediction import noise_ellipsoid, step_function
from diffsmf.filters.remainder_boxes import (
    add_remainder_margin,
    checked_remainder,
    remainder_box,
    rounding_margin,
    spent_initial_box,
    widen,
)
from diffsmf.filters.strips import angle_ambiguous
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System

__all__ = ["ESMF"]

SHAPE_MARGIN = 1e-10  # relative outward margin on shape matrices (float64 rounding)



def _max_sv(M: Tensor) -> Tensor:
    """Largest singular value of symmetric PSD ``M [..., k, k]`` -> ``[...]``."""
    return linalg.eigvalsh(linalg.sym(M))[..., -1].clamp_min(0.0)


class ESMF(EllipsoidalSetFilter):
    """Extended set-membership filter of Song et al. 2017 (guaranteed, ellipsoidal).

    Args:
        system: the system to filter (``system.parameters`` = the mismatch interval, or None).
        rho_rule: weight rho of the update (eq. 36-39). ``"volume"`` (default): the rho that
            minimises the volume of the updated ellipsoid (``Ellipsoid.intersect_measurement``
            1-D search). ``"eq40"``: eq. 40 as printed, ``rho = sqrt(d1)/(sqrt(d1)+sqrt(d2))``,
            d1 = sigma_max(Rhat), d2 = sigma_max(H P H'), which gives the measurement the
            *least* weight when it is most precise. ``"eq13"``: the paper's intersection rule
            eq. 13 with the prior as ellipsoid 1 (d1, d2 swapped). All are guaranteed; the
            printed rules diverge on built-in systems (docs/filters.md): eq. 40 into the pole
            of the fermenter's mu, eq. 13 on spring_damper (m < n: rho -> 1 inflates the
            unobserved direction by 1 / (1 - rho)).
        initial_set: override of ``system.x0_set`` (converted to a covering ellipsoid).
        remainder_margin: the remainder box's margin (`LinearisingFilter`).
        minkowski_scale: learnable factor ``s > 0`` (scalar) on the weight of every Minkowski
            sum of the prediction (eq. 14-17 used in eq. 29-31, eq. 32 and eq. 34-35):
            ``p = s * p_trace`` in ``S(p) = (1 + 1/p) S1 + (1 + p) S2``, ``p_trace`` the
            paper's trace rule ``sqrt(tr S1 / tr S2)`` taken in the coordinates normalised
            by ``diag(S1 + S2)`` (``minkowski_weight(..., "scaled-trace")``; deviation: the
            rule in state units depends on the units of the states). Every ``p > 0`` gives
            an outer bound, so tuning ``s`` never breaks the guarantee; 1 (default)
            reproduces the rule bit for bit. One factor is shared by the (up to) three sums
            of a step: it keeps the parameter a single scalar like CDSMF's, and the sums
            play the same role (how much of the bound goes to which operand); the sum that
            dominates the prior is the last one (eq. 34-35, prior ``A P A'`` + virtual
            noise). Softplus-scaled (``scale * softplus(raw)``). Raises ``ValueError`` for 0,
            negative, NaN or infinite values.
        remainder: guaranteed remainder bound (`LinearisingFilter`; default ``"lagrange"``,
            Song et al. 2017, eq. 26-28). ESMF linearises with the autograd Jacobian (eq. 24)
            and has no Stirling step.

    State set: ``Ellipsoid`` with batch shape ``[B]``.
    """

    stirling: ClassVar[bool] = False  # eq. 24: the autograd Jacobian
    default_remainder: ClassVar[str] = "lagrange"  # eq. 26-28
    minkowski_scale = StrictlyPositive()

    def __init__(
        self,
        system: System,
        *,
        rho_rule: str = "volume",
        minkowski_scale: float | Tensor = 1.0,
        **kw,
    ) -> None:
        if rho_rule not in ("eq40", "eq13", "volume"):
            raise ValueError(f"rho_rule: expected 'eq13', 'eq40' or 'volume', got {rho_rule!r}")
        super().__init__(system, **kw)
        register_minkowski_scale(self, minkowski_scale)
        self.rho_rule = rho_rule

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Eq. 24-35: ``E(f(c) + a, A P A') (+) [(Qbar (+) Q) (+) Delta]``."""
        from diffsmf.linearize import jacobian, parameter_deviation
        from diffsmf.sets.ellipsoid import Ellipsoid

        E = state.set
        c = E.center
        box = remainder_box(E, state.extras)  # eq. 27 (∩ the initial box at k = 0)
        fn = step_function(self.system, u)
        A = jacobian(fn, c)  # eq. 25
        R, ev = checked_remainder(self.remainder_fn(fn, box, c, A))  # eq. 26-28
        fc = fn(c)
        R = widen(R, rounding_margin(fc, R.center, R.radius))
        R = add_remainder_margin(R, self.remainder_margin)  # learnable, only adds
        s = self.minkowski_scale  # p = s * trace rule in every sum (s = 1: the paper)
        Well = noise_ellipsoid(self)  # an ellipsoidal / zonotope W as given
        Wq = self.process_noise_box().to_ellipsoid() if Well is None else Well
        Qhat = scaled_minkowski_sum(R.to_ellipsoid(), Wq, "scaled-trace", s)  # eq. 29-31
        if self.system.parameters is not None:  # eq. 18-23, 30, 32
            D = parameter_deviation(
                self.system.f, box, self.system.parameters, self.system.theta_nominal, u
            )
            D, ev_d = checked_remainder(D)
            ev = ev | ev_d
            Qhat = scaled_minkowski_sum(Qhat, D.to_ellipsoid(), "scaled-trace", s)
        lin = E.linear_map(A, fc - (A @ c.unsqueeze(-1)).squeeze(-1))  # eq. 33
        new = scaled_minkowski_sum(lin, Qhat, "scaled-trace", s)  # eq. 34-35
        new = Ellipsoid(new.center, linalg.sym(new.shape) * (1 + SHAPE_MARGIN))
        return state.replace(set=new, extras=spent_initial_box(state.extras)).flag(ev)

    def _observation_noise(self, y: Tensor, hc: Tensor, Rh: Interval) -> Ellipsoid:
        """Ellipsoid ``E(v', Rhat) [B, m]`` containing measurement noise + remainder of ``h``.

        A box V (the paper's case): the covering ellipsoid ``diag(m r^2)`` of the box
        ``V + Rh`` (eq. 23 with the n-D erratum). An ellipsoidal V is used as given and a
        zonotope V through its covering ellipsoid (not via its interval hull), each
        summed with the covering ellipsoid of the remainder box by the trace-minimal outer
        Minkowski sum (Song et al. 2017, eq. 14-17). Widened for rounding.
        """
        V = self.measurement_noise_set()
        if isinstance(V, Interval):
            noise = Interval(V.lower + Rh.lower, V.upper + Rh.upper)
            noise = widen(noise, rounding_margin(y, hc, noise.center, noise.radius))
            return noise.to_ellipsoid()  # diag(m r^2): covering ellipsoid of the box
        Vell = V if isinstance(V, Ellipsoid) else Ellipsoid.from_zonotope(V)
        vr = Vell.interval_hull().radius
        Rb = widen(Rh, rounding_margin(y, hc, Rh.center, Rh.radius, vr))
        return Rb.to_ellipsoid().minkowski_sum(Vell, method="trace")

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Eq. 36-40: prior ∩ linearised observation set (``Ellipsoid.intersect_measurement``)."""
        from diffsmf.linearize import jacobian

        E = state.set
        c, P = E.center, E.shape
        h = self.system.h
        H = jacobian(h, c)
        hc = h(c)
        # unbounded remainder of h: the measurement cannot shrink the set (update skipped)
        hull = E.interval_hull()
        Rh, ev_h = checked_remainder(self.remainder_fn(h, hull, c, H))
        ok_h = ev_h == 0
        if self.system.angle_outputs:  # a residual that may be on the wrong branch: skipped
            amb = angle_ambiguous(self.system, hull, c, H, Rh, self.measurement_noise_box())
            ok_h = ok_h & ~amb.any(-1)
        noise = self._observation_noise(y, hc, Rh)
        Rhat = noise.shape
        nu = self.system.innovation(y, hc) - noise.center  # innovation (angles wrapped)
        HPH = linalg.sym(H @ P @ H.mT)
        ylin = nu + (H @ c.unsqueeze(-1)).squeeze(-1)  # y' = H x + v', v' in E(0, Rhat)
        if self.rho_rule == "volume":
            # xi(rho) = 1 - rho (1 - rho) nu' D(rho)^-1 nu; the intersection is empty iff
            # xi < 0 for some rho (checked on a grid; eq. 36)
            grid = torch.linspace(0.02, 0.98, 49, dtype=c.dtype)
            r = grid.reshape(-1, *([1] * (nu.dim() - 1)))  # [G, 1..]
            D = linalg.sym(r[..., None, None] * HPH + (1 - r)[..., None, None] * Rhat)
            Dnu = linalg.solve(D, nu.expand(grid.shape[0], *nu.shape).unsqueeze(-1))
            xi = (1 - r * (1 - r) * (nu * Dnu.squeeze(-1)).sum(-1)).amin(0)
            ok = (xi > 0) | ~ok_h
            new = E.intersect_measurement(H, ylin, Rhat, method="volume")
            return state.replace(set=where(ok & ok_h, new, E), consistent=ok).flag(
                ev_h, unbounded=False
            )
        d1, d2 = _max_sv(Rhat), _max_sv(HPH)
        if self.rho_rule == "eq13":
            d1, d2 = d2, d1
        rho = (d1.sqrt() / (d1.sqrt() + d2.sqrt())).clamp(1e-12, 1 - 1e-12)  # eq. 40
        D = linalg.sym(rho[..., None, None] * HPH + (1 - rho)[..., None, None] * Rhat)
        Dnu = linalg.solve(D, nu.unsqueeze(-1)).squeeze(-1)
        xi = 1 - rho * (1 - rho) * (nu * Dnu).sum(-1)  # eq. 36 (times rho (1 - rho))
        ok = (xi > 0) | ~ok_h  # Song et al. 2017: xi <= 0 means the bounds are violated (a fault)
        new = E.intersect_measurement(H, ylin, Rhat, rho=torch.where(ok, rho, 0.5 * rho))
        return state.replace(set=where(ok & ok_h, new, E), consistent=ok).flag(
            ev_h, unbounded=False
        )
