"""The IPC baseline contact model (``cfd_torch.contact.ipc``): against ipc-toolkit, its vanishing far field, and
in the stepper (a resting box, a collision, friction, rollout gradients)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from cfd_torch import Action, Scene, State, rigid_body, step
from cfd_torch.contact.bsh import BSH
from cfd_torch.contact.cfd import CfdContact
from cfd_torch.contact.ipc import IpcContact
from cfd_torch.rotation import rotation_matrix
from cfd_torch.sim.stepper import rollout

F64 = torch.float64
PAIR = torch.tensor([[0, 0, 1]])


def _world(bshes, q: torch.Tensor) -> torch.Tensor:
    return torch.cat(
        [
            b.vertices.double() @ rotation_matrix(p[None, 3:])[0].T + p[:3]
            for b, p in zip(bshes, q, strict=True)
        ]
    )


def _touching_at(model, q: torch.Tensor, direction: torch.Tensor, gap: float) -> torch.Tensor:
    """q with body 1 moved along ``direction`` to ``gap`` beyond where the two first touch (bisection on the
    model's collision query)."""
    lo, hi = 0.0, 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        qq = q.clone()
        qq[1, :3] = mid * direction
        lo, hi = (mid, hi) if bool(model.infeasible(qq[None], PAIR)[0]) else (lo, mid)
    out = q.clone()
    out[1, :3] = (hi + gap) * direction
    return out


def _ipctk_reference(ipctk, bshes, F: np.ndarray, q: torch.Tensor, dhat: float, kappa: float):
    """ipc-toolkit's BarrierPotential of the bodies at poses q (2, 6), chained to the poses: value, J^T g,
    J^T H J + g . d2V, and the number of its collisions."""
    V = _world(bshes, q).numpy()
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    mesh.can_collide = ipctk.make_connected_components_filter(F)
    C = ipctk.NormalCollisions()
    C.build(mesh, V, dhat)
    B = ipctk.BarrierPotential(dhat, kappa)
    g = torch.tensor(B.gradient(C, mesh, V))
    H = torch.tensor(B.hessian(C, mesh, V).toarray())
    x = q.reshape(-1)
    J = torch.autograd.functional.jacobian(lambda z: _world(bshes, z.reshape(2, 6)).reshape(-1), x)
    Hg = torch.autograd.functional.hessian(lambda z: _world(bshes, z.reshape(2, 6)).reshape(-1) @ g, x)
    return B(C, mesh, V), J.T @ g, J.T @ H @ J + Hg, len(C)


def test_ipc_matches_ipc_toolkit_on_random_configurations():
    """Value, pose gradient and pose Hessian of an icosphere and a box in random relative poses within dhat equal
    ipc-toolkit 1.6.1's BarrierPotential on the world vertices, chained to the poses (J^T g and J^T H J + g . d2V),
    to 1e-12 relative."""
    ipctk = pytest.importorskip("ipctk")
    a, b = trimesh.creation.icosphere(1, 0.1), trimesh.creation.box((0.2, 0.15, 0.1))
    bshes = (BSH.from_trimesh(a), BSH.from_trimesh(b))
    dhat, kappa = 0.02, 1e6
    model = IpcContact(bshes, dhat, kappa)
    F = np.concatenate([a.faces, b.faces + len(a.vertices)])
    gen = torch.Generator().manual_seed(0)
    checked = 0
    for _ in range(4):
        q = torch.zeros(2, 6, dtype=F64)
        q[:, 3:] = torch.randn(2, 3, generator=gen, dtype=F64)
        d = torch.randn(3, generator=gen, dtype=F64)
        q = _touching_at(model, q, d / d.norm(), float(torch.rand(1, generator=gen)) * 0.8 * dhat)
        ev = model.evaluate(q[None], PAIR, 2)
        value, gq, Hq, count = _ipctk_reference(ipctk, bshes, F, q, dhat, kappa)
        assert count > 0 and float(ev.value[0]) > 0
        assert float(ev.value[0]) == pytest.approx(value, rel=1e-12)
        assert float((ev.grad[0] - gq).abs().max()) <= 1e-12 * float(gq.abs().max())
        assert float((ev.hess[0] - Hq).abs().max()) <= 1e-12 * float(Hq.abs().max())
        checked += 1
    assert checked == 4


def test_ipc_closest_features_follow_ipc_toolkit_at_ties():
    """Where two closest features are equally near (a point over a triangle's edge or vertex, edges crossing at an
    end, parallel edges: every coordinate an integer, so the ties are exact), the distance is the same but its
    Hessian is not: the classification follows ipc-toolkit's ``point_triangle_distance_type`` and
    ``edge_edge_distance_type`` exactly (it differed at 3 % of such configurations). Then a box lying square on a
    floor (its corners over the floor's edges and vertices) has ipc-toolkit's pose Hessian (it was 4 % off)."""
    ipctk = pytest.importorskip("ipctk")
    from cfd_torch.contact.ipc import _classify_ee, _classify_vf

    vf_kinds = ["P_T", "P_E0", "P_E1", "P_E2", "P_T0", "P_T1", "P_T2"]
    ee_kinds = ["EA_EB", "EA0_EB", "EA1_EB", "EA_EB0", "EA_EB1", "EA0_EB0", "EA0_EB1", "EA1_EB0", "EA1_EB1"]
    rng = np.random.default_rng(0)
    x = rng.integers(-2, 3, size=(6000, 4, 3)).astype(np.float64)
    x[:, 0] /= 2
    tri = np.linalg.norm(np.cross(x[:, 2] - x[:, 1], x[:, 3] - x[:, 1]), axis=-1) > 0
    seg = (np.abs(x[:, 1] - x[:, 0]).sum(-1) > 0) & (np.abs(x[:, 3] - x[:, 2]).sum(-1) > 0)
    got_vf, got_ee = _classify_vf(torch.from_numpy(x[tri])), _classify_ee(torch.from_numpy(x[seg]))
    want_vf = [vf_kinds.index(str(ipctk.point_triangle_distance_type(*r)).split(".")[-1]) for r in x[tri]]
    want_ee = [ee_kinds.index(str(ipctk.edge_edge_distance_type(*r)).split(".")[-1]) for r in x[seg]]
    assert len(want_vf) > 4000 and len(want_ee) > 4000 and len(set(want_ee)) == 9 and len(set(want_vf)) == 7
    assert got_vf.tolist() == want_vf
    assert got_ee.tolist() == want_ee

    floor, box = trimesh.creation.box((1.0, 1.0, 0.1)), trimesh.creation.box((0.2, 0.2, 0.2))
    bshes = (BSH.from_trimesh(floor), BSH.from_trimesh(box))
    F = np.concatenate([floor.faces, box.faces + len(floor.vertices)])
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 2] = 0.15 + 0.005
    ev = IpcContact(bshes, 0.02, 1e6).evaluate(q[None], PAIR, 2)
    value, g, H, count = _ipctk_reference(ipctk, bshes, F, q, 0.02, 1e6)
    assert count > 0 and value > 0
    assert float(ev.value[0]) == pytest.approx(value, rel=1e-12)
    assert float((ev.grad[0] - g).abs().max()) <= 1e-12 * float(g.abs().max())
    assert float((ev.hess[0] - H).abs().max()) <= 1e-12 * float(H.abs().max())


