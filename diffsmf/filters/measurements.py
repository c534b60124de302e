"""Validation of the measurements a filter runs on: a log ``y [B, T, m]`` (with ``u``) for
``forward`` and one measurement ``y [B, m]`` for ``step``, each error naming the argument
and the fix (a one-output log given as ``[B, T]``, time-first logs, inf or NaN).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import torch
from torch import Tensor

from diffsmf.filters.state import FilterState
from diffsmf.utils import tracing

__all__ = ["check_finite_y", "check_log", "check_step_y", "measurements"]

#: Measurements with at most this many entries are checked for inf / NaN in Python (an
#: online step's ``y [1, m]``: 1 us instead of two tensor ops and a sync, about 11 us here).
_SMALL_Y = 64


def _y_tensor(y: Any, dtype: torch.dtype, device: torch.device | None) -> Tensor:
    """``y`` as a tensor; ``ValueError`` naming ``y`` when it is None or not numeric (NaN is
    left to the callers, which honour ``skip_nan``)."""
    try:
        return torch.as_tensor(y, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"y: cannot convert {type(y).__name__} to measurements ({exc})") from exc


def check_step_y(y: Any, state: FilterState, m: int, dtype: torch.dtype, skip_nan: bool) -> Tensor:
    """``y [B, m]`` for one step, as a ``dtype`` tensor on the state's device: shape (``B``
    from ``state.consistent [B]``; the system's ``m``), inf / NaN (`check_finite_y`). ``m``
    and ``dtype`` are passed in so that `streaming` reads them once per block."""
    c = state.consistent
    if not isinstance(y, Tensor) or y.dtype != dtype or y.device != c.device:
        y = _y_tensor(y, dtype, c.device)
    if y.shape != (*c.shape, m):
        expected = [*c.shape, m]
        raise ValueError(f"y: expected shape {expected} for this state, got {list(y.shape)}")
    return check_finite_y(y, skip_nan)


def check_finite_y(y: Tensor, skip_nan: bool) -> Tensor:
    """``y`` unchanged; inf raises, NaN raises unless ``skip_nan`` (host syncs)."""
    if y.numel() <= _SMALL_Y and y.is_cpu:  # online B = 1: no tensor ops
        values = y.tolist() if y.dim() == 2 else [y.reshape(-1).tolist()]  # [B, m] rows
        if all(map(math.isfinite, itertools.chain.from_iterable(values))):
            return y
    elif bool(torch.isfinite(y).all()):  # the common case: one check
        return y
    if torch.isinf(y).any():
        raise ValueError("y: contains inf")
    if not skip_nan:
        raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
    return y


def measurements(y: Any, m: int, dtype: torch.dtype, skip_nan: bool) -> Tensor:
    """``y [B, T, m]`` of ``forward`` (a ``[T, m]`` log gets ``B = 1``), checked once for the
    whole horizon (shape; inf / NaN unless traced)."""
    y = _y_tensor(y, dtype, None) if not isinstance(y, Tensor) else y
    given = tuple(y.shape)  # the shape the caller passed, for the message
    if y.dim() == 2:
        y = y.unsqueeze(0)
    if y.dim() != 3 or y.shape[-1] != m:
        raise ValueError(f"y: expected shape [B, T, {m}] (or [T, {m}] for one trajectory), got "
                         f"{given}{_y_hint(given, m)}")
    if tracing():  # value checks would sync with the host (torch.compile of forward)
        return y
    return check_finite_y(y, skip_nan)


def _y_hint(given: tuple[int, ...], m: int) -> str:
    """What a wrong shape of ``y`` most likely means, as a hint for its error message."""
    if m == 1 and len(given) == 2 and given[-1] != 1:
        return ("; with one output keep its dimension: y.unsqueeze(-1) for [B, T] "
                "measurements")
    if len(given) == 3 and m in given[:-1]:
        return "; the outputs go last: [B, T, m]"
    return ""


def check_log(y: Tensor, u: Any) -> None:
    """Name both ``y [B, T, m]`` and ``u [B, T, p]`` of ``forward`` when one of them has time
    first: ``u``'s leading dims are ``y``'s swapped (which of the two is transposed cannot
    be told from the shapes, so the message gives both).

    Raises:
        ValueError: starting with ``y:``, with both shapes as passed and the fix.
    """
    B, T = int(y.shape[0]), int(y.shape[1])
    shape = getattr(u, "shape", None)
    if B == T or shape is None or len(shape) != 3 or tuple(shape[:2]) != (T, B):
        return
    raise ValueError(
        f"y: shape {tuple(y.shape)} and u: shape {tuple(shape)} disagree on which dimension is "
        "time; both must be [B, T, ...] (trajectories first, then steps): transpose the one "
        "given as [T, B, ...] with .transpose(0, 1)"
    )
