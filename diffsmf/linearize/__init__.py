"""Linearisation: point Jacobians (autograd, Stirling), interval jets and remainder bounds."""

from diffsmf.linearize.jacobians import hessian, jacobian, stirling_jacobian
from diffsmf.linearize.statistical import axis_points, statistical_linearization

__all__ = ["hessian", "jacobian", "stirling_jacobian"]
__all__ += ["axis_points", "statistical_linearization"]
