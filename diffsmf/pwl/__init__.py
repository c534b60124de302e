"""Continuous piecewise-linear (SCPLNN) models fitted to samples (Wang et al. 2009, sec. 3.1).

>>> from diffsmf.pwl import fit_scplnn
>>> model, report = fit_scplnn(X, Y, eps=0.01)   # X [N, n], Y [N, p]
>>> model(x)                                      # torch module, x [..., n] -> [..., p]
"""

from typing import Any

from diffsmf.pwl.certified import (
    ErrorCertificate,
    SCPLNNDynamics,
    as_system,
    certify_error,
    simplex_error,
)
from diffsmf.pwl.fit import FitReport, fit_partition, fit_scplnn
from diffsmf.pwl.hinging import HingingHyperplanes
from diffsmf.pwl.scplnn import SCPLNN, Regions

__all__ = [
    "SCPLNN",
    "ErrorCertificate",
    "FitReport",
    "HingingHyperplanes",
    "PWLRegressor",
    "Regions",
    "SCPLNNDynamics",
    "as_system",
    "certify_error",
    "fit_partition",
    "fit_scplnn",
    "simplex_error",
]


def __getattr__(name: str) -> Any:  # PWLRegressor imports scikit-learn: only when asked for
    if name == "PWLRegressor":
        from diffsmf.pwl.sklearn import PWLRegressor

        return PWLRegressor
    raise AttributeError(f"module 'diffsmf.pwl' has no attribute {name!r}")
