"""Kinematics maps: generalised coordinates q (A, Q) to the poses (A, N, 6) of all bodies of a scene.

The energy, the Newton solve and the adjoint see the simulated bodies only through this map: contact, friction and
inertia are evaluated in pose space and pulled back,

    grad_q = J^T grad_pose,    hess_q = J^T hess_pose J + sum_k grad_pose_k d2pose_k / dq2,

so articulated bodies (a floating base and joint angles through forward kinematics) are a new map, not a new
stepper. Rows of bodies the map does not move (static, kinematic) come from the step's fixed poses.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch

__all__ = ["Kinematics", "FreeBodies"]


@runtime_checkable
class Kinematics(Protocol):
    """A map from generalised coordinates to body poses, with its first and second derivatives."""

    #: Q, the number of generalised coordinates
    num_coords: int
    #: (M,) the bodies the map moves: they carry inertia, and Params have one row per body
    bodies: torch.Tensor
    #: (Q,) the moving body (0..M-1) each coordinate belongs to (the Newton solve freezes converged bodies)
    coord_body: torch.Tensor
    #: whether converged bodies may be frozen one by one (False when a coordinate moves several bodies)
    freezable: bool

    def poses(self, q: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        """(A, N, 6) poses of all bodies: those of the map from q (A, Q), the others from ``fixed`` (A, N, 6)."""
        ...

    def coords(self, poses: torch.Tensor) -> torch.Tensor:
        """(A, Q) the coordinates whose map gives the moving rows of ``poses`` (A, N, 6)."""
        ...

    def pullback(
        self,
        q: torch.Tensor,
        grad: torch.Tensor,
        hess: torch.Tensor | None,
        fixed: torch.Tensor,
        extra: Sequence[torch.Tensor] = (),
    ) -> tuple[torch.Tensor, torch.Tensor | None, tuple[torch.Tensor, ...]]:
        """J^T grad (A, Q), J^T hess J + sum_k grad_k d2pose_k/dq2 (A, Q, Q) for pose-space grad (A, N, 6) and
        hess (A, 6N, 6N) (None for None), and J^T X J (A, Q, Q) for each pose-space matrix X (A, 6N, 6N) of
        ``extra`` (one Jacobian for all), with the other bodies at ``fixed`` (A, N, 6)."""
        ...

    def push(self, q: torch.Tensor, v: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        """(A, N, 6) J v for coordinate vectors v (A, Q) (zero rows for bodies the map does not move)."""
        ...

    def extrapolate(self, q_t: torch.Tensor, q_p: torch.Tensor) -> torch.Tensor:
        """(A, Q) the constant-velocity prediction of the next coordinates (the Newton solve's warm start)."""
        ...

    def carry(self, q: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        """(A, Q) the coordinates with every moving body translated by ``shift`` (A, 3) [m] (a start that carries
        the bodies along with a kinematic pusher)."""
        ...


class FreeBodies:
    """Free rigid bodies: q is the poses of the dynamic bodies, (A, 6 Nd), an identity map onto their rows.

    Args:
        dynamic: (Nd,) indices of the dynamic bodies.
        num_bodies: N.
    """

    def __init__(self, dynamic: torch.Tensor, num_bodies: int) -> None:
        self.dynamic = dynamic
        self.bodies = dynamic
        self.num_bodies = num_bodies
        self.num_coords = 6 * len(dynamic)
        self.coord_body = torch.arange(self.num_coords) // 6
        self._d6 = (dynamic[:, None] * 6 + torch.arange(6)).reshape(-1)  # their rows of a (6N,) pose vector

    def poses(self, q: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        out = fixed.clone()
        out[:, self.dynamic.to(q.device)] = q.reshape(q.shape[0], -1, 6)
        return out

    def coords(self, poses: torch.Tensor) -> torch.Tensor:
        return poses[:, self.dynamic.to(poses.device)].reshape(poses.shape[0], -1)

    #: converged bodies may be frozen one by one (each coordinate moves one body)
    freezable = True

    def pullback(
        self,
        q: torch.Tensor,
        grad: torch.Tensor,
        hess: torch.Tensor | None,
        fixed: torch.Tensor | None = None,
        extra: Sequence[torch.Tensor] = (),
    ) -> tuple[torch.Tensor, torch.Tensor | None, tuple[torch.Tensor, ...]]:
        d6 = self._d6.to(q.device)
        g = grad.reshape(grad.shape[0], -1)[:, d6]
        more = tuple(X[:, d6][:, :, d6] for X in extra)
        return g, (None if hess is None else hess[:, d6][:, :, d6]), more

    def push(self, q: torch.Tensor, v: torch.Tensor, fixed: torch.Tensor | None = None) -> torch.Tensor:
        out = v.new_zeros(v.shape[0], self.num_bodies, 6)
        out[:, self.dynamic.to(v.device)] = v.reshape(v.shape[0], -1, 6)
        return out

    def extrapolate(self, q_t: torch.Tensor, q_p: torch.Tensor) -> torch.Tensor:
        # dropped for a body turning by 1 rad or more per step (its rotation vector would wrap)
        v = (q_t - q_p).reshape(q_t.shape[0], -1, 6)
        v = torch.where((v[..., 3:].abs() < 1.0).all(-1, keepdim=True), v, v * 0.0)
        return q_t + v.reshape(q_t.shape[0], -1)

    def carry(self, q: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        out = q.reshape(q.shape[0], -1, 6).clone()
        out[..., :3] += shift[:, None, :]
        return out.reshape(q.shape[0], -1)
