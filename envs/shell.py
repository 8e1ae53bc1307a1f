"""Gymnasium faces of a :class:`~cfd_torch.envs.core.TaskCore`: a NumPy ``gym.Env`` and a native ``VectorEnv``.

Both hold one core and run it under ``torch.no_grad()``; physics, rewards and initial states are the core's. Actions
are float32 in [-1, 1]; observations float64 within the task's physical bounds. Seeding: a reset with seed s starts
the episode ``core.reset(s)`` starts (the same scene as the differentiable core's, for the same seed) and seeds
``np_random`` with s, from which later resets without a seed draw their core seeds; the vector environment seeds its
copy i with s + i, as ``gym.make_vec(..., vectorization_mode="sync")`` does (and ``core.reset(s, batch_size)``), so
the three give identical starts.
"""

from __future__ import annotations

import copy
import threading
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv

from cfd_torch._validate import is_int
from cfd_torch.sim.types import StepError

from .core import EnvState, TaskCore, real_array, stack_states, task_at

__all__ = ["CoreEnv", "CoreVectorEnv"]

_SEED_HIGH = 2**62


def _check_shell_arguments(render_mode: str | None, width: int, height: int) -> None:
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
    for name, v in (("width", width), ("height", height)):
        if not (is_int(v) and v > 0):
            raise ValueError(f"{name} must be a positive int [pixels], got {v!r}")


def _core_seed(rng: np.random.Generator, seed: int | None) -> int:
    """The core seed of a reset: ``seed`` as given, else one drawn from the environment's generator."""
    return int(rng.integers(_SEED_HIGH)) if seed is None else int(seed)


def _fps(core: TaskCore) -> int:
    """Frames per second of a rollout played at its own pace (at least 1)."""
    return max(1, round(1.0 / core.scene.dt))


def _spaces(core: TaskCore) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    low, high = core.observation_bounds()
    obs = gym.spaces.Box(low.double().cpu().numpy(), high.double().cpu().numpy(), dtype=np.float64)
    act = gym.spaces.Box(-1.0, 1.0, (core.action_dim,), dtype=np.float32)
    return act, obs


def _warn_no_render_mode(spec) -> None:
    """Gymnasium's warning for render() on an environment made without a render mode (its own environments')."""
    gym.logger.warn(
        "You are calling render method without specifying any render mode. You can specify the render_mode at "
        f'initialization, e.g. gym.make("{spec.id if spec is not None else "cfd_torch/<Task>-v0"}", '
        'render_mode="rgb_array")'
    )


class _Frames:
    """The renderer of a core, made on the first frame, on the thread that renders (an OpenGL context is current on
    the thread that made it)."""

    def __init__(self, core: TaskCore, width: int, height: int) -> None:
        self.core, self.width, self.height = core, width, height
        self.renderer = None
        self.thread: int | None = None

    def frame(self, state: EnvState) -> np.ndarray:
        """The frame of the first environment of ``state``."""
        if self.renderer is None:
            self.renderer = self.core.renderer(self.width, self.height)
            self.thread = threading.get_ident()
        elif threading.get_ident() != self.thread:
            raise RuntimeError(
                "render() called on another thread than the one that first rendered this environment: its OpenGL "
                "context is current on that thread only (EGL refuses another, EGL_BAD_ACCESS); render from that "
                "thread, or close() the environment there first (the next render() makes a new renderer)"
            )
        return self.core.draw(self.renderer, state.q[0], task_at(state, 0))

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
            self.thread = None

    def __getstate__(self) -> dict:
        """Pickled and copied without the renderer (an OpenGL context): the copy makes its own on its first frame."""
        return {**self.__dict__, "renderer": None, "thread": None}


