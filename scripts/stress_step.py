"""Stress test of the stepper: random scenes of tumbling bodies dropped on a floor, run for 1 s of simulated time.

Each scene (seeded, reproducible) has 1-4 bodies drawn from a box 0.2 x 0.15 x 0.1, a 320-face ball of radius 0.08,
a capsule (radius 0.05, length 0.2) and a plate 0.3 x 0.3 x 0.02, stacked 0.3 m apart above a static 3 x 3 m floor
(refined to 0.15 m triangles), with random rotations (up to 3 rad about each axis), velocities up to 2 m/s and spins
up to 10 rad/s per axis; dt from {0.005, 0.01, 0.02, 0.033} s and friction from {0, 0.3, 1.0}; in half of the scenes
a kinematic paddle (0.05 x 0.8 x 0.2 m, 5 mm above the floor) sweeps along x through them at 0.3-2 m/s. Every step
must converge (no StepError), give finite poses, and leave every body in a feasible pose (the stepper guarantees it
with its collision query; checked here independently: no centre of mass below the floor's top while over the floor,
and no body pair whose potential is +inf, evaluated by the scene's contact model).
``--duration`` shortens the simulated time (a smoke run).

Writes ``<out>/stress_step.json`` (per scene: bodies, dt, friction, outcome, steps, Newton iterations, wall time)
and ``<out>/stress_step.md`` (a table and the failures).

    python scripts/stress_step.py --out results/stress_step                  # 30 scenes, about 10 min
    python scripts/stress_step.py --out results/stress_step --seeds 100 130  # another range
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
import trimesh
from _cli import positive_float
from _provenance import git_revision
from tqdm import tqdm

from cfd_torch import Action, Scene, rigid_body, step

F64 = torch.float64


def shapes() -> dict:
    return {
        "box": rigid_body(trimesh.creation.box((0.2, 0.15, 0.1))),
        "ball": rigid_body(trimesh.creation.icosphere(subdivisions=2, radius=0.08)),
        "capsule": rigid_body(trimesh.creation.capsule(height=0.2, radius=0.05, count=[12, 12])),
        "plate": rigid_body(trimesh.creation.box((0.3, 0.3, 0.02))),
    }


def floor():
    mesh = trimesh.creation.box((3.0, 3.0, 0.1))
    mesh.apply_translation([0.0, 0.0, -0.05])
    return rigid_body(mesh, kind="static", max_edge=0.15)


PADDLE = rigid_body(trimesh.creation.box((0.05, 0.8, 0.2)), kind="kinematic")


def scene_for(seed: int, kinds: dict, ground) -> tuple[Scene, torch.Tensor, torch.Tensor, dict]:
    g = torch.Generator().manual_seed(seed)

    def r() -> float:
        return float(torch.rand((), generator=g, dtype=F64))

    nb = 1 + int(r() * 4)
    names = [list(kinds)[int(r() * 4)] for _ in range(nb)]
    dt = [0.005, 0.01, 0.02, 0.033][int(r() * 4)]
    friction = [0.0, 0.3, 1.0][int(r() * 3)]
    poses = [[0.0] * 6]
    for i in range(nb):
        w = [(r() - 0.5) * 6 for _ in range(3)]
        poses.append([(r() - 0.5) * 0.4, (r() - 0.5) * 0.4, 0.25 + 0.3 * i, *w])
    v = torch.zeros(nb + 1, 6, dtype=F64)
    for i in range(1, nb + 1):
        v[i, :3] = torch.tensor([(r() - 0.5) * 4 for _ in range(3)], dtype=F64)
        v[i, 3:] = torch.tensor([(r() - 0.5) * 20 for _ in range(3)], dtype=F64)
    paddle_speed = 0.3 + 1.7 * r() if r() < 0.5 else 0.0
    bodies = [ground] + [kinds[k] for k in names]
    if paddle_speed:
        bodies.append(PADDLE)
        poses.append([-0.8, 0.0, 0.105, 0.0, 0.0, 0.0])
        v = torch.cat([v, torch.zeros(1, 6, dtype=F64)])
    scene = Scene(bodies, dt=dt, friction=friction)
    desc = {"bodies": names, "dt": dt, "friction": friction, "paddle_speed": paddle_speed}
    return scene, torch.tensor(poses, dtype=F64), v, desc


def violation(scene: Scene, q: torch.Tensor) -> str | None:
    """An independent check of the end-of-step poses (None when fine)."""
    if not bool(torch.isfinite(q).all()):
        return "non-finite poses"
    c = q[[i for i, b in enumerate(scene.bodies) if b.kind == "dynamic"]]
    under = (c[:, 2] < 0) & (c[:, 0].abs() < 1.45) & (c[:, 1].abs() < 1.45)
    if bool(under.any()):
        return f"a centre of mass below the floor: {c[under].tolist()}"
    pairs = torch.cat([torch.zeros(len(scene.pairs), 1, dtype=torch.long), scene.pairs], 1)  # (P, 3) scene 0
    value = scene.contact_model.evaluate(q.detach().to(F64)[None], pairs, 0).value  # (P,) the potentials
    bad = torch.isinf(value)
    if bool(bad.any()):
        return "penetrating body pairs: " + ", ".join(f"({i}, {j})" for i, j in scene.pairs[bad].tolist())
    return None


def run(seed: int, kinds: dict, ground, duration: float = 1.0) -> dict:
    scene, poses, vel, desc = scene_for(seed, kinds, ground)
    state = scene.initial_state(poses, vel)
    steps = max(1, round(duration / scene.dt))
    iters: list[int] = []
    t0 = time.perf_counter()
    outcome, error = "ok", None
    try:
        for k in range(steps):
            action = None
            if desc["paddle_speed"]:
                x = -0.8 + desc["paddle_speed"] * scene.dt * (k + 1)
                action = Action(target=torch.tensor([[x, 0.0, 0.105, 0.0, 0.0, 0.0]], dtype=F64))
            state, info = step(scene, state, action, return_info=True)
            iters.append(int(info.newton_iters))
            bad = violation(scene, state.q)
            if bad:
                outcome, error = "violation", bad
                break
    except Exception as e:  # noqa: BLE001 (every failure is a result here)
        outcome, error = type(e).__name__, str(e)
    return {
        "seed": seed,
        **desc,
        "outcome": outcome,
        "error": error,
        "steps_done": len(iters),
        "steps": steps,
        "newton_iters_max": max(iters, default=0),
        "newton_iters_median": statistics.median(iters) if iters else 0,
        "wall_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/stress_step"))
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 30), metavar=("FIRST", "END"))
    ap.add_argument("--duration", type=positive_float, default=1.0, help="simulated time per scene [s]")
    args = ap.parse_args()
    if not args.duration > 0:
        ap.error(f"--duration must be > 0, got {args.duration}")
    if not args.seeds[1] > args.seeds[0]:
        ap.error(
            f"--seeds FIRST END must have END > FIRST (seeds FIRST..END-1), got {args.seeds[0]} {args.seeds[1]}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    kinds, ground = shapes(), floor()
    rows = []
    for seed in tqdm(range(*args.seeds), desc="scenes"):
        row = run(seed, kinds, ground, args.duration)
        rows.append(row)
        tqdm.write(
            f"seed {seed}: {row['bodies']} dt={row['dt']} friction={row['friction']} paddle={row['paddle_speed']:.2f}: "
            f"{row['outcome']} "
            f"({row['steps_done']}/{row['steps']} steps, Newton max {row['newton_iters_max']}, {row['wall_s']:.0f} s)"
        )
    ok = sum(r["outcome"] == "ok" for r in rows)
    out = {
        "cfd_torch_commit": git_revision(),
        "scenes": rows,
        "passed": ok,
        "total": len(rows),
        "duration_s": args.duration,
    }
    (args.out / "stress_step.json").write_text(json.dumps(out, indent=1))
    lines = [
        f"Stress test (cfd_torch {out['cfd_torch_commit']}): {ok} of {len(rows)} random scenes ran {args.duration:g} s "
        "without a failure.",
        "",
        "| seed | bodies | dt | friction | paddle (m/s) | outcome | steps | Newton max / median | wall (s) |",
        "|---:|---|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {', '.join(r['bodies'])} | {r['dt']} | {r['friction']} | {r['paddle_speed']:.2f} | "
            f"{r['outcome']} | "
            f"{r['steps_done']}/{r['steps']} | {r['newton_iters_max']} / {r['newton_iters_median']:g} | "
            f"{r['wall_s']:.0f} |"
        )
    fails = [r for r in rows if r["outcome"] != "ok"]
    if fails:
        lines += ["", "Failures:"] + [f"- seed {r['seed']}: {r['outcome']}: {r['error']}" for r in fails]
    text = "\n".join(lines) + "\n"
    (args.out / "stress_step.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
