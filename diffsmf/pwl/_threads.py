"""Run loops of small tensor operations on one intra-op thread."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def single_thread(blas: bool = False) -> Iterator[None]:
    """Set torch to one intra-op thread inside the block, restore the count afterwards; with
    ``blas=True`` also limit numpy/scipy's BLAS (OpenBLAS, MKL) to one thread, if threadpoolctl
    is installed (it comes with scikit-learn).

    The fitting loops here are made of many small operations; on a loaded machine the hand-off
    between threads costs more than the work itself (measured 100x slower with 2 threads; a
    batch of small numpy inverses with 2 OpenBLAS threads took 62 s instead of 0.01 s)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    limiter: contextlib.AbstractContextManager = contextlib.nullcontext()
    if blas:
        try:
            from threadpoolctl import threadpool_limits

            limiter = threadpool_limits(1, user_api="blas")
        except ImportError:  # pragma: no cover - optional
            pass
    try:
        with limiter:
            yield
    finally:
        torch.set_num_threads(threads)
