"""Tuning diffsmf filters by gradient descent on set volume.

``from diffsmf.tuning import tune`` is the loop (`diffsmf.tuning.loop.tune`); ``diffsmf tune``
is the command line (`diffsmf.cli.tune`; ``python -m diffsmf tune`` is the same).
"""

from diffsmf.tuning.bounds import bound_sets, consistent_scale, read_bounds, write_bounds
from diffsmf.tuning.loop import Data, TuneReport, evaluate, simulate_finite, tune
from diffsmf.tuning.losses import (
    LossWeights,
    consistency_loss,
    containment_loss,
    filter_with_predictions,
    fit_loss,
    log_volume_loss,
    normalised_outside,
    prediction_loss,
)

__all__ = [
    "Data",
    "LossWeights",
    "TuneReport",
    "bound_sets",
    "consistent_scale",
    "consistency_loss",
    "containment_loss",
    "evaluate",
    "filter_with_predictions",
    "fit_loss",
    "log_volume_loss",
    "normalised_outside",
    "prediction_loss",
    "read_bounds",
    "simulate_finite",
    "tune",
    "write_bounds",
]
