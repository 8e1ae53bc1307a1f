"""Push-v0: an actuated pole pushes a box to a target 3 m away."""

from __future__ import annotations

import math

import torch
import trimesh

from cfd_torch import Action, Scene, rigid_body
from cfd_torch._validate import is_real

from ._pusher import GAP, Pusher, floor_body
from ._target import BoxToTargetCore
from .core import EnvState, camera_over, check_task_arguments, check_unused_by_potential
from .shell import CoreEnv, CoreVectorEnv

__all__ = ["PushCore", "PushEnv", "PushVectorEnv"]


class PushCore(BoxToTargetCore):
    """Push: drive a pole so that it pushes a box to a target.

    Scene: a 0.3 m cube (``box_density`` 200 kg/m^3: 5.4 kg) resting on a static floor (10 x 10 m, top at z = 0),
    and a pole, a dynamic 0.1 x 0.1 x 0.8 m box (500 kg/m^3: 4 kg) driven by a PD law toward planar velocity
    targets (:class:`~cfd_torch.envs._pusher.Pusher`: it hovers 2 mm above the floor, upright). Friction 0.6,
    gravity 9.81 m/s^2, dt = 0.01 s (retried as up to 8 sub-steps if a solve fails). Bodies: 0 box, 1 pole, 2 floor.

    Action: (2,) in [-1, 1], the pole's planar velocity target, ``max_speed`` (1 m/s) per unit.

    Observation (26,): box pose (translation, rotation vector) and velocity (6 + 6), pole pose and velocity
    (6 + 6), the target's xy (2).

    Reward: ``distance`` = -|box xy - target| [m] after the step, plus ``action`` = -``action_cost`` |a|^2 (1e-3).
    Terminated when the box's centre is within 0.1 m of the target. Horizon 300 steps (3 s at the default
    dt; the time limit counts steps).

    Initial state: box at rest at the origin, 2 mm above the floor (it lands in the first steps); target
    ``distance`` (3 m) away at an angle ~ U(-``angle_range``, ``angle_range``) (0.5 rad) from +x; the pole at rest
    to the side of the box (the trivial start): centre at distance U(0.5, 0.7) m from the box's centre, on a side
    drawn at random (+-90 degrees from the target direction, +- U(0, 0.3) rad). Task variable:
    ``state.task["target"]`` (xy).

    Reach: at these defaults the pole cannot bring the box to the target within the horizon, whatever it does. Its
    velocity law's force, ``m k_v (v* - v) / (1 + k_v dt)`` (67 N at rest, dt = 0.01), against the box's floor
    friction (32 N) caps the box's speed at about 0.5 m/s (0.47 measured; 0.19 at dt = 0.04): started right behind
    the box and pushing straight at the target for 3 s, the box ends 1.95 m from it (``scripts/push_reach.py``).
    With ``box_density=50`` (1.35 kg) the same push reaches 0.88 m/s, and ``distance=1.5`` then leaves time to go
    around the box first.
    """

    action_dim = 2
    obs_dim = 26
    action_body = 1
    horizon = 300

    def __init__(
        self,
        *,
        distance: float = 3.0,
        angle_range: float = 0.5,
        max_speed: float = 1.0,
        friction: float = 0.6,
        box_density: float = 200.0,
        action_cost: float = 1e-3,
        success_radius: float = 0.1,
        potential: str = "cfd",
        eps: float = 1.0,
        dt: float = 0.01,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        check_unused_by_potential(potential, "eps", eps, 1.0)
        check_task_arguments(
            action_cost=action_cost, distance=distance, max_speed=max_speed, box_density=box_density,
            success_radius=success_radius,
        )  # fmt: skip
        if not (is_real(angle_range) and 0 <= angle_range <= math.pi):
            raise ValueError(f"angle_range must be a number in [0, pi] [rad], got {angle_range!r}")
        box = rigid_body(trimesh.creation.box((0.3, 0.3, 0.3)), density=box_density)
        self.pusher = Pusher((0.1, 0.1, 0.8), density=500.0, max_speed=max_speed)
        scene = Scene(
            [box, self.pusher.body, floor_body(2 * distance + 4.0)], dt=dt, friction=friction, substeps=8,
            potential=potential, pair_eps={(0, 1): eps} if potential == "cfd" else None,
        )  # fmt: skip
        super().__init__(scene, device=device, dtype=dtype)
        self.distance = distance
        self.angle_range = angle_range
        self.action_cost = action_cost
        self.success_radius = success_radius

    def _initial(self, gen: torch.Generator):
        u = torch.rand(4, generator=gen, dtype=torch.float64)
        q = torch.zeros(3, 6, dtype=torch.float64)
        q[0, 2] = 0.15 + GAP
        heading = self.angle_range * (2 * u[0] - 1)
        side = heading + (math.pi / 2 if u[1] < 0.5 else -math.pi / 2) + 0.3 * (2 * u[2] - 1)
        r = 0.5 + 0.2 * u[3]
        q[1, 0], q[1, 1], q[1, 2] = r * torch.cos(side), r * torch.sin(side), self.pusher.height
        target = self.distance * torch.stack([torch.cos(heading), torch.sin(heading)])
        return q, q.clone(), {"target": target}

    def _action(self, state: EnvState, action: torch.Tensor) -> Action:
        g = -float(self.scene.gravity[2])
        return self.pusher.action(state, 1, action, self.scene.dt, g, 3)

    def observe(self, state: EnvState) -> torch.Tensor:
        v = self.velocity(state)
        return torch.cat([state.q[:, 0], v[:, 0], state.q[:, 1], v[:, 1], state.task["target"]], 1)

    def observation_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        # positions and velocities are unbounded (an episode may run past the horizon, a box pushed off the floor
        # falls for ever); rotation vectors are re-centred below pi; the target is the task's
        inf = math.inf
        pose = [inf, inf, inf, 4.0, 4.0, 4.0]
        vel = [inf] * 6
        high = torch.tensor(pose + vel + pose + vel + [self.distance + 2.0] * 2, dtype=torch.float64)
        return -high, high

    def render_camera(self, aspect: float = 1.0) -> dict:
        # the box and the pusher's start (within 0.7 m), and every target the angle range can draw
        arc = [-self.angle_range + 2 * self.angle_range * k / 16 for k in range(17)]
        target = [
            (self.distance * math.cos(a), self.distance * math.sin(a), self.success_radius + 0.15)
            for a in arc
        ]
        return camera_over([(0.0, 0.0, 0.75), *target], azimuth=90.0, elevation=-50.0, aspect=aspect)

    def _colour(self, i: int, body) -> tuple[float, float, float, float]:
        return [(0.8, 0.55, 0.25, 1.0), (0.25, 0.45, 0.85, 1.0), (0.6, 0.62, 0.6, 1.0)][i]


class PushEnv(CoreEnv):
    __doc__ = "Gymnasium face of :class:`PushCore` (its docstring is the manual).\n\n" + CoreEnv.__doc__
    core_class = PushCore


class PushVectorEnv(CoreVectorEnv):
    __doc__ = "Native vector face of :class:`PushCore`.\n\n" + CoreVectorEnv.__doc__
    core_class = PushCore
