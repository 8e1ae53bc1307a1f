"""Smoke runs of the experiment scripts (scripts/optimize.py's run_experiment, sweep.py, plot_results.py): two
iterations per contact model on Push's trivial start, the rollout counts they log, and the sweep's files."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
sys.path.insert(0, str(SCRIPTS))
try:
    from optimize import (
        DEFAULTS,
        FD_STEPS,
        MODELS,
        OPTIMISERS,
        Optimiser,
        _mujoco_fd,
        _round_off,
        run_experiment,
    )
    from plot_results import _curves, _together, mixed_settings, table
finally:
    sys.path.pop(0)


def test_the_gif_of_an_open_loop_run_ends_at_its_terminal_step(tmp_path, monkeypatch):
    """A Billiards episode that terminates at its first step (the pocket's radius takes in the object ball where it
    starts): best.gif shows the start and that step only, as the episode does (it showed all 10 steps of the
    horizon, the balls moving on after the end)."""
    import optimize

    from cfd_torch.envs import make_core, rollout

    task_args = {"pocket_radius": 0.8, "pocket": 2, "target_ball": 0}
    core = make_core("cfd_torch/Billiards-v0", **task_args)
    with torch.no_grad():
        ran = rollout(core, core.reset(0, 1), torch.zeros(10, 1, core.action_dim, dtype=torch.float64))
    alive = int(ran.alive[:, 0].sum())
    assert alive < 10  # the episode ends within the horizon
    drawn = []
    monkeypatch.setattr(optimize, "write_gif", lambda frames, path, fps: drawn.append(len(frames)))
    run_experiment(
        {
            "task": "Billiards",
            "iters": 1,
            "horizon": 10,
            "loss": "final",
            "task_args": task_args,
            "out": tmp_path,
        }
    )
    assert drawn == [alive + 1]


@pytest.mark.parametrize("model", MODELS)
def test_two_iterations_per_model(model, tmp_path):
    """Two ngd iterations on 3 actions from Push's trivial start: three evaluations logged, each one rollout and
    its backward (gb: 1 + 2 sampled rollouts, no backward); the files written. The local barriers' and MuJoCo's
    gradient is exactly zero there (the pole is 0.5 m from the box), so their runs stop after the first evaluation
    (mujoco-fd's: 1 + its step-size sweep's 5 x 2 x 6 central differences) with ``stopped_at`` 0; ours and gb's
    are not zero and run on. An earlier run's files in the folder go first (this run writes no GIF)."""
    (tmp_path / "best.gif").write_text("an earlier run's")
    r = run_experiment(
        {
            "task": "Push",
            "model": model,
            "iters": 2,
            "horizon": 3,
            "gb_samples": 2,
            "gif": False,
            "out": tmp_path,
        }
    )
    log = r["log"]
    flat = model in ("ipc", "sdrs", "mujoco-fd")
    assert [row["iter"] for row in log] == ([0] if flat else [0, 1, 2])
    assert r["summary"]["stopped_at"] == (0 if flat else None)
    counts = [row["rollouts"] for row in log]
    if model == "mujoco-fd":
        sweep = r["summary"]["fd_sweep"]
        assert [row["step"] for row in sweep] == list(FD_STEPS) and r["summary"]["fd_step"] in FD_STEPS
        assert all(row["grad_norm"] == 0.0 for row in sweep)
        assert counts == [1 + len(FD_STEPS) * 12]
    else:
        per = 3 if model == "gb" else 1
        assert counts == ([1] if flat else [per, 2 * per, 3 * per])
    assert log[-1]["backward"] == {"gb": 0, "mujoco-fd": 0, "ipc": 1, "sdrs": 1}.get(model, 3)
    assert all(math.isfinite(row["loss"]) for row in log)
    if flat:
        assert log[0]["grad_norm"] == 0.0
    else:
        assert log[0]["grad_norm"] > 0.0
    saved = json.loads((tmp_path / "log.json").read_text())
    assert saved["config"]["model"] == model and len(saved["log"]) == len(log)
    assert (tmp_path / "loss.png").stat().st_size > 0
    assert not (tmp_path / "best.gif").exists()


def test_mujoco_twin_pushes_the_box_like_the_simulator():
    """The MuJoCo twin of Push (its own meshes, masses, friction; the task's PD law and reward): at rest with zero
    actions the box stays (distance to the target 3.0 m to 1e-6), and the pole driven at the box for 0.6 s moves
    it toward the target by 0.3-3 times what this library's simulator gives."""
    import torch

    from cfd_torch.envs import make_core, rollout
    from cfd_torch.envs.mujoco_twin import MujocoTwin

    core = make_core("cfd_torch/Push-v0")
    s = core.reset(0, 1)
    twin = MujocoTwin(core)
    d0, alive = twin.rollout(s, torch.zeros(60, 2, dtype=torch.float64))
    assert float((d0 - 3.0).abs().max()) < 1e-6 and bool((alive == 1).all())
    to_box = s.q[0, 0, :2] - s.q[0, 1, :2]
    a = (to_box / to_box.norm()).expand(60, 2).clone()
    d, _ = twin.rollout(s, a)
    with torch.no_grad():
        ours = -rollout(core, s, a[:, None, :]).info["reward_distance"][:, 0]
    moved, moved_ours = 3.0 - float(d[-1]), 3.0 - float(ours[-1])
    assert moved_ours > 1e-4
    assert 0.3 * moved_ours < moved < 3.0 * moved_ours
    # actions beyond [-1, 1] are clipped as TaskCore.step clips them (the twin drove the pole twice as fast)
    assert torch.equal(twin.rollout(s, 2.0 * a[:5])[0], d[:5])
    # actions of another shape are refused, not reshaped; NaN is refused before MuJoCo sees it
    with pytest.raises(ValueError, match=r"actions must be \(T, 2\) or \(T, 1, 2\), got \(2, 2, 1\)"):
        twin.rollout(s, torch.zeros(2, 2, 1, dtype=torch.float64))
    bad = torch.zeros(3, 2, dtype=torch.float64)
    bad[1, 0] = float("nan")
    with pytest.raises(ValueError, match="actions contain NaN or inf \\(first at step 1\\)"):
        twin.rollout(s, bad)
    # step by step, each step from the MuJoCo state the one before returned, is the rollout bit for bit, and a
    # rollout from a state mid-way is the rest of it
    st, physics, steps = s, None, []
    for t in range(12):
        st, physics, dist, done = twin.step(st, a[t], physics)
        steps.append(dist)
        assert not done
        if t == 5:
            tail, _ = twin.rollout(st, a[6:12], physics)
    assert torch.equal(torch.tensor(steps, dtype=torch.float64), d[:12])
    assert torch.equal(tail, d[6:12])
    with pytest.raises(ValueError, match="physics does not hold state's poses"):
        twin.rollout(s, a[:2], physics)
    with pytest.raises(ValueError, match="physics must be a"):
        twin.step(s, a[0], physics[:-1])
    with pytest.raises(ValueError, match=r"action must be \(2,\) or \(1, 2\), got \(3,\)"):
        twin.step(s, torch.zeros(3, dtype=torch.float64))


