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
    "is_guaranteed",
    "describe_events",
    "event_text",
    "names",
]

_NAMES: dict[str, type[SetFilter]] = {
    "hsnsmf": HSNSMF, "mszm": MSZM, "cdsmf": CDSMF, "esmf": ESMF, "ekf": EKF, "czsmf": CZSMF,
    "combined": CombinedFilter,
}


def names() -> list[str]:
    """Names accepted by `by_name`."""
    return list(_NAMES)


def by_name(name: str) -> type[SetFilter]:
    """Filter class for ``"hsnsmf" | "mszm" | "cdsmf" | "esmf" | "ekf" | "czsmf" | "combined"``."""
    key = name.lower().replace("-", "").replace("_", "")
    if key in _NAMES:
        return _NAMES[key]
    raise ValueError(f"name: unknown filter {name!r}; choose from {names()}")


def is_guaranteed(filt: SetFilter | type[SetFilter]) -> bool:
    """Whether a filter (or filter class) declares ``guaranteed = True``: its set contains every
    state consistent with the model, the noise bounds and the data.

    The attribute is inherited, so a subclass of `HSNSMF` is guaranteed as `HSNSMF` is; a filter
    that does not declare it is not (`EKF` and `CombinedFilter` declare False).
    """
    return bool(getattr(filt, "guaranteed", False))
