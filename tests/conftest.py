from __future__ import annotations

import os
import sys
from pathlib import Path

import numba
import pytest
import torch

import cfd_torch  # noqa: F401  (before any test module imports mujoco: it picks MuJoCo's headless GL backend)

sys.path.insert(0, str(Path(__file__).parent))

F64 = torch.float64
SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


@pytest.fixture
def scripts_path():
    """scripts/ importable (its modules import each other by name) for the test."""
    sys.path.insert(0, str(SCRIPTS))
    yield
    sys.path.remove(str(SCRIPTS))


def pytest_configure(config):
    """Under pytest-xdist (``make test`` runs one worker per core) each worker computes on one thread: the workers
    already fill the cores, and two workers' kernel threads on the same cores spin against each other (measured on
    this project's 2-core machine: 302 s with each worker's default threads, 216 s with one thread each, against
    358 s for the suite in one process). Tests of threaded results raise their thread count themselves."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        numba.set_num_threads(1)  # first: starting numba's pool resets the OpenMP thread count torch shares
        torch.set_num_threads(1)


def _t(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=F64)


def feature_pairs(gap: float) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Triangle pairs whose closest distance is exactly ``gap``, one per feature case (a below, b above)."""
    base = _t([[-1.0, -0.8, 0.0], [1.2, -0.6, 0.0], [0.1, 1.1, 0.0]])
    up = _t([0.0, 0.0, 1.0])
    cases = {
        # a vertex of b above the interior of a's face
        "vertex-face": (base, _t([[0.1, 0.05, 0.0], [0.9, 0.3, 0.8], [-0.5, 0.6, 0.7]]) + gap * up),
        # crossing edges: a's top edge along x, b's bottom edge along y
        "edge-edge": (
            _t([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.3, -1.0]]),
            _t([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.4, 0.0, 1.0]]) + gap * up,
        ),
        # parallel faces, b rotated in plane and stacked
        "face-face": (base, _t([[-0.7, -0.5, 0.0], [0.8, -0.2, 0.0], [0.0, 0.9, 0.0]]) + gap * up),
        # an edge of b parallel to a's face
        "edge-face": (base, _t([[-0.3, 0.0, 0.0], [0.4, 0.1, 0.0], [0.0, 0.2, 0.9]]) + gap * up),
        # apex to apex
        "vertex-vertex": (
            _t([[0.0, 0.0, 0.0], [1.0, 0.2, -1.0], [-0.4, 0.9, -1.1]]),
            _t([[0.0, 0.0, 0.0], [0.8, -0.4, 1.0], [-0.5, -0.7, 1.2]]) + gap * up,
        ),
        # parallel edges (side by side in one plane, not overlapping in projection)
        "parallel-edges": (
            _t([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
            _t([[-0.5, 0.0, 0.0], [1.5, 0.0, 0.0], [0.5, 0.0, 1.0]]) + gap * up,
        ),
        # coplanar, side by side
        "coplanar": (
            _t([[-1.0, -1.0, 0.0], [0.0, -1.0, 0.0], [-0.5, 0.0, 0.0]]),
            _t([[0.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.5, 0.0, 0.0]]) + gap * _t([1.0, 0.0, 0.0]),
        ),
    }
    return cases
