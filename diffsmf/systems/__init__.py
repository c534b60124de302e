"""Systems: :class:`System` and the built-in library (``get``, ``names``, ``register``)."""

from __future__ import annotations

from collections.abc import Callable

from diffsmf.systems.system import System, Trajectory

__all__ = ["System", "Trajectory", "get", "names", "register"]

_REGISTRY: dict[str, Callable[..., System]] = {}


def register(name: str) -> Callable[[Callable[..., System]], Callable[..., System]]:
    """Decorator registering a factory ``(**kwargs) -> System`` under ``name``."""

    def deco(factory: Callable[..., System]) -> Callable[..., System]:
        _REGISTRY[name] = factory
        return factory

    return deco


def _load_builtins() -> None:
    import diffsmf.systems.chain  # noqa: F401  (registers the n-dimensional oscillator chain)
    import diffsmf.systems.library  # noqa: F401  (registers the seed 000/001/004 systems)
    import diffsmf.systems.radar  # noqa: F401  (registers the seed 003 radar system)


def names() -> list[str]:
    """Names of the built-in (and user-registered) systems."""
    _load_builtins()
    return sorted(_REGISTRY)


def get(name: str, **kwargs) -> System:
    """A fresh instance of the built-in system ``name`` (see :func:`names`)."""
    _load_builtins()
    if name not in _REGISTRY:
        raise ValueError(f"name: unknown system {name!r}; choose from {sorted(_REGISTRY)}")
    return _REGISTRY[name](**kwargs)
