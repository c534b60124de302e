"""Samples of f -> SCPLNN model f̂ with a certified error eps -> LMI gain -> simulated observer.

Wang et al. 2009, sec. 3 end to end, on its example eq. 23 (continuous-time van der Pol form)::

    x1' = x2,  x2' = x2 - x1 - x1^2 x2 + u,  y = x1,   u = sin t
    A = [[0, 1], [-1, 1]], B = [0; 1], C = [1, 0], f(x) = B_f phi(x), B_f = [0; 1], phi = -x1^2 x2

Guarantee chain (see docs/observers.md): the bound of `design_lipschitz_observer` holds
if |phi(x) - f̂(x)| <= eps on the domain D, the true state stays in D, and gamma bounds the
Lipschitz constant of f̂ (``SCPLNN.lipschitz_bound``, valid with ``outside="clamp"``, so x̂ may
leave D). eps is CERTIFIED per simplex of the partition: with W_j the model's vertex values,
|phi - f̂| <= max_j |phi(v_j) - W_j| + (M/2) R^2 (Taylor at x of the linear interpolant of phi;
M bounds the Hessian 2-norm of phi on the simplex, R^2 <= diam^2 n / (2 (n + 1)) by Jung's
theorem), not just measured on samples.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from diffsmf.linearize.jets import interval_hessian
from diffsmf.observers.envelope import error_envelope
from diffsmf.observers.lmi import ObserverDesign, design_lipschitz_observer
from diffsmf.observers.observer import PWLObserver, rk4_step
from diffsmf.pwl import SCPLNN, fit_scplnn
from diffsmf.pwl.partition import grid_partition
from diffsmf.sets import Interval

__all__ = [
    "ContinuousModel",
    "PipelineResult",
    "certified_error",
    "simplex_error_bound",
    "design_observer_pipeline",
    "fit_nonlinearity",
    "interval_hess_bound",
    "plot_pipeline",
    "simulate",
    "vdp_model",
]


@dataclass
class ContinuousModel:
    """x' = A x + B_f phi(H x) + B u(t), y = C x, on the box domain (lower, upper) of H x.

    The model a user gives to `design_observer_pipeline` and to
    ``diffsmf design-observer --model FILE.py:FUNC`` (``FUNC()`` returns one). Shapes: A [n, n],
    B [n, p], C [l, n], B_f [n, r], H [q, n], lower/upper [q] (lower < upper), x0/xhat0 [n]
    (true and observer initial states, for the simulation).
    phi: torch function [..., q] -> [..., r]; u: t (0-d tensor) -> [p] input.
    hess_bound(simplex vertices [M, q+1, q]) -> [M, r] upper bounds of the Hessian 2-norm of
    each phi_i on each simplex; None: computed by interval arithmetic
    (`interval_hess_bound`, certified for phi built from the operations that
    `diffsmf.linearize.jets` supports). The observer's bound holds while H x stays in the
    domain (checked in the simulation).
    Checked on construction: ValueError naming the field for wrong shapes, NaN or inf, an empty
    domain, or a phi / u / hess_bound that is not callable.
    """

    name: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    B_f: np.ndarray
    H: np.ndarray
    phi: Callable[[Tensor], Tensor]
    hess_bound: Callable[[Tensor], Tensor] | None
    lower: np.ndarray
    upper: np.ndarray
    x0: np.ndarray
    xhat0: np.ndarray
    u: Callable[[Tensor], Tensor]

    def __post_init__(self) -> None:
        def mat(name, rows=None, cols=None, ndim=2):
            try:
                M = np.asarray(getattr(self, name), dtype=float)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"ContinuousModel.{name} must be numeric") from exc
            if M.ndim != ndim or not np.all(np.isfinite(M)):
                raise ValueError(f"ContinuousModel.{name} must be a finite {ndim}-D array, got "
                                 f"shape {M.shape}")
            if (rows is not None and M.shape[0] != rows) or (
                    cols is not None and ndim == 2 and M.shape[1] != cols):
                want = f"[{rows if rows is not None else '.'}" + (
                    f", {cols if cols is not None else '.'}]" if ndim == 2 else "]")
                raise ValueError(f"ContinuousModel.{name} must have shape {want}, got {M.shape}")
            setattr(self, name, M)
            return M

        A = mat("A")
        n = A.shape[0]
        if A.shape != (n, n) or n == 0:
            raise ValueError(f"ContinuousModel.A must be square [n, n], got {A.shape}")
        mat("B", rows=n)
        mat("C", cols=n)
        mat("B_f", rows=n)
        q = mat("H", cols=n).shape[0]
        lo, hi = mat("lower", rows=q, ndim=1), mat("upper", rows=q, ndim=1)
        if not np.all(lo < hi):
            raise ValueError("ContinuousModel.lower must be < upper in every component")
        mat("x0", rows=n, ndim=1)
        mat("xhat0", rows=n, ndim=1)
        for name in ("phi", "u"):
            if not callable(getattr(self, name)):
                raise ValueError(f"ContinuousModel.{name} must be callable")
        if self.hess_bound is None:
            self.hess_bound = interval_hess_bound(self.phi)
        elif not callable(self.hess_bound):
            raise ValueError("ContinuousModel.hess_bound must be callable or None")


def interval_hess_bound(phi: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """A certified ``hess_bound`` for phi by interval arithmetic (Song et al. 2017, eq. 26-28).

    For simplex vertices V [M, q+1, q]: the interval Hessian [H_lo, H_hi] of each phi_i over the
    simplex's bounding box (`diffsmf.linearize.jets.interval_hessian`); with
    Hmax = max(|H_lo|, |H_hi|) entrywise, every Hessian in the box has 2-norm <= rho(|H|) <=
    rho(Hmax) = |Hmax|_2 (Perron-Frobenius). Returns [M, r] (times 1 + 1e-9 for rounding).
    """
    def bound(V: Tensor) -> Tensor:
        box = Interval(V.amin(-2), V.amax(-2))
        try:
            Hi = interval_hessian(phi, box)
        except Exception as exc:  # noqa: BLE001 - an operation jets do not support
            raise ValueError(
                f"ContinuousModel.phi: the interval Hessian bound failed ({type(exc).__name__}: "
                f"{exc}); give hess_bound= explicitly") from exc
        Hmax = torch.maximum(Hi.lower.abs(), Hi.upper.abs())
        if not torch.all(torch.isfinite(Hmax)):
            raise ValueError("ContinuousModel.phi: the interval Hessian is not finite on the "
                             "domain; give hess_bound= explicitly")
        return torch.linalg.matrix_norm(Hmax, ord=2) * (1 + 1e-9)

    return bound


def _vdp_phi(x: Tensor) -> Tensor:
    return -(x[..., :1] ** 2) * x[..., 1:2]  # Wang et al. 2009, eq. 23: f(X) = -x1^2 x2


def _vdp_hess_bound(V: Tensor) -> Tensor:
    # Hess phi = [[-2 x2, -2 x1], [-2 x1, 0]]: |.|_2 <= |.|_F = 2 sqrt(x2^2 + 2 x1^2), a norm of x,
    # hence convex: its max over a simplex is at a vertex.
    fro = 2.0 * torch.sqrt(V[..., 1] ** 2 + 2.0 * V[..., 0] ** 2)
    return fro.amax(-1, keepdim=True) * (1 + 1e-12)


def vdp_model() -> ContinuousModel:
    """Wang et al. 2009, eq. 23 with the paper's x(0) = [1.2, 0.5], x̂(0) = [1.5, 0.7], u = sin t.
    The domain covers the forced limit cycle (|x1| <= 2.38, |x2| <= 3.77 on t in [0, 30])."""
    return ContinuousModel(
        name="vdp",
        A=np.array([[0.0, 1.0], [-1.0, 1.0]]),
        B=np.array([[0.0], [1.0]]),
        C=np.array([[1.0, 0.0]]),
        B_f=np.array([[0.0], [1.0]]),
        H=np.eye(2),
        phi=_vdp_phi,
        hess_bound=_vdp_hess_bound,
        lower=np.array([-2.5, -4.0]),
        upper=np.array([2.5, 4.0]),
        x0=np.array([1.2, 0.5]),
        xhat0=np.array([1.5, 0.7]),
        u=lambda t: torch.sin(t).reshape(1),
    )


def simplex_error_bound(V: Tensor, W: Tensor, phi: Callable[[Tensor], Tensor],
                        hess_bound) -> Tensor:
    """Per-simplex bound ``[M, r]`` of sup |phi_i - f̂_i| over each simplex (module docstring):
    vertex mismatch + (M/2) R^2. V: simplex vertices [M, q+1, q]; W: their weights [M, q+1, r]."""
    with torch.no_grad():
        vert = (phi(V) - W).abs().amax(-2)  # [M, r] vertex mismatch (the affine part's max)
        d2 = (V[:, :, None, :] - V[:, None, :, :]).pow(2).sum(-1).amax((-1, -2))  # diam^2
        q = V.shape[-1]
        R2 = d2 * q / (2 * (q + 1))  # Jung's theorem
        return (vert + 0.5 * hess_bound(V) * R2[:, None]) * (1 + 1e-9) + 1e-12


def certified_error(model, phi: Callable[[Tensor], Tensor], hess_bound) -> float:
    """sup over the model's domain of |phi - model| (2-norm over outputs), certified per simplex
    (module docstring). model: an SCPLNN (vertices, simplices, weight)."""
    with torch.no_grad():
        err = simplex_error_bound(model.vertices[model.simplices],
                                  model.weight[model.simplices], phi, hess_bound)
        return float(err.norm(dim=-1).max()) * (1 + 1e-9) + 1e-12


def _grid_model(sysm: ContinuousModel, cells: list[int]):
    lo, hi = torch.as_tensor(sysm.lower), torch.as_tensor(sysm.upper)
    V, S = grid_partition(lo, hi, cells)
    with torch.no_grad():
        W = sysm.phi(V)
    return SCPLNN(V, S, W, outside="clamp")


def fit_nonlinearity(
    sysm: ContinuousModel,
    eps: float,
    method: str = "auto",
    samples: int = 4000,
    max_regions: int = 20000,
    seed: int = 0,
    progress: bool | None = False,
) -> tuple[object, dict]:
    """SCPLNN model of phi on the domain with certified error, and a report dict.

    method "scplnn": ``diffsmf.pwl.fit_scplnn`` (Wang et al. 2009, sec. 3.1.2) on ``samples``
    uniform random samples, with the vertex values taken from phi (``vertex_fn``) and every region
    also split until its certified bound (`simplex_error_bound`, with ``sysm.hess_bound``) is
    below eps (``region_bound``).
    "grid": interpolation on a Kuhn-triangulated grid refined until the certified error <= eps.
    "auto": "scplnn", falling back to "grid" when its certified error exceeds eps or its
    Lipschitz bound is above 2x the grid model's.
    """
    if method not in ("auto", "scplnn", "grid"):
        raise ValueError(f"method must be 'auto', 'scplnn' or 'grid', got {method!r}")
    if not eps > 0:
        raise ValueError(f"eps must be positive, got {eps}")
    t0 = _time.perf_counter()
    info: dict = {}
    model = None
    if method in ("auto", "scplnn"):
        model = _scplnn_model(sysm, eps, samples, max_regions, seed, info, progress)
    if method in ("auto", "grid"):
        gm, cells = _refined_grid(sysm, eps)
        if model is not None:
            sc = certified_error(model, sysm.phi, sysm.hess_bound)
            with torch.no_grad():
                lip_s, lip_g = float(model.lipschitz_bound()), float(gm.lipschitz_bound())
            info.update(scplnn_certified_error=sc, scplnn_lipschitz=lip_s)
            if sc <= eps and lip_s <= 2 * lip_g:
                gm = None
            else:
                info["fallback"] = (f"fit_scplnn model rejected (certified error {sc:.3g}, "
                                    f"Lipschitz {lip_s:.3g}); using the grid interpolant")
        if gm is not None:
            model = gm
            info.update(method="grid", regions=int(gm.simplices.shape[0]), cells=cells)
    with torch.no_grad():
        info["certified_error"] = certified_error(model, sysm.phi, sysm.hess_bound)
        info["lipschitz"] = float(model.lipschitz_bound())
    info["seconds"] = _time.perf_counter() - t0
    return model, info


def _scplnn_model(sysm: ContinuousModel, eps: float, samples: int, max_regions: int, seed: int,
                  info: dict, progress: bool | None = False):
    """fit_scplnn on uniform random samples of phi; certified when sysm.hess_bound is given."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.as_tensor(sysm.lower), torch.as_tensor(sysm.upper)
    X = lo + torch.rand(samples, lo.shape[0], generator=g, dtype=torch.float64) * (hi - lo)
    with torch.no_grad():
        Y = sysm.phi(X)
    kw: dict = {}
    eps_i = eps
    if sysm.hess_bound is not None:  # certify inside the fit: interpolate phi, split on bound
        eps_i = eps / math.sqrt(Y.shape[1])  # per-output bounds -> 2-norm over outputs <= eps
        kw = dict(vertex_fn=sysm.phi, region_bound=lambda V, W: simplex_error_bound(
            V, W, sysm.phi, sysm.hess_bound), rule="edge")
    model, rep = fit_scplnn(X, Y, eps_i, max_regions=max_regions, domain=(lo, hi),
                            progress=progress, **kw)
    model.outside = "clamp"
    info.update(method="scplnn", fit_converged=bool(rep.converged), regions=int(rep.regions),
                sample_max_error=float(rep.max_error.max()), fit_seconds=float(rep.seconds),
                fit_stop=rep.stop_reason)
    return model


