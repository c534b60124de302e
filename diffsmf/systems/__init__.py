"""Systems: `System` and the built-in library (``get``, ``names``, ``register``)."""

from __future__ import annotations

from diffsmf.systems.observer_tests import recorded
from diffsmf.systems.registry import check_name, get, names, register
from diffsmf.systems.system import System, Trajectory, check_system, scale_set, wrap_angle

__all__ = [
    "System", "Trajectory", "check_name", "check_system", "get", "names", "recorded", "register",
    "scale_set", "wrap_angle",
]
