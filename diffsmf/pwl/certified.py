"""A fitted SCPLNN as the dynamics of a guaranteed filter, with its certified error.

The chain of guarantees::

    true step   x+ = g(x, u) + w,          w in W
    model step  x+ = f(x, u) + w',         w' in W ⊕ [-e, e]      (f the SCPLNN)

holds for every x in the model's domain D when ``|g_i - f_i| <= e_i`` on D. That bound is an
`ErrorCertificate`, computed per simplex by `certify_error` from g (its values at
the partition's vertices and a bound of its Hessian), not measured on samples. The System built
by `as_system` adds ``e`` to the process noise and bounds the model over the filter's sets
with `SCPLNN.interval_enclosure` in the domain exit mode: a set whose box leaves D gets NaN
bounds, so the filter flags that trajectory unbounded (guarantee lost, said per trajectory)
instead of using the model where the certificate says nothing. While the sets stay in D, every
state consistent with the true system, the noise bounds and the data stays in them (by induction
over the steps: ``x_k`` in ``X_k ⊂ D``, so the certificate applies at ``x_k``).

Extension point: the filters' guaranteed remainders treat any ``f`` or ``h`` (``nn.Module`` or
callable) with a method ``interval_enclosure(lo, hi, *rest) -> (val_lo, val_hi, jac_lo,
jac_hi)`` as an opaque leaf: ``lo, hi [..., d]`` bound its first argument, ``rest`` are its other
arguments as points (``u``, ``theta`` for a System's ``f``), ``val_* [..., k]`` enclose its value
over the box and ``jac_* [..., k, d]`` its (generalised) Jacobian w.r.t. the first argument;
NaN marks an element for which no bound exists. The remainder is then the first-order
(mean-value) one: ``r(x) in ([J] - J)(box - c)``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.pwl.scplnn import SCPLNN

__all__ = ["ErrorCertificate", "SCPLNNDynamics", "as_system", "certify_error",
           "simplex_error", "simplex_hessian_bound"]

_F64 = torch.float64


def _fingerprint(model: SCPLNN) -> str:
    """SHA-256 of the partition and the weights (a certificate belongs to one model)."""
    h = hashlib.sha256()
    for t in (model.vertices, model.simplices, model.weight.detach()):
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class ErrorCertificate:
    """``sup_{x in D} |g_i(x) - f_i(x)| <= bound_i`` for the model f with this fingerprint.

    bound ``[p]``; lower / upper ``[n]``: the bounding box of the domain D (D itself is the
    union of the model's simplices, the box for box domains); method: how the bound was
    obtained (``"certified"``: `certify_error`; ``"given"``: stated by the user,
    `given`, checked only for belonging to the model and against samples).
    """

    bound: Tensor
    lower: Tensor
    upper: Tensor
    fingerprint: str
    method: str

    @classmethod
    def given(cls, model: SCPLNN, bound: Any) -> ErrorCertificate:
        """A bound the user vouches for (e.g. from a physical argument), attached to ``model``."""
        b = torch.as_tensor(bound, dtype=_F64).reshape(-1).expand(model.n_outputs).clone()
        return cls(b, model.lower.clone(), model.upper.clone(), _fingerprint(model), "given")

    def check(self, model: SCPLNN, samples: tuple[Any, Any] | None = None) -> None:
        """ValueError (naming ``certificate``) unless the bound is finite, >= 0, of shape
        ``[p]`` and was made for this very model (same partition and weights); with
        ``samples = (X [N, n], Y [N, p])`` also unless every sample inside the domain is
        within the bound (plus a 1e-9 relative rounding allowance)."""
        b = self.bound
        if b.shape != (model.n_outputs,) or not bool(torch.isfinite(b).all() & (b >= 0).all()):
            raise ValueError(f"certificate: bound must be finite, >= 0, of shape "
                             f"[{model.n_outputs}], got {b.tolist()}")
        if self.fingerprint != _fingerprint(model):
            raise ValueError("certificate: made for another model (the partition or the "
                             "weights changed since); certify the model again")
        if samples is None:
            return
        X, Y = (torch.as_tensor(a, dtype=_F64) for a in samples)
        X, Y = X.reshape(-1, model.n_inputs), Y.reshape(-1, model.n_outputs)
        _, inside = model.locate(X)
        with torch.no_grad():
            err = (model(X[inside]) - Y[inside]).abs()
        over = err > b * (1 + 1e-9) + 1e-12
        if bool(over.any()):
            raise ValueError(
                f"certificate: contradicted by {int(over.any(-1).sum())} of {int(inside.sum())} "
                f"samples (error up to {err.amax(0).tolist()} > bound {b.tolist()})")


def simplex_hessian_bound(fn: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """Entrywise bound ``[M, p, n, n]`` of |Hessian of fn| over each simplex ``V [M, n+1, n]``,
    by interval arithmetic over the simplex's bounding box (second-order interval jets,
    ``diffsmf.linearize.jets``; fn must be built from the operations they support)."""
    from diffsmf.linearize.jets import interval_hessian
    from diffsmf.sets import Interval

    def bound(V: Tensor) -> Tensor:
        Hi = interval_hessian(fn, Interval(V.amin(-2), V.amax(-2)))
        return torch.maximum(Hi.lower.abs(), Hi.upper.abs())

    return bound


def certify_error(model: SCPLNN, fn: Callable[[Tensor], Tensor],
                  hess_bound: Callable[[Tensor], Tensor] | None = None) -> ErrorCertificate:
    """Certified ``sup_D |fn_i - model_i|`` per output (an `ErrorCertificate`).

    Per simplex S with vertices v_j and model weights W_j: ``|fn - model| <= max_j |fn(v_j) -
    W_j| + (1/8) r' H r`` with ``r [n]`` the coordinate ranges of S and ``H [n, n]`` an
    entrywise bound of |Hessian of fn_i| on S. Proof: model minus the linear interpolant I of
    fn is affine on S (bounded by its vertex values); Taylor at x in S with ``d_j = v_j - x``
    and ``sum_j lam_j d_j = 0`` gives ``|I(x) - fn(x)| <= (1/2) sum_ab H_ab sum_j lam_j
    |d_ja| |d_jb| <= (1/2) sum_ab H_ab sqrt(Var_a Var_b)``, and a variance of values in a
    range r is at most r^2 / 4 (Popoviciu). Anisotropic: a map curved along one axis only
    needs short edges along that axis only. Rounding: times (1 + 1e-9) plus 1e-12.

    Args:
        fn: the true map ``[..., n] -> [..., p]`` (torch ops).
        hess_bound: ``V [M, n+1, n] -> [M, p, n, n]`` entrywise Hessian bounds; default
            `simplex_hessian_bound` (interval arithmetic).
    """
    with torch.no_grad():
        err = simplex_error(model.vertices[model.simplices], model.weight[model.simplices],
                            fn, hess_bound or simplex_hessian_bound(fn))
    return ErrorCertificate(err.amax(0), model.lower.clone(), model.upper.clone(),
                            _fingerprint(model), "certified")


def simplex_error(V: Tensor, W: Tensor, fn: Callable[[Tensor], Tensor],
                  hess_bound: Callable[[Tensor], Tensor]) -> Tensor:
    """Per-simplex bound ``[M, p]`` of `certify_error`; ``V [M, n+1, n]`` simplex
    vertices, ``W [M, n+1, p]`` their weights (usable as ``fit_scplnn(region_bound=...)``)."""
    with torch.no_grad():
        vert = (fn(V).reshape(W.shape) - W).abs().amax(-2)  # [M, p]
        r = V.amax(-2) - V.amin(-2)  # [M, n]
        H = hess_bound(V).reshape(*W.shape[:1], W.shape[-1], V.shape[-1], V.shape[-1])
        curv = 0.125 * torch.einsum("ma,mpab,mb->mp", r, H, r)
        return (vert + curv) * (1 + 1e-9) + 1e-12


class SCPLNNDynamics(nn.Module):
    """``f(x, u, theta) = model([x, u])``: an SCPLNN as a System's dynamics.

    Points outside the domain are evaluated on the clamped model (centres and difference
    stencils of a filter step never raise); box enclosures end at the domain: a box leaving it
    gives NaN bounds (`interval_enclosure`), because the certified error holds on the
    domain only. ``theta`` is ignored (no mismatched parameters).

    Args:
        model: an SCPLNN ``R^(n+p) -> R^n`` (states first, then inputs).
        n_inputs: p (default 0: an autonomous model ``R^n -> R^n``).
    """

    def __init__(self, model: SCPLNN, n_inputs: int = 0):
        super().__init__()
        if not isinstance(model, SCPLNN):
            raise ValueError(f"model: expected an SCPLNN, got {type(model).__name__}")
        if n_inputs < 0 or model.n_inputs != model.n_outputs + n_inputs:
            raise ValueError(f"model: maps R^{model.n_inputs} -> R^{model.n_outputs}; a step "
                             f"with {n_inputs} inputs needs R^(n+{n_inputs}) -> R^n")
        self.model = model
        self.n_inputs = n_inputs
        #: the model's `ErrorCertificate` once `as_system` added it to the process noise
        self.certificate: ErrorCertificate | None = None

    def _z(self, x: Any, u: Tensor | None) -> Any:
        if self.n_inputs == 0:
            return x
        if u is None:
            raise ValueError(f"u: the model takes {self.n_inputs} inputs; pass u")
        return torch.cat([x, u.to(_F64).expand(*x.shape[:-1], self.n_inputs)], -1)

    def forward(self, x: Any, u: Tensor | None = None, theta: Tensor | None = None) -> Any:
        """``x [..., n]`` (a tensor or a first-order interval jet) -> ``[..., n]``."""
        z = self._z(x, u)
        if isinstance(z, Tensor):
            return self.model(z, outside="clamp")
        return self.model(z, outside="error")  # jets: enclosures, NaN outside the domain

    def interval_enclosure(self, lo: Tensor, hi: Tensor, u: Tensor | None = None,
                           theta: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Exact enclosures over ``x in [lo, hi] [..., n]`` at the input ``u [..., p]``:
        ``(val_lo, val_hi [..., n], jac_lo, jac_hi [..., n, n])`` (Jacobian w.r.t. x; NaN
        where the box leaves the domain). See ``SCPLNN.interval_enclosure``."""
        n = self.model.n_outputs
        zl, zh = self._z(lo, u), self._z(hi, u)
        vl, vh, jl, jh = self.model.interval_enclosure(zl, zh, outside="error", check=False)
        return vl, vh, jl[..., :n], jh[..., :n]


