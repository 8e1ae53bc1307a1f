"""Demo: gradient descent through the simulator discovers a contact it has never seen.

A cue ball and an object ball lie 1 m apart on a frictionless table seen from above (zero gravity, so the motion
stays in the plane). The only parameter is the cue ball's initial velocity, initialised at ZERO: nothing moves and
nothing touches. The loss is the squared distance of the object ball, after T steps, from a pocket placed at an
angle behind it. With a local barrier (IPC, SDRS, MuJoCo, ...) the gradient of that loss with respect to the cue
velocity is exactly zero at the start, and gradient descent never moves. Our potential's gradient never vanishes:
it is tiny (the balls are 1 m apart) but points the right way, Adam normalises its scale, the cue ball starts to
roll toward the object ball, the two collide, and the optimisation then aims the shot at the pocket. At the
default step (0.05 s: the aimed cue ball moves more than its diameter per step) the loss is not smooth in the
velocity near the optimum: a step is a local minimum of its incremental potential (docs/simulator.md, "A step is a
local minimum"), and two shots 2e-4 m/s apart can end in different ones (loss 7e-4 against 6e-2 in iterations 58
and 59 of a run); the JSON and the GIF give the best iterate beside the last.

Writes ``<out>/billiards_demo.png`` (loss, gradient norm, trajectories), ``<out>/billiards_demo.json`` and
``<out>/billiards_demo.gif`` (the best iterate's shot seen from above, the pocket a black disc; ``--no-gif`` skips
it: it needs MuJoCo's headless EGL renderer).

    python scripts/demo_billiards.py --out results/demo
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
import trimesh  # noqa: E402
from _cli import positive_float, positive_int  # noqa: E402
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch import Scene, rigid_body, rollout  # noqa: E402
from cfd_torch.envs.core import camera_over, disc  # noqa: E402


def simulate(scene: Scene, q0: torch.Tensor, v_cue: torch.Tensor, steps: int) -> torch.Tensor:
    """Poses (T + 1, N, 6) of a rollout of ``steps`` steps, the cue ball (body 0) starting at ``v_cue`` (2,) in
    the plane (differentiable in ``v_cue``)."""
    v = torch.stack([torch.cat([v_cue, v_cue.new_zeros(4)]), v_cue.new_zeros(6)])  # (N, 6)
    return rollout(scene, scene.initial_state(q0, v), steps).q


def write_shot_gif(
    mesh: trimesh.Trimesh, q: torch.Tensor, pocket: torch.Tensor, radius: float, path: Path, fps: float
) -> None:
    """A GIF of the poses ``q`` (T + 1, 2, 6) of the two balls seen from above (+x right, +y up), the pocket a black
    disc 1.5 times the balls' radius on the drawn table under them."""
    from cfd_torch.envs.render import MeshRenderer, write_gif

    colours = [(0.95, 0.95, 0.92, 1.0), (0.95, 0.75, 0.1, 1.0), (0.0, 0.0, 0.0, 1.0)]
    pocket_mesh = disc(1.5 * radius, 1e-3)
    meshes = [(mesh.vertices, mesh.faces)] * 2 + [pocket_mesh]
    q = q.cpu()
    pocket_pose = torch.tensor([[*pocket.tolist(), -radius, 0.0, 0.0, 0.0]], dtype=q.dtype)
    centres = torch.cat([q[:, :, :2].reshape(-1, 2), pocket[None]]).tolist()
    camera = camera_over([(x, y, radius) for x, y in centres], azimuth=90.0, elevation=-90.0)
    r = MeshRenderer(meshes, colours, width=400, height=400, camera=camera, floor=-radius)
    try:
        frames = [r.render(torch.cat([qt, pocket_pose])) for qt in q]
    finally:
        r.close()
    write_gif(frames, path, fps=fps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/demo"), help="output folder")
    ap.add_argument("--iters", type=positive_int, default=60, help="Adam iterations")
    ap.add_argument(
        "--steps", type=positive_int, default=20, help="time steps per rollout (1 s at the default dt)"
    )
    ap.add_argument("--dt", type=positive_float, default=0.05, help="time step [s]")
    ap.add_argument("--lr", type=positive_float, default=0.3, help="Adam learning rate [m/s]")
    ap.add_argument("--mu", type=positive_float, default=1e-8, help="the contact potential's mu")
    ap.add_argument("--no-gif", dest="gif", action="store_false", help="skip billiards_demo.gif")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    radius = 0.1
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    ball = rigid_body(mesh, density=1700.0)  # a billiard ball's density
    scene = Scene([ball, ball], dt=args.dt, gravity=(0.0, 0.0, 0.0), mu=args.mu)
    f64 = torch.float64
    q0 = torch.tensor([[0.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]], dtype=f64)  # 1 m apart, centre to centre
    pocket = torch.tensor([2.0, 0.6], dtype=f64)  # behind the object ball, at an angle: needs a cut shot

    v = torch.zeros(2, dtype=f64, requires_grad=True)  # trivial initialisation: nothing moves
    opt = torch.optim.Adam([v], lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=args.iters)
    history = []
    first_traj = last_traj = best_q = None
    best = -1
    t0 = time.perf_counter()
    for it in (bar := tqdm(range(args.iters), desc="billiards")):
        traj = simulate(scene, q0, v, args.steps)
        loss = ((traj[-1][1, :2] - pocket) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        gnorm = float(v.grad.norm())
        touched = float((traj[:, 1, :2].detach() - q0[1, :2]).norm(dim=1).max())
        history.append(
            {
                "iter": it,
                "loss": float(loss.detach()),
                "grad_norm": gnorm,
                "v": v.detach().tolist(),
                "object_moved": touched,
            }
        )
        xy = traj[..., :2].detach()
        if it == 0:
            first_traj = xy
        last_traj = xy
        cur = history[-1]["loss"]  # (a NaN loss is never the best; a finite one replaces a NaN best)
        if best < 0 or (cur == cur and not history[best]["loss"] <= cur):
            best, best_q = it, traj.detach()
        bar.set_postfix(loss=f"{float(loss.detach()):.4f}", grad=f"{gnorm:.1e}")
        opt.step()
        sched.step()
    wall = time.perf_counter() - t0

    final = history[-1]
    result = {
        "commit": git_revision(),
        "settings": vars(args) | {"out": str(args.out), "radius": radius, "faces": int(len(mesh.faces))},
        "pocket": pocket.tolist(),
        "initial_loss": history[0]["loss"],
        "initial_grad_norm": history[0]["grad_norm"],
        "final_loss": final["loss"],
        "final_v": final["v"],
        "best_iter": best,
        "best_loss": history[best]["loss"],
        "best_v": history[best]["v"],
        "wall_s": wall,
        "history": history,
    }
    (args.out / "billiards_demo.json").write_text(json.dumps(result, indent=1))

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    its = [h["iter"] for h in history]
    ax[0].semilogy(its, [h["loss"] for h in history], "o-")
    ax[0].set(xlabel="Adam iteration", ylabel="loss [m^2]", title="object ball to pocket")
    ax[1].semilogy(its, [h["grad_norm"] for h in history], "o-", color="C3")
    ax[1].set(
        xlabel="Adam iteration", ylabel="|dloss/dv| ", title="gradient: never zero, even before contact"
    )
    for xy, style, name in ((first_traj, ":", "iteration 0"), (last_traj, "-", f"iteration {its[-1]}")):
        ax[2].plot(xy[:, 0, 0], xy[:, 0, 1], style, color="C0", label=f"cue ball, {name}")
        ax[2].plot(xy[:, 1, 0], xy[:, 1, 1], style, color="C1", label=f"object ball, {name}")
    for c, col in ((q0[0, :2], "C0"), (q0[1, :2], "C1")):
        ax[2].add_patch(plt.Circle(c.tolist(), radius, fill=False, color=col))
    ax[2].plot(*pocket.tolist(), "k*", ms=14, label="pocket")
    ax[2].set(xlabel="x [m]", ylabel="y [m]", title="top view", aspect="equal")
    ax[2].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(args.out / "billiards_demo.png", dpi=120)
    plt.close(fig)
    gif = args.gif and bool(torch.isfinite(best_q).all())
    if gif:
        write_shot_gif(mesh, best_q, pocket, radius, args.out / "billiards_demo.gif", fps=1.0 / args.dt)

    print(
        f"initial: v = (0, 0), loss {history[0]['loss']:.4f}, |grad| {history[0]['grad_norm']:.3e} (non-zero)"
    )
    print(f"final:   v = ({final['v'][0]:.3f}, {final['v'][1]:.3f}) m/s, loss {final['loss']:.2e}")
    b = history[best]
    print(f"best:    v = ({b['v'][0]:.3f}, {b['v'][1]:.3f}) m/s, loss {b['loss']:.2e} (iteration {best})")
    print(
        f"{args.iters} iterations x {args.steps} steps in {wall:.1f} s; wrote {args.out}/billiards_demo.png/.json"
        + ("/.gif" if gif else "")
    )
    if not math.isfinite(final["loss"]):
        raise SystemExit("non-finite loss")


if __name__ == "__main__":
    main()
