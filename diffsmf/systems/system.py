"""Discrete-time nonlinear system with bounded (and optionally Gaussian) noise.

Model (the convention of every filter in diffsmf, DESIGN.md)::

    x_k = f(x_{k-1}, u_{k-1}, theta_{k-1}) + w_{k-1} (+ g_{k-1}),   w in W,  g ~ N(0, Q)
    y_k = h(x_k) + v_k (+ e_k),                                        v in V,  e ~ N(0, R)
    x_0 in X0

``W``, ``V``, ``X0`` are any :mod:`diffsmf.sets` set; ``theta`` is an unknown parameter known
only to lie in the :class:`~diffsmf.sets.Interval` ``parameters`` (nominal value: its midpoint).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from diffsmf.sets.base import ConvexSet

__all__ = ["System", "Trajectory"]


class Trajectory(NamedTuple):
    """A batch of simulated trajectories.

    x: ``[B, T+1, n]`` true states (``x[:, 0]`` in ``x0_set``);
    y: ``[B, T, m]`` measurements, ``y[:, k-1] = h(x_k) + v_k``;
    u: ``[B, T, p]`` inputs (``u[:, k-1]`` drives ``x_{k-1} -> x_k``) or ``None``;
    theta: ``[B, T, q]`` parameters used at each step, or ``None``.
    """

    x: Tensor
    y: Tensor
    u: Tensor | None
    theta: Tensor | None


def _as_schedule(
    name: str, value: Tensor | Callable[[int], Tensor] | None
) -> Callable[[int], Tensor] | None:
    if value is None or callable(value):
        return value
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.dim() < 2:
        raise ValueError(f"{name}: a tensor schedule must have shape [T, dim] or [B, T, dim]")
    return lambda k: t[..., k, :]


class System(nn.Module):
    """Nonlinear system with set-bounded noise, as an ``nn.Module``.

    Args:
        f: ``f(x [..., n], u [..., p] | None, theta [..., q] | None) -> [..., n]``, torch ops.
        h: ``h(x [..., n]) -> [..., m]``, torch ops.
        x0_set: initial set (batch shape ``[]``), dim n.
        process_noise: bounded process noise set W (dim n) or ``None`` (zero).
        measurement_noise: bounded measurement noise set V (dim m) or ``None`` (zero).
        parameters: ``Interval`` of mismatched parameters (dim q) or ``None``.
        inputs: ``u(k) -> [p]`` or ``[B, p]`` (k = 0, 1, ...), or a tensor ``[T, p]``; ``None``
            for an autonomous system.
        theta_schedule: the true parameter used by ``simulate`` at step k (``k -> [q]``,
            or a tensor ``[T, q]``); default: the midpoint of ``parameters``.
        process_cov, measurement_cov: optional Gaussian covariances Q ``[n, n]``, R ``[m, m]``.
        name: a label for tables and figures.
    """

    def __init__(
        self,
        f: Callable[..., Tensor],
        h: Callable[[Tensor], Tensor],
        x0_set: ConvexSet,
        process_noise: ConvexSet | None = None,
        measurement_noise: ConvexSet | None = None,
        parameters: ConvexSet | None = None,
        *,
        inputs: Tensor | Callable[[int], Tensor] | None = None,
        theta_schedule: Tensor | Callable[[int], Tensor] | None = None,
        process_cov: Tensor | None = None,
        measurement_cov: Tensor | None = None,
        name: str = "system",
    ) -> None:
        super().__init__()
        if not callable(f) or not callable(h):
            raise ValueError("f, h: must be callables written with torch ops")
        if not isinstance(x0_set, ConvexSet):
            raise ValueError("x0_set: must be a diffsmf set")
        if len(x0_set.batch_shape) != 0:
            raise ValueError("x0_set: must have an empty batch shape")
        self.f = f
        self.h = h
        self.x0_set = x0_set
        self.n = x0_set.dim
        self.m = int(h(x0_set.center).shape[-1])
        for label, s, d in (
            ("process_noise", process_noise, self.n),
            ("measurement_noise", measurement_noise, self.m),
        ):
            if s is not None and (not isinstance(s, ConvexSet) or s.dim != d):
                raise ValueError(f"{label}: must be a diffsmf set of dim {d}")
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        self.parameters = parameters
        self.inputs = _as_schedule("inputs", inputs)
        self.theta_schedule = _as_schedule("theta_schedule", theta_schedule)
        self.process_cov = _check_cov("process_cov", process_cov, self.n)
        self.measurement_cov = _check_cov("measurement_cov", measurement_cov, self.m)
        self.name = name

    # ------------------------------------------------------------------ helpers
    @property
    def theta_nominal(self) -> Tensor | None:
        """Midpoint of the parameter interval ``[q]`` (or ``None``)."""
        return None if self.parameters is None else self.parameters.center

    def input_at(self, k: int, batch: int) -> Tensor | None:
        """Input ``u_k`` as ``[batch, p]`` (or ``None``)."""
        if self.inputs is None:
            return None
        u = torch.as_tensor(self.inputs(k), dtype=self.x0_set.dtype, device=self.x0_set.device)
        u = u.reshape(-1) if u.dim() == 0 else u
        return u.expand(batch, u.shape[-1])

    def theta_at(self, k: int, batch: int) -> Tensor | None:
        """True parameter at step k for ``simulate``, ``[batch, q]`` (or ``None``)."""
        if self.parameters is None:
            return None
        th = self.theta_nominal if self.theta_schedule is None else self.theta_schedule(k)
        th = torch.as_tensor(th, dtype=self.x0_set.dtype, device=self.x0_set.device)
        return th.expand(batch, th.shape[-1])

    def forward(self, x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        """One noise-free step ``f(x, u, theta)``; ``theta`` defaults to the nominal value."""
        if theta is None:
            theta = self.theta_nominal
        return self.f(x, u, theta)

    # ------------------------------------------------------------------ simulation
    def simulate(
        self,
        steps: int,
        batch: int = 1,
        seed: int | None = 0,
        noise: str = "uniform",
        theta: Tensor | Callable[[int], Tensor] | None = None,
        x0: Tensor | None = None,
    ) -> Trajectory:
        """Simulate ``batch`` trajectories of ``steps`` steps.

        Args:
            noise: ``"uniform"`` (points drawn inside the noise sets and X0) or ``"vertex"``
                (worst case: vertices / boundary points of the sets, new draw every step).
            theta: parameter schedule overriding ``theta_schedule`` (``k -> [q]`` or
                ``[B, q]``, or a tensor ``[T, q]`` / ``[B, T, q]``).
            x0: initial states ``[B, n]``; default drawn from ``x0_set`` like the noise.

        Returns:
            :class:`Trajectory` with ``x [B, T+1, n]``, ``y [B, T, m]``, ``u``, ``theta``.
        """
        if noise not in ("uniform", "vertex"):
            raise ValueError(f"noise: expected 'uniform' or 'vertex', got {noise!r}")
        if steps < 1 or batch < 1:
            raise ValueError("steps, batch: must be positive")
        gen = torch.Generator(device=self.x0_set.device)
        gen.manual_seed(0 if seed is None else seed)

        def draw(s: ConvexSet | None, dim: int) -> Tensor:
            if s is None:
                return torch.zeros(batch, dim, dtype=self.x0_set.dtype, device=self.x0_set.device)
            pts = s.sample_extreme(batch, gen) if noise == "vertex" else s.sample(batch, gen)
            return pts.reshape(batch, dim)

        def gauss(cov: Tensor | None, dim: int) -> Tensor | float:
            if cov is None:
                return 0.0
            evals, evecs = torch.linalg.eigh(cov)  # PSD square root (Q may be singular)
            root = evecs * evals.clamp_min(0).sqrt().unsqueeze(-2)
            z = torch.randn(batch, dim, generator=gen, dtype=cov.dtype, device=cov.device)
            return z @ root.mT

        schedule = _as_schedule("theta", theta) or self.theta_schedule
        x = draw(self.x0_set, self.n) if x0 is None else torch.as_tensor(x0).expand(batch, self.n)
        xs, ys, us, ths = [x], [], [], []
        for k in range(steps):
            u = self.input_at(k, batch)
            th = None
            if self.parameters is not None:
                th = self.theta_nominal if schedule is None else schedule(k)
                th = torch.as_tensor(th, dtype=x.dtype, device=x.device)
                th = th.expand(batch, th.shape[-1])
            w = draw(self.process_noise, self.n) + gauss(self.process_cov, self.n)
            x = self.f(x, u, th) + w
            v = draw(self.measurement_noise, self.m) + gauss(self.measurement_cov, self.m)
            y = self.h(x) + v
            xs.append(x)
            ys.append(y)
            us.append(u)
            ths.append(th)
        return Trajectory(
            x=torch.stack(xs, 1),
            y=torch.stack(ys, 1),
            u=None if self.inputs is None else torch.stack(us, 1),
            theta=None if self.parameters is None else torch.stack(ths, 1),
        )


def _check_cov(name: str, cov: Tensor | None, dim: int) -> Tensor | None:
    if cov is None:
        return None
    c = torch.as_tensor(cov, dtype=torch.float64)
    if c.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape ({dim}, {dim}), got {tuple(c.shape)}")
    if not torch.allclose(c, c.mT) or torch.linalg.eigvalsh(c).min() < 0:
        raise ValueError(f"{name}: must be symmetric positive semidefinite")
    return c
