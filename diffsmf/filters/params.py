"""Learnable hyperparameters of the filters that are not the noise bounds of every filter.

`register_minkowski_scale` and `scaled_minkowski_sum`: the learnable factor of the
ellipsoidal filters' (CDSMF, ESMF) Minkowski-sum weight.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.utils import check_half_widths, check_strictly_positive, register_positive

__all__ = [
    "DEFAULT_STIRLING_FACTOR",
    "register_minkowski_scale",
    "register_remainder",
    "register_remainder_margin",
    "register_stirling_step",
    "scaled_minkowski_sum",
    "stirling_steps",
]


def register_minkowski_scale(module: nn.Module, value: Any) -> None:
    """Validate and register the learnable scalar ``minkowski_scale`` (> 0, finite).

    ``minkowski_scale = scale * softplus(raw)`` (`register_positive`):
    positive whatever the raw value, and exactly the given value at construction (softplus of
    the initial raw is exactly 1 in float32 and float64). Used by the ellipsoidal filters
    (CDSMF, ESMF) through `scaled_minkowski_sum`. Raises ``ValueError`` naming
    ``minkowski_scale`` for 0, negative, NaN, infinite or non-scalar values.
    """
    v = check_strictly_positive("minkowski_scale", value)
    register_positive(module, "minkowski_scale", v.clone())


def scaled_minkowski_sum(E1: Any, E2: Any, method: str, scale: Tensor) -> Any:
    """``E1 (+) E2`` with the weight ``p = rule_p * scale`` of ``S(p) = (1 + 1/p) S1 + (1 + p) S2``.

    ``rule_p = minkowski_weight(S1, S2, method)`` is the per-step rule (``"trace"`` or
    ``"volume"``); every ``p > 0`` gives an outer bound, so the factor ``scale > 0`` never
    costs the guarantee. ``scale == 1`` reproduces ``E1.minkowski_sum(E2, method)`` bit for bit
    (``x * 1.0 == x`` in IEEE arithmetic). Both operands are ellipsoids (positive definite).
    A weight that is not finite and positive (shapes that overflowed) is replaced by 1.
    """
    from diffsmf.sets.ellipsoid import minkowski_weight

    rule_p = minkowski_weight(E1.shape, E2.shape, method)
    p = rule_p * scale
    # an overflowed / underflowed rule (shapes beyond 1e150: the set is diverging) gives
    # p = 0, inf or NaN; any p > 0 is an outer bound, and the guard flags the set
    p = torch.where(torch.isfinite(p) & (p > 0), p, torch.ones_like(p))
    return E1.minkowski_sum(E2, p=p)



#: Default Stirling step of the linearising filters, relative to the set: ``h_j = 0.5 r_j`` with
#: ``r`` the half-widths of the interval hull of the set being linearised (Wang et al. 2022
#: give no value). Relative, so that a change of state units scales the step with the set
#: (scale invariance, docs/which_filter.md); an absolute step (a number in state units, the
#: earlier default 0.1) is still accepted.
DEFAULT_STIRLING_FACTOR = 0.5


def register_stirling_step(module: torch.nn.Module, value: float | Tensor | None, n: int) -> None:
    """Validate and register the learnable Stirling step ``[n]`` (Wang et al. 2022, eq. 12-13).

    ``value=None`` (the filters' default): relative mode, ``module.stirling_relative = True``,
    the registered ``stirling_step`` is the factor (default `DEFAULT_STIRLING_FACTOR`)
    and the step used is ``stirling_step * r`` with ``r`` the set's hull half-widths
    (`stirling_steps`). A number or tensor: an absolute step in state units, as given.
    """
    module.stirling_relative = value is None
    h = DEFAULT_STIRLING_FACTOR if value is None else value
    h = check_half_widths("stirling_step", h, n, positive=True)
    register_positive(module, "stirling_step", h)


def stirling_steps(filt: torch.nn.Module, c: Tensor, radius: Tensor) -> Tensor:
    """The Stirling step ``h [..., n]`` that ``filt`` uses about ``c [..., n]`` on a set with
    hull half-widths ``radius [..., n]``: ``filt.stirling_step`` itself (absolute mode) or
    ``filt.stirling_step * max(radius, 1e-8 |c|)`` (relative mode; a flat direction falls
    back to a step relative to the centre, and to 1e-150 at 0). Both relative choices scale
    with the state's units, so the slopes of the scaled system are the scaled slopes. The
    radius enters without gradient (a choice of expansion, like the discrete choices of the
    sets; the factor ``stirling_step`` keeps its gradient), so a diverged element's infinite
    radius cannot reach the gradients of the others."""
    if not getattr(filt, "stirling_relative", False):
        return filt.stirling_step
    with torch.no_grad():
        r = torch.maximum(radius, 1e-8 * c.abs()).clamp(min=1e-150)
        r = r.nan_to_num(nan=1.0, posinf=1.0)  # a diverged element: 1 (r >= 1e-150)
    return filt.stirling_step * r


def register_remainder(module: torch.nn.Module, spec: Any, n: int) -> None:
    """Validate ``remainder`` (a `diffsmf.linearize.RemainderBound` or its name, see
    `diffsmf.linearize.resolve_remainder`) and set ``module.remainder`` (the resolved name)
    and ``module.remainder_fn`` (the bound the steps call).

    ``"auto"``: the Wang et al. 2022 vertex method (``"dc-vertices"``) up to
    `AUTO_VERTEX_MAX_N` states, then the vertex-free bounds
    (``"lagrange"`` up to `AUTO_LAGRANGE_MAX_N`, ``"mean-value"``
    above; 2^n vertices are out of reach at n = 16, 32). Every choice is guaranteed.
    """
    from diffsmf.linearize import resolve_remainder

    module.remainder, module.remainder_fn = resolve_remainder(spec, n)


def register_remainder_margin(module: torch.nn.Module, value: float | Tensor, n: int) -> None:
    """Validate and register the learnable remainder margin ``m [n]`` (>= 0).

    The prediction remainder box becomes ``[lo - m, hi + m]`` (`add_remainder_margin`):
    an inflation for unmodelled dynamics and model error. The guarantee needs the computed
    remainder, so the margin can only add to it, never shrink it; 0 gives exactly the filter
    without it. It enters the predicted set the same way the process-noise box does; it is
    kept separate because the noise bound is a property of the data and the margin one of the
    model.

    ``margin = scale * softplus(raw)`` (`register_positive`), so it stays
    >= 0 and a component that starts at 0 stays exactly 0 (tune it from a positive start). A
    scalar broadcasts to ``[n]``. Raises ``ValueError`` for negative or NaN values or a shape
    other than ``[]``, ``[1]`` or ``[n]``.
    """
    m = check_half_widths("remainder_margin", value, n)
    register_positive(module, "remainder_margin", m)
