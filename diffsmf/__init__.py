"""diffsmf: differentiable set-membership filtering, PWL models and LMI observers in PyTorch.

>>> import diffsmf as ds
>>> Z = ds.Zonotope(center, generators)          # sets
>>> sys = ds.systems.get("spring_damper")         # systems
>>> res = ds.filters.HSNSMF(sys)(traj.y, u=traj.u) # filters
"""

import torch as _torch

if not hasattr(_torch.library, "custom_op"):  # the engine's leaf operations need it
    raise ImportError(f"diffsmf needs torch >= 2.4 (torch.library.custom_op); this is torch "
                      f"{_torch.__version__}: pip install -U torch (CPU-only machine: its CPU "
                      "build, see the README)")

from diffsmf import filters, sets, systems
from diffsmf.sets import Ellipsoid, Interval, Parallelotope, Strip, Zonotope, stack, where
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope
from diffsmf.systems import System, Trajectory

__version__ = "0.1.0"

_LAZY = ("audit", "comparison", "linearize", "observers", "plot", "pwl", "tightness", "tuning")


def __getattr__(name: str):
    """Import the heavier sub-packages on first use (``ds.pwl``, ``ds.observers``, ...)."""
    if name in _LAZY:
        import importlib

        return importlib.import_module(f"diffsmf.{name}")
    if name == "compare":  # observers on the same data (`diffsmf.comparison.compare`)
        from diffsmf.comparison import compare

        return compare
    raise AttributeError(f"module 'diffsmf' has no attribute {name!r}")

__all__ = [
    "audit",
    "compare",
    "comparison",
    "linearize",
    "observers",
    "plot",
    "pwl",
    "tightness",
    "ConstrainedZonotope",
    "Ellipsoid",
    "Interval",
    "Parallelotope",
    "Strip",
    "System",
    "Trajectory",
    "Zonotope",
    "filters",
    "sets",
    "stack",
    "systems",
    "where",
]
