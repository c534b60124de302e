"""CZSMF: exactness on linear systems (per-coordinate HiGHS LPs over the whole horizon),
containment audits with worst-case noise, the filter contract, gradients, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linprog

import diffsmf as ds
from diffsmf.filters.czsmf import CZSMF
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope, distance_lp

A_LIN = torch.tensor([[0.9, 0.25], [-0.3, 0.85]], dtype=torch.float64)
C_LIN = torch.tensor([[1.0, 0.0]], dtype=torch.float64)


def linear_system(C: torch.Tensor = C_LIN, name: str = "linear") -> ds.System:
    """x_k = A x_{k-1} + w, y = C x + v, box X0, W, V (non-centred W to test offsets)."""
    A = A_LIN

    def f(x, u=None, theta=None):
        return x @ A.T

    def h(x):
        return x @ C.T

    m = C.shape[0]
    return ds.System(
        f,
        h,
        ds.Interval(torch.tensor([-1.0, -0.5]), torch.tensor([1.0, 1.5])),
        process_noise=ds.Interval(torch.tensor([-0.05, -0.12]), torch.tensor([0.07, 0.1])),
        measurement_noise=ds.Interval(-0.1 * torch.ones(m), 0.15 * torch.ones(m)),
        name=name,
    )


def exact_hulls(system: ds.System, y: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval hull of the exact feasible set of x_k given y_1..y_k, k = 0..T, by HiGHS LPs
    on the stacked variables (x0, w_0, ..., w_{T-1}) with the measurement inequalities."""
    A = A_LIN.numpy()
    n, T = 2, y.shape[0]
    x0 = system.x0_set
    W, V = system.process_noise, system.measurement_noise
    bounds0 = list(zip(x0.lower.numpy(), x0.upper.numpy()))
    wb = list(zip(W.lower.numpy(), W.upper.numpy()))
    vlo, vhi = V.lower.numpy(), V.upper.numpy()
    lo = np.zeros((T + 1, n))
    hi = np.zeros((T + 1, n))
    lo[0], hi[0] = x0.lower.numpy(), x0.upper.numpy()
    for k in range(1, T + 1):
        nv = n * (k + 1)
        # x_j = M_j z with z = (x0, w_0..w_{k-1})
        M = [np.hstack([np.eye(n), np.zeros((n, n * k))])]
        for j in range(1, k + 1):
            Mj = A @ M[-1]
            Mj[:, n * j : n * (j + 1)] += np.eye(n)
            M.append(Mj)
        rows, rhs = [], []
        for j in range(1, k + 1):  # vlo <= y_j - C x_j <= vhi
            CM = C @ M[j]
            rows += [CM, -CM]
            rhs += [y[j - 1] - vlo, -(y[j - 1] - vhi)]
        A_ub, b_ub = np.vstack(rows), np.concatenate(rhs)
        bnds = bounds0 + wb * k
        for i in range(n):
            for s in (1.0, -1.0):
                r = linprog(-s * M[k][i], A_ub=A_ub, b_ub=b_ub, bounds=bnds, method="highs")
                assert r.status == 0
                if s > 0:
                    hi[k, i] = -r.fun
                else:
                    lo[k, i] = r.fun
        assert nv == len(bnds)
    return lo, hi


def _linear_run(steps: int, seed: int, noise: str):
    """The linear system, 3 simulated trajectories and their exact hulls (HiGHS)."""
    system = linear_system()
    traj = system.simulate(steps=steps, batch=3, seed=seed, noise=noise)
    exact = [exact_hulls(system, traj.y[i].numpy(), C_LIN.numpy()) for i in range(3)]
    return system, traj, exact


@pytest.fixture(scope="module")
def linear_run():
    return _linear_run(15, 3, "vertex")


