"""Differentiable rollouts of a task core: open-loop action sequences or policies, with graph cuts and checkpoints."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch.utils.checkpoint import checkpoint

from cfd_torch import Params
from cfd_torch._validate import is_int
from cfd_torch.sim.types import allow_in_torch_load

from .core import EnvState, TaskCore

__all__ = ["Rollout", "rollout"]

Policy = Callable[[torch.Tensor, int], torch.Tensor]


class Rollout(NamedTuple):
    """A rollout of T steps of B environments.

    Attributes:
        obs: (T + 1, B, O) observations, the initial one first.
        actions: (T, B, A) the actions taken (as given, before clipping to [-1, 1]).
        rewards: (T, B) rewards.
        terminated: (T, B) bool, the state after step t is terminal.
        alive: (T, B) 1.0 until (and including) the first terminal step, then 0.0: ``(rewards * alive).sum(0)`` is
            the return of episodes that end at termination (the core keeps stepping with fixed shapes).
        info: per step info, each (T, B).
        final: the :class:`EnvState` after the last step.
        q: (T + 1, B, N, 6) body poses along the rollout (for rendering and analysis).
    """

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    terminated: torch.Tensor
    alive: torch.Tensor
    info: dict[str, torch.Tensor]
    final: EnvState
    q: torch.Tensor


allow_in_torch_load(Rollout)


def _policy_action(core: TaskCore, policy: Policy, obs: torch.Tensor, t: int) -> torch.Tensor:
    """policy(obs, t), checked: a tensor of shape (B, A) or (A,)."""
    a = policy(obs, t)
    B, A = obs.shape[0], core.action_dim
    if not isinstance(a, torch.Tensor):
        raise TypeError(f"policy(obs, {t}) must return a torch tensor of actions, got {type(a).__name__}")
    if tuple(a.shape) not in ((B, A), (A,)):
        raise ValueError(
            f"policy(obs, {t}) must return actions of shape ({B}, {A}) or ({A},), got {tuple(a.shape)}"
        )
    if a.is_floating_point() and not bool(torch.isfinite(a).all()):
        raise ValueError(f"policy(obs, {t}) returned actions with NaN or inf")
    return a


def _same_actions(a: torch.Tensor, first: torch.Tensor) -> bool:
    """Whether a recomputed action equals the forward's (to 64 eps of the actions' scale: a GPU kernel may round
    differently on a second run)."""
    if a.shape != first.shape:
        return False
    if not first.numel():
        return True
    eps = torch.finfo(first.dtype).eps if first.is_floating_point() else 0.0
    return float((a.detach() - first).abs().max()) <= 64 * eps * max(1.0, float(first.abs().max()))


def _chunk(
    core: TaskCore,
    state: EnvState,
    policy,
    t0: int,
    n: int,
    params: Params | None,
    taken: list[torch.Tensor] | None = None,
):
    """n steps from ``state`` at time t0: (state, obs (n, B, O), actions, rewards, terminated, info, q).
    ``taken`` (a checkpointed chunk's): the policy's actions of the forward run, recorded there and compared with
    the recomputation's in the backward."""
    obs, acts, rews, terms, qs = [], [], [], [], []
    infos: dict[str, list[torch.Tensor]] = {}
    o = core.observe(state)
    recomputing = taken is not None and len(taken) == n
    for k in range(n):
        a = policy[t0 + k] if isinstance(policy, torch.Tensor) else _policy_action(core, policy, o, t0 + k)
        if taken is not None and not isinstance(policy, torch.Tensor):
            if not recomputing:
                taken.append(a.detach().clone())
            elif not _same_actions(a, taken[k]):
                raise RuntimeError(
                    f"policy(obs, {t0 + k}) returned other actions when rollout(checkpoint_every=...) recomputed "
                    "its chunk in the backward pass: under checkpointing the policy must be a function of "
                    "(obs, t) and its parameters alone (no state kept between calls, such as a recurrent "
                    "policy's hidden state, and noise only from torch's default generator, which checkpointing "
                    "replays); the gradients would be wrong. Use checkpoint_every=None for such a policy."
                )
        if a.dim() == 1:
            a = a.expand(state.batch_size, -1)
        out = core.step(state, a, params)
        state, o = out.state, out.obs
        obs.append(o)
        acts.append(a)
        rews.append(out.reward)
        terms.append(out.terminated)
        qs.append(state.q)
        for key, v in out.info.items():
            infos.setdefault(key, []).append(v)
    stack = {key: torch.stack(v) for key, v in infos.items()}
    return (
        state,
        torch.stack(obs),
        torch.stack(acts),
        torch.stack(rews),
        torch.stack(terms),
        stack,
        torch.stack(qs),
    )


def rollout(
    core: TaskCore,
    state: EnvState,
    policy: torch.Tensor | Policy,
    horizon: int | None = None,
    *,
    params: Params | None = None,
    truncate_every: int | None = None,
    checkpoint_every: int | None = None,
) -> Rollout:
    """Step B environments ``horizon`` times, differentiably.

    Args:
        core: the task.
        state: the start (its tensors may require grad).
        policy: a (T, B, A) or (T, A) tensor of actions (open loop; T >= horizon), or a callable
            ``policy(obs (B, O), t) -> action (B, A) or (A,)`` (closed loop; its parameters get gradients; t counts
            this rollout's steps from 0, whatever ``state.t`` is: an MPC window's first step is t = 0).
        horizon: steps (default: T of an action tensor, else ``core.horizon``).
        params: the simulator's physical parameters (``core.scene.params()`` with requires_grad), or None.
        truncate_every: cut the graph of the poses (``q``, ``q_prev``) every k steps: gradients flow within windows
            of k steps only (truncated backpropagation through time, as in SHAC / Brax APG); the task variables
            (``state.task``, goals) are not cut, so a goal's gradient sums every window's. Every window's graph
            lives until the one backward, so it saves no memory.
        checkpoint_every: recompute chunks of k steps in the backward pass instead of storing the tensors their
            steps save (``torch.utils.checkpoint``, non-reentrant): one more forward per chunk, the same gradients
            (the forward solve is deterministic). A callable policy must then be a function of (obs, t) and its
            parameters alone (noise from torch's default generator is replayed, not an explicit
            torch.Generator's): the backward raises RuntimeError if the recomputed chunk's policy returns other
            actions (a recurrent policy's hidden state kept on the object, NumPy noise). Memory stays linear in
            the horizon, whatever k, and checkpointing saves little of it: a step saves only small tensors (its
            Hessian over the moving bodies' coordinates, the contact Hessian's blocks with the fixed poses), and
            the graph's nodes, which are kept, weigh more; a session-53 audit measured 0.18 -> 0.14 MB per step on
            Billiards and none on Push (0.16 MB per step either way; 3 % less with 4 environments).

    Returns:
        A :class:`Rollout`.
    """
    if not isinstance(core, TaskCore):
        raise TypeError(f"core must be a task core (cfd_torch.envs.make_core), got {type(core).__name__}")
    if not isinstance(state, EnvState):
        raise TypeError(f"state must be an EnvState, got {type(state).__name__}")
    core.check_state(state)  # (the start's observation reads it before any step checks it)
    if horizon is not None and (not is_int(horizon) or horizon < 0):
        raise ValueError(f"horizon must be an int >= 0 or None, got {horizon!r}")
    if isinstance(policy, torch.Tensor):
        if policy.dim() == 2:
            policy = policy[:, None, :].expand(-1, state.batch_size, -1)
        if policy.dim() != 3 or policy.shape[1:] != (state.batch_size, core.action_dim):
            raise ValueError(
                f"policy must be a (T, {state.batch_size}, {core.action_dim}) or (T, {core.action_dim}) tensor, "
                f"got {tuple(policy.shape)}"
            )
        T = policy.shape[0] if horizon is None else horizon
        if T > policy.shape[0]:
            raise ValueError(f"horizon {T} exceeds the {policy.shape[0]} actions given")
    elif callable(policy):
        T = core.horizon if horizon is None else horizon
    else:
        raise TypeError(f"policy must be a tensor of actions or a callable, got {type(policy).__name__}")
    for name, k in (("truncate_every", truncate_every), ("checkpoint_every", checkpoint_every)):
        if k is not None and (not is_int(k) or k < 1):
            raise ValueError(f"{name} must be a positive int or None, got {k!r}")
    if not is_int(T) or T < 0:
        raise ValueError(f"horizon must be an int >= 0, got {T!r}")

    # chunk boundaries: every truncate_every and every checkpoint_every step
    cuts = {0, T}
    for k in (truncate_every, checkpoint_every):
        if k is not None:
            cuts.update(range(0, T, k))
    bounds = sorted(cuts)
    parts = []
    obs0 = core.observe(state)
    q0 = state.q
    for t0, t1 in zip(bounds[:-1], bounds[1:], strict=True):
        if truncate_every is not None and t0 > 0 and t0 % truncate_every == 0:
            # the dynamics' state is cut; the task variables (goals) enter every window's rewards as they are
            state = EnvState(state.q.detach(), state.q_prev.detach(), state.t, state.task)
        if checkpoint_every is not None:  # (non-reentrant: the chunk's inputs and outputs may be any pytree)
            state, *part = checkpoint(
                _chunk, core, state, policy, t0, t1 - t0, params, [], use_reentrant=False
            )
        else:
            state, *part = _chunk(core, state, policy, t0, t1 - t0, params)
        parts.append(part)
    if parts:
        obs, acts, rews, terms, infos, qs = (list(x) for x in zip(*parts, strict=True))
        obs = torch.cat([obs0[None], *obs])
        acts, rews, terms, qs = torch.cat(acts), torch.cat(rews), torch.cat(terms), torch.cat(qs)
        info = {k: torch.cat([i[k] for i in infos]) for k in infos[0]}
    else:
        B = state.batch_size
        obs = obs0[None]
        acts = obs0.new_zeros(0, B, core.action_dim)
        rews = obs0.new_zeros(0, B)
        terms = torch.zeros(0, B, dtype=torch.bool, device=obs0.device)
        qs = state.q[None][:0]
        # the keys a step's info has, each (0, B)
        names = core.reward_terms(state, obs0.new_zeros(B, core.action_dim), state)
        info = {f"reward_{k}": rews.clone() for k in names}
        info.update(
            {k: torch.zeros(0, B, dtype=torch.long, device=obs0.device) for k in ("newton_iters", "substeps")}
        )
    done_before = torch.cumsum(terms.long(), 0) - terms.long()  # terminal steps strictly before t
    alive = (done_before == 0).to(rews.dtype)
    return Rollout(obs, acts, rews, terms, alive, info, state, torch.cat([q0[None], qs]))