def _refined_grid(sysm: ContinuousModel, eps: float):
    """Grid interpolant refined until its certified error is <= eps. Returns (model, cells)."""
    span = sysm.upper - sysm.lower
    cells = [max(2, int(math.ceil(s))) for s in span]
    while True:
        gm = _grid_model(sysm, cells)
        ce = certified_error(gm, sysm.phi, sysm.hess_bound)
        if ce <= eps or min(cells) > 2000:
            return gm, cells
        cells = [int(math.ceil(c * min(2.0, 1.05 * math.sqrt(ce / eps)))) for c in cells]


def simulate(sysm: ContinuousModel, observer: PWLObserver, T: float, dt: float,
             progress: bool = False) -> dict:
    """Joint RK4 of the true system and the observer (exact y and u at every stage).

    Returns numpy arrays t [K+1], x [K+1, n], xhat [K+1, n], d [K+1] = |phi(H x) - f̂(H x)|.
    progress: a tqdm bar over the K = round(T / dt) steps.
    """
    n = sysm.A.shape[0]
    A, B, Bf, H = (torch.as_tensor(M) for M in (sysm.A, sysm.B, sysm.B_f, sysm.H))
    C = torch.as_tensor(sysm.C)

    def rhs(z: Tensor, t: Tensor) -> Tensor:
        x, xh = z[..., :n], z[..., n:]
        u = sysm.u(t)
        dx = x @ A.T + sysm.phi(x @ H.T) @ Bf.T + u @ B.T
        return torch.cat([dx, observer.rhs(xh, x @ C.T, u)], -1)

    steps = int(round(T / dt))
    z = torch.as_tensor(np.concatenate([sysm.x0, sysm.xhat0]))
    zs = [z]
    from tqdm.auto import tqdm

    with torch.no_grad():
        for k in tqdm(range(steps), desc="simulate", unit="step", disable=not progress,
                      leave=False):  # time loop only
            z = rk4_step(rhs, z, torch.tensor(k * dt, dtype=torch.float64), dt)
            zs.append(z)
        Z = torch.stack(zs)
        x = Z[:, :n]
        d = (sysm.phi(x @ H.T) - observer.fhat(x @ H.T)).norm(dim=-1)
    return dict(t=np.arange(steps + 1) * dt, x=x.numpy(), xhat=Z[:, n:].numpy(), d=d.numpy())


