"""SCPLNN.forward under torch.func.vmap / jacrev and torch.compile(fullgraph=True),
compared with plain batched evaluation and with the affine pieces' slopes (an independent
reference: the Jacobian of f on simplex k is A_k)."""

import pytest
import torch

from diffsmf.pwl import SCPLNN, fit_scplnn

F64 = torch.float64




def _model(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(1500, n, generator=g, dtype=F64) * 2 - 1
    Y = torch.stack([torch.sin(2 * X).sum(-1), (X ** 2).sum(-1)], -1)
    model, _ = fit_scplnn(X, Y, 0.1 if n < 4 else 0.2)
    x = torch.rand(40, n, generator=g, dtype=F64) * 1.8 - 0.9
    return model, x


@pytest.mark.parametrize("n", [2, 4])  # bins point location in 2-D, walk in 4-D
def test_vmap_and_jacrev_match_batched_forward_and_piece_slopes(n):
    model, x = _model(n)
    assert model._get("locator").mode == ("bins" if n == 2 else "walk")
    with torch.no_grad():
        ref = model(x)
        assert torch.equal(torch.func.vmap(model)(x), ref)
        J = torch.func.vmap(torch.func.jacrev(model))(x)  # [40, p, n]
    s, _ = model.locate(x)
    A = model.regions().A.detach()[s]  # slope of the piece containing each point
    assert J.shape == (40, 2, n) and torch.allclose(J, A, atol=1e-10)
    # vmap over a batch of models' weights (functional_call), e.g. an ensemble
    W = model.weight.detach()[None] * torch.tensor([1.0, 2.0, -1.0], dtype=F64)[:, None, None]
    out = torch.func.vmap(lambda w: torch.func.functional_call(model, {"weight": w}, (x,)))(W)
    assert torch.allclose(out, ref[None] * torch.tensor([1.0, 2.0, -1.0], dtype=F64)[:, None,
                                                                                      None])


@pytest.mark.parametrize("n", [2, 4])
def test_compile_fullgraph_no_graph_breaks(n):
    model, x = _model(n, seed=1)
    model.prepare()
    if n == 2:  # (the 4-D walk unrolls into a long graph: traced once, below)
        explain = torch._dynamo.explain(model)(x)
        assert explain.graph_break_count == 0 and explain.graph_count == 1
    compiled = torch.compile(model, fullgraph=True, backend="eager")  # raises on a break
    with torch.no_grad():
        assert torch.equal(compiled(x), model(x))
    xg = x.clone().requires_grad_(True)
    compiled(xg).sum().backward()
    xr = x.clone().requires_grad_(True)
    model(xr).sum().backward()
    assert torch.allclose(xg.grad, xr.grad)


def test_compile_needs_prepared_locator():
    model, x = _model(2, seed=2)
    fresh = SCPLNN.from_state_dict(model.state_dict())
    with pytest.raises(Exception, match="prepare"):
        torch.compile(fresh, fullgraph=True, backend="eager")(x)


def test_one_dimensional_inputs_round_trip():
    """A 1-D X accepted by fit_scplnn gives a model that accepts the same 1-D x."""
    t = torch.linspace(0, 3, 400, dtype=F64)
    model, rep = fit_scplnn(t, torch.sin(2 * t), 0.01)
    assert rep.converged
    with torch.no_grad():
        a, b = model(t), model(t[:, None])
        assert a.shape == (400, 1) and torch.equal(a, b)
        assert float((a[:, 0] - torch.sin(2 * t)).abs().max()) < 0.01
        assert model(torch.tensor(1.5, dtype=F64)).shape == (1,)
        assert torch.func.vmap(model)(t).shape == (400, 1)
