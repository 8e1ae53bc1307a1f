"""Where a task core's step spends its time on a device: cProfile's Python-level table and torch.profiler's operator
table (with CUDA, the kernel launches, the device operations and the device's busy time) of one step.

For every ``TASK:B`` of ``--cases``: the core is made on ``--device`` (float64), reset with seed 0 and B
environments, stepped once untimed (compilation, CUDA context, the landing), then one step from there under
cProfile (its wall time is the header's figure) and the same step again under torch.profiler. On the CPU the
contact model is switched to its tensor code (``ContactConfig(backend="torch")``, what other devices run) unless
``--numba``. Writes ``prof_TASK_B.txt`` per case under ``--out``.

    python scripts/profile_task_step.py --device cuda --cases Push:1 Billiards:128 --out results/profile_cuda
    python scripts/profile_task_step.py --device cpu --cases Push:1 --out results/profile_torch_path
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import pstats
import time
from pathlib import Path

import torch
from _cli import folder_problem, torch_device
from torch.profiler import ProfilerActivity, profile

from cfd_torch.envs import TASKS, make_core, rollout


def case(text: str) -> tuple[str, int]:
    """An argparse ``type=``: TASK:B."""
    task, _, b = text.partition(":")
    if task not in TASKS or not b.isdigit() or int(b) < 1:
        raise argparse.ArgumentTypeError(
            f"must be TASK:B with TASK one of {', '.join(TASKS)} and B >= 1, got {text!r}"
        )
    return task, int(b)


def profile_step(task: str, batch: int, device: torch.device, numba: bool) -> str:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    core = make_core(f"cfd_torch/{task}-v0", device=device)
    if device.type == "cpu" and not numba:
        core.scene = core.scene.replace(contact=dataclasses.replace(core.scene.contact, backend="torch"))
    gen = torch.Generator().manual_seed(0)
    a = (torch.rand(2, batch, core.action_dim, generator=gen, dtype=torch.float64) - 0.5).to(device)
    start = rollout(core, core.reset(seed=0, batch_size=batch), a[:1]).final
    sync()
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    rollout(core, start, a[1:])
    sync()
    pr.disable()
    wall = time.perf_counter() - t0
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=acts) as prof:
        rollout(core, start, a[1:])
        sync()
    ops = prof.key_averages()
    device_ops = sum(e.count for e in ops if e.device_type.name == "CUDA")  # kernels, copies and fills
    launches = sum(e.count for e in ops if e.key == "cudaLaunchKernel")
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("cumtime").print_stats(35)
    head = f"{task} B={batch} one step on {device}: {wall:.3f} s (cProfile on)"
    if device.type == "cuda":
        head += f"; {launches} kernel launches, {device_ops} device operations (kernels, copies, fills)"
    table = ops.table(sort_by="self_cpu_time_total", row_limit=30, max_name_column_width=60)
    return f"{head}\n\n{table}\n\n{buf.getvalue()}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", type=torch_device, default="cuda", help="cpu, cuda or cuda:N")
    ap.add_argument(
        "--cases", nargs="+", type=case, default=[("Push", 1), ("Billiards", 128)], help="TASK:B ..."
    )
    ap.add_argument("--numba", action="store_true", help="on the CPU, keep the numba kernels")
    ap.add_argument("--out", type=Path, default=Path("results/profile_task_step"), help="output folder")
    args = ap.parse_args()
    problem = folder_problem(args.out)
    if problem:
        ap.error(f"argument --out: {problem}")
    device = args.device
    args.out.mkdir(parents=True, exist_ok=True)
    for task, batch in args.cases:
        text = profile_step(task, batch, device, args.numba)
        (args.out / f"prof_{task}_{batch}.txt").write_text(text)
        print(text.splitlines()[0], flush=True)


if __name__ == "__main__":
    main()
