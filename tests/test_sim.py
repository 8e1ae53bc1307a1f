"""Tests of the simulator's seams: batches of scenes, the Newton solver's stop reasons, the contact-model protocol,
the config objects, sub-stepping, pairwise forces, StepInfo and the torch backend of a step.

Oracle of the batch tests: stepping B scenes together equals stepping each alone (to 1e-12), forward and adjoint.
"""

from __future__ import annotations

import io
import math
import pickle
import re
import warnings

import pytest
import torch
import trimesh

from cfd_torch import (
    Action,
    CfdContact,
    ContactConfig,
    ContactModel,
    FrictionConfig,
    Scene,
    SolverConfig,
    State,
    StepError,
    StepInfo,
    pair_forces,
    rigid_body,
    rollout,
    step,
)
from cfd_torch.sim.energy import EnergyEval
from cfd_torch.sim.newton import Stop, _incidence, _restricted, newton

F64 = torch.float64
G = 9.81


def _box(extents, *, kind="dynamic", max_edge=None):
    return rigid_body(trimesh.creation.box(extents=extents), kind=kind, max_edge=max_edge)


@pytest.fixture(scope="module")
def bodies():
    cube = _box((0.2, 0.2, 0.2), max_edge=0.1)
    mesh = trimesh.creation.box(extents=(1.4, 0.6, 0.05))
    mesh.apply_translation([0.0, 0.0, -0.025])
    ground = rigid_body(mesh, kind="static", max_edge=0.2)
    pusher = _box((0.05, 0.2, 0.1), kind="kinematic", max_edge=0.1)
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1))
    return cube, ground, pusher, ball


def _pose(*xyz_rot) -> list[float]:
    return list(xyz_rot) + [0.0] * (6 - len(xyz_rot))


def _scene_batch(bodies):
    """Three scenes of a cube, the ground, a kinematic pusher and a ball, in different states: resting, pushed and
    sliding into the ball, and dropping with a spin."""
    cube, ground, pusher, ball = bodies
    scene = Scene((cube, ground, pusher, ball), friction=0.4)
    h = 0.1 + 1.5e-3
    q = torch.tensor(
        [
            [_pose(0.0, 0.0, h), _pose(), _pose(-0.5, 0.0, 0.06), _pose(0.4, 0.0, 0.1015)],
            [_pose(0.0, 0.0, h), _pose(), _pose(-0.128, 0.0, 0.06), _pose(0.3, 0.05, 0.1015)],
            [_pose(0.1, 0.0, 0.3, 0.2, 0.1), _pose(), _pose(-0.5, 0.0, 0.06), _pose(-0.2, 0.1, 0.35)],
        ],
        dtype=F64,
    )
    v = torch.zeros_like(q)
    v[1, 0, 0] = 0.3
    v[2, 0, 3:] = torch.tensor([2.0, -1.0, 0.5], dtype=F64)
    v[2, 3, 2] = -0.5
    target = q[:, 2:3].clone()
    target[1, 0, 0] += 0.004  # the pusher advances 4 mm per step in scene 1
    force = torch.zeros(3, 4, 3, dtype=F64)
    force[0, 3, 0] = -5.0
    return scene, scene.initial_state(q, v), target, force


def test_batch_of_scenes_equals_stepping_each_alone(bodies):
    scene, state, target, force = _scene_batch(bodies)
    B = state.q.shape[0]
    batched, infos = state, []
    singles = [State(state.q[b], state.q_prev[b]) for b in range(B)]
    for _ in range(4):
        batched, info = step(scene, batched, Action(force=force, target=target), return_info=True)
        infos.append(info)
        for b in range(B):
            singles[b] = step(scene, singles[b], Action(force=force[b], target=target[b]))
    iters = torch.stack([i.newton_iters for i in infos])
    assert iters.shape == (4, B) and bool((iters >= 1).all())
    assert len(set(iters[-1].tolist())) > 1  # the scenes needed different numbers of iterations
    for b in range(B):
        assert float((singles[b].q - state.q[b]).abs().max()) > 1e-6  # something moved
        torch.testing.assert_close(batched.q[b], singles[b].q, rtol=0, atol=1e-12)
        torch.testing.assert_close(batched.q_prev[b], singles[b].q_prev, rtol=0, atol=1e-12)


