"""Gymnasium environments over the differentiable simulator: Billiards, Push, Sort, Gather and AntPush.

Importing ``cfd_torch.envs`` registers ``cfd_torch/Billiards-v0``, ``cfd_torch/Push-v0``, ``cfd_torch/Sort-v0``,
``cfd_torch/Gather-v0`` and ``cfd_torch/AntPush-v0`` with Gymnasium (``gym.make``, ``gym.make_vec``; the vector entry
point is the task's native :class:`~cfd_torch.envs.shell.CoreVectorEnv`).

Three faces of one task core (the physics is the same):

    env = gym.make("cfd_torch/Push-v0")                              # NumPy, for RL code
    envs = gym.make_vec("cfd_torch/Push-v0", 8)                      # native vector env, NEXT_STEP autoreset
    core = make_core("cfd_torch/Push-v0")                            # pure torch, differentiable
    state = core.reset(seed=0, batch_size=4)
    actions = torch.zeros(100, 4, 2, dtype=torch.float64, requires_grad=True)  # (T, B, A)
    out = rollout(core, state, actions)                              # differentiable in the actions
    (-(out.rewards * out.alive).sum()).backward()

The library proper (``cfd_torch``) never imports this package.
"""

from __future__ import annotations

import importlib

import gymnasium as gym

from .core import EnvState, StepOut, TaskCore
from .rollout import Rollout, rollout

__all__ = ["EnvState", "IDS", "TASKS", "Rollout", "StepOut", "TaskCore", "core_class", "make_core", "rollout"]

# id -> (module, class prefix, max_episode_steps)
_TASKS = {
    "cfd_torch/Billiards-v0": ("billiards", "Billiards", 100),
    "cfd_torch/Push-v0": ("push", "Push", 300),
    "cfd_torch/Sort-v0": ("sort", "Sort", 300),
    "cfd_torch/Gather-v0": ("gather", "Gather", 300),
    "cfd_torch/AntPush-v0": ("ant_push", "AntPush", 500),
}
IDS = tuple(_TASKS)
TASKS = tuple(name for _, name, _ in _TASKS.values())  # the tasks' names: "Billiards", ...

for _id, (_module, _name, _steps) in _TASKS.items():
    if _id not in gym.registry:
        gym.register(
            _id,
            entry_point=f"cfd_torch.envs.{_module}:{_name}Env",
            vector_entry_point=f"cfd_torch.envs.{_module}:{_name}VectorEnv",
            max_episode_steps=_steps,
        )


def core_class(env_id: str) -> type[TaskCore]:
    """The :class:`TaskCore` subclass of a registered task (its constructor's arguments are the task's)."""
    if env_id not in _TASKS:
        raise ValueError(f"unknown environment id {env_id!r}; known: {', '.join(IDS)}")
    module, name, _ = _TASKS[env_id]
    return getattr(importlib.import_module(f"cfd_torch.envs.{module}"), f"{name}Core")


def make_core(env_id: str, **kwargs) -> TaskCore:
    """The differentiable torch core of a registered task.

    Args:
        env_id: one of ``IDS``: "cfd_torch/Billiards-v0", "cfd_torch/Push-v0", "cfd_torch/Sort-v0",
            "cfd_torch/Gather-v0", "cfd_torch/AntPush-v0".
        **kwargs: the core's arguments (``help(core_class(env_id))``), e.g. ``dtype`` or ``device``.

    Raises:
        ValueError: an unknown ``env_id`` (the message lists the known ones), or a bad argument of the core.
    """
    return core_class(env_id)(**kwargs)
