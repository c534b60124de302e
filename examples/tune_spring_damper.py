"""Learning noise bounds and Stirling steps by gradient descent on set volume.

Parts (``--part``; each prints a table and writes JSON under ``--out``):

* ``bounds``: spring_damper simulated with its true bounds b* (vertex noise). HSNSMF starts
  from 5 b* and from 0.2 b*, is tuned with the consistency loss only (no ground truth; one
  shared scale for all bounds), and is audited on held-out vertex-noise trajectories.
* ``stirling``: tune the Stirling step h and the remainder margin (``remainder_margin``,
  starting from ``--margin-start`` x the process-noise radius; containment loss with ground
  truth, noise bounds fixed at b*) on ``bilinear`` (HSNSMF) and ``fermenter`` (HSNSMF);
  held-out containment and area before/after, and of the plain filter (margin 0).
* ``minkowski``: tune the Minkowski-weight scale (``minkowski_scale``, p = scale x the trace
  rule's p; any p > 0 keeps the guarantee) of CDSMF on ``spring_damper`` and ``bilinear``
  (containment loss with ground truth, windowed back-propagation ``tune(window=10)``, noise
  bounds and h fixed); held-out mean area and violations before/after. Not part of ``all``
  (about 3.5 min on a 2-core CPU): run it with ``--part minkowski``.
* ``grad``: the gradient of the log-area at every step of a 100-step horizon w.r.t. every
  hyperparameter (finite?).
* ``tightness``: outer/inner width ratios (diffsmf.tightness) of HSNSMF, MSZM and CDSMF on
  both Wang et al. 2022 examples (bilinear, spring_damper) at steps 5, 20 and the last.
* ``timing``: a 200-epoch run of 64 trajectories x 100 steps with windowed back-propagation
  (``tune(window=10)``, timed in full), and full-horizon back-propagation (a few epochs
  timed, extrapolated to 200); both from 5 b* with the consistency loss, held-out audit.

    python examples/tune_spring_damper.py --part bounds --epochs 40
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

import diffsmf as ds
from diffsmf.tuning import simulate_finite, tune
from diffsmf.tuning.loop import Data

torch.set_default_dtype(torch.float64)


def _fmt(v: list[float]) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def _audit(filt, test, chunk: int = 250) -> dict:
    """Mean area (k >= 1), violations (exact contains) and consistency on held-out data."""
    vols, viol, cons = [], 0, []
    with torch.no_grad():
        for s in range(0, test.y.shape[0], chunk):
            y, x = test.y[s : s + chunk], test.x[s : s + chunk]
            u = None if test.u is None else test.u[s : s + chunk]
            res = filt(y, u=u)
            vols.append(res.volume[:, 1:])
            viol += int((~res.sets.contains(x)).sum())
            cons.append(res.consistent[:, 1:].double())
    return {
        "mean_area": float(torch.cat(vols).mean()),
        "violations": viol,
        "consistent_frac": float(torch.cat(cons).mean()),
        "trajectories": int(test.y.shape[0]),
        "steps": int(test.y.shape[1]),
    }


def _head(tr, k: int):
    return type(tr)(tr.x[:k], tr.y[:k], None if tr.u is None else tr.u[:k], None)


def _horizon(system, cap: int) -> int:
    """The system's horizon (100 if it has none), at most ``cap`` steps."""
    return min(int(getattr(system, "horizon", 100) or 100), cap)


def _run_stats(rep) -> dict:
    """Epochs run, best epoch, seconds and skipped (non-finite) steps of a tuning report."""
    return {
        "epochs_run": len(rep.history),
        "best_epoch": rep.best_epoch,
        "seconds": rep.seconds,
        "nonfinite_steps": rep.nonfinite_steps,
    }


