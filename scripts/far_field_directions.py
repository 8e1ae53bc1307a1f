"""Which way the far-field gradient tells Push's pole to move, around the box.

The pole is placed at rest at radius r from the box's centre and at angle phi from the box-to-target direction
(phi = 180 deg: straight behind the box; 90 or 270: to its side, Push's trivial start), the box at rest on the
floor. One constant action a (the pole's velocity target) is held for ``--horizon`` steps from a = 0; the loss is
the box's final distance to the target. The descent direction -dL/da / |dL/da| is reported by its components toward
the box and along the box-to-target direction, with |dL/da|. All placements run as one batch of scenes.

Writes ``directions.json`` and ``directions.png`` (the descent directions as arrows around the box) under ``--out``.

    python scripts/far_field_directions.py --out results/far_field_directions
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _cli import positive_float, positive_int  # noqa: E402
from _provenance import git_revision, json_args  # noqa: E402

from cfd_torch.envs import make_core, rollout  # noqa: E402
from cfd_torch.envs.core import EnvState  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--radii", type=positive_float, nargs="+", default=[0.3, 0.45, 0.6], help="pole-box distances [m]"
    )
    ap.add_argument("--angles", type=positive_int, default=12, help="angles phi, equally spaced over 360 deg")
    ap.add_argument("--horizon", type=positive_int, default=30, help="steps the action is held")
    ap.add_argument("--dt", type=positive_float, default=0.02, help="time step [s]")
    ap.add_argument("--seed", type=int, default=0, help="the reset whose box and target are used")
    ap.add_argument("--out", type=Path, default=Path("results/far_field_directions"), help="output folder")
    args = ap.parse_args()

    core = make_core("cfd_torch/Push-v0", dt=args.dt)
    s0 = core.reset(args.seed, 1)
    target = s0.task["target"][0]
    box = s0.q[0, 0, :2]
    u = (target - box) / (target - box).norm()
    heading = math.atan2(float(u[1]), float(u[0]))
    places = [(r, 360.0 * k / args.angles) for r in args.radii for k in range(args.angles)]
    B = len(places)
    radius = torch.tensor([r for r, _ in places], dtype=torch.float64)
    angle = heading + torch.deg2rad(torch.tensor([phi for _, phi in places], dtype=torch.float64))
    q = s0.q.expand(B, -1, -1).clone()
    q[:, 1, :2] = box + radius[:, None] * torch.stack([angle.cos(), angle.sin()], 1)
    state = EnvState(
        q, q.clone(), s0.t.expand(B).clone(), {k: v.expand(B, *v.shape[1:]) for k, v in s0.task.items()}
    )

    a = torch.zeros(B, core.action_dim, dtype=torch.float64, requires_grad=True)
    t0 = time.perf_counter()
    try:
        out = rollout(core, state, a[None].expand(args.horizon, -1, -1))
    except ValueError as err:  # a radius that puts the pole into the box
        ap.error(f"argument --radii: {err}")
    final = -out.info["reward_distance"][-1]  # (B,) final distances
    (g,) = torch.autograd.grad(final.sum(), a)
    seconds = time.perf_counter() - t0

    rows = []
    for b, (r, phi) in enumerate(places):
        d = -g[b] / g[b].norm()
        toward_box = (box - q[b, 1, :2]) / r
        rows.append({
            "radius": r, "phi_deg": phi, "grad_norm": float(g[b].norm()),
            "toward_box": float(d @ toward_box), "along_target": float(d @ u),
            "direction_target_frame": [float(d @ u), float(d[1] * u[0] - d[0] * u[1])],
            "final_distance_minus_start": float(final[b].detach() - (target - box).norm()),
        })  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"args": json_args(args),
            "commit": git_revision(), "seconds": seconds, "rows": rows}  # fmt: skip
    (args.out / "directions.json").write_text(json.dumps(meta, indent=1))

    print(f"{'r [m]':>6} {'phi':>5} {'|dL/da|':>10} {'toward box':>10} {'along target':>12}")
    for row in rows:
        print(f"{row['radius']:6.2f} {row['phi_deg']:5.0f} {row['grad_norm']:10.2e} "
              f"{row['toward_box']:10.3f} {row['along_target']:12.3f}")  # fmt: skip

    # arrows in the box's frame with the target direction along +x
    fig, ax = plt.subplots(figsize=(5, 5))
    turn = float(s0.q[0, 0, 5]) - heading  # the box's yaw in this frame
    corners = [(math.cos(turn) * x - math.sin(turn) * y, math.sin(turn) * x + math.cos(turn) * y)
               for x, y in ((-0.15, -0.15), (0.15, -0.15), (0.15, 0.15), (-0.15, 0.15))]  # fmt: skip
    ax.add_patch(plt.Polygon(corners, color=(0.8, 0.55, 0.25)))
    for row in rows:
        phi = math.radians(row["phi_deg"])
        x, y = row["radius"] * math.cos(phi), row["radius"] * math.sin(phi)
        dx, dy = row["direction_target_frame"]
        ax.arrow(x, y, 0.08 * dx, 0.08 * dy, head_width=0.02, color="k")
    lim = max(args.radii) + 0.3
    ax.annotate(
        "to target",
        xy=(0.95 * lim, 0.9 * lim),
        xytext=(0.55 * lim, 0.9 * lim),
        arrowprops={"arrowstyle": "->", "color": "g"},
    )
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="along box -> target [m]",
           ylabel="across [m]",
           title=f"Push: far-field descent direction of the pole\n(seed {args.seed}, {args.horizon} steps of "
                 f"{args.dt} s)")  # fmt: skip
    fig.tight_layout()
    fig.savefig(args.out / "directions.png", dpi=120)
    print(f"{B} placements in {seconds:.1f} s; written to {args.out}")


if __name__ == "__main__":
    main()