def test_batched_adjoint_equals_single_adjoints(bodies):
    scene, state, target, force = _scene_batch(bodies)
    B = state.q.shape[0]
    w = torch.linspace(0.5, 1.5, 6, dtype=F64)

    q0 = state.q.clone().requires_grad_(True)
    f = force.clone().requires_grad_(True)
    tgt = target.clone().requires_grad_(True)
    st = State(q0, q0 - (state.q - state.q_prev))
    for _ in range(2):
        st = step(scene, st, Action(force=f, target=tgt))
    gq, gf, gt = torch.autograd.grad((st.q * w).sum(), (q0, f, tgt))
    for b in range(B):
        q0b = state.q[b].clone().requires_grad_(True)
        fb = force[b].clone().requires_grad_(True)
        tb = target[b].clone().requires_grad_(True)
        sb = State(q0b, q0b - (state.q[b] - state.q_prev[b]))
        for _ in range(2):
            sb = step(scene, sb, Action(force=fb, target=tb))
        hq, hf, ht = torch.autograd.grad((sb.q * w).sum(), (q0b, fb, tb))
        assert float(hq.abs().max()) > 0 and float(hf.abs().max()) > 0
        torch.testing.assert_close(gq[b], hq, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(gf[b], hf, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(gt[b], ht, rtol=1e-10, atol=1e-12)


def test_no_pair_between_scenes(bodies):
    """Scene 1's ball sits where scene 0's ball is: no penetration is seen (no pair crosses scenes), each scene's
    result is its own, and one scene's outcome has exactly zero gradient with respect to the other's start."""
    _, _, _, ball = bodies
    scene = Scene((ball, ball), gravity=(0.0, 0.0, 0.0))
    q = torch.tensor([[_pose(0.0), _pose(0.5)], [_pose(0.02), _pose(0.7, 0.02)]], dtype=F64)
    v = torch.zeros_like(q)
    v[:, 0, 0] = 0.5
    q0 = q.clone().requires_grad_(True)
    st = scene.initial_state(q0, v)
    for _ in range(3):
        st = step(scene, st)
    alone = scene.initial_state(q[1], v[1])
    for _ in range(3):
        alone = step(scene, alone)
    torch.testing.assert_close(st.q[1].detach(), alone.q, rtol=0, atol=1e-12)
    (g,) = torch.autograd.grad(st.q[1, 1, 0], q0)
    assert float(g[1].abs().max()) > 0  # the long-range gradient within scene 1
    assert float(g[0].abs().max()) == 0.0  # nothing from scene 0


def test_rollout_returns_a_stacked_trajectory(bodies):
    cube, ground, _, _ = bodies
    scene = Scene((cube, ground))
    traj = rollout(scene, scene.initial_state(torch.tensor([_pose(0.0, 0.0, 0.12), _pose()], dtype=F64)), 3)
    assert len(traj) == 4 and traj.q.shape == (4, 2, 6)
    assert isinstance(traj[-1], State) and torch.equal(traj[-1].q, traj.q[3])
    assert [s.q.shape for s in traj] == [(2, 6)] * 4
    assert float(traj.q[-1, 0, 2]) < 0.12  # falling


# ------------------------------------------------------------------------------------------------ Newton
def _quadratic(A: torch.Tensor, b: torch.Tensor):
    def energy(q, scenes, order):
        Aq = torch.einsum("aij,aj->ai", A[scenes], q)
        value = 0.5 * (q * Aq).sum(1) - (b[scenes] * q).sum(1)
        value = torch.where((q.abs() < 10).all(1), value, torch.full_like(value, math.inf))
        n = len(scenes)
        z = q.new_zeros(n, 6, 6)
        return EnergyEval(value, Aq - b[scenes], A[scenes], z, value.abs(), None, q.new_ones(n) * 1e-3, None, None,
                          0, 0)  # fmt: skip

    return energy


def _run(energy, q, **kw):
    args = {"tol": 1e-10, "max_iter": 20, "max_move": 100.0, "free_move": 100.0}
    args.update(kw)
    return newton(
        energy, q, energy(q, torch.arange(len(q)), 2), move_ok=lambda a, b, s: torch.ones(len(a), dtype=torch.bool),
        displacement=lambda a, b, s: (b - a).abs().amax(1), **args,
    )  # fmt: skip


def test_newton_converges_per_scene_and_says_why_it_stops():
    A = torch.stack([torch.eye(6, dtype=F64) * s for s in (1.0, 4.0)])
    A[1, 0, 1] = A[1, 1, 0] = 1.0
    b = torch.ones(2, 6, dtype=F64)
    res = _run(_quadratic(A, b), torch.zeros(2, 6, dtype=F64))
    assert res.reason.tolist() == [Stop.CONVERGED, Stop.CONVERGED]
    torch.testing.assert_close(res.q, torch.linalg.solve(A, b[:, :, None])[:, :, 0], rtol=1e-12, atol=0)
    # a start outside the finite region, and an iteration cap of 1 from far away
    q = torch.zeros(2, 6, dtype=F64)
    q[0, 0] = 20.0
    res = _run(_quadratic(A, 1e3 * b), q, max_iter=1)
    assert res.reason[0] == Stop.INFEASIBLE_START
    assert res.reason[1] in (Stop.MAX_ITER, Stop.LINE_SEARCH_FAILED)


def test_a_loose_newton_tol_still_takes_the_converged_step(bodies):
    """A converged step longer than the solver takes unchecked (newton_tol loose against the contact margin) goes
    through the line search: a cube pushed by a force too weak to move it by newton_tol in one step moves as it
    does at the default tolerance, and a falling one falls (both stood still before)."""
    cube, ground = bodies[0], bodies[1]
    q = torch.tensor([[0.0, 0.0, 0.4, 0, 0, 0], [0.0] * 6], dtype=F64)
    force = torch.zeros(2, 3, dtype=F64)
    force[0, 0] = 0.5 * float(cube.mass)  # 0.5 m/s^2: 5e-5 m in the first step of dt = 0.01
    ends = {}
    for tol in (1e-9, 1e-4, 1e-3):
        scene = Scene([cube, ground], newton_tol=tol, gravity=(0.0, 0.0, 0.0))
        ends[tol] = rollout(scene, scene.initial_state(q), [Action(force=force)] * 10).q[-1, 0]
    assert float(ends[1e-9][0]) == pytest.approx(
        0.5 * 1e-4 * 55, rel=1e-3
    )  # backward Euler: a dt^2 sum(1..10)
    for tol in (1e-4, 1e-3):
        torch.testing.assert_close(ends[tol], ends[1e-9], rtol=0, atol=1e-8)
    z = [
        rollout(Scene([cube, ground], newton_tol=tol), State(q, q.clone()), 10).q[-1, 0, 2]
        for tol in (1e-9, 1e-3)
    ]
    assert float(z[0]) == pytest.approx(
        0.4 - G * 1e-4 * 55, abs=1e-6
    )  # (the ground's far field holds it by 4e-7 m)
    assert float(z[1]) == pytest.approx(
        float(z[0]), abs=1e-7
    )  # (the error of a step: about its last step squared)
    # the converged step taken whole ends the solve: at an iteration cap of 1 that is a converged step, not MAX_ITER
    scene = Scene([cube, ground], newton_tol=1e-4, gravity=(0.0, 0.0, 0.0), max_newton_iter=1)
    nxt, info = step(scene, State(q, q.clone()), Action(force=force), return_info=True)
    assert float(nxt.q[0, 0]) == pytest.approx(0.5 * 1e-4, rel=1e-3) and int(info.newton_iters) == 1


def test_island_energies_summed_by_index_equal_the_masked_sums():
    """Newton's per-island energies (``_restricted``): summed by index over the pairs at each island's bodies (large
    scenes, where (islands x pairs) masks grew like N^3) equal the masked sums over all pairs, to rounding."""
    g = torch.Generator().manual_seed(0)
    checked = 0
    for _ in range(200):
        M = int(torch.randint(2, 12, (1,), generator=g))
        N = M + int(torch.randint(0, 3, (1,), generator=g))  # with static bodies (moving index M)
        moving = torch.full((N,), M)
        moving[torch.randperm(N, generator=g)[:M]] = torch.arange(M)
        pairs = moving[torch.triu_indices(N, N, 1).T]
        pairs = pairs[(pairs < M).any(1) & (torch.rand(pairs.shape[0], generator=g) < 0.8)]
        ev = EnergyEval(
            *([None] * 9), 0, 0, *(torch.randn(3, n, generator=g, dtype=F64) for n in (M, len(pairs)))
        )
        A = int(torch.randint(1, 6, (1,), generator=g))
        rows = torch.randint(0, 3, (A,), generator=g)
        label = torch.randint(-1, 3, (A, M), generator=g)  # 0: the island, > 0: other islands, -1: frozen
        for others in (None, label > 0):
            dense = _restricted(ev, rows, label == 0, pairs, others)
            by_index = _restricted(ev, rows, label == 0, _incidence(pairs, M), others)
            for x, y in zip(dense, by_index, strict=True):
                if x is None:
                    assert y is None
                    continue
                torch.testing.assert_close(y, x, rtol=1e-14, atol=1e-14)
                checked += int((x != 0).sum())
    assert checked > 1000


def test_a_step_with_island_energies_summed_by_index_equals_the_masked_one(bodies, monkeypatch):
    from cfd_torch.sim import newton as newton_module

    scene, state, target, force = _scene_batch(bodies)
    traj = rollout(scene, state, [Action(target=target, force=force)] * 4)
    monkeypatch.setattr(newton_module, "_DENSE_ISLANDS", 0)  # every scene sums by index
    again = rollout(scene, state, [Action(target=target, force=force)] * 4)
    assert float((traj.q[-1] - traj.q[0]).abs().max()) > 1e-3  # they moved
    torch.testing.assert_close(again.q, traj.q, rtol=0, atol=1e-10)


def test_newton_line_search_failure_is_reported():
    """Every trial along the direction is infeasible (+inf): the line search fails, and says so."""
    A = torch.eye(6, dtype=F64)[None]
    quad = _quadratic(A, torch.full((1, 6), 5.0, dtype=F64))

    def walled(q, scenes, order):
        ev = quad(q, scenes, order)
        return ev._replace(value=torch.where((q == 0).all(1), ev.value, torch.full_like(ev.value, math.inf)))

    res = _run(walled, torch.zeros(1, 6, dtype=F64))
    assert res.reason.tolist() == [Stop.LINE_SEARCH_FAILED] and res.iters.tolist() == [1]


def test_newton_stops_at_non_finite_derivatives_and_says_so():
    """A Hessian that overflows to inf in one scene of two: that scene stops with NONFINITE (no factorisation of
    it is attempted), the other converges."""
    A = torch.eye(6, dtype=F64).repeat(2, 1, 1)
    quad = _quadratic(A, torch.ones(2, 6, dtype=F64))

    def overflowing(q, scenes, order):
        ev = quad(q, scenes, order)
        hess = ev.hess.clone()
        hess[scenes == 1, 0, 0] = math.inf
        return ev._replace(hess=hess)

    res = _run(overflowing, torch.zeros(2, 6, dtype=F64))
    assert res.reason.tolist() == [Stop.CONVERGED, Stop.NONFINITE] and res.iters.tolist()[1] == 1
    torch.testing.assert_close(res.q[0], torch.ones(6, dtype=F64), rtol=1e-12, atol=0)


def test_overflowing_settings_raise_clear_errors(bodies):
    """A time step whose 1/dt^2 overflows is refused by the Scene; a friction coefficient whose Hessian overflows
    raises a StepError naming the overflow (it was linalg.eigh's 'failed to converge') and the coefficient the step
    used, also when it came in ``Params`` (the message quoted the Scene's)."""
    cube, ground, _, _ = bodies
    with pytest.raises(ValueError, match="dt must be a finite number of at least 1e-12"):
        Scene((cube, ground), dt=1e-200)
    scene = Scene((cube, ground), friction=1e307)
    state = scene.initial_state(torch.tensor([_pose(0.0, 0.0, 0.125 + 2e-3), _pose()], dtype=F64))  # resting
    with pytest.raises(
        StepError, match="non-finite gradient or Hessian at Newton iteration 1.*friction coefficient 1e\\+307"
    ):
        step(scene, state)
    plain = Scene((cube, ground), friction=0.0)
    params = plain.params()._replace(friction=torch.tensor(1e307, dtype=F64))
    with pytest.raises(StepError, match="friction coefficient 1e\\+307"):
        step(plain, state, params=params)


def test_a_gap_of_exactly_one_margin_is_refused_as_penetrating(bodies):
    """A pusher face exactly one margin (1 mm) from the cube (gap - margin = 9e-19 m): the collision query and the
    plane solve measure it in different frames; the query errs toward infeasible, so the state is refused naming
    the pair (before: feasible to the query, +inf to the potential, and a StepError after 200 Newton iterations)."""
    from cfd_torch.sim.feasibility import feasible

    cube, ground, pusher, _ = bodies
    scene = Scene((cube, ground, pusher), friction=0.5)
    q = torch.tensor([_pose(0.0, 0.0, 0.1 + 1.4e-3), _pose(), _pose(-0.126, 0.0, 0.06)], dtype=F64)
    assert not bool(feasible(scene, q[None])[0])
    with pytest.raises(ValueError, match=r"state.q: bodies penetrate .* pairs \(0, 2\)"):
        step(scene, scene.initial_state(q))


def test_batch_errors_name_the_scene_and_misuse_is_named(bodies):
    """A kinematic push-out that fails in scene 1 of a batch says so; a state on the meta device, a tensor of
    actions for rollout and a gravity tensor that requires grad are refused naming the argument."""
    cube, ground, pusher, _ = bodies
    wall = _box((0.05, 0.6, 0.4), kind="static", max_edge=0.1)
    scene = Scene((cube, ground, pusher, wall), friction=0.3)
    h = 0.1 + 1.5e-3
    q = torch.tensor(
        [
            [_pose(0, 0, h), _pose(), _pose(-0.2, 0, 0.06), _pose(0.5, 0, 0.2)],
            [
                _pose(0, 0, h),
                _pose(),
                _pose(-0.2, 0, 0.06),
                _pose(0.128, 0, 0.2),
            ],  # the cube 3 mm from the wall
        ],
        dtype=F64,
    )
    target = q[:, 2:3].clone()
    target[1, 0, 0] += 0.09  # scene 1's pusher squeezes the cube into the wall
    with pytest.raises(StepError, match=r"the kinematic targets \(scene 1\): bodies penetrate"):
        step(scene, scene.initial_state(q), Action(target=target))
    plain = Scene((cube, ground))
    q2 = torch.tensor([_pose(0.0, 0.0, 0.2), _pose()], dtype=F64)
    with pytest.raises(ValueError, match="state.q is on the 'meta' device"):
        step(plain, State(q2.to("meta"), q2.to("meta")))
    with pytest.raises(TypeError, match=r"actions must be a sequence .* got a tensor of shape \(3, 2, 3\)"):
        rollout(plain, plain.initial_state(q2), torch.zeros(3, 2, 3, dtype=F64))
    with pytest.raises(TypeError, match="gravity must be numbers, not a tensor that requires grad"):
        Scene((cube, ground), gravity=torch.tensor([0.0, 0.0, -G], dtype=F64, requires_grad=True))


def test_step_error_names_the_reason(bodies):
    cube, ground, _, _ = bodies
    scene = Scene((cube, ground), max_newton_iter=1)
    state = scene.initial_state(torch.tensor([_pose(0.0, 0.0, 0.2), _pose()], dtype=F64))
    with pytest.raises(StepError, match="did not converge in 1 Newton iterations") as err:
        step(scene, state)
    # every setting that can cause it is named with its value (a tiny ccd_spacing caps each iteration's move)
    assert "newton_tol=" in str(err.value) and "ccd_spacing=0.01 " in str(err.value)
    assert "masses span" not in str(err.value)
    # a 1 g ball on a 10 kg box: the message names the mass ratio (a ratio of 1e5 stalled Newton in an audit)
    pebble = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.0062), density=1000.0)
    heavy = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=1250.0)
    scene = Scene((heavy, pebble, ground), max_newton_iter=1, mu=1e-12, refine_obstacles=None)
    q = torch.tensor([_pose(0.0, 0.0, 0.1015), _pose(0.0, 0.0, 0.2105), _pose()], dtype=F64)
    with pytest.raises(StepError, match=r"the moving bodies' masses span 1e\+04x: a light body pressed"):
        step(scene, scene.initial_state(q))
    with pytest.raises(TypeError, match="return_info must be a bool, got str"):
        step(scene, state, return_info="no")


def test_step_error_reports_the_whole_energys_gradient_when_bodies_were_frozen(monkeypatch):
    """A failed solve's message quoted the gradient of the last evaluation, which after a freeze covers only the
    bodies still iterating: a frozen 160 kg cube resting on the ground read as its weight (1.59e3), the ball that
    failed to converge as 454 (a session-54 audit). The message quotes the whole energy's gradient at the last
    iterate."""
    import re

    import cfd_torch.sim.solve as solve_module
    from cfd_torch.sim.energy import incremental_potential

    cube = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=20000.0, max_edge=0.1)
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1))
    m = trimesh.creation.box((3.0, 1.0, 0.05))
    m.apply_translation([0, 0, -0.025])
    ground = rigid_body(m, kind="static", max_edge=0.2)
    scene = Scene((cube, ball, ground), friction=0.5, mu=1e-7)
    q = torch.tensor([_pose(0, 0, 0.1015), [1.0, 0, 0.25, 0.3, 0.2, 0], _pose()], dtype=F64)
    v = torch.tensor([[0.0] * 6, [0.5, 0, -4.0, 6.0, 3.0, 0], [0.0] * 6], dtype=F64)
    state = scene.initial_state(q, v)
    for _ in range(3):  # the cube settles: it freezes early in the failing step
        state = step(scene, state)
    seen = {}
    newton_fn = solve_module._newton

    def spy(prob, *args):
        res, work = newton_fn(prob, *args)
        seen["prob"], seen["res"] = prob, res
        return res, work

    monkeypatch.setattr(solve_module, "_newton", spy)
    with pytest.raises(StepError, match="did not converge in 5 Newton iterations") as err:
        step(scene.replace(max_newton_iter=5), state)
    reported = float(re.search(r"max \|dL/dq\| = ([0-9.e+-]+),", str(err.value)).group(1))
    res = seen["res"]
    whole = incremental_potential(seen["prob"], res.q, 1).grad[0]
    assert float(res.at.grad[0, :6].abs().max()) > 1e3  # the frozen cube's restricted gradient: its weight
    assert float(whole[:6].abs().max()) < 1e-2  # the cube at rest on the ground
    assert reported == pytest.approx(float(whole.abs().max()), rel=1e-3)


