"""The pure, batched, differentiable torch core every task is built on.

A task is a :class:`TaskCore`: a :class:`cfd_torch.Scene` plus an initial-state distribution, an action map, an
observation and a reward. The core is always batched (a leading dimension B of independent scenes, B = 1 for a
single environment), never writes into its inputs and never resets by itself:

    state = core.reset(seed=0, batch_size=4)            # EnvState, B = 4: scene i drawn with seed 0 + i
    out = core.step(state, action)                      # action (B, A) in [-1, 1]
    out.state, out.obs, out.reward, out.terminated, out.info

Everything is a function of its arguments, so autograd flows from the rewards to the actions, to the initial
state's tensors and to the physical parameters (``core.step(state, action, params=...)``). The Gymnasium shells
(:mod:`cfd_torch.envs.shell`) and :func:`cfd_torch.envs.rollout` drive the same core.
"""

from __future__ import annotations

import abc
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
import torch.utils._pytree as pytree
import trimesh

from cfd_torch import Action, Params, Scene, State, step
from cfd_torch._validate import FLOATS, check_positive, is_real, max_coord, usable_device
from cfd_torch._validate import is_int as _is_int
from cfd_torch.sim.bodies import RigidBody
from cfd_torch.sim.types import allow_in_torch_load

__all__ = ["EnvState", "StepOut", "TaskCore", "disc", "marker_rows", "stack_states", "task_at"]


def real_array(x: object, name: str) -> np.ndarray:
    """``x`` as a float64 array; a TypeError naming ``name`` if it is not real numbers (complex, bool, text) or is a
    tensor that requires grad (the array would drop its gradient: torch's "Can't call numpy()" named nothing)."""
    if isinstance(x, torch.Tensor) and x.requires_grad:
        raise TypeError(
            f"{name} requires grad, but this takes plain arrays and is not differentiated: step a task core "
            "(cfd_torch.envs.make_core) for gradients, or pass it detached"
        )
    array = np.asarray(x)
    if array.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be an array of real numbers, got dtype {array.dtype}")
    return array.astype(np.float64)


def half_view_angle(fovy: float, aspect: float) -> float:
    """Half the narrower field of view [rad] of a camera with vertical field of view ``fovy`` [deg] and image
    ``aspect`` (width / height): the vertical half-angle, or in a portrait image (aspect < 1) the horizontal one,
    atan(aspect tan(fovy / 2)). A sphere within it at a distance is in the picture whatever the image's shape."""
    half = math.radians(0.5 * fovy)
    return half if aspect >= 1.0 else math.atan(aspect * math.tan(half))


def camera_over(
    discs: Sequence[tuple[float, float, float]], azimuth: float, elevation: float, aspect: float = 1.0
) -> dict:
    """A free camera (MeshRenderer's settings) that shows the floor discs ``discs`` ((x, y, radius) [m] each: where
    a task's bodies start and its goals lie, for any draw of them) from ``azimuth`` and ``elevation`` [deg] in an
    image of ``aspect`` (width / height): it looks at the centre of their bounding box, from the distance at which
    the smallest circle about that point holding every disc, enlarged by 10 %, fills MuJoCo's 45 degree vertical
    field of view (the horizontal one in a portrait image, :func:`half_view_angle`). Tasks derive their cameras
    from their arguments so, and a goal moved by an argument stays in the picture."""
    d = np.asarray(discs, dtype=np.float64)
    lo = (d[:, :2] - d[:, 2:]).min(0)
    hi = (d[:, :2] + d[:, 2:]).max(0)
    centre = 0.5 * (lo + hi)
    radius = float((np.linalg.norm(d[:, :2] - centre, axis=1) + d[:, 2]).max())
    return {
        "lookat": (float(centre[0]), float(centre[1]), 0.0),
        "distance": 1.1 * radius / math.sin(half_view_angle(45.0, aspect)),
        "azimuth": azimuth,
        "elevation": elevation,
    }


def _same_device(a: torch.device, b: torch.device) -> bool:
    """The same device ("cuda" matches "cuda:0": an unset index is the current one)."""
    return a.type == b.type and (a.index is None or b.index is None or a.index == b.index)


