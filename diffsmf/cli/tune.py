"""Tune a filter's noise bounds (and step sizes) on your logs, or on simulated data of a
built-in system.

    diffsmf tune --model my_model.py:make_system --data run1.csv run2.csv --outputs y1 \
        [--inputs u1] --filter hsnsmf --epochs 100 --window 10 --out runs/mine
    diffsmf tune --system spring_damper --filter hsnsmf --epochs 200 --out runs/sd
    diffsmf tune --config sd.toml
    torchrun --nproc_per_node 2 -m diffsmf tune ...      # data-parallel (gloo / NCCL)

With ``--model``, the model's noise sets are the starting guess and each ``--data`` file is one
logged run from ``x0_set`` (columns as ``diffsmf filter``); without true states the loss is
the consistency loss with one shared scale for all noise bounds (`TuneConfig`).

Writes to ``--out``: ``bounds.json`` (the tuned half-widths times ``--safety``, for
``diffsmf filter --bounds`` and `diffsmf.tuning.bound_sets`), ``hyperparameters.json``
(initial and tuned values; true bounds for a built-in), ``report.json``, ``loss_curve.csv``
(per epoch: the losses and every tuned value) and ``tuning.png`` (the loss and the tuned
bounds over the epochs, and for a built-in the mean set area before/after on held-out
trajectories). The loop itself is `diffsmf.tuning.loop.tune`.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch

import diffsmf as ds
from diffsmf.filters.base import SetFilter
from diffsmf.tuning import ddp
from diffsmf.tuning.bounds import consistent_scale, write_bounds
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
      help="built-in system name (ds.systems.names()); NAME:N for a sized system; tuned on "
           "its simulated trajectories")
    a("--model", default=d.model, metavar="FILE.py:FUNC",
      help="your model instead of --system: the function in FILE.py that returns your "
           "diffsmf.System (its noise sets are the starting guess); needs --data and --outputs")
    a("--data", nargs="+", default=d.data, metavar="FILE",
      help="with --model: logged runs, one file each (all of the same length), as for "
           "diffsmf filter: .csv with a header row, .npz or .npy")
    a("--outputs", default=d.outputs, metavar="COLS",
      help="with --model: comma-separated measurement columns, in the order of h(x)")
    a("--inputs", default=d.inputs, metavar="COLS",
      help="with --model: comma-separated input columns, in the order of u")
    a("--val-runs", type=int, default=d.val_runs,
      help="with --model: the last N --data runs are held out for validation (0: none)")
    a("--safety", type=float, default=d.safety,
      help="factor >= 1 on the tuned half-widths written to bounds.json: tuned bounds are "
           "the smallest the data do not refute and can lie below the true ones")
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
        default=None,
        help="comma-separated hyperparameter names (process_noise, measurement_noise, "
        "stirling_step, remainder_margin, minkowski_scale); default: "
        f"{','.join(d.params)} with --system, the noise bounds (what bounds.json holds) "
        "with --model",
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
    if vals.get("params") is None:
        vals["params"] = list(d.params)
    elif isinstance(vals["params"], str):
        vals["params"] = [p for p in vals["params"].split(",") if p]
    given = getattr(args, "params", None) is not None
    if getattr(args, "config", None):
        config = load_config(args.config)
        given = given or "params" in config
        for k, v in config.items():
            if k not in vals or vals[k] == getattr(d, k):
                vals[k] = v
    if vals.get("model") is not None and not given:  # bounds.json holds the noise bounds
        vals["params"] = ["process_noise", "measurement_noise"]
    return TuneConfig(**vals)


def _check_config(cfg: TuneConfig) -> None:
    """One ``ValueError`` naming the option for each user error in a run configuration."""
    if cfg.model is None:
        ds.systems.check_name(cfg.system, option="--system")
        for key in ("data", "outputs", "inputs"):
            if getattr(cfg, key):
                raise ValueError(f"--{key}: goes with --model (your model and its logs); a "
                                 "built-in --system is tuned on its own simulated data")
    else:
        _check_model_config(cfg)
    try:
        ds.filters.by_name(cfg.filter)
    except ValueError:
        raise ValueError(
            f"--filter: unknown filter {cfg.filter!r}; choose from {ds.filters.names(presets=True)}"
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


def _check_model_config(cfg: TuneConfig) -> None:
    """The options of a run on the user's model and logs."""
    if not cfg.data:
        raise ValueError("--data: --model needs the logged runs (one file each)")
    if not cfg.outputs:
        raise ValueError("--outputs: name the measurement columns of the --data files")
    if cfg.ground_truth:
        raise ValueError("--ground-truth: logs hold no true states; --model tunes from the "
                         "measurements (consistency loss)")
    if cfg.val_runs < 0 or cfg.val_runs >= len(cfg.data):
        raise ValueError(f"--val-runs: must be in 0..{len(cfg.data) - 1} (fewer than the "
                         f"{len(cfg.data)} --data runs), got {cfg.val_runs}")
    if not (cfg.safety >= 1 and cfg.safety < float("inf")):
        raise ValueError(f"--safety: must be a number >= 1, got {cfg.safety}")


