"""Containment audit: does a filter's set contain the true state, on many simulated runs?

``containment(filter, system, trials, steps, noise)`` simulates ``trials`` trajectories (one
batch), filters them, and counts the (trajectory, step) pairs whose true state is outside the
set. The size of a miss is the *normalised distance outside*: ``gauge(x) - 1``, where
``gauge(x)`` is the factor by which the set must be scaled about its centre to reach ``x``
(``||T^-1 (x - c)||_inf`` for a parallelotope, the Mahalanobis radius for an ellipsoid, the
smallest ``||alpha||_inf`` with ``G alpha = x - c`` for a zonotope, by LP). A pair counts as a
violation when ``gauge(x) > 1 + tol`` (default ``tol = 1e-9``: scale-free, i.e. a relative
tolerance). Pairs whose set the filter flagged unbounded (it diverged and says so: bounds
+-inf) are counted apart (``AuditReport.unbounded``), not as violations.

Command line: ``diffsmf audit --system spring_damper --filter hsnsmf --trials 1000``.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.optimize import linprog
from torch import Tensor

from diffsmf.convex import ConvexSet, as_vector
from diffsmf.filters import is_guaranteed
from diffsmf.filters.base import check_filter
from diffsmf.filters.presets import filter_name
from diffsmf.sets import Ellipsoid, Interval, Parallelotope, Zonotope, ZonotopeBundle
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope, distance_lp
from diffsmf.systems.system import check_system
from diffsmf.tightness import TightnessReport, inner_bounds, tightness  # noqa: F401 (re-exported)
from diffsmf.utils import HIGHS_OPTIONS, is_int, progress_bar

__all__ = [
    "AuditReport", "containment", "gauge", "gaussian_note", "has_gaussian_noise", "paper_steps",
]

TOL = 1e-9
#: Trajectories filtered per batch with ``progress`` or ``on_chunk`` (`containment`).
CHUNK = 100

def paper_steps(system) -> int:
    """Horizon of a system: its ``horizon`` attribute (the built-ins carry the papers'), or 100."""
    return int(getattr(system, "horizon", None) or 100)


@dataclass
class AuditReport:
    """Result of `containment`."""

    filter: str
    system: str
    noise: str
    trials: int
    steps: int
    pairs: int
    violations: int
    fraction: float
    worst_distance: float
    mean_volume: float
    inconsistent: int
    seconds: float
    #: (trajectory, step) pairs whose set the filter flagged unbounded (``bounded`` False: it
    #: gave up on that trajectory, its bounds are +-inf, the set is R^n). Such a pair is never
    #: counted outside (the placeholder set that the result carries is not a claim), so a
    #: filter that diverges passes the count of violations vacuously: read both.
    unbounded: int = 0

    def __str__(self) -> str:
        return (
            f"{self.filter} on {self.system} ({self.noise} noise, {self.trials} trajectories x "
            f"{self.steps} steps): {self.violations}/{self.pairs} pairs outside "
            f"(fraction {self.fraction:.3g}, worst normalised distance outside "
            f"{self.worst_distance:.3g}), mean volume {self.mean_volume:.4g}, "
            f"{self.inconsistent} inconsistent steps, {self.unbounded} unbounded pairs, "
            f"{self.seconds:.2f} s"
        )


def _zonotope_gauge_lp(c: np.ndarray, G: np.ndarray, x: np.ndarray) -> float:
    """``min ||a||_inf s.t. G a = x - c`` (scipy linprog) for one point."""
    n, m = G.shape
    # variables [a (m), t]; minimise t; -t <= a_i <= t
    cost = np.zeros(m + 1)
    cost[-1] = 1.0
    A_ub = np.zeros((2 * m, m + 1))
    A_ub[:m, :m] = np.eye(m)
    A_ub[m:, :m] = -np.eye(m)
    A_ub[:, -1] = -1.0
    A_eq = np.hstack([G, np.zeros((n, 1))])
    res = linprog(
        cost, A_ub=A_ub, b_ub=np.zeros(2 * m), A_eq=A_eq, b_eq=x - c,
        bounds=[(None, None)] * m + [(0, None)], method="highs", options=HIGHS_OPTIONS,
    )
    return float(res.x[-1]) if res.status == 0 else float("inf")


def gauge(S: ConvexSet, x: Tensor, tol: float = TOL) -> Tensor:
    """Scale factor about the centre at which ``S`` reaches ``x`` -> ``[...]`` (detached).

    0 at the unbounded elements of a filter result (``mark_unbounded``: all of R^n there).
    Exact for Interval, Parallelotope, Ellipsoid. For a Zonotope, points that ``contains``
    accepts (with ``atol = tol * scale``) get gauge 0 (not computed) and the others an LP. For
    a ConstrainedZonotope (whose centre may lie outside it) points that ``contains`` accepts
    (not proved farther than ``tol * scale``) get 0 and the others ``1 + distance / scale``
    (HiGHS distance; > 1 means outside). For a ZonotopeBundle, the largest of its members'
    gauges (each about its own centre: above 1 exactly where x is outside the bundle).
    """
    from diffsmf.filters.events import is_marked

    if is_marked(S):  # a filter result's unbounded elements are all of R^n: gauge 0 there
        g = gauge(S._plain(), x, tol)
        return torch.where(S.bounded, g, torch.zeros_like(g))
    S = S.detach()
    x = as_vector("x", x, S.center, S.dim).detach()
    c = S.center
    if isinstance(S, Interval):
        r = S.radius.clamp_min(1e-300)
        return ((x - c).abs() / r).amax(-1)
    if isinstance(S, Parallelotope):
        a = torch.linalg.solve(S.T, (x - c).unsqueeze(-1)).squeeze(-1)
        return a.abs().amax(-1)
    if isinstance(S, Ellipsoid):
        return S.mahalanobis2(x).clamp_min(0).sqrt()
    if isinstance(S, ZonotopeBundle):  # outside the bundle = outside some member
        return gauge(S.members, x.unsqueeze(-2), tol).amax(-1)
    if isinstance(S, Zonotope):
        scale = 1.0 + x.abs().amax(-1) + S.generators.abs().sum(-1).amax(-1)
        inside = S.contains(x, atol=tol * float(scale.max()))
        g = torch.zeros(inside.shape, dtype=x.dtype)
        bad = (~inside).nonzero()
        cb = c.expand(*inside.shape, c.shape[-1])
        Gb = S.generators.expand(*inside.shape, *S.generators.shape[-2:])
        xb = x.expand(*inside.shape, x.shape[-1])
        for idx in bad.tolist():
            i = tuple(idx)
            g[i] = _zonotope_gauge_lp(cb[i].numpy(), Gb[i].numpy(), xb[i].numpy())
        return g
    if isinstance(S, ConstrainedZonotope):
        # the centre need not lie in a constrained zonotope: points that ``contains``
        # accepts get gauge 0, the others 1 + (HiGHS distance to the set) / scale, so a
        # violation (gauge > 1 + tol) is exactly a point farther than tol * scale
        scale = 1.0 + x.abs().amax(-1) + S.generators.abs().sum(-1).amax(-1)
        inside = S.contains(x, atol=tol * float(scale.max()))
        g = torch.zeros(inside.shape, dtype=x.dtype)
        out = ~inside
        if bool(out.any()):  # HiGHS on the uncertified pairs only
            sh = inside.shape
            d = distance_lp(S.expand(sh)[out], x.expand(*sh, x.shape[-1])[out]).to(x.dtype)
            g[out] = 1.0 + d / scale.expand(sh)[out]
        return g
    raise ValueError(f"S: no gauge for set type {type(S).__name__}")


def containment(
    filt: torch.nn.Module,
    system=None,
    trials: int = 1000,
    steps: int | None = None,
    noise: str = "vertex",
    seed: int = 0,
    tol: float = TOL,
    progress: bool = False,
    first: int = 0,
    count: int | None = None,
    on_chunk: Callable[[dict], None] | None = None,
) -> AuditReport:
    """Containment audit of ``filt`` (a `SetFilter`) on ``system``.

    Args:
        filt: the filter (its own ``system`` is used when ``system`` is None).
        trials: number of simulated trajectories (one batch).
        steps: horizon (default `paper_steps`).
        noise: ``"vertex"`` (worst case) or ``"uniform"``.
        seed: seed of the simulation.
        tol: relative tolerance on the gauge.
        progress: ``True`` (or a bar factory, `diffsmf.utils.progress_bar`): a progress bar
            over trajectories with the running counts of outside pairs and inconsistent
            steps (the batch is then filtered in chunks of at most `CHUNK` trajectories;
            the counts are the same).
        first, count: audit only the trajectories ``first .. first + count - 1`` of the
            ``trials`` simulated ones (default: all), e.g. to split a long audit into runs;
            the trajectories are the same as in the whole audit.
        on_chunk: called after each chunk of at most `CHUNK` trajectories (chunking
            as with ``progress``) with a dict of its counts: ``start``, ``stop`` (trajectory
            indices), ``violations``, ``pairs``, ``worst_distance``, ``volume_sum`` (over
            its trajectories and steps 1..T), ``inconsistent``, ``seconds``, ``unbounded``
            (pairs flagged unbounded, steps 0..T); a log of these
            lets an audit that is stopped resume (``benchmarks/filters_audit.py --log``).

    Returns:
        `AuditReport` over the audited trajectories. ``mean_volume`` averages over
        trajectories and steps 1..T.
    """
    check_filter("filt", filt, None if system is None else check_system("system", system))
    system = filt.system if system is None else system
    count = _check_audit_args(trials, steps, tol, first, count)
    steps = paper_steps(system) if steps is None else steps
    if has_gaussian_noise(system) and is_guaranteed(filt):
        warnings.warn(
            f"containment: {gaussian_note(system)} (audit {type(filt).__name__} on the system "
            "built without the Gaussian part)",
            stacklevel=2,
        )
    traj = system.simulate(steps=steps, batch=trials, seed=seed, noise=noise)
    chunk = CHUNK if progress or on_chunk is not None else count
    viol_n, worst, vol_sum, incons, unb, seconds = 0, 0.0, 0.0, 0, 0, 0.0
    bar = progress_bar(progress, count, f"audit ({noise} noise)", "traj")
    for i in range(first, first + count, chunk):
        j = min(i + chunk, first + count)
        part = _audit_chunk(filt, traj, i, j, steps, tol)
        viol_n += part["violations"]
        worst = max(worst, part["worst_distance"])
        vol_sum += part["volume_sum"]
        incons += part["inconsistent"]
        unb += part["unbounded"]
        seconds += part["seconds"]
        if on_chunk is not None:
            on_chunk(part)
        if bar is not None:  # running counts: a stopped audit still tells what it checked
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(outside=viol_n, inconsistent=incons, unbounded=unb,
                                refresh=False)
            bar.update(j - i)
    if bar is not None:
        bar.close()
    pairs = count * (steps + 1)
    return AuditReport(
        filter=filter_name(filt),
        system=system.name,
        noise=noise,
        trials=count,
        steps=steps,
        pairs=pairs,
        violations=viol_n,
        fraction=viol_n / pairs,
        worst_distance=worst,
        mean_volume=vol_sum / (count * steps),
        inconsistent=incons,
        seconds=seconds,
        unbounded=unb,
    )


def has_gaussian_noise(system) -> bool:
    """True when ``system`` simulates Gaussian noise (``process_cov`` or ``measurement_cov``)
    besides its bounded sets: no set-membership filter's guarantee covers that part."""
    return system.process_cov is not None or system.measurement_cov is not None


def gaussian_note(system) -> str:
    """What the audit says of a system with Gaussian noise (API warning and CLI note)."""
    return (
        f"{system.name} has Gaussian noise (process_cov / measurement_cov) besides its bounded "
        "sets, which no set filter bounds, so pairs outside are expected here and are no "
        "violation of a guarantee"
    )


def _check_audit_args(trials: Any, steps: Any, tol: Any, first: Any, count: Any) -> int:
    """Validate `containment`'s counts (errors name the argument) -> ``count`` resolved."""
    if not is_int(trials) or trials < 1:
        raise ValueError(f"trials: must be an integer >= 1, got {trials!r}")
    if steps is not None and (not is_int(steps) or steps < 1):
        raise ValueError(f"steps: must be an integer >= 1 or None, got {steps!r}")
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and 0 <= tol < 1):
        raise ValueError(f"tol: must be a number in [0, 1) (relative gauge tolerance), got {tol!r}")
    if not is_int(first) or not 0 <= first < trials:
        raise ValueError(
            f"first: must be an integer in 0..{trials - 1} (trials = {trials}), got {first!r}"
        )
    count = trials - first if count is None else count
    if not is_int(count) or not 1 <= count <= trials - first:
        raise ValueError(
            f"count: must be an integer in 1..{trials - first} (trajectories {first}.."
            f"{trials - 1} of {trials}), got {count!r}"
        )
    return count


def _audit_chunk(filt: torch.nn.Module, traj: Any, i: int, j: int, steps: int, tol: float
                 ) -> dict:
    """Filter trajectories ``i .. j - 1`` of ``traj`` and count them (`containment`'s
    ``on_chunk`` dict)."""
    x = traj.x[i:j]
    u = None if traj.u is None else traj.u[i:j]
    t0 = time.perf_counter()
    with torch.no_grad():
        res = filt(traj.y[i:j], u=u)
    dt = time.perf_counter() - t0
    g = gauge(res.sets, x, tol)  # [b, T+1]
    if res.bounded is not None:  # flagged unbounded: the set is R^n (counted apart)
        g = torch.where(res.bounded, g, torch.zeros_like(g))
    return {
        "start": i, "stop": j, "violations": int((g > 1 + tol).sum()),
        "pairs": (j - i) * (steps + 1),
        "worst_distance": float((g - 1).clamp_min(0).max()),
        "volume_sum": float(res.volume[:, 1:].sum()),
        "inconsistent": int((~res.consistent).sum()), "seconds": dt,
        "unbounded": 0 if res.bounded is None else int((~res.bounded).sum()),
    }
