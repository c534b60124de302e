"""System inputs: ``n_inputs``, ``System.check_input``, ``simulate(..., u=U)`` (issues 12, 14)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import diffsmf as ds

F64 = torch.float64


def _forced_system(n_inputs: int | None = 2, **kw) -> ds.System:
    """x+ = 0.9 x + u (two states, two inputs), y = x1 + x2^2 / 10."""

    def f(x, u, theta=None):
        return 0.9 * x + u

    def h(x):
        return (x[..., 0] + 0.1 * x[..., 1] ** 2).unsqueeze(-1)

    X0 = ds.Interval(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    W = ds.Interval(torch.full((2,), -1e-3, dtype=F64), torch.full((2,), 1e-3, dtype=F64))
    V = ds.Interval(torch.full((1,), -1e-2, dtype=F64), torch.full((1,), 1e-2, dtype=F64))
    return ds.System(f, h, X0, W, V, n_inputs=n_inputs, name="forced", **kw)


def test_n_inputs_inferred_from_schedule_and_default_zero():
    assert ds.systems.get("bilinear").n_inputs == 2
    assert ds.systems.get("vdp").n_inputs == 1
    assert ds.systems.get("spring_damper").n_inputs == 0
    sched = _forced_system(None, inputs=torch.zeros(10, 2))
    assert sched.n_inputs == 2
    auto = ds.System(lambda x, u, th=None: 0.9 * x, lambda x: x[..., :1],
                     ds.Interval([0.0, 0.0], [1.0, 1.0]))
    assert auto.n_inputs == 0


def test_f_and_h_are_checked_at_construction():
    X0 = ds.Interval([0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"^f: .*failed.*give n_inputs=p"):
        ds.System(lambda x, u, th=None: x + u, lambda x: x[..., :1], X0)  # uses u, no inputs
    with pytest.raises(ValueError, match=r"^f: must map x \[\.\.\., 2\].*returned \(1,\)"):
        ds.System(lambda x, u, th=None: x[..., 0], lambda x: x[..., :1], X0)
    with pytest.raises(ValueError, match=r"^h: must map .*x\[\.\.\., :1\].*returned \(1,\)"):
        ds.System(lambda x, u, th=None: x, lambda x: x[..., 0], X0)
    with pytest.raises(ValueError, match=r"^h: h\(x \[1, 2\]\).*failed"):
        ds.System(lambda x, u, th=None: x, lambda x: x @ torch.ones(3, 1), X0)


def test_f_and_h_must_be_finite_and_differentiable_at_construction():
    """NaN at the centre of X0, numpy inside the model, in-place updates of x: named at once."""
    X0 = ds.Interval([0.0, 0.0], [1.0, 1.0])
    h1 = lambda x: x[..., :1]  # noqa: E731
    with pytest.raises(ValueError, match=r"^f: returned NaN or inf at the centre of x0_set"):
        ds.System(lambda x, u, th=None: torch.log(x - 2.0), h1, X0)
    with pytest.raises(ValueError, match=r"^h: returned NaN or inf .*h\(c\) = \[inf\]"):
        ds.System(lambda x, u, th=None: x, lambda x: 1.0 / (x[..., :1] - 0.5), X0)
    with pytest.raises(ValueError, match=r"^f: autograd cannot differentiate f .*numpy"):
        ds.System(lambda x, u, th=None: x + torch.as_tensor(np.sin(x.numpy())), h1, X0)
    with pytest.raises(ValueError, match=r"^f: autograd cannot differentiate f"):
        ds.System(lambda x, u, th=None: x.mul_(0.9), h1, X0)
    with pytest.raises(ValueError, match=r"^h: its Jacobian is NaN or inf"):
        ds.System(lambda x, u, th=None: x, lambda x: torch.sqrt(x[..., :1] - 0.5), X0)


def test_parameters_must_be_one_set():
    X0 = ds.Interval([0.0, 0.0], [1.0, 1.0])
    f = lambda x, u, th=None: 0.9 * x  # noqa: E731
    for bad, match in (([0.1, 0.2], "list"), (torch.tensor([0.1]), "Tensor"),
                       (ds.Interval(torch.zeros(2, 1), torch.ones(2, 1)), "empty batch shape")):
        with pytest.raises(ValueError, match=f"^parameters: .*{match}"):
            ds.System(f, lambda x: x[..., :1], X0, parameters=bad)


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2"])
def test_n_inputs_must_be_a_nonnegative_int(bad):
    with pytest.raises(ValueError, match="^n_inputs"):
        _forced_system(bad)


def test_n_inputs_must_match_schedule():
    with pytest.raises(ValueError, match="^n_inputs: 3 does not match"):
        _forced_system(3, inputs=torch.zeros(10, 2))


def test_check_input_accepts_and_converts():
    s = _forced_system()
    u = np.ones((4, 2), dtype=np.float32)
    out = s.check_input(u, (4,))
    assert isinstance(out, torch.Tensor) and out.dtype == F64 and out.shape == (4, 2)
    out = s.check_input(torch.zeros(3, 5, 2, dtype=torch.float32), torch.Size([3, 5]))
    assert out.dtype == F64
    auto = ds.System(lambda x, u, th=None: x, lambda x: x[..., :1],
                     ds.Interval([0.0, 0.0], [1.0, 1.0]))
    assert auto.check_input(None, (3,)) is None


@pytest.mark.parametrize(
    "u, shape, match",
    [
        (None, (4,), r"^u: system 'forced' has 2 input\(s\).*no u was given"),
        (torch.ones(4, 1), (4,), r"^u: expected last dimension 2"),  # u[..., :1]: no broadcast
        (torch.ones(4, 3), (4,), r"^u: expected last dimension 2"),
        (torch.ones(2), (4,), r"^u: expected shape \[4, 2\]"),
        (torch.ones(5, 2), (4,), r"^u: expected shape \[4, 2\]"),
        (torch.ones(1, 2), (4,), r"^u: expected shape \[4, 2\]"),
        (torch.ones(4, 10, 2), (4, 9), r"^u: expected shape \[4, 9, 2\]"),
        (torch.tensor([[0.0, float("nan")]]), (1,), r"^u: contains NaN or inf"),
        (torch.tensor([[float("inf"), 0.0]]), (1,), r"^u: contains NaN or inf"),
        ([["a", "b"]], (1,), r"^u: cannot be read"),
        (torch.tensor(1.0), (), r"^u: expected last dimension 2"),
    ],
)
def test_check_input_rejects(u, shape, match):
    with pytest.raises(ValueError, match=match):
        _forced_system().check_input(u, shape)


def test_check_input_rejects_u_for_autonomous_system():
    s = ds.systems.get("spring_damper")
    with pytest.raises(ValueError, match=r"^u: system 'spring_damper' has no inputs"):
        s.check_input(torch.zeros(1, 1), (1,))


def test_simulate_with_given_inputs_follows_the_model():
    s = _forced_system()
    B, T = 3, 6
    U = torch.randn(B, T, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    tr = s.simulate(T, batch=B, seed=0, u=U)
    assert tr.u is not None and torch.equal(tr.u, U)
    assert tr.x.shape == (B, T + 1, 2) and tr.y.shape == (B, T, 1)
    w = tr.x[:, 1:] - (0.9 * tr.x[:, :-1] + U)  # the process noise actually drawn
    assert (w.abs() <= 1e-3 + 1e-12).all()
    # different inputs -> different states (the inputs are really used)
    tr2 = s.simulate(T, batch=B, seed=0, u=U + 1.0)
    assert not torch.allclose(tr.x[:, 1:], tr2.x[:, 1:])
    torch.testing.assert_close(tr2.x[:, 1:] - tr.x[:, 1:], _geometric(T, B))


def _geometric(T: int, B: int) -> torch.Tensor:
    """x2 - x1 when u2 = u1 + 1 and the same noise: sum_{j<k} 0.9^j."""
    d = torch.tensor([sum(0.9**j for j in range(k)) for k in range(1, T + 1)], dtype=F64)
    return d.reshape(1, T, 1).expand(B, T, 2)


def test_simulate_needs_inputs_when_there_is_no_schedule():
    s = _forced_system()
    with pytest.raises(ValueError, match=r"^u: .*no u was given"):
        s.simulate(5, batch=2)
    with pytest.raises(ValueError, match=r"^u: expected shape \[2, 5, 2\]"):
        s.simulate(5, batch=2, u=torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match=r"^u: expected last dimension 2"):
        s.simulate(5, batch=2, u=torch.zeros(2, 5, 1))
    with pytest.raises(ValueError, match=r"^u: contains NaN"):
        s.simulate(5, batch=1, u=torch.full((1, 5, 2), float("nan")))


def test_simulate_given_u_overrides_the_schedule():
    s = ds.systems.get("vdp")
    T = 20
    tr_sched = s.simulate(T, batch=1, seed=0)
    torch.testing.assert_close(
        tr_sched.u[0, :, 0], torch.tensor([math.sin(k * 0.05) for k in range(T)], dtype=F64)
    )
    tr_zero = s.simulate(T, batch=1, seed=0, u=torch.zeros(1, T, 1))
    assert torch.equal(tr_zero.u, torch.zeros(1, T, 1, dtype=F64))
    assert not torch.allclose(tr_zero.x, tr_sched.x)


def test_simulate_rejects_u_for_autonomous_system():
    with pytest.raises(ValueError, match=r"^u: system 'spring_damper' has no inputs"):
        ds.systems.get("spring_damper").simulate(3, batch=1, u=torch.zeros(1, 3, 1))
