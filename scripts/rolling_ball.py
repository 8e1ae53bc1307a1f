"""A faceted ball rolling on a floor: its energy against the time step and the mesh.

A ball (an icosphere) settles on a static floor, then starts rolling without slipping (speed ``--speed`` along +x,
spin about +y of speed / its centre's height above the floor) and rolls for ``--duration`` s with friction
``--friction``. A polyhedron rolls over an edge at every facet, and each crossing is a small impact: a 320-face ball
of radius 0.1 m at 2 m/s crosses one about every 15 ms. Where the step resolves the crossings the ball loses energy
to them (rolling resistance, less for a finer mesh); where it does not, the energy is not monotone: an implicit step
minimises an incremental potential that is not convex over the facets, and backward Euler dissipates energy only
where it is convex. Energy = translational + rotational kinetic + gravitational (the floor's top at z = 0), the
velocities from the last two poses (the rotational one from their relative rotation).

Writes ``rolling_ball.json`` (settings, commit, per run the energy history and summary), ``rolling_ball.md`` (the
table) and ``rolling_ball.png`` (energy change over time, one line per mesh and step) under ``--out``.

    python scripts/rolling_ball.py --out results/rolling_ball
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import apply_preset, folder_problem, int_range, nonnegative_float, positive_float  # noqa: E402
from _provenance import git_revision, json_args  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch import Scene, rigid_body, step  # noqa: E402
from cfd_torch.rotation import quaternion, quaternion_multiply, rotation_matrix, rotation_vector  # noqa: E402

GRAVITY = 9.81
SETTLE = 0.3  # [s] at rest on the floor before the roll starts


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("results/rolling_ball"), help="output folder")
    p.add_argument("--subdivisions", type=int_range(1, 4), nargs="+", default=[2, 3],
                   help="icosphere subdivisions (2: 320 faces, 3: 1,280)")  # fmt: skip
    p.add_argument(
        "--dt", type=positive_float, nargs="+", default=[0.01, 0.005, 0.0025], help="time steps [s]"
    )
    p.add_argument("--radius", type=positive_float, default=0.1, help="ball radius [m]")
    p.add_argument("--speed", type=positive_float, default=2.0, help="initial rolling speed [m/s]")
    p.add_argument("--friction", type=nonnegative_float, default=0.3, help="friction coefficient")
    p.add_argument("--duration", type=positive_float, default=1.0, help="rolling time [s]")
    p.add_argument(
        "--quick",
        action="store_true",
        help="one mesh (320 faces), dt 0.01, 0.2 s (where not given): a smoke run",
    )
    args = p.parse_args(argv)
    if args.quick:
        apply_preset(p, args, {"subdivisions": [2], "dt": [0.01], "duration": 0.2}, argv)
    problem = folder_problem(args.out)
    if problem:
        p.error(f"argument --out: {problem}")
    return args


def angular_velocity(q: torch.Tensor, q_prev: torch.Tensor, dt: float) -> torch.Tensor:
    """World-frame angular velocity (3,) [rad/s] that turns the rotation of ``q_prev`` into that of ``q`` in ``dt``."""
    rel = quaternion_multiply(quaternion(q[3:]), quaternion(-q_prev[3:]))
    return rotation_vector(rel) / dt


def roll(subdivisions: int, dt: float, args) -> dict:
    """One run: the ball's energy history after the roll starts and its summary."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=args.radius)
    edge = float(np.mean(mesh.edges_unique_length))
    ball = rigid_body(mesh, density=1000.0)
    length = 2.0 * args.speed * args.duration + 2.0
    floor = rigid_body(trimesh.creation.box((length, 1.0, 0.2)), kind="static", max_edge=2.0 * edge)
    scene = Scene([ball, floor], dt=dt, friction=args.friction, gravity=(0.0, 0.0, -GRAVITY))
    x0 = -length / 2 + 0.5
    q = torch.tensor([[x0, 0.0, args.radius + 1.5e-3, 0, 0, 0], [0.0, 0, -0.1, 0, 0, 0]], dtype=torch.float64)
    state = scene.initial_state(q)
    for _ in range(round(SETTLE / dt)):
        state = step(scene, state)
    height = float(state.q[0, 2])  # the centre above the floor's top: the rolling radius
    q_prev = state.q.clone()
    q_prev[0, 0] -= dt * args.speed
    q_prev[0, 4] -= (
        dt * args.speed / height
    )  # (the settled rotation vector is about zero: its rate is the spin)
    state = state._replace(q_prev=q_prev)
    S = ball.second_moment
    inertia = torch.trace(S) * torch.eye(3, dtype=S.dtype) - S

    def energy(st) -> tuple[float, float, float, float, float]:
        v = (st.q[0, :3] - st.q_prev[0, :3]) / dt
        w = angular_velocity(st.q[0], st.q_prev[0], dt)
        R = rotation_matrix(st.q[0, 3:])
        trans = 0.5 * ball.mass * float(v @ v)
        rot = 0.5 * float(w @ (R @ inertia @ R.T) @ w)
        pot = ball.mass * GRAVITY * float(st.q[0, 2])
        return trans + rot + pot, trans, rot, float(v[0]), float(w[1]) * height

    hist = [(0.0, *energy(state))]
    newton = 0
    t0 = time.perf_counter()
    for k in range(round(args.duration / dt)):
        state, info = step(scene, state, return_info=True)
        newton += int(info.newton_iters)
        hist.append(((k + 1) * dt, *energy(state)))
    h = np.array(hist)
    kinetic0 = h[0, 2] + h[0, 3]
    return {
        "subdivisions": subdivisions,
        "faces": int(len(mesh.faces)),
        "dt": dt,
        "rolling_radius_m": height,
        "facet_crossings_per_step": args.speed * dt / edge,
        "energy_change_of_kinetic": float((h[-1, 1] - h[0, 1]) / kinetic0),
        "final_speed_m_s": float(h[-1, 4]),
        "final_spin_times_radius_m_s": float(h[-1, 5]),
        "newton_iters": newton,
        "wall_s": time.perf_counter() - t0,
        "history_t_energy_trans_rot_vx_spinr": h.tolist(),
    }