def check_task_arguments(*, action_cost: float, **positive: float) -> None:
    """A task's constructor arguments: ``action_cost`` a finite number >= 0 and every other one finite and > 0
    (a clear ValueError naming the argument otherwise)."""
    if not (is_real(action_cost) and 0 <= action_cost < float("inf")):
        raise ValueError(f"action_cost must be a finite number >= 0, got {action_cost!r}")
    for name, value in positive.items():
        check_positive(value, name)


def check_unused_by_potential(potential: str, name: str, value: float, default: float) -> None:
    """A task's contact setting ``eps`` (this library's blend width, its ``pair_eps``) or ``dhat`` (the baselines'
    reach): a finite number > 0, and its default where the chosen contact potential does not read it (it would be
    silently ignored): ``eps`` with a baseline, ``dhat`` with "cfd"."""
    check_positive(value, name)
    for_cfd = name == "eps"
    if value != default and (potential == "cfd") != for_cfd:
        reads = "potential='cfd'" if for_cfd else "the baselines (potential 'ipc' or 'sdrs')"
        raise ValueError(
            f"{name} is read only by {reads}; potential={potential!r} does not use it: leave it at its default "
            f"{default!r}"
        )


@dataclass(frozen=True)
class EnvState:
    """The full state of B environments.

    Attributes:
        q: (B, N, 6) body poses (translation [m], rotation vector [rad]) now.
        q_prev: (B, N, 6) body poses one step earlier (velocities are (q - q_prev) / dt).
        t: (B,) int64 steps taken since reset.
        task: per-environment task variables (goal positions, classes, ...), each (B, ...).
    """

    q: torch.Tensor
    q_prev: torch.Tensor
    t: torch.Tensor
    task: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def batch_size(self) -> int:
        return int(self.q.shape[0])

    @property
    def sim(self) -> State:
        """The simulator's :class:`cfd_torch.State` of the B scenes."""
        return State(self.q, self.q_prev)

    def select(self, index: torch.Tensor | slice | int) -> EnvState:
        """The environments ``index`` (a slice or index tensor keeps the batch dimension; an int keeps it too, and
        counts from the end when negative, as in a sequence)."""
        if isinstance(index, (bool, np.bool_)) or (
            isinstance(index, torch.Tensor) and index.dtype == torch.bool and index.dim() == 0
        ):
            raise TypeError(f"index must be an int, a slice or an index tensor, got {index!r}")
        if _is_int(index):
            B = self.batch_size
            if not -B <= int(index) < B:
                raise IndexError(f"index {int(index)} is out of range for a batch of {B} environments")
            i = int(index) % B
            index = slice(i, i + 1)
        elif isinstance(index, torch.Tensor) and index.dtype != torch.bool:
            if index.is_floating_point() or index.is_complex():
                raise TypeError(
                    f"index must be an int, a slice or an index tensor, got a {index.dtype} tensor"
                )
            B = self.batch_size
            out = (index < -B) | (index >= B)
            if bool(out.any()):
                raise IndexError(
                    f"index {int(index[out].flatten()[0])} is out of range for a batch of {B} environments"
                )
        return EnvState(
            self.q[index], self.q_prev[index], self.t[index], {k: v[index] for k, v in self.task.items()}
        )

    def detach(self) -> EnvState:
        """The same state cut from the autograd graph (truncated backpropagation starts here)."""
        return pytree.tree_map(lambda x: x.detach(), self)


def _flatten(s: EnvState):
    keys = tuple(sorted(s.task))
    return [s.q, s.q_prev, s.t, *(s.task[k] for k in keys)], keys


def _unflatten(values, keys) -> EnvState:
    q, q_prev, t, *rest = values
    return EnvState(q, q_prev, t, dict(zip(keys, rest, strict=True)))


pytree.register_pytree_node(
    EnvState, _flatten, _unflatten, flatten_with_keys_fn=None, serialized_type_name="cfd_torch.envs.EnvState"
)


def task_at(state: EnvState, index: int) -> dict[str, torch.Tensor]:
    """The task variables of environment ``index`` (unbatched)."""
    return {k: v[index] for k, v in state.task.items()}


