"""Filters by the names of other toolboxes: a `Preset` is a filter class with some of its
options fixed, so that CORA's ``"FRad-B"`` is `MSZM` with ``strip_method="wang"`` -- one filter
with options, not a copy."""

from __future__ import annotations

from typing import Any

from diffsmf.filters.base import SetFilter
from diffsmf.systems.system import System

__all__ = ["Preset", "filter_name"]


def filter_name(filt: Any) -> str:
    """The name reports give a filter: its preset's (``"FRad-B"``) where it was built by one,
    else its class's (``"MSZM"``)."""
    return getattr(filt, "preset", None) or type(filt).__name__


class Preset:
    """A filter class with fixed options, built like the class: ``Preset(system, **kw)``.

    The caller's keywords override the preset's own. Attributes the class declares
    (``set_family``, ``guaranteed``, ...) are read through, so `diffsmf.filters.is_guaranteed`
    and the comparison treat a preset as its class.

    Args:
        name: the preset's name (e.g. CORA's ``"FRad-B"``).
        cls: the filter class.
        options: its fixed keyword arguments.
    """

    def __init__(self, name: str, cls: type[SetFilter], **options: Any) -> None:
        self.name, self.cls, self.options = name, cls, dict(options)

    def __call__(self, system: System, **kw: Any) -> SetFilter:
        filt = self.cls(system, **{**self.options, **kw})
        filt.preset = self.name  # reports name it (`filter_name`)
        return filt

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("__") or attr in ("name", "cls", "options"):
            raise AttributeError(attr)
        return getattr(self.cls, attr)

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"Preset({self.name!r}: {self.cls.__name__}({opts}))"