def table(runs: list[dict], args) -> str:
    rows = [
        f"Ball of radius {args.radius} m rolling at {args.speed} m/s for {args.duration} s, friction {args.friction}.",
        "",
        "| faces | dt (s) | facet crossings per step | energy change (% of kinetic) | final speed (m/s) "
        "| spin x radius (m/s) | Newton iterations |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        rows.append(
            f"| {r['faces']} | {r['dt']:g} | {r['facet_crossings_per_step']:.2f} | "
            f"{100 * r['energy_change_of_kinetic']:+.1f} | {r['final_speed_m_s']:.3f} | "
            f"{r['final_spin_times_radius_m_s']:.3f} | {r['newton_iters']} |"
        )
    return "\n".join(rows) + "\n"


def plot(runs: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    for r in runs:
        h = np.array(r["history_t_energy_trans_rot_vx_spinr"])
        kinetic0 = h[0, 2] + h[0, 3]
        ax.plot(h[:, 0], 100 * (h[:, 1] - h[0, 1]) / kinetic0, label=f"{r['faces']} faces, dt {r['dt']:g} s")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set(xlabel="time rolling [s]", ylabel="energy change [% of the initial kinetic energy]",
           title="a faceted ball rolling without slipping")  # fmt: skip
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cases = [(s, dt) for s in args.subdivisions for dt in args.dt]
    runs = []
    for s, dt in tqdm(cases, desc="rolling ball"):
        runs.append(roll(s, dt, args))
    result = {"commit": git_revision(), "settings": json_args(args), "runs": runs}
    (args.out / "rolling_ball.json").write_text(json.dumps(result, indent=1, allow_nan=False))
    md = table(runs, args)
    (args.out / "rolling_ball.md").write_text(md)
    plot(runs, args.out / "rolling_ball.png")
    print(md)


if __name__ == "__main__":
    main()