def test_exact_on_linear_system(linear_run):
    """No reduction: the hull of CZSMF equals the exact feasible set's hull at every step."""
    system, traj, exact = linear_run
    filt = CZSMF(system, max_generators=None, max_constraints=None)
    with torch.no_grad():
        res = filt(traj.y)
    for i, (lo, hi) in enumerate(exact):
        scale = 1 + np.abs(hi).max()
        assert np.abs(res.lower[i].numpy() - lo).max() <= 1e-7 * scale
        assert np.abs(res.upper[i].numpy() - hi).max() <= 1e-7 * scale
        # outer, never inner (beyond rounding)
        assert (res.lower[i].numpy() <= lo + 1e-12 * scale).all()
        assert (res.upper[i].numpy() >= hi - 1e-12 * scale).all()
    assert res.consistent.all()


@pytest.fixture(scope="module")
def linear_run_uniform():
    return _linear_run(20, 4, "uniform")


@pytest.mark.parametrize("caps,bound", [(None, 1.01), ((16, 3), 1.3)])
def test_reduced_close_to_exact(linear_run_uniform, caps, bound):
    """With reduction: outer, and the summed hull widths within ``bound`` of the exact set's
    (default caps (80, 10): measured 1.00014 over 30 steps, see docs/constrained_zonotopes.md)."""
    system, traj, exact = linear_run_uniform
    kw = {} if caps is None else dict(max_generators=caps[0], max_constraints=caps[1])
    with torch.no_grad():
        res = CZSMF(system, **kw)(traj.y)
    ratios = []
    for i, (lo, hi) in enumerate(exact):
        assert (res.lower[i].numpy() <= lo + 1e-9).all()
        assert (res.upper[i].numpy() >= hi - 1e-9).all()
        w = (res.upper[i] - res.lower[i]).numpy()[1:]
        ratios.append(w.sum() / (hi - lo)[1:].sum())
    r = float(np.mean(ratios))
    assert 1.0 - 1e-9 <= r <= bound, r


def test_exact_two_outputs():
    """Two outputs (two strips per step), no reduction, short horizon."""
    C = torch.tensor([[1.0, 0.0], [0.5, -1.0]])
    system = linear_system(C, "linear2")
    traj = system.simulate(steps=6, batch=1, seed=5, noise="uniform")
    lo, hi = exact_hulls(system, traj.y[0].numpy(), C.numpy())
    with torch.no_grad():
        res = CZSMF(system, max_generators=None, max_constraints=None)(traj.y)
    assert np.abs(res.lower[0].numpy() - lo).max() <= 1e-7 * (1 + np.abs(lo).max())
    assert np.abs(res.upper[0].numpy() - hi).max() <= 1e-7 * (1 + np.abs(hi).max())


# ---------------------------------------------------------------------------- W as given
W_GEN = torch.tensor([[-0.12, 0.01], [0.02, 0.03]], dtype=torch.float64)  # not axis-aligned
W_CEN = torch.tensor([0.01, -0.02], dtype=torch.float64)


def zonotope_w_system(W=None) -> ds.System:
    """The linear system of `linear_system` with a zonotope (or given) process noise."""
    base = linear_system()
    W = ds.Zonotope(W_CEN, W_GEN) if W is None else W
    return ds.System(
        base.f, base.h, base.x0_set, process_noise=W,
        measurement_noise=base.measurement_noise, name="linear_zonotope_w",
    )