def as_system(
    model: SCPLNN,
    h: Callable[[Tensor], Tensor],
    x0_set: Any,
    process_noise: Any = None,
    measurement_noise: Any = None,
    *,
    certificate: ErrorCertificate,
    n_inputs: int = 0,
    samples: tuple[Any, Any] | None = None,
    name: str = "scplnn",
) -> Any:
    """A ``System`` whose dynamics are a fitted SCPLNN with its certified error.

    Args:
        model: the fitted SCPLNN, ``R^(n+p) -> R^n`` (states, then inputs).
        h: measurement function ``h(x [..., n]) -> [..., m]``.
        x0_set: initial set; must lie in the model's domain (ValueError otherwise).
        process_noise: the true system's process noise set W (None: zero).
        measurement_noise: measurement noise set V.
        certificate: `certify_error` (or `ErrorCertificate.given`) for this model;
            checked (`ErrorCertificate.check`), then ``[-bound, bound]`` is added to W.
        n_inputs: p, the inputs of the model (``f(x, u) = model([x, u])``).
        samples: optional ``(X, Y)`` that the certificate must not contradict.

    Returns:
        ``System(SCPLNNDynamics(model, n_inputs), h, x0_set, W ⊕ [-e, e], V)``. Filter it with
        a first-order remainder, e.g. ``HSNSMF(system, remainder="mean-value")`` (the model is
        piecewise linear: no Hessian). Guarantee: see the module docstring.
    """
    from diffsmf.sets import Interval
    from diffsmf.systems import System

    if not isinstance(certificate, ErrorCertificate):
        raise ValueError("certificate: expected an ErrorCertificate (certify_error(model, g) or "
                         f"ErrorCertificate.given(model, bound)), got {type(certificate).__name__}")
    f = SCPLNNDynamics(model, n_inputs)
    certificate.check(model, samples)
    f.certificate = certificate
    box = x0_set.interval_hull()
    tol = model.atol * (model.upper - model.lower)
    if bool(((box.lower < model.lower - tol) | (box.upper > model.upper + tol)).any()):
        raise ValueError(f"x0_set: its box {box.lower.tolist()}..{box.upper.tolist()} is not "
                         f"inside the model's domain {model.lower.tolist()}.."
                         f"{model.upper.tolist()}")
    e = certificate.bound
    err = Interval(-e, e)
    W = err if process_noise is None else process_noise.minkowski_sum(err)
    return System(f, h, x0_set, W, measurement_noise, n_inputs=n_inputs or None, name=name)