def test_mujoco_twin_of_a_float32_core_hands_back_states_the_core_steps_on():
    """twin.step returns the next state in the core's dtype (float32 here), so the core can step on from it; a
    non-tensor action is refused as such."""
    import numpy as np
    import torch

    from cfd_torch.envs import make_core
    from cfd_torch.envs.mujoco_twin import MujocoTwin

    core = make_core("cfd_torch/Push-v0", dtype=torch.float32)
    twin = MujocoTwin(core)
    nxt, physics, _, _ = twin.step(core.reset(0, 1), torch.full((2,), 0.5))
    assert nxt.q.dtype == nxt.q_prev.dtype == torch.float32
    assert core.step(nxt, torch.zeros(1, 2)).state.q.dtype == torch.float32
    # and the twin steps on from it and MuJoCo's state (the float32 poses are MuJoCo's rounded)
    again, _, _, _ = twin.step(nxt, torch.full((2,), 0.5), physics)
    assert again.q.dtype == torch.float32 and float((again.q - nxt.q).abs().max()) > 0
    with pytest.raises(TypeError, match="actions must be a torch tensor, got ndarray"):
        twin.rollout(core.reset(0, 1), np.zeros((2, 2)))


def test_mujoco_twin_friction_is_coulombs_isotropic_cone():
    """Push's box sliding on the floor with the pole far away, in the twin: it decelerates by mu g (within 5 %,
    MuJoCo's soft contact) with the friction force opposite its velocity, whatever the direction (MuJoCo's default
    pyramidal cone gave 0.74 mu g at 45 degrees to its axes and a force 7 degrees off the velocity at 22.5)."""
    import torch

    from cfd_torch.envs import make_core
    from cfd_torch.envs.core import EnvState
    from cfd_torch.envs.mujoco_twin import MujocoTwin

    core = make_core("cfd_torch/Push-v0")
    twin = MujocoTwin(core)
    dt, mu_g = core.scene.dt, core.scene.friction.coefficient * 9.81
    s0 = core.reset(0, 1)
    for phi in (0.0, math.pi / 8, math.pi / 4):
        q, q_prev = s0.q.clone(), s0.q_prev.clone()
        q[0, 1, :2] = q_prev[0, 1, :2] = torch.tensor([-3.0, 3.0])  # the pole parked 4 m away
        v = torch.tensor([math.cos(phi), math.sin(phi)], dtype=torch.float64)
        q_prev[0, 0, :2] = q[0, 0, :2] - v * dt  # 1 m/s
        st, physics, xy = EnvState(q, q_prev, s0.t, s0.task), None, []
        for _ in range(13):
            st, physics, _, _ = twin.step(st, torch.zeros(2, dtype=torch.float64), physics)
            xy.append(st.q[0, 0, :2])
        vel = torch.diff(torch.stack(xy), dim=0) / dt
        decel = (vel[11] - vel[3]) / (8 * dt)  # (after the box settles on the floor)
        assert float(decel.norm()) == pytest.approx(mu_g, rel=0.05)
        assert float(-(decel @ v) / decel.norm()) > math.cos(math.radians(1.0))


def test_finite_differences_of_round_off_are_told_from_a_derivative():
    """The step-size sweep's test: differences of one size at every step, or at the larger steps and none below
    (AntPush's box moved by MuJoCo's one solve of every contact: 1e-6 of a loss of 60 at steps 0.1 to 1e-3), are
    round-off; differences that shrink with the step, a jump within reach of the larger steps (above 1e-6 of the
    loss), all-zero differences and a sweep too narrow to tell are not."""
    g = torch.tensor([0.3, -1.0, 0.02], dtype=torch.float64)

    def sweep(diff):  # step -> the gradient whose central differences are diff(h)
        return {h: diff(h) / (2 * h) for h in FD_STEPS}

    assert _round_off(sweep(lambda h: 2e-7 * torch.tensor([1.0, -0.6, 0.3], dtype=torch.float64)), 60.0)
    assert _round_off(sweep(lambda h: (1e-6 if h >= 1e-3 else 0.0) * g), 60.0)
    assert not _round_off(sweep(lambda h: 2 * h * g), 60.0)
    assert not _round_off(sweep(lambda h: 2 * h * g + 1e-12), 60.0)  # a derivative over rounding
    assert not _round_off(sweep(lambda h: (0.5 if h >= 1e-3 else 0.0) * g), 60.0)  # a contact event's jump
    assert not _round_off(sweep(lambda h: (1e-6 if h >= 1e-1 else 0.0) * g), 60.0)  # one step: cannot tell
    assert not _round_off(sweep(lambda h: 0 * g), 60.0)
    assert not _round_off({1e-2: g * 1e-9, 1e-3: g * 1e-8}, 60.0)  # too narrow a sweep to tell


def test_mujoco_fd_zeroes_round_off_at_every_evaluation_and_keeps_a_derivative():
    """mujoco-fd's evaluations through a stand-in twin: a loss of 60 that changes by up to 1e-6 whatever the step
    (round-off) gives a zero gradient at the sweep and at each later evaluation (as MPC's control steps make them:
    one evaluate_from per state, one shared record), each later one over the sweep's steps; a smooth loss keeps its
    derivative and one step's differences."""

    class Twin:
        def __init__(self, noisy: bool) -> None:
            self.noisy = noisy

        def rollout(self, env, actions, physics=None):
            s = float(actions.sum())
            extra = 1e-6 * math.sin(1e7 * s) if self.noisy else 0.01 * s
            return torch.full((4,), 15.0 + extra / 4, dtype=torch.float64), torch.ones(4)

    for noisy in (True, False):
        config = {"loss": "sum", "fd_step": None, "lr": 0.5}
        evaluate_from = _mujoco_fd(Twin(noisy), config, lambda th: th)
        for t in range(3):
            th = torch.full((3,), 0.01 * t, dtype=torch.float64)
            _, _, g, _, _, rollouts, _ = evaluate_from(None)(th)
            assert config["fd"]["round_off"] == noisy
            if noisy:
                # (at the sweep each step's lr trial too)
                assert float(g.abs().max()) == 0.0 and rollouts == 1 + len(FD_STEPS) * (7 if t == 0 else 6)
            else:
                torch.testing.assert_close(g, torch.full((3,), 0.01, dtype=torch.float64), rtol=1e-6, atol=0)
                assert rollouts == (1 + len(FD_STEPS) * 7 if t == 0 else 7)


