"""Linearisation: point Jacobians (autograd, Stirling), interval jets and remainder bounds."""

from diffsmf.linearize.jacobians import hessian, jacobian, stirling_jacobian
from diffsmf.linearize.jets import (
    Enclosure,
    JetError,
    interval_hessian,
    interval_jacobian,
    jet_eval,
)
from diffsmf.linearize.remainders import (
    AUTO_VERTEX_MAX_N,
    REMAINDERS,
    Auto,
    DCVertices,
    Lagrange,
    MeanValue,
    RemainderBound,
    dc_remainder,
    diagonal_shift,
    hessian_eig_lower_bound,
    lagrange_remainder,
    mean_value_remainder,
    parameter_deviation,
    resolve_remainder,
)
from diffsmf.linearize.statistical import axis_points, statistical_linearization

__all__ = [
    "AUTO_VERTEX_MAX_N",
    "REMAINDERS",
    "Auto",
    "DCVertices",
    "Lagrange",
    "MeanValue",
    "RemainderBound",
    "Enclosure",
    "JetError",
    "dc_remainder",
    "diagonal_shift",
    "hessian",
    "hessian_eig_lower_bound",
    "interval_hessian",
    "interval_jacobian",
    "jacobian",
    "jet_eval",
    "lagrange_remainder",
    "mean_value_remainder",
    "parameter_deviation",
    "resolve_remainder",
    "stirling_jacobian",
]
__all__ += ["axis_points", "statistical_linearization"]


def __getattr__(name: str):
    """``Jet``: the deprecated name of `Enclosure` (`diffsmf.linearize.jets`)."""
    if name == "Jet":
        from diffsmf.linearize import jets

        return jets.__getattr__(name)
    raise AttributeError(f"module 'diffsmf.linearize' has no attribute {name!r}")