def exact_hulls_zonotope_w(system: ds.System, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval hulls of the exact feasible sets for a zonotope W = c_w + G_w [-1, 1]^q, by
    HiGHS LPs over the whole horizon on the stacked variables (x0, alpha_0..alpha_{k-1}),
    ``w_j = c_w + G_w alpha_j`` (independent of CZSMF: plain numpy + scipy)."""
    A, C = A_LIN.numpy(), C_LIN.numpy()
    cw, Gw = system.process_noise.center.numpy(), system.process_noise.generators.numpy()
    n, q, T = 2, Gw.shape[1], y.shape[0]
    x0, V = system.x0_set, system.measurement_noise
    vlo, vhi = V.lower.numpy(), V.upper.numpy()
    lo, hi = np.zeros((T + 1, n)), np.zeros((T + 1, n))
    lo[0], hi[0] = x0.lower.numpy(), x0.upper.numpy()
    for k in range(1, T + 1):
        # x_j = M_j z + o_j, z = (x0, alpha_0, .., alpha_{k-1})
        M = [np.hstack([np.eye(n), np.zeros((n, q * k))])]
        o = [np.zeros(n)]
        for j in range(1, k + 1):
            Mj = A @ M[-1]
            Mj[:, n + q * (j - 1) : n + q * j] += Gw
            M.append(Mj)
            o.append(A @ o[-1] + cw)
        rows, rhs = [], []
        for j in range(1, k + 1):  # vlo <= y_j - C x_j <= vhi
            CM, Co = C @ M[j], C @ o[j]
            rows += [CM, -CM]
            rhs += [y[j - 1] - vlo - Co, -(y[j - 1] - vhi - Co)]
        A_ub, b_ub = np.vstack(rows), np.concatenate(rhs)
        bnds = list(zip(x0.lower.numpy(), x0.upper.numpy())) + [(-1.0, 1.0)] * (q * k)
        for i in range(n):
            for s in (1.0, -1.0):
                r = linprog(-s * M[k][i], A_ub=A_ub, b_ub=b_ub, bounds=bnds, method="highs")
                assert r.status == 0
                v = -s * r.fun + o[k][i]
                if s > 0:
                    hi[k, i] = v
                else:
                    lo[k, i] = v
    return lo, hi


def assert_contains(sets: ConstrainedZonotope, x: torch.Tensor, tol: float = 1e-9) -> None:
    """Every ``x [B, T+1, n]`` in ``sets [B, T+1]``: certified by ``contains`` or within
    ``tol`` (relative) of the set by HiGHS (``distance_lp``)."""
    inside = sets.contains(x, atol=tol)
    for i, k in (~inside).nonzero().tolist():
        d = float(distance_lp(sets[i, k], x[i, k]))
        assert d <= tol * (1 + float(x[i, k].abs().max())), (i, k, d)


def test_exact_with_zonotope_noise():
    """A zonotope W with non-axis-aligned generators enters as its generators: no reduction
    gives the exact feasible set (HiGHS over the whole horizon) to 1e-7, and strictly tighter
    than the filter on W's interval hull (what CZSMF used before)."""
    system = zonotope_w_system()
    traj = system.simulate(steps=12, batch=2, seed=7, noise="vertex")
    filt = CZSMF(system, max_generators=None, max_constraints=None)
    boxed = CZSMF(zonotope_w_system(system.process_noise.interval_hull()),
                  max_generators=None, max_constraints=None)
    with torch.no_grad():
        res = filt(traj.y)
        res_box = boxed(traj.y)
    for i in range(2):
        lo, hi = exact_hulls_zonotope_w(system, traj.y[i].numpy())
        scale = 1 + np.abs(hi).max()
        assert np.abs(res.lower[i].numpy() - lo).max() <= 1e-7 * scale
        assert np.abs(res.upper[i].numpy() - hi).max() <= 1e-7 * scale
        assert (res.lower[i].numpy() <= lo + 1e-12 * scale).all()
        assert (res.upper[i].numpy() >= hi - 1e-12 * scale).all()
        w, wb = (hi - lo)[1:].sum(), (res_box.upper[i] - res_box.lower[i]).numpy()[1:].sum()
        assert wb > 1.05 * w  # the box hull of W was measurably looser
    assert res.consistent.all()


def test_zonotope_noise_reduced_contains_truth():
    """Default caps with a zonotope W: outer to the exact set, every true state inside."""
    system = zonotope_w_system()
    traj = system.simulate(steps=12, batch=2, seed=8, noise="vertex")
    with torch.no_grad():
        res = CZSMF(system)(traj.y)
    for i in range(2):
        lo, hi = exact_hulls_zonotope_w(system, traj.y[i].numpy())
        assert (res.lower[i].numpy() <= lo + 1e-9).all()
        assert (res.upper[i].numpy() >= hi - 1e-9).all()
    assert_contains(res.sets, traj.x)


def test_box_noise_bit_identical():
    """A box W gives bit-identical sets to the previous formula (W's box centre and
    half-widths added as the diagonal generators, ``process_noise_box``), with and without
    reduction, learnable noise scale included."""
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=8, batch=3, seed=2)

    class OldNoise(CZSMF):
        def _noise(self):
            W = self.process_noise_box()
            return W.center, W.radius, None

    for kw in ({}, dict(max_generators=None, max_constraints=None)):
        new, old = CZSMF(system, **kw), OldNoise(system, **kw)
        with torch.no_grad():
            new.process_noise = old.process_noise = 0.7 * new.process_noise
            a, b = new(traj.y, u=traj.u), old(traj.y, u=traj.u)
        for x, z in zip(a.sets._tensors(), b.sets._tensors()):
            assert torch.equal(x, z)
        assert torch.equal(a.lower, b.lower) and torch.equal(a.upper, b.upper)