@dataclass
class PipelineResult:
    """Everything the pipeline made: the model and its report, both LMI designs (structured and
    general), the simulation and its checks."""

    system: ContinuousModel
    model: object
    fit: dict
    design: ObserverDesign
    design_general: ObserverDesign
    sim: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)

    def summary(self) -> str:
        d, g, c = self.design, self.design_general, self.checks
        lines = [
            f"model: {self.fit['method']}, {self.fit['regions']} regions, certified eps = "
            f"{self.fit['certified_error']:.4g}, Lipschitz(f̂) = {self.fit['lipschitz']:.4g}",
            f"structured LMI (f = B_f phi(x)): {d.status}; L = {np.round(d.L, 3).ravel().tolist()}"
            f", gain = {d.gain:.4g}, bound = {d.bound:.4g}, decay = {d.decay:.4g}"
            if d.feasible else f"structured LMI: {d.status}: {d.message}",
            f"general LMI (|f(x)-f(x̂)| <= gamma|e|): {g.status}"
            + (f", bound = {g.bound:.4g}" if g.feasible else f" ({g.message[:60]}...)"),
        ]
        if c:
            lines.append(
                f"simulation: state in domain {c['state_in_domain']}, |e| <= envelope "
                f"{c['within_envelope']}, max |e| after t={c['t_after']:.0f}: "
                f"{c['max_err_after']:.4g} <= bound {d.bound:.4g}: {c['within_bound_after']}, "
                f"max |phi - f̂| on trajectory {c['max_model_error']:.4g}"
            )
        return "\n".join(lines)