def test_mujoco_fd_under_mpc_plans_and_executes_in_mujoco(tmp_path):
    """mujoco-fd under --mpc: at Push's trivial start its finite differences are exactly zero in every control
    step (the pole 0.5 m from the box), so no iteration runs and the executed actions are zero: the executed
    distances are MuJoCo's zero-action rollout's to the last bit (executed in MuJoCo), the
    step-size sweep runs once, and every control step counts its 1 + 2 x 3 x 2 rollouts."""
    r = run_experiment(
        {"task": "Push", "model": "mujoco-fd", "mpc": True, "steps": 3, "horizon": 3, "iters": 2, "gif": False,
         "out": tmp_path}
    )  # fmt: skip
    log, summary = r["log"], r["summary"]
    assert [row["iters_run"] for row in log] == [0, 0, 0]
    assert all(row["grad_norm"] == 0.0 for row in log)
    assert [row["executed_distance"] for row in log] == summary["zero_distances"][:3]
    assert len(summary["fd_sweep"]) == len(FD_STEPS)
    first = 1 + len(FD_STEPS) * 12
    assert [row["rollouts"] for row in log] == [first, first + 13, first + 26]


def test_mujoco_twin_of_the_ant_takes_its_state_and_stands_on_the_floor():
    """AntPush's MuJoCo twin (the Ant from the core's own MJCF, the scene's box and floor): the state's link poses
    arrive as MuJoCo's bodies (centre of mass, frame orientation) to 1e-12 and come back to 1e-12; with zero
    torques the Ant stands on the floor for 0.5 s (torso between 0.3 and 0.8 m, the box in place to 1e-5 of its
    landing), and its box, struck by the Ant sliding into it, moves."""
    import numpy as np
    import torch

    from cfd_torch.envs import make_core
    from cfd_torch.envs.mujoco_twin import MujocoTwin
    from cfd_torch.rotation import rotation_matrix

    core = make_core("cfd_torch/AntPush-v0")
    s = core.reset(0, 1)
    twin = MujocoTwin(core)
    twin._set_state(s)
    d, q = twin.data, s.q[0]
    for row in range(2, 2 + core.ant.num_links):
        bid = twin._body_id[row]
        assert np.abs(d.xipos[bid] - q[row, :3].numpy()).max() < 1e-12
        assert np.abs(d.xmat[bid].reshape(3, 3) - rotation_matrix(q[row, 3:]).numpy()).max() < 1e-12
    assert float((twin._poses(s.q) - s.q).abs().max()) < 1e-12
    dist, alive = twin.rollout(s, torch.zeros(50, 8, dtype=torch.float64))
    assert float((dist - 2.0).abs().max()) < 1e-5 and bool((alive == 1).all())
    assert 0.3 < float(twin.data.qpos[twin._root_q + 2]) < 0.8
    # the Ant sliding at 3 m/s toward the box (+x; friction stops it after about 0.45 m), with the box moved to
    # 0.2 m ahead of its torso's sphere, runs into it (its diagonal legs straddle the box)
    s_fast = type(s)(s.q.clone(), s.q_prev.clone(), s.t, s.task)
    s_fast.q[0, 0, 0] = s_fast.q_prev[0, 0, 0] = 0.6
    s_fast.q_prev[0, 2:, 0] -= 0.01 * 3.0
    hit, _ = twin.rollout(s_fast, torch.zeros(80, 8, dtype=torch.float64))
    assert float(hit[-1]) < 2.4 - 5e-4  # the box's distance to the target, 2.4 m at 0.6 (it moved 1.4 mm)
    with pytest.raises(ValueError, match="core.mjcf"):
        core_bad = make_core("cfd_torch/AntPush-v0")
        core_bad.mjcf = ()
        MujocoTwin(core_bad)