def test_ellipsoid_noise_cover():
    """An ellipsoid W enters by its constrained-zonotope cover: every true state inside, and
    never looser than the filter on W's interval hull."""
    Q = torch.tensor([[0.012, -0.004], [-0.004, 0.003]], dtype=torch.float64)
    W = ds.Ellipsoid(W_CEN, Q)
    system = zonotope_w_system(W)
    traj = system.simulate(steps=10, batch=20, seed=9, noise="vertex")
    kw = dict(max_generators=None, max_constraints=None)
    with torch.no_grad():
        res = CZSMF(system, **kw)(traj.y)
        res_box = CZSMF(zonotope_w_system(W.interval_hull()), **kw)(traj.y)
    assert_contains(res.sets, traj.x)
    assert (res.upper - res.lower <= res_box.upper - res_box.lower + 1e-9).all()
    assert float((res.upper - res.lower)[:, 1:].sum()) < float(
        (res_box.upper - res_box.lower)[:, 1:].sum()
    )


def test_zonotope_noise_gradient():
    """The learnable noise scale reaches a zonotope W (``process_noise_set``)."""
    system = zonotope_w_system()
    traj = system.simulate(steps=3, batch=2, seed=1)
    filt = CZSMF(system)
    filt(traj.y).volume[:, 1:].log().mean().backward()
    g = filt.raw_process_noise.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


def _bounded_systems() -> list[str]:
    out = []
    for name in ds.systems.names():
        s = ds.systems.get(name)
        if s.process_cov is None and s.measurement_cov is None:
            out.append(name)
    return out


def audit(filt, system, trials: int, steps: int, noise: str, seed: int = 11) -> tuple[int, int]:
    """(violations, inconsistent steps). A pair is a violation when the true state is outside
    the certified hull, or neither ``contains`` (torch LP) nor HiGHS puts it within 1e-9
    (relative) of the set."""
    traj = system.simulate(steps=steps, batch=trials, seed=seed, noise=noise)
    with torch.no_grad():
        res = filt(traj.y, u=traj.u)
    x = traj.x
    scale = 1 + x.abs().amax(-1)
    tol = 1e-9 * scale
    out_hull = ((x < res.lower - tol.unsqueeze(-1)) | (x > res.upper + tol.unsqueeze(-1))).any(-1)
    inside = res.sets.contains(x, atol=1e-9 * float(scale.max()))
    unsure = (~inside & ~out_hull).nonzero().tolist()
    bad = int(out_hull.sum())
    for i, k in unsure:
        Z = res.sets[i, k]
        if float(distance_lp(Z, x[i, k])) > tol[i, k]:
            bad += 1
    return bad, int((~res.consistent).sum())


FAST = dict(max_generators=12, max_constraints=3, elimination="propagation")


@pytest.mark.parametrize("noise", ["vertex", "uniform"])
@pytest.mark.parametrize("system_name", _bounded_systems())
def test_containment(system_name, noise):
    """Fast caps on every bounded built-in (the full audit: benchmarks/filters_audit.py)."""
    system = ds.systems.get(system_name)
    n = system.n
    trials, steps = (150, 6) if n <= 2 else (30, 3) if n <= 3 else (10, 2)
    bad, inconsistent = audit(CZSMF(system, **FAST), system, trials, steps, noise)
    assert bad == 0
    assert inconsistent == 0


@pytest.mark.parametrize("system_name", ["spring_damper", "bilinear", "vdp"])
def test_containment_default_caps(system_name):
    system = ds.systems.get(system_name)
    bad, inconsistent = audit(CZSMF(system), system, 40, 6, "vertex")
    assert bad == 0 and inconsistent == 0


