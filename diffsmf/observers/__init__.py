"""LMI observer design (Wang et al. 2009), PWL-model observer pipeline, ILC fault estimation (Jiang
et al. 2016)."""

from diffsmf.observers.differentiable import DifferentiableObserverDesign
from diffsmf.observers.envelope import error_envelope, simulate_error_check
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
    lmi_matrix,
)
from diffsmf.observers.observer import PWLObserver, rk4_step
from diffsmf.observers.pipeline import (
    ContinuousModel,
    PipelineResult,
    certified_error,
    design_observer_pipeline,
    fit_nonlinearity,
    interval_hess_bound,
    plot_pipeline,
    vdp_model,
)

__all__ = [
    "ContinuousModel",
    "DifferentiableObserverDesign",
    "ILCDesign",
    "ILCFaultEstimator",
    "ObserverDesign",
    "PWLObserver",
    "PipelineResult",
    "RepeatedSystem",
    "analyze_observer_gain",
    "certified_error",
    "design_ilc",
    "design_lipschitz_observer",
    "design_observer_pipeline",
    "error_envelope",
    "fit_nonlinearity",
    "intermittent_fault_example",
    "interval_hess_bound",
    "lmi_matrix",
    "plot_pipeline",
    "rk4_step",
    "simulate_error_check",
    "vdp_model",
]
