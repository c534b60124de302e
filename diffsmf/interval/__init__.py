"""The guarantee engine: interval arithmetic and derivative enclosures of any torch model.

* `rounding`: outward rounding, the guarantee of every operation;
* `arith`: interval arrays, Moore arithmetic on ``lower``/``upper`` tensors;
* `box`: ``Interval``, the box set and the engine's value type (`diffsmf.sets` re-exports it);
* `jet`: interval jets (value, gradient and Hessian enclosures);
* `rules`: one inclusion rule per ATen op, in a registry;
* `capture`: a model captured once as an ATen graph, evaluated by rules;
* `engine`: the entry point, `enclose`.
"""

from __future__ import annotations

from typing import Any

from diffsmf.interval.rounding import down, up

__all__ = ["EngineError", "Enclosure", "StepModel", "down", "enclose", "inclusion",
           "supported_ops", "up"]

_LAZY = {
    "EngineError": "diffsmf.interval.errors",
    "inclusion": "diffsmf.interval.capture",
    "Enclosure": "diffsmf.interval.engine",
    "StepModel": "diffsmf.interval.engine",
    "enclose": "diffsmf.interval.engine",
    "supported_ops": "diffsmf.interval.rules",
}


def __getattr__(name: str) -> Any:
    """Lazy imports: ``import diffsmf.interval.rounding`` does not load the engine."""
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'diffsmf.interval' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(mod), name)