def disc(radius: float, height: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """(vertices, faces) of a flat 48-sided disc of ``radius`` whose top face is at ``height`` (a marker resting on
    the plane z = 0 at pose (x, y, 0, 0, 0, 0))."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    mesh.apply_translation((0.0, 0.0, height / 2))
    return torch.as_tensor(mesh.vertices, dtype=torch.float64), torch.as_tensor(mesh.faces, dtype=torch.long)


def marker_rows(xy: torch.Tensor, z: float = 0.0) -> torch.Tensor:
    """(M, 6) unrotated poses at the points xy ((M, 2) or (2,)) and height z: markers lying on a plane."""
    xy = xy.detach().cpu().double().reshape(-1, 2)
    return torch.cat(
        [xy, torch.full((len(xy), 1), float(z), dtype=torch.float64), xy.new_zeros(len(xy), 3)], 1
    )


def stack_states(states: list[EnvState]) -> EnvState:
    """The environments of several states (each (B_k, ...)) as one state, concatenated along the batch.

    Raises:
        TypeError: an entry is not an EnvState.
        ValueError: no states, or states whose fields differ in their shapes after the batch or their dtypes
            (states of another task, or of another core's size or dtype)."""
    states = list(states)
    if not states:
        raise ValueError("states must hold at least one EnvState")

    def kind(st: EnvState) -> dict:
        """What must agree between the states: each field's shape after the batch and its dtype."""
        fields = {
            "q": st.q,
            "q_prev": st.q_prev,
            "t": st.t,
            **{f"task[{k!r}]": v for k, v in st.task.items()},
        }
        return {k: (tuple(v.shape[1:]), v.dtype) for k, v in fields.items()}

    first = None
    for i, st in enumerate(states):
        if not isinstance(st, EnvState):
            raise TypeError(f"states[{i}] must be an EnvState, got {type(st).__name__}")
        if set(st.task) != set(states[0].task):
            raise ValueError(
                f"states[{i}] has the task variables {sorted(st.task)}, states[0] {sorted(states[0].task)}: "
                "states of one task only"
            )
        this = kind(st)
        if first is None:  # (states[0]'s)
            first = this
        for k in first:
            if this[k] != first[k]:
                raise ValueError(
                    f"states[{i}].{k} is {this[k][1]} of shape (B, {', '.join(map(str, this[k][0]))}), "
                    f"states[0].{k} {first[k][1]} of shape (B, {', '.join(map(str, first[k][0]))}): states of "
                    "one task and one core only"
                )
    return pytree.tree_map(lambda *xs: torch.cat(xs), *states)


class StepOut(NamedTuple):
    """What :meth:`TaskCore.step` returns.

    Attributes:
        state: the next :class:`EnvState`.
        obs: (B, O) observation of the next state.
        reward: (B,) reward of the step (the sum of ``info``'s reward terms).
        terminated: (B,) bool, the task reached a terminal state (success or failure) at the next state.
        info: per-environment (B,) tensors: ``reward_<term>`` for every reward term, ``newton_iters`` and
            ``substeps`` of the step's solve (a solve that does not converge raises :class:`cfd_torch.StepError`).
    """

    state: EnvState
    obs: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    info: dict[str, torch.Tensor]


def _generator_seed(seed: int) -> int:
    """The seed for torch's CPU generator, which keeps only a seed's low 32 bits: seeds in [0, 2^32) unchanged,
    others (larger or negative) hashed to 32 bits (numpy's SeedSequence)."""
    if 0 <= seed < 2**32:
        return seed
    return int(np.random.SeedSequence(seed % 2**128).generate_state(1)[0])


allow_in_torch_load(EnvState, StepOut)


class TaskCore(abc.ABC):
    """A task over the differentiable simulator: subclasses build ``self.scene`` and define the abstract methods.

    Every task's constructor takes ``potential`` ("cfd" default, "ipc" or "sdrs": ``ContactConfig.potential``), so
    the same task runs on the locally supported baselines' contact for comparisons, and ``eps``, the blend width of
    this library's potential between the actuated body and the objects it should find (``Scene(pair_eps=...)``;
    every other pair keeps the library's ``ContactConfig.eps``, 0.01; the baselines ignore it). The far field is a
    staircase: a node pair's central term (one 12 mu) gives way to its children's sum (many such terms) inside a
    band eps times the pair's radii wide, so between bands the gradient is the faint central one and inside a band
    it is up to 1e5 times larger. At 0.01 the bands are millimetres wide and an optimiser's rollouts cross them
    hit-or-miss: on Push (seed 0, 30 iterations of normalised momentum) the pole never reached the box; at 1.0 the
    bands overlap into one slope and the same run brought the pole into contact at iteration 9. So the pushing tasks
    default to 1.0. Billiards keeps 0.01 for its cue ball (its loss already falls there; not measured at 1.0).

    Attributes:
        scene: the :class:`cfd_torch.Scene` (bodies, dt, contact and friction settings).
        action_dim: A, the size of an action (every component in [-1, 1], scaled inside).
        action_body: the body the action drives (the cue ball, the pole, the pusher).
        action_cost: the weight of the reward's ``action`` term, -action_cost |a|^2.
        obs_dim: O, the size of an observation.
        horizon: the episode length the task is designed for (the Gymnasium id's ``max_episode_steps``).
        device, dtype: of every tensor the core makes (float64 by default: the simulator's reference path).
        mjcf: the MJCF (text) of each of the scene's articulations, in scene order (empty without articulations):
            what :class:`~cfd_torch.envs.mujoco_twin.MujocoTwin` rebuilds them from.
    """

    mjcf: tuple[str, ...] = ()
    action_dim: int
    action_body: int
    action_cost: float
    obs_dim: int
    horizon: int

    def __init__(
        self, scene: Scene, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64
    ):
        if dtype not in FLOATS:
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.scene = scene
        self.device = usable_device(device)
        self.dtype = dtype

    # ---- what a task defines -------------------------------------------------------------------------------------

    @abc.abstractmethod
    def _initial(self, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """One environment's initial (q (N, 6), q_prev (N, 6), task variables) drawn with ``gen`` (CPU, float64)."""

    @abc.abstractmethod
    def _action(self, state: EnvState, action: torch.Tensor) -> Action:
        """The simulator's batched :class:`cfd_torch.Action` for actions (B, A) in [-1, 1] at ``state``."""

    @abc.abstractmethod
    def observe(self, state: EnvState) -> torch.Tensor:
        """(B, O) observation of ``state``."""

    @abc.abstractmethod
    def reward_terms(
        self, state: EnvState, action: torch.Tensor, next_state: EnvState
    ) -> dict[str, torch.Tensor]:
        """The reward's terms, each (B,); the reward is their sum."""

    @abc.abstractmethod
    def terminated(self, state: EnvState) -> torch.Tensor:
        """(B,) bool: ``state`` is terminal."""

    @abc.abstractmethod
    def observation_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(O,) lower and upper physical bounds of an observation (the Gymnasium Box)."""

    def render_meshes(self) -> list[tuple[torch.Tensor, torch.Tensor, tuple[float, float, float, float]]]:
        """(vertices (V, 3) body frame, faces (F, 3), RGBA colour) of every body, in scene order, then of every
        marker (:meth:`render_markers`)."""
        bodies = [(b.bsh.vertices, b.bsh.faces, self._colour(i, b)) for i, b in enumerate(self.scene.bodies)]
        return bodies + self.render_markers()

    def render_markers(self) -> list[tuple[torch.Tensor, torch.Tensor, tuple[float, float, float, float]]]:
        """Drawn-only meshes (goal regions, targets) after the bodies: (vertices, faces, RGBA); none by default.
        They are not in the scene: nothing touches them."""
        return []

    def marker_poses(self, task: dict[str, torch.Tensor]) -> torch.Tensor:
        """(M, 6) poses of the markers for one environment's task variables (unbatched)."""
        return torch.zeros(0, 6, dtype=torch.float64)

    def render_colours(self, task: dict[str, torch.Tensor]) -> list[tuple[float, ...]] | None:
        """RGBA of every body and marker for one environment's task variables (unbatched), or None for the
        renderer's construction colours (:meth:`construction_colours`)."""
        return None

    def construction_colours(self) -> list[tuple[float, ...]]:
        """RGBA of every body and marker as the renderer is built with (task-dependent colours start from it)."""
        return [self._colour(i, b) for i, b in enumerate(self.scene.bodies)] + [
            c for *_, c in self.render_markers()
        ]

    def draw(self, renderer, q: torch.Tensor, task: dict[str, torch.Tensor]) -> np.ndarray:
        """One frame of a :meth:`renderer`: the bodies at poses q (N, 6) and the markers of one environment's task
        variables (``state.task`` at one index: :func:`task_at`)."""
        poses = torch.cat([q.detach().cpu().double(), self.marker_poses(task).cpu().double()])
        return renderer.render(poses, self.render_colours(task))

    def render_camera(self, aspect: float = 1.0) -> dict | None:
        """A free camera (lookat, distance, azimuth, elevation) framing the task in an image of ``aspect`` (width /
        height), or None for the renderer's automatic framing."""
        return None

    def render_floor(self) -> float | None:
        """Height [m] of a drawn-only ground plane under the scene, or None."""
        return None

    def renderer(self, width: int = 480, height: int = 480):
        """A :class:`~cfd_torch.envs.render.MeshRenderer` of this task's bodies, camera and floor (close it)."""
        from .render import MeshRenderer

        meshes = self.render_meshes()
        return MeshRenderer(
            [(v, f) for v, f, _ in meshes], [c for _, _, c in meshes], width=width, height=height,
            camera=self.render_camera(width / height), floor=self.render_floor(),
        )  # fmt: skip

    def _colour(self, i: int, body: RigidBody) -> tuple[float, float, float, float]:
        if body.kind == "static":
            return (0.55, 0.6, 0.55, 1.0)
        return (0.85, 0.45, 0.2, 1.0)

    # ---- the pure functions --------------------------------------------------------------------------------------

    def reset(self, seed: int | Sequence[int] | np.ndarray, batch_size: int | None = None) -> EnvState:
        """Initial states of B environments: environment i drawn with seed ``seed + i`` (an int; ``batch_size``
        environments, default 1) or ``seed[i]`` (a sequence of B ints), as Gymnasium's SyncVectorEnv seeds its
        copies. Any int seeds (torch's generator takes 32 bits: seeds outside [0, 2^32) are hashed to 32 bits, so
        that seed + 2^32 is not seed again; there are 2^32 distinct draws)."""
        if isinstance(seed, np.ndarray) and seed.ndim == 0:
            seed = seed[()]
        if _is_int(seed):
            B = 1 if batch_size is None else batch_size
            if not _is_int(B) or B < 1:
                raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
            seeds = [int(seed) + i for i in range(int(B))]
        elif isinstance(seed, (Sequence, np.ndarray)) and not isinstance(seed, (str, bytes)):
            if not all(_is_int(s) for s in seed):
                raise TypeError(
                    f"seed: every entry of a sequence of seeds must be an int, got {list(seed)!r}"
                )
            seeds = [int(s) for s in seed]
            if batch_size is not None and not (_is_int(batch_size) and batch_size >= 1):
                raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
            if not seeds or (batch_size is not None and batch_size != len(seeds)):
                raise ValueError(f"seed has {len(seeds)} entries but batch_size is {batch_size}")
        else:
            raise TypeError(f"seed must be an int or a sequence of ints, got {seed!r}")
        parts = []
        for s in seeds:
            gen = torch.Generator().manual_seed(_generator_seed(s))
            parts.append(self._initial(gen))
        q = torch.stack([p[0] for p in parts])
        q_prev = torch.stack([p[1] for p in parts])
        task = {k: torch.stack([p[2][k] for p in parts]) for k in parts[0][2]}
        return self._to(EnvState(q, q_prev, torch.zeros(len(seeds), dtype=torch.long), task))

    def step(self, state: EnvState, action: torch.Tensor, params: Params | None = None) -> StepOut:
        """One step of B environments.

        Args:
            state: the current :class:`EnvState` (B environments).
            action: (B, A) actions, each component in [-1, 1] (the physics sees values outside clipped; the
                reward's action cost is of the action as given, as in Gymnasium's MuJoCo tasks).
            params: the simulator's differentiable physical parameters (``core.scene.params()``), or None.

        Raises:
            TypeError: a state or action that :meth:`check_state` / :meth:`check_action` refuse by type (another
                dtype or device, a task variable of the wrong kind).
            ValueError: a state field of the wrong shape or with NaN/inf, a task variable out of its range, an
                action of the wrong shape or with NaN/inf.
            cfd_torch.StepError: the simulator's solve did not converge.
        """
        self.check_state(state)
        action = self.check_action(action, state.batch_size)
        sim_action = self._action(state, action.clamp(-1.0, 1.0))
        nxt, info = step(self.scene, state.sim, sim_action, params, return_info=True)
        next_state = EnvState(nxt.q, nxt.q_prev, state.t + 1, dict(state.task))  # (not the caller's dict)
        terms = self.reward_terms(state, action, next_state)
        reward = torch.stack(list(terms.values())).sum(0)
        out_info = {f"reward_{k}": v for k, v in terms.items()}
        out_info["newton_iters"] = info.newton_iters.reshape(-1)
        out_info["substeps"] = info.substeps.reshape(-1)
        return StepOut(next_state, self.observe(next_state), reward, self.terminated(next_state), out_info)

    def check_state(self, state: EnvState) -> None:
        """A clear TypeError or ValueError naming the field unless ``state`` is an EnvState of this core's dtype
        and device whose every field has the batch size of ``state.q``: ``q`` and ``q_prev`` (B, N, 6) finite,
        ``t`` (B,) int64 and >= 0, and the task variables a start of this task has (the same keys, shapes after the
        batch, float or int64), the float ones (positions) finite and within the contact functions' coordinate
        limit (1e30 m in float64, 1e12 m in float32), and each within its range (:meth:`check_task`)."""
        if not isinstance(state, EnvState):
            raise TypeError(f"state must be an EnvState, got {type(state).__name__}")
        fields = {"state.q": state.q, "state.q_prev": state.q_prev, "state.t": state.t}
        fields.update({f"state.task[{k!r}]": v for k, v in state.task.items()})
        for name, x in fields.items():
            if not isinstance(x, torch.Tensor):
                raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
            # (the poses in the core's dtype exactly; other tensors, where floating point)
            wrong_dtype = (
                x.dtype != self.dtype
                if name in ("state.q", "state.q_prev")
                else (x.is_floating_point() and x.dtype != self.dtype)
            )
            if wrong_dtype or not _same_device(x.device, self.device):
                raise TypeError(
                    f"{name} is {x.dtype} on {x.device} but this core is {self.dtype} on {self.device} "
                    "(make_core(..., dtype=, device=)); make the state with core.reset"
                )
        N = self.scene.num_bodies
        if state.q.dim() != 3 or state.q.shape[1:] != (N, 6):
            raise ValueError(f"state.q must be a (B, {N}, 6) tensor, got shape {tuple(state.q.shape)}")
        B = state.batch_size
        if state.q_prev.shape != state.q.shape:
            raise ValueError(
                f"state.q_prev has shape {tuple(state.q_prev.shape)}, state.q {tuple(state.q.shape)}"
            )
        for name, x in (("state.q", state.q), ("state.q_prev", state.q_prev)):
            bad = ~torch.isfinite(x.detach()).flatten(1).all(1)
            if bool(bad.any()):
                raise ValueError(f"{name} contains NaN or inf (environment {int(torch.nonzero(bad)[0, 0])})")
        if state.t.shape != (B,) or state.t.dtype != torch.int64:
            raise ValueError(
                f"state.t must be an int64 tensor of shape ({B},), got {state.t.dtype} {tuple(state.t.shape)}"
            )
        if bool((state.t < 0).any()):
            i = int(torch.nonzero(state.t < 0)[0, 0])
            raise ValueError(
                f"state.t counts steps: it must be >= 0, got {int(state.t[i])} (environment {i})"
            )
        fields = self._task_fields
        if set(state.task) != set(fields):
            raise ValueError(
                f"state.task must hold this task's variables {sorted(fields)}, got {sorted(state.task)}; make the "
                "state with core.reset"
            )
        for k, v in state.task.items():
            shape, is_float = fields[k]
            if v.dim() == 0 or v.shape[0] != B:
                raise ValueError(
                    f"state.task[{k!r}] must have the batch size {B} first, got shape {tuple(v.shape)}"
                )
            if tuple(v.shape[1:]) != shape:
                raise ValueError(f"state.task[{k!r}] must have shape {(B, *shape)}, got {tuple(v.shape)}")
            if is_float != v.is_floating_point() or not (is_float or v.dtype == torch.int64):
                raise TypeError(
                    f"state.task[{k!r}] must be {'a float' if is_float else 'an int64'} tensor, got {v.dtype}"
                )
            if is_float and not bool(torch.isfinite(v).all()):
                raise ValueError(f"state.task[{k!r}] contains NaN or inf")
            if is_float:
                far = v.reshape(B, -1).abs().amax(1) > max_coord(self.dtype)
                if bool(far.any()):
                    raise ValueError(
                        f"state.task[{k!r}] holds a coordinate beyond {max_coord(self.dtype):g} m (environment "
                        f"{int(torch.nonzero(far)[0, 0])}): the limit on positions in {self.dtype} (the rewards' "
                        "squared distances would overflow)"
                    )
        self.check_task(state.task)

    @functools.cached_property
    def _task_fields(self) -> dict[str, tuple[tuple[int, ...], bool]]:
        """Each task variable's shape without the batch and whether it is floating point (else int64), as a drawn
        start has them."""
        task = self._initial(torch.Generator().manual_seed(0))[2]
        return {k: (tuple(v.shape), v.is_floating_point()) for k, v in task.items()}

    def check_task(self, task: dict[str, torch.Tensor]) -> None:
        """A ValueError naming the variable where a (B, ...) task variable holds a value the task cannot draw
        (an index out of range, an unknown class); their shapes and dtypes are checked before. None by default."""
        return None

    def check_action(self, action: torch.Tensor, batch_size: int) -> torch.Tensor:
        """``action`` as a (B, A) tensor of the core's dtype and device; a clear TypeError (not real numbers) or
        ValueError (shape, NaN/inf, overflow) otherwise."""
        if not isinstance(action, torch.Tensor):
            # (float64 first: a value beyond the core's dtype is named as such, not as inf)
            action = torch.as_tensor(real_array(action, "action"), dtype=torch.float64, device=self.device)
        if action.dtype == torch.bool or action.is_complex():
            raise TypeError(f"action must be a tensor of real numbers, got {action.dtype}")
        if action.shape != (batch_size, self.action_dim):
            raise ValueError(
                f"action must have shape ({batch_size}, {self.action_dim}), got {tuple(action.shape)}"
            )
        if not bool(torch.isfinite(action).all()):
            raise ValueError("action contains NaN or inf")
        given, action = action, action.to(dtype=self.dtype, device=self.device)
        square = (action.detach() * action.detach()).sum(1)
        if not bool(torch.isfinite(square).all()):
            largest = float(given.detach().abs().max())  # (as given: in the core's dtype it may read inf)
            raise ValueError(
                f"action: |a|^2 overflows {self.dtype} (largest |a_i| {largest:.3g}); actions are in [-1, 1]"
            )
        if not bool(torch.isfinite(self.action_cost * square).all()):
            largest = float(given.detach().abs().max())
            raise ValueError(
                f"action: the reward's action_cost |a|^2 overflows {self.dtype} (action_cost {self.action_cost:g}, "
                f"largest |a_i| {largest:.3g}); actions are in [-1, 1]"
            )
        return action

    def _to(self, state: EnvState) -> EnvState:
        def cast(x: torch.Tensor) -> torch.Tensor:
            if x.is_floating_point():
                return x.to(dtype=self.dtype, device=self.device)
            return x.to(device=self.device)

        return pytree.tree_map(cast, state)

    def velocity(self, state: EnvState) -> torch.Tensor:
        """(B, N, 6) backward-difference generalised velocities."""
        return state.sim.velocity(self.scene.dt)

    def _distance_terms(self, distance: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """The reward terms every task has: ``distance`` = -distance (B,) [m] and ``action`` = -action_cost |a|^2."""
        return {"distance": -distance, "action": -self.action_cost * (action * action).sum(1)}