def test_substeps_retry_a_failed_step(bodies):
    """A fast drop that the full step cannot solve in its iteration cap goes through as sub-steps, and lands
    where the same scene with a 4 times smaller dt lands."""
    cube, ground, _, _ = bodies
    q = torch.tensor([_pose(0.0, 0.0, 0.103), _pose()], dtype=F64)
    v = torch.zeros_like(q)
    v[0, 2] = -0.1
    hard = Scene((cube, ground), dt=0.04, max_newton_iter=8)  # 14 iterations needed; 8 and 4 at dt = 0.02
    state = hard.initial_state(q, v)
    with pytest.raises(StepError):
        step(hard, state)
    with pytest.raises(StepError, match=r"\(the step failed whole and as 2, 4 sub-steps\)"):
        step(hard.replace(substeps=4, max_newton_iter=1), state)
    retry = hard.replace(substeps=4)
    nxt, info = step(retry, state, return_info=True)
    k = int(info.substeps)
    assert k == 2
    fine = Scene((cube, ground), dt=0.04 / k)
    st = fine.initial_state(q, v)
    for _ in range(k):
        st = step(fine, st)
    torch.testing.assert_close(nxt.q, st.q, rtol=0, atol=1e-12)
    torch.testing.assert_close(nxt.velocity(0.04), st.velocity(fine.dt), rtol=0, atol=1e-9)


def test_batch_with_a_failing_scene_and_per_scene_params_equals_each_alone(bodies):
    """A batch in which one scene needs sub-steps and the others do not, with per-scene friction coefficients
    (0 in the failing one) and shared masses: each scene comes out as it does alone (sub-steps, friction contacts,
    poses)."""
    cube, ground, _, _ = bodies
    scene = Scene((cube, ground), dt=0.04, max_newton_iter=8, substeps=4)
    q = torch.tensor(
        [
            [_pose(0.0, 0.0, 0.103), _pose()],
            [_pose(0.0, 0.0, 0.1014), _pose()],
            [_pose(0.1, 0.0, 0.1014), _pose()],
        ],
        dtype=F64,
    )
    v = torch.zeros_like(q)
    v[0, 0, 2] = -0.1  # the drop that needs sub-steps
    p = scene.params()
    params = p._replace(friction=torch.tensor([0.0, 0.3, 0.5], dtype=F64))
    state = scene.initial_state(q, v)
    nxt, info = step(scene, state, params=params, return_info=True)
    for b in range(3):
        alone, ai = step(
            scene, State(state.q[b], state.q_prev[b]), params=p._replace(friction=params.friction[b]),
            return_info=True,
        )  # fmt: skip
        assert int(info.substeps[b]) == int(ai.substeps)
        assert int(info.friction_contacts[b]) == int(ai.friction_contacts)
        torch.testing.assert_close(nxt.q[b], alone.q, rtol=0, atol=1e-12)
        torch.testing.assert_close(nxt.q_prev[b], alone.q_prev, rtol=0, atol=1e-12)
    assert info.substeps.tolist() == [2, 1, 1] and info.friction_contacts.tolist()[0] == 0
    with pytest.raises(ValueError, match=r"params.mass must have shape"):
        step(scene, state, params=p._replace(mass=p.mass.expand(2, -1)))


# ------------------------------------------------------------------------------------------------ contact models
class _CountingModel:
    """A contact model of its own class (delegating to the paper's): the stepper needs nothing else."""

    def __init__(self, inner):
        self.inner = inner
        self.calls = 0

    def evaluate(self, poses, pairs, order):
        self.calls += 1
        return self.inner.evaluate(poses, pairs, order)

    def infeasible(self, poses, pairs, scale=None):
        return self.inner.infeasible(poses, pairs, scale)

    def lagged(self, poses, pairs, active, create_graph=False):
        return self.inner.lagged(poses, pairs, active, create_graph)


def test_a_contact_model_is_a_class_not_a_stepper_change(bodies):
    cube, ground, _, _ = bodies
    ref = Scene((cube, ground), friction=0.5)
    # the contact model of the bodies as simulated (the ground refined to the cube's scale)
    model = _CountingModel(CfdContact([b.bsh for b in ref.bodies], ContactConfig()))
    assert isinstance(model, ContactModel)
    own = Scene((cube, ground), friction=0.5, contact_model=model)
    q = torch.tensor([_pose(0.0, 0.0, 0.108, 0.05), _pose()], dtype=F64)
    a, b = ref.initial_state(q), own.initial_state(q)
    for _ in range(3):
        a, b = step(ref, a), step(own, b)
    assert model.calls > 0
    # the same solve, except that CfdContact warm-starts its plane solves (observed 8.8e-15 m apart)
    torch.testing.assert_close(a.q, b.q, rtol=0, atol=1e-12)
    # and its backward (friction's lagged contacts with a graph through the model's own lagged): the same gradient
    grads = []
    for scene in (ref, own):
        q0 = q.clone().requires_grad_(True)
        s = scene.initial_state(q0)
        for _ in range(2):
            s = step(scene, s)
        (g,) = torch.autograd.grad(s.q[0, :3].sum(), q0)
        grads.append(g)
    assert float(grads[0].abs().max()) > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-9, atol=1e-12)


def test_replace_rebuilds_from_the_bodies_as_given_and_keeps_the_other_settings(bodies):
    """replace() builds from the meshes as given (a 12-face floor refined for the cfd potential is 12 faces again
    under IPC, and the contact forces equal a direct build's), and friction= a number changes only the
    coefficient (before: the refined meshes were passed on, and eps_v and active reset to their defaults)."""
    from cfd_torch import pair_forces

    cube = bodies[0]
    mesh = trimesh.creation.box(extents=(1.4, 0.6, 0.05))
    mesh.apply_translation([0.0, 0.0, -0.025])
    ground = rigid_body(mesh, kind="static")  # 12 faces, as given
    s = Scene((cube, ground), friction=FrictionConfig(0.5, eps_v=1e-6, active=1e-3))
    assert s.bodies[1].bsh.num_faces > 12  # refined for the cfd potential
    ipc = s.replace(potential="ipc")
    direct = Scene((cube, ground), potential="ipc", friction=FrictionConfig(0.5, eps_v=1e-6, active=1e-3))
    assert ipc.bodies[1].bsh.num_faces == direct.bodies[1].bsh.num_faces == 12
    q = torch.tensor([[0.0, 0.0, 0.1 + 3e-3, 0.0, 0.0, 0.0], [0.0] * 6], dtype=F64)
    f = pair_forces(ipc, q)
    assert float(f.abs().max()) > 0.0
    torch.testing.assert_close(f, pair_forces(direct, q), rtol=0.0, atol=0.0)
    assert s.replace(friction=0.3).friction == FrictionConfig(0.3, eps_v=1e-6, active=1e-3)
    assert s.replace(dt=0.005).friction == s.friction
    # through a chain of replace() calls too: a change that keeps the refinement passed the refined meshes on as
    # the ones given, and the next change refined them again (1672 faces) or kept them (IPC on the cfd mesh)
    chained = s.replace(dt=0.005).replace(potential="ipc")
    assert chained.bodies[1].bsh.num_faces == 12 and chained.dt == 0.005
    assert s.replace(friction=0.3).replace(refine_obstacles=None).bodies[1].bsh.num_faces == 12


def test_configs_hold_the_defaults_and_check_their_fields(bodies):
    cube, ground, _, _ = bodies
    s = Scene((cube, ground), mu=1e-9, friction=0.3, newton_tol=1e-11)
    assert s.contact == ContactConfig(stiffness=1e-9)
    assert s.friction == FrictionConfig(coefficient=0.3)
    assert s.solver == SolverConfig(newton_tol=1e-11)
    assert Scene((cube, ground), friction=FrictionConfig(0.3, active=0.0)).friction.active == 0.0
    assert (s.mu, s.margin, s.newton_tol) == (1e-9, s.contact.margin, 1e-11)  # shorthands read the configs
    for bad, match in (
        ({"mu": -1.0}, "ContactConfig.stiffness"),
        ({"split": "all"}, "ContactConfig.split"),
        ({"friction": -0.1}, "FrictionConfig.coefficient"),
        ({"friction_active": 1.0}, "FrictionConfig.active"),
        ({"max_newton_iter": 0}, "SolverConfig.max_newton_iter"),
        ({"substeps": 0}, "SolverConfig.substeps"),
    ):
        with pytest.raises(ValueError, match=match):
            Scene((cube, ground), **bad)
    with pytest.raises(TypeError, match="unexpected keyword argument 'stiffness'"):
        Scene((cube, ground), stiffness=1.0)


def test_scene_pickles_without_its_device_caches_and_bodies_and_configs_load_weights_only(bodies):
    size = len(pickle.dumps(Scene(bodies, friction=0.4)))  # as _scene_batch builds it, before any use
    scene, state, target, force = _scene_batch(bodies)
    out = step(scene, state, Action(target=target, force=force))
    assert len(pickle.dumps(scene)) == size  # the forest the step built stays out of the pickle
    again = step(pickle.loads(pickle.dumps(scene)), state, Action(target=target, force=force))
    assert torch.equal(again.q, out.q) and not torch.equal(out.q, state.q)
    for obj in (bodies[0], bodies[0].bsh, scene.contact, scene.friction, scene.solver):
        buf = io.BytesIO()
        torch.save(obj, buf)
        buf.seek(0)
        loaded = torch.load(buf)  # weights_only=True, torch's default
        assert type(loaded) is type(obj)
        if hasattr(obj, "radius"):
            assert torch.equal(loaded.radius, obj.radius)
        elif hasattr(obj, "bsh"):
            assert torch.equal(loaded.bsh.centre, obj.bsh.centre) and loaded.mass == obj.mass
        else:
            assert loaded == obj


