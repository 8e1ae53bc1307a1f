"""numba's thread pool, started without touching torch's thread count; serial twins of the parallel kernels; what a
forked child process may run."""

from __future__ import annotations

import functools
import os
import threading
import types

import numba
import torch

_FORKED = False  # this process is a fork() child of one that imported cfd_torch


def _after_fork_in_child() -> None:
    """A fork() child inherits GNU OpenMP's thread pool (torch's and numba's, one libgomp) without its threads: its
    first torch op on several threads waits for them forever, and numba's OpenMP layer terminates the process
    (SIGTERM) at its first parallel kernel. The child computes on one thread instead (torch's DataLoader workers do
    the same) and the library runs its kernels' serial twins (:func:`parallel_kernels`)."""
    global _FORKED
    _FORKED = True
    torch.set_num_threads(1)


os.register_at_fork(after_in_child=_after_fork_in_child)


def parallel_kernels() -> bool:
    """Whether numba's parallel kernels (and the traversal's threads) may run here: not in a fork() child (start
    worker processes with multiprocessing's "spawn" or "forkserver" context to keep them), and under numba's
    workqueue threading layer only on the main thread (that layer is not thread-safe: two threads in parallel
    kernels at once abort the process, "Concurrent access has been detected"; other threads run the serial twins)."""
    if _FORKED:
        return False
    return threading.current_thread() is threading.main_thread() or not _workqueue_layer()


@functools.cache
def _workqueue_layer() -> bool:
    """Whether numba's thread pool runs on its workqueue layer (its fallback without OpenMP or TBB)."""
    start_numba_pool()  # (the layer is chosen when the pool starts)
    return numba.threading_layer() == "workqueue"


def serial_twin(kernel, **jit):
    """The serial compilation of a parallel numba kernel ``kernel`` (``jit``: its njit options without
    ``parallel``), cached apart from it.

    numba's cache names an entry by the function's module, qualified name and first line and keys it by its
    bytecode, not by its compile options: ``njit(cache=True)(kernel.py_func)`` shared the parallel kernel's cache
    entry, so whichever of the two compiled first in a cold cache was what both ran from then on (the serial twin
    ran numba's thread pool, or the parallel kernel one thread). The twin is a copy of the function under its own
    qualified name."""
    f = kernel.py_func
    twin = types.FunctionType(
        f.__code__, f.__globals__, f.__name__ + "_serial", f.__defaults__, f.__closure__
    )
    twin.__qualname__ = f.__qualname__ + "_serial"
    twin.__module__ = f.__module__
    twin.__doc__ = f.__doc__
    return numba.njit(**jit)(twin)


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
