"""Gather-v0: push ten cubes into one region."""

from __future__ import annotations

import math

import torch

from cfd_torch._validate import check_positive, is_real

from ._cubes import CubesCore
from .core import EnvState, disc, marker_rows
from .shell import CoreEnv, CoreVectorEnv

__all__ = ["GatherCore", "GatherEnv", "GatherVectorEnv"]


class GatherCore(CubesCore):
    """Gather: push ten cubes (``num_cubes``) into one region.

    Scene: as :class:`~cfd_torch.envs.sort.SortCore` (ten 0.1 m cubes, a PD-driven 0.1 x 0.1 x 0.3 m pusher
    hovering 2 mm above a floor (6 x 6 m, or wider to reach 1 m beyond the spread and the region), friction 0.5,
    dt = 0.01 s). Bodies: 0-9 cubes, 10 pusher, 11 floor.

    Action: (2,) in [-1, 1], the pusher's planar velocity target, ``max_speed`` (1 m/s) per unit.

    Observation (46,; 4 n + 6 for n cubes): per cube xy and planar velocity (40), the pusher's xy and planar velocity
    (4), the region's centre (2).

    Reward: ``distance`` = -mean over cubes of how far each centre is outside the region (a disc of radius
    ``region_radius``, 0.35 m) [m], plus ``action`` = -``action_cost`` |a|^2 (1e-3). Terminated when every cube is
    inside. Horizon 300 steps (3 s at the default dt; the time limit counts steps).

    Initial state: cubes and pusher at rest as in Sort (centres uniform in [-0.8, 0.8]^2, footprints 5 cm apart,
    cubes 2 mm above the floor); the region's centre at distance ``region_distance`` (1.5 m) from the origin at a
    uniform angle. Task variable: ``state.task["centre"]`` (2,). With ``num_cubes`` n the bodies are 0..n-1 cubes,
    n pusher, n + 1 floor.
    """

    def __init__(self, *, region_radius: float = 0.35, region_distance: float = 1.5, **kwargs) -> None:
        check_positive(region_radius, "region_radius")
        if not (is_real(region_distance) and 0 <= region_distance < math.inf):
            raise ValueError(f"region_distance must be a finite number >= 0, got {region_distance!r}")
        self.region_radius = region_radius
        self.region_distance = region_distance
        super().__init__(**kwargs)  # (sizes the floor from the region)

    def _task_obs_dim(self, n: int) -> int:
        return 2

    def _goal_high(self) -> float:
        return abs(self.region_distance)  # the region's centre

    def _goal_discs(self) -> list[tuple[float, float, float]]:
        return [(0.0, 0.0, self.region_distance + self.region_radius)]  # the region, at any angle

    def _task(self, gen: torch.Generator, q: torch.Tensor) -> dict[str, torch.Tensor]:
        a = 2 * math.pi * float(torch.rand(1, generator=gen, dtype=torch.float64))
        return {
            "centre": self.region_distance * torch.tensor([math.cos(a), math.sin(a)], dtype=torch.float64)
        }

    def outside(self, state: EnvState) -> torch.Tensor:
        """(B, n) how far each cube's centre is outside the region [m]."""
        xy = state.q[:, : self.num_cubes, :2]
        return self._region_distance(xy, state.task["centre"][:, None, :], self.region_radius)

    def _goal_obs(self, state: EnvState) -> torch.Tensor:
        return state.task["centre"]

    def render_markers(self):
        return [(*disc(self.region_radius), (0.2, 0.75, 0.3, 0.5))]

    def marker_poses(self, task: dict[str, torch.Tensor]) -> torch.Tensor:
        return marker_rows(task["centre"])


class GatherEnv(CoreEnv):
    __doc__ = "Gymnasium face of :class:`GatherCore` (its docstring is the manual).\n\n" + CoreEnv.__doc__
    core_class = GatherCore


class GatherVectorEnv(CoreVectorEnv):
    __doc__ = "Native vector face of :class:`GatherCore`.\n\n" + CoreVectorEnv.__doc__
    core_class = GatherCore