# ------------------------------------------------------------------------------------------------ read-outs
def test_pair_forces_and_step_info_at_rest(bodies):
    cube, ground, _, _ = bodies
    scene = Scene((cube, ground), friction=0.5)
    state = scene.initial_state(torch.tensor([_pose(0.0, 0.0, 0.1 + 1.2e-3), _pose()], dtype=F64))
    for _ in range(30):
        state, info = step(scene, state, return_info=True)
    assert isinstance(info, StepInfo) and info.contact_evals >= 1 and info.leaf_pairs > 0 and info.seconds > 0
    F = pair_forces(scene, state.q)
    assert F.shape == (2, 2, 6)
    weight = cube.mass * G
    assert abs(float(F[1, 0, 2]) - weight) < 1e-3 * weight  # the ground carries the cube
    torch.testing.assert_close(F[0, 1, :3], -F[1, 0, :3], rtol=1e-12, atol=1e-12)  # action = reaction
    torch.testing.assert_close(info.contact_force[0], F[1, 0], rtol=1e-9, atol=1e-9)  # same read-out
    # within the margin, or sunk into the ground, the potential is +inf and there is no force to report
    for z in (0.1 + 0.5e-3, 0.05):
        with pytest.raises(ValueError, match=r"q: bodies penetrate .* pairs \(0, 1\)"):
            pair_forces(scene, torch.tensor([_pose(0.0, 0.0, z), _pose()], dtype=F64))
    # poses that require grad: the same forces, and a loss through them refuses to backpropagate (a constant
    # dropped their part of the gradient silently: 1 against -3.4e5 by central differences, a gradient audit)
    q = state.q.clone().requires_grad_(True)
    Fg = pair_forces(scene, q)
    torch.testing.assert_close(Fg.detach(), F, rtol=0.0, atol=0.0)
    with pytest.raises(RuntimeError, match="pair_forces carries no gradient"):
        (Fg[1, 0, 2] + q[0, 2]).backward()


def test_transforms_and_forward_mode_are_refused_by_name_and_batched_gradients_too(bodies):
    """step and pair_forces under torch.func, forward-mode AD (forward_ad) and autograd's batched gradients
    (jacobian(vectorize=True)): a NotImplementedError naming the function and the way out, not torch's internal
    errors; initial_state's checks run under vmap."""
    import torch.autograd.forward_ad as fwad

    cube, ground, _, _ = bodies
    scene = Scene((cube, ground), friction=0.5)
    q = torch.tensor([_pose(0.0, 0.0, 0.1 + 2e-3), _pose()], dtype=F64)
    state = scene.initial_state(q)
    f = lambda x: step(scene, State(x, state.q_prev)).q  # noqa: E731
    with fwad.dual_level():
        with pytest.raises(NotImplementedError, match="cfd_torch.step: .* forward-mode AD do not pass"):
            f(fwad.make_dual(q, torch.ones_like(q)))
    with pytest.raises(NotImplementedError, match=r"cfd_torch.step: batched gradients .* vectorize=False"):
        torch.autograd.functional.jacobian(f, q, vectorize=True)
    J = torch.autograd.functional.jacobian(f, q)  # one backward per output: works
    assert J.shape == (2, 6, 2, 6) and float(J[0, 2, 0, 2]) > 0.5
    for transform in (torch.func.grad, torch.func.jacrev):
        with pytest.raises(NotImplementedError, match="cfd_torch.pair_forces: torch.func transforms"):
            transform(lambda x: pair_forces(scene, x)[1, 0, 2])(q)
    batch = torch.stack([q, q + torch.tensor([0.0, 0.0, 0.01, 0, 0, 0], dtype=F64)])
    vm = torch.func.vmap(lambda x: scene.initial_state(x).q_prev)(batch)
    torch.testing.assert_close(vm, scene.initial_state(batch).q_prev)


def test_torch_backend_step_matches_numba(bodies):
    """The GPU route (batched tensor traversal and pair solves) on the CPU: a step with friction and its
    gradient agree with the numba kernels."""
    cube, ground, _, _ = bodies
    q = torch.tensor([_pose(0.02, 0.0, 0.107, 0.03, -0.02), _pose()], dtype=F64)
    v = torch.zeros_like(q)
    v[0, 0] = 0.2
    out = {}
    for backend in ("auto", "torch"):
        scene = Scene((cube, ground), friction=0.5, backend=backend)
        q0 = q.clone().requires_grad_(True)
        st = scene.initial_state(q0, v)
        for _ in range(2):
            st = step(scene, st)
        (g,) = torch.autograd.grad(st.q[0, 0], q0)
        out[backend] = (st.q.detach(), g)
    assert float(out["torch"][1].abs().max()) > 0
    torch.testing.assert_close(out["torch"][0], out["auto"][0], rtol=0, atol=1e-10)
    torch.testing.assert_close(out["torch"][1], out["auto"][1], rtol=1e-6, atol=1e-8)


def test_pair_eps_sets_one_body_pairs_blend_width_and_leaves_the_others(bodies):
    """``Scene(pair_eps=...)``: the named pair's potential is the one a scene-wide eps gives, every other pair's is
    the default's, on both backends, for values, gradients and the feasibility query."""
    cube, ground, _, ball = bodies
    q = torch.tensor([[_pose(0.0, 0.0, 0.1015), _pose(), _pose(0.45, 0.1, 0.15)]], dtype=F64)
    pairs = torch.tensor([[0, 0, 1], [0, 0, 2], [0, 1, 2]])
    for backend in ("auto", "torch"):
        plain = Scene((cube, ground, ball), backend=backend).contact_model.evaluate(q, pairs, 2)
        wide = Scene((cube, ground, ball), backend=backend, eps=1.0).contact_model.evaluate(q, pairs, 2)
        mixed_scene = Scene((cube, ground, ball), backend=backend, pair_eps={(2, 0): 1.0})
        mixed = mixed_scene.contact_model.evaluate(q, pairs, 2)
        # the ball is 0.46 m from the cube: inside the wide band of their root pair, beyond the narrow one
        assert float((wide.grad[1] - plain.grad[1]).abs().max()) > 10 * float(plain.grad[1].abs().max())
        for k, ref in ((0, plain), (1, wide), (2, plain)):
            torch.testing.assert_close(mixed.value[k], ref.value[k], rtol=1e-12, atol=0)
            torch.testing.assert_close(mixed.grad[k], ref.grad[k], rtol=1e-10, atol=1e-18)
            torch.testing.assert_close(mixed.hess[k], ref.hess[k], rtol=1e-9, atol=1e-15)
        assert not bool(mixed_scene.contact_model.infeasible(q, pairs).any())
    sunk = q.clone()
    sunk[0, 2, 0] = 0.2  # the ball into the cube
    assert mixed_scene.contact_model.infeasible(sunk, pairs).tolist() == [False, True, False]
    for bad, match in (({(0, 3): 1.0}, "pair of two body indices"), ({(0, 2): 0.0}, "positive number")):
        with pytest.raises(ValueError, match=match):
            Scene((cube, ground, ball), pair_eps=bad)


def test_pair_mu_scales_one_body_pairs_potential_and_friction_and_leaves_the_others(bodies):
    """``Scene(pair_mu=...)``: the named pair's value, gradient, Hessian and lagged normal forces are the default
    ones times its stiffness ratio (the potential is linear in mu), every other pair's are unchanged (bit for bit),
    on both backends; a pair_mu equal to the scene's stiffness changes nothing."""
    cube, ground, _, ball = bodies
    q = torch.tensor([[_pose(0.0, 0.0, 0.1015), _pose(), _pose(0.45, 0.1, 0.15)]], dtype=F64)
    pairs = torch.tensor([[0, 0, 1], [0, 0, 2], [0, 1, 2]])
    mu = Scene((cube, ground, ball)).contact.stiffness
    for backend in ("auto", "torch"):
        plain_model = Scene((cube, ground, ball), backend=backend).contact_model
        plain = plain_model.evaluate(q, pairs, 2)
        mixed_model = Scene((cube, ground, ball), backend=backend, pair_mu={(1, 0): 7 * mu}).contact_model
        mixed = mixed_model.evaluate(q, pairs, 2)
        assert float(plain.grad[0].abs().max()) > 0 and float(plain.grad[2].abs().max()) > 0
        for k, ratio in ((0, 7.0), (1, 1.0), (2, 1.0)):
            torch.testing.assert_close(mixed.value[k], ratio * plain.value[k], rtol=1e-14, atol=0)
            torch.testing.assert_close(mixed.grad[k], ratio * plain.grad[k], rtol=1e-14, atol=0)
            torch.testing.assert_close(mixed.hess[k], ratio * plain.hess[k], rtol=1e-14, atol=0)
        lag0, lag = plain_model.lagged(q, pairs, 0.0), mixed_model.lagged(q, pairs, 0.0)
        assert torch.equal(lag.pair, lag0.pair) and bool((lag0.pair == 0).any())
        expect = torch.where(lag0.pair == 0, 7.0, 1.0).to(F64) * lag0.normal_force
        torch.testing.assert_close(lag.normal_force, expect, rtol=1e-14, atol=0)
        same = Scene((cube, ground, ball), backend=backend, pair_mu={(0, 1): mu}).contact_model.evaluate(
            q, pairs, 2
        )
        assert torch.equal(same.value, plain.value) and torch.equal(same.hess, plain.hess)


def test_pair_mu_rests_a_small_body_at_its_own_gap_beside_a_large_one():
    """A mixed scene: a 2 cm, 8 g cube hovers millimetres up at the default stiffness (a RestGapWarning) beside a
    20 cm box that rests at the default's gap; with the small cube's floor pair at the stiffness for a 2 mm gap
    (``stiffness_for_rest_gap``) the Scene does not warn, the small cube settles at that gap and the box where it
    did."""
    from cfd_torch import RestGapWarning, stiffness_for_rest_gap

    small = rigid_body(trimesh.creation.box((0.02, 0.02, 0.02)), density=1000.0)
    big = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), density=500.0)
    floor = rigid_body(trimesh.creation.box((1.0, 1.0, 0.1)), kind="static")
    q = torch.tensor([_pose(0, 0, -0.05), _pose(0.3, 0, 0.0125), _pose(-0.2, 0, 0.1025)], dtype=F64)
    with pytest.warns(RestGapWarning, match=r"body 1 \(0.008 kg.*pair_mu=\{\(body, floor\): mu\}"):
        Scene((floor, small, big), friction=0.5)
    pusher = rigid_body(trimesh.creation.box((0.05, 0.05, 0.3)), kind="kinematic")
    with pytest.warns(RestGapWarning, match=r"body 1 \(0.008 kg"):  # judged on its floor, not on the pusher
        Scene((floor, small, big, pusher), friction=0.5, pair_mu={(1, 3): 1e-10})
    mu_small = stiffness_for_rest_gap(small, 2e-3, floor=floor)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RestGapWarning)
        scene = Scene((floor, small, big), friction=0.5, pair_mu={(1, 0): mu_small})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RestGapWarning)
        plain = Scene((floor, small, big), friction=0.5)
    z = rollout(scene, scene.initial_state(q), 80).q[-1, :, 2]
    z_plain = rollout(plain, plain.initial_state(q), 80).q[-1, :, 2]
    assert abs(float(z[1]) - 0.01 - 2e-3) < 0.05 * 2e-3  # the small cube at its own gap
    assert float(z_plain[1]) - 0.01 > 3 * 2e-3  # (where the default left it)
    assert abs(float(z[2] - z_plain[2])) < 1e-6  # the box as at the default (the far pair's pull aside)