def part_bounds(a: argparse.Namespace) -> dict:
    sys_ = ds.systems.get("spring_damper")
    ref = ds.filters.HSNSMF(sys_)
    b_w = ref.process_half_widths.detach().clone()
    b_v = ref.measurement_half_widths.detach().clone()
    train = simulate_finite(sys_, a.train_steps, a.train, a.seed, "vertex")
    val = simulate_finite(sys_, a.train_steps, a.val, a.seed + 1, "vertex")
    test = simulate_finite(sys_, 100, a.test, a.seed + 2, "vertex")
    out = {"b_star": {"process_noise": b_w.tolist(), "measurement_noise": b_v.tolist()}}
    for start in [float(v) for v in a.bound_starts.split(",")]:
        f = ds.filters.HSNSMF(sys_, process_half_widths=start * b_w,
                              measurement_half_widths=start * b_v)
        # before-tuning audit on all held-out trajectories at 5 b* (the area reduction), on
        # the first 200 at 0.2 b* (only its consistency is of interest; saves CPU time)
        before = _audit(f, test if start > 1 else _head(test, 200))
        rep, f = tune(
            f,
            Data(train.y),  # no ground truth
            params=("process_noise", "measurement_noise"),
            tie="noise",
            loss="consistency",
            epochs=a.epochs,
            batch_size=a.batch_size,
            lr=a.lr,
            validation=Data(val.y),
            val_every=2,
            patience=a.patience,
            seed=a.seed,
            progress=not a.no_progress,
        )
        after = _audit(f, test)
        row = {
            "start": start,
            "learned": rep.final,
            "scale": rep.final["measurement_noise"][0] / float(b_v[0]),
            "before": before,
            "after": after,
            "area_reduction": 1 - after["mean_area"] / before["mean_area"] if start > 1 else None,
            **_run_stats(rep),
            "val_consistent_after": rep.validation_after["consistent_frac"],
        }
        out[f"start_{start}"] = row
        print(f"\nstart {start} b*: {len(rep.history)} epochs ({rep.seconds:.0f} s)")
        print(f"  process_noise      {_fmt(rep.final['process_noise'])}  b* {_fmt(b_w.tolist())}")
        print(
            f"  measurement_noise  {_fmt(rep.final['measurement_noise'])}  b* {_fmt(b_v.tolist())}"
        )
        print(f"  learned / b* = {row['scale']:.4f}")
        print(
            f"  held out ({after['trajectories']} vertex traj x 100): mean area "
            f"{before['mean_area']:.4g} -> {after['mean_area']:.4g} "
            f"({100 * (row['area_reduction'] or 0):.1f} % less); violations "
            f"{before['violations']} -> {after['violations']}; consistent "
            f"{before['consistent_frac']:.4f} -> {after['consistent_frac']:.4f}"
        )
    return out


def part_stirling(a: argparse.Namespace) -> dict:
    """Tune the Stirling step h and the remainder margin together (containment loss).

    The margin starts from ``--margin-start`` times the system's process-noise radius (a
    margin that starts at 0 stays 0 under the softplus scaling, so 0 tunes h alone); the plain
    filter (margin 0, h = 0.1) is audited on the same held-out data as a reference.
    """
    out = {}
    for name, fname in (("bilinear", "hsnsmf"), ("fermenter", "hsnsmf")):
        sys_ = ds.systems.get(name)
        steps = _horizon(sys_, a.stirling_steps)
        train = simulate_finite(sys_, steps, a.train, a.seed, "vertex")
        test = simulate_finite(sys_, steps, a.test_stirling, a.seed + 2, "vertex")
        cls = ds.filters.by_name(fname)
        plain = cls(sys_)
        w = plain.process_half_widths.detach().clone()  # process-noise radius b*_w
        m0 = a.margin_start * w
        f = cls(sys_, remainder_margin=m0)
        params = ("stirling_step", "remainder_margin") if a.margin_start > 0 else ("stirling_step",)
        h0 = f.stirling_step.detach().clone()
        ref = _audit(plain, test)
        before = _audit(f, test)
        rep, f = tune(
            f,
            train,
            params=params,
            loss="containment",
            epochs=a.stirling_epochs,
            batch_size=a.batch_size,
            lr=a.lr,
            validation=0.25,
            val_every=2,
            patience=a.patience,
            seed=a.seed,
            progress=not a.no_progress,
        )
        after = _audit(f, test)
        m1 = f.remainder_margin.detach().clone()
        out[name] = {
            "filter": fname,
            "steps": steps,
            "params": list(params),
            "process_noise_radius": w.tolist(),
            "h_before": h0.tolist(),
            "h_after": f.stirling_step.detach().tolist(),
            "margin_before": m0.tolist(),
            "margin_after": m1.tolist(),
            "plain_filter": ref,
            "before": before,
            "after": after,
            **_run_stats(rep),
        }
        print(
            f"\n{name} ({fname}, {steps} steps, tuned {', '.join(params)}; "
            f"{len(rep.history)} epochs, {rep.seconds:.0f} s):\n"
            f"  h {_fmt(h0.tolist())} -> {_fmt(out[name]['h_after'])}\n"
            f"  remainder-margin parameter: {_fmt(m0.tolist())} -> {_fmt(m1.tolist())} "
            f"(process-noise radius {_fmt(w.tolist())})\n"
            f"  mean area k>=1: {before['mean_area']:.4g} -> {after['mean_area']:.4g} "
            f"(plain filter, margin 0: {ref['mean_area']:.4g})\n"
            f"  held-out violations ({after['trajectories']} vertex traj x {steps}): "
            f"{before['violations']} -> {after['violations']} (plain filter: "
            f"{ref['violations']})"
        )
    return out