def _logs(system: Any, cfg: TuneConfig) -> Data:
    """The ``--data`` runs as ``Data(y [R, T, m], u [R, T, p] or None)``."""
    from diffsmf.cli.filter import _names, read_log

    ys, us = [], []
    for path in cfg.data:
        y, u = read_log(system, path, _names(cfg.outputs), _names(cfg.inputs))
        if ys and y.shape[0] != ys[0].shape[0]:
            raise ValueError(f"--data: {path!r} has {y.shape[0]} steps, {cfg.data[0]!r} has "
                             f"{ys[0].shape[0]}; give runs of the same length (cut them to "
                             "the shortest)")
        ys.append(y)
        us.append(u)
    u = None if us[0] is None else torch.stack(us)
    return Data(y=torch.stack(ys), u=u)


def build_model_run(cfg: TuneConfig) -> tuple[Any, SetFilter, Data, Data, Data | None]:
    """System (your ``--model``), filter (its noise sets times ``init_scale``), all the
    runs, the training runs and the validation runs (the last ``val_runs`` of ``--data``, or
    None)."""
    from diffsmf.cli.filter import load_model

    system = load_model(cfg.model)
    filt = _make_filter(cfg, system)
    if cfg.init_scale != 1.0:
        filt.process_half_widths = filt.process_half_widths.detach() * cfg.init_scale
        filt.measurement_half_widths = filt.measurement_half_widths.detach() * cfg.init_scale
    logs = _logs(system, cfg)
    k = len(logs) - cfg.val_runs
    idx = torch.arange(len(logs))
    return system, filt, logs, logs.take(idx[:k]), (logs.take(idx[k:]) if cfg.val_runs else None)


def _make_filter(cfg: TuneConfig, system: Any) -> SetFilter:
    try:
        return ds.filters.by_name(cfg.filter)(system, **cfg.filter_kwargs)
    except TypeError as exc:
        if "unexpected keyword" not in str(exc):
            raise
        raise ValueError(f"config: filter_kwargs: {exc}") from None


