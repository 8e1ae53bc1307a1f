"""The Gymnasium environments (cfd_torch.envs): registration, Gymnasium's checker, seeding, the native vector env
against make_vec's sync one, reward terms, gradients from the trivial starts against finite differences, and the
rollout helper's truncated and checkpointed gradients."""

from __future__ import annotations

import dataclasses
import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import cfd_torch.envs as envs
from cfd_torch import RestGapWarning
from cfd_torch.envs import EnvState, make_core, rollout
from cfd_torch.envs.core import stack_states, task_at

F64 = torch.float64
AVAILABLE = ["cfd_torch/Billiards-v0", "cfd_torch/Push-v0", "cfd_torch/Sort-v0", "cfd_torch/Gather-v0"]


def test_every_task_is_registered_with_both_entry_points():
    for env_id in envs.IDS:
        spec = gym.spec(env_id)
        assert spec.entry_point.startswith("cfd_torch.envs.")
        assert spec.vector_entry_point.startswith("cfd_torch.envs.")
        assert spec.max_episode_steps > 0
    assert set(AVAILABLE) | {"cfd_torch/AntPush-v0"} == set(envs.IDS)


def test_unknown_id_is_refused():
    with pytest.raises(ValueError, match="unknown environment id"):
        make_core("cfd_torch/Nope-v0")


def test_ant_push_stands_and_observes():
    """The Ant at rest on the floor with zero action: two steps, its torso settles by less than 2 mm, the
    observation is finite and within the declared bounds, the box has not moved."""
    core = make_core("cfd_torch/AntPush-v0")
    s = core.reset(0, 1)
    z0 = float(s.q[0, 2, 2])
    for _ in range(2):
        out = core.step(s, torch.zeros(1, 8, dtype=F64))
        s = out.state
    low, high = core.observation_bounds()
    assert bool(((out.obs >= low) & (out.obs <= high)).all())
    assert abs(float(s.q[0, 2, 2]) - z0) < 2e-3
    assert float((s.q[0, 0, :2] - torch.tensor([1.0, 0.0], dtype=F64)).abs().max()) < 1e-4


def test_ant_push_position_actuation_follows_its_targets():
    """AntPush with actuation="position": a constant action of +0.5 drives every actuated joint from its stance
    to three quarters of its range (0.17-0.26 rad away; within 0.03 rad after 20 steps of the default servos, which
    then overshoot and settle), and the Gymnasium shell passes the option through."""
    core = make_core("cfd_torch/AntPush-v0", actuation="position")
    s = core.reset(0, 1)
    lo, hi = torch.as_tensor(core.ant.lower), torch.as_tensor(core.ant.upper)
    j0 = core.scene.kinematics.coords(s.q)[0, 12:]
    for _ in range(20):
        s = core.step(s, torch.full((1, 8), 0.5, dtype=F64)).state
    j = core.scene.kinematics.coords(s.q)[0, 12:]
    goal = lo + 0.75 * (hi - lo)
    assert float((j0 - goal).abs().min()) > 0.15
    assert float((j - goal).abs().max()) < 0.03
    with pytest.raises(ValueError, match="actuation must be 'torque' or 'position'"):
        make_core("cfd_torch/AntPush-v0", actuation="velocity")
    env = gym.make("cfd_torch/AntPush-v0", actuation="position").unwrapped
    assert env.core.actuation == "position"
    env.close()


@pytest.mark.slow
def test_gymnasium_check_env_ant_push():
    env = gym.make("cfd_torch/AntPush-v0").unwrapped
    check_env(env)
    env.close()


@pytest.mark.parametrize("env_id", AVAILABLE)
def test_gymnasium_check_env(env_id):
    env = gym.make(env_id).unwrapped
    check_env(env)
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float64 and env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs) and isinstance(reward, float)
    terms = [v for k, v in info.items() if k.startswith("reward_")]
    assert len(terms) >= 2 and reward == pytest.approx(sum(terms), rel=1e-12, abs=1e-15)
    assert info["newton_iters"] >= 1 and info["substeps"] >= 1
    env.close()


def test_observations_stay_within_the_declared_bounds_when_the_pusher_runs_away():
    """Sort's pusher driven straight at full speed leaves the floor behind (it hovers): its position passes 3 m (the
    floor's half width, the old bound of the positions, crossed at step 231 of 300 at dt = 0.01; Gather shares the
    scene) and every observation stays inside observation_bounds. dt = 0.02 gets there in half the steps."""
    core = make_core("cfd_torch/Sort-v0", dt=0.02)
    low, high = core.observation_bounds()
    s = core.reset(0, 1)
    far = 0.0
    for _ in range(160):
        out = core.step(s, torch.tensor([[0.0, 1.0]], dtype=F64))
        s = out.state
        assert bool(((out.obs >= low) & (out.obs <= high)).all())
        far = max(far, float(s.q[0, core.action_body, 1]))
    assert far > 3.1


def test_seeds_beyond_32_bits_do_not_alias_small_ones():
    """torch's generator keeps a seed's low 32 bits: the core hashes larger seeds first (the Gymnasium shells draw
    core seeds up to 2^62), so seed + 2^32 is another draw, and seeds below 2^32 keep their draws."""
    core = make_core("cfd_torch/Push-v0")
    a, b = core.reset(7), core.reset(7 + 2**32)
    assert float((a.q - b.q).abs().max()) > 1e-3
    pair = core.reset(2**32 - 1, batch_size=2)  # environment 1 has seed 2^32
    assert float((pair.q[1] - core.reset(0).q[0]).abs().max()) > 1e-3
    gen = torch.Generator().manual_seed(7)  # a small seed: torch's own draw, as before
    first = core._initial(gen)[0]
    torch.testing.assert_close(a.q[0], first, rtol=0.0, atol=0.0)


def test_seeding_is_deterministic_and_seeds_differ():
    a, b = gym.make("cfd_torch/Push-v0"), gym.make("cfd_torch/Push-v0")
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    oc, _ = b.reset(seed=8)
    np.testing.assert_array_equal(oa, ob)
    assert np.abs(oa - oc).max() > 1e-3
    b.reset(seed=7)
    for u in ([1.0, 0.0], [0.3, -1.0]):
        sa, ra, *_ = a.step(np.array(u, dtype=np.float32))
        sb, rb, *_ = b.step(np.array(u, dtype=np.float32))
        np.testing.assert_array_equal(sa, sb)
        assert ra == rb


def test_native_vector_env_equals_make_vec_sync_bit_for_bit():
    """Two Push environments truncated after 3 steps, stepped 5 times (one NEXT_STEP autoreset): observations,
    rewards, terminations and truncations identical."""
    sync = gym.make_vec("cfd_torch/Push-v0", 2, vectorization_mode="sync", max_episode_steps=3)
    native = gym.make_vec(
        "cfd_torch/Push-v0", 2, vectorization_mode="vector_entry_point", max_episode_steps=3
    )
    assert type(native).__name__ == "PushVectorEnv"
    o1, _ = sync.reset(seed=3)
    o2, _ = native.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(0)
    truncations = 0
    for _ in range(5):
        act = rng.uniform(-1, 1, (2, 2)).astype(np.float32)
        r1 = sync.step(act)
        r2 = native.step(act)
        for x, y in zip(r1[:4], r2[:4], strict=True):
            np.testing.assert_array_equal(x, y)
        assert r1[4].keys() == r2[4].keys()
        for key in r1[4]:  # the info arrays too, dtypes included (integers stay integers)
            assert r1[4][key].dtype == r2[4][key].dtype, key
            np.testing.assert_array_equal(r1[4][key], r2[4][key])
        truncations += int(r1[3].sum())
    assert truncations == 2  # both environments truncated once and were reset
    sync.close()
    native.close()


