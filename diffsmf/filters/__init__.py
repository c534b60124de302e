"""Filters: HSNSMF, MSZM, CDSMF, ESMF, CombinedFilter, EKF (all ``nn.Module``)."""

from diffsmf.filters.base import FilterResult, FilterState, SetFilter
from diffsmf.filters.cdsmf import CDSMF
from diffsmf.filters.combined import CombinedFilter
from diffsmf.filters.czsmf import CZSMF
from diffsmf.filters.ekf import EKF
from diffsmf.filters.esmf import ESMF
from diffsmf.filters.events import FilterEvent, describe_events, event_text
from diffsmf.filters.hsnsmf import HSNSMF
from diffsmf.filters.mszm import MSZM

__all__ = [
    "CDSMF",
    "CombinedFilter",
    "CZSMF",
    "EKF",
    "ESMF",
    "HSNSMF",
    "MSZM",
    "FilterEvent",
    "FilterResult",
    "FilterState",
    "SetFilter",
    "by_name",
    "describe_events",
    "event_text",
    "names",
]

_NAMES = {"hsnsmf": HSNSMF, "mszm": MSZM, "cdsmf": CDSMF, "esmf": ESMF, "ekf": EKF, "czsmf": CZSMF}


def names() -> list[str]:
    """Names accepted by :func:`by_name`."""
    return [*_NAMES, "combined"]


def by_name(name: str) -> type[SetFilter]:
    """Filter class for ``"hsnsmf" | "mszm" | "cdsmf" | "esmf" | "ekf" | "combined"``."""
    key = name.lower().replace("-", "").replace("_", "")
    if key in _NAMES:
        return _NAMES[key]
    if key == "combined":
        from diffsmf.filters.combined import CombinedFilter  # lazy: another engineer's module

        return CombinedFilter
    raise ValueError(f"name: unknown filter {name!r}; choose from {names()}")
