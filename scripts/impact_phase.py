"""Restitution and rollout-gradient bias against impact phase: where in an implicit step the impact falls.

How an impact resolved within one implicit step depends on where in the step it falls.

Scene. Two equal bodies, no gravity, no friction: the striker (body 0) moves along +x at ``v`` toward the struck
body (body 1) at rest, face to face: two 320-face icospheres of radius 0.1 m, a face of each turned to face the
other (``balls``), or two 0.1 m cubes (``cubes``). The initial gap is ``gap0 + phase v dt``: sweeping ``phase``
over [0, 1) moves the impact through one step while nothing else changes. Rollout of ``--duration`` (0.3 s).

Measured per run: the restitution e = (v1 - v0) / v from the bodies' x velocities at the end, and the rollout
gradient d x1(T) / d x0(0) of the struck body's final position in the striker's start (autograd through the rollout,
the library's adjoint). If e did not depend on the phase, shifting the striker's start by s would shift the impact
time by -s / v and the struck body's final position by (1 + e) / 2 s: the gradient's physical value. The bias is
gradient - (1 + e) / 2. Where e varies with the phase, the gradient of the discrete map carries its derivative,
(T - t_impact) / 2 de/dphase / dt: a variation of e by 1e-3 over a step is amplified by (T - t_impact) / dt.

Also ``--substeps k`` runs every step as k sub-steps of dt / k (the impact resolved finer).

The cubes do not stay aligned: face to face is a saddle of the potential in the twist about x, and they leave
the impact turning at about 1 rad/s in opposite senses (the table's max spin column; v = 1, dt = 0.01).

A run whose step fails (the simulator's ``StepError``) is recorded with its error and left out of the table; any
other exception stops the script.

Writes ``<out>/impact_phase.json`` (every run), ``<out>/impact_phase.md`` (per scene, speed, dt: range of e, range
and largest |bias|) and ``<out>/impact_phase.png`` (e and the gradient against phase).

    python scripts/impact_phase.py --out results/impact_phase                 # about 15 min on 2 cores
    python scripts/impact_phase.py --out results/impact_phase --quick         # 1 speed, 1 dt, 8 phases
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import trimesh
from _cli import apply_preset, folder_problem, positive_float, positive_int
from _provenance import git_revision, json_args
from tqdm import tqdm

from cfd_torch import ContactConfig, Scene, State, StepError, rigid_body, rollout

F64 = torch.float64


def _turn(mesh: trimesh.Trimesh, normal: np.ndarray, to: np.ndarray) -> trimesh.Trimesh:
    """The mesh rotated so that ``normal`` points along ``to``."""
    a, b = normal / np.linalg.norm(normal), to / np.linalg.norm(to)
    v, c = np.cross(a, b), float(np.dot(a, b))
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    R = np.eye(3) + vx + vx @ vx / (1.0 + c)
    T = np.eye(4)
    T[:3, :3] = R
    out = mesh.copy()
    out.apply_transform(T)
    return out


def bodies(scene: str):
    """The striker and the struck body, facing each other along x."""
    if scene == "cubes":
        cube = rigid_body(trimesh.creation.box((0.1, 0.1, 0.1)))
        return cube, cube
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    a = _turn(ball, ball.face_normals[0], np.array([1.0, 0.0, 0.0]))  # face 0 toward +x
    b = _turn(ball, ball.face_normals[0], np.array([-1.0, 0.0, 0.0]))  # face 0 toward -x
    return rigid_body(a), rigid_body(b)


def run(pair, *, phase: float, v: float, dt: float, duration: float, substeps: int, gap0: float) -> dict:
    a, b = pair
    h = dt / substeps
    scene = Scene([a, b], dt=h, gravity=(0.0, 0.0, 0.0))
    ra = float(a.bsh.vertices[:, 0].max())
    rb = -float(b.bsh.vertices[:, 0].min())
    x0 = torch.tensor(-ra - gap0 - phase * v * dt, dtype=F64, requires_grad=True)
    q = torch.zeros(2, 6, dtype=F64)
    q[1, 0] = rb
    q = torch.cat([torch.cat([x0[None], torch.zeros(5, dtype=F64)])[None], q[1:]])
    vel = torch.zeros(2, 6, dtype=F64)
    vel[0, 0] = v
    steps = int(round(duration / h))
    traj = rollout(scene, State(q, q - h * vel), [None] * steps)
    x1 = traj.q[-1, 1, 0]
    (grad,) = torch.autograd.grad(x1, x0)
    with torch.no_grad():
        v_end = (traj.q[-1] - traj.q[-2]) / h
        e = float(v_end[1, 0] - v_end[0, 0]) / v
        spin = float(v_end[:, 3:].norm(dim=1).max())
    g = float(grad)
    return {"restitution": e, "gradient": g, "bias": g - 0.5 * (1.0 + e), "spin": spin}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("results/impact_phase"))
    p.add_argument("--scenes", nargs="+", default=["balls", "cubes"], choices=["balls", "cubes"])
    p.add_argument(
        "--speeds", nargs="+", type=positive_float, default=[0.1, 0.3, 1.0, 3.0], help="striker speeds [m/s]"
    )
    p.add_argument(
        "--dts", nargs="+", type=positive_float, default=[0.02, 0.01, 0.005], help="time steps [s]"
    )
    p.add_argument(
        "--phases", type=positive_int, default=16, help="phases per step, evenly spread over [0, 1)"
    )
    p.add_argument("--substeps", nargs="+", type=positive_int, default=[1], help="sub-steps per step")
    p.add_argument("--duration", type=positive_float, default=0.3, help="rollout length [s]")
    p.add_argument(
        "--gap0", type=positive_float, default=0.01, help="gap at phase 0 [m], above the contact margin"
    )
    p.add_argument("--quick", action="store_true", help="1 m/s, dt 0.01, 8 phases, cubes (where not given)")
    args = p.parse_args(argv)
    if args.quick:  # its values for the settings not given
        apply_preset(p, args, {"scenes": ["cubes"], "speeds": [1.0], "dts": [0.01], "phases": 8}, argv)
    if args.duration < max(args.dts):
        p.error(
            f"argument --duration: {args.duration:g} s is shorter than the longest --dts step {max(args.dts):g} s"
        )
    margin = ContactConfig().margin  # the Scene's default, which run() uses
    if args.gap0 <= margin:
        p.error(
            f"argument --gap0: must exceed the contact margin {margin:g} m (the bodies start apart), got {args.gap0:g}"
        )
    # the latest phase reaches contact in free flight at gap0 / v + dt; a step more resolves it. Later, e and the
    # gradient would be read before (e = -1) or without (a far-field bounce) the impact
    late = max(args.gap0 / v + 2 * dt for v in args.speeds for dt in args.dts)
    if late > args.duration:
        p.error(
            f"argument --duration: {args.duration:g} s ends before the impact is over (gap0 / v + 2 dt = {late:g} s "
            "at the slowest --speeds and longest --dts); give a longer --duration, a smaller --gap0 or faster --speeds"
        )
    problem = folder_problem(args.out)
    if problem:
        p.error(f"argument --out: {problem}")
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", category=UserWarning)
    args.out.mkdir(parents=True, exist_ok=True)
    configs = [
        (s, v, dt, k) for s in args.scenes for v in args.speeds for dt in args.dts for k in args.substeps
    ]
    runs, pairs = [], {s: bodies(s) for s in args.scenes}
    bar = tqdm(total=len(configs) * args.phases, desc="impact phases")
    t0 = time.time()
    for scene, v, dt, k in configs:
        for i in range(args.phases):
            phase = i / args.phases
            try:
                r = run(
                    pairs[scene], phase=phase, v=v, dt=dt, duration=args.duration, substeps=k, gap0=args.gap0
                )
                r["error"] = None
            except StepError as err:  # a failed step is a result here, not a crash
                r = {"restitution": None, "gradient": None, "bias": None, "spin": None, "error": repr(err)}
            runs.append({"scene": scene, "speed": v, "dt": dt, "substeps": k, "phase": phase, **r})
            bar.update()
    bar.close()
    rows = []
    for scene, v, dt, k in configs:
        rs = [
            r for r in runs
            if (r["scene"], r["speed"], r["dt"], r["substeps"]) == (scene, v, dt, k) and r["error"] is None
        ]  # fmt: skip
        if not rs:
            continue
        e = [r["restitution"] for r in rs]
        b = [r["bias"] for r in rs]
        rows.append({
            "scene": scene, "speed": v, "dt": dt, "substeps": k, "runs": len(rs),
            "failed": args.phases - len(rs), "e_min": min(e), "e_max": max(e), "bias_min": min(b),
            "bias_max": max(b), "bias_abs_max": max(abs(x) for x in b),
            "bias_median_abs": statistics.median(abs(x) for x in b),
            "spin_max": max(r["spin"] for r in rs),
        })  # fmt: skip
    result = {
        "revision": git_revision(), "args": json_args(args),
        "wall_s": time.time() - t0, "summary": rows, "runs": runs,
    }  # fmt: skip
    (args.out / "impact_phase.json").write_text(json.dumps(result, indent=1))
    lines = [
        "| scene | v (m/s) | dt (s) | substeps | e range | bias range | max abs bias | median abs bias "
        "| max spin (rad/s) |",
        "|---|---:|---:|---:|---|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['speed']:g} | {r['dt']:g} | {r['substeps']} | {r['e_min']:.4f}-{r['e_max']:.4f} "
            f"| {r['bias_min']:+.3f} to {r['bias_max']:+.3f} | {r['bias_abs_max']:.3f} | {r['bias_median_abs']:.3f} "
            f"| {r['spin_max']:.3f} |"
        )
    table = "\n".join(lines)
    (args.out / "impact_phase.md").write_text(f"revision {result['revision']}\n\n{table}\n")
    print(table)
    _plot(runs, configs, args.out / "impact_phase.png")
    return result


def _plot(runs, configs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({c[0] for c in configs})
    fig, axes = plt.subplots(2, len(scenes), figsize=(6 * len(scenes), 7), squeeze=False)
    for j, scene in enumerate(scenes):
        for _, v, dt, k in [c for c in configs if c[0] == scene]:
            rs = [
                r for r in runs
                if (r["scene"], r["speed"], r["dt"], r["substeps"]) == (scene, v, dt, k) and r["error"] is None
            ]  # fmt: skip
            ph = [r["phase"] for r in rs]
            label = f"v={v:g}, dt={dt:g}" + (f", {k} sub" if k > 1 else "")
            axes[0, j].plot(ph, [r["restitution"] for r in rs], "o-", ms=3, label=label)
            axes[1, j].plot(ph, [r["bias"] for r in rs], "o-", ms=3, label=label)
        axes[0, j].set_title(f"{scene}: restitution against impact phase")
        axes[1, j].set_title("gradient bias d x1(T)/d x0(0) - (1 + e)/2")
        axes[1, j].axhspan(-0.05, 0.05, color="0.9")
        axes[1, j].set_xlabel("impact phase (fraction of a step)")
        axes[0, j].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