def test_run_experiment_refuses_unknown_keys_and_models():
    with pytest.raises(ValueError, match="unknown keys"):
        run_experiment({"task": "Push", "learning_rate": 0.1})
    with pytest.raises(ValueError, match="config\\['model'\\]"):
        run_experiment({"task": "Push", "model": "mujoco"})
    for key, value in (
        ("iters", -1), ("horizon", 0), ("lr", float("nan")), ("lr_final", -0.1), ("fd_step", 0.0), ("threads", 0)
    ):  # fmt: skip
        with pytest.raises(ValueError, match=f"config\\['{key}'\\] \\(--{key.replace('_', '-')}\\) must be"):
            run_experiment({"task": "Push", "iters": 1, "horizon": 2, key: value})
    for model, key, value in (
        ("cfd", "knots", 0), ("cfd", "knots", 3), ("cfd", "dt", -0.01), ("cfd", "eps", 0.0), ("gb", "gb_samples", 0),
        ("gb", "gb_sigma", -1.0), ("mujoco-fd", "mj_substeps", 0),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=f"config\\['{key}'\\] \\(--{key.replace('_', '-')}\\) must be"):
            run_experiment({"task": "Push", "model": model, "iters": 1, "horizon": 2, key: value})
    # the model chooses the potential (the logs and tables are grouped by it); --dt/--eps and task_args not both;
    # seeds in torch's range
    with pytest.raises(ValueError, match="'potential' is chosen by config\\['model'\\]"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "task_args": {"potential": "ipc"}})
    with pytest.raises(ValueError, match="both set dt: give one"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "dt": 0.02, "task_args": {"dt": 0.04}})
    with pytest.raises(ValueError, match="config\\['seed'\\] \\(--seed\\) must be an int in"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "seed": 2**64})
    # the command line turns them into usage errors before anything runs
    bad = subprocess.run(
        [sys.executable, str(SCRIPTS / "optimize.py"), "--task", "Push", "--knots", "0", "--out", "/nonexistent"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert bad.returncode == 2 and "--knots" in bad.stderr and "Traceback" not in bad.stderr


def test_plot_results_refuses_to_average_runs_made_with_different_settings():
    """Two folders' runs of one task and model with different horizons made one row and one curve (the table named
    the first run's settings); settings a model does not read (gb's samples for cfd) or that do not change a
    run (its folder, threads) may differ."""
    base = {**DEFAULTS, "task": "Billiards", "model": "cfd", "seed": 0, "out": "a"}
    same = {**base, "seed": 1, "out": "b", "threads": 2, "gb_samples": 99}
    assert mixed_settings([{"config": base}, {"config": same}]) is None
    other = {**same, "horizon": base["horizon"] + 1}
    msg = mixed_settings([{"config": base}, {"config": other}])
    assert msg is not None and "Billiards cfd: seed 0 and seed 1 were run with different horizon" in msg
    gb = {**base, "model": "gb"}
    assert "different gb_samples" in mixed_settings(
        [{"config": gb}, {"config": {**gb, "seed": 1, "gb_samples": 3}}]
    )


def test_sweep_and_plot_results(tmp_path):
    """sweep.py over 2 models x 1 seed in one process, then plot_results.py: sweep.json holds both runs, the table
    one row per model, the plot exists."""
    cmd = [sys.executable, str(SCRIPTS / "sweep.py"), "--tasks", "Push", "--models", "cfd", "gb", "--seeds", "3",
           "--iters", "1", "--horizon", "2", "--gb-samples", "2", "--workers", "1", "--out", str(tmp_path)]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True)
    runs = json.loads((tmp_path / "sweep.json").read_text())["runs"]
    assert sorted(r["config"]["model"] for r in runs) == ["cfd", "gb"]
    assert all(r["config"]["seed"] == 3 and r["config"]["iters"] == 1 for r in runs)
    assert (tmp_path / "Push" / "gb" / "seed3" / "log.json").exists()
    subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path)], check=True, capture_output=True
    )
    table = (tmp_path / "results.md").read_text().splitlines()
    assert len(table) == 4 and "| Push | cfd |" in table[2] and "| Push | gb |" in table[3]
    assert (tmp_path / "Push.png").stat().st_size > 0
    subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path), "--best", "--out", str(tmp_path / "b")],
        check=True, capture_output=True,
    )  # fmt: skip
    assert (tmp_path / "b" / "Push.png").stat().st_size > 0
    # --resume continues the same experiment only: other settings for a finished cell are refused, and for a new
    # seed of a task and model that has runs (plot_results.py refused the folder after); an existing sweep.json is
    # kept unless --resume or --overwrite says what to do with it (it was replaced silently)
    for seed in ("3", "4"):
        message = f"seed 3 run with other settings than seed {seed} now (iters: 1 there, 2 now)"
        again = subprocess.run(
            [*cmd[:-2], "--resume", "--iters", "2", "--seeds", seed, "--out", str(tmp_path)],
            capture_output=True, text=True,
        )  # fmt: skip
        assert again.returncode != 0 and message in again.stderr, again.stderr
    anew = subprocess.run(cmd, capture_output=True, text=True)
    assert (
        anew.returncode == 2
        and "sweep.json exists: --resume adds to it, --overwrite replaces it" in anew.stderr
    )
    assert len(json.loads((tmp_path / "sweep.json").read_text())["runs"]) == 2
    # a new seed with the same settings is added, and each invocation is recorded
    subprocess.run(
        [*cmd[:-2], "--resume", "--models", "cfd", "--seeds", "4", "--out", str(tmp_path)], check=True
    )
    resumed = json.loads((tmp_path / "sweep.json").read_text())
    assert sorted((r["config"]["model"], r["config"]["seed"]) for r in resumed["runs"]) == [
        ("cfd", 3), ("cfd", 4), ("gb", 3)
    ]  # fmt: skip
    assert [s["workers"] for s in resumed["sweeps"]] == [1, 1] and "--resume" in resumed["sweeps"][1]["argv"]
    # --seeds keeps the runs of those seeds only (gb ran seed 3 alone: its row goes)
    subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path), "--seeds", "4", "--out",
         str(tmp_path / "s4")],
        check=True, capture_output=True,
    )  # fmt: skip
    rows = (tmp_path / "s4" / "results.md").read_text().splitlines()[2:]
    assert len(rows) == 1 and rows[0].startswith("| Push | cfd |") and "| 4 |" in rows[0], rows
    none = subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path), "--seeds", "9", "--out",
         str(tmp_path / "s9")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert none.returncode != 0 and "no runs of seeds [9]" in none.stderr
    # a cell in two of the folders given to plot_results.py is refused (it would count twice)
    twice = subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path), str(tmp_path), "--out", str(tmp_path / "p")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert twice.returncode == 2 and "a folder is given more than once" in twice.stderr
    (tmp_path / "copy").mkdir()
    (tmp_path / "copy" / "sweep.json").write_text((tmp_path / "sweep.json").read_text())
    both = subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path), str(tmp_path / "copy"), "--out",
         str(tmp_path / "p")], capture_output=True, text=True,
    )  # fmt: skip
    assert both.returncode != 0 and "is in both" in both.stderr
    # MPC runs beside open-loop ones are refused before anything is written
    sweep = json.loads((tmp_path / "sweep.json").read_text())
    for name, model, mpc in (("open", "cfd", False), ("mpc", "gb", True)):
        (tmp_path / name).mkdir()
        keep = [r for r in sweep["runs"] if r["config"]["model"] == model]
        for r in keep:
            r["config"]["mpc"] = mpc
        (tmp_path / name / "sweep.json").write_text(json.dumps({**sweep, "runs": keep}))
    kinds = subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path / "open"), str(tmp_path / "mpc"), "--out",
         str(tmp_path / "k")], capture_output=True, text=True,
    )  # fmt: skip
    assert kinds.returncode != 0 and "MPC and open-loop runs together" in kinds.stderr
    assert not (tmp_path / "k" / "results.md").exists()
    no_sweep = subprocess.run(
        [sys.executable, str(SCRIPTS / "plot_results.py"), str(tmp_path / "Push")],
        capture_output=True,
        text=True,
    )
    assert no_sweep.returncode == 2 and "has no sweep.json" in no_sweep.stderr
    # a cell twice, or settings out of range, are refused before any run (usage errors, exit status 2)
    for args, message in (
        (["--seeds", "3", "3"], "--seeds lists [3] more than once"),
        (["--iters", "-1"], "config['iters'] (--iters) must be an int >= 1"),
    ):
        ref = subprocess.run([*cmd[:-2], *args, "--out", str(tmp_path / "r")], capture_output=True, text=True)
        assert ref.returncode == 2 and message in ref.stderr and not (tmp_path / "r").exists()


