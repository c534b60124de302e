"""Tuning diffsmf filters by gradient descent on set volume.

``from diffsmf.tuning import tune`` is the loop (`diffsmf.tuning.loop.tune`); ``diffsmf tune``
is the command line (`diffsmf.cli.tune`; ``python training/tune.py`` from a source checkout).
"""

from diffsmf.tuning.loop import Data, TuneReport, evaluate, simulate_finite, tune
from diffsmf.tuning.losses import (
    LossWeights,
    consistency_loss,
    containment_loss,
    filter_with_predictions,
    log_volume_loss,
    normalised_outside,
)

__all__ = [
    "Data",
    "LossWeights",
    "TuneReport",
    "consistency_loss",
    "containment_loss",
    "evaluate",
    "filter_with_predictions",
    "log_volume_loss",
    "normalised_outside",
    "simulate_finite",
    "tune",
]
