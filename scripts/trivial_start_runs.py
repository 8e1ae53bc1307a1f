"""A user's first optimisation on each task: plain Adam on the action sequence from the trivial start.

The README's environments snippet as an optimisation loop: actions U (T, 1, A) start at zero, the loss is minus
the summed ``reward_distance`` of ``rollout(core, state, U.clamp(-1, 1))`` (the task's distance term over the
horizon), Adam with ``--lr`` on the raw gradient, ``--iters`` iterations, the task's default dt. It answers one
question: does the loss fall from the trivial start in a short run through the torch API, and by how much (the
relative decrease 1 - best / initial). ``scripts/optimize.py`` is the tuned experiment (unit gradients, longer
steps); this is the naive use.

Writes ``<out>/trivial_start_runs.json`` (per run: the losses, gradient norms and seconds per iteration) and
``<out>/table.md``.

    python scripts/trivial_start_runs.py --tasks Push Sort Gather Billiards AntPush --seeds 3 4 5 --out X
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numba
import torch
from _cli import interrupted
from _provenance import git_revision
from tqdm import tqdm

from cfd_torch.envs import TASKS, make_core, rollout


def run(task: str, seed: int, horizon: int, iters: int, lr: float) -> dict:
    core = make_core(f"cfd_torch/{task}-v0")
    state = core.reset(seed, 1)
    U = torch.zeros(horizon, 1, core.action_dim, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([U], lr=lr)
    losses, grads, seconds = [], [], []
    for it in tqdm(range(iters), desc=f"{task} seed {seed}", leave=False):
        t0 = time.perf_counter()
        out = rollout(core, state, U.clamp(-1, 1))
        loss = -(out.info["reward_distance"] * out.alive).sum()
        opt.zero_grad()
        loss.backward()
        losses.append(float(loss.detach()))
        grads.append(float(U.grad.norm()))
        seconds.append(time.perf_counter() - t0)
        if it + 1 < iters:  # (a step after the last evaluation would never be measured)
            opt.step()
    return {
        "task": task, "seed": seed, "losses": losses, "grad_norms": grads, "seconds": seconds,
        "decrease": (losses[0] - min(losses)) / abs(losses[0]),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[3, 4, 5])
    ap.add_argument("--horizon", type=int, default=100, help="steps (at the task's dt)")
    ap.add_argument("--iters", type=int, default=12)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=1, help="torch and numba threads")
    ap.add_argument("--out", type=Path, default=Path("results/trivial_start_runs"))
    args = ap.parse_args()
    for name in ("horizon", "iters", "threads"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not args.lr > 0:
        ap.error(f"--lr must be > 0, got {args.lr}")
    for name in ("tasks", "seeds"):  # a cell twice would run and be tabulated twice
        values = getattr(args, name)
        if len(set(values)) != len(values):
            ap.error(
                f"argument --{name}: lists {sorted({v for v in values if values.count(v) > 1})} more than once"
            )
    # numba first: starting its pool resets the OpenMP thread count torch shares
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    cells = [(t, s) for t in args.tasks for s in args.seeds]
    meta = {
        "commit": git_revision(),
        "horizon": args.horizon,
        "iters": args.iters,
        "lr": args.lr,
        "threads": args.threads,
    }
    runs: list[dict] = []
    failed: list[dict] = []
    for t, s in tqdm(cells, desc="runs"):
        try:
            runs.append(run(t, s, args.horizon, args.iters, args.lr))
        except Exception as e:  # noqa: BLE001 (one failed run does not lose the others)
            if interrupted(e):
                raise KeyboardInterrupt from e
            failed.append({"task": t, "seed": s, "error": f"{type(e).__name__}: {e}"})
            tqdm.write(f"{t} seed {s}: FAILED {failed[-1]['error']}")
        write(args.out, {**meta, "runs": runs, "failed": failed})  # after every run: an interrupt keeps them
    print(write(args.out, {**meta, "runs": runs, "failed": failed}))
    print("wrote", args.out / "trivial_start_runs.json", args.out / "table.md")
    if failed:
        sys.exit(1)


def write(out: Path, meta: dict) -> str:
    """Write ``trivial_start_runs.json`` and ``table.md`` under ``out``; returns the table."""
    (out / "trivial_start_runs.json").write_text(json.dumps(meta, indent=1))
    lines = [
        "| task | seed | loss start | loss best | decrease 1 - best / start | s per iteration (median) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in meta["runs"]:
        sec = statistics.median(r["seconds"])
        lines.append(
            f"| {r['task']} | {r['seed']} | {r['losses'][0]:.10g} | {min(r['losses']):.10g} | {r['decrease']:.2g} "
            f"| {sec:.1f} |"
        )
    lines += [f"| {f['task']} | {f['seed']} | failed: {f['error']} | | | |" for f in meta["failed"]]
    table = "\n".join(lines)
    (out / "table.md").write_text(table + "\n")
    return table


if __name__ == "__main__":
    main()
