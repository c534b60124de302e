"""Containment audit (diffsmf.audit) and the comparison/demo helpers (diffsmf.comparison)."""

from __future__ import annotations

import argparse
import json
import re
import warnings

import numpy as np
import pytest
import torch

import diffsmf as ds
from diffsmf import audit, filters, systems
from diffsmf.cli import audit as audit_cli
from diffsmf.comparison import compare_simulated, demo, format_table


def test_gauge_matches_the_scale_of_a_scaled_point():
    c = torch.tensor([0.3, -0.2])
    T = torch.tensor([[0.2, 0.05], [-0.1, 0.3]])
    alpha = torch.tensor([[1.0, -0.4], [0.2, 0.7], [-1.0, 1.0]])  # inf-norms 1, 0.7, 1
    scale = torch.tensor([1.5, 0.5, 1.0 + 1e-6])
    x = c + (scale[:, None] * alpha) @ T.T
    expect = scale * alpha.abs().amax(-1)
    P = ds.Parallelotope(c, T)
    torch.testing.assert_close(audit.gauge(P, x), expect)
    Z = ds.Zonotope(c, T)
    g = audit.gauge(Z, x)
    inside = expect <= 1
    assert (g[inside] == 0).all()  # inside points are not measured for zonotopes
    torch.testing.assert_close(g[~inside], expect[~inside], atol=1e-8, rtol=0)
    I = ds.Interval(c - torch.tensor([0.1, 0.2]), c + torch.tensor([0.1, 0.2]))
    torch.testing.assert_close(audit.gauge(I, c + torch.tensor([0.15, 0.0])), torch.tensor(1.5))
    E = ds.Ellipsoid(c, torch.diag(torch.tensor([4.0, 1.0])))
    torch.testing.assert_close(audit.gauge(E, c + torch.tensor([0.0, 3.0])), torch.tensor(3.0))


def test_audit_detects_a_filter_with_too_small_noise_bounds():
    system = systems.get("spring_damper")
    honest = audit.containment(filters.HSNSMF(system), system, trials=50, steps=10)
    assert honest.violations == 0 and honest.pairs == 50 * 11
    liar = filters.HSNSMF(system, process_noise=torch.full((2,), 1e-5))
    rep = audit.containment(liar, system, trials=50, steps=10)
    assert rep.violations > 0 and rep.worst_distance > 1e-9
    assert 0 < rep.fraction <= 1 and "outside" in str(rep)


def test_cli_main_prints_reports(capsys):
    args = argparse.Namespace(
        system="bilinear", filter="mszm", trials=20, steps=4, noise="both", seed=0, json=True
    )
    assert audit_cli.main(args) == 0
    lines = [json.loads(s) for s in capsys.readouterr().out.strip().splitlines()]
    assert [r["noise"] for r in lines] == ["vertex", "uniform"]
    assert all(r["violations"] == 0 and r["pairs"] == 20 * 5 for r in lines)
    parser = argparse.ArgumentParser()
    audit_cli.add_arguments(parser)
    ns = parser.parse_args(["--system", "vdp", "--filter", "esmf"])
    assert ns.trials == 1000 and ns.noise == "both"


