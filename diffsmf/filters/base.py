"""Filter contract shared by every filter: state, result and the predict/update loop.

``forward(y, u)`` is exactly: for each k, ``predict(state, u[:, k-1])`` then
``update(state, y[:, k-1])`` (DESIGN.md). Subclasses implement ``initial_state``,
``predict`` and ``_update``; NaN handling and result assembly live here once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.sets.base import ConvexSet, align, stack, where
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System
from diffsmf.utils import Positive, StrictlyPositive, check_strictly_positive, register_positive

__all__ = [
    "FilterResult",
    "FilterState",
    "SetFilter",
    "StrictlyPositive",
    "register_minkowski_scale",
    "scaled_minkowski_sum",
]


@dataclass(frozen=True)
class FilterState:
    """Online filter state.

    set: current set, batch shape ``[B]``; consistent: ``[B]`` bool (False when the last
    measurement did not meet the predicted set); extras: filter-specific tensors
    (e.g. ``"covariance" [B, n, n]``).
    """

    set: ConvexSet
    consistent: Tensor
    extras: dict[str, Tensor] = field(default_factory=dict)

    def replace(self, **kw: Any) -> FilterState:
        d = {"set": self.set, "consistent": self.consistent, "extras": self.extras}
        d.update(kw)
        return FilterState(**d)


@dataclass(frozen=True)
class FilterResult:
    """Sets over time.

    sets: batch shape ``[B, T+1]`` (index 0 = initial set, k = after ``y_k``);
    center, lower, upper: ``[B, T+1, n]``; volume: ``[B, T+1]``; consistent: ``[B, T+1]``
    bool; extras: stacked filter-specific tensors, e.g. ``"covariance" [B, T+1, n, n]``.
    """

    sets: ConvexSet
    center: Tensor
    lower: Tensor
    upper: Tensor
    volume: Tensor
    consistent: Tensor
    extras: dict[str, Tensor] = field(default_factory=dict)

    @property
    def covariance(self) -> Tensor | None:
        return self.extras.get("covariance")


def _pad_and_stack(sets: list[ConvexSet]) -> ConvexSet:
    """Stack along a new dim 1; zonotopes with differing generator counts are zero-padded."""
    return stack(align(sets), dim=1)


class SetFilter(nn.Module):
    """Base class of every filter (set-membership or Kalman).

    Learnable hyperparameters shared by all filters: ``process_noise [n]`` and
    ``measurement_noise [m]``, the half-widths of box noise bounds centred at the system's
    noise centres (default: the half-widths of the interval hulls of the system's noise sets).

    Args:
        system: the :class:`~diffsmf.systems.System` to filter.
        process_noise, measurement_noise: half-width overrides ``[n]`` / ``[m]``.
        skip_nan: skip the update of a batch element whose measurement has NaN (else raise).
    """

    process_noise = Positive()
    measurement_noise = Positive()

    def __init__(
        self,
        system: System,
        *,
        process_noise: Tensor | None = None,
        measurement_noise: Tensor | None = None,
        skip_nan: bool = False,
        learn_noise: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(system, System):
            raise ValueError("system: must be a diffsmf.System")
        self.system = system
        self.skip_nan = skip_nan
        n, m = system.n, system.m
        dt = system.x0_set.dtype
        for name, s, dim, override in (
            ("process_noise", system.process_noise, n, process_noise),
            ("measurement_noise", system.measurement_noise, m, measurement_noise),
        ):
            if s is None:
                c, r = torch.zeros(dim, dtype=dt), torch.zeros(dim, dtype=dt)
            else:
                hull = s.interval_hull()
                c, r = hull.center.detach(), hull.radius.detach()
            if override is not None:
                r = torch.as_tensor(override, dtype=dt).expand(dim).clone()
            register_positive(self, name, r, learnable=learn_noise)
            self.register_buffer(f"{name}_center", c.clone())

    # ------------------------------------------------------------------ noise sets
    def process_noise_box(self) -> Interval:
        """Current process-noise box W ``[n]`` (differentiable in ``process_noise``)."""
        c, r = self.process_noise_center, self.process_noise
        return Interval(c - r, c + r)

    def measurement_noise_box(self) -> Interval:
        """Current measurement-noise box V ``[m]`` (differentiable in ``measurement_noise``)."""
        c, r = self.measurement_noise_center, self.measurement_noise
        return Interval(c - r, c + r)

    # ------------------------------------------------------------------ contract
    def initial_state(self, batch: int | None = None) -> FilterState:
        """State at k = 0 (the system's initial set), batch shape ``[batch]``."""
        x0 = self.system.x0_set
        b = 1 if batch is None else batch
        return FilterState(
            set=x0.expand(b), consistent=torch.ones(b, dtype=torch.bool, device=x0.device)
        )

    def predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Time update with input ``u [B, p]`` (the input that drives x_{k-1} -> x_k)."""
        raise NotImplementedError

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update with finite ``y [B, m]``; sets ``consistent``."""
        raise NotImplementedError

    def update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update with ``y [B, m]``; NaN rows raise or (``skip_nan``) are skipped."""
        bad = torch.isnan(y).any(-1)
        if not bad.any():
            return self._update(state, y)
        if not self.skip_nan:
            raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
        new = self._update(state, torch.where(bad.unsqueeze(-1), torch.zeros_like(y), y))
        keep = ~bad
        extras = {
            k: torch.where(keep.reshape(keep.shape + (1,) * (v.dim() - 1)), v, state.extras[k])
            for k, v in new.extras.items()
            if k in state.extras
        }
        return FilterState(
            set=where(keep, new.set, state.set),
            consistent=torch.where(keep, new.consistent, state.consistent),
            extras={**new.extras, **extras},
        )

    def forward(self, y: Tensor, u: Tensor | None = None) -> FilterResult:
        """Filter measurements ``y [B, T, m]`` (inputs ``u [B, T, p]``) -> :class:`FilterResult`."""
        y = self._check_y(y)
        B, T, _ = y.shape
        if u is not None and (u.dim() != 3 or u.shape[:2] != (B, T)):
            raise ValueError(f"u: expected shape [{B}, {T}, p], got {tuple(u.shape)}")
        state = self.initial_state(batch=B)
        states = [state]
        for k in range(T):
            state = self.predict(state, None if u is None else u[:, k])
            state = self.update(state, y[:, k])
            states.append(state)
        return self.collect(states)

    def collect(self, states: list[FilterState]) -> FilterResult:
        """Assemble a :class:`FilterResult` from the per-step states."""
        sets = _pad_and_stack([s.set for s in states])
        hull = sets.interval_hull()
        extras = {
            k: torch.stack([s.extras[k] for s in states], 1)
            for k in states[-1].extras
            if all(k in s.extras for s in states)
        }
        return FilterResult(
            sets=sets,
            center=sets.center,
            lower=hull.lower,
            upper=hull.upper,
            volume=sets.volume(),
            consistent=torch.stack([s.consistent for s in states], 1),
            extras=extras,
        )

    def _check_y(self, y: Tensor) -> Tensor:
        dt = self.system.x0_set.dtype
        y = torch.as_tensor(y, dtype=dt) if not isinstance(y, Tensor) else y
        if y.dim() == 2:
            y = y.unsqueeze(0)
        if y.dim() != 3 or y.shape[-1] != self.system.m:
            raise ValueError(f"y: expected shape [B, T, {self.system.m}], got {tuple(y.shape)}")
        if torch.isinf(y).any():
            raise ValueError("y: contains inf")
        if torch.isnan(y).any() and not self.skip_nan:
            raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
        return y


# ---------------------------------------------------------------------------- Minkowski weights
def register_minkowski_scale(module: nn.Module, value: Any) -> None:
    """Validate and register the learnable scalar ``minkowski_scale`` (> 0, finite).

    ``minkowski_scale = scale * softplus(raw)`` (:func:`~diffsmf.utils.register_positive`):
    positive whatever the raw value, and exactly the given value at construction (softplus of
    the initial raw is exactly 1 in float32 and float64). Used by the ellipsoidal filters
    (CDSMF, ESMF) through :func:`scaled_minkowski_sum`. Raises ``ValueError`` naming
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
    """
    from diffsmf.sets.ellipsoid import minkowski_weight

    rule_p = minkowski_weight(E1.shape, E2.shape, method)
    return E1.minkowski_sum(E2, p=rule_p * scale)
