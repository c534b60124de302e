"""scikit-learn estimator around `diffsmf.pwl.fit_scplnn`."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from diffsmf.pwl.fit import fit_scplnn

__all__ = ["PWLRegressor"]


class PWLRegressor(RegressorMixin, BaseEstimator):
    """Continuous piecewise-linear regression (SCPLNN, Wang et al. 2009, sec. 3.1) as an sklearn
    estimator.

    Args:
        eps: target max absolute training error (number or one per output); None: ``rel_eps``
            times the range of each training output.
        rel_eps: relative target used when ``eps`` is None.
        max_regions: cap on the number of simplices.
        domain: as in `fit_scplnn` (None: bounding box of the training inputs, or an
            enclosing simplex beyond 5 inputs).
        outside: prediction outside the training domain, ``"clamp"`` (default: sklearn
            estimators must predict anywhere) or ``"extrapolate"``.
        ridge: relative Laplacian regularisation of the least squares.

    Learned attributes: ``model_`` (`SCPLNN`), ``report_`` (`FitReport`),
    ``n_features_in_``.
    """

    def __init__(self, eps: Any = None, rel_eps: float = 0.01, max_regions: int = 2000,
                 domain: Any = None, outside: str = "clamp", ridge: float = 0.1):
        self.eps = eps
        self.rel_eps = rel_eps
        self.max_regions = max_regions
        self.domain = domain
        self.outside = outside
        self.ridge = ridge

    def __sklearn_tags__(self):  # noqa: D105
        tags = super().__sklearn_tags__()
        tags.target_tags.multi_output = True
        tags.target_tags.single_output = True
        return tags

    def fit(self, X: Any, y: Any) -> PWLRegressor:
        """Fit to X ``[N, n]`` and y ``[N]`` or ``[N, p]``; returns self."""
        X, y = validate_data(self, X, y, multi_output=True, y_numeric=True, dtype=np.float64)
        if X.shape[0] < 2:
            raise ValueError(f"X: got {X.shape[0]} sample; PWLRegressor needs at least 2")
        Y = y.reshape(len(y), -1)
        if self.eps is None:
            rng = Y.max(0) - Y.min(0)
            eps = np.where(rng > 0, self.rel_eps * rng, 1.0)
        else:
            eps = self.eps
        self.model_, self.report_ = fit_scplnn(
            torch.from_numpy(X), torch.from_numpy(Y), eps, max_regions=self.max_regions,
            domain=self.domain, outside=self.outside, ridge=self.ridge, progress=False)
        self._y_ndim = y.ndim
        return self

    def predict(self, X: Any) -> np.ndarray:
        """Predictions ``[N]`` (or ``[N, p]`` for 2-D training targets)."""
        check_is_fitted(self, "model_")
        X = validate_data(self, X, reset=False, dtype=np.float64)
        with torch.no_grad():
            out = self.model_(torch.from_numpy(X)).numpy()
        return out[:, 0] if self._y_ndim == 1 else out
