"""AntPush-v0: the Gymnasium Ant pushes a box to a target."""

from __future__ import annotations

import math

import torch
import trimesh

from cfd_torch import Action, Scene, rigid_body
from cfd_torch._validate import is_real
from cfd_torch.rotation import rotation_matrix
from cfd_torch.sim.articulation import articulation
from cfd_torch.sim.mjcf import gymnasium_ant_xml

from ._pusher import GAP, floor_body
from ._target import BoxToTargetCore
from .core import EnvState, camera_over, check_task_arguments, check_unused_by_potential
from .shell import CoreEnv, CoreVectorEnv

__all__ = ["AntPushCore", "AntPushEnv", "AntPushVectorEnv"]

_SERVO_GAINS = (100.0, 5.0)  # position actuation's default (kp, kv)


class AntPushCore(BoxToTargetCore):
    """AntPush: the Gymnasium Ant (``gymnasium/envs/mujoco/assets/ant.xml``: a torso on a floating base, four legs
    of two hinges each, eight motors of gear 150) pushes a box to a target.

    Scene: a 0.3 m cube (``box_density`` 50 kg/m^3: 1.35 kg) and the Ant on a static floor (top at z = 0; a square
    of side ``distance`` + 5 m centred between the Ant and the target: 7 m by default), friction 1 (the Ant's MJCF
    value), gravity 9.81 m/s^2, dt = 0.01 s (retried as up to 8 sub-steps if a solve fails). Rows: 0 box, 1 floor,
    2-10 the Ant's links (torso first). The Ant's joint limits, damping and armature are its MJCF's (limits as the
    simulator's C2 barrier).

    Action: (8,) in [-1, 1], one per actuator in MJCF order. ``actuation="torque"`` (default, Gymnasium's Ant): the
    motors' controls (joint torque 150 x control). ``actuation="position"``: PD targets, mapped linearly onto each
    joint's range (-1: its lower limit, +1: its upper limit), followed by position servos of gains ``servo_gains``
    = (kp [N m/rad], kv [N m s/rad]) (default (100, 5); the step's ``Params.kp`` / ``kv`` make them differentiable).

    Observation (42,): the torso's pose (translation, rotation vector) and velocity (6 + 6), the 8 joint angles and
    their velocities (8 + 8), the box's pose and velocity (6 + 6), the target's xy (2).

    Reward: ``distance`` = -|box xy - target| [m] after the step, plus ``action`` = -``action_cost`` |a|^2 (1e-3).
    Terminated when the box's centre is within 0.1 m of the target. Horizon 500 steps (5 s at the default
    dt; the time limit counts steps).

    Initial state: the Ant at rest, joints at zero where their limits allow it (hips) and mid-range otherwise
    (ankles: +-50 degrees), torso at the origin with its lowest point 2 mm above the floor
    and a heading ~ U(-0.3, 0.3) rad about z; the box at rest 1 m ahead along +x, 2 mm above the floor; the target
    ``distance`` (2 m) beyond the box along +x (the trivial start: zero action, nothing touches but the feet on the
    floor). Task variable: ``state.task["target"]`` (xy).
    """

    action_dim = 8
    action_body = 2
    obs_dim = 42
    horizon = 500

    def __init__(
        self,
        *,
        distance: float = 2.0,
        box_density: float = 50.0,
        action_cost: float = 1e-3,
        success_radius: float = 0.1,
        actuation: str = "torque",
        servo_gains: tuple[float, float] = _SERVO_GAINS,
        potential: str = "cfd",
        eps: float = 1.0,
        dt: float = 0.01,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        check_unused_by_potential(potential, "eps", eps, 1.0)
        check_task_arguments(
            action_cost=action_cost, distance=distance, box_density=box_density, success_radius=success_radius
        )
        if actuation not in ("torque", "position"):
            raise ValueError(f"actuation must be 'torque' or 'position', got {actuation!r}")
        gains_ok = isinstance(servo_gains, (tuple, list)) and len(servo_gains) == 2
        gains_ok = gains_ok and all(is_real(g) and math.isfinite(g) for g in servo_gains)
        if not (gains_ok and servo_gains[0] > 0 and servo_gains[1] >= 0):
            raise ValueError(f"servo_gains must be (kp > 0, kv >= 0), finite numbers, got {servo_gains!r}")
        if actuation == "torque" and tuple(servo_gains) != _SERVO_GAINS:
            raise ValueError(
                "servo_gains is read only by actuation='position'; actuation='torque' does not use it: leave it at "
                f"its default {_SERVO_GAINS}"
            )
        self.actuation = actuation
        self.mjcf = (gymnasium_ant_xml(servos=servo_gains if actuation == "position" else None),)
        self.ant = articulation(self.mjcf[0])
        box = rigid_body(trimesh.creation.box((0.3, 0.3, 0.3)), density=box_density)
        # the floor is refined to the Ant's capsule edges: keep it no larger than the task needs
        floor = floor_body(distance + 5.0, centre=((1.0 + distance) / 2, 0.0))
        scene = Scene(
            [box, floor],
            articulations=[self.ant],
            dt=dt,
            friction=1.0,
            substeps=8,
            potential=potential,
            pair_eps={(0, 2 + k): eps for k in range(self.ant.num_links)} if potential == "cfd" else None,
        )
        super().__init__(scene, device=device, dtype=dtype)
        self.distance = distance
        self.action_cost = action_cost
        self.success_radius = success_radius
        # joints at zero where their limits allow it, else mid-range (the ankles' range is 30-70 degrees)
        lo, hi = torch.as_tensor(self.ant.lower), torch.as_tensor(self.ant.upper)
        inside = (lo < 0) & (hi > 0)
        self._joints = torch.where(inside, torch.zeros_like(lo), 0.5 * (lo + hi)).double()
        # the Ant's lowest vertex at those joints and a base at the origin
        rows = self.ant.poses(self._joints)
        low = min(
            float((b.bsh.vertices.double() @ rotation_matrix(r[None, 3:])[0].T + r[:3])[:, 2].min())
            for b, r in zip(self.ant.bodies, rows, strict=True)
        )
        self._base_height = GAP - low
        # position actuation: an action's affine map onto the actuated joints' ranges
        joint = torch.as_tensor(self.ant.actuator_joint)
        self._target_mid = (0.5 * (lo + hi))[joint].to(dtype=dtype, device=device)
        self._target_half = (0.5 * (hi - lo))[joint].to(dtype=dtype, device=device)

    def _initial(self, gen: torch.Generator):
        u = torch.rand(1, generator=gen, dtype=torch.float64)
        base = torch.tensor([0.0, 0.0, self._base_height, 0.0, 0.0, 0.0], dtype=torch.float64)
        base[5] = 0.3 * (2 * u[0] - 1)
        q = torch.zeros(2 + self.ant.num_links, 6, dtype=torch.float64)
        q[0, 0], q[0, 2] = 1.0, 0.15 + GAP
        q[2:] = self.ant.poses(self._joints, base)
        target = torch.tensor([1.0 + self.distance, 0.0], dtype=torch.float64)
        return q, q.clone(), {"target": target}

    def _action(self, state: EnvState, action: torch.Tensor) -> Action:
        if self.actuation == "position":
            return Action(ctrl=self._target_mid + self._target_half * action)
        return Action(ctrl=action)

    def _coords(self, q: torch.Tensor) -> torch.Tensor:
        """(B, 6 + 6 + 8): the box's pose, the Ant's base pose and joint angles."""
        return self.scene.kinematics.coords(q)

    def observe(self, state: EnvState) -> torch.Tensor:
        c, cp = self._coords(state.q), self._coords(state.q_prev)
        d = c - cp
        d[:, 12:] = torch.remainder(d[:, 12:] + torch.pi, 2 * torch.pi) - torch.pi  # hinge angles wrap at pi
        v = d / self.scene.dt
        return torch.cat(
            [c[:, 6:12], v[:, 6:12], c[:, 12:], v[:, 12:], c[:, :6], v[:, :6], state.task["target"]], 1
        )

    def observation_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        # positions and velocities are unbounded (an Ant that walks off the floor falls for ever); rotation vectors
        # are re-centred below pi, joint angles within their limits; the target is the task's
        inf = math.inf
        pose = [inf, inf, inf, 4.0, 4.0, 4.0]
        vel = [inf] * 6
        joints = [4.0] * 8 + [inf] * 8
        half = self.distance + 3.0
        high = torch.tensor(pose + vel + joints + pose + vel + [half, half], dtype=torch.float64)
        return -high, high

    def render_camera(self, aspect: float = 1.0) -> dict:
        # the Ant (legs within about 0.8 m of its base), the box 1 m ahead and the target beyond it
        discs = [(0.0, 0.0, 0.8), (1.0, 0.0, 0.25), (1.0 + self.distance, 0.0, self.success_radius + 0.15)]
        return camera_over(discs, azimuth=90.0, elevation=-35.0, aspect=aspect)

    def _colour(self, i: int, body) -> tuple[float, float, float, float]:
        if i == 0:
            return (0.8, 0.55, 0.25, 1.0)
        if i == 1:
            return (0.6, 0.62, 0.6, 1.0)
        return (0.3, 0.5, 0.85, 1.0)


class AntPushEnv(CoreEnv):
    __doc__ = "Gymnasium face of :class:`AntPushCore` (its docstring is the manual).\n\n" + CoreEnv.__doc__
    core_class = AntPushCore


class AntPushVectorEnv(CoreVectorEnv):
    __doc__ = "Native vector face of :class:`AntPushCore`.\n\n" + CoreVectorEnv.__doc__
    core_class = AntPushCore