# ================================================================================================ coarse obstacles
def _ball_on_box_scene(**kw):
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1))
    box = rigid_body(trimesh.creation.box(extents=(2.0, 2.0, 0.2)), kind="static")  # 12 triangles, 2 m edges
    return ball, box, Scene((ball, box, ball), **kw)


def test_scene_refines_coarse_obstacles_to_their_partners_scale():
    ball, box, scene = _ball_on_box_scene()
    longest = lambda b: float((b.bsh.triangles[:, [1, 2, 0]] - b.bsh.triangles).norm(dim=-1).max())  # noqa: E731
    assert scene.bodies[0] is ball and scene.bodies[2] is ball  # dynamic bodies untouched, shared ones shared
    refined = scene.bodies[1]
    assert refined.kind == "static" and refined.bsh.num_faces > box.bsh.num_faces
    assert longest(refined) <= 2.0 * longest(ball) * (1 + 1e-12)
    # the same surface: every refined vertex lies on the box's faces
    v = refined.bsh.vertices
    assert float((v.abs() - torch.tensor([1.0, 1.0, 0.1], dtype=F64)).abs().amin(1).max()) < 1e-12
    assert Scene((ball, box), refine_obstacles=None).bodies[1] is box  # off: meshes as given
    again = scene.replace(dt=0.005)  # already fine enough: not refined twice
    assert again.bodies[1].bsh.num_faces == refined.bsh.num_faces


def test_each_obstacle_is_refined_to_its_own_finest_partner():
    """Two plain boxes and two balls of different sizes: each box takes the scale of the finest dynamic body it can
    touch; a pair left out by ``exclude`` is no partner, and a box whose only partner is about as coarse as itself
    stays as given."""
    small = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.05))
    big = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.4))
    box = rigid_body(trimesh.creation.box(extents=(2.0, 2.0, 0.2)), kind="static")
    longest = lambda b: float((b.bsh.triangles[:, [1, 2, 0]] - b.bsh.triangles).norm(dim=-1).max())  # noqa: E731
    scene = Scene((small, box, big, box), exclude=[(0, 3)])
    a, b = scene.bodies[1], scene.bodies[3]
    assert longest(a) <= 2.0 * longest(small) * (1 + 1e-12) < longest(b)  # box 1: the small ball's scale
    assert 2.0 * longest(small) < longest(b) <= 2.0 * longest(big) * (1 + 1e-12)  # box 3: the big ball's only
    huge = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=3.0))
    assert Scene((huge, box)).bodies[1] is box  # its partner's edges are longer than the box's: not refined


def test_refined_obstacle_costs_fewer_leaf_pairs_and_holds_the_ball_the_same():
    """A ball resting on a plain 12-triangle box: the automatic refinement cuts the exact leaf pairs per evaluation
    several-fold, and the ball comes to rest at the same height (the surface is the same) to within the rest gap's
    sensitivity to the triangulation."""
    heights, leaves = {}, {}
    for ref in (None, 2.0):
        ball, box, _ = _ball_on_box_scene()
        scene = Scene((ball, box), refine_obstacles=ref)
        # the lowest vertex 2 mm above the box's top face (z = 0)
        z0 = 2e-3 - float(ball.bsh.vertices[:, 2].min())
        state = scene.initial_state(torch.tensor([_pose(0.03, 0.02, z0), _pose(0, 0, -0.1)], dtype=F64))
        for _ in range(25):
            state, info = step(scene, state, return_info=True)
        heights[ref] = float(state.q[0, 2])
        leaves[ref] = info.leaf_pairs / info.contact_evals
    assert leaves[2.0] < 0.5 * leaves[None]  # observed 191 against 960
    assert abs(heights[2.0] - heights[None]) < 5e-5  # observed 1.7e-5 m (rest gaps about 1e-3 m)


def test_refinement_beyond_the_face_cap_warns_and_coarsens(monkeypatch):
    import cfd_torch.sim.bodies as bodies_mod

    monkeypatch.setattr(bodies_mod, "MAX_REFINED_FACES", 100)
    ball, box, _ = _ball_on_box_scene(refine_obstacles=None)
    with pytest.warns(UserWarning, match="more than 100 triangles"):
        scene = Scene((ball, box))
    assert 12 < scene.bodies[1].bsh.num_faces <= 100


# ======================================================================================== islands, frozen bodies
def test_bodies_far_apart_step_as_if_alone(bodies):
    """A cube resting at one end of the ground and a ball dropped with a spin at the other: the Newton solve takes
    them as two islands (own line searches) and freezes the one that converged first, yet every step ends where
    each body's own scene ends it, up to the far field between them (about 1e-12 m here) and newton_tol."""
    cube, ground, _, ball = bodies
    both = Scene((cube, ground, ball), friction=0.3)
    q = torch.tensor([_pose(-0.5, 0.0, 0.1 + 1.2e-3), _pose(), _pose(0.5, 0.0, 0.1 + 0.02, 0.3)], dtype=F64)
    v = torch.zeros(3, 6, dtype=F64)
    v[2, 3:] = torch.tensor([0.0, 5.0, 2.0], dtype=F64)  # the ball spins: it lands rocking on a vertex
    s_both = both.initial_state(q, v)
    alone = [Scene((cube, ground), friction=0.3), Scene((ground, ball), friction=0.3)]
    s_alone = [alone[0].initial_state(q[:2], v[:2]), alone[1].initial_state(q[1:], v[1:])]
    for _ in range(12):
        s_both = step(both, s_both)
        s_alone[0] = step(alone[0], s_alone[0])
        s_alone[1] = step(alone[1], s_alone[1])
        torch.testing.assert_close(s_both.q[0], s_alone[0].q[0], rtol=0, atol=1e-8)
        torch.testing.assert_close(s_both.q[2], s_alone[1].q[1], rtol=0, atol=1e-8)
    assert float((s_both.q[2, 2] - q[2, 2]).abs()) > 1e-3  # the ball fell and landed: the test saw contact


def test_islands_moving_through_each_other_are_caught():
    """Two plates 0.3 m apart flying at each other at 18 m/s: far apart at the start they are two islands, each of
    whose paths is clear alone; their moves together cross, so the scene searches whole and they collide instead
    of passing through each other (found by review: the islands' joint path was not checked)."""
    plate = rigid_body(trimesh.creation.box(extents=(0.01, 0.2, 0.2)), max_edge=0.1)
    scene = Scene((plate, plate), gravity=(0.0, 0.0, 0.0))
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 0] = 0.31
    v = torch.zeros(2, 6, dtype=F64)
    v[0, 0], v[1, 0] = 18.0, -18.0
    nxt = step(scene, scene.initial_state(q, v))
    assert float(nxt.q[1, 0] - nxt.q[0, 0]) > 0.01  # still in order, at least a plate thickness apart


def test_a_body_pulled_only_by_the_far_field_of_another_island_steps_at_once():
    """Two balls 0.5 m apart in zero gravity, one pushed: the other moves only by the pushed ball's far field, a
    force its island's own energy (inertia) cannot show. Its line search must accept the full Newton step, not
    halve it 20 times before handing the scene to a whole search (it did: 23 evaluations for this step)."""
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.03), density=1000.0)
    scene = Scene((ball, ball), gravity=(0.0, 0.0, 0.0))
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 0] = 0.5
    force = torch.zeros(2, 3, dtype=F64)
    force[0, 1] = 1.0
    nxt, info = step(scene, scene.initial_state(q), Action(force=force), return_info=True)
    assert info.contact_evals <= 4
    plain, _ = step(scene.replace(fast=False), scene.initial_state(q), Action(force=force), return_info=True)
    moved = nxt.q[1] - q[1]
    assert float(moved.abs().max()) > 0  # the far field moved the free ball
    torch.testing.assert_close(nxt.q, plain.q, rtol=0, atol=1e-12)


def test_islands_take_the_full_step_the_whole_scene_accepts():
    """A 15-ball rack at rest (4.5 mm gaps) and a cue ball 0.5 m away, all separate islands: the rack balls move by
    their neighbours' far field, the apex toward the cue ball, whose own pull (away from the rack) is then cancelled
    in its island's test by the apex's approach. The whole Newton step passes the scene's own test, so every island
    takes it: the solve converges in two iterations and two evaluations (it halved the cue ball's step, then needed
    a third iteration: five evaluations), where the reference path (one search for the whole scene) ends."""
    from cfd_torch.envs.billiards import rack_positions

    r = 0.0286
    ball = rigid_body(
        trimesh.creation.icosphere(subdivisions=2, radius=r), density=0.17 / (4 / 3 * math.pi * r**3)
    )
    scene = Scene(
        [ball] * 16, gravity=(0.0, 0.0, 0.0), planar=True, pair_eps={(15, k): 0.01 for k in range(15)}
    )
    q = torch.zeros(16, 6, dtype=F64)
    q[:15, :2] = rack_positions(r).to(F64)
    q[15, :2] = torch.tensor([0.03, -0.5], dtype=F64)
    state = scene.initial_state(q)
    nxt, info = step(scene, state, return_info=True)
    plain = step(scene.replace(fast=False), state)
    moved = (nxt.q - q).abs()
    assert float(moved[0].max()) > 1e-8 and float(moved[15].max()) > 1e-10  # the apex and the cue ball moved
    assert int(info.newton_iters) == 2 and info.contact_evals == 2
    torch.testing.assert_close(nxt.q, plain.q, rtol=0, atol=1e-12)


def test_head_on_impact_of_small_balls_meeting_vertex_to_vertex():
    """Two 80-face balls of radius 2.86 cm, vertices aligned, at 6 m/s head on in zero gravity. The blend band of
    such small nodes (eps d1 = 0.57 mm) was narrower than the margin (1 mm): the potential stayed finite and flat
    inside the margin up to a jump to +inf, and the impact's Newton solve stalled against that wall (StepError
    after 200 iterations). The band is now at least two margins wide: the step converges, nothing penetrates and
    momentum is conserved."""
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.0286), density=1740.0)
    scene = Scene((ball, ball), gravity=(0.0, 0.0, 0.0))
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 1] = 0.0572 + 0.03  # 3 cm apart along y, where both meshes have a vertex
    v = torch.zeros(2, 6, dtype=F64)
    v[0, 1] = 6.0
    state = scene.initial_state(q, v)
    for _ in range(3):
        state, info = step(scene, state, return_info=True)
    vel = state.velocity(scene.dt)
    assert float(vel[1, 1]) > 1.0  # the struck ball moves
    torch.testing.assert_close(vel[:, :3].sum(0), v[:, :3].sum(0), rtol=0, atol=1e-9)
    # the balls glance off each other's vertices (they leave the line); centres stay about a diameter apart
    assert float((state.q[1, :3] - state.q[0, :3]).norm()) > 0.9 * 0.0572


