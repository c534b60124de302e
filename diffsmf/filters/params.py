"""Learnable hyperparameters of the filters that are not the noise bounds of every filter.

`register_minkowski_scale` and `scaled_minkowski_sum`: the learnable factor of the
ellipsoidal filters' (CDSMF, ESMF) Minkowski-sum weight.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.utils import check_strictly_positive, register_positive

__all__ = ["register_minkowski_scale", "scaled_minkowski_sum"]


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