def test_batched_vector_env_agrees_with_the_one_by_one_steps():
    one = gym.make_vec("cfd_torch/Sort-v0", 3, max_episode_steps=4)
    batch = gym.make_vec("cfd_torch/Sort-v0", 3, max_episode_steps=4, batched=True)
    o1, _ = one.reset(seed=11)
    o2, _ = batch.reset(seed=11)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    for _ in range(5):  # crosses one truncation and autoreset
        act = rng.uniform(-1, 1, (3, 2)).astype(np.float32)
        r1, r2 = one.step(act), batch.step(act)
        np.testing.assert_allclose(r2[0], r1[0], rtol=0, atol=1e-10)
        np.testing.assert_allclose(r2[1], r1[1], rtol=0, atol=1e-10)
        for x, y in zip(r1[2:4], r2[2:4], strict=True):
            np.testing.assert_array_equal(x, y)


def _loss(core, s0: EnvState, U: torch.Tensor) -> torch.Tensor:
    """The task loss of an open-loop rollout: minus the last step's distance reward term, summed over the batch."""
    out = rollout(core, s0, U)
    return -out.info["reward_distance"][-1].sum()


def _first_action_gradient(core, h: float) -> tuple[torch.Tensor, torch.Tensor]:
    """From seed 3's initial state with 3 zero actions: the gradient of ``_loss`` with respect to the first action
    (A,) by autograd and by central differences of step ``h``."""
    s0 = core.reset(3, 1)
    U = torch.zeros(3, 1, core.action_dim, dtype=F64, requires_grad=True)
    _loss(core, s0, U).backward()
    g = U.grad[0, 0]
    fd = torch.zeros_like(g)
    with torch.no_grad():
        for a in range(core.action_dim):
            dU = torch.zeros_like(U)
            dU[0, 0, a] = h
            fd[a] = (_loss(core, s0, U + dU) - _loss(core, s0, U - dU)) / (2 * h)
    return g, fd


@pytest.mark.parametrize(
    ("env_id", "kwargs", "h"),
    [
        ("cfd_torch/Billiards-v0", {"target_ball": 0, "pocket": 0}, 1e-2),
        ("cfd_torch/Push-v0", {}, 1e-3),
        # (the pusher and the cubes 0.2-0.5 m apart, inside their wide blend band: the loss is linear to 0.1 % at
        # h = 1e-2, to 15 % at 0.1)
        ("cfd_torch/Sort-v0", {}, 1e-2),
        ("cfd_torch/Gather-v0", {}, 1e-2),
    ],
)
def test_gradient_from_the_trivial_start_is_nonzero_and_matches_finite_differences(env_id, kwargs, h):
    """Zero actions from the initial state: nothing touches, yet the task loss after 3 steps depends on the first
    action through the contact model's far field (a locally supported model gives exactly zero here)."""
    g, fd = _first_action_gradient(make_core(env_id, **kwargs), h)
    assert bool((g.abs() > 0).all())
    torch.testing.assert_close(g, fd, rtol=2e-2, atol=0)


def test_ant_push_gradient_from_the_trivial_start_matches_finite_differences():
    """AntPush from its trivial start (the Ant standing 1 m from the box): the box's distance after 3 steps depends
    on the first step's 8 motor controls through the far field, and the gradient matches central differences at
    h = 1e-4 (the feet's contacts curve the loss: at h = 1e-3 a component is 10 % off, at 1e-2 signs flip).
    Components below 1e-9 are compared absolutely: central differences resolve 2 ulp / (2 h) = 2e-11 of a 2 m
    distance."""
    g, fd = _first_action_gradient(make_core("cfd_torch/AntPush-v0"), 1e-4)
    assert float(g.abs().max()) > 1e-8
    torch.testing.assert_close(g, fd, rtol=1e-2, atol=5e-11)


@pytest.mark.parametrize(
    ("env_id", "kwargs", "potential"),
    [
        ("cfd_torch/Push-v0", {}, "ipc"),
        ("cfd_torch/Push-v0", {}, "sdrs"),
        *(
            (env_id, kwargs, potential)
            for env_id, kwargs in [
                ("cfd_torch/Billiards-v0", {"target_ball": 0, "pocket": 0}),
                ("cfd_torch/Sort-v0", {}),
                ("cfd_torch/Gather-v0", {}),
                ("cfd_torch/AntPush-v0", {}),
            ]
            for potential in ("ipc", "sdrs")
        ),
    ],
)
def test_locally_supported_models_give_no_gradient_from_the_trivial_start(env_id, kwargs, potential):
    """The test above with the baselines' contact (``potential="ipc"`` or ``"sdrs"``, dhat 1 cm; Billiards 1 mm):
    the task loss after 3 steps does not depend on the first action at all, its gradient is exactly zero (the boxes,
    and the Ant's feet, resting within dhat of the floor have active contacts, so the models do act)."""
    from cfd_torch.sim.energy import scene_pairs

    core = make_core(env_id, potential=potential, **kwargs)
    s0 = core.reset(3, 1)
    active = float(core.scene.contact_model.evaluate(s0.q, scene_pairs(core.scene, 1), 0).value.sum())
    if "Billiards" in env_id:
        assert active == 0.0  # the rack's gaps (4.5 mm) are wider than Billiards' barrier dhat (1 mm)
    else:
        assert active > 0  # bodies within dhat of each other: the boxes on the floor
    U = torch.zeros(3, 1, core.action_dim, dtype=F64, requires_grad=True)
    loss = _loss(core, s0, U)
    (g,) = torch.autograd.grad(loss, U)
    assert torch.isfinite(loss) and float(g.abs().max()) == 0.0


def test_billiards_rack_rests_under_the_baselines():
    """Billiards with IPC's barrier: its dhat (1 mm) is under the rack's gaps, so with the cue ball driven toward
    the rack the rack's balls do not move in 5 steps (with the models' 1 cm the barrier spans the 4.5 mm gaps and
    the first step blows the rack apart); the cue ball does move."""
    core = make_core("cfd_torch/Billiards-v0", potential="ipc", target_ball=14, pocket=1)
    assert core.scene.contact.dhat == 1e-3
    s = core.reset(2, 1)
    q0 = s.q.clone()
    a = torch.tensor([[0.0, 1.0]], dtype=F64)
    for _ in range(5):
        s = core.step(s, a).state
    assert float((s.q[0, 15, :2] - q0[0, 15, :2]).norm()) > 1e-3
    assert float((s.q[0, :15] - q0[0, :15]).abs().max()) == 0.0


