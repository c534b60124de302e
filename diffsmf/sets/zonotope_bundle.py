"""Zonotope bundles (Althoff & Krogh 2011): the intersection of k zonotopes, kept implicitly.

A bundle holds k member zonotopes with the same generator count (``centers [..., k, n]``,
``generators [..., k, n, m]``); the set is their intersection. The intersection of zonotopes is
not a zonotope, but every operation a filter needs acts on the members one by one: a linear
map and a Minkowski sum with a zonotope map each member (the image of an intersection lies in
the intersection of the images), a strip intersects each member, and a point is in the bundle
when it is in every member. What needs the intersection itself is bounded from outside:

* `interval_hull`: the intersection of the members' hulls (an outer box of the bundle; the
  exact hull would take 2n LPs);
* `volume`: the least of the members' volumes and of that box's (an upper bound);
* `support`: the least of the members' supports (an upper bound).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, as_tensor, as_vector, check_count
from diffsmf.sets.interval import Interval
from diffsmf.sets.zonotope import Zonotope

__all__ = ["ZonotopeBundle"]


class ZonotopeBundle(ConvexSet):
    """The intersection of k zonotopes (Althoff & Krogh 2011), batched.

    Args:
        centers: ``[..., k, n]`` the members' centres.
        generators: ``[..., k, n, m]`` their generators (pad with zero columns to one m).

    ``center [..., n]`` is the centre of `interval_hull` (a point of the outer box, not
    necessarily of the bundle); ``members`` is the Zonotope of batch shape ``[..., k]``.
    """

    _fields: ClassVar[tuple[str, ...]] = ("centers", "generators")
    _event_dims: ClassVar[tuple[int, ...]] = (2, 3)

    def __init__(self, centers: Any, generators: Any) -> None:
        c = as_tensor("centers", centers)
        G = as_tensor("generators", generators, like=c)
        if c.dim() < 2 or G.dim() < 3 or G.shape[-3:-1] != c.shape[-2:]:
            raise ValueError(f"centers, generators: expected [..., k, n] and [..., k, n, m], "
                             f"got {tuple(c.shape)} and {tuple(G.shape)}")
        if c.shape[-2] < 1:
            raise ValueError("centers: a bundle needs at least one member zonotope")
        batch = torch.broadcast_shapes(c.shape[:-2], G.shape[:-3])
        self._set(centers=c.expand(*batch, *c.shape[-2:]),
                  generators=G.expand(*batch, *G.shape[-3:]))

    @classmethod
    def of(cls, members: list[Zonotope]) -> ZonotopeBundle:
        """The bundle of ``members`` (zonotopes of one batch shape; padded to one m)."""
        if not members:
            raise ValueError("members: a bundle needs at least one member zonotope")
        m = max(Z.num_generators for Z in members)
        Zs = [Z.pad_generators(m) for Z in members]
        return cls._from_tensors([torch.stack([Z.center for Z in Zs], -2),
                                  torch.stack([Z.generators for Z in Zs], -3)])

    @classmethod
    def from_zonotope(cls, Z: Zonotope, k: int = 1) -> ZonotopeBundle:
        """``k`` copies of ``Z`` (the bundle equal to Z)."""
        k = check_count("k", k)
        return cls._from_tensors([Z.center.unsqueeze(-2).expand(*Z.batch_shape, k, Z.dim),
                                  Z.generators.unsqueeze(-3).expand(
                                      *Z.batch_shape, k, *Z.generators.shape[-2:])])

    # ------------------------------------------------------------------ structure
    @property
    def members(self) -> Zonotope:
        """The member zonotopes, batch shape ``[..., k]``."""
        return Zonotope._make(self.centers, self.generators)

    @property
    def num_members(self) -> int:
        return self.centers.shape[-2]

    @property
    def num_generators(self) -> int:
        return self.generators.shape[-1]

    @property
    def center(self) -> Tensor:
        return self.interval_hull().center

    @property
    def batch_shape(self) -> torch.Size:
        return self.centers.shape[:-2]

    @property
    def dim(self) -> int:
        return self.centers.shape[-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.centers.dtype

    def with_members(self, Z: Zonotope) -> ZonotopeBundle:
        """The bundle of the member zonotopes ``Z`` (batch shape ``[..., k]``)."""
        return ZonotopeBundle._from_tensors([Z.center, Z.generators])

    def pad_generators(self, m: int) -> ZonotopeBundle:
        """Zero generators appended up to ``m`` per member (the same set)."""
        return self.with_members(self.members.pad_generators(m))

    # ------------------------------------------------------------------ geometry
    def interval_hull(self) -> Interval:
        """The intersection of the members' hulls ``[..., n]``: an outer box of the bundle."""
        H = self.members.interval_hull()
        return Interval._make(H.lower.amax(-2), H.upper.amin(-2))

    def volume(self) -> Tensor:
        """An upper bound of the volume ``[...]``: the least of the members' volumes and of
        the outer box's."""
        v = self.members.volume().amin(-1)
        return torch.minimum(v, self.interval_hull().volume())

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """Exact membership: ``x [..., n]`` is in every member -> bool ``[...]``."""
        x = as_vector("x", x, self.centers, self.dim)
        return self.members.contains(x.unsqueeze(-2), atol=atol).all(-1)

    def support(self, d: Tensor) -> Tensor:
        """An upper bound of the support function ``[...]``: the least member support."""
        d = as_vector("d", d, self.centers, self.dim)
        return self.members.support(d.unsqueeze(-2)).amin(-1)

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> ZonotopeBundle:
        """``A S + b`` member by member (an outer bound of the image; exact for invertible
        ``A``)."""
        A = torch.as_tensor(A, dtype=self.dtype, device=self.centers.device)
        if b is not None:
            b = torch.as_tensor(b, dtype=self.dtype, device=self.centers.device).unsqueeze(-2)
        return self.with_members(self.members.linear_map(A.unsqueeze(-3), b))

    def translate(self, b: Tensor) -> ZonotopeBundle:
        b = torch.as_tensor(b, dtype=self.dtype, device=self.centers.device)
        return ZonotopeBundle._from_tensors([self.centers + b.unsqueeze(-2), self.generators])

    def minkowski_sum(self, other: ConvexSet) -> ZonotopeBundle:
        """``S (+) Z`` for a zonotope or box ``Z``, member by member (an outer bound)."""
        from diffsmf.sets.conversions import as_zonotope

        Z = as_zonotope(other)
        Zk = Zonotope._make(Z.center.unsqueeze(-2), Z.generators.unsqueeze(-3))
        return self.with_members(self.members.minkowski_sum(Zk))

    def reduce(self, order: float, method: str = "girard") -> ZonotopeBundle:
        """Each member reduced to ``order * n`` generators (`Zonotope.reduce`)."""
        return self.with_members(self.members.reduce(order, method=method))

    def intersect_strip(self, strip: Any, methods: tuple[str, ...] | str = "fradius"
                        ) -> ZonotopeBundle:
        """Each member intersected with ``strip`` (`Zonotope.intersect_strip`), member i by
        ``methods[i]`` (one name for all): an outer bound of the bundle's intersection."""
        k = self.num_members
        methods = (methods,) * k if isinstance(methods, str) else tuple(methods)
        if len(methods) != k:
            raise ValueError(f"methods: expected one strip method per member ({k}), got "
                             f"{len(methods)}")
        cut = [self.members[..., i].intersect_strip(strip, method=mt)
               for i, mt in enumerate(methods)]
        return ZonotopeBundle.of(cut)

    def intersects_strip(self, strip: Any, atol: float = 0.0) -> Tensor:
        """False where the strip misses some member (then it misses the bundle); True does
        not prove that it meets the intersection."""
        from diffsmf.sets.strip import Strip

        s = Strip._make(strip.normal.unsqueeze(-2), torch.as_tensor(strip.offset).unsqueeze(-1),
                        torch.as_tensor(strip.halfwidth).unsqueeze(-1))
        if torch.is_tensor(atol) and atol.dim() > 0:
            atol = atol.unsqueeze(-1)
        return self.members.intersects_strip(s, atol=atol).all(-1)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` points of the first member that lie in every member, by rejection, filled up
        with the outer box's centre where too few are accepted -> ``[..., k, n]``. For tests
        and figures; the accepted points are inside."""
        k = check_count("k", k)
        pts = self.members[..., 0].sample(8 * k, generator=generator)  # [..., 8k, n]
        ok = self.members.contains(pts.unsqueeze(-2)).all(-1)  # [..., 8k]
        order = torch.argsort((~ok).to(torch.int8), dim=-1, stable=True)[..., :k]
        picked = torch.gather(pts, -2, order.unsqueeze(-1).expand(*order.shape, self.dim))
        keep = torch.gather(ok, -1, order).unsqueeze(-1)
        return torch.where(keep, picked, self.members[..., 0].center.unsqueeze(-2))

    def __repr__(self) -> str:
        return (f"ZonotopeBundle(dim={self.dim}, members={self.num_members}, "
                f"generators={self.num_generators}, batch_shape={tuple(self.batch_shape)})")


