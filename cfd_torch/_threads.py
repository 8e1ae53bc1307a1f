"""numba's thread pool, started without touching torch's thread count."""

from __future__ import annotations

import functools

import numba
import torch


@functools.cache
def start_numba_pool() -> None:
    """Start numba's thread pool (once per process), keeping torch's intra-op thread count.

    numba's parallel kernels start the pool at their first call, and its OpenMP threading layer then sets the
    process's OpenMP thread count, which torch's CPU operations share (one libgomp), to NUMBA_NUM_THREADS: a
    ``torch.set_num_threads`` made before would silently be undone (a worker process set to one thread would run
    torch on every core). Call it before a parallel kernel or ``numba.get_num_threads`` (which starts it too)."""
    n = torch.get_num_threads()
    numba.set_num_threads(numba.get_num_threads())
    torch.set_num_threads(n)
