"""Tuning diffsmf filters by gradient descent on set volume.

``from training import tune`` is the loop (`training.loop.tune`); ``python -m
training.tune`` is the command line (`training.tune`).
"""

from training.loop import TuneReport, evaluate, tune
from training.losses import (
    LossWeights,
    consistency_loss,
    containment_loss,
    filter_with_predictions,
    log_volume_loss,
    normalised_outside,
)

__all__ = [
    "LossWeights",
    "TuneReport",
    "consistency_loss",
    "containment_loss",
    "evaluate",
    "filter_with_predictions",
    "log_volume_loss",
    "normalised_outside",
    "tune",
]
