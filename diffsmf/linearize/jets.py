"""Guaranteed Jacobian and Hessian enclosures over a box (the remainders' view of the engine).

Thin entry points over `diffsmf.interval`: the model is captured once as an ATen graph and
evaluated in interval-jet arithmetic (Song et al. 2017, sec. 3 interval extensions, used for the
interval Hessian of Song et al. 2017, eq. 26-28 and for the DC parameter of Wang et al. 2022,
eq. 15-16, erratum). Every op of the "Writing models" docs page is supported, non-smooth ones
included (their Hessian enclosure is ``[-inf, inf]`` where a kink lies in the box).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

from diffsmf.interval.box import Interval
from diffsmf.interval.capture import EngineError
from diffsmf.interval.engine import Enclosure, enclose

__all__ = ["Enclosure", "JetError", "interval_hessian", "interval_jacobian", "jet_eval"]
#: A model the engine cannot enclose (a ``ValueError``: the CLI prints one line).
JetError = EngineError


def jet_eval(fn: Callable[[Any], Any], box: Interval, order: int = 2) -> Enclosure:
    """Enclose ``fn`` over the box ``[..., n]`` -> `Enclosure` of shape ``[..., k]``.

    ``out.val`` encloses ``fn`` over the box, ``out.grad`` its Jacobian ``[..., k, n]`` and
    (order 2) ``out.hess`` the Hessians ``[..., k, n, n]``.
    """
    if order not in (1, 2):
        raise ValueError(f"order: expected 1 or 2, got {order}")
    return enclose(fn, box, order)


def interval_jacobian(fn: Callable[[Any], Any], box: Interval) -> Interval:
    """Guaranteed enclosure of the Jacobian of ``fn`` over ``box [..., n]`` -> ``[..., k, n]``.

    Interval extension (Song et al. 2017, sec. 3.2) of the derivative; used for the mean-value
    form of the parameter deviation (Song et al. 2017, eq. 18-21).
    """
    return enclose(fn, box, 1).grad


def interval_hessian(fn: Callable[[Any], Any], box: Interval) -> Interval:
    """Guaranteed enclosure of the Hessians of ``fn`` over ``box`` -> ``[..., k, n, n]``.

    Interval Hessian of Song et al. 2017, eq. 26-28 (there written for the Lagrange remainder).
    """
    out = enclose(fn, box, 2)
    assert out.hess is not None
    return out.hess


def __getattr__(name: str) -> Any:
    """``Jet``: the deprecated name of `Enclosure` here (``diffsmf.interval.jet.Jet`` is the
    engine's interval jet, another type)."""
    if name == "Jet":
        warnings.warn("diffsmf.linearize.Jet is renamed Enclosure (diffsmf.interval.jet.Jet is "
                      "the engine's interval jet)", DeprecationWarning, stacklevel=2)
        return Enclosure
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