def part_minkowski(a: argparse.Namespace) -> dict:
    """Tune CDSMF's ``minkowski_scale`` alone (from 1 = the trace rule; containment loss)."""
    out = {}
    for name in ("spring_damper", "bilinear"):
        sys_ = ds.systems.get(name)
        steps = _horizon(sys_, a.minkowski_steps)
        train = simulate_finite(sys_, steps, a.minkowski_train, a.seed, "vertex")
        test = simulate_finite(sys_, steps, a.test_stirling, a.seed + 2, "vertex")
        f = ds.filters.CDSMF(sys_)
        before = _audit(f, test)
        rep, f = tune(
            f,
            train,
            params=("minkowski_scale",),
            loss="containment",
            epochs=a.minkowski_epochs,
            batch_size=a.minkowski_train,
            lr=a.lr,
            seed=a.seed,
            progress=not a.no_progress,
            window=a.minkowski_window,
        )
        after = _audit(f, test)
        s1 = float(f.minkowski_scale.detach())
        out[name] = {
            "filter": "cdsmf",
            "steps": steps,
            "train_trajectories": a.minkowski_train,
            "window": a.minkowski_window,
            "scale_after": s1,
            "before": before,
            "after": after,
            "area_reduction": 1 - after["mean_area"] / before["mean_area"],
            **_run_stats(rep),
        }
        print(
            f"\n{name} (CDSMF, {a.minkowski_train} train traj x {steps} steps, window "
            f"{a.minkowski_window}; {len(rep.history)} epochs, {rep.seconds:.0f} s):\n"
            f"  minkowski_scale 1 -> {s1:.4g}\n"
            f"  held out ({after['trajectories']} vertex traj x {steps}): mean area k>=1 "
            f"{before['mean_area']:.4g} -> {after['mean_area']:.4g} "
            f"({100 * out[name]['area_reduction']:.1f} % less); violations "
            f"{before['violations']} -> {after['violations']}"
        )
    return out


def part_grad(a: argparse.Namespace) -> dict:
    sys_ = ds.systems.get("spring_damper")
    tr = simulate_finite(sys_, 100, 4, a.seed + 5, "vertex")
    out = {}
    for fname in a.grad_filters.split(","):
        f = ds.filters.by_name(fname)(sys_)
        params = [p for p in f.parameters() if p.requires_grad]
        res = f(tr.y, u=tr.u)
        logv = torch.log(res.volume.clamp_min(1e-300)).mean(0)  # [T+1]
        bad = []
        t0 = time.perf_counter()
        for k in range(1, logv.shape[0]):
            g = torch.autograd.grad(logv[k], params, retain_graph=True, allow_unused=True)
            if not all(gi is None or torch.isfinite(gi).all() for gi in g):
                bad.append(k)
        out[fname] = {"steps": logv.shape[0] - 1, "nonfinite_steps": bad}
        print(
            f"{fname}: d log-area_k / d hyperparameters finite at "
            f"{logv.shape[0] - 1 - len(bad)}/{logv.shape[0] - 1} steps "
            f"({time.perf_counter() - t0:.0f} s){'; bad: ' + str(bad) if bad else ''}"
        )
    return out


def part_tightness(a: argparse.Namespace) -> dict:
    """Outer/inner width ratios of HSNSMF, MSZM, CDSMF on both Wang et al. 2022 examples."""
    from diffsmf.tightness import inner_bounds, tightness

    out = {}
    for name in ("bilinear", "spring_damper"):
        sys_ = ds.systems.get(name)
        T = int(getattr(sys_, "horizon", 100) or 100)
        tr = simulate_finite(sys_, T, 1, a.seed, "vertex")
        steps = [5, 20, T]
        t0 = time.perf_counter()
        inner = inner_bounds(ds.filters.HSNSMF(sys_), sys_, tr, steps, starts=a.starts)
        out[name] = {
            "inner_seconds": time.perf_counter() - t0,
            "solves": inner.solves,
            "feasible_solves": inner.feasible_solves,
        }
        print(
            f"\n{name}: inner estimates {inner.feasible_solves}/{inner.solves} feasible solves "
            f"({out[name]['inner_seconds']:.0f} s)"
        )
        print(f"{'filter':<8} {'step':>4} {'ratio x1':>9} {'ratio x2':>9} {'failures':>8}")
        for fname in ("hsnsmf", "mszm", "cdsmf"):
            rep = tightness(ds.filters.by_name(fname)(sys_), sys_, tr, steps, inner=inner)
            out[name][fname] = rep.to_dict()
            for k in steps:
                r = [row["ratio"] for row in rep.rows if row["step"] == k]
                nf = sum(1 for f in rep.failures if f["step"] == k)
                print(f"{fname:<8} {k:>4} {r[0]:>9.3f} {r[1]:>9.3f} {nf:>8}")
    return out