def test_friction_summed_per_pair_in_numba_equals_the_per_contact_terms():
    """The CPU kernel that sums lagged friction per body pair (no autograd wanted) equals the per-contact closed form
    summed with index_add, at every order, with the majorizer gap, in the slipping and the static regime; for
    contacts whose pair has one pair of pose rows (body pairs: pairs 0-3 here) and ones whose rows vary."""
    from cfd_torch.contact.model import LaggedContacts
    from cfd_torch.rotation import rotation_matrix
    from cfd_torch.sim.friction import friction_by_pair, friction_terms

    g = torch.Generator().manual_seed(3)
    C, M, e = 400, 5, 1e-4
    n = torch.nn.functional.normalize(torch.randn(C, 3, generator=g, dtype=F64), dim=1)
    tangent = torch.eye(3, dtype=F64) - n[:, :, None] * n[:, None, :]
    rows = torch.randint(0, M, (C, 2), generator=g)
    rows[:, 1] = (rows[:, 0] + 1 + torch.randint(0, M - 1, (C,), generator=g)) % M  # two different bodies
    pair = torch.randint(0, 7, (C,), generator=g)
    rows = torch.where((pair < 4)[:, None], rows[torch.arange(4)][pair.clamp(max=3)], rows)
    poses = torch.cat(
        [torch.randn(M, 3, generator=g, dtype=F64), 0.8 * torch.randn(M, 3, generator=g, dtype=F64)], 1
    )
    X = 0.1 * torch.randn(C, 2, 3, generator=g, dtype=F64)
    R = rotation_matrix(poses[:, 3:])
    x = torch.einsum("csij,csj->csi", R[rows], X) + poses[rows, :3]
    # start-of-step points: slips from 0.01 e to 100 e, so both regimes of f0 occur
    slip = torch.logspace(-2, 2, C, dtype=F64)[torch.randperm(C, generator=g)] * e
    x_t = x.clone()
    x_t[:, 0] -= slip[:, None] * torch.randn(C, 3, generator=g, dtype=F64)
    data = LaggedContacts(pair, X, x_t, tangent, torch.rand(C, generator=g, dtype=F64) + 0.1)
    mu = torch.rand(C, generator=g, dtype=F64)
    for order in (0, 1, 2):
        pair, *fast = friction_by_pair(data, poses, rows, mu, e, order, majorizer_gap=True)
        ref = friction_terms(data, poses, rows, mu, e, order, majorizer_gap=True)
        assert torch.equal(pair, torch.unique(data.pair))
        slot = torch.unique(data.pair, return_inverse=True)[1]
        for k, got in enumerate(fast):
            want = ref[k] if k < len(ref) else None
            if want is None:
                assert got is None
                continue
            want = want.new_zeros(len(pair), *want.shape[1:]).index_add_(0, slot, want)
            assert float(want.abs().max()) > 0
            assert torch.allclose(got, want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))


def test_lagged_contacts_carry_the_planes_the_evaluation_would_find(bodies):
    """With pair ids, CfdContact.lagged also returns warm-start data (the step's first evaluation starts its plane
    solves from it): the same leaf-pair keys as an evaluation at the same poses and the same optimal planes, in the
    pair frames that evaluate() uses; and its friction contacts are those of the call without ids."""
    scene, state, _, _ = _scene_batch(bodies)
    model = scene.contact_model
    poses = state.q.detach()
    from cfd_torch.sim.energy import scene_pairs

    pairs = scene_pairs(scene, poses.shape[0])
    ids = torch.arange(pairs.shape[0]) + 7
    lag = model.lagged(poses, pairs, scene.friction.active, ids=ids)
    plain = model.lagged(poses, pairs, scene.friction.active)
    assert plain.warm is None and lag.warm is not None
    for a, b in zip(lag[:5], plain[:5], strict=True):
        assert torch.equal(a, b)
    ev = model.evaluate(poses, pairs, 2, ids=ids, warm=None)
    keys, planes = lag.warm
    assert keys.numel() > 10 and torch.equal(keys, ev.warm[0])
    assert bool((keys[1:] > keys[:-1]).all())
    torch.testing.assert_close(planes, ev.warm[1], rtol=0.0, atol=1e-8)


@pytest.mark.parametrize("active", [0.0, 0.2])
def test_lagged_contacts_from_the_numba_pass_equal_the_differentiable_form(bodies, active):
    """The forward's lagged contacts (one numba pass over the leaf pairs' vertex forces) equal the differentiable
    tensor form the adjoint uses (create_graph=True), with and without dropping weak contacts."""
    from cfd_torch.sim.energy import scene_pairs

    scene, state, _, _ = _scene_batch(bodies)
    model = scene.contact_model
    poses = state.q.detach()
    pairs = scene_pairs(scene, poses.shape[0])
    fast = model.lagged(poses, pairs, active)
    ref = model.lagged(poses.clone().requires_grad_(), pairs, active, create_graph=True)
    n_all = model.lagged(poses, pairs, 0.0).pair.numel()
    assert fast.pair.numel() > 10 and (
        fast.pair.numel() < n_all if active > 0 else fast.pair.numel() == n_all
    )
    assert torch.equal(fast.pair, ref.pair)
    for a, b in zip(fast[1:5], ref[1:5], strict=True):
        torch.testing.assert_close(a, b.detach(), rtol=1e-12, atol=1e-12 * float(b.abs().max()))