def test_contract_online_equals_forward():
    system = ds.systems.get("bilinear")
    traj = system.simulate(steps=5, batch=4, seed=0)
    filt = CZSMF(system, **FAST)
    with torch.no_grad():
        res = filt(traj.y, u=traj.u)
        st = filt.initial_state(batch=4)
        for k in range(5):
            st = filt.predict(st, None if traj.u is None else traj.u[:, k])
            st = filt.update(st, traj.y[:, k])
    assert res.sets.batch_shape == (4, 6)
    assert res.lower.shape == (4, 6, 2) and res.volume.shape == (4, 6)
    assert res.consistent.shape == (4, 6)
    assert torch.allclose(st.extras["lower"], res.lower[:, -1], rtol=0, atol=1e-14)
    assert torch.allclose(st.extras["upper"], res.upper[:, -1], rtol=0, atol=1e-14)
    # fixed size after the first steps: constant cost per step
    assert st.set.num_generators == filt.max_generators
    assert st.set.num_constraints == filt.max_constraints


def test_batch_elements_independent():
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=6, batch=3, seed=1)
    filt = CZSMF(system)
    with torch.no_grad():
        res = filt(traj.y)
        one = filt(traj.y[1:2])
    assert torch.allclose(res.lower[1], one.lower[0], atol=1e-12)
    assert torch.allclose(res.upper[1], one.upper[0], atol=1e-12)


def test_inconsistent_measurement_flagged():
    system = linear_system()
    traj = system.simulate(steps=4, batch=2, seed=2)
    y = traj.y.clone()
    y[0, 2] += 50.0  # impossible measurement at step 3 for element 0
    with torch.no_grad():
        res = CZSMF(system)(y)
    assert not bool(res.consistent[0, 3])
    assert bool(res.consistent[1].all())
    assert torch.isfinite(res.lower).all() and (res.lower <= res.upper).all()


def test_skip_nan():
    system = linear_system()
    traj = system.simulate(steps=3, batch=2, seed=2)
    y = traj.y.clone()
    y[1, 1] = float("nan")
    with pytest.raises(ValueError, match="y"):
        CZSMF(system)(y)
    with torch.no_grad():
        res = CZSMF(system, skip_nan=True)(y)
    assert torch.isfinite(res.lower).all()
    # the skipped update keeps the predicted set: contains the truth
    assert ((traj.x >= res.lower - 1e-9) & (traj.x <= res.upper + 1e-9)).all()


def test_gradients_flow_to_hyperparameters():
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=4, batch=2, seed=0)
    filt = CZSMF(system)
    res = filt(traj.y)
    res.volume[:, 1:].log().mean().backward()
    for name in ("raw_process_noise", "raw_measurement_noise", "raw_stirling_step"):
        g = getattr(filt, name).grad
        assert g is not None and torch.isfinite(g).all(), name
    assert filt.raw_process_noise.grad.abs().sum() > 0


def test_lagrange_remainder_option():
    system = ds.systems.get("bilinear")
    bad, _ = audit(CZSMF(system, remainder="lagrange"), system, 50, 4, "vertex")
    assert bad == 0


