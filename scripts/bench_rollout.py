"""Cost of differentiable rollouts against their horizon: each task's core stepped H times from its trivial start and
its backward, optionally beside an older revision.

For every task of ``--tasks`` and horizon H of ``--horizons``: ``core.reset(seed=0)``, then ``rollout(core, state,
actions)`` with (H, 1, A) actions that require grad (zero, the trivial start; with ``--action-scale`` s > 0, seeded
uniform actions in [-s, s]), and ``torch.autograd.grad`` of the sum of its rewards with respect to the actions.
Each (revision, task) runs in a fresh process with one torch and one numba thread, every horizon ``--runs`` times
after one untimed warm-up rollout of the shortest horizon; the figures are the medians of the CPU times
(``time.process_time``, which a loaded machine disturbs less than wall time; the JSON has the wall times too) of the
forward rollout and of its backward. With ``--baseline REV`` the revision REV (a git worktree) runs the same, the
two revisions alternating task by task; the table's ratios are this / baseline (the first run at a revision
compiles its numba kernels into its worktree's cache: a few minutes). Checks that both revisions' rewards
agree (to 1e-9 of their magnitude: a solver change within its tolerances may move them that much), and so do
their gradients' norms (to 1e-6 relative).

Writes ``bench_rollout.json``, ``bench_rollout.md`` (printed too) and ``bench_rollout.png`` (forward and backward
milliseconds per step against the horizon, one panel per task) under ``--out``.

    python scripts/bench_rollout.py --out results/bench_rollout
    python scripts/bench_rollout.py --tasks Billiards Push --horizons 50 100 200 400 --baseline 74a3241 --out X
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _cli import folder_problem, nonnegative_float, positive_int  # noqa: E402
from _provenance import git_commit, git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch.envs import TASKS  # noqa: E402 (this checkout's; each revision is timed in a process of its own)

ROOT = Path(__file__).resolve().parents[1]

# One (revision, task) in a fresh process, its settings as JSON in argv[1]: the revision's root (whose cfd_torch and
# envs/ it imports), the task, the horizons, the runs and the action scale.
CHILD = r"""
import importlib.util, json, os, statistics, sys, time
import torch
cfg = json.loads(sys.argv[1])
REV, TASK, HORIZONS, RUNS, SCALE = cfg["rev"], cfg["task"], cfg["horizons"], cfg["runs"], cfg["scale"]
torch.set_num_threads(1)
import cfd_torch
here = os.path.realpath
assert here(os.path.dirname(cfd_torch.__file__)) == here(os.path.join(REV, "cfd_torch")), cfd_torch.__file__
# cfd_torch.envs is the revision's own envs/ folder (the editable install would map it to this checkout's)
envs = os.path.join(REV, "envs")
spec = importlib.util.spec_from_file_location("cfd_torch.envs", os.path.join(envs, "__init__.py"),
                                              submodule_search_locations=[envs])
sys.modules["cfd_torch.envs"] = mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
from cfd_torch.envs import make_core, rollout
core = make_core(f"cfd_torch/{TASK}-v0")
state = core.reset(seed=0)
gen = torch.Generator().manual_seed(0)

def once(H):
    a = SCALE * (2 * torch.rand(H, 1, core.action_dim, generator=gen, dtype=torch.float64) - 1)
    a.requires_grad_(True)
    w0, c0 = time.perf_counter(), time.process_time()
    out = rollout(core, state, a)
    w1, c1 = time.perf_counter(), time.process_time()
    loss = out.rewards.sum()
    (g,) = torch.autograd.grad(loss, a)
    w2, c2 = time.perf_counter(), time.process_time()
    return c1 - c0, c2 - c1, float(loss.detach()), float(g.norm()), w1 - w0, w2 - w1

once(min(HORIZONS))
res = {}
for H in HORIZONS:
    runs = []
    for _ in range(RUNS):
        gen.manual_seed(0)
        runs.append(once(H))
    res[str(H)] = {
        "forward_s": statistics.median(r[0] for r in runs),
        "backward_s": statistics.median(r[1] for r in runs),
        "forward_runs_s": [r[0] for r in runs],
        "backward_runs_s": [r[1] for r in runs],
        "forward_wall_s": statistics.median(r[4] for r in runs),
        "backward_wall_s": statistics.median(r[5] for r in runs),
        "return": runs[0][2],
        "grad_norm": runs[0][3],
    }
