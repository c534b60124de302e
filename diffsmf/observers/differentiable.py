r"""Differentiable observer design: the seed-004 LMI as a ``cvxpylayers`` layer (optional extra).

`DifferentiableObserverDesign` solves, at a FIXED decay rate alpha, the same SDP as
`design_lipschitz_observer` with ``objective="bound"`` (the cvxpy
problem is built by the same `diffsmf.observers.lmi.lmi_problem`, so there is one home for
the LMI: the reduced 2-block LMI, equivalent to the 3-block one, see lmi.py)::

    min mu  s.t.  R(P, Y, lambda, nu; A, C, gamma^2, alpha) < -margin I,  P >= I,
                  (lambda - nu)(mu - nu) >= nu^2,  [|Y|_2 <= max_gain, if given]

and returns L = P^-1 Y (Wang et al. 2009, eq. 22) and the guaranteed bound (module docstring of
lmi.py) ``bound = eps sqrt(mu / (alpha lambda_min(P)))`` computed in torch from the layer's outputs,
so ``bound.backward()`` gives d bound / d (A, C, lipschitz, alpha) through the implicit
differentiation of the conic program (diffcp), and d bound / d eps = bound / eps exactly (eps only
scales the bound).

Why a fixed alpha: the design searches alpha outside the SDP (a few secant steps on the
dual sensitivity, lmi.py). At the searched optimum alpha* the bound is stationary in alpha,
so by the envelope theorem the gradient of the optimal-alpha bound w.r.t. (A, C, gamma)
equals the fixed-alpha gradient at alpha* — pass ``alpha=design_lipschitz_observer(...).decay``.
alpha is also a layer input, so its own gradient (~0 at alpha*) is available.

Well-posedness: when the bound infimum is only approached by L -> infinity (high-gain designs,
e.g. the Wang et al. 2009 structured example), the SDP solution is not attained and its derivative
is meaningless; cap the gain with ``max_gain`` (as in the design function) to get a
well-posed, differentiable problem. The layer uses diffcp's default SCS backend (tight ``eps``);
diffcp's Clarabel backend gave wrong derivatives in our checks. The layer output is for
gradient-based design; certify a final gain with `analyze_observer_gain`.
"""

from __future__ import annotations

import numpy as np
import torch

from diffsmf.observers.lmi import lmi_problem, structure_keys

__all__ = ["DifferentiableObserverDesign"]

_PARAMS = ("A", "C", "g2", "alpha", "margin")
_VARS = ("P", "Y", "lam", "mu")


def _require_cvxpylayers():
    try:
        from cvxpylayers.torch import CvxpyLayer
    except ImportError as exc:  # optional extra
        raise ImportError(
            "DifferentiableObserverDesign needs cvxpylayers: pip install diffsmf[diff]"
        ) from exc
    return CvxpyLayer