def test_bad_arguments():
    system = ds.systems.get("bilinear")
    with pytest.raises(ValueError, match="max_generators"):
        CZSMF(system, max_generators=3, max_constraints=3)
    with pytest.raises(ValueError, match="max_generators"):
        CZSMF(system, max_generators=None, max_constraints=3)
    with pytest.raises(ValueError, match="max_constraints"):
        CZSMF(system, max_generators=20, max_constraints=-2)
    with pytest.raises(ValueError, match="remainder"):
        CZSMF(system, remainder="taylor")
    with pytest.raises(ValueError, match="reduce_method"):
        CZSMF(system, reduce_method="pca")
    with pytest.raises(ValueError, match="stirling_step"):
        CZSMF(system, stirling_step=-1.0)
    with pytest.raises(ValueError, match="y"):
        CZSMF(system)(torch.zeros(2, 3, 5))
    for key, value in [("lp_iters", True), ("max_constraints", True), ("lp_iters", 2.0),
                       ("elimination", None)]:  # a bool is not a count
        with pytest.raises(ValueError, match=key):
            CZSMF(system, **{key: value})
    with pytest.raises(ValueError, match="max_generators"):
        CZSMF(system, max_generators=True, max_constraints=0)
    # -1 was a hidden "default" sentinel: max_generators=-1 silently gave the default caps;
    # now the default is "auto" and -1, another string or a string constraint cap are named
    for kw, key in [({"max_generators": -1}, "max_generators"),
                    ({"max_constraints": -1}, "max_constraints"),
                    ({"max_generators": "AUTO"}, "max_generators"),
                    ({"max_constraints": "x"}, "max_constraints")]:
        with pytest.raises(ValueError, match=f"^{key}: must be"):
            CZSMF(system, **kw)
    n, m = system.n, system.m
    auto = CZSMF(system, max_generators="auto", max_constraints="auto")
    assert (auto.max_generators, auto.max_constraints) == (35 * n + 4 + 6 * m, 4 + 6 * m)
    assert CZSMF(system, max_constraints=3).max_generators == 35 * n + 3


def test_by_name_and_initial_set():
    system = ds.systems.get("mismatch_quadratic")  # ellipsoidal X0: outer conversion
    filt = ds.filters.by_name("czsmf")(system)
    assert isinstance(filt, CZSMF)
    S = filt.initial_state(batch=2).set
    assert isinstance(S, ConstrainedZonotope)
    pts = system.x0_set.sample_extreme(200, generator=torch.Generator().manual_seed(0))
    assert float(distance_lp(S[0], pts).max()) == 0.0  # outer (HiGHS)
    assert bool(S[0].contains(pts, atol=1e-7).all())  # boundary points, certified to 1e-7


@pytest.mark.parametrize("traced", [False, True])
@pytest.mark.parametrize("elimination", ["hull", "propagation"])
def test_certified_empty_update_keeps_the_predicted_set(elimination, traced, monkeypatch):
    """An element whose update is certified empty (crossed hull bounds) is flagged
    inconsistent and carries on with the predicted set itself (at the caps: same shape as the
    update, no second reduction); the other elements are updated as usual. ``traced``: the
    branch-free path that ``compile()`` traces (taken for every element, selected by
    ``empty``)."""
    import diffsmf.filters.czsmf as czmod

    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=6, batch=2, seed=0, noise="vertex")
    filt = CZSMF(s, max_generators=12, max_constraints=3, elimination=elimination)
    with torch.no_grad():
        st = filt.initial_state(batch=2)
        for k in range(5):
            st = filt.step(st, None, tr.y[:, k])
        pred = filt.predict(st)
        assert (pred.set.num_generators, pred.set.num_constraints) == (12, 3)  # at the caps
        normal = filt._update(pred, tr.y[:, 5])
        hull = filt._hull

        def crossed(Z):  # element 0 certified empty
            lo, hi = hull(Z)
            return lo, torch.where(torch.tensor([[True], [False]]), lo - 1.0, hi)

        cap_hull, caps = filt._cap_hull, []

        def counted(Z, box=None):  # no hull from the ranking's duals, and count the caps
            caps.append(Z.num_constraints)
            return cap_hull(Z, box)[0], None

        monkeypatch.setattr(filt, "_hull", crossed)
        monkeypatch.setattr(filt, "_cap_hull", counted)
        if traced:
            monkeypatch.setattr(czmod, "tracing", lambda: True)
        out = filt._update(pred, tr.y[:, 5])
    assert out.consistent.tolist() == [False, True]
    assert caps == [3 + 1]  # one reduction (the update's), none for the fault path
    for f_out, f_pred, f_norm in zip(out.set._tensors(), pred.set._tensors(),
                                     normal.set._tensors()):
        assert torch.equal(f_out[0], f_pred[0])  # the predicted set, not an outer bound of it
        assert torch.equal(f_out[1], f_norm[1])
    assert torch.equal(out.extras["lower"][0], pred.extras["lower"][0])
    assert torch.equal(out.extras["upper"][0], pred.extras["upper"][0])