print(json.dumps(res))
"""


def run(path: Path, task: str, horizons: list[int], runs: int, scale: float) -> dict:
    """The child's results for one revision (its root ``path``) and task."""
    env = {**os.environ, "PYTHONPATH": str(path), "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    cfg = {"rev": str(path.resolve()), "task": task, "horizons": horizons, "runs": runs, "scale": scale}
    res = subprocess.run([sys.executable, "-c", CHILD, json.dumps(cfg)], env=env, cwd=tempfile.gettempdir(),
                         capture_output=True, text=True)  # fmt: skip
    if res.returncode != 0:
        raise SystemExit(f"the rollouts of {task} at {path} failed:\n{res.stderr.strip()[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def table(out: dict) -> str:
    base = out.get("baseline")
    head = "| task | H | forward [s] | backward [s] | fwd ms/step | bwd ms/step |"
    rule = "|---|---:|---:|---:|---:|---:|"
    if base:
        b = base["commit"]
        head += f" forward {b} | backward {b} | fwd ratio | bwd ratio | same |"
        rule += "---:|---:|---:|---:|---|"
    lines = [
        f"Rollouts from each task's trivial start (seed 0, action scale {out['config']['action_scale']:g}), median "
        f"CPU times over {out['config']['runs']} runs, one thread, at {out['commit']}"
        + (f" against {base['commit']} (ratio = this / baseline)" if base else ""),
        "",
        head,
        rule,
    ]
    for task, rows in out["tasks"].items():
        for H, r in rows.items():
            n = int(H)
            line = (
                f"| {task} | {n} | {r['forward_s']:.2f} | {r['backward_s']:.2f} | {1e3 * r['forward_s'] / n:.1f} "
                f"| {1e3 * r['backward_s'] / n:.1f} |"
            )
            if base:
                o = base["tasks"][task][H]
                same = abs(r["return"] - o["return"]) <= 1e-9 * max(1.0, abs(o["return"])) and abs(
                    r["grad_norm"] - o["grad_norm"]
                ) <= 1e-6 * max(1e-300, abs(o["grad_norm"]))
                line += (
                    f" {o['forward_s']:.2f} | {o['backward_s']:.2f} | {r['forward_s'] / o['forward_s']:.2f} | "
                    f"{r['backward_s'] / o['backward_s']:.2f} | {'yes' if same else 'NO'} |"
                )
            lines.append(line)
    return "\n".join(lines)


def plot(out: dict, path: Path) -> None:
    tasks = list(out["tasks"])
    fig, axes = plt.subplots(1, len(tasks), figsize=(3.6 * len(tasks), 3.4), squeeze=False)
    base = out.get("baseline")
    for ax, task in zip(axes[0], tasks, strict=True):
        for who, data, style in (("", out, "-"), (base["commit"] if base else "", base, "--")):
            if data is None:
                continue
            rows = data["tasks"][task]
            H = [int(h) for h in rows]
            for key, color in (("forward_s", "C0"), ("backward_s", "C3")):
                ms = [1e3 * rows[h][key] / int(h) for h in rows]
                label = f"{key.split('_')[0]} {who or data['commit']}"
                ax.plot(H, ms, style, marker="o", color=color, label=label)
        ax.set_title(task)
        ax.set_xlabel("horizon [steps]")
        ax.set_ylabel("ms per step")
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--tasks", nargs="+", choices=TASKS, default=list(TASKS), help="tasks (default: all five)"
    )
    ap.add_argument("--horizons", nargs="+", type=positive_int, default=[25, 50, 100, 200],
                    help="rollout lengths in steps")  # fmt: skip
    ap.add_argument("--runs", type=positive_int, default=3, help="timed rollouts per horizon (median)")
    ap.add_argument("--action-scale", type=nonnegative_float, default=0.0,
                    help="uniform random actions in [-s, s] (seeded); 0: zero actions, the trivial start")  # fmt: skip
    ap.add_argument(
        "--baseline", type=git_commit, metavar="REV", default=None, help="git revision to time side by side"
    )
    ap.add_argument("--out", type=Path, default=Path("results/bench_rollout"))
    args = ap.parse_args()
    problem = folder_problem(args.out)
    if problem:
        ap.error(f"--out {problem}")
    args.out.mkdir(parents=True, exist_ok=True)
    horizons = sorted(set(args.horizons))
    out = {
        "commit": git_revision(),
        "config": {
            "tasks": args.tasks,
            "horizons": horizons,
            "runs": args.runs,
            "action_scale": args.action_scale,
        },
        "tasks": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        base = None
        if args.baseline:
            base = Path(tmp) / "baseline"
            added = subprocess.run(["git", "worktree", "add", "--detach", str(base), args.baseline], cwd=ROOT,
                                   capture_output=True, text=True)  # fmt: skip
            if added.returncode != 0:
                ap.error(f"--baseline {args.baseline}: {added.stderr.strip()}")
            commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=base, capture_output=True,
                                    text=True).stdout.strip()  # fmt: skip
            out["baseline"] = {"rev": args.baseline, "commit": commit, "tasks": {}}
        try:
            for task in tqdm(args.tasks, desc="tasks"):
                if base is not None:
                    out["baseline"]["tasks"][task] = run(base, task, horizons, args.runs, args.action_scale)
                out["tasks"][task] = run(ROOT, task, horizons, args.runs, args.action_scale)
        finally:
            if base is not None:
                subprocess.run(
                    ["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, capture_output=True
                )
    text = table(out)
    print(text)
    (args.out / "bench_rollout.json").write_text(json.dumps(out, indent=1))
    (args.out / "bench_rollout.md").write_text(text + "\n")
    plot(out, args.out / "bench_rollout.png")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
