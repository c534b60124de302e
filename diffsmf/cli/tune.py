"""Tune a filter's noise bounds (and step sizes) on simulated data of a built-in system.

    diffsmf tune --system spring_damper --filter hsnsmf --epochs 200 --out runs/sd
    diffsmf tune --config sd.toml
    torchrun --nproc_per_node 2 -m diffsmf tune ...      # data-parallel (gloo / NCCL)

Writes ``hyperparameters.json`` (initial, tuned and true bounds), ``report.json``,
``loss_curve.csv`` and ``tuning.png`` (loss curve and mean set area before/after on held-out
trajectories) to ``--out``. The loop itself is `diffsmf.tuning.loop.tune`.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch

import diffsmf as ds
from diffsmf.filters.base import SetFilter
from diffsmf.tuning import ddp
from diffsmf.tuning.config import TuneConfig, load_config
from diffsmf.tuning.loop import LOSS_MODES, Data, TuneReport, evaluate, simulate_finite, tune
from diffsmf.tuning.losses import LossWeights

__all__ = ["add_arguments", "build", "main"]


# ---------------------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``diffsmf tune`` (defaults: `TuneConfig`)."""
    d = TuneConfig()
    a = parser.add_argument
    a("--config", default=None, help="TOML file of options (command-line values win)")
    a("--system", default=d.system,
      help="built-in system name (ds.systems.names()); NAME:N for a sized system")
    a("--filter", default=d.filter, help="filter name (ds.filters.by_name)")
    a("--epochs", type=int, default=d.epochs)
    a("--batch-size", type=int, default=d.batch_size)
    a("--trajectories", type=int, default=d.trajectories, help="training trajectories")
    a("--val-trajectories", type=int, default=d.val_trajectories)
    a("--test-trajectories", type=int, default=d.test_trajectories, help="held-out audit")
    a("--steps", type=int, default=d.steps, help="horizon of each trajectory")
    a("--noise", default=d.noise, choices=["uniform", "vertex"], help="simulated noise")
    a("--init-scale", type=float, default=d.init_scale, help="start from init_scale * b*")
    a("--ground-truth", action="store_true", help="train with the true states")
    a("--loss", default=d.loss, choices=list(LOSS_MODES))
    a(
        "--params",
        default=",".join(d.params),
        help="comma-separated hyperparameter names (process_noise, measurement_noise, "
        "stirling_step, remainder_margin, minkowski_scale)",
    )
    a("--tie", default=d.tie, choices=["auto", "noise", "none"], help="shared noise scale")
    a("--optimizer", default=d.optimizer, choices=["adam", "adamw", "sgd"])
    a("--lr", type=float, default=d.lr)
    a("--patience", type=int, default=d.patience)
    a("--val-every", type=int, default=d.val_every)
    a("--checkpoint-every", type=int, default=d.checkpoint_every)
    a("--seed", type=int, default=d.seed)
    a(
        "--window",
        type=int,
        default=d.window,
        help="truncated back-propagation: steps per window, all windows side by side "
        "(about steps/window times faster; 0 = back-propagate through the whole horizon)",
    )
    a(
        "--compile",
        action="store_true",
        help="tune through the compiled filter step (filt.compile(): a one-off compile of "
        "1-3 minutes, then 5-8x faster epochs)",
    )
    a("--out", default=d.out, help="output folder (created when missing)")
    a("--no-progress", "--quiet", dest="progress", action="store_false", help="no progress bar")


def _merge_config(args: argparse.Namespace) -> TuneConfig:
    """TuneConfig from parsed args, with ``--config`` values where the CLI kept its default."""
    d = TuneConfig()
    vals = {k: getattr(args, k) for k in TuneConfig.keys() if hasattr(args, k)}
    if isinstance(vals.get("params"), str):
        vals["params"] = [p for p in vals["params"].split(",") if p]
    if getattr(args, "config", None):
        for k, v in load_config(args.config).items():
            if k not in vals or vals[k] == getattr(d, k):
                vals[k] = v
    return TuneConfig(**vals)


