"""Filters: HSNSMF, MSZM, CDSMF, ESMF, CombinedFilter, EKF (all ``nn.Module``)."""

from diffsmf.filters.base import FilterResult, FilterState, SetFilter

__all__ = ["FilterResult", "FilterState", "SetFilter"]
