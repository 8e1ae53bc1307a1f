"""What an accelerator buys: batched differentiable rollouts of the task cores on the CPU and on a device, side by side.

For every task of ``--tasks``, batch size B of ``--batches`` and device (``cpu``, then ``--device``): the core is
made on that device (float64), reset with seed 0 and ``batch_size=B``, and rolled out ``--horizon`` steps with seeded
uniform random actions in [-0.5, 0.5] that require grad, then ``torch.autograd.grad`` of the summed rewards; one
untimed warm-up rollout of one step first (numba compilation, CUDA context and allocator), then ``--runs`` timed
rollouts (wall time, the device synchronised around each phase), medians. Environment steps per second count B
environments stepped ``--horizon`` times (forward only, and forward + backward). The two devices' rewards must agree
to 1e-7 of their magnitude, absolutely below 1 (the CPU's numba kernels and the device's tensor code take different
round-off paths; a Newton step may land within the solver's tolerance elsewhere): a larger difference is reported
in the table's "same" column. A (task, device) stops at the first batch size whose rollouts took longer than
``--budget-s``.

Writes ``bench_device.json``, ``bench_device.md`` (printed too) and ``bench_device.png`` (environment steps per
second, forward + backward, against B; one panel per task) under ``--out``.

    python scripts/bench_device.py --device cuda --out results/bench_device
    python scripts/bench_device.py --device cuda --tasks Billiards --batches 1 16 256 --horizon 10
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numba  # noqa: E402
import torch  # noqa: E402
from _cli import folder_problem, positive_float, positive_int, torch_device  # noqa: E402
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch.envs import TASKS, make_core, rollout  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_rollouts(task: str, device: torch.device, batch: int, horizon: int, runs: int) -> dict:
    """Medians of ``runs`` timed rollouts of ``batch`` environments of ``task`` on ``device``."""
    core = make_core(f"cfd_torch/{task}-v0", device=device)
    state = core.reset(seed=0, batch_size=batch)
    gen = torch.Generator().manual_seed(0)
    actions = (torch.rand(horizon, batch, core.action_dim, generator=gen, dtype=torch.float64) - 0.5).to(
        device
    )

    def once(a: torch.Tensor) -> tuple[float, float, torch.Tensor]:
        a = a.clone().requires_grad_(True)
        _sync(device)
        t0 = time.perf_counter()
        out = rollout(core, state, a)
        _sync(device)
        t1 = time.perf_counter()
        torch.autograd.grad(out.rewards.sum(), a)
        _sync(device)
        return t1 - t0, time.perf_counter() - t1, out.rewards.detach().cpu()

    once(actions[:1])
    timed = [once(actions) for _ in range(runs)]
    fwd = statistics.median(t[0] for t in timed)
    bwd = statistics.median(t[1] for t in timed)
    steps = batch * horizon
    return {
        "task": task, "device": str(device), "batch": batch, "horizon": horizon,
        "forward_s": fwd, "backward_s": bwd, "forward_runs_s": [t[0] for t in timed],
        "backward_runs_s": [t[1] for t in timed], "env_steps_per_s_forward": steps / fwd,
        "env_steps_per_s": steps / (fwd + bwd), "rewards": timed[0][2].tolist(),
    }  # fmt: skip


def table(out: dict) -> str:
    dev = out["config"]["device"]
    lines = [
        f"Batched rollouts of {out['config']['horizon']} steps (seed 0, random actions in [-0.5, 0.5]), float64, "
        f"medians of {out['config']['runs']} runs, wall time, at {out['commit']}; CPU: {out['cpu_threads']} torch / "
        f"{out['numba_threads']} numba threads; device: {out['device_name']}",
        "",
        f"| task | B | cpu fwd ms/step | cpu fwd+bwd env-steps/s | {dev} fwd ms/step | {dev} fwd+bwd env-steps/s "
        f"| {dev} / cpu | same |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    rows = {(r["task"], r["device"], r["batch"]): r for r in out["rows"]}
    for task in out["config"]["tasks"]:
        for B in out["config"]["batches"]:
            c, d = rows.get((task, "cpu", B)), rows.get((task, dev, B))
            if c is None and d is None:
                continue

            def cells(r):
                if r is None:
                    return "-", "-"
                return f"{1e3 * r['forward_s'] / r['horizon']:.1f}", f"{r['env_steps_per_s']:.1f}"

            ratio = f"{d['env_steps_per_s'] / c['env_steps_per_s']:.2f}x" if c and d else "-"
            same = "-"
            if c and d:
                rc, rd = torch.tensor(c["rewards"]), torch.tensor(d["rewards"])
                same = (
                    "yes" if float((rc - rd).abs().max()) <= 1e-7 * max(1.0, float(rc.abs().max())) else "NO"
                )
            lines.append(
                f"| {task} | {B} | {' | '.join(cells(c))} | {' | '.join(cells(d))} | {ratio} | {same} |"
            )
    return "\n".join(lines)


def plot(out: dict, path: Path) -> None:
    tasks = out["config"]["tasks"]
    fig, axes = plt.subplots(1, len(tasks), figsize=(3.6 * len(tasks), 3.4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for dev, color in (("cpu", "C0"), (out["config"]["device"], "C3")):
            rows = [r for r in out["rows"] if r["task"] == task and r["device"] == dev]
            ax.plot(
                [r["batch"] for r in rows], [r["env_steps_per_s"] for r in rows], "-o", color=color, label=dev
            )
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_title(task)
        ax.set_xlabel("environments in the batch")
        ax.set_ylabel("env steps/s (fwd + bwd)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--device",
        type=torch_device,
        default="cuda",
        help="the device to time beside the CPU: cuda or cuda:N",
    )
    ap.add_argument("--tasks", nargs="+", choices=TASKS, default=["Billiards", "Push", "Sort"], help="tasks")
    ap.add_argument("--batches", nargs="+", type=positive_int, default=[1, 8, 64], help="batch sizes B")
    ap.add_argument("--horizon", type=positive_int, default=5, help="steps per rollout")
    ap.add_argument("--runs", type=positive_int, default=2, help="timed rollouts per case (median)")
    ap.add_argument(
        "--budget-s", type=positive_float, default=60.0,
        help="a (task, device) stops after the first batch size whose rollouts took longer than this",
    )  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path("results/bench_device"), help="output folder")
    args = ap.parse_args()
    problem = folder_problem(args.out)
    if problem:
        ap.error(f"argument --out: {problem}")
    device = args.device
    if device.type != "cuda":
        ap.error(f"argument --device: must be cuda or cuda:N (the CPU is the other side), got {device}")
    args.out.mkdir(parents=True, exist_ok=True)
    batches = sorted(set(args.batches))
    rows = []
    jobs = [(task, dev) for task in args.tasks for dev in (torch.device("cpu"), device)]
    with tqdm(total=len(jobs) * len(batches), desc="bench_device") as bar:
        for task, dev in jobs:
            for B in batches:
                t0 = time.perf_counter()
                rows.append(time_rollouts(task, dev, B, args.horizon, args.runs))
                bar.update()
                if time.perf_counter() - t0 > args.budget_s:
                    bar.update(len(batches) - 1 - batches.index(B))
                    break
    out = {
        "commit": git_revision(),
        "torch": torch.__version__,
        "cpu_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "device_name": torch.cuda.get_device_name(device),
        "config": {
            "device": str(device),
            "tasks": args.tasks,
            "batches": batches,
            "horizon": args.horizon,
            "runs": args.runs,
            "budget_s": args.budget_s,
        },  # fmt: skip
        "rows": rows,
    }
    (args.out / "bench_device.json").write_text(json.dumps(out, indent=1))
    text = table(out)
    (args.out / "bench_device.md").write_text(text + "\n")
    plot(out, args.out / "bench_device.png")
    print(text)


if __name__ == "__main__":
    main()
