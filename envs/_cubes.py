"""The scene Sort and Gather share: ten cubes scattered on a floor and one actuated pusher."""

from __future__ import annotations

import math

import torch
import trimesh

from cfd_torch import Action, Scene, rigid_body

from ._pusher import GAP, Pusher, floor_body
from .core import EnvState, TaskCore, _is_int, camera_over, check_task_arguments, check_unused_by_potential

__all__ = ["CubesCore"]


# draws of one centre before a scatter starts afresh, and fresh starts before it gives up
_SCATTER_TRIES = 1000
_SCATTER_RESTARTS = 20
_CLEARANCE = 0.05  # between the footprints of the scattered cubes and pusher [m]


class CubesCore(TaskCore):
    """``num_cubes`` cubes (ten) and a pusher on a floor (the manual is in :class:`SortCore` and
    :class:`GatherCore`).

    Bodies: 0..n-1 the cubes, n the pusher, n + 1 the floor. Subclasses define the reward's target regions and
    ``_task_obs_dim``, the size of the task's part of the observation for n cubes.
    """

    action_dim = 2
    horizon = 300

    def __init__(
        self,
        *,
        num_cubes: int = 10,
        cube_size: float = 0.1,
        cube_density: float = 500.0,
        spread: float = 0.8,
        max_speed: float = 1.0,
        friction: float = 0.5,
        action_cost: float = 1e-3,
        potential: str = "cfd",
        eps: float = 1.0,
        dt: float = 0.01,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if not (_is_int(num_cubes) and num_cubes >= 1):
            raise ValueError(f"num_cubes must be an int >= 1, got {num_cubes!r}")
        num_cubes = int(num_cubes)
        check_unused_by_potential(potential, "eps", eps, 1.0)
        check_task_arguments(
            action_cost=action_cost, cube_size=cube_size, cube_density=cube_density, spread=spread,
            max_speed=max_speed,
        )  # fmt: skip
        # footprints (discs of the half diagonal plus half the clearance) that cannot fit in the square at all:
        # refused before a Scene of that many bodies is built (10**6 cubes asked torch for 8 TB)
        r = math.hypot(cube_size, cube_size) / 2 + _CLEARANCE / 2
        if num_cubes * math.pi * r * r > (2 * spread + 2 * r) ** 2:
            raise ValueError(
                f"spread {spread} m is too small to scatter num_cubes = {num_cubes} cubes of cube_size {cube_size} m "
                "(their footprints alone cover more than the square): raise spread, or lower num_cubes or cube_size"
            )
        self.num_cubes = num_cubes
        self.action_body = num_cubes
        self.obs_dim = 4 * (num_cubes + 1) + self._task_obs_dim(num_cubes)
        cube = rigid_body(trimesh.creation.box((cube_size,) * 3), density=cube_density)
        self.pusher = Pusher((0.1, 0.1, 0.3), density=500.0, max_speed=max_speed)
        self.cube_size = cube_size
        self.spread = spread
        self.action_cost = action_cost
        # the floor holds the scattered cubes and every goal region, with 1 m to spare (6 m square at least)
        reach = max([spread + cube_size] + [math.hypot(x, y) + r for x, y, r in self._goal_discs()])
        bodies = [cube] * self.num_cubes + [self.pusher.body, floor_body(max(6.0, 2.0 * (reach + 1.0)))]
        scene = Scene(
            bodies, dt=dt, friction=friction, substeps=8, potential=potential,
            pair_eps={(k, self.num_cubes): eps for k in range(self.num_cubes)} if potential == "cfd" else None,
        )  # fmt: skip
        super().__init__(scene, device=device, dtype=dtype)
        # a layout that cannot be drawn fails here (a tight one can still fail in reset, by chance)
        self._scatter(torch.Generator().manual_seed(0), num_cubes + 1, _CLEARANCE)

    def _scatter(self, gen: torch.Generator, n: int, clearance: float) -> torch.Tensor:
        """(n, 2) centres uniform in [-spread, spread]^2 whose footprints are ``clearance`` apart: circles of the
        cube's half diagonal, the last one the pusher's (its own half diagonal). Rejection sampling, one draw at a
        time, started afresh when a centre finds no room in _SCATTER_TRIES draws (the centres placed so far can
        leave none), a ValueError after _SCATTER_RESTARTS fresh starts."""
        cube = math.hypot(self.cube_size, self.cube_size) / 2
        radii = [cube + clearance / 2] * (n - 1) + [math.hypot(*self.pusher.size[:2]) / 2 + clearance / 2]
        best = 0
        for _ in range(_SCATTER_RESTARTS):
            pts: list[torch.Tensor] = []
            misses = 0
            while len(pts) < n and misses < _SCATTER_TRIES:
                p = self.spread * (2 * torch.rand(2, generator=gen, dtype=torch.float64) - 1)
                r = radii[len(pts)]
                if all(float((p - o).norm()) > r + radii[k] for k, o in enumerate(pts)):
                    pts.append(p)
                    misses = 0
                else:
                    misses += 1
            if len(pts) == n:
                return torch.stack(pts)
            best = max(best, len(pts))
        raise ValueError(
            f"spread {self.spread} m is too small to scatter num_cubes = {self.num_cubes} cubes of cube_size "
            f"{self.cube_size} m and the pusher apart (at most {best} of {n} placed in {_SCATTER_RESTARTS} tries): "
            "raise spread, or lower num_cubes or cube_size"
        )

    def _initial(self, gen: torch.Generator):
        n = self.num_cubes
        xy = self._scatter(gen, n + 1, _CLEARANCE)  # the last point is the pusher's
        q = torch.zeros(n + 2, 6, dtype=torch.float64)
        q[:n, :2] = xy[:n]
        q[:n, 2] = self.cube_size / 2 + GAP
        q[:n, 5] = math.pi * (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1)  # yaw
        q[n, :2] = xy[n]
        q[n, 2] = self.pusher.height
        return q, q.clone(), self._task(gen, q)

    def _task(self, gen: torch.Generator, q: torch.Tensor) -> dict[str, torch.Tensor]:
        return {}

    def _action(self, state: EnvState, action: torch.Tensor) -> Action:
        g = -float(self.scene.gravity[2])
        return self.pusher.action(state, self.num_cubes, action, self.scene.dt, g, self.num_cubes + 2)

    def outside(self, state: EnvState) -> torch.Tensor:
        """(B, n) how far each cube's centre is outside its target region [m] (0 inside)."""
        raise NotImplementedError(f"{type(self).__name__} must define outside")

    def reward_terms(
        self, state: EnvState, action: torch.Tensor, next_state: EnvState
    ) -> dict[str, torch.Tensor]:
        return self._distance_terms(self.outside(next_state).mean(1), action)

    def terminated(self, state: EnvState) -> torch.Tensor:
        return (self.outside(state) == 0).all(1)

    def _task_obs_dim(self, n: int) -> int:
        """The size of the task's part of the observation with ``n`` cubes."""
        raise NotImplementedError(f"{type(self).__name__} must define _task_obs_dim")

    def _region_distance(self, xy: torch.Tensor, centre: torch.Tensor, radius: float) -> torch.Tensor:
        """(B, n) how far each cube's centre is outside its region (0 inside) [m]."""
        return ((xy - centre).norm(dim=-1) - radius).clamp_min(0.0)

    def _planar(self, state: EnvState) -> torch.Tensor:
        """(B, n, 4) cube xy and planar velocity."""
        v = self.velocity(state)
        n = self.num_cubes
        return torch.cat([state.q[:, :n, :2], v[:, :n, :2]], 2)

    def observe(self, state: EnvState) -> torch.Tensor:
        B, n = state.batch_size, self.num_cubes
        v = self.velocity(state)
        pusher = torch.cat([state.q[:, n, :2], v[:, n, :2]], 1)
        return torch.cat([self._planar(state).reshape(B, 4 * n), pusher, self._goal_obs(state)], 1)

    def _goal_obs(self, state: EnvState) -> torch.Tensor:
        """(B, obs_dim - 4 (n + 1)) the task's part of the observation."""
        raise NotImplementedError(f"{type(self).__name__} must define _goal_obs")

    def _goal_high(self) -> float:
        """The largest magnitude of an entry of the task's part of the observation (its bound is at least twice
        that, and at least 3)."""
        return 1.5

    def observation_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        # xy and planar velocities are unbounded: an episode may run past the horizon, the pusher runs off the
        # floor's edge if told to (it hovers) and the cubes go where it pushes them
        body = [math.inf] * 4
        extra = self.obs_dim - 4 * (self.num_cubes + 1)
        goal = max(3.0, 2.0 * self._goal_high())
        high = torch.tensor(body * (self.num_cubes + 1) + [goal] * extra, dtype=torch.float64)
        return -high, high

    def render_camera(self, aspect: float = 1.0) -> dict:
        # the cubes' and the pusher's starts and the task's goal regions
        start = (0.0, 0.0, self.spread + self.cube_size)
        return camera_over([start, *self._goal_discs()], azimuth=90.0, elevation=-60.0, aspect=aspect)

    def _goal_discs(self) -> list[tuple[float, float, float]]:
        """Floor discs (x, y, radius) [m] that hold every goal region the task can draw."""
        return []
