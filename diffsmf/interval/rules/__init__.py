"""Inclusion rules, one per ATen operation, and the registry that maps ops to rules.

A rule receives the evaluated arguments of one node of a captured model program and returns
its enclosure. A tensor argument is a `Jet` (it depends on the
inputs enclosed), a plain ``Tensor`` (a constant of the program, or a point input such as
``u``) or a `BoolBox` (a comparison of enclosed values). Every argument carries extra
*leading* dims that the captured graph does not know about (the caller's batch dims, and the
tangent dims of gradients and Hessians); a rule applies the op's shape and dim arguments to
the *trailing* dims only, so one rule serves values, gradients and Hessians alike. ``ctx`` gives
the captured rank of each argument and of the result.

Rules never raise for numerical reasons. Where a box reaches outside an op's domain (``sqrt``,
``log`` or a real power of a box reaching below 0, ``asin`` outside ``[-1, 1]``), only its part
inside the domain is enclosed: the true states lie there (the model is evaluated on them). The
value of ``log`` at 0 is then ``-inf`` (the filters flag the trajectory's set as unbounded).
Where no such bound exists (a box across a pole of ``tan``) the enclosure of that element is
NaN, which the filters flag as a domain event for that trajectory.

Register a rule for a further op with `register` (see the "Writing models" docs page).

The rules live by kind: `moving` (views, indexing, joins, constants), `arithmetic`,
`elementwise` (smooth functions), `nonsmooth` (kinks), `branches` (comparisons and
``where``) and `reductions` (sums, products, norms, matrix products); `base` holds the
registry and the helpers every rule is written with. Importing this package registers them all.
"""

from __future__ import annotations

from diffsmf.interval.rules import (  # noqa: F401  (each module registers its rules)
    arithmetic,
    branches,
    elementwise,
    moving,
    nonsmooth,
    reductions,
)
from diffsmf.interval.rules.base import (
    CATEGORIES,
    RULES,
    BoolBox,
    Ctx,
    register,
    supported_ops,
)

__all__ = ["CATEGORIES", "RULES", "BoolBox", "Ctx", "register", "supported_ops"]
