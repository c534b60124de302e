"""Run loops of small tensor operations on one intra-op thread."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """Set torch to one intra-op thread inside the block, restore the count afterwards.

    The fitting loops here are made of many small operations; on a loaded machine the hand-off
    between threads costs more than the work itself (measured 100x slower with 2 threads)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
