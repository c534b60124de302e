import os

import torch

os.environ.setdefault("MPLBACKEND", "Agg")
torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)  # small batched ops: one thread is fastest and deterministic


import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread and one BLAS thread in every test: small tensor ops on a loaded 2-core
    machine are dominated by thread hand-offs (measured 30 s instead of 2 s for one PWL test;
    OpenBLAS 62 s instead of 0.01 s), and results do not depend on the thread count (tested
    explicitly where it matters, e.g. tests/test_pwl.py)."""
    from threadpoolctl import threadpool_limits

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    with threadpool_limits(1, user_api="blas"):
        yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def fresh_dynamo():
    """Dynamo's caches reset before and after a module (the compile tests: each module's graphs
    and recompile counts start from nothing, whatever ran before on the worker)."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def load_script(folder: str, name: str):
    """``folder/name.py`` of the repository (a script, not part of the package) as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def gradcheck_noise_bounds(filt, traj, outputs=("volume", "center")) -> bool:
    """``torch.autograd.gradcheck`` of ``filt(traj.y, u=traj.u)``'s last-step ``outputs``
    (names of `FilterResult` fields) in the filter's two stored noise parameters."""
    from torch.func import functional_call

    names = ["raw_process_noise", "raw_measurement_noise"]
    params = tuple(getattr(filt, n).detach().clone().requires_grad_(True) for n in names)

    def fn(a, b):
        res = functional_call(filt, {names[0]: a, names[1]: b}, (traj.y,), {"u": traj.u})
        return tuple(getattr(res, o)[:, -1] for o in outputs)

    return torch.autograd.gradcheck(fn, params, eps=1e-7, atol=1e-6, rtol=1e-4)
