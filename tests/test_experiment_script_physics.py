"""Physics of the experiment scripts' building blocks, against independent calculations (cheap: no rollout).
scripts/stacked_books.py's placement and support margin, scripts/impact_model_1d.py's implicit step and schedules."""

from __future__ import annotations

import math

import pytest
import torch


@pytest.mark.parametrize("retract", [0.0, 1e-3, 0.25])
def test_harmonic_placement_puts_every_substack_com_r_l_over_2_inside(scripts_path, retract):
    from stacked_books import overhang_edges

    n, L = 7, 1.3
    edges = overhang_edges(n, L, retract)  # board k = 1..n from the top; the table's edge at 0
    below = edges[1:] + [0.0]
    for k in range(1, n + 1):
        com = sum(e - L / 2 for e in edges[:k]) / k
        assert below[k - 1] - com == pytest.approx(retract * L / 2, abs=1e-12)


def test_support_margin_and_tilt_of_the_rigid_placement(scripts_path):
    from stacked_books import overhang_edges, support

    n, L, h, r = 5, 1.0, 0.03, 2e-3
    q = torch.zeros(n + 1, 6, dtype=torch.float64)
    q[0, 0], q[0, 2] = -L / 2, -0.05
    for i, e in enumerate(reversed(overhang_edges(n, L, r)), start=1):
        q[i, 0], q[i, 2] = e - L / 2, (i - 0.5) * h
    masses = torch.tensor([0.0] + [3.6] * n, dtype=torch.float64)
    margin, tilt = support(q, masses, L)
    assert torch.allclose(margin, torch.full((n,), r * L / 2, dtype=torch.float64), atol=1e-12)
    assert float(tilt.abs().max()) < 1e-7
    q[1:, 0] += 0.01  # the whole stack 1 cm outward: only the table interface loses it
    margin, _ = support(q, masses, L)
    assert float(margin[0]) == pytest.approx(r * L / 2 - 0.01, abs=1e-12)
    assert torch.allclose(margin[1:], torch.full((n - 1,), r * L / 2, dtype=torch.float64), atol=1e-12)


def test_implicit_step_solves_the_stationarity_condition(scripts_path):
    from impact_model_1d import GapPotential, implicit_step
    from scipy.optimize import brentq

    P = GapPotential()
    mr, h = 0.5 * float(P.cube.mass), 0.01
    for g, v in ((0.004, -1.0), (0.0015, -1.0), (0.0012, 0.3)):
        x, _ = implicit_step(P, g, v, h, mr)
        gt = g + h * v
        root = brentq(
            lambda y, gt=gt: mr / h**2 * (y - gt) + P(y)[1], P.margin * (1 + 1e-9), g + 1.0, xtol=1e-15
        )
        assert x == pytest.approx(root, abs=1e-12)


def test_aligned_schedule_splits_at_the_crossing_and_sums_to_the_step(scripts_path):
    from impact_model_1d import schedule

    g, v, dt = 0.0105, -1.0, 0.01
    hs = schedule("aligned:0.004:2", g, v, dt, 0.004)
    assert sum(hs) == pytest.approx(dt, abs=1e-15) and all(x > 0 for x in hs)
    assert g + v * hs[0] == pytest.approx(0.004, abs=1e-15)
    assert schedule("aligned:0.004:2", 0.02, v, dt, 0.004) == [dt]  # no crossing in this step
    assert math.isclose(sum(schedule("sub:4", g, v, dt, 0.0)), dt)