def test_pair_sums_in_numba_equal_the_tensor_scatter():
    """sum_pairs' CPU loop (no autograd wanted) equals its tensor form (taken when an input needs a graph), with
    repeated rows, several pose sets and either input alone."""
    from cfd_torch.contact.model import sum_pairs

    g = torch.Generator().manual_seed(4)
    S, N, P = 3, 5, 40
    rows = torch.stack(
        [
            torch.randint(0, S, (P,), generator=g),
            torch.randint(0, N, (P,), generator=g),
            torch.zeros(P, dtype=torch.long),
        ],
        1,
    )
    rows[:, 2] = (rows[:, 1] + 1 + torch.randint(0, N - 1, (P,), generator=g)) % N
    rows[P // 2 :] = rows[: P // 2]  # every pair twice
    gr = torch.randn(P, 12, generator=g, dtype=F64)
    hs = torch.randn(P, 12, 12, generator=g, dtype=F64)
    for a, b in ((gr, hs), (gr, None), (None, hs)):
        fast = sum_pairs(S, N, rows, a, b)
        with torch.enable_grad():
            ref = sum_pairs(S, N, rows, *(None if x is None else x.clone().requires_grad_() for x in (a, b)))
        for x, y in zip(fast, ref, strict=True):
            assert (x is None) == (y is None)
            if x is not None:
                assert float(x.abs().max()) > 0
                torch.testing.assert_close(x, y.detach(), rtol=0.0, atol=1e-13)


def test_body_terms_in_numba_equal_the_tensor_form():
    """body_terms' CPU loop (no graph wanted) equals its tensor form (taken when q needs a graph) at every order:
    inertia of translations and of rotations (a full second moment), gravity, force and torque."""
    from cfd_torch.sim.energy import body_terms, predicted_rotation

    g = torch.Generator().manual_seed(6)
    E = 7
    q = torch.randn(E, 6, generator=g, dtype=F64)
    q_t = q + 0.01 * torch.randn(E, 6, generator=g, dtype=F64)
    q_p = q_t + 0.01 * torch.randn(E, 6, generator=g, dtype=F64)
    force, torque = torch.randn(E, 3, generator=g, dtype=F64), torch.randn(E, 3, generator=g, dtype=F64)
    mass = torch.rand(E, generator=g, dtype=F64) + 0.5
    A = torch.randn(E, 3, 3, generator=g, dtype=F64)
    S = A @ A.transpose(1, 2)
    gravity = torch.tensor([0.0, 0.0, -9.81], dtype=F64)
    r = predicted_rotation(q_t, q_p, S)
    for order in (0, 1, 2):
        fast = body_terms(q, q_t, q_p, r, force, torque, mass, S, gravity, 0.01, order)
        with torch.enable_grad():
            ref = body_terms(
                q.clone().requires_grad_(), q_t, q_p, r, force, torque, mass, S, gravity, 0.01, order
            )
        for k, (x, y) in enumerate(zip(fast, ref, strict=True)):
            assert (x is None) == (y is None) == (k > order)
            if x is not None:
                assert float(x.abs().max()) > 0
                torch.testing.assert_close(x, y.detach(), rtol=0.0, atol=1e-15 * float(y.abs().max()))
    # a forward-mode tangent takes the tensor form (the kernel would drop it): the value's derivative along the
    # force is minus the displacement it works over
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        v = body_terms(
            q, q_t, q_p, r, fwAD.make_dual(force, torch.ones_like(force)), torque, mass, S, gravity, 0.01, 0
        )[0]
        tangent = fwAD.unpack_dual(v).tangent
    assert tangent is not None
    torch.testing.assert_close(tangent, -(q - q_t)[:, :3].sum(1), rtol=1e-12, atol=0.0)


def test_body_terms_torque_work_is_tau_dot_the_rotation_vector_of_the_step():
    """The torque's work over a step is tau . log(R R_t^T), for step rotations from 0 to 2.8 rad (the angle
    factors' series and closed forms): the value's torque part is exactly tau . (angle axis), the closed-form
    gradient and Hessian equal autograd's of the value, and the numba kernel equals the tensor form."""
    from cfd_torch.rotation import quaternion, quaternion_multiply, rotation_vector
    from cfd_torch.sim.energy import body_terms, predicted_rotation

    g = torch.Generator().manual_seed(11)
    angle = torch.tensor([0.0, 1e-7, 0.01, 0.3, 0.44, 0.46, 1.0, 2.0, 2.8], dtype=F64)
    E = angle.numel()
    q_t = torch.randn(E, 6, generator=g, dtype=F64)
    axis = torch.nn.functional.normalize(torch.randn(E, 3, generator=g, dtype=F64), dim=1)
    turn = quaternion_multiply(quaternion(axis * angle[:, None]), quaternion(q_t[:, 3:]))
    q = torch.cat([q_t[:, :3] + 0.01, rotation_vector(turn)], 1)
    q_p = q_t + 0.01 * torch.randn(E, 6, generator=g, dtype=F64)
    force, torque = torch.randn(E, 3, generator=g, dtype=F64), torch.randn(E, 3, generator=g, dtype=F64)
    mass = torch.rand(E, generator=g, dtype=F64) + 0.5
    A = torch.randn(E, 3, 3, generator=g, dtype=F64)
    S = A @ A.transpose(1, 2)
    gravity = torch.zeros(3, dtype=F64)
    r = predicted_rotation(q_t, q_p, S)

    def terms(qq, tau, order):
        return body_terms(qq, q_t, q_p, r, force, tau, mass, S, gravity, 1.0, order)

    work = terms(q, torch.zeros_like(torque), 0)[0] - terms(q, torque, 0)[0]
    torch.testing.assert_close(work, (torque * axis * angle[:, None]).sum(1), rtol=0.0, atol=1e-14)
    fast = terms(q, torque, 2)
    with torch.enable_grad():
        ref = terms(q.clone().requires_grad_(), torque, 2)
    for x, y in zip(fast, ref, strict=True):
        torch.testing.assert_close(x, y.detach(), rtol=0.0, atol=1e-14 * float(y.abs().max()))
    grad = torch.autograd.functional.jacobian(lambda qq: terms(qq, torque, 0)[0].sum(), q)
    hess = torch.autograd.functional.hessian(lambda qq: terms(qq, torque, 0)[0].sum(), q)
    hess = hess[torch.arange(E), :, torch.arange(E)]  # (E, 6, 6): each body's own block
    assert float(fast[1][:, 3:].abs().max()) > 0
    torch.testing.assert_close(fast[1], grad, rtol=0.0, atol=1e-14 * float(grad.abs().max()))
    torch.testing.assert_close(fast[2], hess, rtol=0.0, atol=1e-14 * float(hess.abs().max()))


def test_warm_start_tables_merge_with_the_newer_plane_winning():
    """The step's warm-start table merges each evaluation's sorted (key, plane) table into its own: every key of
    both once, sorted, with the newer plane where both have it."""
    from cfd_torch.sim.solve import WarmStarts

    g = torch.Generator().manual_seed(2)
    old_k = torch.unique(torch.randint(0, 500, (200,), generator=g))
    new_k = torch.unique(torch.randint(0, 500, (150,), generator=g))
    old_p, new_p = (
        torch.randn(len(old_k), 4, generator=g, dtype=F64),
        torch.randn(len(new_k), 4, generator=g, dtype=F64),
    )
    w = WarmStarts()
    w.update((old_k, old_p))
    w.update((new_k, new_p))
    keys, planes = w.data
    want = torch.unique(torch.cat([old_k, new_k]))
    assert torch.equal(keys, want) and len(set(old_k.tolist()) & set(new_k.tolist())) > 10
    table = {int(k): p for k, p in zip(old_k, old_p, strict=True)} | {
        int(k): p for k, p in zip(new_k, new_p, strict=True)
    }
    assert torch.equal(planes, torch.stack([table[int(k)] for k in keys]))


def test_differentiable_lagged_contacts_reuse_the_solved_planes(bodies):
    """The adjoint's lagged contacts (create_graph=True) take their vertex forces from the gradient Function at the
    planes the forward pass solved (no second solve): their values and their derivatives in the poses equal those
    of the pair potential's own double backward (the torch backend, which solves again), to rounding."""
    import dataclasses

    import numpy as np

    from cfd_torch.sim.energy import scene_pairs

    scene, state, _, _ = _scene_batch(bodies)
    model = scene.contact_model
    other = CfdContact(
        [model._bshes[int(i)] for i in model._which], dataclasses.replace(model.config, backend="torch")
    )
    pairs = scene_pairs(scene, state.q.shape[0])
    outs = []
    for m in (model, other):
        poses = state.q.detach().clone().requires_grad_()
        lag = m.lagged(poses, pairs, 0.0, create_graph=True)
        assert lag.pair.numel() > 10
        # a function of each contact's own data only (the backends list the contacts in different orders)
        s = (lag.normal_force**2).sum() + (lag.x_t * lag.X.detach()).sum()
        s = s + (lag.tangent[:, 0, 1] * lag.normal_force).sum()
        (g,) = torch.autograd.grad(s, poses)
        outs.append((lag, g))
    (a, ga), (b, gb) = outs

    def order(lag):  # the backends traverse in different orders: contacts by pair, then force centres
        key = torch.cat([lag.pair[:, None].to(F64), lag.X.detach().reshape(-1, 6)], 1).numpy().round(9)
        return torch.from_numpy(np.lexsort(key.T[::-1]).copy())

    ia, ib = order(a), order(b)
    assert bool(torch.equal(a.pair[ia], b.pair[ib])) and float(ga.abs().max()) > 0
    for x, y in zip(a[1:5], b[1:5], strict=True):
        x, y = x.detach()[ia], y.detach()[ib]
        torch.testing.assert_close(x, y, rtol=1e-8, atol=1e-8 * float(y.abs().max()))
    torch.testing.assert_close(ga, gb, rtol=1e-7, atol=1e-7 * float(gb.abs().max()))


def test_predicted_rotation_gradcheck_and_isotropic_bodies_keep_the_constant_velocity_prediction():
    """The discrete rigid body's free rotation (the inertia term's prediction) passes a float64 gradcheck in the
    poses and the second moment, solves its equation F S - S F^T = S F0 - F0^T S, and is R_t R_{t-1}^T R_t to the
    last bit for an isotropic second moment."""
    from cfd_torch.rotation import rotation_matrix
    from cfd_torch.sim.energy import predicted_rotation

    g = torch.Generator().manual_seed(3)
    E = 4
    q_t = torch.randn(E, 6, generator=g, dtype=F64)
    q_p = q_t.clone()
    q_p[:, 3:] -= 0.05 * torch.randn(E, 3, generator=g, dtype=F64)  # a few degrees per step
    A = torch.randn(E, 3, 3, generator=g, dtype=F64)
    S = A @ A.transpose(1, 2) + 0.1 * torch.eye(3, dtype=F64)
    R = predicted_rotation(q_t, q_p, S)
    Rt, Rp = rotation_matrix(q_t[:, 3:]), rotation_matrix(q_p[:, 3:])
    F, F0 = Rt.transpose(1, 2) @ R, Rp.transpose(1, 2) @ Rt
    lhs, rhs = F @ S - S @ F.transpose(1, 2), S @ F0 - F0.transpose(1, 2) @ S
    assert float((lhs - rhs).abs().max()) <= 1e-14 * float(S.abs().max())
    assert float((F - F0).abs().max()) > 1e-6  # the gyroscopic correction is there
    x = [t.clone().requires_grad_(True) for t in (q_t, q_p, S)]
    assert torch.autograd.gradcheck(
        lambda a, b, c: predicted_rotation(a, b, 0.5 * (c + c.transpose(1, 2))), x
    )
    iso = 0.7 * torch.eye(3, dtype=F64).expand(E, 3, 3)
    assert torch.equal(predicted_rotation(q_t, q_p, iso), Rt @ Rp.transpose(1, 2) @ Rt)


def test_predicted_rotation_refuses_a_turn_beyond_its_solvable_range():
    """Beyond about pi/2 rad of turn per step the discrete rigid body's equation has other roots, where Newton's
    method can land: a root that does not conserve tr(F S) (the kinetic energy) is a StepError (the step's sub-steps
    take over), never a silent wrong rotation."""
    import trimesh

    from cfd_torch import StepError, rigid_body
    from cfd_torch.rotation import rotation_matrix
    from cfd_torch.sim.energy import predicted_rotation

    S = rigid_body(trimesh.creation.box((0.4, 0.2, 0.1))).second_moment.double()[None]
    g = torch.Generator().manual_seed(1)
    refused = 0
    for _ in range(40):
        axis = torch.randn(3, generator=g, dtype=F64)
        q_t = torch.zeros(1, 6, dtype=F64)
        q_p = torch.zeros(1, 6, dtype=F64)
        q_p[0, 3:] = -2.0 * axis / axis.norm()  # 2 rad per step
        try:
            R = predicted_rotation(q_t, q_p, S)
        except StepError as err:
            assert "turns more than about pi / 2 rad per step" in str(err)
            refused += 1
            continue
        F0 = rotation_matrix(-q_p[:, 3:])
        assert abs(float(((R - F0) * S).sum())) <= 1e-9 * float(S[0].trace())  # the energy-conserving root
    assert 0 < refused < 40


_THREADS_PROBE = """
import sys, torch
torch.set_num_threads(1)
assert torch.get_num_threads() == 1  # (a read of the count, as the stepper makes, is what exposes it to numba's reset)
case = sys.argv[1]
if case == "bare":  # numba alone: its pool's start resets the OpenMP thread count torch shares
    import numba
    numba.get_num_threads()
elif case == "pairs":  # the parallel plane solve (2,000 pairs and more)
    from cfd_torch import pair_potential
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2500, 3, 3, dtype=torch.float64, generator=g)
    pair_potential(a, a + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), mu=1e-8, margin=1e-3)
elif case == "triangles":  # the parallel triangle check (100,000 triangles and more)
    from cfd_torch._validate import check_triangles
    g = torch.Generator().manual_seed(0)
    check_triangles(torch.rand(100_000, 3, 3, dtype=torch.float64, generator=g), "tri")
elif case == "rollout":  # the node traversal's thread count (32 body pairs and more)
    from cfd_torch.envs import make_core, rollout
    core = make_core("cfd_torch/Sort-v0")
    rollout(core, core.reset(seed=0), torch.zeros(2, 1, 2, dtype=torch.float64))
from numba.np.ufunc import parallel
print(int(parallel._is_initialized), torch.get_num_threads())
"""


def _threads_after(case: str) -> tuple[int, int]:
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"} | {"NUMBA_NUM_THREADS": "2"}
    out = subprocess.run(
        [sys.executable, "-c", _THREADS_PROBE, case], env=env, capture_output=True, text=True, check=True
    )
    started, threads = out.stdout.split()
    return int(started), int(threads)


def test_torch_thread_count_survives_the_start_of_numba_threads():
    """A process set to one torch thread keeps it through the library's numba kernels: numba's pool, started by
    them, resets the OpenMP thread count torch shares (a worker set to one thread ran torch on two)."""
    started, threads = _threads_after("bare")
    if threads == 1:
        pytest.skip("this numba's threading layer leaves torch's thread count alone")
    assert started == 1 and threads == 2
    for case in ("pairs", "triangles", "rollout"):
        assert _threads_after(case) == (1, 1), case


def test_a_scene_that_froze_nothing_keeps_its_energies_when_another_in_its_batch_freezes(monkeypatch):
    """When one scene of a batch freezes a body, Newton recomputes the restricted energy and rounding scale of the
    scenes that froze, and only of those: a scene that froze nothing keeps its evaluated ones (it got another scale
    formula's value, 1 % off, which its line search's tolerance reads). Checked on the recomputations themselves
    (each row passed has a frozen body: the calls are spied on); that each scene of the batch also steps as it does
    alone held before the change too, here as in the audit's runs (no end pose moved)."""
    import cfd_torch.sim.newton as newton_module

    g = torch.Generator().manual_seed(1)
    cube = rigid_body(trimesh.creation.box((0.2, 0.2, 0.2)), max_edge=0.1)
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1))
    m = trimesh.creation.box((3.0, 1.0, 0.05))
    m.apply_translation([0, 0, -0.025])
    ground = rigid_body(m, kind="static", max_edge=0.2)
    scene = Scene((cube, cube, ball, ball, ground), friction=0.4)
    xs, qs, vs = [-1.0, -0.4, 0.2, 0.8], [], []
    for _ in range(3):
        rows, vel = [], []
        for i in range(4):
            up = float(torch.rand(1, generator=g)) >= 0.5
            z = 0.15 + 0.3 * float(torch.rand(1, generator=g)) if up else 0.1015
            rot = (0.3 * (torch.rand(3, generator=g) - 0.5)).tolist() if up else [0.0, 0.0, 0.0]
            rows.append([xs[i] + 0.1 * float(torch.rand(1, generator=g)), 0.0, z, *rot])
            vel.append((torch.randn(6, generator=g) * torch.tensor([0.3, 0.3, 0.2, 1, 1, 1])).tolist())
        qs.append(rows + [_pose()])
        vs.append(vel + [[0.0] * 6])
    state = scene.initial_state(torch.tensor(qs, dtype=F64), torch.tensor(vs, dtype=F64))
    calls = []
    restricted = newton_module._restricted

    def spy(ev, rows, act, pair_moving, others=None):
        if others is None:
            calls.append(act.clone())
        return restricted(ev, rows, act, pair_moving, others)

    monkeypatch.setattr(newton_module, "_restricted", spy)
    alone = [State(state.q[b], state.q_prev[b]) for b in range(3)]
    for _ in range(3):
        batch = step(scene, state)
        n_batch = len(calls)
        alone = [step(scene, st) for st in alone]
        for b in range(3):
            torch.testing.assert_close(batch.q[b], alone[b].q, rtol=0, atol=1e-12)
        state = batch
        assert n_batch > 0
    assert calls and all(not bool(a.all(1).any()) for a in calls)  # every recomputed scene froze a body


