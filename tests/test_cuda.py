"""The public API on a CUDA device against the CPU reference path: the same values, gradients and trajectories.

On CPU the numba kernels compute; on CUDA the same algorithms run as batched tensor code (breadth-first traversal,
masked plane solves). Every test here runs the CPU path and the CUDA path on the same inputs and compares them, so
the tests are skipped on machines without CUDA (CI's). ``CFD_TEST_DEVICE=cpu`` runs them against themselves on CPU
(a check of the tests' own code, not of a device)."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest
import torch
import trimesh
from conftest import feature_pairs

from cfd_torch import (
    BSH,
    Action,
    Scene,
    State,
    contact_potential,
    mesh_potential,
    mesh_potential_derivatives,
    pair_forces,
    pair_potential,
    pair_potential_derivatives,
    rigid_body,
    rollout,
    step,
)

DEVICE = torch.device(os.environ.get("CFD_TEST_DEVICE", "cuda"))
pytestmark = pytest.mark.skipif(
    DEVICE.type == "cuda" and not torch.cuda.is_available(),
    reason="needs CUDA (CFD_TEST_DEVICE=cpu to dry-run)",
)
F64 = torch.float64
CPU = torch.device("cpu")


def _close(dev: torch.Tensor, ref: torch.Tensor, rtol: float, atol: float = 0.0, what: str = ""):
    assert dev.device.type == DEVICE.type, f"{what}: result on {dev.device}, inputs on {DEVICE}"
    assert dev.dtype == ref.dtype, f"{what}: {dev.dtype} against {ref.dtype}"
    torch.testing.assert_close(dev.cpu(), ref, rtol=rtol, atol=atol, msg=lambda m: f"{what}: {m}")


def _icosphere(subdivisions: int = 2, radius: float = 0.1) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def _floor(size: float = 1.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.box((size, size, 0.05))
    mesh.apply_translation((0.0, 0.0, -0.025))
    return mesh


# ------------------------------------------------------------------------------------------------ pair potential
def _pairs() -> tuple[torch.Tensor, torch.Tensor]:
    cases = list(feature_pairs(0.01).values()) + list(feature_pairs(0.3).values())
    a = torch.stack([c[0] for c in cases])
    b = torch.stack([c[1] for c in cases])
    g = torch.Generator().manual_seed(0)
    ra = torch.rand(64, 3, 3, generator=g, dtype=F64)
    rb = torch.rand(64, 3, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, 1.2], dtype=F64)
    return torch.cat([a, ra]), torch.cat([b, rb])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_pair_potential_value_gradient_and_second_order_match_cpu(dtype):
    a, b = (x.to(dtype) for x in _pairs())
    out = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        ta = a.to(dev).requires_grad_(True)
        tb = b.to(dev).requires_grad_(True)
        P = pair_potential(ta, tb)
        ga, gb = torch.autograd.grad(P.sum(), (ta, tb), create_graph=True)
        v = torch.ones_like(gb)
        (hv,) = torch.autograd.grad((gb * v).sum(), ta)
        out[key] = (P, ga, gb, hv)
    assert out["cpu"][2].abs().max() > 0
    rtol = 1e-10 if dtype == F64 else 1e-5
    for name, d, r in zip(("value", "grad a", "grad b", "hvp"), out["dev"], out["cpu"], strict=True):
        d, r = d.detach(), r.detach()
        _close(d, r, rtol, atol=rtol * float(r.abs().max()), what=name)


def test_pair_potential_derivatives_match_cpu():
    a, b = _pairs()
    ref = pair_potential_derivatives(a, b)
    dev = pair_potential_derivatives(a.to(DEVICE), b.to(DEVICE))
    assert ref.grad.abs().max() > 0
    for name in ("value", "grad", "hessian", "plane"):
        r = getattr(ref, name)
        _close(getattr(dev, name), r, 1e-9, atol=1e-9 * float(r.abs().max()), what=name)


def test_pair_potential_gradcheck_and_gradgradcheck_on_device():
    a, b = feature_pairs(0.05)["edge-edge"]
    ta = a.to(DEVICE).requires_grad_(True)
    tb = b.to(DEVICE).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, y: pair_potential(x, y), (ta, tb), atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradgradcheck(lambda x, y: pair_potential(x, y), (ta, tb), atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------------------------------------ meshes
def _mesh_poses() -> tuple[torch.Tensor, torch.Tensor]:
    """Three pose pairs of two 0.1 m balls: near contact (centres 0.201 m apart), mid range, far (3 m)."""
    pa = torch.zeros(3, 6, dtype=F64)
    pb = torch.tensor(
        [[0.201, 0.0, 0.0, 0.1, 0.2, 0.3], [0.0, 0.35, 0.1, 1.0, 0.0, -0.5], [3.0, 0.0, 0.0, 0.0, 0.0, 2.0]],
        dtype=F64,
    )
    return pa, pb


def test_mesh_potential_derivatives_and_autograd_match_cpu():
    bsh = BSH.from_trimesh(_icosphere())
    pa, pb = _mesh_poses()
    ref = mesh_potential_derivatives(bsh, pa, bsh, pb)
    dev = mesh_potential_derivatives(bsh, pa.to(DEVICE), bsh, pb.to(DEVICE))
    assert ref.grad.abs().max() > 0
    for name in ("value", "grad", "hessian"):
        r, d = getattr(ref, name), getattr(dev, name)
        scale = (
            r.reshape(len(r), -1).abs().amax(1).reshape(-1, *[1] * (r.dim() - 1))
        )  # near and far differ 1e6x
        _close(d / scale.to(DEVICE), r / scale, 1e-9, atol=1e-9, what=name)
    assert (
        dev.stats["leaf_pairs"] == ref.stats["leaf_pairs"]
        and dev.stats["node_pairs"] == ref.stats["node_pairs"]
    )
    qb = pb.to(DEVICE).requires_grad_(True)
    (g,) = torch.autograd.grad(mesh_potential(bsh, pa.to(DEVICE), bsh, qb).sum(), qb)
    _close(g, ref.grad[:, 6:], 1e-9, atol=1e-9 * float(ref.grad.abs().max()), what="autograd grad")


def test_mesh_potential_on_a_coarse_floor_and_float32():
    ball, floor = BSH.from_trimesh(_icosphere()), BSH.from_trimesh(_floor())
    pa = torch.zeros(2, 6, dtype=F64)
    pb = torch.tensor([[0.05, 0.0, 0.102, 0.3, 0.0, 0.0], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0]], dtype=F64)
    for dtype, rtol in ((F64, 1e-9), (torch.float32, 1e-5)):
        ref = mesh_potential(floor, pa.to(dtype), ball, pb.to(dtype))
        dev = mesh_potential(floor, pa.to(DEVICE, dtype), ball, pb.to(DEVICE, dtype))
        assert torch.isfinite(ref).all() and (ref > 0).all()
        _close(dev, ref, rtol, what=f"value {dtype}")


def test_contact_potential_of_a_scene_matches_cpu():
    bshes = [
        BSH.from_trimesh(_floor()),
        BSH.from_trimesh(_icosphere()),
        BSH.from_trimesh(_icosphere(1, 0.08)),
    ]
    poses = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.1015, 0.2, 0.1, 0.0],
            [0.185, 0.0, 0.0815, 0.0, 0.0, 1.0],
        ],
        dtype=F64,
    )
    kw = dict(static=[True, False, False], grad=True, hessian=True)
    ref = contact_potential(bshes, poses, **kw)
    dev = contact_potential(bshes, poses.to(DEVICE), **kw)
    assert ref.grad.abs().max() > 0
    _close(dev.value, ref.value, 1e-9, what="value")
    _close(dev.grad, ref.grad, 1e-9, atol=1e-9 * float(ref.grad.abs().max()), what="grad")
    _close(dev.hessian, ref.hessian, 1e-9, atol=1e-9 * float(ref.hessian.abs().max()), what="hessian")


# ------------------------------------------------------------------------------------------------ simulator
@pytest.fixture(scope="module")
def ball_scene():
    """A 320-face ball thrown along a floor with friction 0.5, and a second ball in its way."""
    floor = rigid_body(_floor(2.0), kind="static", max_edge=0.2)
    return Scene([floor, rigid_body(_icosphere()), rigid_body(_icosphere())], dt=0.01, friction=0.5)


def _start(scene: Scene, dev: torch.device, v: torch.Tensor) -> State:
    poses = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [-0.3, 0.0, 0.1012, 0.0, 0.0, 0.0],
            [0.0, 0.01, 0.1012, 0.0, 0.0, 0.0],
        ],
        dtype=F64,
        device=dev,
    )
    vel = torch.zeros(3, 6, dtype=F64, device=dev)
    vel = vel.index_put((torch.tensor([1], device=dev), torch.tensor([0], device=dev)), v.reshape(1))
    return scene.initial_state(poses, vel)


def test_rollout_and_its_gradient_match_cpu(ball_scene):
    res = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        v = torch.tensor(3.0, dtype=F64, device=dev, requires_grad=True)
        traj = rollout(ball_scene, _start(ball_scene, dev, v), 15)
        assert traj.q.device.type == dev.type
        loss = traj.q[-1, 2, 0] + traj.q[-1, 1, 1]
        (g,) = torch.autograd.grad(loss, v)
        res[key] = (traj.q.detach(), g)
    q_ref, g_ref = res["cpu"]
    assert q_ref[-1, 2, 0] > 0.02, "the thrown ball hit the other"
    assert g_ref.abs() > 1e-3
    _close(res["dev"][0], q_ref, 0.0, atol=1e-8, what="trajectory")
    _close(res["dev"][1], g_ref, 1e-6, what="rollout gradient")


def test_batched_float32_step_with_actions_and_params_matches_cpu(ball_scene):
    res = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        s = _start(ball_scene, dev, torch.tensor(2.0, dtype=F64, device=dev))
        shifted = s.q.clone()
        shifted[2, 1] += 0.01  # the second scene's ball 2 a centimetre aside
        s = State(
            torch.stack([s.q, shifted]).float(), torch.stack([s.q_prev, shifted - (s.q - s.q_prev)]).float()
        )
        force = torch.zeros(2, 3, 3, dtype=torch.float32, device=dev)
        force[:, 1, 0] = torch.tensor([5.0, -5.0], device=dev)
        params = ball_scene.params(dtype=torch.float32, device=dev)
        out, info = step(ball_scene, s, Action(force=force), params, return_info=True)
        assert out.q.dtype == torch.float32 and out.q.device.type == dev.type
        res[key] = out.q
    _close(res["dev"], res["cpu"], 0.0, atol=1e-6, what="batched float32 step")


def test_pair_forces_match_cpu(ball_scene):
    q = _start(ball_scene, CPU, torch.tensor(0.0, dtype=F64)).q
    q[2, :3] = torch.tensor([-0.0985, 0.0, 0.1012], dtype=F64)  # 1.5 mm from ball 1
    ref = pair_forces(ball_scene, q)
    dev = pair_forces(ball_scene, q.to(DEVICE))
    assert ref[1, 2].abs().max() > 0
    _close(dev, ref, 1e-9, atol=1e-9 * float(ref.abs().max()), what="pair forces")


@pytest.mark.parametrize("potential", ["ipc", "sdrs"])
def test_baseline_contact_models_step_like_cpu(ball_scene, potential):
    scene = ball_scene.replace(potential=potential)
    res = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        traj = rollout(scene, _start(scene, dev, torch.tensor(3.0, dtype=F64, device=dev)), 8)
        res[key] = traj.q
    _close(res["dev"], res["cpu"], 0.0, atol=1e-8, what=potential)


def test_articulated_robot_on_device_matches_cpu():
    import importlib.resources

    from cfd_torch import articulation

    hop = articulation(
        str(importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / "hopper.xml")
    )
    floor = rigid_body(_floor(3.0), kind="static")
    scene = Scene([floor], articulations=[hop], dt=0.01)
    th = torch.tensor(np.clip(hop.ref, hop.lower + 0.1, hop.upper - 0.1), dtype=F64)
    th[hop.joint_names.index("rootz")] += 0.05
    res = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        zero = torch.zeros(1, 6, dtype=F64, device=dev)
        q0 = torch.cat([zero, hop.poses(th.to(dev))])
        u = torch.tensor([0.3, -0.2, 0.4], dtype=F64, device=dev, requires_grad=True)
        traj = rollout(scene, State(q0, q0.clone()), [Action(ctrl=u)] * 12)
        (g,) = torch.autograd.grad(traj.q[-1, 1:, 2].sum(), u)
        res[key] = (traj.q.detach(), g)
    assert res["cpu"][1].abs().max() > 0
    _close(res["dev"][0], res["cpu"][0], 0.0, atol=1e-8, what="trajectory")
    _close(res["dev"][1], res["cpu"][1], 1e-6, atol=1e-9, what="control gradient")


# ------------------------------------------------------------------------------------------------ environments
@pytest.mark.parametrize(
    "env_id",
    ["cfd_torch/Billiards-v0", "cfd_torch/Push-v0", "cfd_torch/Sort-v0", "cfd_torch/Gather-v0",
     "cfd_torch/AntPush-v0"],
)  # fmt: skip
def test_task_core_rollout_and_gradient_match_cpu(env_id):
    from cfd_torch.envs import make_core
    from cfd_torch.envs import rollout as env_rollout

    res = {}
    for key, dev in (("cpu", CPU), ("dev", DEVICE)):
        core = make_core(env_id, device=dev, action_cost=0.0)  # the rewards' gradient all through the physics
        s0 = core.reset(seed=0, batch_size=2)
        U = torch.full((3, 2, core.action_dim), 0.3, dtype=F64, device=dev, requires_grad=True)
        out = env_rollout(core, s0, U)
        (g,) = torch.autograd.grad((out.rewards * out.alive).sum(), U)
        res[key] = (out.rewards.detach(), g, out.q.detach())
    g_ref = res["cpu"][1]
    assert g_ref.abs().max() > 0
    _close(res["dev"][2], res["cpu"][2], 0.0, atol=1e-8, what="states")
    _close(res["dev"][0], res["cpu"][0], 1e-7, atol=1e-9, what="rewards")
    _close(res["dev"][1], g_ref, 1e-5, atol=1e-6 * float(g_ref.abs().max()), what="gradient")


def test_gymnasium_env_on_device_returns_numpy_and_renders():
    import cfd_torch.envs  # noqa: F401  (registers the ids)

    env = gym.make("cfd_torch/Push-v0", device=DEVICE, render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    obs2, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert isinstance(obs2, np.ndarray) and obs2.shape == obs.shape and np.isfinite(obs2).all()
    assert isinstance(reward, float) and isinstance(terminated, bool)
    frame = env.render()
    assert frame.ndim == 3 and frame.std() > 0
    env.close()
    vec = gym.make_vec("cfd_torch/Billiards-v0", 2, device=DEVICE)
    obs, _ = vec.reset(seed=0)
    obs, rewards, *_ = vec.step(vec.action_space.sample())
    assert isinstance(obs, np.ndarray) and rewards.shape == (2,)
    vec.close()
