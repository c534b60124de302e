"""The error envelope that a verified Lipschitz-observer design guarantees, ``sqrt(V(t) /
lambda_min(P))`` from the Lyapunov function of its LMI (`diffsmf.observers.lmi`), and its check
against simulated error trajectories.
"""

from __future__ import annotations

import numpy as np

from diffsmf.observers.lmi import ObserverDesign

__all__ = ["error_envelope", "simulate_error_check"]

def error_envelope(design: ObserverDesign, e0, t) -> np.ndarray:
    """Guaranteed |e(t)| bound from e(0) (`diffsmf.observers.lmi`): sqrt(V(t) / lambda_min(P)).

    e0 [..., n], t [T] (times, continuous; step indices, discrete) -> [..., T].
    """
    P, a = design.P, design.decay
    e0 = np.asarray(e0, float)
    V0 = np.einsum("...i,ij,...j->...", e0, P, e0)[..., None]
    t = np.asarray(t, float)
    decay = np.exp(-a * t) if design.time == "continuous" else (1 - a) ** t
    Vinf = design.mu * design.approx_error**2 / a
    V = decay * V0 + (1 - decay) * Vinf
    return np.sqrt(V / design.margins["P_min_eig"])


def simulate_error_check(
    design: ObserverDesign, steps: int = 2000, dt: float = 1e-3, batch: int = 64, seed: int = 0
) -> dict:
    """Simulate the error system with adversarial-ish admissible dphi and d; compare to envelope.

    dphi = gamma |H e| s(t) (unit s, random switching signs), d = eps on a random unit direction
    switched piecewise-constantly. Continuous time uses RK4 with the disturbances held per step.
    Returns {"max_ratio": max_t |e(t)| / envelope(t), "ok": max_ratio <= 1 + 1e-6}.
    """
    rng = np.random.default_rng(seed)
    if not design.feasible:
        raise ValueError("design must be feasible (status 'verified') to simulate")
    n = design.P.shape[0]
    A_L = design.closed_loop
    Bf, H = design.B_f, design.H
    nf = Bf.shape[1]
    e = rng.standard_normal((batch, n))
    e0 = e.copy()
    g, eps = design.lipschitz, design.approx_error
    ratio = 0.0
    hold = max(1, steps // 20)
    for k in range(steps):
        if k % hold == 0:
            s = rng.standard_normal((batch, nf))
            s /= np.linalg.norm(s, axis=-1, keepdims=True)
            dd = rng.standard_normal((batch, nf))
            dd *= eps / np.linalg.norm(dd, axis=-1, keepdims=True)

        def rhs(x, s=s, dd=dd):
            dphi = g * np.linalg.norm(x @ H.T, axis=-1, keepdims=True) * s
            return x @ A_L.T + (dphi + dd) @ Bf.T

        if design.time == "continuous":
            k1 = rhs(e)
            k2 = rhs(e + 0.5 * dt * k1)
            k3 = rhs(e + 0.5 * dt * k2)
            k4 = rhs(e + dt * k3)
            e = e + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            t = (k + 1) * dt
        else:
            e = rhs(e)
            t = k + 1
        env = error_envelope(design, e0, np.array([t]))[..., 0]
        ratio = max(ratio, float((np.linalg.norm(e, axis=-1) / env).max()))
    return {"max_ratio": ratio, "ok": ratio <= 1 + 1e-6}
