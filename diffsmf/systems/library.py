"""Built-in systems of the implemented papers (registered in `diffsmf.systems.registry`).

Every factory returns a fresh `System` and accepts keyword overrides
(step, noise bounds, ...). Each system also carries two plain attributes used by examples and
tests: ``horizon`` (the simulation length used here; the papers' figures, or a stated choice
where the paper gives none) and ``paper_x0`` (the paper's true initial state, or ``None``).
The model functions use only ``x[..., i]`` indexing, ``torch.stack``, arithmetic and
elementwise torch functions, so they also run on `Interval` arguments
(interval extensions) and on the engine's enclosures (interval Hessians).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffsmf.sets import Ellipsoid, Interval
from diffsmf.systems.system import System

__all__ = [
    "bilinear", "cstr", "fermenter", "mismatch_quadratic", "spring_damper", "unicycle_rb", "vdp",
]

_F64 = torch.float64


def _vec(*v: float) -> Tensor:
    return torch.tensor(v, dtype=_F64)


def box(center: Tensor, radius: Tensor | float) -> Interval:
    return Interval(center - radius, center + radius)


def sym_box(n: int, bound: float, name: str) -> Interval:
    """Noise box ``[-bound, bound]^n``."""
    if not bound >= 0:
        raise ValueError(f"{name}: noise bound must be >= 0, got {bound}")
    return box(torch.zeros(n, dtype=_F64), bound)


def positive(name: str, value: float) -> float:
    if not value > 0:
        raise ValueError(f"{name}: must be positive, got {value}")
    return float(value)


def bilinear(u: float = 0.6, w: float = 1e-3, v: float = 1e-3, horizon: int = 100) -> System:
    """Wang et al. 2022, eq. 42 (sec. 4.1): ``x+ = [0.5 x1 x2, 0.2 x2^2] + u + w``, ``y = x1 + v``.

    Input ``u_k = 0.6`` added to both states (``inputs`` = ``[0.6, 0.6]``), ``|w|_inf <= 1e-3``,
    ``|v| <= 1e-3``, initial set the box ``[-0.2, 0.3] +- 0.1`` (the paper's parallelotope
    ``P0`` with ``T = diag(0.1, 0.1)``). The paper does not state its horizon; 100 steps.
    """

    def f(x: Tensor, u_: Tensor | None, theta: Tensor | None = None) -> Tensor:
        nl = torch.stack([0.5 * x[..., 0] * x[..., 1], 0.2 * x[..., 1] ** 2], -1)
        return nl if u_ is None else nl + u_

    def h(x: Tensor) -> Tensor:
        return x[..., 0:1]

    s = System(
        f, h, box(_vec(-0.2, 0.3), 0.1), sym_box(2, w, "w"), sym_box(1, v, "v"),
        inputs=lambda k: _vec(u, u), name="bilinear",
    )
    s.horizon, s.paper_x0 = horizon, None
    return s


def spring_damper(
    dt: float = 0.1,
    k0: float = 1.5,
    kd: float = 3.0,
    c: float = 1.24,
    w: float = 2e-3,
    v: float = 1e-3,
    x0_radius: float = 0.15,
    horizon: int = 100,
) -> System:
    """Wang et al. 2022, sec. 4.2 (Euler model of the paper): ``x1+ = x1 + dt x2``,
    ``x2+ = x2 + dt (-k0 x1 (1 - kd x1^2) - c x2)``, ``y = x1 + v``.

    ``dt = 0.1 s``, ``k0 = 1.5``, ``kd = 3``, ``c = 1.24``, ``w`` in the box ``+-0.002``,
    ``|v| <= 0.001``. The paper's Fig. 14 discusses steps 38-61, so its horizon is at least 61;
    100 steps here.

    Deviation (stated): the paper's initial parallelotope is the box ``[0.2, 0.3] +- 0.2``, but
    its softening spring ``-k0 x1 (1 - kd x1^2)`` has a potential barrier at
    ``|x1| = 1/sqrt(kd) = 0.577``; about 2 % of the states of that box (the corner
    ``x1 > 0.36, x2 > 0.43``) escape the well and diverge to inf within the horizon. The
    default initial box is therefore ``[0.2, 0.3] +- 0.15`` (every state of it, with
    worst-case noise, stays below ``|x1| = 0.55``); ``x0_radius=0.2`` gives the paper's box.
    """
    dt = positive("dt", dt)

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack(
            [x1 + dt * x2, x2 + dt * (-k0 * x1 * (1.0 - kd * x1**2) - c * x2)], -1
        )

    def h(x: Tensor) -> Tensor:
        return x[..., 0:1]

    s = System(
        f, h, box(_vec(0.2, 0.3), positive("x0_radius", x0_radius)), sym_box(2, w, "w"),
        sym_box(1, v, "v"), name="spring_damper",
    )
    s.horizon, s.paper_x0 = horizon, None
    return s


def mismatch_quadratic(
    w: float = 1e-3,
    v: float = 1e-2,
    c_bounds: tuple[float, float] = (0.06, 0.26),
    c_values: tuple[float, float, float] = (0.11, 0.06, 0.26),
    switch_steps: tuple[int, int] = (30, 70),
    horizon: int = 100,
) -> System:
    """Song et al. 2017, eq. 41: ``x1+ = x1 - 0.2 C x1^2``, ``x2+ = x2 + 0.1 C x1^2``, ``y = [x1, 3
    x2]``.

    ``C`` is mismatched: ``parameters = [0.06, 0.26]`` (nominal 0.16); the true ``C(k)`` is 0.11
    for ``k <= 30``, 0.06 for ``30 < k <= 70``, 0.26 for ``k > 70`` (k = index of the step
    ``x_k -> x_{k+1}``). Noise per the erratum: ``w`` uniform in ``[-1e-3, 1e-3]^2``, ``v`` in
    ``[-1e-2, 1e-2]^2``. Initial set: the paper's ellipsoid ``E([2, 0.5], 3 I)`` (initial
    estimate, "bound 3I"), which contains the true ``x0 = [3, 1]`` (``paper_x0``). The paper
    gives no horizon; 100 steps (past the last switch at 70).
    """
    lo, hi = c_bounds
    if not lo <= min(c_values) <= max(c_values) <= hi:
        raise ValueError(f"c_values: {c_values} must lie in c_bounds {c_bounds}")
    k1, k2 = switch_steps
    c0, c1, c2 = c_values

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        C = (lo + hi) / 2 if theta is None else theta[..., 0]
        q = C * x[..., 0] ** 2
        return torch.stack([x[..., 0] - 0.2 * q, x[..., 1] + 0.1 * q], -1)

    def h(x: Tensor) -> Tensor:
        return torch.stack([x[..., 0], 3.0 * x[..., 1]], -1)

    def schedule(k: int) -> Tensor:
        return _vec(c0 if k <= k1 else c1 if k <= k2 else c2)

    s = System(
        f, h, Ellipsoid(_vec(2.0, 0.5), 3.0 * torch.eye(2, dtype=_F64)),
        sym_box(2, w, "w"), sym_box(2, v, "v"), Interval(_vec(lo), _vec(hi)),
        theta_schedule=schedule, name="mismatch_quadratic",
    )
    s.horizon, s.paper_x0 = horizon, _vec(3.0, 1.0)
    return s


# Table 2 of Song et al. 2017
_FERMENTER = dict(Y=0.4, eta=2.2, gamma=0.2, mu_m=0.48, P_m=50.0, K_m=1.2, K_i=22.0)


def fermenter(
    dt: float = 1.0,
    w: float = 1e-2,
    v: float = 1e-2,
    dD: float = 0.06,
    dSf: float = 3.0,
    switch_times: tuple[float, float] = (80.0, 200.0),
    x0_radius: tuple[float, float, float] = (2.5, 1.5, 5.5),
    horizon: int | None = None,
) -> System:
    """Song et al. 2017, eq. 42-43, Table 2: continuous fermenter, explicit Euler with step ``dt``
    (h).

    State ``[X, S, P]``, all measured (``y = x + v``). ``dX = -D X + mu X``,
    ``dS = D (S_f - S) - mu X / Y``, ``dP = -D P + (eta mu + gamma) X``,
    ``mu = mu_m (1 - P/P_m) S / (K_m + S + S^2/K_i)``. Mismatched ``theta = [D, S_f]`` in
    ``[0.15 +- 0.06] x [20 +- 3]`` (nominal = Table 2 values); the true values switch to
    ``(0.09, 17)`` for ``80 <= t <= 200`` and ``(0.21, 23)`` for ``t > 200`` (``t = k dt``).
    Noise ``U(-1e-2, 1e-2)`` per component and sampling step.

    Stated choices (the paper gives none): ``dt = 1 h`` (the sampling instants 80, 200 of the
    paper are then steps; Euler at 1 h matches Euler at 0.1 h to 1e-2 over 300 h, the
    linearised rates are below 0.37/h), horizon 300 h, initial set the box centred at the
    paper's initial estimate ``[5, 1, 20]`` with half-widths ``x0_radius = [2.5, 1.5, 5.5]``,
    which contains the true initial state ``[7.038, 2.404, 24.87]`` (``paper_x0``, the
    steady state for the nominal D, S_f).
    """
    dt = positive("dt", dt)
    p = _FERMENTER
    t1, t2 = switch_times

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        X, S, P = x[..., 0], x[..., 1], x[..., 2]
        if theta is None:
            D, Sf = 0.15, 20.0
        else:
            D, Sf = theta[..., 0], theta[..., 1]
        mu = p["mu_m"] * (1.0 - P / p["P_m"]) * S / (p["K_m"] + S + S**2 / p["K_i"])
        dX = -D * X + mu * X
        dS = D * (Sf - S) - mu * X / p["Y"]
        dP = -D * P + (p["eta"] * mu + p["gamma"]) * X
        return torch.stack([X + dt * dX, S + dt * dS, P + dt * dP], -1)

    def h(x: Tensor) -> Tensor:
        return x[..., 0:3]

    def schedule(k: int) -> Tensor:
        t = k * dt
        return _vec(0.15, 20.0) if t < t1 else _vec(0.09, 17.0) if t <= t2 else _vec(0.21, 23.0)

    theta_box = box(_vec(0.15, 20.0), _vec(dD, dSf))
    s = System(
        f, h, box(_vec(5.0, 1.0, 20.0), _vec(*x0_radius)),
        sym_box(3, w, "w"), sym_box(3, v, "v"), theta_box,
        theta_schedule=schedule, name="fermenter",
    )
    s.horizon = int(round(300.0 / dt)) if horizon is None else horizon
    s.paper_x0 = _vec(7.038, 2.404, 24.87)
    return s


_B_VDP = torch.tensor([0.0, 1.0], dtype=_F64)


def vdp(dt: float = 0.05, w: float = 1e-3, v: float = 1e-2, horizon: int = 400) -> System:
    """Wang et al. 2009, eq. 23 (Van der Pol type), explicit Euler with step ``dt`` (s):
    ``x1+ = x1 + dt x2``, ``x2+ = x2 + dt (x2 - x1 - x1^2 x2 + u)``, ``y = x1 + v``.

    Input ``u_k = sin(k dt)``. Stated choices (the paper is continuous-time, noise-free):
    ``dt = 0.05 s``, horizon 400 steps (20 s), ``|w| <= 1e-3``, ``|v| <= 1e-2``, initial set
    the box ``[1.5, 0.7] +- 0.5`` centred at the paper's observer start, containing the true
    ``x(0) = [1.2, 0.5]`` (``paper_x0``).
    """
    dt = positive("dt", dt)

    def f(x: Tensor, u: Tensor | None, theta: Tensor | None = None) -> Tensor:
        x1, x2 = x[..., 0], x[..., 1]
        out = torch.stack([x1 + dt * x2, x2 + dt * (x2 - x1 - x1**2 * x2)], -1)
        return out if u is None else out + dt * u[..., 0:1] * _B_VDP  # B u, B = [0, 1]

    def h(x: Tensor) -> Tensor:
        return x[..., 0:1]

    s = System(
        f, h, box(_vec(1.5, 0.7), 0.5), sym_box(2, w, "w"), sym_box(1, v, "v"),
        inputs=lambda k: _vec(math.sin(k * dt)), name="vdp",
    )
    s.horizon, s.paper_x0 = horizon, _vec(1.2, 0.5)
    return s


# A textbook exothermic CSTR (first-order A -> B, Seborg et al. parameters) with a cooling jacket
_CSTR = dict(q_V=1.0, Caf=1.0, Tf=350.0, k0=7.2e10, E_R=8750.0, dH_rcp=-5e4 / 239.0,
             UA_Vrcp=5e4 / (100.0 * 239.0))


def cstr(
    dt: float = 0.1,
    substeps: int = 4,
    Tcin: float = 287.0,
    jacket_tau: float = 2.0,
    jacket_gain: float = 0.2,
    w: tuple[float, float, float] = (1e-3, 0.05, 0.05),
    v: float = 0.4,
    x0_radius: tuple[float, float, float] = (0.1, 5.0, 5.0),
    horizon: int = 1000,
) -> System:
    """Continuous stirred-tank reactor with a cooling jacket: a stable, observable plant whose
    states have very different scales (``Ca`` in mol/L, ``T`` and ``Tc`` in K).

    State ``[Ca, T, Tc]``, temperature measured (``y = T + v``). Exothermic first-order
    reaction ``A -> B`` with the rate ``r = k0 exp(-E/(R T)) Ca`` (the classic parameters:
    ``q/V = 1 /min``, ``Caf = 1 mol/L``, ``Tf = 350 K``, ``k0 = 7.2e10 /min``,
    ``E/R = 8750 K``, ``-dH/(rho Cp) = 5e4/239 K L/mol``, ``UA/(V rho Cp) = 5e4/23900 /min``)::

        dCa/dt = q/V (Caf - Ca) - r
        dT/dt  = q/V (Tf - T) - dH/(rho Cp) r + UA/(V rho Cp) (Tc - T)
        dTc/dt = (Tcin - Tc) / jacket_tau + jacket_gain (T - Tc)

    Discrete time: one sampling step ``dt`` (min) is ``substeps`` explicit Euler steps inside
    ``f``. With ``Tcin = 287 K`` the steady state is ``Ca = 0.918 mol/L``, ``T = 319.1 K``,
    ``Tc = 296.2 K``, stable (eigenvalues -1.82, -1.19, -0.40 /min). Bounded noise
    ``|w| <= (1e-3, 0.05, 0.05)`` per step and ``|v| <= 0.4 K``; initial set the box
    ``[0.9, 320, 295] +- (0.1, 5, 5)``; horizon 1,000 steps (100 min). Not from the seed papers:
    a first-day plant whose state scales differ by two orders of magnitude, used to check that
    the filters do not depend on the units of the states.
    """
    dt = positive("dt", dt)
    if not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"substeps: must be an integer >= 1, got {substeps!r}")
    p = _CSTR
    hs = dt / substeps

    def rhs(Ca: Tensor, T: Tensor, Tc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r = p["k0"] * torch.exp(-p["E_R"] / T) * Ca
        dCa = p["q_V"] * (p["Caf"] - Ca) - r
        dT = p["q_V"] * (p["Tf"] - T) - p["dH_rcp"] * r + p["UA_Vrcp"] * (Tc - T)
        dTc = (Tcin - Tc) / jacket_tau + jacket_gain * (T - Tc)
        return dCa, dT, dTc

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        Ca, T, Tc = x[..., 0], x[..., 1], x[..., 2]
        for _ in range(substeps):
            dCa, dT, dTc = rhs(Ca, T, Tc)
            Ca, T, Tc = Ca + hs * dCa, T + hs * dT, Tc + hs * dTc
        return torch.stack([Ca, T, Tc], -1)

    def h(x: Tensor) -> Tensor:
        return x[..., 1:2]

    s = System(
        f, h, box(_vec(0.9, 320.0, 295.0), _vec(*x0_radius)),
        box(torch.zeros(3, dtype=_F64), _vec(*w)), sym_box(1, v, "v"), name="cstr",
    )
    s.horizon, s.paper_x0 = horizon, None
    return s


def unicycle_rb(
    dt: float = 0.1,
    speed: float = 1.0,
    turn_rate: float = 0.2,
    landmark: tuple[float, float] = (20.0, 0.0),
    w: tuple[float, float, float] = (1e-3, 1e-3, 1e-4),
    v: tuple[float, float] = (0.02, 0.005),
    x0_radius: tuple[float, float, float] = (0.2, 0.2, 0.05),
    heading0: float = 0.0,
    horizon: int = 1000,
) -> System:
    """Unicycle measured by range and bearing to a landmark (a textbook navigation model).

    State ``[px, py, heading]`` (m, m, rad), inputs ``u = [speed, turn_rate]`` (schedule:
    constant, a circle of radius ``speed / turn_rate = 5 m`` about ``(0, 5)``), explicit Euler
    with step ``dt``::

        px+ = px + dt u1 cos(heading),  py+ = py + dt u1 sin(heading),  heading+ = heading + dt u2

    Outputs ``y = [range, bearing]`` to the landmark ``(lx, ly)``: ``range = |l - p|`` and the
    bearing in the body frame ``atan2(ly - py, lx - px) - heading``, an angle output
    (``angle_outputs=[1]``: simulated bearings are wrapped into ``[-pi, pi)``, the filters
    wrap the residual about the predicted bearing). The heading is not wrapped (it grows by
    ``2 pi`` per lap), so the body-frame bearing crosses ``+-pi`` every lap; the landmark
    (default (20, 0), east of the circle) keeps the direction ``l - p`` in the right half
    plane, away from atan2's cut while the set's box stays west of it. Noise ``|w| <= (1e-3,
    1e-3, 1e-4)``, ``|v| <= (0.02 m, 0.005 rad)`` (with 2e-3 m and 1e-3 rad per step of
    process noise, HSNSMF's box reached the landmark after about 980 steps and ESMF's after
    370: one landmark observes position and heading only weakly); initial set ``[0, 0,
    heading0] +- (0.2, 0.2, 0.05)``; horizon 1,000 steps (100 s,
    3.2 laps). Not from the seed papers.
    """
    dt = positive("dt", dt)
    lx, ly = landmark

    def f(x: Tensor, u: Tensor | None, theta: Tensor | None = None) -> Tensor:
        px, py, th = x[..., 0], x[..., 1], x[..., 2]
        sp = speed if u is None else u[..., 0]
        om = turn_rate if u is None else u[..., 1]
        return torch.stack(
            [px + dt * sp * torch.cos(th), py + dt * sp * torch.sin(th), th + dt * om], -1
        )

    def h(x: Tensor) -> Tensor:
        dx, dy = lx - x[..., 0], ly - x[..., 1]
        rng = torch.sqrt(dx * dx + dy * dy)
        return torch.stack([rng, torch.atan2(dy, dx) - x[..., 2]], -1)

    s = System(
        f, h, box(_vec(0.0, 0.0, heading0), _vec(*x0_radius)),
        box(torch.zeros(3, dtype=_F64), _vec(*w)), box(torch.zeros(2, dtype=_F64), _vec(*v)),
        inputs=lambda k: _vec(speed, turn_rate), name="unicycle_rb", angle_outputs=[1],
    )
    s.horizon, s.paper_x0 = horizon, None
    return s
