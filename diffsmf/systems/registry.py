"""The registry of named systems, built-in and the user's (``get``, ``names``, ``register``)."""

from __future__ import annotations

import inspect
from collections.abc import Callable

from diffsmf.systems import chain, library, observer_tests, radar
from diffsmf.systems.system import System

__all__ = ["BUILTINS", "check_name", "get", "names", "register"]

#: The built-in systems, registered here in one place (their modules do not import the
#: registry): the Wang et al. 2022 systems and the other built-ins of `library`, the
#: n-dimensional oscillator chain, the Jiang et al. 2016 radar system, and the systems of the
#: reference toolbox's observer tests with the tank cascade of any size (`observer_tests`).
BUILTINS: dict[str, Callable[..., System]] = {
    "bilinear": library.bilinear,
    "cstr": library.cstr,
    "fermenter": library.fermenter,
    "linear_2d": observer_tests.linear_2d,
    "mismatch_quadratic": library.mismatch_quadratic,
    "oscillator_chain": chain.oscillator_chain,
    "radar": radar.radar,
    "spring_damper": library.spring_damper,
    "tank6": observer_tests.tank6,
    "tank_cascade": observer_tests.tank_cascade,
    "unicycle_rb": library.unicycle_rb,
    "vdp": library.vdp,
}

_REGISTRY: dict[str, Callable[..., System]] = dict(BUILTINS)


def register(name: str) -> Callable[[Callable[..., System]], Callable[..., System]]:
    """Decorator registering a factory ``(**kwargs) -> System`` under ``name``."""

    def deco(factory: Callable[..., System]) -> Callable[..., System]:
        _REGISTRY[name] = factory
        return factory

    return deco


def names() -> list[str]:
    """Names of the built-in (and user-registered) systems."""
    return sorted(_REGISTRY)


def get(name: str, **kwargs) -> System:
    """A fresh instance of the built-in system ``name`` (see `names`).

    ``name`` may carry the size argument of a sized system as ``"NAME:N"``
    (``get("oscillator_chain:16")`` is ``get("oscillator_chain", n=16)``), the spelling of the
    command line (``diffsmf audit --system oscillator_chain:16``) and of the benchmarks.

    Raises:
        ValueError: see `check_name`.
    """
    factory, size = _parse(name, kwargs)
    return factory(**kwargs) if size is None else factory(n=size, **kwargs)


def check_name(name: str, option: str = "name", **kwargs) -> None:
    """Raise the ``ValueError`` that `get` would raise for ``name``, without building the
    system: an unknown name, a size that is not an integer >= 1, a size given twice
    (``"NAME:N"`` and ``n=``), or a size for a system without one. The message starts with
    ``option`` (a command line passes its option, e.g. ``"--system"``)."""
    _parse(name, kwargs, option)


def _parse(
    name: str, kwargs: dict, option: str = "name"
) -> tuple[Callable[..., System], int | None]:
    """``"NAME"`` or ``"NAME:N"`` -> (factory, size or None), checked; errors name ``option``."""
    base, sep, size = name.partition(":")
    if base not in _REGISTRY:
        raise ValueError(f"{option}: unknown system {base!r}; choose from {sorted(_REGISTRY)}")
    if not sep:
        return _REGISTRY[base], None
    if not size.isdigit() or int(size) < 1:
        raise ValueError(f"{option}: expected NAME or NAME:N with N >= 1, got {name!r}")
    if "n" in kwargs:
        raise ValueError(f"{option}: {name!r} gives the size and so does n={kwargs['n']!r}")
    if "n" not in inspect.signature(_REGISTRY[base]).parameters:
        raise ValueError(f"{option}: system {base!r} has no size argument, got {name!r}")
    return _REGISTRY[base], int(size)
