"""Gradient-based control on a task of cfd_torch.envs from its trivial start, gradients by autograd through the
differentiable simulator: open-loop trajectory optimisation, or model-predictive control (``--mpc``).

Loss (``--loss``, :func:`task_loss`): ``sum`` (the default), minus the sum over the horizon of the task's
``distance`` reward term; ``final``, the distance to the goal after the last step (the terminal step where the task
terminates first); ``closest``, the smallest distance over the steps alive. The action cost is left out: at the trivial
start its gradient, 2e-3 |a| per step, would swamp the far field's 1e-11 after the first update. The logs'
``final_distance`` is the distance after the last step alive, whatever the loss. Actions are the tanh of free
parameters (so they stay in [-1, 1]), all zero at the start. Every optimiser takes the unit gradient g / |g|:
far-field gradients grow by orders of magnitude as bodies approach (Push's start: about 1e-13
per action), and an optimiser fed raw gradients either crawls in the far field or, like Adam, remembers the largest
one and stalls after it. Optimisers: ``ngd`` (default: heavy-ball momentum 0.9 on the unit gradient, steps of
``--lr``; it keeps the gradient's direction, so Push's pole turns toward the back of the box), ``adam`` (Adam on the
unit gradient: per-coordinate steps of about ``--lr``, which bends the direction toward the diagonals) and
``ngd-ls`` (steps of at most ``--lr`` along -g / |g|, halved until the loss falls: the loss never rises, but
changes below the solver's tolerance, as in Push's far field, stop it). With ``--lr-final`` the rate (``ngd``'s
and ``adam``'s step, ``ngd-ls``'s largest step) decays geometrically from ``--lr`` at the first step to
``--lr-final`` at the last (under ``--mpc``, again in every control step's iterations).
Each iteration costs one rollout and its backward; with ``--smooth-samples`` N (cfd, ipc, sdrs), a forward rollout
at the parameters for the loss and N differentiated rollouts, as one batch, at perturbations theta + sigma eps_i
(eps_i ~ N(0, I), sigma = ``--smooth-sigma``), whose gradients' mean is the step's gradient (first-order randomised
smoothing, Suh et al. 2022). The run's answer is its best iterate (``loss_best`` in the
summary; momentum can leave the last one worse). An open-loop run with a deterministic gradient (``cfd``, ``ipc``,
``sdrs`` without smoothing, ``mujoco-fd``) stops at an iteration whose gradient is exactly zero while the optimiser
holds no momentum (``stopped_at`` in the summary; ``None`` when it ran its ``--iters``): every later iterate would
be the same parameters and the same rollout; ``scripts/plot_results.py`` carries such a run flat to its budget. Under
``--mpc`` the same condition ends a control step's iterations (``iters_run`` in its log row).
The pushing tasks' blend width between the pusher and the boxes
(``--eps``) is 1.0 by default: with the library's 0.01 the far field is a staircase of millimetre-wide bands that
rollouts cross hit-or-miss (:class:`cfd_torch.envs.core.TaskCore`).

Models (``--model``; the optimiser, its settings and the loss are the same for every one): ``cfd`` (this library's
contact, the default), ``ipc`` and ``sdrs`` (the baselines' local barriers in the same stepper,
``make_core(..., potential=...)``, dhat and kappa at their model defaults): gradients by autograd; ``gb``
(randomised smoothing, Suh et al. 2022, the zeroth-order "bundled" gradient of this library's simulator): with
``--gb-samples`` N perturbations eps_i ~ N(0, I) of the action parameters, g = sum_i (L(theta + sigma eps_i) -
L(theta)) eps_i / (N sigma), sigma = ``--gb-sigma``; the N rollouts run as one batch of N scenes, forward only.
``mujoco-fd``: the same task in MuJoCo (:class:`cfd_torch.envs.mujoco_twin.MujocoTwin`: the scene's meshes, masses,
friction and gravity, AntPush's Ant from its own MJCF, the task's own actions and reward, ``--mj-substeps`` MuJoCo
steps per task step),
its loss's gradient by central differences in every action parameter (2 K A + 1 rollouts for K knots and A action
dimensions), with the step ``--fd-step``, or, by default, the step chosen at the start by a sweep over
``FD_STEPS``: the one whose unit gradient, stepped by ``--lr``, lowers the loss most (recorded in the log's summary
with every step's gradient norm and loss; the sweep's rollouts are counted). Differences that do not shrink with
the step and stay below 1e-6 of the loss (MuJoCo's rounding and solver tolerance, ``_round_off``) are no
gradient: the sweep records ``round_off`` and the gradient is zero; after such a sweep every evaluation (MPC's
later control steps) takes its differences over the sweep's steps and is tested the same way. Under ``--mpc`` it
plans and executes in MuJoCo: each control step's finite differences start from MuJoCo's exact state after the
executed actions (``MujocoTwin.step``), and the first action runs there. Every log row counts the rollouts spent
(``rollouts``: forward rollouts; ``backward``: rollouts differentiated).

Open loop (default): ``--iters`` iterations on ``--horizon`` actions. MPC: at each of ``--steps`` control steps,
``--iters`` iterations on the window of the next ``--horizon`` actions from the current state, then the first
action is executed and the window shifts (its last action repeats); each control step's log row holds the
optimised window's loss and final distance (``loss``, ``final_distance``), the executed step's distance
(``executed_distance``), its action (``action``) and the planar position the driven body reached
(``action_body_xy``: the cue ball, the pole, the pusher; the Ant's torso); the summary's ``loss_executed`` is the
executed trajectory's loss, next to the same loss with zero actions (``loss_zero_actions``, the trivial start's).

Writes ``log.json`` (the configuration, the commit, and per iteration or control step: loss, gradient norm, wall
times, rollouts, Newton iterations), ``loss.png`` and ``best.gif`` (open loop: the rollout of the best iterate, the
smallest loss, none for mujoco-fd; MPC: the executed trajectory, MuJoCo's for mujoco-fd) under ``--out``, and
while a run goes, ``progress.jsonl`` (one line per finished iteration, or per executed control step with ``--mpc``:
what an interrupted run keeps). A run first removes those four files from the folder (an earlier run's, which
would otherwise pass for its own: a best.gif where this run writes none).
:func:`run_experiment` (a config dict in, a JSON-able dict out) is the whole experiment; ``scripts/sweep.py`` runs
it over a grid.

    python scripts/optimize.py --task Billiards --optimizer ngd-ls --lr 0.5 --iters 20 --horizon 100 --out X
    python scripts/optimize.py --task Push --mpc --dt 0.02 --horizon 48 --steps 100 --iters 3 --out X
    python scripts/optimize.py --task Billiards --model gb --gb-samples 16 --iters 20 --out X
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from _cli import folder_problem  # noqa: E402
from _provenance import git_revision  # noqa: E402
from _settings import DEFAULTS, FD_STEPS, LOSSES, MODELS, OPTIMISERS, TASK_KWARGS, unused_settings  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch._validate import is_int, is_real  # noqa: E402
from cfd_torch.envs import TASKS, core_class, make_core, rollout  # noqa: E402
from cfd_torch.envs.core import EnvState, task_at  # noqa: E402
from cfd_torch.envs.render import write_gif  # noqa: E402

OUTPUTS = ("log.json", "loss.png", "best.gif", "progress.jsonl")  # what a run writes in its --out folder


def task_loss(reward_distance: torch.Tensor, alive: torch.Tensor, kind: str) -> torch.Tensor:
    """(B,) the loss of rollouts with distance terms ``reward_distance`` (T, B) (minus the distance to the goal)
    and ``alive`` (T, B): ``sum``, minus the distance term summed over the steps alive; ``final``, the distance
    after the last step alive (the terminal step, or the horizon's last); ``closest``, the smallest distance over
    the steps alive (Billiards: a ball that passes within the pocket's radius is potted, whenever it does)."""
    if kind == "sum":
        return -(reward_distance * alive).sum(0)
    if kind == "closest":
        return torch.where(alive > 0, -reward_distance, torch.inf).amin(0)
    last = (alive.sum(0).long() - 1).clamp_min(0)  # alive is 1 up to and including the first terminal step
    return -reward_distance.gather(0, last[None])[0]


class Optimiser:
    """An optimiser on the unit gradient of one parameter tensor (see the module docstring): ``start`` begins a
    problem (parameters and their evaluation function), ``step`` returns the evaluation at the new parameters."""

    def __init__(
        self,
        kind: str,
        lr: float,
        lr_final: float | None = None,
        iters: int = 1,
        theta_max: float | None = None,
    ) -> None:
        if kind not in OPTIMISERS:
            raise ValueError(f"kind must be one of {OPTIMISERS}, got {kind!r}")
        self.kind, self.lr = kind, lr
        self.theta_max = theta_max  # every step ends with the parameters clamped to [-theta_max, theta_max]
        self.lr_final, self.iters = lr if lr_final is None else lr_final, iters
        self.step_size = lr
        self.k = 0  # steps taken since start

    def rate(self) -> float:
        """The learning rate of the next step: ``lr`` decayed geometrically to ``lr_final`` at the last of
        ``iters`` steps (constant without ``lr_final``)."""
        return self.lr * (self.lr_final / self.lr) ** (self.k / max(1, self.iters - 1))

    def start(self, theta: torch.Tensor, evaluate):
        self.evaluate = evaluate
        self.theta = theta.detach().clone().requires_grad_(True)
        if self.kind == "adam":
            self.torch_opt = torch.optim.Adam([self.theta], lr=self.lr)
        elif self.kind == "ngd":
            self.torch_opt = torch.optim.SGD([self.theta], lr=self.lr, momentum=0.9)
        self.step_size = self.lr
        self.k = 0
        self.current = self.evaluate(self.theta)
        return self.current

    def still(self) -> bool:
        """Whether a step from a zero gradient leaves the parameters where they are: no momentum held (``ngd``'s
        buffer and ``adam``'s first moment zero or not yet made); ``ngd-ls`` always (its trial is the point)."""
        if self.kind == "ngd-ls":
            return True
        held = self._momentum()
        return held is None or not bool(held.any())

    def _momentum(self) -> torch.Tensor | None:
        """ngd's momentum buffer or adam's first moment (None before the first step)."""
        state = self.torch_opt.state.get(self.theta, {})
        return state.get("momentum_buffer" if self.kind == "ngd" else "exp_avg")

    def _project(self) -> None:
        """Clamp the parameters to [-theta_max, theta_max]; at the bound, drop the momentum (ngd's buffer, adam's
        first moment) that pushes outward, so that the parameters leave the bound as soon as the gradient turns."""
        with torch.no_grad():
            th = self.theta
            th.clamp_(-self.theta_max, self.theta_max)
            held = self._momentum()
            # the update is -lr * held (scaled): outward where held's sign is opposite th's
            if held is not None:
                held.masked_fill_((th.abs() >= self.theta_max) & (held * th < 0), 0.0)

    def step(self):
        """One iteration: (the held iterate's evaluation, the evaluation this iteration ran: the new iterate's, or
        ngd-ls's trial whether accepted or not; None where it ran none)."""
        loss, _, g = self.current[:3]
        unit = g / g.norm().clamp_min(1e-300)
        lr = self.rate()
        self.k += 1
        if self.kind != "ngd-ls":
            for group in self.torch_opt.param_groups:
                group["lr"] = lr
            self.step_size = lr
            self.theta.grad = unit
            self.torch_opt.step()
            if self.theta_max is not None:
                self._project()
            self.current = self.evaluate(self.theta)
            return self.current, self.current
        # a step of length step_size (at most this step's rate) along -unit, taken only if the loss falls (else
        # halved); an accepted step grows the next one by 1.5, up to the rate
        self.step_size = min(self.step_size, lr)
        th = self.theta.detach()
        down = -unit
        if self.theta_max is not None:  # the projected direction: no component out through the bound
            down = down.masked_fill((th.abs() >= self.theta_max) & (down * th > 0), 0.0)
            # stationary on the bound: nothing to try (and no reason to shrink the step)
            if not bool(down.any()):
                return self.current, None
        trial = th + self.step_size * down
        if self.theta_max is not None:
            trial = trial.clamp(-self.theta_max, self.theta_max)
        nxt = self.evaluate(trial)
        if nxt[0] < loss:
            self.theta, self.current = trial, nxt
            self.step_size = min(1.5 * self.step_size, lr)
        else:
            self.step_size *= 0.5
        return self.current, nxt


def _gradient_fn(core, model: str, config: dict, actions, twin=None):
    """evaluate_from(state) -> evaluate(theta) -> (loss, rollout, gradient, forward s, gradient s, rollouts,
    backward rollouts) of the task loss (module docstring) with ``model``'s gradient (``mujoco-fd``: in ``twin``,
    from an EnvState or a :class:`_TwinState`)."""

    def loss_of(out) -> torch.Tensor:
        return task_loss(out.info["reward_distance"], out.alive, config["loss"])  # (B,)

    if model == "mujoco-fd":
        return _mujoco_fd(twin, config, actions)
    if model != "gb" and not config["smooth_samples"]:

        def evaluate_from(state):
            def evaluate(th: torch.Tensor):
                th = th.detach().requires_grad_(True)
                t0 = time.perf_counter()
                out = rollout(core, state, actions(th))
                loss = loss_of(out).sum()
                t1 = time.perf_counter()
                (g,) = torch.autograd.grad(loss, th)
                return float(loss.detach()), out, g, t1 - t0, time.perf_counter() - t1, 1, 1

            return evaluate

        return evaluate_from
    # sampled gradients: first-order smoothing (cfd, ipc, sdrs with smooth_samples), the mean of the autograd
    # gradients at N perturbed parameters; gb, the zeroth-order (bundled) estimate from the same N rollouts' losses
    first_order = model != "gb"
    if first_order:
        n, sigma = int(config["smooth_samples"]), float(config["smooth_sigma"])  # checked by _check_settings
    else:
        n, sigma = int(config["gb_samples"]), float(config["gb_sigma"])
        if n < 1 or not sigma > 0:
            raise ValueError(f"gb_samples must be >= 1 and gb_sigma > 0, got {n} and {sigma}")
    gen = torch.Generator().manual_seed(int(config["seed"]))

    def evaluate_from(state):
        many = state.select(torch.zeros(n, dtype=torch.long))

        def evaluate(th: torch.Tensor):
            th = th.detach()
            t0 = time.perf_counter()
            with torch.no_grad():
                out = rollout(core, state, actions(th))
                loss = float(loss_of(out).sum())
            t1 = time.perf_counter()
            eps = torch.randn((n, *th.shape), generator=gen, dtype=th.dtype)
            ths = (th + sigma * eps).requires_grad_(first_order)  # (N, K, 1, A)
            with torch.set_grad_enabled(first_order):
                acts = actions(ths[:, :, 0].transpose(0, 1))  # the N perturbed plans as one batch (T, N, A)
                losses = loss_of(rollout(core, many, acts))
            if first_order:
                (g,) = torch.autograd.grad(losses.sum(), ths)
                g = g.mean(0)
            else:
                g = ((losses - loss)[:, None, None, None] * eps).mean(0) / sigma
            return loss, out, g, t1 - t0, time.perf_counter() - t1, 1 + n, n if first_order else 0

        return evaluate

    return evaluate_from


@dataclass
class _TwinState:
    """Where an MPC run of ``mujoco-fd`` stands: the task's state and MuJoCo's own (``MujocoTwin.step``; None at
    the start, which MuJoCo takes from the task's state)."""

    env: EnvState
    physics: np.ndarray | None


def _round_off(grads: dict[float, torch.Tensor], loss: float) -> bool:
    """Whether a step-size sweep's central differences (``grads``: step -> gradient at the loss ``loss``) are
    MuJoCo's rounding, not a derivative: the steps whose differences are not zero span at least 100x, the largest
    difference at the smallest of them is at least a tenth of that at the largest (a derivative's differences
    shrink with the step), and none exceeds 1e-6 of the loss (a jump of a contact event within reach of the steps
    is larger). AntPush's box, which the Ant never reaches, moved its loss of 60 by 1e-6 at steps of 0.1 to 1e-3
    and not at all below: MuJoCo solves every contact in one solve, and the Ant's feet change the box's by rounding
    and solver tolerance."""
    diff = {h: 2 * h * float(g.abs().max()) for h, g in grads.items()}
    live = [h for h in diff if diff[h] > 0]
    if not live or max(live) < 100 * min(live):
        return False
    lo, hi = min(live), max(live)
    return diff[lo] >= 0.1 * diff[hi] and max(diff.values()) <= 1e-6 * abs(loss)


def _mujoco_fd(twin, config: dict, actions):
    """evaluate_from for ``mujoco-fd`` (module docstring); the chosen step and the sweep go to ``config["fd"]``."""
    sweep = config.setdefault("fd", {})

    def loss_at(state, th: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        env, physics = (state.env, state.physics) if isinstance(state, _TwinState) else (state, None)
        d, alive = twin.rollout(env, actions(th), physics)
        return float(task_loss(-d[:, None], alive[:, None], config["loss"]).sum()), d, alive

    def fd_gradient(state, th: torch.Tensor, h: float) -> torch.Tensor:
        g = torch.zeros_like(th)
        flat = g.view(-1)
        for i in range(th.numel()):
            e = torch.zeros_like(th).view(-1)
            e[i] = h
            e = e.view_as(th)
            flat[i] = (loss_at(state, th + e)[0] - loss_at(state, th - e)[0]) / (2 * h)
        return g

    def evaluate_from(state):
        def evaluate(th: torch.Tensor):
            th = th.detach()
            t0 = time.perf_counter()
            loss, d, alive = loss_at(state, th)
            t1 = time.perf_counter()
            n = 1  # rollouts: this loss, the gradient's, and (at the first evaluation) the step-size sweep's
            if "step" in sweep and not sweep["round_off"]:
                g = fd_gradient(state, th, sweep["step"])
                n += 2 * th.numel()
            else:
                # the step-size sweep's differences: at the first evaluation, and at every later one (MPC's later
                # control steps start elsewhere) after a sweep whose differences were round-off
                steps = FD_STEPS if config["fd_step"] is None else (float(config["fd_step"]),)
                grads = {h: fd_gradient(state, th, h) for h in steps}
                n += len(steps) * 2 * th.numel()
                noise = _round_off(grads, loss)
                if "step" not in sweep:  # the step chosen once: the one whose unit step lowers the loss most
                    rows = []
                    for h, g in grads.items():
                        norm = float(g.norm())
                        after = loss_at(state, th - config["lr"] * g / norm)[0] if norm > 0 else loss
                        rows.append({"step": h, "grad_norm": norm, "loss_after_lr_step": after})
                        n += 1 if norm > 0 else 0
                    best = min(rows, key=lambda r: (r["loss_after_lr_step"], -r["step"]))
                    sweep.update({"step": best["step"], "sweep": rows, "round_off": noise})
                # differences of round-off are no gradient: zero (the run stops there, as on a flat loss)
                g = torch.zeros_like(th) if noise else grads[sweep["step"]]
            out = _TwinRollout(d, alive)
            return loss, out, g, t1 - t0, time.perf_counter() - t1, n, 0

        return evaluate

    return evaluate_from


class _TwinRollout:
    """What run_experiment reads from a rollout, for MuJoCo's: ``info["reward_distance"]`` (T, 1), ``alive``
    (T, 1), ``info["newton_iters"]`` (zeros: MuJoCo has none) and ``q`` (None: the GIF shows the simulator's
    rollouts only)."""

    def __init__(self, distances: torch.Tensor, alive: torch.Tensor) -> None:
        self.alive = alive[:, None]  # (T, 1)
        self.info = {"reward_distance": -distances[:, None], "newton_iters": torch.zeros(1, dtype=torch.long)}
        self.q = None


def _json_object(text: str) -> dict:
    """--task-args: a JSON object."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"not JSON ({err}): {text!r}") from err
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object of the task's arguments, got {text!r}")
    return value


def _constructor_parameters(cls: type) -> dict:
    """The keyword arguments ``cls(...)`` takes: its ``__init__``'s, and its bases' where it passes ``**kwargs`` on."""
    params: dict = {}
    for klass in cls.__mro__:
        if "__init__" not in vars(klass):
            continue
        own = inspect.signature(klass.__init__).parameters
        params.update({k: v for k, v in own.items() if k != "self" and v.kind != v.VAR_KEYWORD})
        if not any(v.kind == v.VAR_KEYWORD for v in own.values()):
            break
    return params


def check_seed(seed) -> None:
    """Raise ValueError unless ``seed`` is None or one torch takes (scripts/sweep.py checks every seed of its grid)."""
    if seed is not None and not (is_int(seed) and -(2**63) <= seed < 2**64):
        raise ValueError(
            f"config['seed'] (--seed) must be an int in [-2^63, 2^64) (torch's seeds), got {seed!r}"
        )


def _check_settings(cfg: dict) -> None:
    """Raise ValueError naming the first setting of ``cfg`` out of its range."""

    def count(key: str, low: int) -> None:
        v = cfg[key]
        if not (is_int(v) and v >= low):
            raise ValueError(
                f"config['{key}'] (--{key.replace('_', '-')}) must be an int >= {low}, got {v!r}"
            )

    def positive(key: str) -> None:
        v = cfg[key]
        if not (is_real(v) and 0 < v < math.inf):
            raise ValueError(
                f"config['{key}'] (--{key.replace('_', '-')}) must be a finite number > 0, got {v!r}"
            )

    count("iters", 1)
    count("horizon", 1)
    check_seed(cfg["seed"])
    count("smooth_samples", 0)
    if cfg["smooth_samples"] and cfg["model"] not in ("cfd", "ipc", "sdrs"):
        raise ValueError(
            "config['smooth_samples'] (--smooth-samples) applies to the autograd models cfd, ipc, sdrs"
        )
    if cfg["smooth_samples"]:
        positive("smooth_sigma")
    if cfg["mpc"]:
        count("steps", 1)
    if cfg["loss"] not in LOSSES:
        raise ValueError(f"config['loss'] (--loss) must be one of {LOSSES}, got {cfg['loss']!r}")
    if cfg["threads"] is not None:
        count("threads", 1)
    positive("lr")
    if cfg["lr_final"] is not None:
        positive("lr_final")
    if cfg["fd_step"] is not None:
        positive("fd_step")
    if cfg["theta_max"] is not None:
        positive("theta_max")
    if cfg["task_args"] is not None and not isinstance(cfg["task_args"], dict):
        raise ValueError(
            f"config['task_args'] (--task-args) must be a dict of the task core's arguments, got {cfg['task_args']!r}"
        )
    if cfg["knots"] is not None and not (is_int(cfg["knots"]) and 1 <= cfg["knots"] <= cfg["horizon"]):
        raise ValueError(
            f"config['knots'] (--knots) must be an int in [1, horizon = {cfg['horizon']}], got {cfg['knots']!r}"
        )
    for key in ("dt", "eps"):
        if cfg[key] is not None:
            positive(key)
    if cfg["model"] == "gb":
        count("gb_samples", 1)
        positive("gb_sigma")
    if cfg["model"] == "mujoco-fd":
        count("mj_substeps", 1)
    given = set(cfg["task_args"] or {})
    if "potential" in given:
        raise ValueError(
            "config['task_args'] (--task-args): 'potential' is chosen by config['model'] (--model), which the logs "
            "and the sweep's tables are grouped by: leave it out"
        )
    for key in ("dt", "eps"):
        if key in given and cfg[key] is not None:
            raise ValueError(
                f"config['task_args'] (--task-args) and config['{key}'] (--{key}) both set {key}: give one"
            )
    if cfg["task"] in TASKS:  # the task's own arguments: names its constructor takes
        params = _constructor_parameters(core_class(f"cfd_torch/{cfg['task']}-v0"))
        unknown = sorted(set(cfg["task_args"] or {}) - set(params))
        if unknown:
            raise ValueError(
                f"config['task_args'] (--task-args): {cfg['task']} takes no argument {', '.join(unknown)} "
                f"(it takes {', '.join(k for k in params if k not in ('device', 'dtype'))})"
            )
        # and values it accepts: the core is built once here (under a second for every task), so that a bad value
        # fails before any run starts rather than in each run
        try:
            make_core(f"cfd_torch/{cfg['task']}-v0", **_core_kwargs(cfg))
        except (TypeError, ValueError) as err:
            raise ValueError(f"config['task_args'] (--task-args, --dt, --eps): {cfg['task']}: {err}") from err


def _core_kwargs(cfg: dict) -> dict:
    """The task core's arguments of a run: the task's defaults here, ``task_args``, ``dt``, ``eps`` (this library's
    potential's, so not for ipc and sdrs) and the baselines' ``potential``."""
    kwargs = dict(TASK_KWARGS.get(cfg["task"], {})) | dict(cfg["task_args"] or {})
    if cfg["dt"] is not None:
        kwargs["dt"] = cfg["dt"]
    # the baselines' cores refuse eps, this library's blend: a sweep's --eps skips them
    if cfg["model"] in ("ipc", "sdrs"):
        kwargs["potential"] = cfg["model"]
    elif cfg["eps"] is not None:
        kwargs["eps"] = cfg["eps"]
    return kwargs


def run_experiment(config: dict) -> dict:
    """One optimisation run (module docstring) from ``config`` (keys of :data:`DEFAULTS`; missing ones take their
    default): returns {"config", "commit", "summary", "log"} (JSON-able) and, with ``config["out"]``, writes
    log.json, loss.png and (with ``gif``) best.gif there."""
    unknown = set(config) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"config: unknown keys {sorted(unknown)}")
    cfg = {**DEFAULTS, **config}
    if cfg["task"] not in TASKS:
        raise ValueError(f"config['task'] must be one of {TASKS}, got {cfg['task']!r}")
    if cfg["model"] not in MODELS:
        raise ValueError(f"config['model'] must be one of {MODELS}, got {cfg['model']!r}")
    _check_settings(cfg)
    if cfg["threads"] is not None:
        import numba

        # numba first: its first set_num_threads launches its pool, and its OpenMP layer then sets OpenMP's thread
        # count (torch's too: one libgomp) to NUMBA_NUM_THREADS, undoing a torch.set_num_threads made before it
        numba.set_num_threads(min(int(cfg["threads"]), numba.config.NUMBA_NUM_THREADS))
        torch.set_num_threads(int(cfg["threads"]))
    torch.manual_seed(cfg["seed"])
    out_dir = Path(cfg["out"]) if cfg["out"] is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in OUTPUTS:  # an earlier run's files would sit beside this run's as if they were its
            (out_dir / name).unlink(missing_ok=True)
    task, model = cfg["task"], cfg["model"]
    core = make_core(f"cfd_torch/{task}-v0", **_core_kwargs(cfg))
    s0 = core.reset(cfg["seed"], 1)
    horizon = cfg["horizon"]
    knots = horizon if cfg["knots"] is None else cfg["knots"]
    segment = torch.arange(horizon) * knots // horizon  # the knot each step's action comes from

    def actions(th: torch.Tensor) -> torch.Tensor:
        """(horizon, B, A) actions in [-1, 1] from the knot parameters th (knots, B, A)."""
        return torch.tanh(th)[segment]

    spent = {"rollouts": 0, "backward": 0, "wall_s": 0.0}  # over every evaluation, rejected trials included
    twin = None
    if model == "mujoco-fd":
        from cfd_torch.envs.mujoco_twin import MujocoTwin

        twin = MujocoTwin(core, substeps=int(cfg["mj_substeps"]))
    gradient_from = _gradient_fn(core, model, cfg, actions, twin)

    def evaluate_from(state):
        evaluate = gradient_from(state)

        def counted(th: torch.Tensor):
            cur = evaluate(th)
            spent["rollouts"] += cur[5]
            spent["backward"] += cur[6]
            spent["wall_s"] += cur[3] + cur[4]
            return cur

        return counted

    def record(cur, ran, **extra):
        """A log row: the held iterate ``cur``'s loss, distance and gradient norm; the times and Newton iterations of
        the evaluation the iteration ran (``ran``: ngd-ls's trial, accepted or not; zeros where it ran none)."""
        loss, out, g = cur[:3]
        final = float(task_loss(out.info["reward_distance"].detach(), out.alive, "final").sum())
        t_fwd, t_grad, newton = (
            (0.0, 0.0, 0) if ran is None else (*ran[3:5], int(ran[1].info["newton_iters"].sum()))
        )
        return {
            "loss": loss, "final_distance": final, "forward_s": t_fwd, "gradient_s": t_grad,
            "grad_norm": float(g.norm()), "newton_iters": newton, "rollouts": spent["rollouts"],
            "backward": spent["backward"], "wall_s": spent["wall_s"],
        } | extra  # fmt: skip

    theta = torch.zeros(knots, 1, core.action_dim, dtype=torch.float64)
    log = []
    name = f"{task} {model} {cfg['optimizer']} seed {cfg['seed']}"
    # a deterministic gradient (no sampling) that is exactly zero, with no momentum held, ends the run (open loop)
    # or the control step's iterations (MPC): every later iterate would be the same parameters and rollout
    deterministic = model != "gb" and not cfg["smooth_samples"]

    def flat(cur, opt: Optimiser) -> bool:
        return deterministic and not bool(cur[2].any()) and opt.still()

    if not cfg["mpc"]:
        opt = Optimiser(cfg["optimizer"], cfg["lr"], cfg["lr_final"], cfg["iters"], cfg["theta_max"])
        cur = ran = opt.start(theta, evaluate_from(s0))
        best, stopped = None, None
        for it in tqdm(range(cfg["iters"] + 1), desc=name, leave=False):
            # the largest knot parameter: beyond about 3 its tanh saturates and passes on under 1 % of the gradient
            rec = record(
                cur, ran, iter=it, step=opt.step_size, theta_abs_max=float(opt.theta.detach().abs().max())
            )
            if best is None or rec["loss"] < best[0]:  # its poses up to the first terminal step (the GIF's)
                alive = int(cur[1].alive[:, 0].sum())
                best = (rec["loss"], None if cur[1].q is None else cur[1].q.detach()[: alive + 1, 0])
            log.append(rec)
            if out_dir is not None:  # an interrupted run keeps the iterations it finished
                with open(out_dir / "progress.jsonl", "a" if it else "w") as f:
                    f.write(json.dumps(rec) + "\n")
            if it < cfg["iters"]:
                if flat(cur, opt):
                    stopped = it
                    break
                cur, ran = opt.step()
        first, last = log[0], log[-1]
        low = min(log, key=lambda r: r["loss"])  # the optimiser's answer: its best iterate
        summary = {"loss_start": first["loss"], "loss_end": last["loss"], "loss_best": low["loss"],
                   "best_iter": low["iter"], "final_distance_best_iter": low["final_distance"],
                   "best_final_distance": min(r["final_distance"] for r in log),
                   "final_distance_start": first["final_distance"], "final_distance_end": last["final_distance"],
                   "rollouts": spent["rollouts"], "wall_s": spent["wall_s"], "stopped_at": stopped}  # fmt: skip
        frames_q = best[1]
    else:
        # mujoco-fd plans and executes in MuJoCo (its state a _TwinState), the others in the simulator
        steps = cfg["steps"]
        zeros = torch.zeros(steps, 1, core.action_dim, dtype=torch.float64)
        if twin is None:
            with torch.no_grad():
                zero = rollout(core, s0, zeros)
            zero_d, zero_alive = -zero.info["reward_distance"][:, 0], zero.alive[:, 0]
        else:
            zero_d, zero_alive = twin.rollout(s0, zeros)
        zero_loss = float(task_loss(-zero_d[:, None], zero_alive[:, None], cfg["loss"]).sum())
        state, executed, qs = (s0 if twin is None else _TwinState(s0, None)), [], [s0.q[0]]
        opt = Optimiser(cfg["optimizer"], cfg["lr"], cfg["lr_final"], cfg["iters"], cfg["theta_max"])
        for t in tqdm(range(steps), desc=f"{name} MPC", leave=False):
            cur = ran = opt.start(theta, evaluate_from(state))
            window0, iters_run = cur[0], 0
            for _ in range(cfg["iters"]):
                if flat(cur, opt):
                    break
                cur, ran = opt.step()
                iters_run += 1
            theta = opt.theta.detach()
            act = actions(theta)[0]
            if twin is None:
                with torch.no_grad():
                    out = core.step(state, act)
                state, done = out.state.detach(), bool(out.terminated.all())
                executed.append(float(-out.info["reward_distance"].sum()))
                qs.append(state.q[0])
            else:
                env, physics, distance, done = twin.step(state.env, act, state.physics)
                state = _TwinState(env, physics)
                executed.append(distance)
                qs.append(env.q[0])
            log.append(
                record(
                    cur,
                    ran,
                    step=t,
                    window_loss_start=window0,
                    executed_distance=executed[-1],
                    iters_run=iters_run,
                    action=act[0].tolist(),
                    action_body_xy=qs[-1][core.action_body, :2].tolist(),
                )
            )
            if out_dir is not None:  # an interrupted run keeps the control steps it executed
                with open(out_dir / "progress.jsonl", "a" if t else "w") as f:
                    f.write(json.dumps(log[-1]) + "\n")
            # shift the window, repeating its last action (with knots the plan's segments stay)
            if knots == horizon:
                theta = torch.cat([theta[1:], theta[-1:]])
            if done:
                break
        ex = torch.tensor(executed, dtype=torch.float64)[:, None]
        loss_executed = float(task_loss(-ex, torch.ones_like(ex), cfg["loss"]))
        summary = {"loss_zero_actions": zero_loss, "loss_executed": loss_executed, "steps_run": len(executed),
                   "final_distance": executed[-1], "final_distance_zero_actions":
                   float(zero_d[len(executed) - 1]), "zero_distances": zero_d.tolist(),
                   "rollouts": spent["rollouts"], "wall_s": spent["wall_s"]}  # fmt: skip
        frames_q = torch.stack(qs)
    fd = cfg.pop("fd", None)
    if fd is not None:
        summary["fd_step"], summary["fd_sweep"], summary["fd_round_off"] = (
            fd["step"],
            fd["sweep"],
            fd["round_off"],
        )
    result = {"config": {k: str(v) if isinstance(v, Path) else v for k, v in cfg.items()},
              "commit": git_revision(), "summary": summary, "log": log}  # fmt: skip
    if out_dir is not None:
        (out_dir / "log.json").write_text(json.dumps(result, indent=1))
        _plot(result, out_dir / "loss.png")
        if cfg["gif"] and frames_q is not None:
            r = core.renderer(320, 320)
            frames = [core.draw(r, q, task_at(s0, 0)) for q in frames_q]
            r.close()
            write_gif(frames, out_dir / "best.gif", fps=1.0 / core.scene.dt)
    return result


def _plot(result: dict, path: Path) -> None:
    cfg, log = result["config"], result["log"]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    x = "step" if cfg["mpc"] else "iter"
    ax[0].plot([r[x] for r in log], [r["loss"] for r in log])
    what = {"sum": "distance summed over the steps", "final": "final distance", "closest": "closest distance"}
    ax[0].set(xlabel=x, ylabel=f"loss: {what[cfg['loss']]} [m]" + (" of the window" if cfg["mpc"] else ""),
              title=f"{cfg['task']} ({cfg['model']}): {'MPC ' if cfg['mpc'] else ''}{cfg['optimizer']} "
              f"lr {cfg['lr']}")  # fmt: skip
    key = "executed_distance" if cfg["mpc"] else "final_distance"
    ax[1].plot([r[x] for r in log], [r[key] for r in log])
    ax[1].set(xlabel=x, ylabel="distance to goal [m]" if cfg["mpc"] else "final distance to goal [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The optimisation's options (shared with scripts/sweep.py): every key of DEFAULTS but task, model, seed, out."""
    d = DEFAULTS
    ap.add_argument("--iters", type=int, default=d["iters"], help="iterations (MPC: per control step)")
    ap.add_argument("--horizon", type=int, default=d["horizon"], help="actions optimised (MPC: the window)")
    ap.add_argument(
        "--mpc", action="store_true", help="receding-horizon control instead of one open-loop plan"
    )
    ap.add_argument("--steps", type=int, default=d["steps"], help="MPC: control steps executed")
    ap.add_argument("--knots", type=int, default=d["knots"],
                    help="hold actions over this many equal parts of the horizon (default: one per step)")  # fmt: skip
    ap.add_argument(
        "--dt", type=float, default=d["dt"], help="the task's time step [s] (default: the task's)"
    )
    ap.add_argument("--eps", type=float, default=d["eps"],
                    help="the blend width between the actuated body and the objects (the task's eps; default: "
                    "the task's, 1.0 for the pushing tasks, 0.01 for Billiards; the cfd model's only: the baselines "
                    "have no blend, and a sweep passes it to every model alike)")  # fmt: skip
    ap.add_argument("--task-args", type=_json_object, default=d["task_args"],
                    help='the task core\'s arguments as a JSON object, e.g. \'{"distance": 1.5}\' (Push)')  # fmt: skip
    ap.add_argument("--lr", type=float, default=d["lr"])
    ap.add_argument("--lr-final", type=float, default=d["lr_final"],
                    help="decay the learning rate geometrically from --lr to this at the last iteration")  # fmt: skip
    ap.add_argument(
        "--theta-max", type=float, default=d["theta_max"],
        help="clamp the knot parameters to [-this, this] after every step (the actions are their tanh: at 3, 0.995)",
    )  # fmt: skip
    ap.add_argument(
        "--loss",
        default=d["loss"],
        choices=LOSSES,
        help="sum: the distance summed over the steps alive; final: the distance after the last step alive; "
        "closest: the smallest distance over the steps alive",
    )
    ap.add_argument("--optimizer", default=d["optimizer"], choices=OPTIMISERS,
                    help="ngd (momentum on the unit gradient), adam or ngd-ls (with backtracking)")  # fmt: skip
    ap.add_argument("--gb-samples", type=int, default=d["gb_samples"], help="gb: rollouts per gradient")
    ap.add_argument(
        "--smooth-samples",
        type=int,
        default=d["smooth_samples"],
        help="cfd, ipc, sdrs: average the gradient over this many perturbed parameters (0: none)",
    )
    ap.add_argument("--smooth-sigma", type=float, default=d["smooth_sigma"],
                    help="--smooth-samples: the perturbations' standard deviation")  # fmt: skip
    ap.add_argument(
        "--gb-sigma", type=float, default=d["gb_sigma"], help="gb: smoothing scale of the parameters"
    )
    ap.add_argument("--fd-step", type=float, default=d["fd_step"],
                    help="mujoco-fd: central-difference step (default: chosen by a sweep over FD_STEPS)")  # fmt: skip
    ap.add_argument(
        "--mj-substeps", type=int, default=d["mj_substeps"], help="mujoco-fd: MuJoCo steps per task step"
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=d["threads"],
        help="torch and numba threads (default: theirs; sweep.py: 1)",
    )
    ap.add_argument("--no-gif", dest="gif", action="store_false")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default=DEFAULTS["task"], choices=TASKS, help="the task (its Gymnasium core)")
    ap.add_argument("--model", default=DEFAULTS["model"], choices=MODELS, help="the gradient's source")
    ap.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="the task's start (reset seed)")
    ap.add_argument(
        "--out", type=Path, default=Path("results/optimize"), help="folder for log.json, loss.png, best.gif"
    )
    add_arguments(ap)
    config = vars(ap.parse_args())
    problem = folder_problem(config["out"])
    if problem:
        ap.error(f"--out {problem}")
    try:
        _check_settings({**DEFAULTS, **config})
    except ValueError as err:
        ap.error(str(err))
    unused = unused_settings(config, [config["model"]])
    if unused:
        ap.error(f"argument {unused[0]}: {unused[1]}")
    result = run_experiment(config)
    for r in result["log"]:
        x = f"step {r['step']}" if config["mpc"] else f"iter {r['iter']}"
        print(
            f"{x}: loss {r['loss']:.10g} final distance {r['final_distance']:.6f} m, {r['rollouts']} rollouts"
        )
    print(json.dumps(result["summary"], indent=1), f"\nwritten to {config['out']}")


if __name__ == "__main__":
    main()