class DifferentiableObserverDesign(torch.nn.Module):
    """Observer gain and guaranteed bound as differentiable functions of (A, C, gamma, eps).

    n states, l outputs; alpha > 0 the fixed decay rate (continuous) or in (0, 1] (discrete);
    structure=(B_f [n, nf], H [h, n]) fixed (default B_f = H = I); max_gain caps |L|_2 (via
    |Y|_2 <= max_gain, as design_lipschitz_observer). solver_args go to diffcp (SCS).
    """

    def __init__(
        self,
        n: int,
        l: int,
        *,
        alpha: float,
        time: str = "continuous",
        structure=None,
        max_gain: float | None = None,
        margin: float = 1e-6,
        solver_args: dict | None = None,
    ) -> None:
        super().__init__()
        CvxpyLayer = _require_cvxpylayers()
        if n < 1 or l < 1:
            raise ValueError(f"n and l must be >= 1, got n={n}, l={l}")
        if time not in ("continuous", "discrete"):
            raise ValueError(f"time must be 'continuous' or 'discrete', got {time!r}")
        if not alpha > 0 or (time == "discrete" and alpha > 1):
            raise ValueError(f"alpha must be in (0, inf) (continuous) or (0, 1], got {alpha}")
        if max_gain is not None and not max_gain > 0:
            raise ValueError(f"max_gain must be positive, got {max_gain}")
        Bf, H = (np.eye(n), np.eye(n)) if structure is None else structure
        Bf, H = np.asarray(Bf, dtype=float), np.asarray(H, dtype=float)
        if Bf.ndim != 2 or Bf.shape[0] != n:
            raise ValueError(f"structure B_f must be [n={n}, nf], got shape {Bf.shape}")
        if H.ndim != 2 or H.shape[1] != n:
            raise ValueError(f"structure H must be [h, n={n}], got shape {H.shape}")
        self.n, self.l, self.time = n, l, time
        self.alpha, self.margin = float(alpha), float(margin)
        self.max_gain = None if max_gain is None else float(max_gain)
        self.register_buffer("Bf", torch.as_tensor(Bf, dtype=torch.float64))
        self.register_buffer("HtH", torch.as_tensor(H.T @ H, dtype=torch.float64))
        # same SDP as design_lipschitz_observer (uncached copy: the layer owns its problem)
        prob, par, var, _ = lmi_problem.__wrapped__(n, l, time, False, max_gain is not None,
                                                    *structure_keys(Bf, H))
        names = _PARAMS + (("kappa",) if max_gain is not None else ())
        args = dict(eps=1e-10, max_iters=100_000)
        args.update(solver_args or {})
        self.layer = CvxpyLayer(
            prob, [par[k] for k in names], [var[k] for k in _VARS], solver_args=args
        )

    def forward(self, A, C, lipschitz, approx_error, *, alpha=None, full: bool = False):
        """A [..., n, n], C [..., l, n], lipschitz [...], approx_error [...] (broadcast; float64).

        Returns (L [..., n, l], bound [...]); with full=True also P [..., n, n] and mu [...].
        alpha (tensor, optional) overrides the fixed decay rate (differentiable).
        """
        A, C, gamma, eps, alpha = self._check(A, C, lipschitz, approx_error, alpha)
        batch = torch.broadcast_shapes(A.shape[:-2], C.shape[:-2], gamma.shape, eps.shape)
        n, l = self.n, self.l
        g2 = (gamma**2).expand(batch)  # eq. 2: gamma^2 (H'H is a constant of the problem)
        ins = [A.expand(*batch, n, n), C.expand(*batch, l, n)]
        if batch:  # cvxpylayers takes one batch dim: flatten, solve, restore
            ins = [x.reshape(-1, *x.shape[-2:]) for x in ins] + [g2.reshape(-1)]
        else:
            ins.append(g2)
        B = ins[0].shape[0] if batch else None
        consts = [alpha, torch.tensor(self.margin, dtype=torch.float64)]
        if self.max_gain is not None:
            consts.append(torch.tensor(self.max_gain, dtype=torch.float64))
        if B is not None:
            consts = [c.expand(B, *c.shape) for c in consts]
        try:
            P, Y, _lam, mu = self.layer(*ins, *consts)
        except Exception as exc:  # noqa: BLE001 - diffcp.SolverError etc.: say what it means
            raise RuntimeError(
                f"observer LMI not solved at alpha={float(alpha):g} ({exc}); the LMI may be "
                "infeasible at this decay rate / max_gain: check design_lipschitz_observer"
            ) from exc
        P = 0.5 * (P + P.transpose(-1, -2))
        L = torch.linalg.solve(P, Y)  # Wang et al. 2009, eq. 22: L = P^-1 Y
        p_min = torch.linalg.eigvalsh(P)[..., 0]
        mu = mu.reshape(batch)
        p_min = p_min.reshape(batch)
        L, P = L.reshape(*batch, n, l), P.reshape(*batch, n, n)
        bound = eps * torch.sqrt(mu / (alpha * p_min))  # limsup |e| (lmi.py module docstring)
        return (L, bound, P, mu) if full else (L, bound)

    def _check(self, A, C, lipschitz, approx_error, alpha):
        f64 = dict(dtype=torch.float64)
        A, C = torch.as_tensor(A, **f64), torch.as_tensor(C, **f64)
        gamma, eps = torch.as_tensor(lipschitz, **f64), torch.as_tensor(approx_error, **f64)
        alpha = torch.as_tensor(self.alpha if alpha is None else alpha, **f64)
        if A.ndim < 2 or A.shape[-2:] != (self.n, self.n):
            raise ValueError(f"A must be [..., {self.n}, {self.n}], got shape {tuple(A.shape)}")
        if C.ndim < 2 or C.shape[-2:] != (self.l, self.n):
            raise ValueError(f"C must be [..., {self.l}, {self.n}], got shape {tuple(C.shape)}")
        if not torch.all(torch.isfinite(gamma) & (gamma >= 0)):
            raise ValueError("lipschitz must be finite and >= 0")
        if not torch.all(torch.isfinite(eps) & (eps >= 0)):
            raise ValueError("approx_error must be finite and >= 0")
        if alpha.ndim != 0 or not alpha > 0:
            raise ValueError(f"alpha must be a positive scalar, got {alpha}")
        return A, C, gamma, eps, alpha
