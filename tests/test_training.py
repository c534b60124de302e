"""Losses and the tuning loop (diffsmf.tuning), on the exact toy interval filter."""

from __future__ import annotations

import pytest
import torch
from test_training_toy import V_BOUND, W_BOUND, ToyIntervalFilter, toy_system

from diffsmf.sets import Interval
from diffsmf.tuning import LossWeights, evaluate, tune
from diffsmf.tuning.loop import Data, resolve_params
from diffsmf.tuning.losses import (
    consistency_excess,
    filter_with_predictions,
    log_volume_loss,
    normalised_outside,
    total_loss,
)


@pytest.fixture(scope="module")
def data():
    s = toy_system()
    return s, s.simulate(40, batch=24, seed=0, noise="vertex")


def test_filter_with_predictions_matches_forward(data):
    s, traj = data
    f = ToyIntervalFilter(s)
    out = filter_with_predictions(f, traj.y, guard_empty=False)
    ref = f(traj.y)
    assert torch.equal(out.result.lower, ref.lower) and torch.equal(out.result.upper, ref.upper)
    assert out.excess.shape == traj.y.shape
    # the guard keeps the prediction at (near-)empty steps: a superset, flagged inconsistent
    f.measurement_noise = torch.tensor([0.5 * V_BOUND])
    g = filter_with_predictions(f, traj.y).result
    r = f(traj.y)
    assert ((g.lower <= r.lower) & (g.upper >= r.upper)).all()
    assert not g.consistent.all() and (g.consistent <= r.consistent).all()


def test_log_volume_loss_is_mean_log_of_box_areas(data):
    s, traj = data
    res = ToyIntervalFilter(s)(traj.y)
    w = res.upper - res.lower
    ref = torch.log(w[:, 1:].prod(-1).clamp_min(1e-300)).mean()  # exact filter: may be 0
    assert torch.allclose(log_volume_loss(res, skip=1), ref, rtol=1e-12)


def test_normalised_outside_on_boxes_equals_axis_formula():
    g = torch.Generator().manual_seed(0)
    lo = torch.rand(50, 3, generator=g) - 1
    hi = lo + torch.rand(50, 3, generator=g) + 0.1
    box = Interval(lo, hi)
    inside = box.sample(20, g).movedim(-2, 0)  # [20, 50, 3]
    assert (normalised_outside(box, inside) == 0).all()
    x = lo + (hi - lo) * (3 * torch.rand(50, 3, generator=g) - 1)  # often outside
    # independent reference: along +-e_i the normalised excess is (x_i - hi_i) / width_i
    w = hi - lo
    ref = torch.maximum((x - hi) / w, (lo - x) / w).amax(-1).clamp_min(0)
    got = normalised_outside(box, x)
    assert torch.all(got >= ref - 1e-12)  # extra probe directions can only find more
    assert torch.equal(got > 0, ~box.contains(x, atol=0.0))


def test_consistency_excess_sign_is_exact_emptiness(data):
    s, traj = data
    f = ToyIntervalFilter(s, measurement_noise=torch.tensor([0.3 * V_BOUND]))
    out = filter_with_predictions(f, traj.y)
    # the filter's own flag (exact interval emptiness) must agree with excess <= 0
    flags = out.result.consistent[:, 1:]
    assert torch.equal(flags, (out.excess <= 1e-12).all(-1))
    assert not flags.all() and flags.any()


def test_consistency_excess_reference_value():
    s = toy_system()
    f = ToyIntervalFilter(s)
    pred = Interval(torch.tensor([[0.0, -1.0]]), torch.tensor([[0.2, 1.0]]))
    y = torch.tensor([[0.25]])  # output set [0, 0.2] +- 0.01 -> centre 0.1, half 0.11
    e = consistency_excess(f, pred, y)
    # by hand: excess 0.15 - 0.11 in units of one step of noise at the output, 0.01 + 0.02
    assert torch.allclose(e, torch.tensor([[(0.15 - 0.11) / (V_BOUND + W_BOUND)]]), rtol=1e-12)


