"""The base of the filters that linearise the model about the set's centre and bound the
remainder: HSNSMF, MSZM, CDSMF, ESMF, CZSMF and IntervalFilter.

`LinearisingFilter` registers, once for all of them, what such a filter learns and chooses
besides the noise bounds of `SetFilter`: the Stirling step of the linearisation (Wang et al.
2022, eq. 12-13), the margin on the remainder box and the remainder bound
(`diffsmf.linearize.RemainderBound`), and it converts the initial set to the filter's family.
A filter then writes its constructor's own options, its ``_predict`` and its ``_update``.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.filters.params import (
    register_remainder,
    register_remainder_margin,
    register_stirling_step,
)
from diffsmf.filters.state import check_initial_set, expand_state_set
from diffsmf.linearize.remainders import RemainderBound
from diffsmf.systems.system import System
from diffsmf.utils import Positive

__all__ = ["LinearisingFilter"]


class LinearisingFilter(SetFilter):
    """A set filter that linearises ``f`` and ``h`` about the set's centre (Stirling slopes or
    autograd Jacobians) and adds a guaranteed remainder box.

    Args (every subclass takes them as keywords):
        system: the system to filter.
        stirling_step: Stirling step h (learnable; Wang et al. 2022, eq. 12-13): ``None``
            (default) for the step relative to the set, ``0.5`` times its hull half-widths
            (scale-invariant; the registered ``stirling_step`` is then the factor), or an
            absolute step in state units (scalar or ``[n]``); see
            `diffsmf.filters.params.stirling_steps`. A filter that linearises with the
            autograd Jacobian (``stirling = False``, ESMF) refuses it.
        remainder_margin: learnable inflation ``m >= 0`` (scalar or ``[n]``) of the guaranteed
            prediction remainder box, ``[lo - m, hi + m]``; it only ever enlarges the box, 0
            (default) is the filter without it (`register_remainder_margin`).
        remainder: the guaranteed remainder bound, a `diffsmf.linearize.RemainderBound`
            (``DCVertices(max_vertices=...)``, ``Lagrange()``, ``MeanValue()``,
            ``Auto(...)``) or its name: ``"dc-vertices"`` (Wang et al. 2022, eq. 14-18, 2^n
            vertices), ``"lagrange"`` (interval Hessian, vertex-free), ``"mean-value"``
            (interval Jacobian, cheapest) or ``"auto"``. ``None``: the filter's
            ``default_remainder`` (``"auto"``: ``"dc-vertices"`` up to n = 8,
            ``"lagrange"`` up to 16, ``"mean-value"`` above; `resolve_remainder`).
        initial_set: override of ``system.x0_set``, converted to the filter's family
            (`_convert_initial`).
        **kw: ``process_noise``, ``measurement_noise``, ``skip_nan``, ``learn_noise``
            (`SetFilter`).

    After construction: ``remainder`` (the resolved name) and ``remainder_fn`` (the bound
    called by the steps).
    """

    #: The set contains every state consistent with the model, the noise bounds and the data.
    guaranteed: bool = True
    #: whether the filter linearises with Stirling slopes (and so has a ``stirling_step``)
    stirling: ClassVar[bool] = True
    #: the remainder bound when ``remainder=None``
    default_remainder: ClassVar[str] = "auto"
    stirling_step = Positive()
    remainder_margin = Positive()

    def __init__(
        self,
        system: System,
        *,
        stirling_step: float | Tensor | None = None,
        remainder_margin: float | Tensor = 0.0,
        remainder: str | RemainderBound | None = None,
        initial_set: ConvexSet | None = None,
        **kw,
    ) -> None:
        super().__init__(system, **kw)
        n = system.n
        check_initial_set("initial_set", initial_set, n)
        if self.stirling:
            register_stirling_step(self, stirling_step, n)
        elif stirling_step is not None:
            raise ValueError(f"stirling_step: {type(self).__name__} linearises with the "
                             "autograd Jacobian and has no Stirling step")
        register_remainder_margin(self, remainder_margin, n)
        register_remainder(self, self.default_remainder if remainder is None else remainder, n)
        self._x0 = self._convert_initial(initial_set if initial_set is not None else system.x0_set)

    def _convert_initial(self, S: ConvexSet) -> ConvexSet:
        """The initial set ``S`` in the filter's family (an outer bound where not exact)."""
        raise NotImplementedError

    def _initial_state(self, batch: int | None = None) -> FilterState:
        S = expand_state_set(self._x0, batch)
        return FilterState(set=S, consistent=torch.ones(S.batch_shape, dtype=torch.bool))
