"""Gradient-based control on a task of cfd_torch.envs from its trivial start, gradients by autograd through the
differentiable simulator: open-loop trajectory optimisation, or model-predictive control (``--mpc``).

Loss: minus the sum over the horizon of the task's ``distance`` reward term (the action cost is left out: at the
trivial start its gradient, 2e-3 |a| per step, would swamp the far field's 1e-11 after the first update). Actions
are the tanh of free parameters (so they stay in [-1, 1]), all zero at the start. Every optimiser takes the unit
gradient g / |g|: far-field gradients grow by orders of magnitude as bodies approach (Push's start: about 1e-13
per action), and an optimiser fed raw gradients either crawls in the far field or, like Adam, remembers the largest
one and stalls after it. Optimisers: ``ngd`` (default: heavy-ball momentum 0.9 on the unit gradient, steps of
``--lr``; it keeps the gradient's direction, so Push's pole turns toward the back of the box), ``adam`` (Adam on the
unit gradient: per-coordinate steps of about ``--lr``, which bends the direction toward the diagonals) and
``ngd-ls`` (steps of at most ``--lr`` along -g / |g|, halved until the loss falls: the loss never rises, but
changes below the solver's tolerance, as in Push's far field, stop it).
Each iteration costs one rollout and its backward.

Open loop (default): ``--iters`` iterations on ``--horizon`` actions. MPC: at each of ``--steps`` control steps,
``--iters`` iterations on the window of the next ``--horizon`` actions from the current state, then the first
action is executed and the window shifts (its last action repeats); the logged loss is the executed trajectory's,
next to the same loss with zero actions (the trivial start's).

Writes ``log.json`` (the arguments, the commit, and per iteration or control step: loss, gradient norm, wall times,
Newton iterations), ``loss.png`` and ``best.gif`` (open loop: the rollout with the smallest final distance; MPC: the
executed trajectory) under ``--out``.

    python scripts/optimize.py --task Billiards --optimizer ngd-ls --lr 0.5 --iters 20 --horizon 100 --out X
    python scripts/optimize.py --task Push --mpc --dt 0.02 --horizon 48 --steps 100 --iters 3 --out X
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
from cfd_torch.envs.core import task_at  # noqa: E402
from cfd_torch.envs.render import write_gif  # noqa: E402

TASKS = ("Billiards", "Push", "Sort", "Gather", "AntPush")
TASK_KWARGS = {"Billiards": {"target_ball": 14, "pocket": 1}}
OPTIMISERS = ("ngd", "adam", "ngd-ls")


class Optimiser:
    """An optimiser on the unit gradient of one parameter tensor (see the module docstring): ``start`` begins a
    problem (parameters and their evaluation function), ``step`` returns the evaluation at the new parameters."""

    def __init__(self, kind: str, lr: float) -> None:
        if kind not in OPTIMISERS:
            raise ValueError(f"kind must be one of {OPTIMISERS}, got {kind!r}")
        self.kind, self.lr = kind, lr
        self.step_size = lr

    def start(self, theta: torch.Tensor, evaluate):
        self.evaluate = evaluate
        self.theta = theta.detach().clone().requires_grad_(True)
        if self.kind == "adam":
            self.torch_opt = torch.optim.Adam([self.theta], lr=self.lr)
        elif self.kind == "ngd":
            self.torch_opt = torch.optim.SGD([self.theta], lr=self.lr, momentum=0.9)
        self.step_size = self.lr
        self.current = self.evaluate(self.theta)
        return self.current

    def step(self):
        loss, _, g = self.current[:3]
        unit = g / g.norm().clamp_min(1e-300)
        if self.kind != "ngd-ls":
            self.theta.grad = unit
            self.torch_opt.step()
            self.current = self.evaluate(self.theta)
            return self.current
        # a step of length step_size along -unit, taken only if the loss falls (else halved); an accepted step
        # grows the next one by 1.5, up to lr
        trial = self.theta.detach() - self.step_size * unit
        nxt = self.evaluate(trial)
        if nxt[0] < loss:
            self.theta, self.current = trial, nxt
            self.step_size = min(1.5 * self.step_size, self.lr)
        else:
            self.step_size *= 0.5
        return self.current


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="Billiards", choices=TASKS)
    ap.add_argument("--iters", type=int, default=30, help="iterations (MPC: per control step)")
    ap.add_argument("--horizon", type=int, default=40, help="actions optimised (MPC: the window)")
    ap.add_argument(
        "--mpc", action="store_true", help="receding-horizon control instead of one open-loop plan"
    )
    ap.add_argument("--steps", type=int, default=100, help="MPC: control steps executed")
    ap.add_argument("--knots", type=int, default=None,
                    help="hold actions over this many equal parts of the horizon (default: one per step)")  # fmt: skip
    ap.add_argument("--dt", type=float, default=None, help="the task's time step [s] (default: the task's)")
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--optimizer", default="ngd", choices=OPTIMISERS,
                    help="ngd (momentum on the unit gradient), adam or ngd-ls (with backtracking)")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("results/optimize"))
    ap.add_argument("--no-gif", action="store_true")
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    kwargs = dict(TASK_KWARGS.get(args.task, {}))
    if args.dt is not None:
        kwargs["dt"] = args.dt
    core = make_core(f"cfd_torch/{args.task}-v0", **kwargs)
    s0 = core.reset(args.seed, 1)

    def evaluate_from(state):
        def evaluate(th: torch.Tensor):
            """Loss, gradient, rollout and wall times at the parameters th."""
            th = th.detach().requires_grad_(True)
            t0 = time.perf_counter()
            out = rollout(core, state, actions(th))
            loss = -(out.info["reward_distance"] * out.alive).sum()
            t1 = time.perf_counter()
            (g,) = torch.autograd.grad(loss, th)
            return float(loss.detach()), out, g, t1 - t0, time.perf_counter() - t1

        return evaluate

    def record(cur, **extra):
        loss, out, g, t_fwd, t_bwd = cur
        return {
            "loss": loss, "final_distance": float(-out.info["reward_distance"][-1].sum()), "forward_s": t_fwd,
            "backward_s": t_bwd, "grad_norm": float(g.norm()), "newton_iters": int(out.info["newton_iters"].sum()),
        } | extra  # fmt: skip

    knots = args.horizon if args.knots is None else args.knots
    if not 1 <= knots <= args.horizon:
        raise SystemExit(f"--knots must be in [1, --horizon], got {knots}")
    segment = torch.arange(args.horizon) * knots // args.horizon  # the knot each step's action comes from

    def actions(th: torch.Tensor) -> torch.Tensor:
        """(horizon, 1, A) actions in [-1, 1] from the knot parameters th (knots, 1, A)."""
        return torch.tanh(th)[segment]

    theta = torch.zeros(knots, 1, core.action_dim, dtype=torch.float64)
    log = []
    if not args.mpc:
        opt = Optimiser(args.optimizer, args.lr)
        cur = opt.start(theta, evaluate_from(s0))
        best = None
        for it in tqdm(range(args.iters + 1), desc=f"{args.task} {args.optimizer}"):
            rec = record(cur, iter=it, step=opt.step_size)
            if best is None or rec["final_distance"] < best[0]:
                best = (rec["final_distance"], cur[1].q.detach()[:, 0])
            log.append(rec)
            tqdm.write(f"iter {it}: loss {rec['loss']:.10g} final distance {rec['final_distance']:.6f} m")
            if it < args.iters:
                cur = opt.step()
        first, last = log[0], log[-1]
        summary = {"loss_start": first["loss"], "loss_end": last["loss"], "best_final_distance": best[0]}
        frames_q = best[1]
    else:
        with torch.no_grad():
            zero = rollout(core, s0, torch.zeros(args.steps, 1, core.action_dim, dtype=torch.float64))
        zero_loss = float(-(zero.info["reward_distance"] * zero.alive).sum())
        state, executed, qs = s0, [], [s0.q[0]]
        opt = Optimiser(args.optimizer, args.lr)
        for t in tqdm(range(args.steps), desc=f"{args.task} MPC {args.optimizer}"):
            cur = opt.start(theta, evaluate_from(state))
            window0 = cur[0]
            for _ in range(args.iters):
                cur = opt.step()
            theta = opt.theta.detach()
            with torch.no_grad():
                out = core.step(state, actions(theta)[0])
            state = out.state.detach()
            executed.append(float(-out.info["reward_distance"].sum()))
            qs.append(state.q[0])
            log.append(record(cur, step=t, window_loss_start=window0, executed_distance=executed[-1]))
            tqdm.write(
                f"step {t}: window loss {window0:.10g} -> {cur[0]:.10g}; distance {executed[-1]:.6f} m"
            )
            # shift the window, repeating its last action (with knots the plan's segments stay)
            if knots == args.horizon:
                theta = torch.cat([theta[1:], theta[-1:]])
            if bool(out.terminated.all()):
                break
        summary = {"loss_zero_actions": zero_loss, "loss_executed": sum(executed), "steps_run": len(executed),
                   "final_distance": executed[-1], "final_distance_zero_actions":
                   float(-zero.info["reward_distance"][len(executed) - 1].sum())}  # fmt: skip
        frames_q = torch.stack(qs)
    meta = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "commit": git_revision(), "summary": summary, "log": log}  # fmt: skip
    (args.out / "log.json").write_text(json.dumps(meta, indent=1))

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    x = "step" if args.mpc else "iter"
    ax[0].plot([r[x] for r in log], [r["loss"] for r in log])
    ax[0].set(xlabel=x, ylabel="loss (-return)" + (" of the window" if args.mpc else ""),
              title=f"{args.task}: {'MPC ' if args.mpc else ''}{args.optimizer} lr {args.lr}")  # fmt: skip
    key = "executed_distance" if args.mpc else "final_distance"
    ax[1].plot([r[x] for r in log], [r[key] for r in log])
    ax[1].set(xlabel=x, ylabel="distance to goal [m]" if args.mpc else "final distance to goal [m]")
    fig.tight_layout()
    fig.savefig(args.out / "loss.png", dpi=120)
    if not args.no_gif:
        r = core.renderer(320, 320)
        frames = [core.draw(r, q, task_at(s0, 0)) for q in frames_q]
        r.close()
        write_gif(frames, args.out / "best.gif", fps=round(1 / core.scene.dt))
    print(json.dumps(summary, indent=1), f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
