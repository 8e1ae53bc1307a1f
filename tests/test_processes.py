"""The library under fork() and numba's cache: serial twins of the parallel kernels keep their own cache entries, and a
process forked after the library ran its parallel kernels computes (on one thread) instead of hanging; a run that
compiles the kernels computes what a run that loads them from the cache does."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cfd_torch import _validate
from cfd_torch.contact import _pair_numba

ROOT = Path(__file__).resolve().parents[1]


def test_serial_twins_have_their_own_cache_entries():
    """numba names a cache entry by module, qualified name and line, not by ``parallel``: a serial kernel compiled
    from the parallel kernel's own function would share its entry, and whichever compiled first in a cold cache
    would run for both (the serial path starting numba's pool, or the parallel path running on one thread)."""
    for parallel, serial in (
        (_pair_numba.solve_pairs, _pair_numba.solve_pairs_serial),
        (_validate._triangle_codes_nb, _validate._triangle_codes_serial),
    ):
        assert parallel._cache._impl._filename_base != serial._cache._impl._filename_base


_FORK_SCRIPT = """
import multiprocessing as mp, sys
import numba, torch
numba.set_num_threads(2)
torch.set_num_threads(2)
from cfd_torch import pair_potential_derivatives
from cfd_torch.contact._pair_numba import PARALLEL_MIN_PAIRS

def solve():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(PARALLEL_MIN_PAIRS, 3, 3, generator=g, dtype=torch.float64)
    d = pair_potential_derivatives(a, a + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    return (torch.rand(1000, 1000, generator=g, dtype=torch.float64).exp().sum() + d.value.sum()).item()

def child(q):
    q.put(solve())

if __name__ == "__main__":
    expected = solve()  # numba's pool and torch's OpenMP threads started here
    q = mp.get_context("fork").Queue()
    p = mp.get_context("fork").Process(target=child, args=(q,))
    p.start()
    p.join(40)
    if p.exitcode is None:
        p.kill()
        sys.exit("the forked child hung")
    assert p.exitcode == 0, p.exitcode
    assert q.get(timeout=5) == expected
    print("ok")
"""


def test_forked_child_computes(tmp_path):
    """A child forked after the library's parallel kernels ran: libgomp's pool is inherited without its threads
    (torch's next threaded op waited forever, numba's OpenMP layer terminated the child at its next parallel
    kernel); the child now runs on one thread with the serial kernels, with the parent's results."""
    script = tmp_path / "fork_child.py"
    script.write_text(_FORK_SCRIPT)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stdout + out.stderr


_THREADS_SCRIPT = """
from concurrent.futures import ThreadPoolExecutor
import numba, torch
from cfd_torch import pair_potential_derivatives
from cfd_torch.contact._pair_numba import PARALLEL_MIN_PAIRS
from cfd_torch.testing import random_separated_pairs

a, b, _ = random_separated_pairs(2 * PARALLEL_MIN_PAIRS, seed=0)
expected = pair_potential_derivatives(a, b).hessian  # the main thread: the parallel kernel
assert numba.threading_layer() == "workqueue", numba.threading_layer()
with ThreadPoolExecutor(3) as pool:
    got = list(pool.map(lambda _: pair_potential_derivatives(a, b).hessian, range(6)))
assert all(torch.equal(g, expected) for g in got)
print("ok")
"""


def test_threads_under_numba_workqueue_layer_run_the_serial_kernels(tmp_path):
    """numba's workqueue threading layer (its fallback without OpenMP or TBB) is not thread-safe: threads calling
    the parallel pair kernel at once aborted the process ("Concurrent access has been detected"). Other threads
    than the main one run the serial twins there, with the same results."""
    script = tmp_path / "threads.py"
    script.write_text(_THREADS_SCRIPT)
    env = {
        **os.environ,
        "NUMBA_THREADING_LAYER": "workqueue",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stdout + out.stderr


_CACHE_SCRIPT = """
import sys
import numpy as np, torch
torch.set_num_threads(1)
from cfd_torch.envs import make_core, rollout

core = make_core("cfd_torch/Billiards-v0")
state = core.reset(0, 4)
cue = state.q[:, 15, :2]
actions = torch.zeros(50, 4, 2, dtype=torch.float64)
actions[:10] = -cue / cue.norm(dim=-1, keepdim=True)  # the cue ball driven at the rack for 10 steps: a break
actions.requires_grad_(True)
out = rollout(core, state, actions)
out.rewards.sum().backward()
# the plane solve's and the traversal's own kernels compiled in this process (none where loaded from the cache) and
# those with a literal-typed argument (add_rotation_terms, a few lines imported from elsewhere, takes its literal
# block offsets 3 and 9)
from numba.core import types
from numba.core.dispatcher import Dispatcher
from cfd_torch.contact import _pair_numba, _traverse_numba
kernels = [
    f for m in (_pair_numba, _traverse_numba) for f in vars(m).values()
    if isinstance(f, Dispatcher) and f.py_func.__module__ == m.__name__
]
compiled = sorted(f.py_func.__name__ for f in kernels if f.signatures)
literal = sorted(
    f"{f.py_func.__name__}{sig}" for f in kernels for sig in f.signatures
    if any(isinstance(t, types.Literal) for t in sig)
)
np.savez(sys.argv[1], q=out.q.detach().numpy(), grad=actions.grad.numpy(), compiled=compiled, literal=literal)
"""


@pytest.mark.slow
def test_a_first_run_compiling_the_kernels_equals_later_runs_loading_them(tmp_path):
    """A fresh clone's first run compiles numba's kernels in the process; later runs load them from its cache. With
    fastmath (FMA contraction, reciprocal multiplication) in the pair kernel the two rounded differently (a 4-scene
    break shot's positions 5e-16 m apart at step 30, its gradient 9e-22): the first run was not reproduced. The
    first run compiles no contact kernel twice (for a literal argument and for int64)."""
    script = tmp_path / "break.py"
    script.write_text(_CACHE_SCRIPT)
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache"),  # empty: the first run compiles every kernel
        "NUMBA_NUM_THREADS": "1",
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    for name in ("cold", "warm"):
        out = subprocess.run(
            [sys.executable, str(script), str(tmp_path / f"{name}.npz")], capture_output=True, text=True,
            timeout=900, env=env,
        )  # fmt: skip
        assert out.returncode == 0, out.stdout + out.stderr
    cold, warm = np.load(tmp_path / "cold.npz"), np.load(tmp_path / "warm.npz")
    assert (
        np.abs(cold["grad"]).max() > 0 and np.abs(cold["q"][-1] - cold["q"][0]).max() > 0.1
    )  # the balls broke
    assert np.array_equal(cold["q"], warm["q"]) and np.array_equal(cold["grad"], warm["grad"])
    # numba compiles a kernel called from another with a constant argument (``f(0, ...)``, a counter ``top = 1``
    # before its loop) once for the literal's type and again for int64: the serial plane solve's
    # ``_solve_range(0, ...)`` cost a second 40 s compile of the whole solve, the traversal's counters seconds more
    assert {"_solve_range", "solve_pairs_serial", "_pair_nodes", "_far_moments"} <= set(cold["compiled"])
    assert cold["literal"].size == 0, cold["literal"]
