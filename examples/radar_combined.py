"""Jiang et al. 2016, sec. 3: radar tracking with Gaussian + bounded noise, EKF vs ESMF vs combined
filter.

Runs ``--runs`` Monte Carlo trajectories (default 100, batched) of the ``radar`` system for
``--steps`` steps (default 100; the paper does not state its horizon), filters them with

* ``EKF`` (diffsmf.filters.EKF): covariances from the bounds (uniform variance r^2/3 of each
  noise box half-width) plus the Gaussian parts; initial covariance from ``x0_set``'s hull;
* ``ESMF`` (diffsmf.filters.ESMF, Song et al. 2017): a pure set-membership filter, so the Gaussian
parts
  are folded into the bounds as 3-sigma ellipsoids (Jiang et al. 2016, sec. 1.1 suggests 3 sigma):
  ``D (+) F(0, 9 Q)`` and ``E (+) F(0, 9 R)``, outer Minkowski sums of minimal trace;
* ``CombinedFilter`` (Jiang et al. 2016, eq. 39-57): Kalman centre/covariance with the Gaussian
parts,
  ellipsoidal mean set with the bounded parts, statistical linearisation of the measurement;
* ``SMF (set gain)``: ``CombinedFilter(gain="set")`` on the 3-sigma system, i.e. a pure
  ellipsoidal set-membership filter with statistical linearisation (our stand-in next to
  Song et al. 2017's ESMF, not a paper row),

and prints position and velocity RMSE (per-step RMSE over the runs, averaged over the steps)
next to the paper's Table 1. The true initial state is the paper's x0 = [200, 12, 200, 10]
(the centre of every filter's initial set). Writes ``out/radar_combined.png`` (trajectory of
run 0 with mean sets every 10 steps) and ``out/radar_combined_rmse.png``.

    python examples/radar_combined.py [--runs 100] [--steps 100] [--seed 0] [--noise uniform]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import diffsmf as ds
from diffsmf.filters.combined import CombinedFilter, outer_sum_shape
from diffsmf.sets import Ellipsoid
from diffsmf.systems import System
from diffsmf.systems.radar import RADAR_X0, radar_initial_cov

PAPER = {
    "EKF": (11.2541, 1.9795),
    "ESMF": (17.7999, 3.3716),
    "Combined": (13.5249, 2.1869),
    "SMF (set gain)": (float("nan"), float("nan")),
}


def esmf_view(sys: System) -> System:
    """The radar system with Gaussian parts folded into 3-sigma bounds (for a pure SMF)."""
    D = outer_sum_shape(sys.process_noise.shape, 9.0 * sys.process_cov)
    E = outer_sum_shape(sys.measurement_noise.shape, 9.0 * sys.measurement_cov)
    return System(
        sys.f,
        sys.h,
        sys.x0_set,
        Ellipsoid(torch.zeros(4, dtype=torch.float64), D),
        Ellipsoid(torch.zeros(2, dtype=torch.float64), E),
        name="radar-3sigma",
    )


def rmse(center: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-step RMSE over the runs of position and velocity ``[T]`` (steps 1..T)."""
    e = center[:, 1:] - x[:, 1:]
    pos = e[..., [0, 2]].pow(2).sum(-1).mean(0).sqrt()
    vel = e[..., [1, 3]].pow(2).sum(-1).mean(0).sqrt()
    return pos, vel


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", default="uniform", choices=["uniform", "vertex"],
                    help="how the bounded noise is drawn inside its ellipsoid")
    ap.add_argument("--out", default="out")
    args = ap.parse_args()
    torch.set_num_threads(1)
    sys = ds.systems.get("radar")
    x0 = torch.tensor(RADAR_X0, dtype=torch.float64).expand(args.runs, 4)
    traj = sys.simulate(args.steps, batch=args.runs, seed=args.seed, x0=x0, noise=args.noise)
    sys3 = esmf_view(sys)

    filters = {
        "EKF": ds.filters.EKF(sys),
        "ESMF": ds.filters.ESMF(sys3),
        "Combined": CombinedFilter(sys, initial_cov=radar_initial_cov()),
        "SMF (set gain)": CombinedFilter(sys3, initial_cov=radar_initial_cov(), gain="set"),
    }
    results, rows, failed = {}, [], {}
    for name, filt in filters.items():
        t0 = time.perf_counter()
        try:
            with torch.no_grad():
                res = filt(traj.y)
        except (NotImplementedError, ValueError, RuntimeError) as exc:  # report, don't hide
            failed[name] = f"{type(exc).__name__}: {exc}"
            continue
        secs = time.perf_counter() - t0
        pos, vel = rmse(res.center, traj.x)
        results[name] = (res, pos, vel)
        inside = res.sets.contains(traj.x, atol=1e-9).double().mean().item()
        rows.append((name, pos.mean().item(), vel.mean().item(), *PAPER[name], inside, secs))

    print(f"radar, {args.runs} Monte Carlo runs x {args.steps} steps (seed {args.seed}, "
          f"{args.noise} bounded noise)")
    print(f"{'filter':<15} {'pos RMSE':>9} {'paper':>8} {'vel RMSE':>9} {'paper':>7}"
          f" {'x in set':>9} {'seconds':>8}")
    for name, p, v, pp, pv, inside, secs in rows:
        print(f"{name:<15} {p:9.4f} {pp:8.4f} {v:9.4f} {pv:7.4f} {inside:9.3f} {secs:8.2f}")
    for name, msg in failed.items():
        pp, pv = PAPER[name]
        print(f"{name:<15} {'failed':>9} {pp:8.4f} {'-':>9} {pv:7.4f}   ({msg})")
    res_c = results["Combined"][0]
    region = res_c.confidence_region(k=3.0)
    print(f"combined 3-sigma region (mean set (+) F(0, 9P)) contains x: "
          f"{region.contains(traj.x, atol=1e-9).double().mean().item():.3f}")
    print("('x in set': fraction of (run, step) where the true state lies in the filter's set;"
          " EKF's set is its 3-sigma ellipsoid)")
    _figures(Path(args.out), traj, results)