def test_gaussian_noise_is_said_and_does_not_fail_the_audit(capsys, monkeypatch):
    """radar simulates Gaussian noise besides its bounded sets: a set filter's audit there
    warns (API) and notes it without exit status 1 (CLI), although pairs are outside; on the
    same system without the Gaussian part the audit is silent and clean, and a guaranteed
    filter with too small noise bounds still fails the CLI run."""
    with pytest.warns(UserWarning, match="radar has Gaussian noise"):
        audit.containment(filters.HSNSMF(systems.get("radar")), trials=2, steps=2)
    bounded = systems.get("radar", gaussian=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep = audit.containment(filters.HSNSMF(bounded), trials=20, steps=5)
    assert rep.violations == 0 and rep.pairs == 20 * 6
    args = argparse.Namespace(
        system="radar", filter="hsnsmf", trials=2, steps=2, noise="vertex", seed=0, json=False,
    )
    assert audit_cli.main(args) == 0
    out = capsys.readouterr().out
    outside = re.search(r"HSNSMF on radar \(vertex noise, 2 trajectories x 2 steps\): (\d+)/6", out)
    assert outside is not None and int(outside.group(1)) > 0, out  # outside, yet exit status 0
    assert "Note: radar has Gaussian noise" in out
    liar = lambda s: filters.HSNSMF(s, process_noise=torch.full((2,), 1e-5))  # noqa: E731
    monkeypatch.setattr(filters, "by_name", lambda name: liar)
    args.system, args.trials, args.steps = "spring_damper", 50, 10
    assert audit_cli.main(args) == 1
    assert "Note:" not in capsys.readouterr().out


def test_compare_rows_and_demo(tmp_path):
    system = systems.get("spring_damper")
    rows = compare_simulated(system, ["hsnsmf", "ekf"], trials=3, steps=6, noise="vertex")
    assert [r["filter"] for r in rows] == ["hsnsmf", "ekf"]
    assert rows[0]["guaranteed"] and not rows[1]["guaranteed"] and rows[0]["violations"] == 0
    text = format_table(rows)
    assert "not guaranteed" in text and "hsnsmf" in text
    out = demo(tmp_path, trials=2, steps=6)
    assert "HSNSMF" in out and "CDSMF" in out and (tmp_path / "filters_demo.png").exists()


def test_gauge_of_constrained_zonotope_vs_highs():
    """Certified points have gauge 0; a point at HiGHS distance d outside has 1 + d / scale."""
    import diffsmf as ds
    from diffsmf.audit import gauge
    from diffsmf.sets.constrained_zonotope import distance_lp

    F = torch.float64
    Z = ds.ConstrainedZonotope(torch.zeros(2, dtype=F), torch.eye(2, dtype=F),
                               torch.tensor([[1.0, 1.0]], dtype=F), torch.tensor([0.5], dtype=F))
    x = torch.tensor([[0.25, 0.25], [0.9, 0.9], [-0.25, 0.75], [-0.5, 1.0]], dtype=F)
    g = gauge(Z, x)  # inside, outside, inside, on the boundary
    assert g[0] == 0 and g[2] == 0
    assert g[3] <= 1 + 1e-9  # a boundary point is never a violation
    d = distance_lp(Z, x[1:2])[0]
    assert d > 0.1 and g[1] > 1 + 1e-3
    scale = 1.0 + x[1].abs().max() + 1.0
    assert torch.isclose(g[1], 1 + d / scale)


def test_partial_audits_add_up_to_the_whole():
    """``first`` / ``count`` audit a part of the same simulated trajectories, and ``on_chunk``
    reports chunks of `audit.CHUNK`: the parts' counts and volume sums add up to the
    whole audit's. Out-of-range parts raise naming the argument."""
    system = systems.get("spring_damper")
    filt = filters.HSNSMF(system)
    whole = audit.containment(filt, system, trials=7, steps=6, noise="vertex", seed=5)
    parts, chunks = [], []
    for first, count in ((0, 3), (3, 4)):
        parts.append(audit.containment(
            filt, system, trials=7, steps=6, noise="vertex", seed=5, first=first, count=count,
            on_chunk=chunks.append,
        ))
    assert [p.trials for p in parts] == [3, 4]
    assert sum(p.pairs for p in parts) == whole.pairs == sum(c["pairs"] for c in chunks)
    assert [(c["start"], c["stop"]) for c in chunks] == [(0, 3), (3, 7)]
    vol = sum(c["volume_sum"] for c in chunks) / (7 * 6)
    assert abs(vol - whole.mean_volume) <= 1e-12 * whole.mean_volume
    assert sum(p.violations for p in parts) == whole.violations
    with pytest.raises(ValueError, match="first"):
        audit.containment(filt, system, trials=7, steps=2, first=7)
    with pytest.raises(ValueError, match="count"):
        audit.containment(filt, system, trials=7, steps=2, first=3, count=5)


def test_containment_and_simulate_arguments_named():
    """A negative ``tol`` made every pair a violation (12 / 12 outside, worst distance 0);
    ``trials=True`` reached ``sample`` and was reported as ``k``; ``steps=2.5`` raised a raw
    TypeError; ``gauge`` with points of the wrong dimension a raw broadcasting error."""
    system = systems.get("spring_damper")
    filt = filters.HSNSMF(system)
    for kw, name in (
        ({"tol": -1.0}, "tol"), ({"tol": 1.5}, "tol"), ({"trials": True}, "trials"),
        ({"trials": 2.0}, "trials"), ({"steps": 0}, "steps"), ({"steps": 2.5}, "steps"),
        ({"first": 0.5}, "first"), ({"count": 1.0}, "count"),
    ):
        args = {"trials": 3, "steps": 2, **kw}
        with pytest.raises(ValueError, match=f"^{name}: must be"):
            audit.containment(filt, system, **args)
    for kw, name in (({"steps": 2.5}, "steps"), ({"batch": True}, "batch"),
                     ({"batch": 0}, "batch"), ({"steps": -1}, "steps")):
        with pytest.raises(ValueError, match=f"^{name}: must be an integer >= 1"):
            system.simulate(**{"steps": 2, "batch": 1, **kw})
    box = system.x0_set.interval_hull()
    with pytest.raises(ValueError, match=r"^x: expected \[\.\.\., 2\]"):
        audit.gauge(box, torch.zeros(3, 3))
    # numpy integers are integers
    assert audit.containment(filt, system, trials=np.int64(2), steps=np.int64(2)).pairs == 6


def test_swapped_or_wrong_filter_system_and_trajectory_are_named():
    """A Trajectory passed as the system (swapped arguments) reached ``system.process_cov``
    and raised a raw AttributeError; a filter class (not instantiated), a system of other
    dimensions and a System passed as the trajectory are named the same way, in the audit,
    the tightness report, the filters' constructors and tuning (``tune(system, traj)`` said
    "params: none of [...] is a parameter of this filter", ``tune(HSNSMF, traj)`` raised a raw
    TypeError)."""
    from diffsmf.tightness import inner_bounds, tightness
    from diffsmf.tuning import evaluate, tune

    system = systems.get("spring_damper")
    traj = system.simulate(steps=2, batch=1)
    filt = filters.HSNSMF(system)
    other = systems.get("fermenter")  # n = 3, m = 3
    cases = [
        (lambda: audit.containment(filt, traj), r"^system: must be a diffsmf.System, got Traj"),
        (lambda: audit.containment(filters.HSNSMF, system), r"^filt: .* got the class HSNSMF"),
        (lambda: audit.containment(system), r"^filt: must be a filter .* got System"),
        (lambda: audit.containment(filt, other, trials=1), r"^system: n = 3, m = 3, but filt"),
        (lambda: tightness(filt, traj, system, [1]), r"^system: must be a diffsmf.System"),
        (lambda: inner_bounds(filt, system, system, [1]), r"^traj: must be a diffsmf Traj"),
        (lambda: inner_bounds(filt, other, traj, [1]), r"^system: n = 3, m = 3"),
        (lambda: filters.HSNSMF(traj), r"^system: must be a diffsmf.System, got Trajectory"),
        (lambda: filters.CombinedFilter(traj), r"^system: must be a diffsmf.System"),
        (lambda: tune(system, traj), r"^filt: must be a filter .* got System"),
        (lambda: tune(filters.HSNSMF, traj), r"^filt: .* got the class HSNSMF"),
        (lambda: evaluate(traj, filt), r"^filt: must be a filter .* got Trajectory"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()
    # the same calls with the arguments in their places run
    assert audit.containment(filt, system, trials=1, steps=2).pairs == 3


def _audit_script():
    """``benchmarks/filters_audit.py`` as a module (a script, not part of the package)."""
    from conftest import load_script

    return load_script("benchmarks", "filters_audit")


def test_audit_script_filter_kwargs(tmp_path, monkeypatch):
    """``--filter-kwargs`` reaches the filter (other caps: other sets), names the row, and a
    bad value is a one-line error naming the option."""
    script = _audit_script()
    log = tmp_path / "a.jsonl"
    caps = '{"max_generators": 12, "max_constraints": 3, "elimination": "propagation"}'
    common = ["x", "--filters", "czsmf", "--systems", "spring_damper", "--trials", "3",
              "--steps", "3", "--noises", "vertex", "--log", str(log)]
    for extra in ([], ["--filter-kwargs", caps]):
        monkeypatch.setattr("sys.argv", common + extra)
        assert script.main() == 0
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["filter"] for r in rows] == ["CZSMF", 'CZSMF ' + json.dumps(json.loads(caps),
                                                                          sort_keys=True)]
    assert rows[0]["sets"] != rows[1]["sets"]  # the caps changed the filter
    assert all(r["violations"] == 0 and r["pairs"] == 3 * 4 for r in rows)
    with pytest.raises(ValueError, match="--filter-kwargs: not JSON"):
        script._filter_kwargs("{max_generators: 12}")
    with pytest.raises(ValueError, match="--filter-kwargs: expected a JSON object"):
        script._filter_kwargs("[12]")


def test_audit_script_resume(tmp_path, monkeypatch, capsys):
    """``--resume`` audits the first stretch without a logged chunk of the same row, up to the
    next logged chunk (no overlap, so the log still merges), then reports nothing left; a
    chunk of another row (other noise) or of other package code (other source fingerprint)
    does not count; without ``--log`` it is an error."""
    script = _audit_script()
    log = tmp_path / "r.jsonl"
    common = ["x", "--filters", "hsnsmf", "--systems", "spring_damper", "--trials", "5",
              "--steps", "2", "--log", str(log)]

    def run(*extra: str) -> int:
        monkeypatch.setattr("sys.argv", common + list(extra))
        return script.main()

    def spans() -> list[tuple[str, int, int]]:
        rows = [json.loads(line) for line in log.read_text().splitlines()]
        return [(r["noise"], r["start"], r["stop"]) for r in rows]

    assert run("--noises", "vertex", "--first", "3", "--count", "2") == 0
    assert run("--noises", "vertex", "--resume") == 0  # the gap before the logged chunk
    assert spans() == [("vertex", 3, 5), ("vertex", 0, 3)]
    capsys.readouterr()
    assert run("--noises", "vertex", "--resume") == 0
    assert "all requested trajectories logged" in capsys.readouterr().out
    assert run("--noises", "uniform", "--resume") == 0  # another row: all five
    assert spans()[2:] == [("uniform", 0, 5)]
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    rows[2]["source"] = "0" * 12  # as if logged by other code: not done for this code
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert run("--noises", "uniform", "--resume") == 0
    assert spans()[3:] == [("uniform", 0, 5)]
    capsys.readouterr()
    assert script.merge(str(log), ["0" * 12]) == 0  # only the relabelled chunk
    out = capsys.readouterr().out
    assert out.count("5 x 2 (all 5") == 1 and "vertex" not in out
    assert script.merge(str(log)) == 0
    out = capsys.readouterr().out
    assert out.count("5 x 2 (all 5, seed 2024") == 2
    assert script.resume_range(0, 10, [(0, 2), (2, 4), (6, 8)]) == (4, 2)
    assert script.resume_range(5, 3, [(0, 10)]) == (10, 0)
    assert script.resume_range(0, 10, []) == (0, 10)
    with pytest.raises(ValueError, match="--source: only with --merge"):
        monkeypatch.setattr("sys.argv", ["x", "--source", "abc", "--systems", "spring_damper"])
        script.main()
    with pytest.raises(ValueError, match="--resume: needs --log"):
        monkeypatch.setattr("sys.argv", ["x", "--resume", "--systems", "spring_damper"])
        script.main()


class MyHSNSMF(filters.HSNSMF):
    """A user's subclass: it inherits the parent's guarantee, whatever its class name."""


def test_guaranteed_is_a_class_attribute_that_subclasses_inherit(tmp_path):
    expect = {"hsnsmf": True, "mszm": True, "cdsmf": True, "esmf": True, "czsmf": True,
              "ekf": False, "combined": False, "interval": True, "zbsmf": True,
              "eso": True}
    assert {n: filters.by_name(n).guaranteed for n in filters.names()} == expect
    system = systems.get("spring_damper")
    mine = MyHSNSMF(system)
    assert mine.guaranteed and filters.is_guaranteed(mine) and filters.is_guaranteed(MyHSNSMF)
    rows = compare_simulated(system, {"mine": mine, "ekf": filters.EKF(system)}, trials=2, steps=4)
    assert [r["guaranteed"] for r in rows] == [True, False]
    # the audit's warning about Gaussian noise is for guaranteed filters: the subclass gets it
    with pytest.warns(UserWarning, match="radar has Gaussian noise"):
        audit.containment(MyHSNSMF(systems.get("radar")), trials=2, steps=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        audit.containment(filters.EKF(systems.get("radar")), trials=2, steps=2)


def test_a_filter_that_declares_nothing_is_not_guaranteed():
    class Undeclared(torch.nn.Module):
        pass

    assert not filters.is_guaranteed(Undeclared())

    class Declared(filters.EKF):
        guaranteed = True

    assert filters.is_guaranteed(Declared(systems.get("spring_damper")))