def test_mujoco_fd_on_antpush_is_flat_at_the_trivial_start(tmp_path):
    """mujoco-fd runs on AntPush (the Ant's MuJoCo twin): on 2 actions every finite-difference step of the sweep
    finds a gradient of exactly zero (the box is 1 m from the Ant), the rollouts are counted, and the run stops
    there (``stopped_at`` 0: every later iterate would repeat it)."""
    r = run_experiment(
        {"task": "AntPush", "model": "mujoco-fd", "iters": 1, "horizon": 2, "gif": False, "out": tmp_path}
    )
    sweep = r["summary"]["fd_sweep"]
    assert [row["step"] for row in sweep] == list(FD_STEPS)
    assert all(row["grad_norm"] == 0.0 for row in sweep)
    assert [row["rollouts"] for row in r["log"]] == [1 + len(FD_STEPS) * 32]
    assert r["log"][0]["grad_norm"] == 0.0 and r["summary"]["stopped_at"] == 0


def test_ngd_ls_rows_count_the_work_of_their_own_iteration():
    """ngd-ls with a rate so large that trials are rejected: a rejected iteration's row keeps the held iterate's
    loss but reports its own trial's time and Newton iterations, so the rows' times add up to the run's wall time
    (rejected rows repeated the last accepted evaluation's: 8.3 s of rows against 5.9 s of wall time)."""
    r = run_experiment(
        {
            "task": "Push",
            "model": "cfd",
            "optimizer": "ngd-ls",
            "iters": 4,
            "horizon": 3,
            "lr": 50.0,
            "gif": False,
        }
    )
    log = r["log"]
    losses = [row["loss"] for row in log]
    rejected = [k for k in range(1, len(log)) if losses[k] == losses[k - 1]]
    assert rejected, losses  # the rate makes some trial fail
    assert all(row["forward_s"] > 0 and row["newton_iters"] > 0 for row in log)
    rows = sum(row["forward_s"] + row["gradient_s"] for row in log)
    assert rows == pytest.approx(r["summary"]["wall_s"], rel=1e-9)


def test_a_zero_gradient_stops_a_run_only_without_momentum():
    """Optimiser.still: from a zero gradient with no momentum held, a step of every optimiser leaves the parameters
    where they are (so optimize.py stops the run); with momentum held (ngd, adam after a non-zero gradient) the
    step moves them and the run goes on. plot_results carries a stopped run flat to its budget and names the stop."""
    zeros = torch.zeros(3, dtype=torch.float64)
    for kind in OPTIMISERS:
        opt = Optimiser(kind, 0.1, iters=5)
        opt.start(zeros, lambda th: (float(th.detach().sum()), None, torch.zeros_like(th)))
        assert opt.still()
        before = opt.theta.detach().clone()
        opt.step()
        assert torch.equal(before, opt.theta.detach())
    for kind in ("ngd", "adam"):
        grads = [torch.ones(3, dtype=torch.float64)]  # the first evaluation's gradient, then zero ones

        def evaluate(th, grads=grads):
            return float(th.detach().sum()), None, grads.pop() if grads else torch.zeros_like(th)

        opt = Optimiser(kind, 0.1, iters=5)
        opt.start(zeros, evaluate)
        opt.step()  # along the non-zero gradient; the new point's gradient is zero
        assert not opt.still()
        before = opt.theta.detach().clone()
        opt.step()
        assert (before - opt.theta.detach()).abs().max() > 0
    run = {
        "config": {"task": "Push", "model": "ipc", "seed": 0, "mpc": False, "iters": 4, "loss": "sum"},
        "summary": {"stopped_at": 0, "loss_start": 2.0, "loss_best": 2.0, "loss_end": 2.0, "rollouts": 1,
                    "wall_s": 3.0, "best_final_distance": 1.0},
        "log": [{"iter": 0, "loss": 2.0, "wall_s": 3.0}],
    }  # fmt: skip
    x, wall, loss = _curves(run)
    assert x.tolist() == [0, 1, 2, 3, 4] and wall.tolist() == [3.0] * 5 and loss.tolist() == [1.0] * 5
    assert "| Push | ipc | 0 (0 .. 0) | 1 | 4 (stopped at 0: zero gradient) | 1 | 3 | 0 |" in table([run])


def test_mpc_skips_a_control_steps_iterations_only_at_a_zero_gradient():
    """MPC on Push's trivial start: IPC's gradient is exactly zero there, so each control step evaluates its window
    once and runs none of its iterations (``iters_run`` 0, one rollout per step); ours is not zero and runs all. The
    results table gives the budget and the iterations run."""
    runs = {
        model: run_experiment(
            {"task": "Push", "model": model, "mpc": True, "steps": 2, "iters": 2, "horizon": 3, "gif": False}
        )
        for model in ("ipc", "cfd")
    }
    ipc, cfd = runs["ipc"]["log"], runs["cfd"]["log"]
    assert [row["grad_norm"] for row in ipc] == [0.0, 0.0]
    assert [row["iters_run"] for row in ipc] == [0, 0] and [row["rollouts"] for row in ipc] == [1, 2]
    assert all(row["grad_norm"] > 0.0 for row in cfd)
    assert [row["iters_run"] for row in cfd] == [2, 2] and [row["rollouts"] for row in cfd] == [3, 6]
    # each row's executed action and where it took the pole: replaying the logged actions reaches those positions
    from cfd_torch.envs import make_core

    core = make_core("cfd_torch/Push-v0")
    s = core.reset(0, 1)
    assert any(abs(a) > 1e-3 for a in cfd[0]["action"]) and all(row["action"] == [0.0, 0.0] for row in ipc)
    for row in cfd:
        assert len(row["action"]) == core.action_dim and all(abs(a) <= 1.0 for a in row["action"])
        s = core.step(s, torch.tensor([row["action"]], dtype=torch.float64)).state
        assert s.q[0, core.action_body, :2].tolist() == row["action_body_xy"]
    rows = table(list(runs.values())).splitlines()
    assert "| 2 x 2 steps (0 run) |" in next(r for r in rows if "| ipc |" in r)
    assert "| 2 x 2 steps (4 run) |" in next(r for r in rows if "| cfd |" in r)