def build(cfg: TuneConfig) -> tuple[Any, SetFilter, dict[str, Any]]:
    """System, filter (bounds scaled by ``init_scale``) and simulated data of a config."""
    system = ds.systems.get(cfg.system)
    filt = _make_filter(cfg, system)
    true = {
        "process_noise": filt.process_half_widths.detach().clone(),
        "measurement_noise": filt.measurement_half_widths.detach().clone(),
    }
    if cfg.init_scale != 1.0:
        filt.process_half_widths = true["process_noise"] * cfg.init_scale
        filt.measurement_half_widths = true["measurement_noise"] * cfg.init_scale
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
    out: Path, cfg: TuneConfig, report: TuneReport, filt: SetFilter, areas: tuple | None,
    test: int, true: dict, record: dict,
) -> dict[str, Any]:
    """``bounds.json``, ``hyperparameters.json``, ``report.json``, ``loss_curve.csv`` and
    ``tuning.png`` (loss; tuned values over the epochs; held-out areas before/after);
    returns what ``bounds.json`` holds."""
    out.mkdir(parents=True, exist_ok=True)
    doc = write_bounds(out / "bounds.json", filt, cfg.safety, initial=report.initial, **record)
    hp = {
        "system": cfg.system if cfg.model is None else cfg.model,
        "filter": cfg.filter,
        "true_bounds": {k: v.tolist() for k, v in true.items()},
        "initial": report.initial,
        "tuned": report.final,
        "best_epoch": report.best_epoch,
        "seconds": report.seconds,
    }
    (out / "hyperparameters.json").write_text(json.dumps(hp, indent=2))
    (out / "report.json").write_text(json.dumps(report.to_dict(), indent=2, default=str))
    keys = ["epoch", *sorted({k for r in report.history for k in r} - {"epoch"})]
    with (out / "loss_curve.csv").open("w") as fh:
        fh.write(",".join(keys) + "\n")
        for r in report.history:
            fh.write(",".join("" if k not in r else f"{r[k]:.10g}" for k in keys) + "\n")
    written = {k: doc[k]["half_widths"] for k in ("process_noise", "measurement_noise")}
    _tuning_figure(out / "tuning.png", cfg, report, areas, test, true, written)
    return doc


