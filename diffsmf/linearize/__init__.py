"""Linearisation: point Jacobians (autograd, Stirling), interval jets and remainder bounds."""

from diffsmf.linearize.jacobians import hessian, jacobian, stirling_jacobian

__all__ = ["hessian", "jacobian", "stirling_jacobian"]
