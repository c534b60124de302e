"""LMI observer design (seed 004), PWL-model observer pipeline, ILC fault estimation (seed 003)."""

from diffsmf.observers.ilc import (
    ILCDesign,
    ILCFaultEstimator,
    RepeatedSystem,
    design_ilc,
    intermittent_fault_example,
)
from diffsmf.observers.lmi import (
    ObserverDesign,
    analyze_observer_gain,
    design_lipschitz_observer,
    error_envelope,
    lmi_matrix,
    simulate_error_check,
)

__all__ = [
    "ILCDesign",
    "ILCFaultEstimator",
    "ObserverDesign",
    "RepeatedSystem",
    "analyze_observer_gain",
    "design_ilc",
    "design_lipschitz_observer",
    "error_envelope",
    "intermittent_fault_example",
    "lmi_matrix",
    "simulate_error_check",
]
