"""Sort-v0: push ten cubes of two classes, each class into its own region."""

from __future__ import annotations

import torch

from cfd_torch._validate import check_positive

from ._cubes import CubesCore
from .core import EnvState, disc, marker_rows
from .shell import CoreEnv, CoreVectorEnv

__all__ = ["SortCore", "SortEnv", "SortVectorEnv"]


class SortCore(CubesCore):
    """Sort: push each of ten cubes (``num_cubes``) into the region of its class.

    Scene: ten 0.1 m cubes (``cube_density`` 500 kg/m^3: 0.5 kg) on a static floor (top at z = 0; 6 x 6 m, or
    wider to reach 1 m beyond the cubes' spread and the regions) and a pusher, a dynamic 0.1 x 0.1 x 0.3 m box
    driven by a PD law toward planar velocity targets
    (:class:`~cfd_torch.envs._pusher.Pusher`: it hovers 2 mm above the floor, upright). Friction 0.5, gravity
    9.81 m/s^2, dt = 0.01 s (retried as up to 8 sub-steps if a solve fails). Bodies: 0-9 cubes, 10 pusher, 11 floor.

    Action: (2,) in [-1, 1], the pusher's planar velocity target, ``max_speed`` (1 m/s) per unit.

    Observation (58,; 5 n + 8 for n cubes): per cube xy and planar velocity (40), the pusher's xy and planar velocity
    (4), each cube's class as -1 / +1 (10), the two regions' centres (4).

    Reward: ``distance`` = -mean over cubes of how far each centre is outside its class's region (discs of radius
    ``region_radius`` 0.4 m centred at (-``region_offset``, 0) for class 0 and (+``region_offset``, 0) for class 1,
    1.2 m) [m], plus ``action`` = -``action_cost`` |a|^2 (1e-3). Terminated when every cube is inside its region.
    Horizon 300 steps (3 s at the default dt; the time limit counts steps).

    Initial state: cubes at rest 2 mm above the floor (they land in the first steps), centres uniform in
    [-``spread``, ``spread``]^2 (0.8 m) with footprints 5 cm apart, yaw uniform; the pusher at rest at another such
    point (the trivial start: zero action leaves everything in place); five cubes of each class (n // 2 of class 0),
    assigned by a random permutation. Task variables: ``state.task["classes"]`` (n,) int64, ``state.task["centres"]``
    (2, 2).

    With ``num_cubes`` n the bodies are 0..n-1 cubes, n pusher, n + 1 floor.
    """

    def __init__(self, *, region_radius: float = 0.4, region_offset: float = 1.2, **kwargs) -> None:
        check_positive(region_radius, "region_radius")
        check_positive(region_offset, "region_offset")
        self.region_radius = region_radius
        self.region_offset = region_offset
        super().__init__(**kwargs)  # (sizes the floor from the regions)

    def _task_obs_dim(self, n: int) -> int:
        return n + 4

    def _goal_high(self) -> float:
        return max(1.0, abs(self.region_offset))  # the classes (+-1) and the regions' centres

    def _goal_discs(self) -> list[tuple[float, float, float]]:
        return [(-self.region_offset, 0.0, self.region_radius), (self.region_offset, 0.0, self.region_radius)]

    def _task(self, gen: torch.Generator, q: torch.Tensor) -> dict[str, torch.Tensor]:
        classes = (torch.randperm(self.num_cubes, generator=gen) >= self.num_cubes // 2).long()
        centres = torch.tensor([[-self.region_offset, 0.0], [self.region_offset, 0.0]], dtype=torch.float64)
        return {"classes": classes, "centres": centres}

    def check_task(self, task: dict[str, torch.Tensor]) -> None:
        bad = ((task["classes"] != 0) & (task["classes"] != 1)).any(1)
        if bool(bad.any()):
            raise ValueError(
                f"state.task['classes'] must hold classes 0 and 1 only (environment {int(torch.nonzero(bad)[0])})"
            )

    def outside(self, state: EnvState) -> torch.Tensor:
        """(B, n) how far each cube's centre is outside its class's region [m]."""
        centre = torch.gather(state.task["centres"], 1, state.task["classes"][:, :, None].expand(-1, -1, 2))
        return self._region_distance(state.q[:, : self.num_cubes, :2], centre, self.region_radius)

    def _goal_obs(self, state: EnvState) -> torch.Tensor:
        sign = 2.0 * state.task["classes"].to(state.q.dtype) - 1.0
        return torch.cat([sign, state.task["centres"].reshape(-1, 4)], 1)

    CLASS_COLOURS = ((0.85, 0.25, 0.2), (0.95, 0.75, 0.15))  # class 0 red, class 1 yellow

    def _colour(self, i: int, body) -> tuple[float, float, float, float]:
        if i < self.num_cubes:
            return (0.85, 0.45, 0.2, 1.0)
        return [(0.25, 0.45, 0.85, 1.0), (0.6, 0.62, 0.6, 1.0)][i - self.num_cubes]

    def render_markers(self):
        return [(*disc(self.region_radius), (*c, 0.45)) for c in self.CLASS_COLOURS]

    def marker_poses(self, task: dict[str, torch.Tensor]) -> torch.Tensor:
        return marker_rows(task["centres"])

    def render_colours(self, task: dict[str, torch.Tensor]) -> list[tuple[float, ...]]:
        """Cubes in their class's colour, regions in a lighter one."""
        colours = self.construction_colours()
        colours[: self.num_cubes] = [(*self.CLASS_COLOURS[int(k)], 1.0) for k in task["classes"]]
        return colours


class SortEnv(CoreEnv):
    __doc__ = "Gymnasium face of :class:`SortCore` (its docstring is the manual).\n\n" + CoreEnv.__doc__
    core_class = SortCore


class SortVectorEnv(CoreVectorEnv):
    __doc__ = "Native vector face of :class:`SortCore`.\n\n" + CoreVectorEnv.__doc__
    core_class = SortCore
