"""Throughput of the exact pair potential (pairs solved per second).

Modes, each on the same K random separated pairs (``cfd_torch.testing.random_separated_pairs``, slab gaps
log-uniform in [2e-3, 1] with unit-size triangles, margin 1e-3, tol 1e-12):

- value:              ``pair_potential`` under no_grad
- value+grad:         ``pair_potential_derivatives(..., hessian=False)`` (closed form)
- value+grad+hessian: ``pair_potential_derivatives(...)`` (closed form, 18 x 18 Hessians)
- autograd value+grad: ``pair_potential`` then ``torch.autograd.grad`` (envelope-theorem backward)

Median of ``--repeats`` runs after one warm-up, float64 and float32 inputs. Writes JSON and prints a table.

    python scripts/bench_pair.py --out results/bench_pair
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numba
import torch
from _cli import positive_int, torch_device
from _provenance import git_revision
from tqdm import tqdm

from cfd_torch import pair_potential, pair_potential_derivatives
from cfd_torch.testing import random_separated_pairs


def _modes(a: torch.Tensor, b: torch.Tensor, backend: str):
    def value():
        with torch.no_grad():
            pair_potential(a, b, backend=backend)

    def value_grad():
        pair_potential_derivatives(a, b, hessian=False, backend=backend)

    def value_grad_hess():
        pair_potential_derivatives(a, b, backend=backend)

    def autograd_value_grad():
        bb = b.detach().requires_grad_(True)
        torch.autograd.grad(pair_potential(a, bb, backend=backend).sum(), bb)

    return {
        "value": value,
        "value+grad": value_grad,
        "value+grad+hessian": value_grad_hess,
        "autograd value+grad": autograd_value_grad,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/bench_pair"), help="output folder")
    ap.add_argument(
        "--sizes", type=positive_int, nargs="+", default=[1_000, 10_000, 100_000, 1_000_000],
        help="numbers of pairs K to time",
    )  # fmt: skip
    ap.add_argument(
        "--dtypes", nargs="+", default=["float64", "float32"], choices=["float64", "float32"],
        help="input dtypes to time",
    )  # fmt: skip
    ap.add_argument(
        "--repeats", type=positive_int, default=5, help="timed runs per case (the median is kept)"
    )
    ap.add_argument(
        "--backend", default="auto", choices=["auto", "numba", "torch"],
        help="pair solver backend (auto: numba on CPU, torch elsewhere; numba needs --device cpu)",
    )  # fmt: skip
    ap.add_argument(
        "--device", type=torch_device, default="cpu", help="torch device of the inputs: cpu, cuda or cuda:N"
    )
    args = ap.parse_args()
    device = args.device
    if args.backend == "numba" and device.type != "cpu":
        ap.error(f"argument --backend: numba needs --device cpu, got {args.device!r}")
    args.out.mkdir(parents=True, exist_ok=True)

    rows = []
    jobs = [(k, dt) for k in args.sizes for dt in args.dtypes]
    for k, dt in tqdm(jobs, desc="bench_pair"):
        a, b, _ = random_separated_pairs(k, seed=1, dtype=getattr(torch, dt))
        a, b = a.to(args.device), b.to(args.device)
        for mode, fn in _modes(a, b, args.backend).items():
            fn()  # warm-up (JIT compile, allocator)
            times = []
            for _ in range(args.repeats):
                if args.device != "cpu":
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                fn()
                if args.device != "cpu":
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - t0)
            med = statistics.median(times)
            rows.append(
                {"K": k, "dtype": dt, "mode": mode, "median_s": med, "pairs_per_s": k / med, "times_s": times}
            )

    meta = {
        "commit": git_revision(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "backend": args.backend,
        "device": args.device,
        "sizes": args.sizes,
        "dtypes": args.dtypes,
        "repeats": args.repeats,
    }
    (args.out / "bench_pair.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    modes = list(_modes(a, b, args.backend))
    lines = [
        f"pairs/s (median of {args.repeats}), backend={args.backend}, device={args.device}, "
        f"commit {meta['commit']}, {meta['threads']} torch / {meta['numba_threads']} numba threads",
        "",
    ]
    header = f"| {'K':>9} | {'dtype':7} | " + " | ".join(f"{m:>20}" for m in modes) + " |"
    lines += [header, "|" + "|".join("-" * len(c) for c in header.split("|")[1:-1]) + "|"]
    for k, dt in jobs:
        cells = [next(r for r in rows if r["K"] == k and r["dtype"] == dt and r["mode"] == m) for m in modes]
        lines.append(
            f"| {k:>9} | {dt:7} | " + " | ".join(f"{c['pairs_per_s']:>20,.0f}" for c in cells) + " |"
        )
    table = "\n".join(lines) + "\n"
    (args.out / "bench_pair.md").write_text(table)
    print("\n" + table)
    print(f"wrote {args.out / 'bench_pair.json'} and {args.out / 'bench_pair.md'}")


if __name__ == "__main__":
    main()