def _check_config(cfg: TuneConfig) -> None:
    """One ``ValueError`` naming the option for each user error in a run configuration."""
    ds.systems.check_name(cfg.system, option="--system")
    try:
        ds.filters.by_name(cfg.filter)
    except ValueError:
        raise ValueError(
            f"--filter: unknown filter {cfg.filter!r}; choose from {ds.filters.names()}"
        ) from None
    for key in ("epochs", "batch_size", "trajectories", "steps", "val_every"):
        if getattr(cfg, key) < 1:
            raise ValueError(f"--{key.replace('_', '-')}: must be >= 1, got {getattr(cfg, key)}")
    for key in ("val_trajectories", "test_trajectories", "patience", "window"):
        if getattr(cfg, key) < 0:
            raise ValueError(f"--{key.replace('_', '-')}: must be >= 0, got {getattr(cfg, key)}")
    if cfg.checkpoint_every < 1:
        raise ValueError(f"--checkpoint-every: must be >= 1, got {cfg.checkpoint_every}")
    if not cfg.lr > 0:
        raise ValueError(f"--lr: must be > 0, got {cfg.lr}")
    if not cfg.init_scale > 0:
        raise ValueError(f"--init-scale: must be > 0, got {cfg.init_scale}")
    if not cfg.params:
        raise ValueError("--params: name at least one hyperparameter to tune")
    known = [f.name for f in fields(LossWeights)]
    unknown = sorted(set(cfg.weights) - set(known))
    if unknown:
        raise ValueError(f"config: weights: unknown loss weights {unknown}; allowed: {known}")
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {str(out)!r} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--out: cannot create folder {str(out)!r} ({exc.strerror})") from None


def build(cfg: TuneConfig) -> tuple[Any, SetFilter, dict[str, Any]]:
    """System, filter (bounds scaled by ``init_scale``) and simulated data of a config."""
    system = ds.systems.get(cfg.system)
    try:
        filt = ds.filters.by_name(cfg.filter)(system, **cfg.filter_kwargs)
    except TypeError as exc:
        if "unexpected keyword" not in str(exc):
            raise
        raise ValueError(f"config: filter_kwargs: {exc}") from None
    true = {
        "process_noise": filt.process_noise.detach().clone(),
        "measurement_noise": filt.measurement_noise.detach().clone(),
    }
    if cfg.init_scale != 1.0:
        filt.process_noise = true["process_noise"] * cfg.init_scale
        filt.measurement_noise = true["measurement_noise"] * cfg.init_scale
    sim = {
        split: simulate_finite(system, cfg.steps, b, cfg.seed + off, cfg.noise)
        for split, b, off in (
            ("train", cfg.trajectories, 0),
            ("val", cfg.val_trajectories, 1),
            ("test", cfg.test_trajectories, 2),
        )
        if b > 0
    }
    return system, filt, {"true": true, **sim}


def _strip_x(traj: Any) -> Data:
    return Data(y=traj.y, x=None, u=traj.u)


def _write_outputs(
    out: Path, cfg: TuneConfig, report: TuneReport, before: Any, after: Any, test: Any, true: dict
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    hp = {
        "system": cfg.system,
        "filter": cfg.filter,
        "true_bounds": {k: v.tolist() for k, v in true.items()},
        "initial": report.initial,
        "tuned": report.final,
        "best_epoch": report.best_epoch,
        "seconds": report.seconds,
    }
    (out / "hyperparameters.json").write_text(json.dumps(hp, indent=2))
    (out / "report.json").write_text(json.dumps(report.to_dict(), indent=2, default=str))
    keys = sorted({k for r in report.history for k in r})
    with (out / "loss_curve.csv").open("w") as fh:
        fh.write(",".join(keys) + "\n")
        for r in report.history:
            fh.write(",".join("" if k not in r else f"{r[k]:.10g}" for k in keys) + "\n")
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ep = [r["epoch"] for r in report.history]
    ax[0].plot(ep, [r["loss"] for r in report.history], label="train loss")
    vv = [(r["epoch"], r["val_loss"]) for r in report.history if "val_loss" in r]
    if vv:
        ax[0].plot(*zip(*vv), "o-", label="validation loss")
    ax[0].set_xlabel("epoch")
    ax[0].set_ylabel(f"loss ({cfg.loss}: log-volume + penalty)")
    ax[0].xaxis.get_major_locator().set_params(integer=True)
    ax[0].legend()
    ax[0].set_title("loss")
    if before is not None and after is not None:
        k = torch.arange(before.shape[-1])
        ax[1].semilogy(k, before, label="before tuning")
        ax[1].semilogy(k, after, label="after tuning")
        ax[1].set_xlabel("step k")
        ax[1].set_ylabel("mean set area / volume")
        ax[1].set_title(f"mean set area, {test} held-out trajectories")
        ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "tuning.png", dpi=110)
    plt.close(fig)