def design_observer_pipeline(
    system: str | ContinuousModel = "vdp",
    eps: float = 0.05,
    *,
    method: str = "auto",
    T: float = 20.0,
    dt: float = 5e-3,
    max_gain: float = 1e4,
    simulate_system: bool = True,
    samples: int = 4000,
    seed: int = 0,
    progress: bool = False,
) -> PipelineResult:
    """Sample phi, fit SCPLNN with certified error, design L (structured and general LMIs),
    build the `PWLObserver`, simulate system and observer, check the guarantee.

    system: "vdp" (Wang et al. 2009, eq. 23) or a `ContinuousModel`; eps: target certified
    model error; T, dt: simulated time and RK4 step; max_gain: cap on |L|_2; samples, seed: the
    uniform random samples of phi for ``fit_scplnn``; progress: tqdm bars (fit, simulation).
    Bad arguments raise ValueError naming them.
    """
    if isinstance(system, str):
        if system != "vdp":
            raise ValueError(f"system: unknown built-in {system!r} (built-in: 'vdp'; or pass a "
                             "ContinuousModel)")
        sysm = vdp_model()
    elif isinstance(system, ContinuousModel):
        sysm = system
    else:
        raise ValueError(f"system must be 'vdp' or a ContinuousModel, got "
                         f"{type(system).__name__}")
    for name, v in (("eps", eps), ("T", T), ("dt", dt), ("max_gain", max_gain)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive number, got {v!r}")
    if dt > T:
        raise ValueError(f"dt must be <= T, got dt={dt}, T={T}")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    model, fit = fit_nonlinearity(sysm, eps, method=method, samples=samples, seed=seed,
                                  progress=progress)
    gamma, eps_c = fit["lipschitz"], fit["certified_error"]
    design = design_lipschitz_observer(sysm.A, sysm.C, gamma, eps_c,
                                       structure=(sysm.B_f, sysm.H), max_gain=max_gain)
    general = design_lipschitz_observer(sysm.A, sysm.C, gamma, eps_c, max_gain=max_gain)
    res = PipelineResult(system=sysm, model=model, fit=fit, design=design, design_general=general)
    if not (simulate_system and design.feasible):
        return res
    obs = PWLObserver(sysm.A, sysm.B, sysm.C, design.L, model, B_f=sysm.B_f, H=sysm.H)
    sim = simulate(sysm, obs, T, dt, progress=progress)
    e = np.linalg.norm(sim["x"] - sim["xhat"], axis=-1)
    env = error_envelope(design, sysm.x0 - sysm.xhat0, sim["t"])
    after = sim["t"] >= T / 2
    hx = sim["x"] @ sysm.H.T
    res.sim = dict(sim, err=e, envelope=env)
    res.checks = dict(
        state_in_domain=bool(((hx >= sysm.lower) & (hx <= sysm.upper)).all()),
        within_envelope=bool((e <= env * (1 + 1e-6)).all()),
        t_after=T / 2,
        max_err_after=float(e[after].max()),
        within_bound_after=bool(e[after].max() <= design.bound),
        max_model_error=float(sim["d"].max()),
    )
    return res


def plot_pipeline(res: PipelineResult, path: str) -> None:
    """Figure: the first (up to 3) states and their estimates; |e(t)| against the guaranteed
    envelope and the bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = res.sim
    k = min(s["x"].shape[1], 3)
    fig, ax = plt.subplots(k + 1, 1, figsize=(7, 2.5 * (k + 1)), sharex=True)
    for i in range(k):
        ax[i].plot(s["t"], s["x"][:, i], "k", lw=1.2, label=f"x{i + 1}")
        ax[i].plot(s["t"], s["xhat"][:, i], "r--", lw=1.0, label=f"x̂{i + 1}")
        ax[i].set_ylabel(f"x{i + 1}")
        ax[i].legend(loc="upper right")
    ax[k].semilogy(s["t"], s["err"], "b", lw=1.0, label="|e(t)|")
    ax[k].semilogy(s["t"], s["envelope"], "g", lw=1.0, label="guaranteed envelope")
    ax[k].axhline(res.design.bound, color="r", ls=":", label=f"bound {res.design.bound:.3g}")
    ax[k].set_xlabel("t")
    ax[k].set_ylabel("|x - x̂|")
    ax[k].legend(loc="upper right")
    ax[0].set_title(f"PWL observer ({res.system.name}), eps = {res.fit['certified_error']:.3g} "
                    "(certified)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
