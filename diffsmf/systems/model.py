"""Model functions as users write them, adapted to the filters' convention.

The filters call the dynamics as ``f(x, u, theta)`` and the measurement as ``h(x)``. A user may
write ``f(x)``, ``f(x, u)`` or ``f(x, u, theta)``, as a function or as an ``nn.Module``
(``forward(x)``, ...); `as_dynamics` adapts them once, when the ``System`` is built, and
`diffsmf.systems.checks` runs both through the guarantee engine so that what the engine
cannot enclose is reported then, naming ``f`` or ``h``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

import torch
from torch import Tensor, nn

__all__ = [
    "Dynamics",
    "as_dynamics",
    "check_dtype",
    "check_module_dtype",
    "positional_arity",
]


def positional_arity(fn: Callable[..., Tensor]) -> int | None:
    """Number of positional parameters of ``fn`` (``forward`` for a module), ``None`` for
    ``*args`` or an unreadable signature."""
    counts = _positional_counts(fn)
    return None if counts is None else counts[1]


def _positional_counts(fn: Callable[..., Tensor]) -> tuple[int, int] | None:
    """``(required, total)`` positional parameters of ``fn`` (``forward`` for a module):
    those without a default, and all of them; ``None`` for ``*args`` or an unreadable
    signature."""
    target = fn.forward if isinstance(fn, nn.Module) else fn
    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return None
    required = total = 0
    for p in sig.parameters.values():
        if p.kind is p.VAR_POSITIONAL:
            return None
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            total += 1
            required += p.default is p.empty
    return required, total


class Dynamics(nn.Module):
    """``f(x)`` or ``f(x, u)`` seen as ``f(x, u, theta)`` (the arguments it lacks are unused).

    Args:
        f: the user's function or module.
        arity: how many of ``(x, u, theta)`` it takes (1 or 2).
    """

    def __init__(self, f: Callable[..., Tensor], arity: int) -> None:
        super().__init__()
        self.fn = f  # a module is registered (its parameters are the system's)
        self.arity = arity
        self.__name__ = "f"

    def forward(self, x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        return self.fn(x) if self.arity == 1 else self.fn(x, u)

    @property
    def engine_wraps(self) -> tuple[tuple[str, int], Callable[..., Tensor]]:
        """What the engine's program cache keys this wrapper by (`diffsmf.interval.engine.
        fingerprint`): its arity and the user's function."""
        return ("dynamics", self.arity), self.fn


def as_dynamics(f: Callable[..., Tensor]) -> Callable[..., Tensor]:
    """``f`` as ``f(x, u, theta)``.

    Raises:
        ValueError: naming ``f`` when it takes no argument or more than three.
    """
    counts = _positional_counts(f)
    if counts is None:
        return f
    required, total = counts
    if total >= 3 and required <= 3:  # f(x, u, theta, k=0.5): the extras keep their defaults
        return f
    if total in (1, 2):
        return Dynamics(f, total)
    if total == 0:
        raise ValueError("f: must take the state, f(x), f(x, u) or f(x, u, theta); it takes "
                         "no positional argument")
    raise ValueError(
        f"f: must take the state and optionally the input and parameter, f(x), f(x, u) or "
        f"f(x, u, theta); it needs {required} positional arguments (give the ones after "
        "theta default values, e.g. def f(x, u=None, theta=None, k=0.5))"
    )


def check_dtype(name: str, fn: Callable[..., Tensor], out: Tensor) -> None:
    """A model must compute in float64 (the guarantee's rounding analysis assumes it).

    Raises:
        ValueError: naming ``name``, saying to call ``.double()`` on a float32 module.
    """
    params = list(fn.parameters()) if isinstance(fn, nn.Module) else []
    bad = [p.dtype for p in params if p.is_floating_point() and p.dtype != torch.float64]
    if bad or out.dtype != torch.float64:
        dt = bad[0] if bad else out.dtype
        hint = "call .double() on the module" if isinstance(fn, nn.Module) or bad else (
            "compute in float64 (torch.set_default_dtype(torch.float64) or float64 constants)")
        raise ValueError(f"{name}: computes in {dt}; diffsmf's guaranteed sets need float64: "
                         f"{hint}")


def check_module_dtype(name: str, fn: Callable[..., Tensor]) -> None:
    """An ``nn.Module`` model must hold float64 parameters (before it is first called).

    Raises:
        ValueError: naming ``name``: call ``.double()`` on the module.
    """
    if not isinstance(fn, nn.Module):
        return
    for p in fn.parameters():
        if p.is_floating_point() and p.dtype != torch.float64:
            raise ValueError(f"{name}: the module holds {p.dtype} parameters; diffsmf's "
                             "guaranteed sets need float64: call .double() on the module")