# ======================================================================================== rest gaps
def test_rest_gap_is_where_a_settled_body_rests_and_the_stiffness_for_a_gap_inverts_it():
    """A 5 cm, 125 g cube dropped from 2 mm onto a 1 m floor settles where rest_gap (with that floor) says, to 1 %;
    the stiffness for a chosen gap rests the body at that gap (the force is linear in the stiffness)."""
    from cfd_torch import rest_gap, stiffness_for_rest_gap

    cube = rigid_body(trimesh.creation.box((0.05, 0.05, 0.05)), density=1000.0)
    floor = rigid_body(trimesh.creation.box((1.0, 1.0, 0.1)), kind="static")
    predicted = rest_gap(cube, floor=floor)
    scene = Scene((cube, floor), friction=0.5)
    q = torch.tensor([_pose(0, 0, 0.027), _pose(0, 0, -0.05)], dtype=F64)
    z = rollout(scene, scene.initial_state(q), 120).q[:, 0, 2] - 0.025
    assert float((z[-20:].max() - z[-20:].min()).abs()) < 1e-7  # at rest
    assert abs(float(z[-1]) - predicted) < 0.01 * predicted  # observed 2.647e-3 m for both
    mu = stiffness_for_rest_gap(cube, 4e-3)
    assert abs(rest_gap(cube, mu) - 4e-3) < 1e-8
    assert (
        rest_gap(cube, 10 * mu) > 4e-3 > rest_gap(cube, mu / 10) > 1e-3
    )  # stiffer: higher; never in the margin


def test_a_scene_warns_of_a_body_that_would_hover_and_names_a_stiffness_that_rests_it(monkeypatch):
    """At the default stiffness a 2 cm, 8 g cube rests millimetres to centimetres above its floor: the Scene warns
    with the stiffness that rests it two margins up, and with that stiffness it does not warn; a 10 cm, 1 kg cube,
    a planar scene, one without gravity, with gravity along another axis than -z or with nothing to rest on, a
    baseline potential and a robot's light link are not warned of; gravity tilted by 1 degree still is; a
    stiffness whose far field outweighs the body at every height says so. Bodies of one shape built separately
    share one verdict."""
    import cfd_torch.sim.rest as rest_mod
    from cfd_torch import RestGapWarning, articulation, rest_gap

    small = rigid_body(trimesh.creation.box((0.02, 0.02, 0.02)), density=1000.0)
    floor = rigid_body(trimesh.creation.box((0.5, 0.5, 0.1)), kind="static")
    with pytest.warns(
        RestGapWarning, match=r"body 1 \(0.008 kg, 2 cm tall\) would rest about 6.\d+ mm .* mu=(\S+) rests"
    ):
        Scene((floor, small))
    with pytest.warns(RestGapWarning) as record:
        Scene((floor, small))
    mu = float(re.search(r" mu=(\S+) rests", str(record[0].message)).group(1))
    assert abs(rest_gap(small, mu) - 2e-3) < 2e-4  # the suggestion is rounded to two digits
    big = rigid_body(trimesh.creation.box((0.1, 0.1, 0.1)), density=1000.0)
    link = articulation(
        '<mujoco><worldbody><body name="a" pos="0 0 0.1"><freejoint/>'
        '<geom type="box" size="0.01 0.01 0.01" mass="0.001"/></body></worldbody></mujoco>'
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", RestGapWarning)
        Scene((floor, small), mu=mu)
        Scene((floor, big))
        Scene((floor, small), planar=True)
        Scene((floor, small), gravity=(0.0, 0.0, 0.0))
        Scene((floor, small), gravity=(0.0, -9.81, 0.0))  # (the floor model is z up: not judged)
        Scene((small, small))  # nothing to rest on
        Scene((floor, small), potential="ipc")
        Scene((floor,), articulations=[link])  # a robot's links hang from their joints
    with pytest.warns(RestGapWarning, match="body 1"):
        Scene((floor, small), gravity=(0.17, 0.0, -9.81))
    with pytest.warns(RestGapWarning, match="would be pushed off a flat floor to any height"):
        Scene((floor, small), mu=1e20)
    calls = []
    judge = rest_mod._verdict
    monkeypatch.setattr(rest_mod, "_verdict", lambda *a: calls.append(1) or judge(*a))
    twins = [rigid_body(trimesh.creation.box((0.02, 0.02, 0.02)), density=999.0) for _ in range(3)]
    with pytest.warns(RestGapWarning) as record:
        Scene((floor, *twins))
    assert len(calls) == 1 and [str(w.message)[:17] for w in record] == ["bodies 1, 2, 3 (0"]


def test_a_light_body_over_a_wide_floor_balances_at_several_heights():
    """A 2 cm, 8 g cube over a 1 m floor: its lift is not monotone in the gap (1.05, 0.77, 1.05 times its weight at
    12, 13, 14 mm at the default stiffness: the far field's blend bands), so where it rests depends on where it is
    released, and the stiffness that balances it at 13 mm balances it unstably: stiffness_for_rest_gap says so and
    where the body then rests; at 17.5 mm, where the lift falls with the gap, it is stable and says nothing."""
    from cfd_torch import RestGapWarning, rest_gap, stiffness_for_rest_gap

    small = rigid_body(trimesh.creation.box((0.02, 0.02, 0.02)), density=1000.0)
    floor = rigid_body(trimesh.creation.box((1.0, 1.0, 0.1)), kind="static")
    low, high = rest_gap(small, floor=floor, start=3e-3), rest_gap(small, floor=floor, start=30e-3)
    assert 11e-3 < low < 13e-3 and 17e-3 < high < 18e-3  # observed 12.1 and 17.3 mm
    with pytest.warns(
        RestGapWarning, match=r"balances 13 mm above the floor, but unstably .* rests at (\S+) mm"
    ) as w:
        mu = stiffness_for_rest_gap(small, 13e-3, floor=floor)
    ends = float(re.search(r"rests at (\S+) mm", str(w[0].message)).group(1))
    assert ends > 14.0 and abs(1e3 * rest_gap(small, mu, floor=floor, start=13.013e-3) - ends) < 1e-2
    with warnings.catch_warnings():
        warnings.simplefilter("error", RestGapWarning)
        mu = stiffness_for_rest_gap(small, 17.5e-3, floor=floor)
    assert abs(rest_gap(small, mu, floor=floor, start=18e-3) - 17.5e-3) < 1e-7


def test_rest_gap_refuses_what_it_cannot_answer():
    from cfd_torch import rest_gap, stiffness_for_rest_gap

    cube = rigid_body(trimesh.creation.box((0.05, 0.05, 0.05)))
    floor = rigid_body(trimesh.creation.box((1.0, 1.0, 0.1)), kind="static")
    with pytest.raises(TypeError, match="body must be a dynamic cfd_torch.RigidBody"):
        rest_gap(floor)
    with pytest.raises(TypeError, match="floor must be a cfd_torch.RigidBody"):
        rest_gap(cube, floor="floor")
    with pytest.raises(ValueError, match="gravity must be a positive finite number"):
        rest_gap(cube, gravity=0.0)
    with pytest.raises(ValueError, match="mu must be a positive finite number"):
        rest_gap(cube, float("nan"))
    with pytest.raises(ValueError, match="contact must be a ContactConfig of this library's potential"):
        rest_gap(cube, contact=ContactConfig(potential="ipc"))
    with pytest.raises(ValueError, match="gap must be a finite number above the contact margin 0.001 m"):
        stiffness_for_rest_gap(cube, 1e-3)
    with pytest.raises(ValueError, match="start must be a finite number above the contact margin"):
        rest_gap(cube, start=5e-4)
    with pytest.raises(ValueError, match="it does not rest"):
        rest_gap(cube, 1e20)


def test_free_body_block_shortcuts_equal_the_general_maps():
    """The coupling test summed by 6 x 6 blocks and the pullback by slices (free bodies numbered in a row) give
    what the one-hot products and the index gathers give."""
    from cfd_torch.sim.kinematics import FreeBodies
    from cfd_torch.sim.newton import _coupling

    g = torch.Generator().manual_seed(0)
    M, Q = 7, 42
    H = torch.randn(3, Q, Q, dtype=torch.float64, generator=g)
    H = H + H.transpose(1, 2)
    scale = torch.rand(M, M, generator=g, dtype=torch.float64) < 0.5  # some blocks far below the threshold
    H = H * torch.where(scale, 1e-9, 1.0).repeat_interleave(6, 0).repeat_interleave(6, 1)
    onehot = (torch.arange(Q)[:, None] // 6 == torch.arange(M)).to(H.dtype)
    general, blocks = _coupling(H, onehot), _coupling(H, onehot, 6)
    assert bool(general.any()) and not bool(general.all())
    assert torch.equal(general, blocks)

    N = 9
    rows = torch.randn(2, N, 6, dtype=torch.float64, generator=g)
    hess = torch.randn(2, 6 * N, 6 * N, dtype=torch.float64, generator=g)
    for dynamic, span in ((torch.arange(1, 8), True), (torch.tensor([0, 2, 3, 7]), False)):
        kin = FreeBodies(dynamic, N)
        assert (kin._span is not None) == span
        d6 = (dynamic[:, None] * 6 + torch.arange(6)).reshape(-1)
        gq, hq, (xq,) = kin.pullback(torch.zeros(2, 6 * len(dynamic)), rows, hess, None, (hess,))
        assert torch.equal(gq, rows.reshape(2, -1)[:, d6])
        assert torch.equal(hq, hess[:, d6][:, :, d6]) and torch.equal(xq, hq)
