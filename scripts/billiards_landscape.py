"""The loss landscape of a Billiards break shot: the object ball's final distance to its pocket over a grid of shots.

The loss is the final distance of the object ball to its pocket, over a two-parameter family of shots, to see why
gradient descent on the shot finds the pocket and then leaves it.

A shot is a constant force on the cue ball for its first ``--shot-steps`` steps (20: 0.2 s) and none after: action
``m (cos a, sin a)``, a measured from the line from the cue ball's centre to the object ball's (degrees), m in
[0, 1] (5 N per unit, the task's ``max_force``). Each shot is rolled out for ``--horizon`` steps (200: 2 s) from the
task's trivial start (``--seed``; the object ball and pocket of ``scripts/optimize.py``: ball 14, the far right
corner), forward only, in batches of ``--batch`` scenes; the loss is ``optimize.task_loss(..., "final")``: the
distance after the last step alive, below the pocket radius (0.08 m) when the ball is potted.

Writes ``<out>/landscape.json`` (the grid, the losses, the set-up, the commit) and ``<out>/landscape.png`` (a heat
map of loss / start loss, the potted shots marked).

    python scripts/billiards_landscape.py --seed 1 --out docs/experiments/billiards_landscape
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
import numpy as np  # noqa: E402
import torch  # noqa: E402
from _cli import positive_int  # noqa: E402
from _provenance import git_revision, json_args  # noqa: E402
from optimize import TASK_KWARGS, task_loss  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch.envs import make_core, rollout  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="the task's reset seed")
    ap.add_argument("--angles", type=float, nargs=3, default=[-20.0, 20.0, 41], metavar=("LO", "HI", "N"),
                    help="shot directions [deg from the cue-to-object-ball line]: from, to, count")  # fmt: skip
    ap.add_argument("--strengths", type=float, nargs=3, default=[0.2, 1.0, 5], metavar=("LO", "HI", "N"),
                    help="shot strengths m (action units): from, to, count")  # fmt: skip
    ap.add_argument("--shot-steps", type=positive_int, default=20, help="steps the shot's force acts")
    ap.add_argument("--horizon", type=positive_int, default=200, help="steps per rollout")
    ap.add_argument("--batch", type=positive_int, default=16, help="shots rolled out together")
    ap.add_argument("--out", type=Path, default=Path("results/billiards_landscape"), help="output folder")
    args = ap.parse_args(argv)
    if args.shot_steps > args.horizon:
        ap.error(f"argument --shot-steps: must be at most --horizon ({args.horizon}), got {args.shot_steps}")
    if not (0 <= args.strengths[0] <= args.strengths[1] <= 1):  # beyond 1 the action clips per component
        ap.error(f"argument --strengths: must satisfy 0 <= LO <= HI <= 1, got {args.strengths[:2]}")
    for name in ("angles", "strengths"):
        n = getattr(args, name)[2]
        if not (2 <= n < math.inf and n == int(n)):  # the heat map needs two values per axis
            ap.error(f"argument --{name}: the count N must be a whole number >= 2, got {n:g}")
    args.out.mkdir(parents=True, exist_ok=True)
    core = make_core("cfd_torch/Billiards-v0", **TASK_KWARGS["Billiards"])
    s0 = core.reset(args.seed, 1)
    q = s0.q[0]
    target = int(s0.task["target"][0])
    aim = math.atan2(float(q[target, 1] - q[15, 1]), float(q[target, 0] - q[15, 0]))
    angles = np.linspace(args.angles[0], args.angles[1], int(args.angles[2]))
    strengths = np.linspace(args.strengths[0], args.strengths[1], int(args.strengths[2]))
    shots = [(a, m) for a in angles for m in strengths]
    losses = []
    t0 = time.perf_counter()
    for lo in tqdm(range(0, len(shots), args.batch), desc="shots"):
        chunk = shots[lo : lo + args.batch]
        a, m = torch.tensor(chunk, dtype=torch.float64).T  # directions [deg], strengths
        direction = aim + torch.deg2rad(a)
        acts = torch.zeros(args.horizon, len(chunk), 2, dtype=torch.float64)
        acts[: args.shot_steps] = m[:, None] * torch.stack([direction.cos(), direction.sin()], 1)
        with torch.no_grad():
            out = rollout(core, s0.select(torch.zeros(len(chunk), dtype=torch.long)), acts)
        losses += task_loss(out.info["reward_distance"], out.alive, "final").tolist()
    with torch.no_grad():
        zero = rollout(core, s0, torch.zeros(args.horizon, 1, 2, dtype=torch.float64))
    start = float(task_loss(zero.info["reward_distance"], zero.alive, "final")[0])
    L = np.array(losses).reshape(len(angles), len(strengths))
    result = {
        "config": json_args(args),
        "commit": git_revision(), "seconds": time.perf_counter() - t0, "aim_rad": aim, "target": target,
        "pocket": s0.task["pocket"][0].tolist(), "pocket_radius": core.pocket_radius, "start_loss": start,
        "angles_deg": angles.tolist(), "strengths": strengths.tolist(), "loss": L.tolist(),
    }  # fmt: skip
    (args.out / "landscape.json").write_text(json.dumps(result, indent=1))
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    im = ax.pcolormesh(strengths, angles, L / start, shading="nearest", cmap="viridis", vmin=0, vmax=1.5)
    fig.colorbar(im, ax=ax, label="final distance / start")
    potted = L < core.pocket_radius
    ai, mi = np.nonzero(potted)
    ax.scatter(strengths[mi], angles[ai], marker="o", facecolors="none", edgecolors="r", label="potted")
    ax.set(xlabel=f"shot strength (action units, 5 N each, for {args.shot_steps} steps)",
           ylabel="shot direction [deg from the object ball]",
           title=f"Billiards seed {args.seed}: object ball {target}, {args.horizon} steps")  # fmt: skip
    if potted.any():
        ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(args.out / "landscape.png", dpi=120)
    plt.close(fig)
    print(f"{len(shots)} shots in {result['seconds']:.0f} s; potted: {int(potted.sum())}; best {L.min():.4f} m "
          f"(start {start:.4f} m); wrote {args.out}")  # fmt: skip


if __name__ == "__main__":
    main()
