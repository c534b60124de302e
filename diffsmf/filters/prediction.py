"""The prediction pieces shared by the linearising set-membership filters (HSNSMF, MSZM, CDSMF,
ESMF, CZSMF): the step function at the nominal parameter, the guaranteed remainder box of a
step (model remainder + parameter mismatch + the user's margin), the process noise as the
zonotope or ellipsoidal predictions take it, and the predicted zonotope of HSNSMF and MSZM.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import SetFilter
from diffsmf.filters.remainder_boxes import (
    ROUND_REL,
    add_remainder_margin,
    checked_remainder,
    sanitize_remainder,
)
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System

__all__ = [
    "noise_ellipsoid",
    "noise_generators",
    "prediction_remainder",
    "step_function",
    "zonotope_prediction",
]


def step_function(system: System, u: Tensor | None) -> Callable[[Tensor], Tensor]:
    """``x [..., n] -> f(x, u, theta_nom) [..., n]`` (the nominal model of one step).

    ``u [B, p]`` is closed over; `diffsmf.linearize` puts extra point dims (stencils,
    vertices) in *leading* positions, so ``u`` broadcasts against them.
    """
    from diffsmf.interval.engine import StepModel

    return StepModel(system.f, u, system.theta_nominal)


def prediction_remainder(
    system: System,
    remainder: Callable[..., Interval],
    fn: Callable[[Tensor], Tensor],
    S: ConvexSet,
    c: Tensor,
    J: Tensor,
    u: Tensor | None,
    margin: Tensor | None = None,
    events: bool = False,
) -> tuple[Interval, Tensor]:
    """Box ``[B, n]`` containing ``f(x, u, theta) - f(c, u, theta_nom) - J (x - c)`` on ``S``,
    and ``ok [B]``: False where no finite box exists (`sanitize_remainder`); with
    ``events=True`` the `FilterEvent` codes ``[B]`` instead (`checked_remainder`:
    ``DOMAIN`` / ``DIVERGED``, 0 where the box is finite), for ``FilterState.flag``.

    ``remainder`` is a `diffsmf.linearize` remainder bound (``dc_remainder`` for Wang et al.
    2022, ``lagrange_remainder`` for Song et al. 2017); when the system has mismatched parameters
    the deviation ``f(x, u, theta) - f(x, u, theta_nom)`` over ``S`` x ``parameters``
    (``linearize.parameter_deviation``, Song et al. 2017, eq. 18-21, evaluated over the whole set,
    not only at the centre as in the paper) is added. ``margin [n]`` (>= 0, the filters'
    ``remainder_margin``) then enlarges the computed box to ``[lo - m, hi + m]``
    (`add_remainder_margin`); it can only add to the guaranteed box, never replace it.
    Where the box is not finite (a singularity of the model over ``S``) it is returned as 0
    with ``ok`` False, and the caller flags those elements (``FilterState.and_bounded(ok)``).
    """
    from diffsmf.linearize import parameter_deviation

    R = remainder(fn, S, c, J)
    if system.parameters is not None:
        D = parameter_deviation(system.f, S, system.parameters, system.theta_nominal, u)
        R = Interval._make(R.lower + D.lower, R.upper + D.upper)
    R = add_remainder_margin(R, margin)
    return checked_remainder(R) if events else sanitize_remainder(R)


def noise_generators(filt: SetFilter) -> tuple[Tensor, Tensor, Tensor | None]:
    """Process noise for the zonotope-type predictions (HSNSMF, MSZM) -> ``(center [n],
    box half-widths [n], generators [n, q] or None)``.

    A box W (the built-ins) is ``(c, r, None)``: the filter's ``process_noise_center`` and
    ``process_noise`` themselves (for a zero centre, the bits of the box's centre and
    half-widths; otherwise without their rounding); a zonotope or
    parallelotope W keeps its own generators (``(c, 0, G)``: exact Minkowski sum); an
    ellipsoid, which a zonotope cannot hold exactly, enters by its interval hull.
    """
    from diffsmf.sets.zonotope import Zonotope

    W0 = filt.system.process_noise
    if (W0 is None or isinstance(W0, Interval)) and _plain_noise_set(filt):
        # the box W itself (`SetFilter.process_noise_box`), without forming the Interval
        return filt.process_noise_center, filt.process_half_widths, None
    W = filt.process_noise_set()
    if isinstance(W, Zonotope):
        return W.center, torch.zeros_like(W.center), W.generators
    box = W if isinstance(W, Interval) else W.interval_hull()
    return box.center, box.radius, None


def _plain_noise_set(filt: SetFilter) -> bool:
    """Whether ``filt`` keeps `SetFilter`'s own ``process_noise_set`` and
    ``process_noise_box`` (a box W is then ``process_noise_center +- process_noise``)."""
    cls = type(filt)
    return (cls.process_noise_set is SetFilter.process_noise_set
            and cls.process_noise_box is SetFilter.process_noise_box)


def noise_ellipsoid(filt: SetFilter) -> ConvexSet | None:
    """Process noise for the ellipsoidal predictions (CDSMF, ESMF): ``None`` for a box W (the
    filters keep their box sum with the remainder, as before), else the ellipsoid W itself or
    the covering ellipsoid of a zonotope W (`Ellipsoid.from_zonotope`, not its hull)."""
    from diffsmf.sets.ellipsoid import Ellipsoid

    W = filt.process_noise_set()
    if isinstance(W, Interval):
        return None
    return W if isinstance(W, Ellipsoid) else Ellipsoid.from_zonotope(W)


def zonotope_prediction(filt: SetFilter, fc: Tensor, FG: Tensor, E: Interval) -> ConvexSet:
    """The predicted zonotope of HSNSMF and MSZM: ``f(c) + F G (+) E (+) W`` (Wang et al. 2022, eq.
    20-21, Theorem 2; Alamo 2005) -> Zonotope ``[B]``.

    ``fc [B, n]`` the model at the centre, ``FG [B, n, q]`` the mapped generators, ``E`` the
    remainder box. A box W joins the remainder box (one diagonal block), a zonotope W adds
    its own generators (`noise_generators`); the diagonal is padded by the float64
    rounding margin of the affine part.
    """
    from diffsmf.sets.zonotope import Zonotope

    wc, wr, Gw = noise_generators(filt)
    ec = E.center
    rad = torch.add(wr, E.upper - E.lower, alpha=0.5)  # Theorem 2: sum of two boxes
    # `rounding_margin(fc, ec, sum_j |FG_ij|, rad)`: rad + ROUND_REL (1 + |fc| + |ec| +
    # sum_j |FG_ij| + rad), the absolute values summed at once over [FG, fc, ec, rad] (a
    # 1-norm is one op but far slower on short rows)
    t = torch.cat([FG, torch.stack([fc, ec, rad], -1)], -1).abs().sum(-1)
    rad = torch.add(rad + ROUND_REL, t, alpha=ROUND_REL)
    parts = [FG, torch.diag_embed(rad)]
    if Gw is not None:
        parts.append(Gw.expand(*FG.shape[:-1], Gw.shape[-1]))
    return Zonotope._make(fc + ec + wc, torch.cat(parts, -1))