def test_task_args_reach_the_task():
    """--task-args: the task core's arguments (Push's target 1.5 m away instead of 3 m); a non-dict or an unknown
    argument is refused."""
    r = run_experiment(
        {"task": "Push", "iters": 1, "horizon": 2, "loss": "final", "task_args": {"distance": 1.5}}
    )
    assert abs(r["summary"]["final_distance_start"] - 1.5) < 1e-3
    assert r["config"]["task_args"] == {"distance": 1.5}
    with pytest.raises(ValueError, match="config\\['task_args'\\] \\(--task-args\\) must be a dict"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "task_args": [1.5]})
    with pytest.raises(ValueError, match="Push takes no argument distanse"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "task_args": {"distanse": 1.5}})
    # Sort and Gather pass their base's arguments on (**kwargs): those are arguments too
    from optimize import _check_settings

    for task, args in (("Sort", {"num_cubes": 2}), ("Gather", {"cube_size": 0.1})):
        _check_settings({**DEFAULTS, "task": task, "task_args": args})
    with pytest.raises(ValueError, match="Sort takes no argument num_cubez"):
        _check_settings({**DEFAULTS, "task": "Sort", "task_args": {"num_cubez": 2}})


def test_task_losses():
    """optimize.task_loss: ``sum`` adds the distances of the steps alive, ``final`` takes the distance after the
    last step alive (the terminal one), ``closest`` the smallest distance among the steps alive; an unknown loss is
    refused by name."""
    from optimize import task_loss

    # two rollouts of 4 steps: the first terminates at step 2 (alive up to and including it), the second runs on
    d = torch.tensor([[3.0, 5.0], [2.0, 4.0], [0.5, 1.0], [4.0, 0.75]], dtype=torch.float64)
    alive = torch.tensor([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    assert task_loss(-d, alive, "sum").tolist() == [5.5, 10.75]
    assert task_loss(-d, alive, "final").tolist() == [0.5, 0.75]
    assert task_loss(-d, alive, "closest").tolist() == [0.5, 0.75]
    assert task_loss(-d, torch.ones_like(d), "final").tolist() == [4.0, 0.75]  # no termination: the last step
    th = torch.zeros(4, 2, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(task_loss(-(d + th), alive, "closest").sum(), th)
    assert g.abs().sum() > 0 and g.tolist() == [[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]
    with pytest.raises(ValueError, match="config\\['loss'\\] \\(--loss\\) must be one of"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "loss": "mean"})


def test_learning_rate_decay():
    """Optimiser's rate: --lr at the first step, --lr-final at the last of the run's iterations, geometric in between
    (constant without --lr-final); each Adam step moves every coordinate by about that rate (the unit gradient's
    sign-consistent steps)."""
    opt = Optimiser("adam", 0.05, 0.005, 5)
    theta = torch.zeros(3, dtype=torch.float64)
    opt.start(theta, lambda th: (float(th.sum()), None, torch.ones_like(th)))
    rates, moves = [], []
    for _ in range(5):
        rates.append(opt.rate())
        before = opt.theta.detach().clone()
        opt.step()
        moves.append(float((before - opt.theta.detach()).abs().max()))
    assert (
        rates[0] == 0.05
        and math.isclose(rates[-1], 0.005)
        and math.isclose(rates[2], math.sqrt(0.05 * 0.005))
    )
    assert all(math.isclose(m, r, rel_tol=1e-6) for m, r in zip(moves, rates, strict=True))
    assert Optimiser("ngd", 0.3).rate() == 0.3
    # ngd-ls: each accepted step is this step's rate (a loss that falls along -g)
    ls = Optimiser("ngd-ls", 0.5, 0.05, 3)
    ls.start(theta, lambda th: (float(th.sum()), None, torch.ones_like(th)))
    moved = []
    for _ in range(3):
        before = ls.theta.detach().clone()
        ls.step()
        moved.append(float((before - ls.theta.detach()).norm()))
    assert moved[0] == 0.5 and math.isclose(moved[1], math.sqrt(0.5 * 0.05)) and math.isclose(moved[2], 0.05)


def test_theta_max_clamps_every_step():
    """--theta-max: the knot parameters stay within [-theta_max, theta_max] under every optimiser, however long the
    gradient pushes them out; at the bound ngd and adam drop the momentum that pushes outward, so they leave it as
    soon as the gradient turns, and ngd-ls, stationary there, keeps its step; without the bound the parameters run
    on; a non-positive bound is refused, naming the option."""
    theta = torch.zeros(2, dtype=torch.float64)
    for kind in OPTIMISERS:
        sign = torch.tensor([1.0, -1.0], dtype=torch.float64)  # the loss falls along +theta_0 and -theta_1

        def evaluate(th, sign=sign):
            return float(-(sign * th.detach()).sum()), None, -sign.clone()

        opt = Optimiser(kind, 0.5, iters=40, theta_max=1.5)
        opt.start(theta, evaluate)
        for _ in range(40):
            opt.step()
        assert opt.theta.detach().tolist() == [1.5, -1.5]
        if kind == "ngd-ls":
            assert opt.step_size == 0.5
        else:
            sign[
                :
            ] = -sign  # now the loss falls inward; the next step's gradient is the one from before the change
            opt.step()
            opt.step()
            th = opt.theta.detach()
            assert 0.0 < float(th[0]) < 1.5 and -1.5 < float(th[1]) < 0.0
        free = Optimiser(kind, 0.5, iters=40)
        free.start(theta, lambda th: (float(-th.detach().sum()), None, -torch.ones_like(th)))
        for _ in range(40):
            free.step()
        assert float(free.theta.detach().min()) > 1.5
    with pytest.raises(
        ValueError, match=r"config\['theta_max'\] \(--theta-max\) must be a finite number > 0"
    ):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "theta_max": 0.0})


def test_resume_takes_missing_settings_as_defaults():
    """A sweep.json written before a setting existed ran with that setting's default: --resume compares it so."""
    sys.path.insert(0, str(SCRIPTS))
    try:
        from optimize import DEFAULTS
        from sweep import _settings_differ
    finally:
        sys.path.pop(0)
    old = {k: v for k, v in DEFAULTS.items() if k not in ("loss", "lr_final")}
    assert _settings_differ(old, dict(DEFAULTS)) == []
    assert _settings_differ(old, {**DEFAULTS, "loss": "final"}) == ["loss"]
    assert (
        _settings_differ(old, {**DEFAULTS, "threads": 2, "gif": not DEFAULTS["gif"]}) == []
    )  # no result changes
    # a setting only another model reads (it refused to resume the cfd cells when --gb-samples changed)
    more = {**DEFAULTS, "model": "cfd", "gb_samples": DEFAULTS["gb_samples"] + 1}
    assert _settings_differ({**old, "model": "cfd"}, more) == []
    assert _settings_differ({**old, "model": "gb"}, {**more, "model": "gb"}) == ["gb_samples"]
    # no task arguments, as --task-args '{}' or left out, are the same run; other task arguments are not
    assert _settings_differ({**old, "task_args": {}}, {**DEFAULTS, "task_args": None}) == []
    assert _settings_differ({**old, "task_args": None}, {**DEFAULTS, "task_args": {}}) == []
    assert _settings_differ({**old, "task_args": {}}, {**DEFAULTS, "task_args": {"distance": 1.5}}) == [
        "task_args"
    ]


def test_first_order_smoothing(tmp_path):
    """--smooth-samples 2 on Push's trivial start: each evaluation one forward rollout and two differentiated ones
    (logged), a non-zero gradient for ours; gb and mujoco-fd refuse the option by name."""
    r = run_experiment(
        {"task": "Push", "iters": 1, "horizon": 3, "smooth_samples": 2, "smooth_sigma": 0.1, "gif": False}
    )
    log = r["log"]
    assert [row["rollouts"] for row in log] == [3, 6] and [row["backward"] for row in log] == [2, 4]
    assert log[0]["grad_norm"] > 0.0 and all(math.isfinite(row["loss"]) for row in log)
    with pytest.raises(ValueError, match="smooth_samples.*applies to the autograd models"):
        run_experiment({"task": "Push", "model": "gb", "iters": 1, "horizon": 2, "smooth_samples": 2})
    with pytest.raises(ValueError, match="config\\['smooth_sigma'\\]"):
        run_experiment({"task": "Push", "iters": 1, "horizon": 2, "smooth_samples": 2, "smooth_sigma": 0.0})


def test_far_field_force_hump_between_pole_and_box():
    """scripts/far_field_staircase.py: with eps 1.0 (the pushing tasks' band) the pole's force on Push's box peaks at
    the root pair's band (0.8-0.95 m) and is weaker closer in, down to under a third of the peak, before it grows
    again; at eps 4 there is no such hump. ``humps`` finds a synthetic one exactly and none in a monotone profile."""
    from cfd_torch.envs import make_core

    sys.path.insert(0, str(SCRIPTS))
    try:
        from far_field_staircase import humps, profile
    finally:
        sys.path.pop(0)
    x = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    bump = torch.tensor([9.0, 5.0, 3.0, 1.0, 2.0, 4.0, 3.0, 1.0, 0.5, 0.4, 0.3], dtype=torch.float64)
    (h,) = humps(x, bump)
    assert (h["peak_distance"], h["dip_distance"], h["recovered_at"]) == pytest.approx((0.5, 0.3, 0.1))
    assert humps(x, torch.linspace(5.0, 1.0, 11, dtype=torch.float64)) == []
    r = torch.linspace(0.3, 1.5, 61, dtype=torch.float64)
    rows = profile(make_core("cfd_torch/Push-v0"), r, [1.0, 4.0])
    (h,) = rows["1.0"]["force_humps"]
    assert 0.8 < h["peak_distance"] < 0.95 and 0.55 < h["dip_distance"] < 0.7
    assert h["dip_force"] < h["peak_force"] / 3 and 0.3 < h["recovered_at"] < 0.45
    assert rows["4.0"]["force_humps"] == []


def test_articulated_accuracy_script(tmp_path):
    """scripts/articulated_accuracy.py, two cases over 0.1 s: its JSON, table and plot, the spinning bar exact
    (its constant rate is the step's solution) and the gimbal's error against MuJoCo's RK4 halving with dt."""
    cmd = [sys.executable, str(SCRIPTS / "articulated_accuracy.py"), "--cases", "bar", "gimbal", "--dts", "0.02",
           "0.01", "--duration", "0.1", "--out", str(tmp_path)]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True)
    out = json.loads((tmp_path / "articulated_accuracy.json").read_text())
    assert (tmp_path / "articulated_accuracy.png").stat().st_size > 0
    assert "| gimbal | 0.01 |" in (tmp_path / "articulated_accuracy.md").read_text()
    err = {n: [out["this"]["errors"][n][dt]["error"] for dt in ("0.02", "0.01")] for n in ("bar", "gimbal")}
    assert max(err["bar"]) < 1e-10
    assert err["gimbal"][1] > 0 and 1.6 < err["gimbal"][0] / err["gimbal"][1] < 2.4


