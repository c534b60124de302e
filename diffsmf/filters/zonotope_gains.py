"""The gain matrices of the zonotope observers that intersect all measurement strips at once
(`diffsmf.sets.Zonotope.intersect_strips`): CORA's FRad-B (Wang, Puig & Cembrano 2018) and
FRad-C (Combastel 2015). Each is an F-radius-type gain, ``L = R A' (A R A' + diag(w^2))^-1``,
for a matrix ``R`` that stands for the spread of the set:

* ``"combastel"``: ``R = G G'`` of the set itself (Combastel 2015, eq. 11-12; CORA's FRad-C
  and its strip method ``normGen``);
* ``"pradius-a"`` / ``"pradius-b"``: the offline P-radius gain of Le et al. 2013
  (`diffsmf.filters.pradius`), designed once at construction (CORA's PRad-A and PRad-B);
* ``"wang"``: ``R = J G G' J' + E E'`` (Wang, Puig & Cembrano 2018, Theorem 2, eq. 12-15), with
  ``J`` the Jacobian of the last prediction and ``E`` the process noise generators. As in
  CORA's FRad-B, ``G`` is the generator matrix of the *predicted* set (see the errata page).

Any gain gives a guaranteed set; the gain only decides how tight it is.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.filters.prediction import noise_generators

__all__ = ["GAINS", "STRIP_WEIGHTS", "fradius_gain"]


def fradius_gain(R: Tensor, A: Tensor, w: Tensor) -> Tensor:
    """``L = R A' (A R A' + diag(w^2))^-1 [..., n, k]`` for ``R [..., n, n]`` (symmetric,
    positive semi-definite), ``A [..., k, n]``, ``w [..., k]`` (> 0): the gain that minimises
    the F-radius of `Zonotope.intersect_strips`'s result when ``R = G G'`` (Combastel 2015).
    A zero row of ``A`` gives a zero column of ``L``."""
    RA = R @ A.transpose(-1, -2)  # [..., n, k]
    S = A @ RA + torch.diag_embed(w * w)
    return linalg.solve(S, RA.transpose(-1, -2)).transpose(-1, -2)  # S symmetric


def _combastel(filt: SetFilter, state: FilterState, S: ConvexSet, A: Tensor, w: Tensor
               ) -> Tensor:
    G = S.generators
    return fradius_gain(G @ G.transpose(-1, -2), A, w)


def _wang(filt: SetFilter, state: FilterState, S: ConvexSet, A: Tensor, w: Tensor) -> Tensor:
    G = S.generators
    JG = state.extras["_jacobian"] @ G
    _, wr, Gw = noise_generators(filt)
    R = JG @ JG.transpose(-1, -2) + torch.diag_embed(wr * wr)
    if Gw is not None:
        R = R + Gw @ Gw.transpose(-1, -2)
    return fradius_gain(R, A, w)


def _fixed(filt: SetFilter, state: FilterState, S: ConvexSet, A: Tensor, w: Tensor) -> Tensor:
    """The offline gain of PRad-A/B (`MSZM.strip_gain`, designed at construction)."""
    L = filt.strip_gain.to(dtype=A.dtype, device=A.device)
    return L.expand(*A.shape[:-2], *L.shape)


#: The gains by `MSZM` ``strip_method`` name: ``(filter, state, set, A, w) -> L``
GAINS: dict[str, Callable[..., Tensor]] = {"wang": _wang, "combastel": _combastel,
                                           "pradius-a": _fixed, "pradius-b": _fixed}

#: Every `MSZM` strip weight: `Zonotope.intersect_strip`'s one-at-a-time methods, then the
#: gains, with CORA's observer names
STRIP_WEIGHTS: dict[str, str] = {
    "fradius": "FRad-A", "volume": "VolMin-A", "bravo": "VolMin-B", "wang": "FRad-B",
    "combastel": "FRad-C", "pradius-a": "PRad-A", "pradius-b": "PRad-B",
}