def test_ipc_vanishes_beyond_dhat_where_ours_does_not():
    """Two spheres 5 cm apart with dhat 1 cm: IPC's value and gradient are exactly zero, this library's are not;
    touching or intersecting bodies are +inf and infeasible."""
    s = BSH.from_trimesh(trimesh.creation.icosphere(2, 0.1))
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 0] = 0.25
    ipc = IpcContact([s, s], dhat=0.01)
    ev = ipc.evaluate(q[None], PAIR, 2)
    assert float(ev.value[0]) == 0.0 and float(ev.grad.abs().max()) == 0.0 and ev.leaf_pairs == 0
    ours = CfdContact([s, s]).evaluate(q[None], PAIR, 1)
    assert float(ours.grad[0, 0]) > 0.0  # pushes body 0 toward -x: dP/dx0 > 0
    q[1, 0] = 0.15
    assert bool(ipc.infeasible(q[None], PAIR)[0]) and float(ipc.evaluate(q[None], PAIR, 0).value[0]) == np.inf
    with pytest.raises(ValueError, match="dhat"):
        IpcContact([s, s], dhat=0.0)
    ball = rigid_body(trimesh.creation.icosphere(1, 0.1))
    with pytest.raises(ValueError, match=r"ContactConfig.potential must be one of \('cfd', 'ipc', 'sdrs'\)"):
        Scene([ball], potential="sdf")
    with pytest.raises(ValueError, match="ContactConfig.barrier_stiffness"):
        Scene([ball], potential="ipc", barrier_stiffness=-1.0)


