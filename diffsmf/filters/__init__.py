"""Filters: HSNSMF, MSZM, CDSMF, ESMF, ESO, CZSMF, ZBSMF, IntervalFilter, CombinedFilter, EKF
(all ``nn.Module``), by name (`get`, `names`; CORA's observer names are `PRESETS`).

`SetFilter` is the contract of every filter; `LinearisingFilter` the base of the ones that
linearise about the set's centre (HSNSMF, MSZM, CDSMF, ESMF, CZSMF, IntervalFilter)."""

from diffsmf.filters.base import FilterResult, FilterState, SetFilter
from diffsmf.filters.bundle import ZBSMF
from diffsmf.filters.cdsmf import CDSMF
from diffsmf.filters.combined import CombinedFilter
from diffsmf.filters.czsmf import CZSMF
from diffsmf.filters.ekf import EKF
from diffsmf.filters.esmf import ESMF
from diffsmf.filters.eso import ESO
from diffsmf.filters.events import FilterEvent, describe_events, event_text
from diffsmf.filters.hsnsmf import HSNSMF
from diffsmf.filters.interval_filter import IntervalFilter
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.filters.mszm import MSZM
from diffsmf.filters.presets import Preset

__all__ = [
    "CDSMF",
    "CombinedFilter",
    "CZSMF",
    "EKF",
    "ESMF",
    "ESO",
    "HSNSMF",
    "IntervalFilter",
    "MSZM",
    "ZBSMF",
    "FilterEvent",
    "FilterResult",
    "FilterState",
    "LinearisingFilter",
    "ALIASES",
    "PRESETS",
    "Preset",
    "SET_FAMILIES",
    "SetFilter",
    "by_name",
    "is_guaranteed",
    "describe_events",
    "event_text",
    "get",
    "names",
]

_NAMES: dict[str, type[SetFilter]] = {
    "hsnsmf": HSNSMF, "mszm": MSZM, "cdsmf": CDSMF, "esmf": ESMF, "ekf": EKF, "czsmf": CZSMF,
    "combined": CombinedFilter, "interval": IntervalFilter, "zbsmf": ZBSMF, "eso": ESO,
}

#: Other names of the filters: CORA's observer names (Althoff's toolbox) for the ones it has,
#: and the papers' spellings (matched without case, ``-`` or ``_``, as the names themselves)
ALIASES: dict[str, str] = {
    "FRad-A": "mszm",  # CORA: zonotopes, Alamo et al. 2005 F-radius strip weights
    "CZN-A": "czsmf",  # CORA: constrained zonotopes, Scott et al. 2016
    "HS-NSMF": "hsnsmf",
    "CD-SMF": "cdsmf",
    "CombinedFilter": "combined",
    "zonotope-bundle": "zbsmf",
}

#: Filters with options fixed, by CORA's observer names: the strip weights of `MSZM`
#: (`diffsmf.filters.mszm.STRIP_WEIGHTS`)
PRESETS: dict[str, Preset] = {
    "FRad-B": Preset("FRad-B", MSZM, strip_method="wang"),  # Wang, Puig & Cembrano 2018
    "FRad-C": Preset("FRad-C", MSZM, strip_method="combastel"),  # Combastel 2015
    "VolMin-A": Preset("VolMin-A", MSZM, strip_method="volume"),  # Alamo et al. 2005
    "VolMin-B": Preset("VolMin-B", MSZM, strip_method="bravo"),  # Bravo et al. 2006
    "PRad-A": Preset("PRad-A", MSZM, strip_method="pradius-a"),  # Le et al. 2013, per output
    "PRad-B": Preset("PRad-B", MSZM, strip_method="pradius-b"),  # Le et al. 2013
    "ESO-A": Preset("ESO-A", ESO, method="gollamudi", alpha=1e-4),  # Gollamudi et al. 1996
    "ESO-B": Preset("ESO-B", ESO, method="liu"),  # Liu et al. 2016
}

#: The set families a filter declares (``set_family``), as the nonlinear observer comparison
#: of Holzinger and Althoff (2026) names them, plus the parallelotope
SET_FAMILIES = ("interval", "ellipsoid", "zonotope", "parallelotope", "constrained-zonotope",
                "zonotope-bundle")


def _key(name: str) -> str:
    return name.lower().replace("-", "").replace("_", "")


def names(presets: bool = False) -> list[str]:
    """The filters' names, one each; with ``presets=True`` followed by the `PRESETS`' (CORA's
    observer names for filters with options). `get` also takes the `ALIASES`."""
    return list(_NAMES) + (list(PRESETS) if presets else [])


def get(name: str) -> type[SetFilter] | Preset:
    """The filter for any of its names: the class for ``"hsnsmf" | "mszm" | "cdsmf" | "esmf" |
    "ekf" | "czsmf" | "combined" | "interval"`` or an alias (`ALIASES`: CORA's ``"FRad-A"``,
    ``"CZN-A"``, the papers' ``"HS-NSMF"``), a `Preset` for CORA's names of a filter with
    options (`PRESETS`: ``"FRad-B"``, ``"FRad-C"``, ``"VolMin-A"``, ``"VolMin-B"``,
    ``"PRad-A"``, ``"PRad-B"``, ``"ESO-A"``, ``"ESO-B"``); without
    regard to case, ``-`` or ``_``. Either is built as ``get(name)(system, **options)``.

    Raises:
        ValueError: starting with ``name:``, listing the names, presets and aliases.
    """
    if not isinstance(name, str):
        raise ValueError(f"name: expected a filter name (str), got {type(name).__name__}")
    key = _key(name)
    preset = next((p for a, p in PRESETS.items() if _key(a) == key), None)
    if preset is not None:
        return preset
    key = next((v for a, v in ALIASES.items() if _key(a) == key), key)
    if key in _NAMES:
        return _NAMES[key]
    raise ValueError(f"name: unknown filter {name!r}; choose from {names(presets=True)} or "
                     f"the aliases {list(ALIASES)}")


#: `get` under its earlier name
by_name = get


def is_guaranteed(filt: SetFilter | type[SetFilter]) -> bool:
    """Whether a filter (or filter class) declares ``guaranteed = True``: its set contains every
    state consistent with the model, the noise bounds and the data.

    The attribute is inherited, so a subclass of `HSNSMF` is guaranteed as `HSNSMF` is; a filter
    that does not declare it is not (`EKF` and `CombinedFilter` declare False).
    """
    return bool(getattr(filt, "guaranteed", False))
