"""EKF: extended Kalman filter baseline (not guaranteed).

Noise covariances from the bounds (our choice, stated): a component bounded by ``|w_i| <= r_i``
is treated as uniform on ``[-r_i, r_i]``, variance ``r_i^2 / 3``; the initial covariance is the
same uniform variance of the interval hull of ``x0_set``; any Gaussian ``process_cov`` /
``measurement_cov`` of the system is added. Jacobians by autograd at the nominal parameter;
Joseph-form update. ``FilterResult.sets`` holds the 3-sigma ellipsoid ``E(x_hat, 9 P)``, which
is NOT a guaranteed bound; the covariance itself is ``result.extras["covariance"]``.
``consistent`` is always True (an EKF has no emptiness test).
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.filters.prediction import step_function
from diffsmf.filters.state import check_initial_set, state_batch
from diffsmf.systems.system import System
from diffsmf.utils import tracing

__all__ = ["EKF"]

SIGMA_LEVEL = 3.0  # the set reported in FilterResult is the SIGMA_LEVEL-sigma ellipsoid



class EKF(SetFilter):
    """Extended Kalman filter with covariances derived from the noise bounds.

    Args:
        system: the system to filter.
        initial_set: override of ``system.x0_set`` (its hull gives the initial mean/covariance).

    State: ``set`` = ``Ellipsoid(x_hat, 9 P)``; ``extras["covariance"] = P [B, n, n]``.
    """

    #: Not a set-membership filter: its set is a 3-sigma ellipsoid, not a bound.
    guaranteed: bool = False
    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "ellipsoid"

    def __init__(self, system: System, *, initial_set: ConvexSet | None = None, **kw) -> None:
        super().__init__(system, **kw)
        check_initial_set("initial_set", initial_set, system.n)
        self._x0 = initial_set if initial_set is not None else system.x0_set

    # covariance <-> reported set
    def _state(self, x: Tensor, P: Tensor, consistent: Tensor) -> FilterState:
        from diffsmf.sets.ellipsoid import Ellipsoid

        P = linalg.sym(P)
        return FilterState(
            set=Ellipsoid(x, SIGMA_LEVEL**2 * P), consistent=consistent, extras={"covariance": P}
        )

    def process_covariance(self) -> Tensor:
        """``Q [n, n]``: ``diag(r_w^2 / 3)`` (+ ``system.process_cov``)."""
        Q = torch.diag_embed(self.process_half_widths**2 / 3)
        return Q if self.system.process_cov is None else Q + self.system.process_cov

    def measurement_covariance(self) -> Tensor:
        """``R [m, m]``: ``diag(r_v^2 / 3)`` (+ ``system.measurement_cov``)."""
        R = torch.diag_embed(self.measurement_half_widths**2 / 3)
        return R if self.system.measurement_cov is None else R + self.system.measurement_cov

    def _initial_state(self, batch: int | None = None) -> FilterState:
        hull = self._x0.interval_hull()
        b = state_batch(batch)
        x = hull.center.expand(b, -1)
        P = torch.diag_embed(hull.radius**2 / 3).expand(b, -1, -1)
        return self._state(x, P, torch.ones(b, dtype=torch.bool))

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """``x = f(x) + w_c``, ``P = A P A' + Q``."""
        from diffsmf.linearize import jacobian

        x, P = state.set.center, state.extras["covariance"]
        fn = step_function(self.system, u)
        A = jacobian(fn, x)
        xn = fn(x) + self.process_noise_center
        Pn = linalg.matmul(linalg.matmul(A, P), A.mT) + self.process_covariance()
        return self._state(xn, Pn, state.consistent)

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Kalman gain, Joseph form ``(I - K H) P (I - K H)' + K R K'``."""
        from diffsmf.linearize import jacobian

        x, P = state.set.center, state.extras["covariance"]
        h = self.system.h
        H = jacobian(h, x)
        R = self.measurement_covariance()
        nu = self.system.innovation(y, h(x)) - self.measurement_noise_center  # angles wrapped
        mm = linalg.matmul  # multiply-and-sum for small matrices (fused when compiled)
        HP = mm(H, P)
        S = linalg.sym(mm(HP, H.mT) + R)
        if not tracing() and bool((torch.linalg.cholesky_ex(S.detach())[1] != 0).any()):
            raise ValueError(
                "measurement_noise: the innovation covariance H P H' + R is not positive "
                "definite (zero measurement noise on a degenerate covariance?)"
            )
        K = linalg.solve(S, HP).mT  # P H' S^-1 (closed form for m <= 2)
        xn = x + mm(K, nu.unsqueeze(-1)).squeeze(-1)
        I_KH = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device) - mm(K, H)
        Pn = mm(mm(I_KH, P), I_KH.mT) + mm(mm(K, R), K.mT)
        return self._state(xn, Pn, torch.ones_like(state.consistent))
