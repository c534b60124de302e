"""Jiang et al. 2016 radar tracking system (registered as ``"radar"``).

Jiang et al. 2016, sec. 3.1: a target moving at (nearly) constant velocity in the plane, tracked by
a radar at the origin measuring range and bearing every ``T = 1 s``::

    x_k = A x_{k-1} + Gamma (w_k + d_k),   w ~ N(0, Q),  d in F(0, D)      state [x1, v1, x2, v2]
    y_k = [sqrt(x1^2 + x2^2), atan2(x2, x1)] + v_k + e_k,   v ~ N(0, R),  e in F(0, E)

with ``Q = diag(0.5^2, 0.5^2)``, ``D = diag(0.8^2, 0.8^2)``, ``R = diag(20^2, 0.01^2)``,
``E = diag(30^2, 0.015^2)`` and ``x0 = [200, 12, 200, 10]``.

`System` adds process noise of dimension n directly, so both parts are
expressed in state space: the Gaussian part as ``Gamma Q Gamma'`` (positive semidefinite, which
``process_cov`` allows) and the bounded part as the ellipsoid ``F(0, Gamma D Gamma' + eps I)``.
``Gamma D Gamma'`` has rank 2; an `Ellipsoid` needs a positive definite
shape, so ``eps = 1e-9`` (a radius of 3e-5 m or m/s in the two degenerate directions) is added.
This only enlarges the noise set (it contains ``Gamma F(0, D)``), so every guarantee still holds;
``simulate`` draws the bounded noise from the enlarged set.

The paper does not give the initial set; we choose (stated in docs/combined.md)
``S0 = diag(20^2, 2^2, 20^2, 2^2)`` for the initial mean set ``F(x0, S0)`` and
``P0 = diag(10^2, 1^2, 10^2, 1^2)`` for the initial covariance (`radar_initial_cov`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.systems.system import System

__all__ = ["RADAR_X0", "radar", "radar_initial_cov", "radar_matrices"]

RADAR_X0 = (200.0, 12.0, 200.0, 10.0)
_S0_DIAG = (20.0**2, 2.0**2, 20.0**2, 2.0**2)
_P0_DIAG = (10.0**2, 1.0**2, 10.0**2, 1.0**2)
_EPS = 1e-9


def radar_matrices(T: float = 1.0) -> tuple[Tensor, Tensor]:
    """Transition ``A [4, 4]`` and noise gain ``Gamma [4, 2]`` of Jiang et al. 2016, sec. 3.1."""
    A = torch.tensor(
        [[1.0, T, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, T], [0.0, 0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )
    G = torch.tensor(
        [[T * T / 2, 0.0], [T, 0.0], [0.0, T * T / 2], [0.0, T]], dtype=torch.float64
    )
    return A, G


def radar_initial_cov() -> Tensor:
    """Our choice of the initial covariance ``P0 = diag(10^2, 1, 10^2, 1)`` ``[4, 4]``."""
    return torch.diag(torch.tensor(_P0_DIAG, dtype=torch.float64))


def _range_bearing(x: Tensor) -> Tensor:
    """Jiang et al. 2016, sec. 3.1 measurement: ``[..., 4] -> [..., 2]`` (range, bearing)."""
    x1, x2 = x[..., 0], x[..., 2]
    return torch.stack([torch.sqrt(x1 * x1 + x2 * x2), torch.atan2(x2, x1)], -1)


def radar(
    T: float = 1.0,
    initial_shape: Tensor | None = None,
    bounded: bool = True,
    gaussian: bool = True,
) -> System:
    """Jiang et al. 2016 radar tracking system.

    Args:
        T: sampling period (s).
        initial_shape: shape ``[4, 4]`` of the initial mean set ``F(x0, S0)``
            (default ``diag(20^2, 2^2, 20^2, 2^2)``).
        bounded: include the bounded noise parts D and E (else ``None``).
        gaussian: include the Gaussian parts Q and R (else ``None``).
    """
    from diffsmf.sets.ellipsoid import Ellipsoid

    A, G = radar_matrices(T)

    def diag(*v: float) -> Tensor:
        return torch.diag(torch.tensor(v, dtype=torch.float64))

    x0 = torch.tensor(RADAR_X0, dtype=torch.float64)
    S0 = diag(*_S0_DIAG) if initial_shape is None else initial_shape
    D = G @ diag(0.8**2, 0.8**2) @ G.mT + _EPS * torch.eye(4, dtype=torch.float64)
    E = diag(30.0**2, 0.015**2)
    Q = G @ diag(0.5**2, 0.5**2) @ G.mT
    R = diag(20.0**2, 0.01**2)

    def f(x: Tensor, u: Tensor | None, theta: Tensor | None) -> Tensor:
        return x @ A.mT  # Jiang et al. 2016, sec. 3.1, constant velocity

    return System(
        f,
        _range_bearing,
        Ellipsoid(x0, S0),
        Ellipsoid(torch.zeros(4, dtype=torch.float64), D) if bounded else None,
        Ellipsoid(torch.zeros(2, dtype=torch.float64), E) if bounded else None,
        process_cov=Q if gaussian else None,
        measurement_cov=R if gaussian else None,
        name="radar",
    )
