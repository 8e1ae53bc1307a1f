"""What Push, Sort and Gather share: a floor, an actuated pusher driven by a PD law, and floor geometry helpers."""

from __future__ import annotations

import torch
import trimesh

from cfd_torch import Action, RigidBody, rigid_body

from .core import EnvState

__all__ = ["floor_body", "Pusher"]

GAP = 2e-3  # bodies start this far above the floor [m] (more than the contact margin, 1 mm) and land


def floor_body(size: float, centre: tuple[float, float] = (0.0, 0.0)) -> RigidBody:
    """A static ``size`` x ``size`` x 0.2 m box centred at ``centre`` (xy) whose top face is the plane z = 0 (12
    triangles; the scene refines it to its partners' scale)."""
    mesh = trimesh.creation.box((size, size, 0.2))
    mesh.apply_translation((centre[0], centre[1], -0.1))
    return rigid_body(mesh, kind="static")


class Pusher:
    """A dynamic box driven toward planar velocity targets by a PD law, hovering at a fixed height, kept upright.

    Each step the law acts as a world-frame force and torque computed from the state at the start of the step, in
    the stable-PD form (Tan, Liu and Turk 2011): the accelerations the law gives when it is applied to the velocity
    and pose at the end of the step, so the hold is unconditionally stable in dt (an explicit law with these gains
    diverges beyond dt = 2 / k_d = 0.033 s: the pole bounced off the floor with a growing amplitude at dt = 0.04).
    With v the velocity at the start of the step, horizontal ``m k_v (v* - v) / (1 + k_v dt)`` (v* = ``max_speed``
    x action), vertical ``m g + m (k_p (z* - z) - (k_d + k_p dt) v_z) / (1 + k_d dt + k_p dt^2)`` (gravity
    compensated: the pusher hovers ``GAP`` above the floor and feels no floor friction), and an upright and heading
    hold ``I (-k_p theta - (k_d + k_p dt) omega) / (1 + k_d dt + k_p dt^2)`` on its rotation vector theta. Gains:
    k_v = 20 1/s, k_p = 900 1/s^2, k_d = 60 1/s (critically damped at 30 rad/s).

    Args:
        size: (3,) box size [m].
        density: [kg/m^3].
        max_speed: the velocity target of a unit action [m/s].
    """

    K_V, K_P, K_D = 20.0, 900.0, 60.0

    def __init__(self, size: tuple[float, float, float], density: float, max_speed: float) -> None:
        self.size = size
        self.body = rigid_body(trimesh.creation.box(size), density=density)
        self.max_speed = max_speed
        self.height = size[2] / 2 + GAP  # centre height [m]
        S = self.body.second_moment.double()
        self.inertia = (
            torch.trace(S) * torch.eye(3, dtype=torch.float64) - S
        )  # body frame, near-upright = world

    def action(
        self, state: EnvState, index: int, action: torch.Tensor, dt: float, gravity: float, n: int
    ) -> Action:
        """The force and torque (B, n, 3) on body ``index`` of n for planar actions (B, 2) in [-1, 1]."""
        q, qp = state.q[:, index], state.q_prev[:, index]
        v = (q - qp) / dt
        m = self.body.mass
        B = state.batch_size
        kp, kd = self.K_P, self.K_D + self.K_P * dt  # the hold's gains on the start-of-step state
        den = 1.0 + self.K_D * dt + self.K_P * dt * dt
        fxy = m * self.K_V * (self.max_speed * action - v[:, :2]) / (1.0 + self.K_V * dt)
        fz = m * (gravity + (kp * (self.height - q[:, 2]) - kd * v[:, 2]) / den)
        force = torch.cat([fxy, fz[:, None]], 1)
        inertia = self.inertia.to(q)
        torque = (-(kp * q[:, 3:] + kd * v[:, 3:]) / den) @ inertia.T
        rows = torch.arange(n, device=q.device) == index  # (n,)
        F = torch.where(rows[None, :, None], force[:, None, :], q.new_zeros(B, n, 3))
        T = torch.where(rows[None, :, None], torque[:, None, :], q.new_zeros(B, n, 3))
        return Action(force=F, torque=T)