def _figures(out: Path, traj, results) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffsmf.plot import plot_set

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 6))
    x = traj.x[0]
    ax.plot(x[:, 0], x[:, 2], "k-", lw=1.5, label="true")
    styles = {"EKF": "C0--", "ESMF": "C1:", "Combined": "C2-", "SMF (set gain)": "C3-."}
    for name, (res, _, _) in results.items():
        c = res.center[0]
        ax.plot(c[:, 0], c[:, 2], styles[name], lw=1, label=name)
    res_c = results["Combined"][0]
    region = res_c.confidence_region(k=3.0)
    T = res_c.center.shape[1] - 1
    for k in range(0, T + 1, 10):
        plot_set(ax, res_c.sets[0, k], dims=(0, 2), edgecolor="C2", linewidth=0.8)
        plot_set(ax, region[0, k], dims=(0, 2), edgecolor="C2", linewidth=0.6, linestyle="--")
        ax.plot(res_c.center[0, k, 0], res_c.center[0, k, 2], "C2*", ms=6)
    ax.set_xlabel("x1 (m)")
    ax.set_ylabel("x2 (m)")
    ax.set_title("radar tracking: combined mean sets (solid) and 3-sigma regions\n"
                 "(mean set (+) F(0, 9P), dashed) every 10 steps", fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "radar_combined.png", dpi=90)
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.5))
    for name, (_, pos, vel) in results.items():
        axs[0].plot(range(1, len(pos) + 1), pos, label=name)
        axs[1].plot(range(1, len(vel) + 1), vel, label=name)
    axs[0].set_ylabel("position RMSE (m)")
    axs[1].set_ylabel("velocity RMSE (m/s)")
    for a in axs:
        a.set_xlabel("step")
        a.legend()
    fig.tight_layout()
    fig.savefig(out / "radar_combined_rmse.png", dpi=90)
    print(f"figures: {out / 'radar_combined.png'}, {out / 'radar_combined_rmse.png'}")


if __name__ == "__main__":
    main()