def test_rollout_checkpointed_and_truncated_gradients():
    """Push, 4 steps of a closed-loop linear policy: checkpointing chunks of 2 steps gives the plain gradients; cutting
    the graph every 2 steps keeps a window's own gradients and zeroes those across the cut."""
    core = make_core("cfd_torch/Push-v0")
    s0 = core.reset(1, 2)
    W = torch.zeros(core.action_dim, core.obs_dim, dtype=F64, requires_grad=True)
    b = torch.tensor([0.2, 0.9], dtype=F64, requires_grad=True)

    def policy(obs, t):
        return torch.tanh(obs @ W.T * 1e-2 + b)

    def grads(**kw):
        out = rollout(core, s0, policy, 4, **kw)
        (gW, gb) = torch.autograd.grad(-out.rewards.sum(), (W, b))
        return out, gW, gb

    plain, gW, gb = grads()
    ckpt, cW, cb = grads(checkpoint_every=2)
    assert float(gb.abs().max()) > 0
    torch.testing.assert_close(ckpt.obs, plain.obs, rtol=0, atol=0)
    torch.testing.assert_close(cW, gW, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(cb, gb, rtol=1e-10, atol=1e-14)

    U = torch.zeros(4, 2, core.action_dim, dtype=F64)
    U[:, :, 1] = 0.5
    U.requires_grad_(True)
    full = rollout(core, s0, U)
    cut = rollout(core, s0, U, truncate_every=2)
    torch.testing.assert_close(cut.obs, full.obs, rtol=0, atol=0)
    g_full = torch.autograd.grad(cut.rewards[3].sum(), U)[0]  # within the window [2, 4): U[2], U[3] only
    g_ref = torch.autograd.grad(full.rewards[3].sum(), U)[0]
    assert float(g_full[:2].abs().max()) == 0.0 and float(g_ref[:2].abs().max()) > 0
    torch.testing.assert_close(g_full[2:], g_ref[2:], rtol=1e-6, atol=1e-15)

    # the cut is the poses': a goal's gradient sums every window's (open loop: the motion does not depend on it)
    target = s0.task["target"].clone().requires_grad_(True)
    s_goal = EnvState(s0.q, s0.q_prev, s0.t, {**s0.task, "target": target})
    g_cut = torch.autograd.grad(rollout(core, s_goal, U, truncate_every=2).rewards.sum(), target)[0]
    g_goal = torch.autograd.grad(rollout(core, s_goal, U).rewards.sum(), target)[0]
    assert float(g_goal.abs().min()) > 0
    torch.testing.assert_close(g_cut, g_goal, rtol=1e-12, atol=0)


def test_checkpointed_rollout_refuses_a_policy_with_hidden_state():
    """A policy that keeps state between calls returns other actions when a checkpointed chunk is recomputed in the
    backward: refused there (its gradients would be wrong), not silently differentiated."""
    core = make_core("cfd_torch/Push-v0")
    s0 = core.reset(1, 1)
    b = torch.tensor([0.2, 0.9], dtype=F64, requires_grad=True)
    calls = []

    def stateful(obs, t):
        calls.append(t)
        return torch.tanh(b + 1e-3 * len(calls))

    out = rollout(core, s0, stateful, 4, checkpoint_every=2)
    with pytest.raises(
        RuntimeError, match=r"policy\(obs, 2\) returned other actions when rollout\(checkpoint_every"
    ):
        out.rewards.sum().backward()
    calls.clear()
    # fine without checkpoints
    plain = torch.autograd.grad(rollout(core, s0, stateful, 4).rewards.sum(), b)[0]
    assert float(plain.abs().max()) > 0


def test_core_checks_its_inputs():
    core = make_core("cfd_torch/Push-v0")
    s = core.reset(0, 2)
    with pytest.raises(ValueError, match=r"action must have shape \(2, 2\)"):
        core.step(s, torch.zeros(1, 2, dtype=F64))
    with pytest.raises(ValueError, match="action contains NaN"):
        core.step(s, torch.full((2, 2), float("nan"), dtype=F64))
    with pytest.raises(TypeError, match="state must be an EnvState"):
        core.step(s.sim, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(ValueError, match="horizon 5 exceeds the 3 actions"):
        rollout(core, s, torch.zeros(3, 2, 2, dtype=F64), 5)
    # the start state is checked before its observation reads it (a Push state in a Billiards rollout failed as
    # "shape '[2, 32]' is invalid", an out-of-range ball as an IndexError; a NaN state gave NaN observations)
    billiards = make_core("cfd_torch/Billiards-v0")
    with pytest.raises(ValueError, match=r"state.q must be a \(B, 16, 6\) tensor"):
        rollout(billiards, s, torch.zeros(1, 2, 2, dtype=F64))
    with pytest.raises(ValueError, match=r"state.q contains NaN or inf \(environment 0\)"):
        rollout(core, dataclasses.replace(s, q=s.q * float("nan")), torch.zeros(0, 2, 2, dtype=F64))
    with pytest.raises(ValueError, match="horizon must be an int >= 0 or None, got '1'"):
        rollout(core, s, torch.zeros(3, 2, 2, dtype=F64), "1")
    with pytest.raises(TypeError, match="core must be a task core"):
        rollout("core", s, torch.zeros(3, 2, 2, dtype=F64))
    s32 = make_core("cfd_torch/Push-v0", dtype=torch.float32).reset([4, 5])
    assert s32.q.dtype == torch.float32 and s32.batch_size == 2
    # seeds: NumPy integers are ints; strings, floats and bool batch sizes are refused
    torch.testing.assert_close(core.reset(np.int64(3)).q, core.reset(3).q, rtol=0, atol=0)
    torch.testing.assert_close(core.reset(np.array([3, 4])).q, core.reset(3, 2).q, rtol=0, atol=0)
    with pytest.raises(TypeError, match="seed must be an int"):
        core.reset("12")
    with pytest.raises(TypeError, match="every entry of a sequence of seeds must be an int"):
        core.reset([1.7, 2.2])
    with pytest.raises(ValueError, match="batch_size must be a positive int"):
        core.reset(0, batch_size=True)
    # select: an int keeps the batch dimension, negative ints count from the end, others are refused
    s3 = core.reset(0, 3)
    torch.testing.assert_close(s3.select(-1).q, s3.q[2:], rtol=0, atol=0)
    with pytest.raises(IndexError, match="index 3 is out of range for a batch of 3"):
        s3.select(3)
    torch.testing.assert_close(s3.select(torch.tensor(1)).q, s3.q[1:2], rtol=0, atol=0)
    with pytest.raises(TypeError, match="index must be an int, a slice or an index tensor"):
        s3.select(True)
    # index tensors: floats and indices out of range were torch's IndexErrors, naming nothing
    torch.testing.assert_close(s3.select(torch.tensor([2, -3])).q, s3.q[[2, 0]], rtol=0, atol=0)
    with pytest.raises(TypeError, match="got a torch.float32 tensor"):
        s3.select(torch.tensor([0.0]))
    with pytest.raises(IndexError, match="index 5 is out of range for a batch of 3 environments"):
        s3.select(torch.tensor([1, 5]))
    # seeds as 0-d tensors or arrays are ints; a bool batch size is refused with a sequence too
    torch.testing.assert_close(core.reset([torch.tensor(3)]).q, core.reset(3).q, rtol=0, atol=0)
    torch.testing.assert_close(core.reset(np.array(3)).q, core.reset(3).q, rtol=0, atol=0)
    with pytest.raises(ValueError, match="batch_size must be a positive int"):
        core.reset([3], batch_size=True)
    with pytest.raises(ValueError, match="truncate_every must be a positive int"):
        rollout(core, s, torch.zeros(3, 2, 2, dtype=F64), 2, truncate_every=True)
    # a rollout of no steps: the start only
    out = rollout(core, s, torch.zeros(3, 2, 2, dtype=F64), 0)
    assert out.q.shape == (1, 2, 3, 6) and out.rewards.shape == (0, 2) and out.obs.shape[0] == 1
    # a policy that returns something else than a (B, A) or (A,) tensor is named with its step
    with pytest.raises(TypeError, match=r"policy\(obs, 0\) must return a torch tensor"):
        rollout(core, s, lambda o, t: np.zeros((2, 2)), 2)
    with pytest.raises(ValueError, match=r"policy\(obs, 1\) must return actions of shape \(2, 2\) or \(2,\)"):
        rollout(core, s, lambda o, t: torch.zeros(2 if t == 0 else 1, 2, dtype=F64), 2)
    with pytest.raises(ValueError, match=r"policy\(obs, 1\) returned actions with NaN or inf"):
        rollout(core, s, lambda o, t: torch.full((2,), 0.0 if t == 0 else float("nan"), dtype=F64), 2)
    # torch.func's transforms cannot pass a simulator step: refused with the way out
    with pytest.raises(
        NotImplementedError, match="torch.func transforms .* do not pass through a simulation step"
    ):
        torch.func.grad(lambda a: core.step(s, a).reward.sum())(torch.zeros(2, 2, dtype=F64))


def test_shells_check_action_shapes_before_stepping():
    """The Gymnasium shells take actions of exactly their space's shape (a (2, 4) batch for 4 environments of 2
    actions is not reshaped into (4, 2)); a non-finite action is refused before any environment steps."""
    env = gym.make("cfd_torch/Push-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(2,\), got \(2, 1\)"):
        env.step(np.zeros((2, 1)))
    vec = gym.make_vec("cfd_torch/Push-v0", 4)
    vec.reset(seed=0)
    for bad in (np.zeros((2, 4)), np.zeros(8)):
        with pytest.raises(ValueError, match=r"actions must have shape \(4, 2\)"):
            vec.step(bad)
    before = [st.q.clone() for st in vec.unwrapped.states]
    act = np.zeros((4, 2))
    act[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"non-finite entries for environments \[2\]"):
        vec.step(act)
    for st, q in zip(vec.unwrapped.states, before, strict=True):
        torch.testing.assert_close(st.q, q, rtol=0, atol=0)  # nothing stepped
    with pytest.raises(ValueError, match="num_envs must be a positive int"):
        gym.make_vec("cfd_torch/Push-v0", True, vectorization_mode="vector_entry_point")
    with pytest.raises(TypeError, match="batched must be a bool, got 'no'"):  # (it read as True)
        gym.make_vec("cfd_torch/Push-v0", 2, vectorization_mode="vector_entry_point", batched="no")
    vec.close()


def test_a_seeded_reset_starts_the_cores_episode_of_that_seed():
    """gym.make's reset(seed=s), make_vec's copy i under seed s and core.reset(s, B)'s environment i are one start
    (debug in one face, optimise the same episode in another); later unseeded resets draw other starts."""
    core = make_core("cfd_torch/Sort-v0", num_cubes=2)
    states = core.reset(5, batch_size=2)
    env = gym.make("cfd_torch/Sort-v0", num_cubes=2)
    obs, _ = env.reset(seed=5)
    np.testing.assert_array_equal(obs, core.observe(states)[0].numpy())
    assert torch.equal(env.unwrapped.state.q, states.q[:1])
    assert not np.array_equal(env.reset()[0], obs)
    env.close()
    vec = gym.make_vec("cfd_torch/Sort-v0", 2, num_cubes=2)
    np.testing.assert_array_equal(vec.reset(seed=5)[0], core.observe(states).numpy())
    vec.close()


def test_native_vector_env_step_is_all_or_nothing_and_seeds_like_sync(monkeypatch):
    """A step in which one environment's solve fails leaves every environment as it was (no environment stepped
    twice on a retry); reset takes NumPy integer seeds and np_random_seed reports them as SyncVectorEnv does."""
    from cfd_torch import StepError

    vec = gym.make_vec("cfd_torch/Push-v0", 3, vectorization_mode="vector_entry_point").unwrapped
    sync = gym.make_vec("cfd_torch/Push-v0", 3, vectorization_mode="sync")
    # before a seeded reset: the entropy seeds the generators were built from (as sync's; -1 was reported)
    assert (
        all(isinstance(s, int) and s >= 0 for s in vec.np_random_seed) and len(set(vec.np_random_seed)) == 3
    )
    obs, _ = vec.reset(seed=np.int64(3))
    obs_sync, _ = sync.reset(seed=3)
    np.testing.assert_array_equal(obs, obs_sync)
    assert vec.np_random_seed == tuple(sync.np_random_seed) == (3, 4, 5)
    # np_random is the environments' generators, as sync's (it was VectorEnv's own, seeded from entropy, unused)
    assert len(vec.np_random) == 3
    for mine, theirs in zip(vec.np_random, sync.np_random, strict=True):
        assert mine.bit_generator.state == theirs.bit_generator.state
    obs, _ = vec.reset()
    np.testing.assert_array_equal(obs, sync.reset()[0])  # unseeded resets drawn from those generators
    with pytest.raises(TypeError, match="seed must be None, an int or a sequence of ints"):
        vec.reset(seed=2.5)
    vec.reset(seed=3)
    act = np.full((3, 2), 0.5)
    vec.step(act)
    before = [(int(st.t[0]), st.q.clone()) for st in vec.states]
    obs_before = vec._obs.copy()
    step, calls = vec.core.step, []

    def fails_second(state, action, params=None):
        calls.append(1)
        if len(calls) == 2:
            raise StepError("injected")
        return step(state, action, params)

    monkeypatch.setattr(vec.core, "step", fails_second)
    with pytest.raises(StepError, match="injected"):
        vec.step(act)
    assert len(calls) == 2  # the first environment did step, and was not kept
    for st, (t, q) in zip(vec.states, before, strict=True):
        assert int(st.t[0]) == t
        torch.testing.assert_close(st.q, q, rtol=0, atol=0)
    np.testing.assert_array_equal(vec._obs, obs_before)
    monkeypatch.setattr(vec.core, "step", step)
    vec.step(act)
    assert [int(st.t[0]) for st in vec.states] == [t + 1 for t, _ in before]
    vec.close()
    sync.close()


def test_task_arguments_actions_and_states_are_checked():
    """Bad task arguments, render sizes, actions (complex, bool, text, overflowing) and states of another dtype are
    refused naming the argument; a step's state does not share its task dict with its parent; a rollout of no
    steps has a step's info keys."""
    for env_id, kwargs, name in [
        ("cfd_torch/Push-v0", {"distance": -3.0}, "distance"),
        ("cfd_torch/Push-v0", {"action_cost": -1.0}, "action_cost"),
        ("cfd_torch/Push-v0", {"max_speed": 0.0}, "max_speed"),
        ("cfd_torch/Push-v0", {"angle_range": -0.1}, "angle_range"),
        ("cfd_torch/Billiards-v0", {"pocket_radius": -0.08}, "pocket_radius"),
        ("cfd_torch/Sort-v0", {"action_cost": float("nan")}, "action_cost"),
        ("cfd_torch/AntPush-v0", {"success_radius": 0.0}, "success_radius"),
        ("cfd_torch/Billiards-v0", {"subdivisions": -3}, "subdivisions"),
        ("cfd_torch/Billiards-v0", {"subdivisions": 1.7}, "subdivisions"),
        ("cfd_torch/Billiards-v0", {"eps": -1.0}, "eps"),
        ("cfd_torch/Gather-v0", {"eps": 0.0}, "eps"),
        ("cfd_torch/Billiards-v0", {"potential": "ipc", "dhat": float("nan")}, "dhat"),
    ]:
        with pytest.raises(ValueError, match=f"^{name} must be"):  # (named as the task's argument)
            make_core(env_id, **kwargs)
    # a setting the chosen potential does not read (it was silently ignored)
    with pytest.raises(
        ValueError, match="eps is read only by potential='cfd'; potential='ipc' does not use it"
    ):
        make_core("cfd_torch/Push-v0", potential="ipc", eps=0.5)
    with pytest.raises(
        ValueError, match="dhat is read only by the baselines .* potential='cfd' does not use it"
    ):
        make_core("cfd_torch/Billiards-v0", dhat=0.01)
    with pytest.raises(ValueError, match="width must be a positive int"):
        gym.make("cfd_torch/Push-v0", width=0)
    with pytest.raises(ValueError, match="height must be a positive int"):
        gym.make_vec("cfd_torch/Push-v0", 2, vectorization_mode="vector_entry_point", height=64.5)

    core = make_core("cfd_torch/Push-v0")
    s0 = core.reset(0, 2)
    with pytest.raises(TypeError, match="action must be a tensor of real numbers"):
        core.step(s0, torch.zeros(2, 2, dtype=torch.complex128))
    with pytest.raises(TypeError, match="action must be a tensor of real numbers"):
        core.step(s0, torch.zeros(2, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"action: \|a\|\^2 overflows"):
        core.step(s0, torch.full((2, 2), 1e160, dtype=F64))
    # a large action_cost made the reward -inf (float32: even at actions in [-1, 1])
    big = make_core("cfd_torch/Push-v0", action_cost=1e300, dtype=torch.float32)
    with pytest.raises(
        ValueError, match=r"the reward's action_cost \|a\|\^2 overflows torch.float32 \(action_cost 1e\+300"
    ):
        big.step(big.reset(0, 2), torch.ones(2, 2))
    with pytest.raises(TypeError, match="state.q is torch.float32 on cpu but this core is torch.float64"):
        core.step(make_core("cfd_torch/Push-v0", dtype=torch.float32).reset(0, 2), torch.zeros(2, 2))
    # every field of the state is checked, not only q: a float64 goal in a float32 core made the observations and
    # rewards float64; a float64 q_prev, a wrong batch size or a NaN goal failed inside torch, or passed
    core32 = make_core("cfd_torch/Push-v0", dtype=torch.float32)
    s32 = core32.reset(0, 2)
    for change, err, match in (
        (
            {"task": {"target": s32.task["target"].double()}},
            TypeError,
            r"state.task\['target'\] is torch.float64",
        ),
        ({"q_prev": s32.q_prev.double()}, TypeError, "state.q_prev is torch.float64 on cpu but this core is"),
        (
            {"task": {"target": s32.task["target"][:1]}},
            ValueError,
            r"state.task\['target'\] must have the batch",
        ),
        (
            {"t": torch.zeros(3, dtype=torch.long)},
            ValueError,
            r"state.t must be an int64 tensor of shape \(2,\)",
        ),
        ({"task": {"target": s32.task["target"] * float("nan")}}, ValueError, r"\['target'\] contains NaN"),
        # a goal beyond the coordinate limit made the reward -inf (its squared distance overflowed)
        (
            {"task": {"target": s32.task["target"] * torch.tensor([[1.0], [1e13]])}},
            ValueError,
            r"state.task\['target'\] holds a coordinate beyond 1e\+12 m \(environment 1\)",
        ),
        # an integer pose failed inside the pusher's action code (torch's "expected m1 and m2 to have the same
        # dtype"); a negative step count passed
        ({"q": s32.q.long()}, TypeError, "state.q is torch.int64 on cpu but this core is torch.float32"),
        ({"q": s32.q.bool()}, TypeError, "state.q is torch.bool on cpu but this core is torch.float32"),
        (
            {"t": torch.tensor([0, -4])},
            ValueError,
            r"state.t counts steps: it must be >= 0, got -4 \(environment 1\)",
        ),
        (
            {"q": s32.q[0], "q_prev": s32.q_prev[0]},
            ValueError,
            r"state.q must be a \(B, 3, 6\) tensor, got shape \(3, 6\)",
        ),
        (
            {"q": s32.q[:, :2], "q_prev": s32.q_prev[:, :2]},
            ValueError,
            r"state.q must be a \(B, 3, 6\) tensor",
        ),
    ):
        with pytest.raises(err, match=match):
            core32.step(dataclasses.replace(s32, **change), torch.zeros(2, 2))
    with pytest.raises(
        ValueError, match=r"state.task\['target'\] holds a coordinate beyond 1e\+30 m \(environment 0"
    ):
        core.step(
            dataclasses.replace(s0, task={"target": s0.task["target"] + 1e160}), torch.zeros(2, 2, dtype=F64)
        )
    with pytest.raises(ValueError, match=r"overflows torch.float32 \(largest \|a_i\| 1e\+39\)"):
        core32.step(s32, np.full((2, 2), 1e39))  # (a non-tensor was cast first, and called NaN or inf)
    with warnings.catch_warnings():  # an action that requires grad is checked quietly (torch warned)
        warnings.simplefilter("error")
        core.step(s0, torch.zeros(2, 2, dtype=F64, requires_grad=True))
    s1 = core.step(s0, torch.zeros(2, 2, dtype=F64)).state
    assert s1.task is not s0.task and s1.task.keys() == s0.task.keys()
    s1.task["target"] = s1.task["target"] + 1.0
    assert float((s1.task["target"] - s0.task["target"]).abs().min()) == 1.0  # the parent's goal unchanged

    env = gym.make("cfd_torch/Push-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(TypeError, match="action must be an array of real numbers, got dtype complex128"):
        env.step(np.array([0.5 + 1j, 0.0]))
    with pytest.raises(TypeError, match="action requires grad, but this takes plain arrays"):
        env.step(torch.zeros(2, dtype=F64, requires_grad=True))  # (torch's "Can't call numpy()")
    with pytest.raises(TypeError, match="action must be an array of real numbers"):
        env.step(["a", "b"])

    one = rollout(core, s0, torch.zeros(1, 2, 2, dtype=F64))
    none = rollout(core, s0, torch.zeros(1, 2, 2, dtype=F64), 0)
    assert none.info.keys() == one.info.keys() and len(one.info) > 2
    for k, v in none.info.items():
        assert v.shape == (0, 2) and v.dtype == one.info[k].dtype, k


@pytest.mark.parametrize(
    "env_id, kwargs",
    [("cfd_torch/Gather-v0", {"region_distance": 5.0}), ("cfd_torch/Sort-v0", {"region_offset": 4.0})],
)
def test_observation_bounds_follow_the_task_arguments(env_id, kwargs):
    """The goal part of Sort's and Gather's observation (the regions' centres) stays inside its bound for regions
    farther out than the defaults."""
    core = make_core(env_id, **kwargs)
    low, high = core.observation_bounds()
    obs = core.observe(core.reset(0, 4))
    assert float(obs.abs().max()) > 3.0  # the old fixed bound of the goal part
    assert bool(((obs >= low) & (obs <= high)).all())


@pytest.mark.parametrize("env_id, task_obs", [("cfd_torch/Gather-v0", 2), ("cfd_torch/Sort-v0", 7)])
def test_cube_tasks_take_a_number_of_cubes(env_id, task_obs):
    """Sort and Gather with three cubes: three cube bodies, the pusher after them (the action drives it), an
    observation of the cubes, the pusher and the task's part sized for three, inside the declared space, and a reward
    over the three cubes; a count that is not a positive int is refused, naming it."""
    env = gym.make(env_id, num_cubes=3).unwrapped
    core = env.core
    assert core.num_cubes == 3 and core.action_body == 3 and core.scene.num_bodies == 5
    assert core.obs_dim == 4 * 4 + task_obs and env.observation_space.shape == (core.obs_dim,)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    s = core.reset(0)
    out = core.step(s, torch.tensor([[1.0, 0.0]], dtype=F64))
    moved = out.state.q[0, :, :2] - s.q[0, :, :2]  # the pusher moves, not the cubes
    assert float(moved[3, 0]) > 1e-3 and float(moved[:3].abs().max()) < 1e-3
    assert core.outside(out.state).shape == (1, 3)
    assert float(out.info["reward_distance"][0]) == pytest.approx(
        -float(core.outside(out.state).mean()), rel=1e-12
    )
    for bad in (0, 2.0, True):
        with pytest.raises(ValueError, match="num_cubes must be an int >= 1"):
            make_core(env_id, num_cubes=bad)


def test_rendered_frames_show_the_scene_and_change_when_it_moves():
    env = gym.make("cfd_torch/Push-v0", render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (120, 160, 3) and first.dtype == np.uint8
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 10
    for _ in range(10):
        env.step(np.array([1.0, 0.0], dtype=np.float32))
    later = env.render()
    assert np.abs(later.astype(int) - first.astype(int)).sum(2).astype(bool).sum() > 20
    env.close()


def test_sort_frames_show_classes_and_regions():
    core = make_core("cfd_torch/Sort-v0")
    state = core.reset(0, 1)
    goal = task_at(state, 0)
    r = core.renderer(200, 200)
    try:
        img = core.draw(r, state.q[0], goal).astype(int)
        red = (img[..., 0] > img[..., 1] + 80) & (img[..., 0] > img[..., 2] + 80)  # class 0 cubes and region
        yellow = (img[..., 0] > img[..., 2] + 80) & (img[..., 1] > img[..., 2] + 80)  # class 1
        assert red.sum() > 100 and yellow.sum() > 100, (red.sum(), yellow.sum())  # observed 178, 173
        moved = dict(goal, centres=goal["centres"].flip(0))  # the two regions swap places
        other = core.draw(r, state.q[0], moved).astype(int)
        assert np.abs(other - img).sum(2).astype(bool).sum() > 500
    finally:
        r.close()


@pytest.mark.parametrize("env_id", envs.IDS)
def test_every_task_renders_its_goal_where_the_task_puts_it(env_id):
    """``env.render()`` gives a (height, width, 3) uint8 frame; shifting every float task variable (targets, region
    centres, the pocket) by 0.3 m in x and y changes it: the goal markers are drawn from ``state.task``."""
    env = gym.make(env_id, render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (120, 160, 3) and first.dtype == np.uint8
    s = env.unwrapped.state
    moved = {k: v + 0.3 if v.is_floating_point() else v for k, v in s.task.items()}
    env.unwrapped.state = EnvState(s.q, s.q_prev, s.t, moved)
    other = env.render()
    assert np.abs(other.astype(int) - first.astype(int)).sum(2).astype(bool).sum() > 20  # observed 37-1331
    env.close()


def test_vector_env_renders_one_frame_per_environment():
    env = gym.make_vec(
        "cfd_torch/Gather-v0",
        2,
        vectorization_mode="vector_entry_point",
        render_mode="rgb_array",
        width=64,
        height=48,
    )
    env.reset(seed=0)
    frames = env.render()
    assert len(frames) == 2 and all(f.shape == (48, 64, 3) and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[1])  # regions and cubes drawn per environment
    env.close()


def test_billiards_observes_which_ball_is_the_object_ball():
    """The object ball is drawn per reset and the reward is its distance to the pocket: the observation carries
    its position and velocity (the same rack with another object ball observes differently)."""
    env = gym.make("cfd_torch/Billiards-v0")
    obs, _ = env.reset(seed=0)
    st, core = env.unwrapped.state, env.unwrapped.core
    k = int(st.task["target"][0])
    assert obs.shape == (70,) and env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs[66:68], obs[2 * k : 2 * k + 2])  # the object ball's xy
    np.testing.assert_array_equal(obs[68:70], obs[32 + 2 * k : 32 + 2 * k + 2])  # its velocity
    other = EnvState(st.q, st.q_prev, st.t, {**st.task, "target": (st.task["target"] + 1) % 15})
    assert not torch.equal(core.observe(st), core.observe(other))
    env.close()


def test_cube_layouts_that_cannot_be_scattered_are_refused_at_construction():
    """Rejection sampling of the cubes' and pusher's footprints used to loop for ever in reset() when they could
    not fit in the spread; now a ValueError names the arguments, when the environment is made."""
    for kwargs in ({"spread": 0.2}, {"cube_size": 0.5}, {"num_cubes": 40, "spread": 0.5}):
        with pytest.raises(ValueError, match=r"spread .* m is too small to scatter num_cubes = \d+ cubes"):
            gym.make("cfd_torch/Gather-v0", **kwargs)
    for name in ("spread", "cube_size"):
        with pytest.raises(ValueError, match=f"{name} must be a finite positive number"):
            make_core("cfd_torch/Sort-v0", **{name: 0.0})
    # far too many to fit: refused before a scene of that many bodies is built (it asked torch for 8 TB)
    with pytest.raises(ValueError, match="their footprints alone cover more than the square"):
        make_core("cfd_torch/Sort-v0", num_cubes=10**6)
    obs, _ = gym.make("cfd_torch/Gather-v0", spread=0.5).reset(seed=3)  # tight, but it fits
    assert obs.shape == (46,)


def test_billiards_refuses_a_ball_radius_whose_start_touches_at_construction():
    """The rack's rows are 0.157 ball_radius apart and the cue ball starts 0.4 m from the apex ball: a radius that
    puts them within the contact margin is refused when the environment is made, naming the argument and its range
    (it used to pass construction and reset, and fail at the first step)."""
    for r in (0.005, 0.25):
        with pytest.raises(ValueError, match=r"ball_radius=.* within the contact margin 0.001 .* between about "
                           r"0.00637 and 0.2 m"):  # fmt: skip
            gym.make("cfd_torch/Billiards-v0", ball_radius=r)
    env = gym.make("cfd_torch/Billiards-v0", ball_radius=0.007)  # 1.1 mm rows: feasible, and it steps
    env.reset(seed=0)
    env.step(np.zeros(2, np.float32))


def test_an_unusable_device_or_unused_servo_gains_are_refused_at_construction():
    """A device this torch build cannot hold tensors on used to pass construction and fail at the first reset with
    torch's AssertionError; AntPush's servo_gains were ignored under its default torque actuation."""
    with pytest.raises(ValueError, match="device 'meta' holds no data"):
        make_core("cfd_torch/Push-v0", device="meta")
    with pytest.raises(ValueError, match="device 'nowhere' is not usable with this torch build"):
        make_core("cfd_torch/Push-v0", device="nowhere")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda' is not usable with this torch build"):
            make_core("cfd_torch/Push-v0", device="cuda")
    with pytest.raises(ValueError, match="servo_gains is read only by actuation='position'"):
        make_core("cfd_torch/AntPush-v0", servo_gains=(1.0, 2.0))
    for gains in ((1.0, 2.0, 3.0), (-7.0, 1.0), (1.0, float("nan")), "12"):
        with pytest.raises(ValueError, match=r"servo_gains must be \(kp > 0, kv >= 0\), finite numbers"):
            make_core("cfd_torch/AntPush-v0", actuation="position", servo_gains=gains)


# the pusher's start at seed 7 with the default sizes, as the scatter drew it before each footprint had its own
# radius (session 52; Sort and Gather share the draw)
PUSHER_START_SEED7 = dict.fromkeys(
    ("cfd_torch/Sort-v0", "cfd_torch/Gather-v0"), [0.23014904117458101, 0.34810130978117243]
)


@pytest.mark.parametrize("task", ["cfd_torch/Sort-v0", "cfd_torch/Gather-v0"])
def test_the_pusher_starts_clear_of_cubes_smaller_than_itself(task):
    """The scatter kept every footprint the cube's half diagonal apart, the pusher's too: with cubes smaller than
    the 0.1 m pusher it could start inside one (Gather, cube_size 0.02, spread 0.3, seed 435: a step then refused
    the penetrating start). Each footprint now has its own radius, 5 cm apart; the default layout is unchanged."""
    from cfd_torch import step

    with pytest.warns(RestGapWarning, match=r"bodies 0, 1, .* \(0.004 kg, 2 cm tall\) would rest about"):
        core = make_core(task, cube_size=0.02, spread=0.3)  # 2 cm cubes at the default stiffness hover
    n = core.num_cubes
    s = core.reset(0, 600)
    half = math.hypot(*core.pusher.size[:2]) / 2
    gaps = (s.q[:, :n, :2] - s.q[:, n : n + 1, :2]).norm(dim=-1) - half - math.hypot(0.02, 0.02) / 2
    assert float(gaps.min()) > 0.05
    s435 = core.reset(435)
    step(core.scene, core.scene.initial_state(s435.q[0]))  # the start is feasible
    ref = make_core(
        task
    )  # the default sizes: the draws of every earlier release (the pusher's start, seed 7)
    q = ref.reset(7).q[0, : ref.num_cubes + 1, :2]
    d = (q[:, None] - q[None]).norm(dim=-1) + torch.eye(ref.num_cubes + 1, dtype=F64)
    assert float(d.min()) > 2 * 0.1 / math.sqrt(2) + 0.05
    assert q[-1].tolist() == PUSHER_START_SEED7[task]


def test_task_variables_are_checked_against_the_task():
    """The keys, shapes and dtypes of ``state.task`` are those a start of the task has, and index-like variables
    are in range: Billiards' target -1 meant ball 14 silently (20: an IndexError; a float: an indexing error), a
    missing key a bare KeyError, a wrong trailing shape a broadcast error, a bool ``t`` was counted on."""
    bil = make_core("cfd_torch/Billiards-v0")
    s = bil.reset(0, 2)
    a = torch.zeros(2, 2, dtype=F64)
    for task, err, match in (
        ({**s.task, "target": torch.tensor([3, -1])}, ValueError, r"\['target'\] must be a rack ball's index in "
         r"0\.\.14, got -1 \(environment 1\)"),
        ({**s.task, "target": torch.tensor([20, 3])}, ValueError, r"index in 0\.\.14, got 20 \(environment 0\)"),
        ({**s.task, "target": s.task["target"].double()}, TypeError, r"\['target'\] must be an int64 tensor"),
        ({**s.task, "target": s.task["target"].int()}, TypeError, r"\['target'\] must be an int64 tensor, got "
         "torch.int32"),
        ({"pocket": s.task["pocket"]}, ValueError, r"state.task must hold this task's variables \['pocket', "
         r"'target'\], got \['pocket'\]"),
        ({**s.task, "extra": s.task["pocket"]}, ValueError, "this task's variables"),
        ({**s.task, "pocket": s.task["pocket"][:, :1]}, ValueError, r"\['pocket'\] must have shape \(2, 2\), got "
         r"\(2, 1\)"),
        ({**s.task, "pocket": s.task["pocket"].long()}, TypeError, r"\['pocket'\] must be a float tensor"),
    ):  # fmt: skip
        with pytest.raises(err, match=match):
            bil.step(EnvState(s.q, s.q_prev, s.t, task), a)
    with pytest.raises(ValueError, match="state.t must be an int64 tensor of shape"):
        bil.step(EnvState(s.q, s.q_prev, s.t.bool(), s.task), a)
    srt = make_core("cfd_torch/Sort-v0", num_cubes=2)
    s = srt.reset(0, 2)
    classes = s.task["classes"].clone()
    classes[1, 0] = 2
    with pytest.raises(ValueError, match=r"\['classes'\] must hold classes 0 and 1 only \(environment 1\)"):
        srt.step(EnvState(s.q, s.q_prev, s.t, {**s.task, "classes": classes}), a)
    srt.step(s, a)  # a drawn start passes


def test_stack_states_concatenates_environments_and_names_what_cannot_be():
    """Stacking single environments gives the batch reset draws; no states, a non-state or states of two tasks
    are named (they failed inside torch's pytree: 'tree_map() missing ...', 'Node arity mismatch')."""
    core = make_core("cfd_torch/Billiards-v0")
    both = stack_states([core.reset(4), core.reset(5)])
    ref = core.reset(4, 2)
    assert torch.equal(both.q, ref.q) and torch.equal(both.t, ref.t)
    assert all(torch.equal(both.task[k], ref.task[k]) for k in ref.task)
    with pytest.raises(ValueError, match="states must hold at least one EnvState"):
        stack_states([])
    with pytest.raises(TypeError, match="states\\[1\\] must be an EnvState, got Tensor"):
        stack_states([core.reset(4), core.reset(5).q])
    push = make_core("cfd_torch/Push-v0").reset(0)
    with pytest.raises(ValueError, match=r"states\[1\] has the task variables \['target'\], states\[0\] "):
        stack_states([core.reset(4), push])
    # the same task variables: another task (AntPush), another core's size or dtype (they failed in torch.cat, or
    # promoted float32 silently)
    for other, what in (
        (make_core("cfd_torch/AntPush-v0").reset(0), r"states\[1\].q is torch.float64 of shape \(B, 11, 6\), "
         r"states\[0\].q torch.float64 of shape \(B, 3, 6\)"),
        (make_core("cfd_torch/Push-v0", dtype=torch.float32).reset(0), r"states\[1\].q is torch.float32"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=what):
            stack_states([push, other])
    sort2, sort3 = (make_core("cfd_torch/Sort-v0", num_cubes=n).reset(0) for n in (2, 3))
    with pytest.raises(ValueError, match=r"states\[1\].q is torch.float64 of shape \(B, 5, 6\)"):
        stack_states([sort2, sort3])


def test_positions_and_velocities_are_unbounded_in_the_observation_space():
    """Physical bounds derived from the default horizon were left by longer episodes, faster pushers and an Ant off
    the floor: the bodies' positions and velocities are unbounded; what is bounded (rotation vectors, joint
    angles, targets) keeps its bound."""
    core = make_core("cfd_torch/Gather-v0", num_cubes=1, max_speed=30.0)
    low, high = core.observation_bounds()
    assert bool(torch.isinf(high[:8]).all()) and bool(torch.isfinite(high[8:]).all())
    s = core.reset(0)
    for _ in range(10):
        out = core.step(s, torch.tensor([[1.0, 0.0]], dtype=F64))
        s = out.state
    assert float(out.obs[0, 6].abs()) > 20.0  # the pusher's speed, beyond the old 20 m/s bound
    assert bool(((out.obs >= low) & (out.obs <= high)).all())
    for env_id in envs.IDS:
        low, high = make_core(env_id).observation_bounds()
        assert bool(torch.isinf(high).any()) and bool((low == -high).all()) and bool((high > 0).all())


def test_vector_env_takes_numpy_integer_counts_and_rendered_envs_pickle():
    import copy
    import pickle

    vec = gym.make_vec("cfd_torch/Push-v0", np.int64(2), vectorization_mode="vector_entry_point")
    assert vec.num_envs == 2 and isinstance(vec.num_envs, int)
    vec.close()
    env = gym.make("cfd_torch/Billiards-v0", render_mode="rgb_array", width=48, height=48)
    env.reset(seed=0)
    frame = env.render()
    for twin in (
        pickle.loads(pickle.dumps(env)),
        copy.deepcopy(env),
    ):  # without the renderer, which is remade
        np.testing.assert_array_equal(twin.render(), frame)
        twin.close()
    env.close()


@pytest.mark.parametrize(
    "core_cls, kwargs, key",
    [
        ("PushCore", dict(distance=8.0, angle_range=1.5), "target"),
        ("GatherCore", dict(region_distance=3.0, num_cubes=2), "centre"),
        ("AntPushCore", dict(distance=6.0), "target"),
    ],
)
def test_render_cameras_follow_the_task_arguments(core_cls, kwargs, key):
    """A goal moved by a task argument stays in the picture: it lies within the circle about the camera's lookat
    that fills the 45 degree field of view at the camera's distance."""
    import importlib

    module = {"PushCore": "push", "GatherCore": "gather", "AntPushCore": "ant_push"}[core_cls]
    core = getattr(importlib.import_module(f"cfd_torch.envs.{module}"), core_cls)(**kwargs)
    cam = core.render_camera()
    reach = cam["distance"] * math.sin(math.radians(22.5))
    goals = core.reset(seed=0, batch_size=16).task[key]
    far = (goals - torch.tensor(cam["lookat"][:2], dtype=goals.dtype)).norm(dim=1)
    assert float(far.max()) > 2.0  # the argument moved the goal far from where the default camera looked
    assert bool((far < reach).all()), (far.max(), reach)


@pytest.mark.parametrize("pocket", [4, 5])
def test_billiards_camera_holds_a_near_corner_pocket(pocket):
    """The near-corner pockets (4, 5) lie below the default view (1.9 m from where it looks, beyond its 0.88 m
    reach): with one of them as the task's pocket the camera is derived to hold it, the rack and the cue ball's
    start region."""
    from cfd_torch.envs.billiards import POCKETS, BilliardsCore

    default = BilliardsCore().render_camera()
    p = torch.tensor(POCKETS[pocket], dtype=torch.float64)
    assert float((p - torch.tensor(default["lookat"][:2])).norm()) > default["distance"] * math.sin(
        math.radians(22.5)
    )
    core = BilliardsCore(pocket=pocket)
    cam = core.render_camera()
    reach = cam["distance"] * math.sin(math.radians(22.5))
    centre = torch.tensor(cam["lookat"][:2], dtype=torch.float64)
    state = core.reset(seed=0, batch_size=8)
    assert bool((state.task["pocket"] == p).all())
    for xy in (p, state.q[:, :, :2].reshape(-1, 2)):  # the pocket, every ball's start
        assert bool(((xy - centre).norm(dim=-1) + 0.08 < reach).all())


def test_native_vector_env_time_limit_follows_gym_make():
    """max_episode_steps of the native vector env as gym.make takes it: a positive int truncates after that many
    steps (then the next step is the autoreset), -1 never does, anything else is refused (0 and -5 truncated every
    step, 2.7 became 2)."""
    for bad in (0, -5, 2.7, "3"):
        with pytest.raises(ValueError, match="max_episode_steps must be a positive int, -1"):
            gym.make_vec("cfd_torch/Push-v0", 2, max_episode_steps=bad)
    for limit, expect in (
        (2, [False, True, False]),
        (-1, [False, False, False]),
        (np.int64(1), [True, False, True]),
    ):
        vec = gym.make_vec("cfd_torch/Push-v0", 2, max_episode_steps=limit)
        vec.reset(seed=0)
        got = [bool(vec.step(np.zeros((2, 2), dtype=np.float32))[3].all()) for _ in range(3)]
        vec.close()
        assert got == expect, (limit, got)
    core = make_core("cfd_torch/Gather-v0", num_cubes=np.int64(2))  # a NumPy int is an int
    assert core.num_cubes == 2 and isinstance(core.num_cubes, int)


def test_native_vector_env_checks_reset_mask_as_gymnasium_does():
    """options['reset_mask'] is checked as gymnasium's SyncVectorEnv checks it: a bool NumPy array (an int array
    or a list is refused, not read as indices or truthiness) of one entry per environment, with a True in it."""
    vec = gym.make_vec("cfd_torch/Push-v0", 2)
    obs, _ = vec.reset(seed=0)
    for mask, err, msg in (
        (np.array([0, 1]), TypeError, "must be a NumPy array of dtype bool, got int64"),
        ([False, True], TypeError, "must be a NumPy array of dtype bool, got list"),
        (np.array([True]), ValueError, r"must have shape \(2,\)"),
        (np.array([False, False]), ValueError, "must hold at least one True"),
    ):
        with pytest.raises(err, match=r"options\['reset_mask'\] " + msg):
            vec.reset(options={"reset_mask": mask})
    again, _ = vec.reset(seed=1, options={"reset_mask": np.array([False, True])})
    assert np.array_equal(again[0], obs[0]) and not np.array_equal(again[1], obs[1])
    vec.close()


def test_native_vector_env_names_the_environment_that_failed():
    """A failure in one environment of the native vector env says which (batched, the core's scene index is the
    position among the environments stepped, not the environment's index)."""
    import dataclasses

    for batched, where in ((False, "environment 2: "), (True, r"environments \[1, 2\] stepped as one batch")):
        vec = gym.make_vec("cfd_torch/Push-v0", 3, batched=batched)
        vec.reset(seed=0)
        vec.reset(options={"reset_mask": np.array([False, True, True])})
        vec.unwrapped._autoreset[0] = True  # environment 0 resets at the next step, 1 and 2 step
        s = vec.unwrapped.states[2]
        sunk = s.q.clone()
        sunk[:, 0, 2] = 0.05  # the box sunk into the floor
        vec.unwrapped.states[2] = dataclasses.replace(s, q=sunk, q_prev=sunk.clone())
        with pytest.raises(ValueError, match=where + ".*bodies penetrate"):
            vec.step(np.zeros((3, 2), dtype=np.float32))
        vec.close()


def test_billiards_camera_holds_wider_pockets():
    """A pocket radius wider than the default's 0.08 m (whose fixed view a 0.3 m disc about a far-corner pocket
    overran) gets the derived view: every pocket that can be drawn, with its radius, is within its reach."""
    from cfd_torch.envs.billiards import POCKETS, BilliardsCore

    cam = BilliardsCore(pocket_radius=0.3).render_camera()
    reach = cam["distance"] * math.sin(math.radians(22.5))
    centre = torch.tensor(cam["lookat"][:2], dtype=torch.float64)
    far = max(float((torch.tensor(POCKETS[k]) - centre).norm()) + 0.3 for k in range(4))
    assert far > 1.0 and far < reach, (far, reach)


@pytest.mark.parametrize(
    "task, kwargs",
    [("Sort", {"spread": 4.0}), ("Sort", {"region_offset": 4.0}), ("Gather", {"region_distance": 4.0})],
)
def test_cube_tasks_floor_holds_the_spread_and_the_goal_regions(task, kwargs):
    """Sort's and Gather's floor reaches 1 m beyond every cube's start and every goal region (a 6 m floor had
    cubes started beyond its edge fall, and a region beyond it count falling cubes as gathered)."""
    core = make_core(f"cfd_torch/{task}-v0", **kwargs)
    V = core.scene.bodies[-1].bsh.vertices
    half = 0.5 * float(V[:, 0].max() - V[:, 0].min())
    state = core.reset(seed=[0, 1, 2], batch_size=3)
    cubes = state.q[:, : core.num_cubes, :2].abs().amax()
    reach = max(math.hypot(x, y) + r for x, y, r in core._goal_discs())
    assert half >= float(cubes) + 1.0 and half >= reach + 1.0, (half, float(cubes), reach)


def test_vector_env_frame_i_is_environment_i():
    """Frame i of the native vector env is the frame of copy i (the single env reset with seed s + i draws the same
    scene), in order (reversed frames passed the suite); the sync vector env gives the same frames."""
    kwargs = dict(render_mode="rgb_array", width=64, height=48)
    single = gym.make("cfd_torch/Sort-v0", **kwargs)
    expected = []
    for i in range(3):
        single.reset(seed=7 + i)
        expected.append(single.render())
    single.close()
    for mode in ("vector_entry_point", "sync"):
        vec = gym.make_vec("cfd_torch/Sort-v0", 3, vectorization_mode=mode, **kwargs)
        vec.reset(seed=7)
        frames = vec.render()
        vec.close()
        assert len(frames) == 3
        for i in range(3):
            np.testing.assert_array_equal(frames[i], expected[i], err_msg=f"{mode}: frame {i}")
    assert not np.array_equal(expected[0], expected[1])


def test_render_metadata_and_render_mode_none():
    """``metadata["render_fps"]`` is the step rate 1 / dt (a frame per step: real time), for the native vector env
    too; render() without a render mode returns None; an unsupported mode is refused naming ``render_mode``."""
    for dt, fps in ((0.01, 100), (0.02, 50)):
        env = gym.make("cfd_torch/Push-v0", dt=dt)
        assert env.metadata["render_fps"] == fps and env.metadata["render_modes"] == ["rgb_array"]
        env.reset(seed=0)
        assert env.unwrapped.render() is None  # render_mode None
        env.close()
        vec = gym.make_vec("cfd_torch/Push-v0", 2, vectorization_mode="vector_entry_point", dt=dt)
        assert vec.metadata["render_fps"] == fps
        vec.reset(seed=0)
        assert vec.render() is None
        vec.close()
    with pytest.raises(ValueError, match="render_mode must be None or 'rgb_array'"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # gym.make's own "not in the possible render_modes"
            gym.make("cfd_torch/Push-v0", render_mode="ansi")


def test_states_and_rollouts_load_with_torch_load_defaults(tmp_path):
    """torch.load's weights_only=True (torch's default from 2.6) refused the library's containers (State, Params,
    Action, Trajectory, StepInfo, EnvState, StepOut, Rollout): 'Weights only load failed'; they are allowlisted."""
    from cfd_torch import Action, Trajectory, step
    from cfd_torch import rollout as sim_rollout

    core = make_core("cfd_torch/Push-v0")
    s = core.reset(0)
    out = core.step(s, torch.zeros(1, 2, dtype=F64))
    roll = rollout(core, s, torch.zeros(2, 1, 2, dtype=F64))
    scene = core.scene
    state = scene.initial_state(s.q[0])
    _, info = step(scene, state, return_info=True)
    things = [s, out, roll, state, scene.params(), Action(force=torch.zeros(3, 3, dtype=F64)), info,
              sim_rollout(scene, state, 1)]  # fmt: skip
    for k, thing in enumerate(things):
        torch.save(thing, tmp_path / f"{k}.pt")
        back = torch.load(tmp_path / f"{k}.pt")
        assert type(back) is type(thing)
        if isinstance(thing, Trajectory):  # (not a pytree)
            thing, back = (thing.q, thing.q_prev), (back.q, back.q_prev)
        flat, _ = torch.utils._pytree.tree_flatten(thing)
        flat_back, _ = torch.utils._pytree.tree_flatten(back)
        assert len(flat) == len(flat_back) > 1
        assert all(
            torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b
            for a, b in zip(flat, flat_back, strict=True)
        )
