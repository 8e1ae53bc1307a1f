"""Pictures of the environments: each task from seed 0, driven for ``--steps`` steps by a scripted action (Push,
Sort, Gather: the pusher heads for the first box or cube; Billiards: the cue ball pushed toward the rack's apex for
8 steps; AntPush: 2 Hz sines of staggered phase on the motors), rendered headless with each task's goal markers
(:meth:`~cfd_torch.envs.core.TaskCore.draw`). Writes ``<task>.png`` (first and last frame side by side) and
``<task>.gif`` under ``--out``, the task's name in lower case (``push.png``).

    python scripts/render_envs.py --out results/envs
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _cli import nonnegative_int, positive_int
from PIL import Image
from tqdm import tqdm

from cfd_torch.envs import TASKS, make_core
from cfd_torch.envs.core import task_at
from cfd_torch.envs.render import write_gif


def scripted(core, state) -> torch.Tensor:
    """(1, 2) action: the actuated body heads for body 0 (unit speed; the cue ball is pushed for 8 steps only)."""
    if core.action_dim != 2:  # the Ant: its eight motors driven by sines of staggered phase
        t = float(state.t[0]) * core.scene.dt
        k = torch.arange(core.action_dim, dtype=state.q.dtype)
        return 0.8 * torch.sin(2 * torch.pi * 2.0 * t + k * torch.pi / 4)[None]
    d = state.q[0, 0, :2] - state.q[0, core.action_body, :2]
    if core.action_body == 15 and int(state.t[0]) >= 8:
        return torch.zeros(1, 2, dtype=d.dtype)
    return (d / d.norm().clamp_min(1e-9))[None]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS, help="tasks to render")
    ap.add_argument("--steps", type=nonnegative_int, default=40, help="scripted steps after the first frame")
    ap.add_argument("--size", type=positive_int, default=320, help="frame width and height [pixels]")
    ap.add_argument("--out", type=Path, default=Path("results/envs"), help="output folder")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for task in tqdm(args.tasks, desc="tasks"):
        core = make_core(f"cfd_torch/{task}-v0")
        state = core.reset(0, 1)
        r = core.renderer(args.size, args.size)
        goal = task_at(state, 0)
        frames = [core.draw(r, state.q[0], goal)]
        with torch.no_grad():
            for _ in range(args.steps):
                state = core.step(state, scripted(core, state)).state
                frames.append(core.draw(r, state.q[0], goal))
        r.close()
        Image.fromarray(np.concatenate([frames[0], frames[-1]], 1)).save(args.out / f"{task.lower()}.png")
        write_gif(frames, args.out / f"{task.lower()}.gif", fps=1.0 / core.scene.dt)


if __name__ == "__main__":
    main()