def _tuning_figure(
    path: Path, cfg: TuneConfig, report: TuneReport, areas: tuple | None, test: int, true: dict,
    written: dict,
) -> None:
    """The loss, each tuned value over the epochs (relative to its start; dashed: the value
    written to bounds.json; dotted: the true bounds of a built-in) and, when held out, the
    mean set area."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 3 if areas is not None else 2
    fig, ax = plt.subplots(1, panels, figsize=(5 * panels, 3.8))
    hist = report.history
    ep = [r["epoch"] for r in hist]
    ax[0].plot(ep, [r["loss"] for r in hist], label="train loss")
    vv = [(r["epoch"], r["val_loss"]) for r in hist if "val_loss" in r]
    if vv:
        ax[0].plot(*zip(*vv), "o-", label="validation loss")
    if report.best_epoch:
        ax[0].axvline(report.best_epoch, color="grey", ls=":", label="kept")
    ax[0].set(xlabel="epoch", ylabel=f"loss ({cfg.loss}: log-volume + penalty)", title="loss")
    ax[0].xaxis.get_major_locator().set_params(integer=True)
    ax[0].legend()
    for name, start in report.initial.items():
        for i, v0 in enumerate(start):
            col = f"{name}[{i}]"
            if v0 > 0 and all(col in r for r in hist):
                line, = ax[1].semilogy([0, *ep], [1.0] + [r[col] / v0 for r in hist],
                                       label=col)
                tv = true.get(name)
                if tv is not None and i < tv.numel():
                    ax[1].axhline(float(tv[i]) / v0, color=line.get_color(), ls=":")
                if name in written:
                    ax[1].axhline(written[name][i] / v0, color=line.get_color(), ls="--",
                                  lw=0.8)
    if report.best_epoch:  # kept: after the best validated epoch, or at the best epoch's
        # start when scored by its training loss
        x_kept = report.best_epoch - (report.validation_before is None)
        ax[1].axvline(x_kept, color="grey", ls=":", label="kept")
    ax[1].set(xlabel="epoch", ylabel="value / starting value",
              title="tuned values (dashed: bounds.json" + ("; dotted: true)" if true else ")"))
    ax[1].xaxis.get_major_locator().set_params(integer=True)
    ax[1].legend(fontsize="small")
    if areas is not None:
        before, after = areas
        k = torch.arange(before.shape[-1])
        ax[2].semilogy(k, before, label="before tuning")
        ax[2].semilogy(k, after, label="after tuning")
        ax[2].set(xlabel="step k", ylabel="mean set area / volume",
                  title=f"mean set area, {test} held-out trajectories")
        ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _tie(cfg: TuneConfig) -> str | None:
    if cfg.tie not in ("auto", "noise", "none"):
        raise ValueError(f"tie: expected 'auto', 'noise' or 'none', got {cfg.tie!r}")
    if cfg.tie == "auto":
        return None if cfg.ground_truth else "noise"
    return None if cfg.tie == "none" else "noise"


def main(args: argparse.Namespace) -> int:
    """Run the tuning command; writes bounds.json, hyperparameters.json, report.json,
    loss_curve.csv and tuning.png."""
    cfg = _merge_config(args)
    _check_config(cfg)
    torch.manual_seed(cfg.seed)
    ddp.init_from_env()
    test = areas = audit = None
    true: dict = {}
    logs = None
    if cfg.model is not None:
        system, filt, logs, train, val = build_model_run(cfg)
    else:
        system, filt, sim = build(cfg)
        true = sim["true"]
        train = sim["train"] if cfg.ground_truth else _strip_x(sim["train"])
        val = sim.get("val")
        if val is not None and not cfg.ground_truth:
            val = _strip_x(val)
        test = sim.get("test")
    if test is not None:
        with torch.no_grad():
            before = filt(test.y, u=test.u).volume.mean(0)
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
    record = {}
    if logs is not None:  # no logged measurement may refute what is written
        with filt.eager():
            record["consistency_scale"] = consistent_scale(filt, logs.y, logs.u)
    if test is not None:
        with filt.eager():  # once, on a new batch size: cheaper than another compile
            with torch.no_grad():
                areas = (before, filt(test.y, u=test.u).volume.mean(0))
            audit = evaluate(filt, test, LossWeights(**cfg.weights), loss="both")
    if ddp.rank() == 0:
        doc = _write_outputs(Path(cfg.out), cfg, report, filt, areas, cfg.test_trajectories,
                             true, record)
        _print_summary(cfg, report, doc, true, areas, audit,
                       None if test is None else len(test.y))
    return 0


def _print_summary(cfg: TuneConfig, report: TuneReport, doc: dict, true: dict,
                   areas: tuple | None, audit: dict | None, tested: int | None) -> None:
    what = cfg.system if cfg.model is None else f"{cfg.model} ({len(cfg.data)} logged runs)"
    print(f"{cfg.filter} on {what}: {report.best_epoch} epochs kept, {report.seconds:.1f} s")
    for k in report.final:
        tv = true.get(k)
        tv_s = "" if tv is None else f"   b* = {[round(t, 6) for t in tv.tolist()]}"
        print(f"  {k:<18} {[round(v, 6) for v in report.initial[k]]} -> "
              f"{[round(v, 6) for v in report.final[k]]}{tv_s}")
    if areas is not None and audit is not None:
        before, after = areas
        print(f"  mean area (held out, k>=1): {float(before[1:].mean()):.4g} -> "
              f"{float(after[1:].mean()):.4g}; containment violations "
              f"{audit.get('violations')} / {tested} traj x {cfg.steps} steps")
    c = doc.get("consistency_scale")
    if c is not None and c > 1:
        print(f"  the tuned noise bounds left logged measurements inconsistent: scaled by "
              f"{c:.4g}, the smallest factor at which every one is consistent")
    print(f"  bounds.json (tuned x {cfg.safety:g}): {doc['options']}")
    print(f"  run the filter with them: diffsmf filter ... --bounds {cfg.out}/bounds.json")
    print(f"  wrote {cfg.out}/bounds.json, hyperparameters.json, loss_curve.csv, tuning.png")