def _tie(cfg: TuneConfig) -> str | None:
    if cfg.tie not in ("auto", "noise", "none"):
        raise ValueError(f"tie: expected 'auto', 'noise' or 'none', got {cfg.tie!r}")
    if cfg.tie == "auto":
        return None if cfg.ground_truth else "noise"
    return None if cfg.tie == "none" else "noise"


def main(args: argparse.Namespace) -> int:
    """Run the tuning command; writes hyperparameters.json, loss_curve.csv, tuning.png."""
    cfg = _merge_config(args)
    _check_config(cfg)
    torch.manual_seed(cfg.seed)
    ddp.init_from_env()
    system, filt, sim = build(cfg)
    train = sim["train"] if cfg.ground_truth else _strip_x(sim["train"])
    val = sim.get("val")
    if val is not None and not cfg.ground_truth:
        val = _strip_x(val)
    test = sim.get("test")
    before = after = None
    if test is not None:
        with torch.no_grad():
            before = filt(test.y, u=test.u).volume.mean(0)
    if cfg.compile and cfg.progress and ddp.rank() == 0:
        print("compiling the tuning step (once: 1-3 minutes on a CPU, seconds from the cache "
              "of an earlier run)...", file=sys.stderr, flush=True)
    report, filt = tune(
        filt,
        train,
        params=cfg.params,
        tie=_tie(cfg),
        optimizer=cfg.optimizer,
        lr=cfg.lr,
        epochs=cfg.epochs,
        batch_size=cfg.batch_size,
        validation=val,
        loss=cfg.loss,
        weights=LossWeights(**cfg.weights),
        val_every=cfg.val_every,
        patience=cfg.patience,
        checkpoint_dir=Path(cfg.out) / "checkpoints",
        checkpoint_every=cfg.checkpoint_every,
        seed=cfg.seed,
        progress=cfg.progress,
        window=cfg.window or None,
        compile=cfg.compile,
    )
    if test is not None:
        with filt.eager():  # once, on a new batch size: cheaper than another compile
            with torch.no_grad():
                after = filt(test.y, u=test.u).volume.mean(0)
            audit = evaluate(filt, test, LossWeights(**cfg.weights), loss="both")
    if ddp.rank() == 0:
        _write_outputs(
            Path(cfg.out), cfg, report, before, after, cfg.test_trajectories, sim["true"]
        )
        print(
            f"{cfg.filter} on {cfg.system}: {report.best_epoch} epochs kept, {report.seconds:.1f} s"
        )
        for k in report.final:
            tv = sim["true"].get(k)
            tv_s = "" if tv is None else f"   b* = {[round(t, 6) for t in tv.tolist()]}"
            print(
                f"  {k:<18} {[round(v, 6) for v in report.initial[k]]} -> "
                f"{[round(v, 6) for v in report.final[k]]}{tv_s}"
            )
        if test is not None:
            k0 = 1
            print(
                f"  mean area (held out, k>=1): {float(before[k0:].mean()):.4g} -> "
                f"{float(after[k0:].mean()):.4g}; containment violations "
                f"{audit.get('violations')} / {test.x.shape[0]} traj x {cfg.steps} steps"
            )
        print(f"  wrote {cfg.out}/hyperparameters.json, loss_curve.csv, tuning.png")
    return 0