class CoreEnv(gym.Env):
    """One environment of a task (subclasses set ``core_class``): NumPy in, NumPy out.

    Args:
        render_mode: None or "rgb_array" (headless frames of the simulator's meshes).
        device, dtype: of the core's tensors (float64 by default).
        width, height: of rendered frames [pixels].
        **task: the task core's own arguments (see its class).

    ``info`` of a step holds the reward terms (``reward_<term>``), the solver's Newton iterations and sub-steps.
    The torch core is ``env.unwrapped.core``; the current :class:`EnvState` is ``env.unwrapped.state``.
    """

    core_class: type[TaskCore]
    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
        width: int = 480,
        height: int = 480,
        **task: Any,
    ) -> None:
        _check_shell_arguments(render_mode, width, height)
        self.core = self.core_class(device=device, dtype=dtype, **task)
        self.render_mode = render_mode
        self.action_space, self.observation_space = _spaces(self.core)
        self.metadata = {**type(self).metadata, "render_fps": _fps(self.core)}
        self.state: EnvState | None = None
        self._frames = _Frames(self.core, width, height)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        with torch.no_grad():
            self.state = self.core.reset(_core_seed(self.np_random, seed))
            obs = self.core.observe(self.state)
        return obs[0].cpu().numpy().astype(np.float64), {}

    def step(self, action):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        action = real_array(action, "action")
        if action.shape != (self.core.action_dim,):
            raise ValueError(f"action must have shape ({self.core.action_dim},), got {action.shape}")
        a = torch.as_tensor(action, dtype=torch.float64, device=self.core.device)  # (cast by the core)
        with torch.no_grad():
            out = self.core.step(self.state, a[None])
        self.state = out.state
        info = {k: v[0].item() for k, v in out.info.items()}
        obs = out.obs[0].cpu().numpy().astype(np.float64)
        return obs, float(out.reward[0]), bool(out.terminated[0]), False, info

    def render(self):
        if self.render_mode is None:
            _warn_no_render_mode(self.spec)
        if self.render_mode != "rgb_array" or self.state is None:
            return None
        return self._frames.frame(self.state)

    def close(self) -> None:
        self._frames.close()