def _box(extent: float, **kw):
    return rigid_body(trimesh.creation.box((extent,) * 3), **kw)


@pytest.mark.slow
def test_ipc_box_rests_holds_and_slides():
    """A 0.2 m box dropped 3 cm onto a floor with potential="ipc" (dhat 1 cm, kappa 1e6): it settles above the
    floor within dhat and stays; pushed with 10 N (friction 0.5: mu m g = 39 N) it holds to a millimetre over
    0.5 s (the soft barrier lets it tilt), pushed with 60 N it slides."""
    floor = trimesh.creation.box((2.0, 2.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    box = _box(0.2)
    scene = Scene([box, rigid_body(floor, kind="static")], potential="ipc", friction=0.5)
    assert isinstance(scene.contact_model, IpcContact)
    q = torch.zeros(2, 6, dtype=F64)
    q[0, 2] = 0.13
    traj = rollout(scene, State(q, q.clone()), 60)
    gap = traj.q[:, 0, 2] - 0.1
    assert float(gap.min()) > 0.0
    assert 0.0 < float(gap[-10:].min()) and float(gap[-10:].max()) < 0.01
    assert float((gap[-10:] - gap[-1]).abs().max()) < 1e-4  # at rest, to its last bounces of about 10 um
    rest = traj[-1]
    for force, lo, hi in ((10.0, 0.0, 2e-3), (60.0, 0.05, 1.0)):
        s = rest
        push = Action(force=torch.tensor([[force, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64))
        for _ in range(50):
            s = step(scene, s, push)
        assert lo <= float(s.q[0, 0] - rest.q[0, 0]) < hi, force


def test_ipc_keeps_a_minimum_separation_so_a_start_within_rounding_of_contact_is_not_taken():
    """A ball thrown at a wall at round-number positions: a step's constant-velocity start landed one ulp short of
    the wall, where IPC's distances are rounding and its Newton steps below the coordinates' spacing (200 iterations,
    StepError); with the minimum separation (1e-6 dhat) that start is infeasible, and the ball bounces back as it
    does with SDRS and from a start 0.1 mm further back. Just beyond the separation the barrier is finite."""
    wall = trimesh.creation.box((0.2, 2.0, 2.0))
    wall.apply_translation((0.3, 0.0, 0.0))
    ball = rigid_body(trimesh.creation.icosphere(2, 0.05), density=500.0)
    scene = Scene([ball, rigid_body(wall, kind="static")], gravity=(0.0, 0.0, 0.0), potential="ipc")
    vel = torch.zeros(2, 6, dtype=F64)
    vel[0, 0] = 1.0
    traj = rollout(scene, scene.initial_state(torch.zeros(2, 6, dtype=F64), vel), 25)
    assert (
        float(traj.q[-1, 0, 0] - traj.q[-2, 0, 0]) < -0.1 * scene.dt
    )  # bounced: moving back at over 0.1 m/s
    assert float(traj.q[:, 0, 0].max()) < 0.15  # never touched the wall (its face at x = 0.2)
    model, pair = scene.contact_model, torch.tensor([[0, 0, 1]])
    for gap, infeasible in ((0.5e-6 * 0.01, True), (2e-6 * 0.01, False)):
        q = torch.zeros(1, 2, 6, dtype=F64)
        q[0, 0, 0] = 0.15 - gap
        assert bool(model.infeasible(q, pair)[0]) == infeasible
        assert math.isinf(float(model.evaluate(q, pair, 0).value[0])) == infeasible


def test_ipc_collision_and_rollout_gradient():
    """Two balls meeting head on with potential="ipc" (no gravity): momentum conserved, they part, and the
    gradient of the struck ball's final position in the striker's initial velocity matches central differences
    (non-zero: the contact acts)."""
    ball = rigid_body(trimesh.creation.icosphere(2, 0.05), density=500.0)
    scene = Scene([ball, ball], potential="ipc", gravity=(0.0, 0.0, 0.0), dhat=5e-3, barrier_stiffness=1e6)
    q0 = torch.zeros(2, 6, dtype=F64)
    q0[1, 0] = 0.12

    def run(v: torch.Tensor):
        vel = torch.zeros(2, 6, dtype=F64)
        vel[0, :3] = v
        return rollout(scene, scene.initial_state(q0, vel), 30)

    v = torch.tensor([0.5, 0.02, 0.0], dtype=F64, requires_grad=True)
    traj = run(v)
    P = (traj.q[-1] - traj.q[-2])[:, :3].sum(0) / scene.dt * ball.mass
    assert torch.allclose(P, ball.mass * v.detach(), rtol=0, atol=1e-9 * ball.mass)
    assert float(traj.q[-1, 1, 0] - traj.q[-1, 0, 0]) > 0.1 + 5e-3  # struck and parted
    w = torch.tensor([1.0, 0.5, 0.0], dtype=F64)
    (g,) = torch.autograd.grad(traj.q[-1, 1, :3] @ w, v)
    assert float(g.abs().max()) > 1e-2
    h = 1e-6
    for k in range(2):
        e = torch.zeros(3, dtype=F64)
        e[k] = h
        with torch.no_grad():
            fd = (run(v + e).q[-1, 1, :3] @ w - run(v - e).q[-1, 1, :3] @ w) / (2 * h)
        assert float(g[k]) == pytest.approx(float(fd), rel=1e-5, abs=1e-8)


# ------------------------------------------------------------------------------------------------------ SDRS
def test_sdrs_model_equals_the_pairwise_barrier_with_consistent_derivatives():
    """An icosphere and a box in a random relative pose 1 cm beyond touching (dhat 2 cm): the model's value is the
    sum of cfd_torch.baselines.sdrs_pair_potential over all triangle pairs (1e-10), its pose gradient that sum's
    autograd gradient through the vertices (1e-8), and its Hessian the directional difference of its gradient
    (1e-5); far apart everything is exactly zero, within the margin +inf."""
    from cfd_torch.baselines import sdrs_pair_potential
    from cfd_torch.contact.sdrs import SdrsContact

    a, b = trimesh.creation.icosphere(1, 0.1), trimesh.creation.box((0.2, 0.15, 0.1))
    bshes = (BSH.from_trimesh(a), BSH.from_trimesh(b))
    model = SdrsContact(bshes, dhat=0.02, stiffness=10.0)
    gen = torch.Generator().manual_seed(1)
    q = torch.zeros(2, 6, dtype=F64)
    q[:, 3:] = torch.randn(2, 3, generator=gen, dtype=F64)
    d = torch.randn(3, generator=gen, dtype=F64)
    q = _touching_at(model, q, d / d.norm(), 0.01)
    ev = model.evaluate(q[None], PAIR, 2)
    assert ev.leaf_pairs > 0 and float(ev.value[0]) > 0

    def brute(z: torch.Tensor) -> torch.Tensor:
        pose = z.reshape(2, 6)
        ta = (
            bshes[0].vertices.double()[bshes[0].faces] @ rotation_matrix(pose[None, 0, 3:])[0].T + pose[0, :3]
        )
        tb = (
            bshes[1].vertices.double()[bshes[1].faces] @ rotation_matrix(pose[None, 1, 3:])[0].T + pose[1, :3]
        )
        A = ta[:, None].expand(-1, len(tb), 3, 3).reshape(-1, 3, 3)
        B = tb[None].expand(len(ta), -1, 3, 3).reshape(-1, 3, 3)
        return sdrs_pair_potential(A, B, dhat=0.02, kappa=10.0).sum()

    z = q.reshape(-1).clone().requires_grad_(True)
    ref = brute(z)
    (g_ref,) = torch.autograd.grad(ref, z)
    assert float(ev.value[0]) == pytest.approx(float(ref), rel=1e-10)
    assert float((ev.grad[0] - g_ref).abs().max()) <= 1e-8 * float(g_ref.abs().max())
    u = torch.randn(12, generator=gen, dtype=F64)
    h = 1e-6
    gp = model.evaluate((q.reshape(-1) + h * u).reshape(1, 2, 6), PAIR, 1).grad[0]
    gm = model.evaluate((q.reshape(-1) - h * u).reshape(1, 2, 6), PAIR, 1).grad[0]
    Hu = ev.hess[0] @ u
    assert float(((gp - gm) / (2 * h) - Hu).abs().max()) <= 1e-5 * float(Hu.abs().max())
    far = q.clone()
    far[1, :3] *= 3.0
    assert float(model.evaluate(far[None], PAIR, 1).grad.abs().max()) == 0.0
    near = _touching_at(model, q, d / d.norm(), -1e-4)
    assert float(model.evaluate(near[None], PAIR, 0).value[0]) == np.inf


def test_sdrs_box_rests_on_a_floor():
    """A 0.2 m box dropped 2 cm onto a floor with potential="sdrs" (dhat 1 cm, kappa 10): it lands and rests
    above the margin, within the barrier's reach."""
    floor = trimesh.creation.box((2.0, 2.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    scene = Scene([_box(0.2, density=500.0), rigid_body(floor, kind="static")], potential="sdrs")
    q = torch.zeros(2, 6, dtype=F64)
    q[0, 2] = 0.12
    traj = rollout(scene, State(q, q.clone()), 50)
    gap = traj.q[:, 0, 2] - 0.1
    assert float(gap.min()) > 1e-3
    assert float(gap[-5:].max()) < 0.021 and float((gap[-5:] - gap[-1]).abs().max()) < 1e-3


@pytest.mark.parametrize("potential", ["ipc", "sdrs"])
def test_baseline_rows_evaluate_as_alone_and_margin_agrees_with_infeasible(potential):
    """Two pose sets of an icosphere and a box, each within reach, plus a far pair: evaluating the rows together
    equals evaluating each alone, bit for bit; lagged contacts are finite even with active = 0; and just beyond the
    infeasible boundary the value is finite, just inside it +inf."""
    from cfd_torch.contact.sdrs import SdrsContact

    a, b = trimesh.creation.icosphere(1, 0.1), trimesh.creation.box((0.2, 0.15, 0.1))
    bshes = (BSH.from_trimesh(a), BSH.from_trimesh(b), BSH.from_trimesh(a))
    model = IpcContact(bshes, dhat=0.02) if potential == "ipc" else SdrsContact(bshes, dhat=0.02)
    gen = torch.Generator().manual_seed(2)
    sets = []
    for _ in range(2):
        q = torch.zeros(3, 6, dtype=F64)
        q[:, 3:] = torch.randn(3, 3, generator=gen, dtype=F64)
        d = torch.randn(3, generator=gen, dtype=F64)
        q[2, 0] = 5.0
        sets.append(_touching_at(model, q, d / d.norm(), 0.008))
    poses = torch.stack(sets)
    rows = torch.tensor([[0, 0, 1], [1, 0, 1], [0, 0, 2]])
    together = model.evaluate(poses, rows, 2)
    assert bool((together.value[:2] > 0).all()) and float(together.value[2]) == 0.0
    for r in range(3):
        alone = model.evaluate(poses, rows[r : r + 1], 2)
        assert torch.equal(alone.value[0], together.value[r])
        assert torch.equal(alone.grad[0], together.grad[r]) and torch.equal(alone.hess[0], together.hess[r])
    lag = model.lagged(poses, rows, 0.0)
    assert len(lag.pair) > 0 and all(bool(torch.isfinite(x).all()) for x in lag[1:5])
    d = torch.randn(3, generator=gen, dtype=F64)
    edge = _touching_at(model, sets[0], d / d.norm(), 0.0)  # the first pose the query calls feasible
    inside = edge.clone()
    inside[1, :3] *= 1.0 - 1e-9
    assert not bool(model.infeasible(edge[None], PAIR)[0])
    assert bool(torch.isfinite(model.evaluate(edge[None], PAIR, 1).value[0]))
    assert bool(model.infeasible(inside[None], PAIR)[0]) == bool(
        torch.isinf(model.evaluate(inside[None], PAIR, 0).value[0])
    )
    deep = sets[0].clone()
    deep[1, :3] = 0.0  # the bodies' centres together: deep inside each other
    ev = model.evaluate(torch.stack([deep, sets[1]]), rows[:2], 2)
    assert float(ev.value[0]) == np.inf and bool(torch.isfinite(ev.value[1]))
    assert float(ev.grad[1].abs().max()) > 0  # (the feasible row keeps its derivatives)
    assert float(ev.grad[0].abs().max()) == 0.0 and float(ev.hess[0].abs().max()) == 0.0  # no force at +inf


@pytest.mark.slow
@pytest.mark.parametrize("potential", ["ipc", "sdrs"])
def test_baseline_friction_rollout_gradient_matches_finite_differences(potential):
    """A box sliding on a floor under 60 N with friction 0.5 and the baseline's contact, 10 steps: the gradient of
    its final pose in the force and in its initial velocity (through the lagged friction contacts' dependence on the
    previous poses) matches central differences to 1e-6 (SDRS: its plane solves stop about 1e-10 from the optimum,
    a noise of about 1e-11 m in the poses, so its differences take longer steps, and its yaw component, 8e-6 m s,
    is checked to 1e-4 at a step of 1e-2; measured in session 47, the yaw differences agree with the gradient to
    1.3e-6 and 2.0e-6 at steps 3e-2 and 1e-2 and drift with the noise below: 7e-5 at 3e-3, 1.1e-3 at 1e-3, the
    step this test took until then (in session 39 that one agreed to 1e-7); the force's to 2e-7 at 3e-2, the
    velocity's to 1.7e-7 at 1e-3)."""
    floor = trimesh.creation.box((2.0, 2.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    scene = Scene([_box(0.2), rigid_body(floor, kind="static")], potential=potential, friction=0.5)
    q0 = torch.zeros(2, 6, dtype=F64)
    q0[0, 2] = 0.105
    w = torch.tensor([1.0, 0.3, 0.7, 0.2, 0.1, 0.5], dtype=F64)

    def final(theta: torch.Tensor) -> torch.Tensor:  # theta: x force [N], initial x velocity [m/s], yaw rate
        qp = q0 - scene.dt * torch.stack([
            torch.stack([theta[1], *[0 * theta[1]] * 4, theta[2]]), torch.zeros(6, dtype=F64)
        ])  # fmt: skip
        force = torch.stack([torch.stack([theta[0], 0 * theta[0], 0 * theta[0]]), torch.zeros(3, dtype=F64)])
        return rollout(scene, State(q0, qp), [Action(force=force)] * 10).q[-1, 0] @ w

    theta = torch.tensor([60.0, 0.3, 0.5], dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(final(theta), theta)
    assert float(g.abs().min()) > (1e-4 if potential == "ipc" else 1e-6)
    steps, rel = (
        ((1e-4, 1e-6, 1e-6), (1e-6,) * 3) if potential == "ipc" else ((3e-2, 1e-3, 1e-2), (1e-6, 1e-6, 1e-4))
    )
    for k, h in enumerate(steps):
        e = torch.zeros(3, dtype=F64)
        e[k] = h
        with torch.no_grad():
            fd = (final(theta + e) - final(theta - e)) / (2 * h)
        assert float(g[k]) == pytest.approx(float(fd), rel=rel[k]), k


def test_settings_a_potential_does_not_read_are_refused_and_penetration_names_its_limit():
    """A setting the chosen potential does not read is refused unless at its default (they were silently
    ignored); a penetrating start state is refused with what +inf means for the model: IPC's barrier at contact,
    SDRS's and ours within the margin (the IPC message quoted a margin IPC does not have)."""
    floor = trimesh.creation.box((2.0, 2.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    bodies = [_box(0.2), rigid_body(floor, kind="static")]
    for kw, match in (
        (
            {"potential": "ipc", "mu": 1e-6},
            "stiffness \\(Scene's mu=\\) sets this library's potential, which ",
        ),
        ({"potential": "sdrs", "eps": 0.1, "refine_obstacles": None}, "eps .*refine_obstacles .* set this "),
        (
            {"dhat": 0.05},
            "dhat \\(Scene's dhat=\\) sets the baselines' barrier, which potential='cfd' does not",
        ),
        ({"barrier_stiffness": 5.0}, "barrier_stiffness"),
    ):
        with pytest.raises(ValueError, match=match):
            Scene(bodies, **kw)
    # margin is read by every potential (the line search's length scale); a change of potential resets what the
    # new one does not read (it raised: the old scene's mu, or dhat, carried over)
    ours = Scene(bodies, mu=1e-7, margin=2e-3)
    ipc = ours.replace(potential="ipc", dhat=0.02)
    assert (ipc.contact.stiffness, ipc.contact.margin, ipc.contact.dhat) == (1e-8, 2e-3, 0.02)
    back = ipc.replace(potential="cfd")
    assert (back.contact.stiffness, back.contact.dhat, back.contact.potential) == (1e-8, 1e-2, "cfd")
    with pytest.raises(ValueError, match="stiffness \\(Scene's mu=\\) sets this library's potential"):
        ours.replace(potential="ipc", mu=1e-7)
    q = torch.tensor([[0.0, 0.0, 0.0995, 0.0, 0.0, 0.0], [0.0] * 6], dtype=F64)  # 0.5 mm into the floor
    for potential, match in (
        (
            "ipc",
            "bodies penetrate \\(within the contact margin 1e-08\\)",
        ),  # (its minimum separation, 1e-6 dhat)
        ("sdrs", "bodies penetrate \\(within the contact margin 0.001\\)"),
        ("cfd", "bodies penetrate \\(within the contact margin 0.001\\)"),
    ):
        with pytest.raises(ValueError, match=match):
            step(Scene(bodies, potential=potential), State(q, q.clone()))
