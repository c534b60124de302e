"""Data-parallel tuning: 2 local gloo processes follow the single-process run."""

from __future__ import annotations

import os
import socket

import pytest
import torch
import torch.multiprocessing as mp
from test_training_toy import V_BOUND, W_BOUND, ToyIntervalFilter, toy_system

from diffsmf.tuning import tune
from diffsmf.tuning.loop import Data

pytestmark = pytest.mark.slow  # starts two gloo processes

KW = dict(epochs=4, batch_size=6, lr=0.1, validation=None, progress=False, seed=5, tie=None)


def _problem():
    s = toy_system()
    tr = s.simulate(12, batch=12, seed=4, noise="vertex")
    f = ToyIntervalFilter(s, process_noise=3 * W_BOUND, measurement_noise=3 * V_BOUND)
    return f, Data(tr.y, tr.x)


def _worker(rank: int, world: int, port: int, path: str, window: int | None = None) -> None:
    import torch.distributed as dist

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        f, data = _problem()
        rep, f = tune(f, data, loss="both", window=window, **KW)
        if rank == 0:
            torch.save(
                {"state": f.state_dict(), "history": rep.history, "ws": rep.world_size}, path
            )
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("window", [None, 5])
def test_two_gloo_processes_match_one_process(tmp_path, window):
    """Also windowed tuning: the carried window states are shared between the processes."""
    path = str(tmp_path / "ddp.pt")
    mp.spawn(_worker, args=(2, _free_port(), path, window), nprocs=2, join=True)
    got = torch.load(path, weights_only=False)
    f, data = _problem()
    rep, f = tune(f, data, loss="both", window=window, **KW)
    assert got["ws"] == 2 and rep.world_size == 1
    for k, v in f.state_dict().items():
        assert torch.allclose(got["state"][k], v, rtol=1e-10, atol=1e-14), k
    for a, b in zip(got["history"], rep.history):
        for k in b:
            assert abs(a[k] - b[k]) <= 1e-9 * (1 + abs(b[k])), k