class CoreVectorEnv(VectorEnv):
    """``num_envs`` environments of a task in one object (subclasses set ``core_class``), NEXT_STEP autoreset.

    Args:
        num_envs: the number of environments.
        max_episode_steps: truncation after this many steps (None: the task's horizon; ``gym.make_vec`` passes the
            registered one; -1: never, as ``gym.make`` takes it); the attribute is None for no limit.
        render_mode, device, dtype, width, height, **task: as :class:`CoreEnv`.
        batched: step the environments as one batch of scenes (see below).

    By default the environments are stepped one by one through the core (B = 1 each), which makes a rollout
    identical to ``gym.make_vec(id, n, vectorization_mode="sync")``'s bit for bit. ``batched=True`` steps them as
    one batch of scenes in one solve (1.3-1.6x faster for 4 environments, ``scripts/bench_envs.py``); scenes are
    masked per scene inside the solve, so the results agree with the one-by-one ones to rounding (1e-12), not
    necessarily bit for bit.
    """

    core_class: type[TaskCore]
    metadata = {"render_modes": ["rgb_array"], "render_fps": 25, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        *,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
        width: int = 480,
        height: int = 480,
        batched: bool = False,
        **task: Any,
    ) -> None:
        if not (is_int(num_envs) and num_envs >= 1):
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        num_envs = int(num_envs)
        _check_shell_arguments(render_mode, width, height)
        self.core = self.core_class(device=device, dtype=dtype, **task)
        self.num_envs = num_envs
        if not isinstance(batched, (bool, np.bool_)):
            raise TypeError(f"batched must be a bool, got {batched!r}")
        self.batched = bool(batched)
        self.render_mode = render_mode
        if max_episode_steps is not None and not (
            is_int(max_episode_steps) and (max_episode_steps >= 1 or max_episode_steps == -1)
        ):
            raise ValueError(
                f"max_episode_steps must be a positive int, -1 (no time limit, as gym.make takes it) or None (the "
                f"task's horizon), got {max_episode_steps!r}"
            )
        # None: no time limit
        self.max_episode_steps = (
            self.core.horizon
            if max_episode_steps is None
            else (None if max_episode_steps == -1 else int(max_episode_steps))
        )
        self.single_action_space, self.single_observation_space = _spaces(self.core)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.metadata = {**type(self).metadata, "render_fps": _fps(self.core)}
        # (each generator seeded from entropy, its seed kept: np_random_seed as gymnasium's Env reports it)
        self._rngs, self._seeds = (
            list(x) for x in zip(*(seeding.np_random() for _ in range(num_envs)), strict=True)
        )
        self.states: list[EnvState | None] = [None] * num_envs
        self._obs = np.zeros((num_envs, self.core.obs_dim), dtype=np.float64)
        self._autoreset = np.zeros(num_envs, dtype=np.bool_)
        self._frames = _Frames(self.core, width, height)

    def _initial(self, rng: np.random.Generator, seed: int | None = None) -> tuple[EnvState, np.ndarray]:
        """A fresh environment's state and observation: the core's for ``seed``, else for a seed drawn from
        ``rng``."""
        with torch.no_grad():
            state = self.core.reset(_core_seed(rng, seed))
            return state, self.core.observe(state)[0].cpu().numpy()

    @property
    def np_random_seed(self) -> tuple[int, ...]:
        """The seed each environment's generator was last seeded with (from entropy until a seeded reset), as
        SyncVectorEnv's."""
        return tuple(self._seeds)

    @property
    def np_random(self) -> tuple[np.random.Generator, ...]:
        """Each environment's generator, which its unseeded resets draw from (read-only, as SyncVectorEnv's)."""
        return tuple(self._rngs)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif is_int(seed):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        elif isinstance(seed, (list, tuple, np.ndarray)) and all(s is None or is_int(s) for s in seed):
            seeds = [None if s is None else int(s) for s in seed]
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed has {len(seeds)} entries for {self.num_envs} environments")
        else:
            raise TypeError(f"seed must be None, an int or a sequence of ints (or None), got {seed!r}")
        mask = np.ones(self.num_envs, dtype=np.bool_)
        if options is not None and "reset_mask" in options:
            mask = options["reset_mask"]  # (as gymnasium's SyncVectorEnv checks it)
            if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
                raise TypeError(
                    "options['reset_mask'] must be a NumPy array of dtype bool, got "
                    f"{getattr(mask, 'dtype', type(mask).__name__)}"
                )
            if mask.shape != (self.num_envs,):
                raise ValueError(
                    f"options['reset_mask'] must have shape ({self.num_envs},), got {mask.shape}"
                )
            if not mask.any():
                raise ValueError(
                    "options['reset_mask'] must hold at least one True (it resets no environment)"
                )
        for i in np.flatnonzero(mask):
            if seeds[i] is not None:
                self._rngs[i], self._seeds[i] = seeding.np_random(seeds[i])
            self.states[i], self._obs[i] = self._initial(self._rngs[i], seeds[i])
            self._autoreset[i] = False
        return self._obs.copy(), {}

    def step(self, actions):
        if any(s is None for s in self.states):
            raise RuntimeError("call reset() before step()")
        actions = real_array(actions, "actions")
        if actions.shape != (self.num_envs, self.core.action_dim):
            raise ValueError(
                f"actions must have shape ({self.num_envs}, {self.core.action_dim}), got {actions.shape}"
            )
        # the actions of environments being reset are ignored, as in SyncVectorEnv
        stepping = ~self._autoreset
        if not np.isfinite(actions[stepping]).all():  # checked before any environment steps
            bad = sorted({int(i) for i in np.nonzero(stepping & ~np.isfinite(actions).all(1))[0]})
            raise ValueError(f"actions: non-finite entries for environments {bad}")
        # computed into copies, kept only if every environment steps: a StepError leaves the vector environment as
        # it was (states, observations, autoreset flags and generators)
        states, obs, rngs = list(self.states), self._obs.copy(), list(self._rngs)
        for i in np.flatnonzero(self._autoreset):  # (only these draw from their generators)
            rngs[i] = copy.deepcopy(self._rngs[i])
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        truncated = np.zeros(self.num_envs, dtype=np.bool_)
        infos: dict[str, Any] = {}
        for i in np.flatnonzero(self._autoreset):
            states[i], obs[i] = self._initial(rngs[i])
        run = [int(i) for i in np.flatnonzero(stepping)]
        groups = [run] if self.batched and run else [[i] for i in run]
        for idx in groups:
            a = torch.as_tensor(actions[idx], dtype=torch.float64, device=self.core.device)
            with torch.no_grad():
                try:
                    out = self.core.step(stack_states([states[i] for i in idx]), a)
                # a failed solve, a penetrating state: name the environment (the batch's scene k is idx[k])
                except (StepError, ValueError) as err:
                    where = (
                        f"environment {idx[0]}"
                        if len(idx) == 1
                        else f"environments {idx} stepped as one batch (its scene k is environment {idx}[k])"
                    )
                    raise type(err)(f"{where}: {err}") from err
            for k, i in enumerate(idx):
                states[i] = out.state.select(k)
                obs[i] = out.obs[k].cpu().numpy()
                rewards[i] = float(out.reward[k])
                terminated[i] = bool(out.terminated[k])
                limit = self.max_episode_steps
                truncated[i] = limit is not None and int(out.state.t[k]) >= limit
                # the single env's info (Python scalars) gathered as SyncVectorEnv does (its dtypes follow them)
                infos = self._add_info(infos, {key: v[k].item() for key, v in out.info.items()}, i)
        self.states, self._obs, self._rngs = states, obs, rngs
        self._autoreset = terminated | truncated
        return self._obs.copy(), rewards, terminated, truncated, infos

    def render(self):
        if self.render_mode is None:
            _warn_no_render_mode(self.spec)
        if self.render_mode != "rgb_array" or any(s is None for s in self.states):
            return None
        return tuple(self._frames.frame(s) for s in self.states)

    def close_extras(self, **kwargs: Any) -> None:
        self._frames.close()