def part_timing(a: argparse.Namespace) -> dict:
    """200 epochs of 64 trajectories x 100 steps: windowed (timed in full) and full-horizon
    back-propagation (``--timing-epochs`` epochs timed, extrapolated to 200)."""
    sys_ = ds.systems.get("spring_damper")
    ref = ds.filters.HSNSMF(sys_)
    b_w = ref.process_half_widths.detach().clone()
    b_v = ref.measurement_half_widths.detach().clone()
    train = simulate_finite(sys_, 100, 64, a.seed, "vertex")
    test = simulate_finite(sys_, 100, a.test_timing, a.seed + 2, "vertex")
    out = {}
    for window, epochs in ((a.timing_window, 200), (None, a.timing_epochs)):
        f = ds.filters.HSNSMF(sys_, process_half_widths=5 * b_w,
                              measurement_half_widths=5 * b_v)
        before = _audit(f, test)
        rep, f = tune(
            f,
            Data(train.y),
            params=("process_noise", "measurement_noise", "stirling_step"),
            tie="noise",
            loss="consistency",
            epochs=epochs,
            batch_size=64,
            lr=a.lr,
            seed=a.seed,
            progress=not a.no_progress,
            window=window,
        )
        after = _audit(f, test)
        per_epoch = rep.seconds / epochs
        key = f"window_{window}" if window else "full_horizon"
        out[key] = {
            "epochs": epochs,
            "seconds": rep.seconds,
            "per_epoch": per_epoch,
            "seconds_200_epochs": 200 * per_epoch,
            "scale": rep.final["measurement_noise"][0] / float(b_v[0]),
            "stirling_step": rep.final["stirling_step"],
            "before": before,
            "after": after,
        }
        how = f"window {window}" if window else "full horizon"
        print(
            f"\ntiming, {how}: {epochs} epochs of 64 x 100 (HSNSMF, from 5 b*): "
            f"{rep.seconds:.1f} s, {per_epoch:.3f} s/epoch -> 200 epochs "
            f"{200 * per_epoch:.0f} s ({200 * per_epoch / 60:.2f} min; torch threads "
            f"{torch.get_num_threads()})\n  learned / b* = {out[key]['scale']:.4f}, h "
            f"{_fmt(rep.final['stirling_step'])}; held out ({after['trajectories']} vertex traj "
            f"x 100): mean area {before['mean_area']:.4g} -> {after['mean_area']:.4g}, "
            f"violations {before['violations']} -> {after['violations']}"
        )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--part",
        default="all",
        choices=["all", "bounds", "stirling", "minkowski", "grad", "timing", "tightness"],
    )
    p.add_argument("--epochs", type=int, default=40)
    p.add_argument("--stirling-epochs", type=int, default=20)
    p.add_argument("--stirling-steps", type=int, default=100)
    p.add_argument("--train", type=int, default=32)
    p.add_argument("--val", type=int, default=16)
    p.add_argument("--test", type=int, default=1000)
    p.add_argument("--test-stirling", type=int, default=200)
    p.add_argument(
        "--margin-start",
        type=float,
        default=1.0,
        help="initial remainder margin / process-noise radius (stirling part; 0: h only)",
    )
    p.add_argument("--minkowski-epochs", type=int, default=15)
    p.add_argument("--minkowski-steps", type=int, default=100)
    p.add_argument("--minkowski-train", type=int, default=32, help="training trajectories")
    p.add_argument("--minkowski-window", type=int, default=10, help="tune(window=...)")
    p.add_argument("--train-steps", type=int, default=50)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=0.2)
    p.add_argument("--patience", type=int, default=6)
    p.add_argument("--timing-epochs", type=int, default=3, help="full-horizon epochs timed")
    p.add_argument("--timing-window", type=int, default=10, help="window of the 200-epoch run")
    p.add_argument("--test-timing", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--bound-starts", default="5,0.2", help="initial bounds / b*")
    p.add_argument("--grad-filters", default="hsnsmf,cdsmf,mszm")
    p.add_argument("--starts", type=int, default=2, help="optimiser starts (tightness)")
    p.add_argument("--out", default="out/training")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args()
    parts = ["bounds", "stirling", "grad", "timing", "tightness"]
    parts = parts if a.part == "all" else [a.part]
    outdir = Path(a.out)
    outdir.mkdir(parents=True, exist_ok=True)
    for part in parts:
        t0 = time.perf_counter()
        res = globals()[f"part_{part}"](a)
        res["wall_seconds"] = time.perf_counter() - t0
        (outdir / f"{part}.json").write_text(json.dumps(res, indent=2, default=str))
        print(f"[{part}] {res['wall_seconds']:.0f} s -> {outdir / (part + '.json')}")


if __name__ == "__main__":
    main()
