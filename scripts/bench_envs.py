"""Environment steps per second: each task's torch core, its Gymnasium env and its native vector env.

For every task: a Gymnasium env (``gym.make(id)``) is reset with seed 0 and stepped ``--steps`` times with seeded
uniform random actions of magnitude up to ``--action-scale``, recording the (state, action) pairs; then, pair by
pair, ``env.step`` from that state (the env's state set to it) and the core's step on it are timed one after the
other (same work, same moment: the shell's overhead is the ratio of the medians; timing the two in separate blocks
put the env's steps, which came first, on colder caches: +38 and +53 % on Billiards, 3 % interleaved);
then a native vector env of ``--num-envs`` environments (``gym.make_vec(id, n)``) is stepped ``--steps`` times.
Medians of per-step wall times; float64, CPU. Writes ``bench_envs.json`` and ``bench_envs.md`` under ``--out``.

    python scripts/bench_envs.py --out results/bench_envs
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from _cli import nonnegative_float, positive_int
from _provenance import git_revision
from tqdm import tqdm

from cfd_torch.envs import TASKS  # (importing it registers the ids)


def bench(task: str, steps: int, num_envs: int, scale: float) -> dict:
    env_id = f"cfd_torch/{task}-v0"
    env = gym.make(env_id)
    core = env.unwrapped.core
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    env.step(np.zeros(core.action_dim, dtype=np.float32))  # warm-up: compilation, landing
    pairs, iters = [], []
    for _ in range(steps):
        a = (scale * rng.uniform(-1, 1, core.action_dim)).astype(np.float32)
        pairs.append((env.unwrapped.state, a))
        iters.append(env.step(a)[4]["newton_iters"])
    t_env, t_core = [], []
    for s, a in pairs:  # interleaved: the env's step and the core's on the same pair, one after the other
        env.unwrapped.state = s
        t0 = time.perf_counter()
        env.step(a)
        t_env.append(time.perf_counter() - t0)
        with torch.no_grad():
            at = torch.as_tensor(a, dtype=core.dtype).reshape(1, -1)
            t0 = time.perf_counter()
            core.step(s, at)
            t_core.append(time.perf_counter() - t0)
    env.close()
    venv = gym.make_vec(env_id, num_envs)
    venv.reset(seed=0)
    t_vec = []
    for _ in range(steps):
        a = (scale * rng.uniform(-1, 1, (num_envs, core.action_dim))).astype(np.float32)
        t0 = time.perf_counter()
        venv.step(a)
        t_vec.append(time.perf_counter() - t0)
    venv.close()
    med = statistics.median
    return {
        "task": task, "core_ms": 1e3 * med(t_core), "env_ms": 1e3 * med(t_env),
        "shell_overhead": med(t_env) / med(t_core) - 1.0, "env_steps_per_s": 1.0 / med(t_env),
        "vector_envs": num_envs, "vector_ms": 1e3 * med(t_vec),
        "vector_env_steps_per_s": num_envs / med(t_vec), "newton_iters_median": med(iters),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS, help="tasks to time")
    ap.add_argument("--steps", type=positive_int, default=20, help="timed steps per task and per env kind")
    ap.add_argument("--num-envs", type=positive_int, default=4, help="environments in the native vector env")
    ap.add_argument(
        "--action-scale", type=nonnegative_float, default=0.5, help="largest magnitude of the random actions"
    )
    ap.add_argument("--out", type=Path, default=Path("results/bench_envs"), help="output folder")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [bench(t, args.steps, args.num_envs, args.action_scale) for t in tqdm(args.tasks, desc="tasks")]
    meta = {"commit": git_revision(), "machine": platform.processor() or platform.machine(),
            "threads": torch.get_num_threads(), "steps": args.steps, "num_envs": args.num_envs,
            "action_scale": args.action_scale, "tasks": args.tasks, "rows": rows}  # fmt: skip
    (args.out / "bench_envs.json").write_text(json.dumps(meta, indent=1))
    lines = [
        "| task | core step ms | env step ms | shell overhead | env steps/s | vector env (n) steps/s | Newton it |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['core_ms']:.1f} | {r['env_ms']:.1f} | {100 * r['shell_overhead']:+.1f} % | "
            f"{r['env_steps_per_s']:.1f} | {r['vector_env_steps_per_s']:.1f} ({r['vector_envs']}) | "
            f"{r['newton_iters_median']:g} |"
        )
    table = "\n".join(lines)
    (args.out / "bench_envs.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
