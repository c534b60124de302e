"""Combined Kalman + set-membership filter for Gaussian plus bounded noise (Jiang et al. 2016).

Model (Jiang et al. 2016, eq. 1-4, in diffsmf's convention, noise added in state space)::

    x_k = f(x_{k-1}, u_{k-1}) + w_k + d_k,   w ~ N(0, Q),  d in F(d_c, D)
    y_k = h(x_k) + v_k + e_k,                v ~ N(0, R),  e in F(e_c, E)

The filter carries the *set of conditional means* ``F(a, S)`` (an `Ellipsoid`) and one
covariance ``P``: the centre and ``P`` follow the Kalman equations, the shape ``S`` follows the
outer-bounding Minkowski sums of an ellipsoidal set-membership filter (Jiang et al. 2016, eq.
39-47). Nonlinear ``f`` and ``h`` are replaced by affine maps fitted by statistical linearisation
over the current ellipsoid (Jiang et al. 2016, eq. 48-55,
`diffsmf.linearize.statistical_linearization`), the centre being propagated through the
nonlinear maps (eq. 56-57).

Guarantee: for affine ``f`` and ``h`` and zero Gaussian noise, the true state stays in ``F(a, S)``
whatever gain is used (x = (I - K H) x + K (y - e) exactly); with Gaussian noise the set bounds
the conditional mean, and ``confidence_region`` adds a k-sigma ellipsoid of ``P``. For nonlinear
maps the paper ignores the linearisation error, so the set is an approximation there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet, stack
from diffsmf.filters.base import (
    FilterResult,
    FilterState,
    SetFilter,
    bounded_result,
    state_batch,
    warn_uncertified_fit,
)
from diffsmf.linearize.statistical import check_levels, statistical_linearization
from diffsmf.sets.ellipsoid import Ellipsoid, outer_sum_shape, unit_ball_volume
from diffsmf.systems.system import System, check_system
from diffsmf.utils import Positive, register_positive

__all__ = ["CombinedFilter", "CombinedResult", "outer_sum_shape"]

_WEIGHTS = ("scaled-trace", "trace", "volume")
# Statistical linearisation is done over F(a, S + LIN_P_WEIGHT * P): the paper's F(a, S) up to a
# relative 1e-6 whenever the mean set is full-dimensional, and still well defined when the mean
# set degenerates (no bounded noise: it collapses to the Kalman estimate, and the fit becomes a
# small-step central difference, i.e. the EKF's Jacobian).
LIN_P_WEIGHT = 1e-6
_GAINS = ("auto", "kalman", "set")



def _scaled(M0: Tensor, v: Tensor, v0: Tensor) -> Tensor:
    """``diag(v / v0) M0 diag(v / v0)`` (components with ``v0 = 0`` have zero rows in M0)."""
    r = v / torch.where(v0 > 0, v0, torch.ones_like(v0))
    return r.unsqueeze(-1) * M0 * r.unsqueeze(-2)


def _psd(name: str, M: Tensor | None, dim: int) -> Tensor:
    """Validated symmetric PSD matrix ``[dim, dim]`` (zeros for ``None``)."""
    if M is None:
        return torch.zeros(dim, dim, dtype=torch.float64)
    M = torch.as_tensor(M, dtype=torch.float64)
    if M.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape ({dim}, {dim}), got {tuple(M.shape)}")
    if not torch.isfinite(M).all():
        raise ValueError(f"{name}: contains NaN or inf")
    scale = M.abs().max().clamp_min(1e-300)
    if (M - M.mT).abs().max() > 1e-10 * scale:
        raise ValueError(f"{name}: must be symmetric")
    if torch.linalg.eigvalsh(linalg.sym(M)).min() < -1e-10 * scale:
        raise ValueError(f"{name}: must be positive semidefinite")
    return linalg.sym(M)


def _cover_shape(s: ConvexSet | None, dim: int) -> Tensor:
    """Shape ``[dim, dim]`` of an ellipsoid covering a bounded noise set (centre excluded)."""
    if s is None:
        return torch.zeros(dim, dim, dtype=torch.float64)
    if isinstance(s, Ellipsoid):
        return s.shape.detach()
    return Ellipsoid.from_box(s.interval_hull()).shape.detach()  # box cover diag(n r^2)


@dataclass(frozen=True)
class CombinedResult(FilterResult):
    """`FilterResult` of `CombinedFilter`.

    ``sets``: the mean sets ``F(a_k, S_k)``, batch ``[B, T+1]``; ``covariance [B, T+1, n, n]``.
    """

    def confidence_region(self, k: float = 3.0, weight: str = "trace") -> Ellipsoid:
        """Probabilistic-plus-bounded region ``F(a, S) (+) F(0, k^2 P)`` ``[B, T+1]``.

        Outer ellipsoid of the mean set plus the k-sigma ellipsoid of the covariance: if the
        conditional mean lies in the mean set and the error about it is N(0, P), the state lies
        in the region with probability at least ``chi2_n(k^2)`` (n the state dimension; 0.989
        for k = 3 in a 2-D projection). Project with ``.linear_map(C)`` for plotting.
        """
        if not k > 0:
            raise ValueError(f"k: must be positive, got {k}")
        S = self.sets.shape
        return Ellipsoid._make(self.center, outer_sum_shape(S, k * k * self.covariance, weight))


class CombinedFilter(SetFilter):
    """Combined Kalman + ellipsoidal set-membership filter (Jiang et al. 2016, eq. 39-57).

    Args:
        system: the system; ``x0_set`` (an Ellipsoid, or a box covered by one) is the initial
            mean set ``F(a_0, S_0)``. Bounded noise ``D``/``E``: the system's ``process_noise`` /
            ``measurement_noise`` (ellipsoids used as they are, other sets covered by the
            ellipsoid of their interval hull); Gaussian ``Q``/``R``: ``process_cov`` /
            ``measurement_cov``. Any of them may be ``None`` (zero).
        initial_cov: ``P_0 [n, n]`` (symmetric PSD). Default: the covariance of the uniform
            distribution on the initial ellipsoid, ``S_0 / (n + 2)`` (the analogue of the EKF's
            ``r^2 / 3`` for a box), so that ``by_name("combined")(system)`` works; pass it to
            separate the Gaussian initial spread from the initial mean set.
        weight: Minkowski weights p, q of the state-space sums by ``"scaled-trace"`` (default:
            the paper's minimal-trace rule in the coordinates normalised by the operands'
            widths, so that the sets do not depend on the units of the states), ``"trace"``
            (the paper's rule in state units) or ``"volume"`` (minimal volume), Jiang et al.
            2016, eq. 34-36 (erratum).
        gain: ``"kalman"`` (eq. 44, ``K = P H' (H P H' + R)^-1``, needs R positive definite),
            ``"set"`` (``K = S H' (H S H' + E)^-1``, a pure ellipsoidal set-membership filter
            that ignores P), or ``"auto"`` (``"kalman"`` when R is positive definite, else
            ``"set"``).
        levels: statistical linearisation levels (point count ``2 len(levels) n + 1``), see
            `diffsmf.linearize.statistical_linearization`.
        point_weights: statistical linearisation point weights l_i (eq. 52-53).
        axes: statistical linearisation semi-axes (see `diffsmf.linearize.axis_points`).
        process_shape: override D ``[n, n]`` (PSD; a degenerate ellipsoid such as
            ``Gamma D Gamma'`` is allowed; it must cover the noise).
        measurement_shape: override E ``[m, m]`` (PSD, as ``process_shape``).
        process_cov: override Q.
        measurement_cov: override R.

    Learnable (softplus-positive): ``process_half_widths [n]``, ``measurement_half_widths [m]``
    (interval hull half-widths of D, E: ``D = diag(r/r0) D0 diag(r/r0)``), ``process_std [n]``,
    ``measurement_std [m]`` (square roots of the diagonals of Q, R, scaled the same way).

    State: ``set = Ellipsoid(a, S)`` ``[B]``, ``extras["covariance"] = P [B, n, n]``.
    """

    #: Not guaranteed in general: with Gaussian noise the set bounds the conditional mean, and
    #: for nonlinear maps the linearisation error is ignored (module docstring).
    guaranteed: bool = False
    #: the family of its sets (`diffsmf.filters.SET_FAMILIES`)
    set_family: str = "ellipsoid"
    process_std = Positive()
    measurement_std = Positive()

    def __init__(
        self,
        system: System,
        *,
        initial_cov: Tensor | None = None,
        weight: str = "scaled-trace",
        gain: str = "auto",
        levels: Sequence[float] = (0.5, 1.0),
        point_weights: Tensor | Sequence[float] | None = None,
        axes: str = "principal",
        process_shape: Tensor | None = None,
        measurement_shape: Tensor | None = None,
        process_cov: Tensor | None = None,
        measurement_cov: Tensor | None = None,
        skip_nan: bool = False,
        learn_noise: bool = True,
    ) -> None:
        check_system("system", system)
        warn_uncertified_fit(system, type(self).__name__)
        n, m = system.n, system.m
        D0 = (
            _cover_shape(system.process_noise, n)
            if process_shape is None
            else _psd("process_shape", process_shape, n)
        )
        E0 = (
            _cover_shape(system.measurement_noise, m)
            if measurement_shape is None
            else _psd("measurement_shape", measurement_shape, m)
        )
        super().__init__(
            system,
            process_half_widths=None if process_shape is None else _diag_sqrt(D0),
            measurement_half_widths=None if measurement_shape is None else _diag_sqrt(E0),
            skip_nan=skip_nan,
            learn_noise=learn_noise,
        )
        if weight not in _WEIGHTS:
            raise ValueError(f"weight: expected one of {_WEIGHTS}, got {weight!r}")
        if gain not in _GAINS:
            raise ValueError(f"gain: expected one of {_GAINS}, got {gain!r}")
        if process_cov is None:
            process_cov = system.process_cov
        if measurement_cov is None:
            measurement_cov = system.measurement_cov
        Q0 = _psd("process_cov", process_cov, n)
        R0 = _psd("measurement_cov", measurement_cov, m)
        r_pd = bool(torch.linalg.cholesky_ex(R0)[1] == 0)
        if gain == "kalman" and not r_pd:
            raise ValueError(
                "measurement_cov: gain='kalman' needs a positive definite R "
                "(Jiang et al. 2016, eq. 2); "
                "use gain='set' for a pure set-membership gain"
            )
        self.gain = ("kalman" if r_pd else "set") if gain == "auto" else gain
        self.weight = weight
        if axes not in ("principal", "symmetric"):
            raise ValueError(f"axes: expected 'principal' or 'symmetric', got {axes!r}")
        self.levels = check_levels(levels)
        self.point_weights = point_weights
        self.axes = axes
        self._x0 = _initial_ellipsoid(system.x0_set)
        if initial_cov is None:
            initial_cov = self._x0.shape.detach() / (n + 2)
        self.register_buffer("initial_cov", _psd("initial_cov", initial_cov, n))
        self.register_buffer("D0", D0)
        self.register_buffer("E0", E0)
        self.register_buffer("Q0", Q0)
        self.register_buffer("R0", R0)
        self.register_buffer("r_w0", self.process_half_widths.detach().clone())
        self.register_buffer("r_v0", self.measurement_half_widths.detach().clone())
        register_positive(self, "process_std", _diag_sqrt(Q0), learnable=learn_noise)
        register_positive(self, "measurement_std", _diag_sqrt(R0), learnable=learn_noise)
        self._gaussian_meas = bool((R0 != 0).any())

    # ------------------------------------------------------------------ noise matrices
    def process_bound(self) -> Tensor:
        """Bounded process-noise shape ``D [n, n]`` (differentiable in ``process_half_widths``)."""
        return _scaled(self.D0, self.process_half_widths, self.r_w0)

    def measurement_bound(self) -> Tensor:
        """Bounded measurement-noise shape ``E [m, m]`` (differentiable)."""
        return _scaled(self.E0, self.measurement_half_widths, self.r_v0)

    def process_covariance(self) -> Tensor:
        """Gaussian process covariance ``Q [n, n]`` (differentiable in ``process_std``)."""
        return _scaled(self.Q0, self.process_std, _diag_sqrt(self.Q0))

    def measurement_covariance(self) -> Tensor:
        """Gaussian measurement covariance ``R [m, m]`` (differentiable)."""
        return _scaled(self.R0, self.measurement_std, _diag_sqrt(self.R0))

    # ------------------------------------------------------------------ contract
    def _initial_state(self, batch: int | None = None) -> FilterState:
        """``F(a_0, S_0) = x0_set`` and ``P_0 = initial_cov``, batch ``[batch]``."""
        b = state_batch(batch)
        n = self.system.n
        return FilterState(
            set=self._x0.expand(b),
            consistent=torch.ones(b, dtype=torch.bool, device=self._x0.device),
            extras={"covariance": self.initial_cov.expand(b, n, n)},
        )

    def _linearize(self, fn, a: Tensor, S: Tensor, P: Tensor) -> Tensor:
        """Fitted matrix of ``fn`` over ``F(a, S + LIN_P_WEIGHT P)`` (Jiang et al. 2016, eq.
        54-55)."""
        A, _ = statistical_linearization(
            fn,
            a,
            S + LIN_P_WEIGHT * P,
            levels=self.levels,
            weights=self.point_weights,
            axes=self.axes,
        )
        return A

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Time update, Jiang et al. 2016, eq. 39-42 (linear) / eq. 54, 56 (nonlinear)."""
        a, S, P = state.set.center, state.set.shape, state.extras["covariance"]
        theta = self.system.theta_nominal

        def fn(x: Tensor) -> Tensor:
            return self.system.f(x, u, theta)

        A = self._linearize(fn, a, S, P)  # eq. 54
        a_new = fn(a) + self.process_noise_center  # eq. 56 (= eq. 40 for linear f)
        mm = linalg.matmul  # multiply-and-sum for small matrices (fused when compiled)
        S_lin = linalg.sym(mm(mm(A, S), A.mT))
        S_new = outer_sum_shape(S_lin, self.process_bound(), self.weight)  # eq. 41
        P_new = linalg.sym(mm(mm(A, P), A.mT) + self.process_covariance())  # eq. 42
        return FilterState(
            set=Ellipsoid._make(a_new, S_new),
            consistent=state.consistent,
            extras={"covariance": P_new},
        )

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update, Jiang et al. 2016, eq. 43-47 (linear) / eq. 55, 57 (nonlinear)."""
        a, S, P = state.set.center, state.set.shape, state.extras["covariance"]
        h = self.system.h
        H = self._linearize(h, a, S, P)  # eq. 55
        R, E = self.measurement_covariance(), self.measurement_bound()
        nu = self.system.innovation(y, h(a)) - self.measurement_noise_center  # eq. 57, wrapped
        G = P if self.gain == "kalman" else S
        W = R if self.gain == "kalman" else E
        mm = linalg.matmul
        HG = mm(H, G)
        Sy = _ridged(linalg.sym(mm(HG, H.mT) + W), 1e-12, torch.finfo(a.dtype).tiny ** 0.25)
        K = linalg.solve(Sy, HG).mT  # eq. 44: G H' (H G H' + W)^-1
        a_new = a + mm(K, nu.unsqueeze(-1)).squeeze(-1)  # eq. 57 (= eq. 45 for linear h)
        I_KH = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device) - mm(K, H)
        S_new = outer_sum_shape(
            linalg.sym(mm(mm(I_KH, S), I_KH.mT)), linalg.sym(mm(mm(K, E), K.mT)), self.weight
        )  # eq. 46
        P_new = linalg.sym(mm(mm(I_KH, P), I_KH.mT) + mm(mm(K, R), K.mT))  # eq. 47 in Joseph form
        return FilterState(
            set=Ellipsoid._make(a_new, S_new),
            consistent=self._consistent(nu, H, S, E, y),
            extras={"covariance": P_new},
        )

    def _consistent(self, nu: Tensor, H: Tensor, S: Tensor, E: Tensor, y: Tensor) -> Tensor:
        """Is ``y`` in the (linearised) predicted output set ``H F(a, S) + F(e_c, E)``?

        Only decided when the measurement has no Gaussian part (a Gaussian error is unbounded,
        so no measurement is then inconsistent). For nonlinear ``h`` the test uses the fitted
        ``H`` and is approximate. A (nearly) singular output shape (no noise and a collapsed
        set) gets a ridge of ``1e-9`` times its largest entry plus ``(1e-9 (1 + max|y|))^2``:
        an innovation that is zero up to rounding is consistent there.
        """
        if self._gaussian_meas:
            return torch.ones(nu.shape[:-1], dtype=torch.bool, device=nu.device)
        mm = linalg.matmul
        Sy = outer_sum_shape(linalg.sym(mm(mm(H, S), H.mT)), E, "trace")
        slack = (1e-9 * (1.0 + y.detach().abs().amax(-1))) ** 2
        Sy = _ridged(Sy, 1e-9, slack)
        d2 = mm(nu.unsqueeze(-2), linalg.solve(Sy, nu.unsqueeze(-1))).squeeze(-1).squeeze(-1)
        return d2 <= 1.0 + 1e-9

    def collect(self, states: list[FilterState]) -> CombinedResult:
        """Stack the states into a `CombinedResult` (adds ``confidence_region``).

        The volume is computed from the eigenvalues (clamped at 0) so that a degenerate mean
        set (no bounded noise: the set collapses towards the Kalman estimate) has volume 0
        instead of failing a Cholesky factorisation.
        """
        sets = stack([s.set for s in states], dim=1)
        hull = sets.interval_hull()
        lam = torch.linalg.eigvalsh(sets.shape).clamp_min(0)
        volume = unit_ball_volume(sets.dim) * lam.prod(-1).sqrt()
        cov = torch.stack([s.extras["covariance"] for s in states], 1)
        return bounded_result(
            CombinedResult, states, sets, sets.center, hull.lower, hull.upper, volume,
            {"covariance": cov},
        )


#: A PSD matrix counts as singular below this fraction of Hadamard's bound ``det <= prod(diag)``.
SINGULAR_RATIO = 1e-12


def _ridged(M: Tensor, rel: float, floor: Tensor | float) -> Tensor:
    """``M [..., m, m]`` (PSD) plus ``(rel * max diag + floor) I`` where it is (nearly) singular.

    ``K = G H' (H G H' + W)^-1`` (eq. 44) is 0 / 0 for outputs that neither the set nor the
    noise spreads: no noise and a set collapsed onto a level set of ``h``. The bounded-noise
    update (eq. 44-46) is an outer bound for *any* gain, so a ridge there keeps the guarantee
    and gives the limit gain (0 for an output with a zero row). A regular matrix (``det`` above
    ``SINGULAR_RATIO`` times the product of its diagonal) gets exact zeros added: the same
    bits as before.
    """
    d = torch.diagonal(M, dim1=-2, dim2=-1)
    near = linalg.det(M) <= SINGULAR_RATIO * d.prod(-1)
    delta = torch.where(near, rel * d.amax(-1) + floor, torch.zeros_like(d[..., 0]))
    eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
    return M + delta.unsqueeze(-1).unsqueeze(-1) * eye


def _diag_sqrt(M: Tensor) -> Tensor:
    return torch.diagonal(M, dim1=-2, dim2=-1).clamp_min(0).sqrt()


def _initial_ellipsoid(x0: ConvexSet) -> Ellipsoid:
    if isinstance(x0, Ellipsoid):
        return x0
    hull = x0.interval_hull()
    if not math.isfinite(float(hull.radius.max())):
        raise ValueError("system: x0_set must be bounded")
    return hull.to_ellipsoid()  # covering ellipsoid of the box (diag n r^2)
