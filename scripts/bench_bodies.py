"""Cost of a step against the number of bodies: N small bodies at rest on a floor, or dropped as a pile.

N bodies alternating 5 cm cubes and 80-face icospheres of radius 2.5 cm (a face down), mu = 3e-10 (light bodies),
friction 0.5, dt = 0.01, on a static 2.4 m x 2.4 m floor box (the Scene refines it to the bodies' scale). ``grid``:
the bodies on a square grid of 0.1 m pitch, 1.5 mm above the floor, turned by seeded random yaws (every body its
own island of the Newton solve); ``pile``: a cubic lattice of 7 cm pitch, seeded jitter, dropped (its steps 4 to
``--steps``: the landing). For each N: the Scene's construction, then ``--steps`` steps; the figures are CPU times
(``time.process_time``) on one torch and one numba thread, the median over the timed steps (grid: all but the first;
pile: steps 4 and later), with the Newton iterations, contact evaluations and the process's peak resident memory.
The library is the one Python imports: run it with ``PYTHONPATH=<other checkout>`` to time another revision side
by side.

Writes ``bench_bodies.json``, ``bench_bodies.md`` (printed too) and ``bench_bodies.png`` (seconds per step against N,
log-log) under ``--out``.

    python scripts/bench_bodies.py --sizes 10 30 100 200 --out results/bench_bodies
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import folder_problem, positive_int  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cfd_torch  # noqa: E402
from cfd_torch import Scene, rigid_body, step  # noqa: E402

EDGE, RADIUS, GAP = 0.05, 0.025, 1.5e-3


def library_revision() -> str:
    """The short commit of the checkout whose cfd_torch Python imported, "+dirty" with uncommitted changes to it
    ("unknown" outside a git checkout)."""
    where = Path(cfd_torch.__file__).resolve().parents[1]
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=where)
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "cfd_torch"], capture_output=True, text=True, cwd=where
    )
    return (out.stdout.strip() or "unknown") + ("+dirty" if dirty.stdout.strip() else "")


def bodies():
    cube = rigid_body(trimesh.creation.box(extents=(EDGE,) * 3))
    ball = trimesh.creation.icosphere(subdivisions=1, radius=RADIUS)
    ball.apply_transform(trimesh.geometry.align_vectors(ball.face_normals[0], [0, 0, -1]))
    return cube, rigid_body(ball), float(-ball.vertices[:, 2].min())


def scene(n: int, layout: str, protos) -> tuple[Scene, torch.Tensor]:
    cube, ball, ball_h = protos
    rng = np.random.default_rng(0)
    poses = []
    for i in range(n):
        if layout == "grid":
            m = math.ceil(math.sqrt(n))
            x, y = (i % m - (m - 1) / 2) * 0.1, (i // m - (m - 1) / 2) * 0.1
            z = (EDGE / 2 if i % 2 == 0 else ball_h) + GAP
            poses.append([x, y, z, 0.0, 0.0, rng.uniform(-math.pi, math.pi)])
        else:
            m = math.ceil(n ** (1 / 3) - 1e-9)
            ix, iy, iz = i % m, (i // m) % m, i // (m * m)
            jitter = rng.uniform(-0.004, 0.004, 2)
            poses.append([(ix - (m - 1) / 2) * 0.07 + jitter[0], (iy - (m - 1) / 2) * 0.07 + jitter[1],
                          0.045 + iz * 0.07, *rng.uniform(-0.2, 0.2, 3)])  # fmt: skip
    floor = rigid_body(trimesh.creation.box(extents=(2.4, 2.4, 0.1)), kind="static")
    s = Scene([floor] + [cube if i % 2 == 0 else ball for i in range(n)], mu=3e-10, friction=0.5)
    return s, torch.tensor([[0, 0, -0.05, 0, 0, 0], *poses], dtype=torch.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=positive_int, nargs="+", default=[10, 30, 100, 200])
    ap.add_argument("--layout", choices=["grid", "pile"], default="grid")
    ap.add_argument("--steps", type=positive_int, default=5)
    ap.add_argument("--out", type=Path, default=Path("results/bench_bodies"))
    args = ap.parse_args()
    if args.layout == "pile" and args.steps < 4:
        ap.error("argument --steps: must be at least 4 for a pile (its landing steps are timed)")
    if problem := folder_problem(args.out):
        ap.error(f"argument --out: {problem}")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    protos = bodies()
    s, q = scene(3, args.layout, protos)  # the kernels compiled outside the timings
    state = s.initial_state(q)
    for _ in range(2):
        state = step(s, state)
    rows = []
    for n in tqdm(args.sizes, desc=f"bench_bodies {args.layout}"):
        t0 = time.process_time()
        s, q = scene(n, args.layout, protos)
        built = time.process_time() - t0
        state, times, iters, evals = s.initial_state(q), [], [], []
        for _ in range(args.steps):
            t0 = time.process_time()
            state, info = step(s, state, return_info=True)
            times.append(time.process_time() - t0)
            iters.append(int(info.newton_iters))
            evals.append(int(info.contact_evals))
        timed = slice(1, None) if args.layout == "grid" else slice(3, None)
        rows.append({
            "n": n, "construct_s": built, "step_s": statistics.median(times[timed] or times), "step_times": times,
            "newton_iters": iters, "contact_evals": evals,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        })  # fmt: skip
    result = {"commit": library_revision(), "layout": args.layout,
              "steps": args.steps, "rows": rows}  # fmt: skip
    (args.out / "bench_bodies.json").write_text(json.dumps(result, indent=1))
    lines = [
        f"{args.layout}, library at {result['commit']}, CPU seconds on one thread",
        "",
        "| N | construct [s] | s / step (median) | Newton iterations | evaluations | peak RSS [MB] |",
        "|---:|---:|---:|---|---|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['construct_s']:.2f} | {r['step_s']:.3f} | {r['newton_iters']} | {r['contact_evals']} "
            f"| {r['peak_rss_mb']:.0f} |"
        )
    (args.out / "bench_bodies.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.loglog([r["n"] for r in rows], [r["step_s"] for r in rows], "o-")
    ax.set_xlabel("bodies N")
    ax.set_ylabel("CPU s per step (median)")
    ax.set_title(f"{args.layout}, {result['commit']}")
    fig.tight_layout()
    fig.savefig(args.out / "bench_bodies.png", dpi=120)
    print(f"wrote {args.out}/bench_bodies.json, .md and .png")


if __name__ == "__main__":
    main()
