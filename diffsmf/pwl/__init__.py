"""Continuous piecewise-linear (SCPLNN) models fitted to samples (seed 004 sec. 3.1)."""

from diffsmf.pwl.fit import FitReport, fit_scplnn
from diffsmf.pwl.scplnn import SCPLNN, Regions

__all__ = ["SCPLNN", "FitReport", "Regions", "fit_scplnn"]
