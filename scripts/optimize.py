"""Open-loop trajectory optimisation on a task of cfd_torch.envs, gradients by autograd through the differentiable
simulator, from the task's trivial start.

Loss: minus the sum over the horizon of the task's ``distance`` reward term (the action cost is left out: at the
trivial start its gradient, 2e-3 |a| per step, would swamp the far field's 1e-11 after the first update). Actions
are the tanh of free parameters (so they stay in [-1, 1]), all zero at the start. Optimiser: Adam (``--optimizer
adam``, eps 1e-30: the default 1e-8 would swallow the far field's gradients) or normalised gradient descent
(``ngd``: steps of at most ``--lr`` along -grad, halved until the loss falls; this keeps the gradient's weighting
across the horizon, where Adam's per-coordinate scaling moves every step's action alike). Each iteration costs one
rollout and its backward. Writes ``log.json`` (per iteration: loss, gradient
norm, wall time, Newton iterations), ``loss.png`` and ``best.gif`` (the rollout with the smallest final distance)
under ``--out``.

    python scripts/optimize.py --task Billiards --optimizer ngd --lr 0.5 --iters 20 --horizon 100 --out X
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch.envs import make_core, rollout  # noqa: E402
from cfd_torch.envs.render import write_gif  # noqa: E402

TASK_KWARGS = {"Billiards": {"target_ball": 14, "pocket": 1}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="Billiards", choices=["Billiards", "Push", "Sort", "Gather"])
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--horizon", type=int, default=40)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--optimizer", default="adam", choices=["adam", "ngd"],
                    help="adam, or ngd: normalised gradient descent (steps of length lr along -grad)")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("results/optimize"))
    ap.add_argument("--no-gif", action="store_true")
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    core = make_core(f"cfd_torch/{args.task}-v0", **TASK_KWARGS.get(args.task, {}))
    s0 = core.reset(args.seed, 1)
    opt = None
    theta = torch.zeros(args.horizon, 1, core.action_dim, dtype=torch.float64, requires_grad=True)
    if args.optimizer == "adam":
        # Adam's update is lr * m / (sqrt(v) + eps): eps must sit far below the far field's gradients (1e-13..1e-5)
        opt = torch.optim.Adam([theta], lr=args.lr, eps=1e-30)

    def evaluate(th: torch.Tensor):
        """Loss, rollout, gradient and wall times at the parameters th."""
        th = th.detach().requires_grad_(True)
        t0 = time.perf_counter()
        out = rollout(core, s0, torch.tanh(th))
        loss = -(out.info["reward_distance"] * out.alive).sum()
        t1 = time.perf_counter()
        (g,) = torch.autograd.grad(loss, th)
        return float(loss), out, g, t1 - t0, time.perf_counter() - t1

    log = []
    best = None
    step = args.lr
    cur = evaluate(theta)
    for it in tqdm(range(args.iters + 1), desc=f"{args.task} {args.optimizer}"):
        loss, out, g, t_fwd, t_bwd = cur
        final_distance = float(-out.info["reward_distance"][-1].sum())
        rec = {
            "iter": it, "loss": loss, "final_distance": final_distance, "forward_s": t_fwd, "backward_s": t_bwd,
            "grad_norm": float(g.norm()), "newton_iters": int(out.info["newton_iters"].sum()),
        }  # fmt: skip
        if best is None or final_distance < best[0]:
            best = (final_distance, out.q.detach()[:, 0])
        log.append(rec)
        tqdm.write(f"iter {it}: loss {loss:.6g} final distance {final_distance:.4f} m")
        if it == args.iters:
            break
        if opt is not None:
            theta.grad = g
            opt.step()
            cur = evaluate(theta)
            continue
        # normalised gradient descent with backtracking: a step of length `step` along -grad, taken only if the
        # loss falls (else halved); an accepted step grows the next one by 1.5, up to --lr
        trial = theta.detach() - step * g / g.norm().clamp_min(1e-300)
        nxt = evaluate(trial)
        rec["step"] = step
        if nxt[0] < loss:
            theta, cur = trial, nxt
            step = min(1.5 * step, args.lr)
        else:
            step *= 0.5
    meta = {
        "task": args.task, "optimizer": args.optimizer, "iters": args.iters, "horizon": args.horizon,
        "lr": args.lr, "seed": args.seed, "commit": git_revision(), "log": log,
    }  # fmt: skip
    (args.out / "log.json").write_text(json.dumps(meta, indent=1))
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].plot([r["loss"] for r in log])
    ax[0].set(
        xlabel="iteration", ylabel="loss (-return)", title=f"{args.task}: {args.optimizer} lr {args.lr}"
    )
    ax[1].plot([r["final_distance"] for r in log])
    ax[1].set(xlabel="iteration", ylabel="final distance to goal [m]")
    fig.tight_layout()
    fig.savefig(args.out / "loss.png", dpi=120)
    if not args.no_gif:
        r = core.renderer(320, 320)
        frames = [r.render(q) for q in best[1]]
        r.close()
        write_gif(frames, args.out / "best.gif", fps=round(1 / core.scene.dt))
    print(f"loss {log[0]['loss']:.4f} -> {log[-1]['loss']:.4f}; final distance {log[0]['final_distance']:.4f} -> "
          f"{log[-1]['final_distance']:.4f} m (best {best[0]:.4f}); written to {args.out}")  # fmt: skip


if __name__ == "__main__":
    main()