def test_loss_gradcheck_in_noise_bounds(data):
    s, traj = data
    f = ToyIntervalFilter(s, measurement_noise=torch.tensor([0.5 * V_BOUND]))
    y, x = traj.y[:3, :4], traj.x[:3, :5]

    class Loss(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.f = f

        def forward(self):
            out = filter_with_predictions(self.f, y)
            w = LossWeights(margin=0.3)
            return total_loss(out, x, w, use_containment=True, use_consistency=True)[0]

    mod = Loss()

    def fcall(rw, rv):
        return torch.func.functional_call(
            mod, {"f.raw_process_noise": rw, "f.raw_measurement_noise": rv}, ()
        )

    rw = (f.raw_process_noise.detach() - 0.37).requires_grad_(True)
    rv = (f.raw_measurement_noise.detach() + 0.11).requires_grad_(True)
    assert fcall(rw, rv) > 0
    assert torch.autograd.gradcheck(fcall, (rw, rv))


@pytest.mark.slow
def test_tune_consistency_shrinks_inflated_bounds_and_stays_consistent(data):
    s, _ = data
    train = s.simulate(30, batch=16, seed=1, noise="vertex")
    val = s.simulate(30, batch=16, seed=2, noise="vertex")
    f = ToyIntervalFilter(s, process_noise=5 * W_BOUND, measurement_noise=5 * V_BOUND)
    before = evaluate(f, val)
    rep, f = tune(
        f,
        Data(train.y),
        epochs=40,
        batch_size=16,
        lr=0.05,
        validation=Data(val.y),
        val_every=5,
        patience=100,
        progress=False,
        seed=0,
        tie="noise",
    )
    after = evaluate(f, Data(val.y, val.x))
    assert after["mean_volume"] < 0.5 * before["mean_volume"]
    assert after["consistent_frac"] == 1.0
    assert after["violations"] == 0  # exact filter: consistent bounds >= truth on this data
    # one shared factor: learned bounds are b* times one scale >= 1 (vertex data, exact filter)
    scale = rep.final["measurement_noise"][0] / V_BOUND
    assert rep.final["process_noise"] == pytest.approx([scale * W_BOUND] * 2, rel=1e-12)
    assert 1.0 <= scale < 1.5
    assert len(rep.history) == 40 and rep.best_epoch > 0


def test_tune_grows_too_small_bounds(data):
    s, _ = data
    train = s.simulate(30, batch=16, seed=1, noise="vertex")
    f = ToyIntervalFilter(s, process_noise=0.2 * W_BOUND, measurement_noise=0.2 * V_BOUND)
    assert evaluate(f, Data(train.y))["consistent_frac"] < 1
    rep, f = tune(f, Data(train.y), epochs=40, batch_size=16, lr=0.3, progress=False, tie="noise")
    assert evaluate(f, Data(train.y))["consistent_frac"] == 1.0
    assert rep.final["measurement_noise"][0] > rep.initial["measurement_noise"][0]


@pytest.mark.slow
def test_tune_is_deterministic_and_resumable(data, tmp_path):
    s, traj = data
    kw = dict(epochs=6, batch_size=8, progress=False, seed=3, validation=0.25, val_every=1)

    def run(**extra):
        f = ToyIntervalFilter(s, process_noise=3 * W_BOUND, measurement_noise=3 * V_BOUND)
        return tune(f, traj, **{**kw, **extra})

    r1, f1 = run()
    r2, f2 = run()
    assert r1.final == r2.final and r1.history == r2.history
    # checkpoint after 3 epochs, resume to 6: same result as one run of 6 epochs
    run(epochs=3, checkpoint_dir=tmp_path, checkpoint_every=3)
    r3, f3 = run(resume=tmp_path / "last.pt")
    assert r3.final == r1.final
    assert (tmp_path / "best.pt").exists()


@pytest.mark.slow
def test_tune_containment_loss_with_ground_truth_and_early_stop(data):
    s, traj = data
    f = ToyIntervalFilter(s, process_noise=3 * W_BOUND, measurement_noise=3 * V_BOUND)
    rep, f = tune(
        f,
        traj,
        loss="containment",
        epochs=200,
        batch_size=8,
        validation=0.25,
        val_every=1,
        patience=8,
        progress=False,
    )
    assert rep.stopped_early and len(rep.history) < 200
    assert rep.validation_after["loss"] < rep.validation_before["loss"]
    assert rep.validation_after["mean_volume"] < 0.5 * rep.validation_before["mean_volume"]
    assert rep.validation_after["loss"] == min(r["val_loss"] for r in rep.history)


def test_tune_parameter_selection_and_bad_input(data):
    s, traj = data
    f = ToyIntervalFilter(s)
    chosen, skipped = resolve_params(f, ("measurement_noise", "stirling_step"))
    assert list(chosen) == ["measurement_noise"] and skipped == ["stirling_step"]
    rep, _ = tune(f, traj, params=["measurement_noise"], epochs=2, progress=False)
    assert rep.params == ["measurement_noise"]
    assert f.process_noise.tolist() == [W_BOUND, W_BOUND]  # frozen
    with pytest.raises(ValueError, match="params"):
        tune(f, traj, params=["nope"], epochs=1, progress=False)
    with pytest.raises(ValueError, match="loss"):
        tune(f, Data(traj.y), loss="containment", epochs=1, progress=False)
    with pytest.raises(ValueError, match="optimizer"):
        tune(f, traj, optimizer="rmsprop", epochs=1, progress=False)
    with pytest.raises(ValueError, match="validation"):
        tune(f, traj, validation=1.5, epochs=1, progress=False)
    with pytest.raises(ValueError, match="trajectories"):
        tune(f, "abc", epochs=1, progress=False)
    with pytest.raises(ValueError, match=r"^trajectories: no data \(y \[N, T, m\] = \[0,"):
        tune(f, Data(traj.y[:0]), epochs=1, progress=False)  # was a KeyError('loss')
    with pytest.raises(ValueError, match=r"^validation: no data"):
        tune(f, traj, validation=Data(traj.y[:0]), epochs=1, progress=False)
    for kw, name in ((dict(epochs=0), "epochs"), (dict(batch_size=2.5), "batch_size"),
                     (dict(patience=-1), "patience"), (dict(val_every=True), "val_every")):
        with pytest.raises(ValueError, match=f"^{name}: must be a positive integer"):
            tune(f, traj, progress=False, **{"epochs": 1, **kw})


def test_cli_with_toml_config_writes_outputs(tmp_path):
    import json

    from diffsmf.cli import main as diffsmf_main

    cfg = tmp_path / "sd.toml"
    cfg.write_text(
        'system = "spring_damper"\nfilter = "hsnsmf"\nepochs = 2\ntrajectories = 3\n'
        "val_trajectories = 2\ntest_trajectories = 2\nsteps = 3\nbatch_size = 3\n"
        "init_scale = 5.0\nval_every = 1\n"
    )
    out = tmp_path / "run"
    rc = diffsmf_main(["tune", "--config", str(cfg), "--out", str(out), "--no-progress"])
    assert rc == 0
    hp = json.loads((out / "hyperparameters.json").read_text())
    assert hp["true_bounds"]["measurement_noise"] == pytest.approx([1e-3])
    assert hp["initial"]["measurement_noise"] == pytest.approx([5e-3])
    assert set(hp["tuned"]) == {"process_noise", "measurement_noise", "stirling_step"}
    head = (out / "loss_curve.csv").read_text().splitlines()[0].split(",")
    assert head[0] == "epoch" and "consistency" in head and "process_noise[0]" in head
    assert (out / "tuning.png").stat().st_size > 0
    bad = tmp_path / "bad.toml"
    bad.write_text("nonsense = 1\n")
    # a user error: one line naming the config, exit 2 (no traceback)
    assert diffsmf_main(["tune", "--config", str(bad), "--out", str(out)]) == 2


def test_tuning_tune_stays_the_function_after_importing_the_command(data):
    """The command module (`diffsmf.cli.tune`) does not shadow the library's ``tune``."""
    import diffsmf.cli.tune  # noqa: F401
    import diffsmf.tuning
    from diffsmf.tuning.loop import tune as loop_tune

    s, traj = data
    f = ToyIntervalFilter(s, process_noise=2 * W_BOUND)
    rep, _ = diffsmf.tuning.tune(f, Data(traj.y), params=("process_noise",), epochs=1,
                                 batch_size=24, progress=False)
    assert diffsmf.tuning.tune is loop_tune and rep.params == ["process_noise"]


def test_the_sample_tuning_config_is_valid():
    """``training/spring_damper.toml`` (the sample ``diffsmf tune --config`` file of a source
    checkout) holds only known keys of the right types."""
    from pathlib import Path

    from diffsmf.tuning.config import TuneConfig, load_config

    path = Path(__file__).resolve().parents[1] / "training" / "spring_damper.toml"
    cfg = TuneConfig(**load_config(path))
    assert (cfg.system, cfg.filter, cfg.init_scale) == ("spring_damper", "hsnsmf", 5.0)
    assert cfg.window == 10 and cfg.out == "runs/spring_damper"
