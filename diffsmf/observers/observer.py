"""The PWL-model observer of Wang et al. 2009, eq. 3 as a batched torch module."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor, nn

__all__ = ["PWLObserver", "rk4_step"]


def rk4_step(rhs: Callable[[Tensor, Tensor], Tensor], z: Tensor, t: Tensor, dt: float) -> Tensor:
    """One classical Runge-Kutta step of z' = rhs(z, t); z [..., k], t scalar tensor."""
    k1 = rhs(z, t)
    k2 = rhs(z + 0.5 * dt * k1, t + 0.5 * dt)
    k3 = rhs(z + 0.5 * dt * k2, t + 0.5 * dt)
    k4 = rhs(z + dt * k3, t + dt)
    return z + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


class PWLObserver(nn.Module):
    """Observer x̂' = A x̂ + B_f f̂(H x̂) + B u + L (y - C x̂) (Wang et al. 2009, eq. 3, our sign of L).

    A [n, n], B [n, m], C [l, n], L [n, l]; ``fhat`` maps [..., q] -> [..., r] (an SCPLNN or
    any torch module/function); B_f [n, r] and H [q, n] default to identities (f̂ of the full
    state). time: "continuous" (fixed-step RK4) or "discrete" (x̂+ = right-hand side).
    Give an SCPLNN ``outside="clamp"``: x̂ may leave the model's domain during transients, and
    the clamped model keeps its Lipschitz bound (which the LMI design uses).
    """

    def __init__(self, A, B, C, L, fhat: Callable[[Tensor], Tensor], B_f=None, H=None,
                 time: str = "continuous"):
        super().__init__()
        if time not in ("continuous", "discrete"):
            raise ValueError(f"time must be 'continuous' or 'discrete', got {time!r}")
        A = torch.as_tensor(np.asarray(A, float))
        n = A.shape[0]
        mats = dict(A=A, B=B, C=C, L=L, B_f=np.eye(n) if B_f is None else B_f,
                    H=np.eye(n) if H is None else H)
        for name, M in mats.items():
            M = torch.as_tensor(np.atleast_2d(np.asarray(M, float)))
            if name in ("B", "L", "B_f") and M.shape[0] != n or name in ("C", "H") and M.shape[
                1
            ] != n:
                raise ValueError(f"{name} has shape {tuple(M.shape)}, incompatible with n={n}")
            self.register_buffer(name, M)
        self.fhat = fhat
        self.time = time

    def rhs(self, xhat: Tensor, y: Tensor, u: Tensor) -> Tensor:
        """Right-hand side of eq. 3: xhat [..., n], y [..., l], u [..., m] -> [..., n]."""
        innov = y - xhat @ self.C.T
        return (xhat @ self.A.T + self.fhat(xhat @ self.H.T) @ self.B_f.T + u @ self.B.T
                + innov @ self.L.T)

    def forward(self, y: Tensor, u: Tensor, x0: Tensor, dt: float = 1.0) -> Tensor:
        """Run the observer over sampled data: y [..., T+1, l] (y_k at t = k dt), u [..., T+1, m],
        x0 [..., n] -> xhat [..., T+1, n]. Continuous time: RK4 with y and u linearly
        interpolated between samples (exact when the caller integrates jointly, see
        `diffsmf.observers.pipeline.simulate`); discrete: x̂_{k+1} = rhs(x̂_k, y_k, u_k).
        """
        if y.shape[-2] != u.shape[-2]:
            raise ValueError("y and u must have the same number of samples")
        xh = x0.expand(*y.shape[:-2], x0.shape[-1])
        out = [xh]
        for k in range(y.shape[-2] - 1):  # time loop only
            if self.time == "discrete":
                xh = self.rhs(xh, y[..., k, :], u[..., k, :])
            else:
                y0, y1, u0, u1 = y[..., k, :], y[..., k + 1, :], u[..., k, :], u[..., k + 1, :]

                def f(z, s, y0=y0, y1=y1, u0=u0, u1=u1):
                    w = s / dt
                    return self.rhs(z, (1 - w) * y0 + w * y1, (1 - w) * u0 + w * u1)

                xh = rk4_step(f, xh, torch.zeros((), dtype=xh.dtype), dt)
            out.append(xh)
        return torch.stack(out, -2)