def test_run_experiment_leaves_torch_one_thread_after_numba_starts(tmp_path):
    """threads=1 is one torch thread for the whole run: numba's OpenMP layer, started by numba.set_num_threads,
    set OpenMP's thread count (torch's) back to NUMBA_NUM_THREADS after torch.set_num_threads(1). A fresh process:
    numba's pool starts once per process."""
    code = (
        f"import sys; sys.path.insert(0, {str(SCRIPTS)!r})\n"
        "import torch\nfrom optimize import run_experiment\n"
        "run_experiment({'task': 'Push', 'iters': 1, 'horizon': 2, 'threads': 1, 'gif': False})\n"
        "import numba; print(torch.get_num_threads(), numba.get_num_threads())\n"
    )
    env = {**__import__("os").environ, "NUMBA_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split()[-2:] == ["1", "1"], out.stdout


def _sweep_module():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import sweep
    finally:
        sys.path.pop(0)
    return sweep


def test_sweep_run_folders_are_absolute(monkeypatch, tmp_path):
    """A relative --out names the same folders wherever a run's process stands (a Ray job's working directory is
    its copy of the scripts: the runs' log.json went there)."""
    import argparse

    sweep = _sweep_module()
    monkeypatch.chdir(tmp_path)
    args = argparse.Namespace(**{**DEFAULTS, "out": Path("rel")}, tasks=["Push"], models=["cfd"], seeds=[4])
    (c,) = sweep.configs(args)
    assert c["out"] == str(tmp_path / "rel" / "Push" / "cfd" / "seed4")


def test_sweep_on_ray_passes_the_commit_and_records_a_dead_worker(monkeypatch, tmp_path):
    """--ray (a stand-in for Ray, in this process): the jobs' environment carries this checkout's commit (their
    copy of the scripts is outside it: git_revision() was None in every run's log), and a run whose worker died is
    a failed run, not the sweep's end."""
    import types

    sweep = _sweep_module()
    import _provenance

    seen = {}

    class RayError(Exception):
        pass

    class Ref:  # an ObjectRef: hashable, its value read by ray.get
        def __init__(self, value):
            self.value = value

    def remote(**_):
        return lambda fn: types.SimpleNamespace(
            remote=lambda c: Ref(RayError("died") if c["seed"] == 1 else fn(c))
        )

    def get(ref):
        if isinstance(ref.value, Exception):
            raise ref.value
        return ref.value

    fake = types.SimpleNamespace(
        init=lambda **kw: seen.update(kw), remote=remote, wait=lambda p, num_returns: (p[:1], p[1:]), get=get,
        exceptions=types.SimpleNamespace(RayError=RayError),
    )  # fmt: skip
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setattr(sweep, "run_one", lambda c: {"config": c})
    monkeypatch.setattr(sweep, "git_revision", lambda: "0123abc")  # (a checkout or not, the driver's commit)
    todo = [{"task": "Push", "model": "cfd", "seed": s} for s in (0, 1)]
    results = list(sweep._run_ray(todo, 1))
    assert seen["runtime_env"]["env_vars"] == {_provenance.REVISION_ENV: "0123abc"}
    assert [r["config"]["seed"] for r in results] == [0, 1] and "died" in results[1]["error"]
    # the scripts outside a checkout (Ray's copy) read the commit from there
    monkeypatch.setattr(_provenance, "_ROOT", tmp_path)
    monkeypatch.setenv(_provenance.REVISION_ENV, "abc1234")
    assert _provenance.git_revision() == "abc1234"


def test_sweep_pool_records_a_run_whose_process_died(monkeypatch, tmp_path):
    """A worker killed mid-run (a crash, the OOM killer) broke the whole pool: BrokenProcessPool ended the sweep
    with a traceback. Now that run is failed and the others run (stand-in runs, no simulation)."""
    (tmp_path / "dying.py").write_text(
        "import os\ndef run(c):\n    if c['seed'] == 1:\n        os._exit(3)\n    return {'config': c}\n"
    )
    sweep = _sweep_module()
    monkeypatch.syspath_prepend(str(tmp_path))  # (spawned workers import dying.py from the parent's sys.path)
    import dying

    monkeypatch.setattr(sweep, "run_one", dying.run)
    todo = [{"task": "Push", "model": "cfd", "seed": s} for s in range(4)]
    results = list(sweep._run_local(todo, 2))
    assert sorted(r["config"]["seed"] for r in results) == [0, 1, 2, 3]
    assert [r["config"]["seed"] for r in results if "error" in r] == [1]


def test_an_interrupted_sweep_ends_its_runs(monkeypatch, tmp_path):
    """Ctrl-C: the pool's workers leave SIGINT to the sweep (a worker that took it reported its run failed and
    started the next), and the sweep interrupted ends the running runs instead of waiting for every pending one
    (the grid ran on for minutes after Ctrl-C, its runs unrecorded). Stand-in runs, no simulation."""
    import multiprocessing
    import time

    (tmp_path / "standin.py").write_text(
        "import os, signal, time\n"
        "def run(c):\n"
        "    if c['seed'] == 0:\n"
        "        os.kill(os.getpid(), signal.SIGINT)  # the terminal's Ctrl-C reaches the workers too\n"
        "        time.sleep(0.2)\n"
        "        return {'config': c}\n"
        "    time.sleep(120)\n"
    )
    sweep = _sweep_module()
    monkeypatch.syspath_prepend(str(tmp_path))
    import standin

    monkeypatch.setattr(sweep, "run_one", standin.run)
    before = set(multiprocessing.active_children())  # (another test's, in this process)
    results = sweep._run_local([{"task": "Push", "model": "cfd", "seed": s} for s in range(4)], 2)
    assert next(results) == {"config": {"task": "Push", "model": "cfd", "seed": 0}}  # it ignored the SIGINT
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        results.throw(KeyboardInterrupt)  # where the sweep's Ctrl-C lands: waiting for the next result
    assert time.perf_counter() - t0 < 30 and set(multiprocessing.active_children()) <= before


def test_an_interrupt_inside_a_run_is_not_a_failed_run(monkeypatch):
    """numba re-raises a KeyboardInterrupt inside its kernels as a SystemError: the serial sweep recorded the run as
    failed and went on to the next. A real failure is kept with its traceback."""
    sweep = _sweep_module()

    def interrupted(config):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise SystemError("CPUDispatcher(...) returned a result with an exception set") from e

    monkeypatch.setattr(sweep, "run_experiment", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sweep.run_one({"seed": 0})
    monkeypatch.setattr(sweep, "run_experiment", lambda config: 1 / 0)
    failed = sweep.run_one({"seed": 0})
    assert failed["error"] == "ZeroDivisionError: division by zero" and "1 / 0" in failed["traceback"]


def test_sweep_workers_default_to_the_usable_cpus(monkeypatch, tmp_path):
    """--workers defaults to the CPUs this process may run on (taskset, cpusets), not the machine's count."""
    import os

    sweep = _sweep_module()
    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no CPU affinity here")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    monkeypatch.setattr(os, "cpu_count", lambda: 64)

    class Stop(Exception):
        pass

    def stop(args):
        raise Stop(args.workers)

    monkeypatch.setattr(sweep, "configs", stop)
    monkeypatch.setattr(sys, "argv", ["sweep.py", "--tasks", "Push", "--out", str(tmp_path / "o")])
    with pytest.raises(Stop) as got:
        sweep.main()
    assert got.value.args == (1,)


def test_plot_results_takes_missing_settings_as_defaults():
    """A run logged before a setting existed ran with its default: sweep.py --resume adds new seeds beside it, and
    plot_results.py refused that folder ("different loss (None and 'sum')")."""
    old = {k: v for k, v in DEFAULTS.items() if k not in ("loss", "smooth_samples")}
    assert mixed_settings([{"config": old}, {"config": {**DEFAULTS, "seed": 1}}]) is None
    assert "different loss" in mixed_settings(
        [{"config": old}, {"config": {**DEFAULTS, "seed": 1, "loss": "final"}}]
    )


def test_plot_results_holds_a_run_that_ended_sooner():
    """An MPC run ended by its task (often the successful seed) cut every seed's mean curve to its length, and the
    model's total-cost dot sat at its wall time; it now holds its last loss and wall time to the longest run's end."""
    short = (np.arange(2.0), np.array([0.1, 0.2]), np.array([1.0, 0.5]))
    long = (np.arange(4.0), np.array([0.1, 0.3, 0.5, 0.9]), np.array([1.0, 0.9, 0.8, 0.7]))
    x, wall, L = _together([short, long])
    assert x.tolist() == [0.0, 1.0, 2.0, 3.0]
    assert L.tolist() == [[1.0, 0.5, 0.5, 0.5], [1.0, 0.9, 0.8, 0.7]]
    assert wall.tolist() == pytest.approx([0.1, 0.25, 0.35, 0.55])
