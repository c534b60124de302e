"""An n-dimensional benchmark system: a chain of coupled nonlinear (Duffing) oscillators.

Not from the papers: a scalable test bed for the filters at n = 2 ... 32 and beyond
(the papers' systems have n <= 3). Registered as ``"oscillator_chain"``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.systems.library import box, positive, sym_box
from diffsmf.systems.system import System

__all__ = ["oscillator_chain"]


def _laplacian(N: int) -> Tensor:
    """Graph Laplacian ``[N, N]`` of a chain of N masses fixed at both ends (``2`` on the
    diagonal, ``-1`` next to it)."""
    L = 2.0 * torch.eye(N, dtype=torch.float64)
    idx = torch.arange(N - 1)
    L[idx, idx + 1] = -1.0
    L[idx + 1, idx] = -1.0
    return L


def oscillator_chain(
    n: int = 8,
    dt: float = 0.05,
    stiffness: float = 1.0,
    coupling: float = 0.5,
    cubic: float = 2.0,
    damping: float = 0.3,
    w: float = 1e-3,
    v: float = 2e-3,
    x0_radius: float = 0.05,
    horizon: int = 50,
) -> System:
    """Chain of ``N = n / 2`` damped Duffing oscillators with nearest-neighbour springs.

    State ``x = [p_1..p_N, v_1..v_N]`` (positions, velocities), explicit Euler step ``dt``::

        p+ = p + dt v
        v+ = v + dt (-stiffness p - cubic p^3 - coupling L p - damping v)

    with ``L`` the chain Laplacian (ends fixed). Output: one nonlinear sensor per mass,
    ``y_i = sin(p_i) + 0.5 p_i^2 + v`` (m = N). Noise boxes ``|w|_inf <= w``, ``|v|_inf <= v``;
    initial box ``p_i = 0.2 (-1)^i``, ``v_i = 0`` plus ``+-x0_radius``. The hardening cubic
    spring and the damping keep every trajectory bounded; the Hessian of ``f`` is diagonal
    (one ``6 dt cubic p_i`` entry per velocity row), that of ``h`` too.

    Args:
        n: state dimension (even, >= 2).
        dt: time step (positive).
        stiffness: linear spring constant (positive).
        coupling: spring constant between neighbouring masses (positive).
        cubic: hardening cubic spring constant (positive).
        damping: damping constant (positive).
        w: process noise half-width (>= 0).
        v: measurement noise half-width (>= 0).
        x0_radius: half-width of the initial box (> 0).
        horizon: the simulation length used by examples and benchmarks.
    """
    if not isinstance(n, int) or n < 2 or n % 2:
        raise ValueError(f"n: must be an even integer >= 2, got {n!r}")
    for name, val in (("dt", dt), ("stiffness", stiffness), ("coupling", coupling),
                      ("cubic", cubic), ("damping", damping), ("x0_radius", x0_radius)):
        positive(name, val)
    N = n // 2
    K = (stiffness * torch.eye(N, dtype=torch.float64) + coupling * _laplacian(N))
    # p+ = p + dt v ; v+ = -dt K p + (1 - dt damping) v - dt cubic p^3  (linear part as one map)
    A = torch.zeros(n, n, dtype=torch.float64)
    A[:N, :N] = torch.eye(N, dtype=torch.float64)
    A[:N, N:] = dt * torch.eye(N, dtype=torch.float64)
    A[N:, :N] = -dt * K
    A[N:, N:] = (1.0 - dt * damping) * torch.eye(N, dtype=torch.float64)
    At = A.T.contiguous()
    sel = torch.cat([torch.zeros(N, N), torch.eye(N)], 0).to(torch.float64)  # [n, N]: into v
    sel_t = sel.T.contiguous()

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        p = x[..., :N]
        return x @ At + (p * p * p) @ (-dt * cubic * sel_t)

    def h(x: Tensor) -> Tensor:
        p = x[..., :N]
        return torch.sin(p) + 0.5 * p * p

    sign = torch.tensor([(-1.0) ** i for i in range(N)], dtype=torch.float64)
    c0 = torch.cat([0.2 * sign, torch.zeros(N, dtype=torch.float64)])
    W, V = sym_box(n, w, "w"), sym_box(N, v, "v")
    s = System(f, h, box(c0, x0_radius), W, V,
               name=f"oscillator_chain(n={n})")
    s.horizon, s.paper_x0 = horizon, None
    return s
