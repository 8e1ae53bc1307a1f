"""Kinematics maps: generalised coordinates q (A, Q) to the poses (A, N, 6) of all bodies of a scene.

The energy, the Newton solve and the adjoint see the simulated bodies only through this map: contact, friction and
inertia are evaluated in pose space and pulled back,

    grad_q = J^T grad_pose,    hess_q = J^T hess_pose J + sum_k grad_pose_k d2pose_k / dq2,

so articulated bodies (a floating base and joint angles through forward kinematics) are a new map, not a new
stepper. Rows of bodies the map does not move (static, kinematic), and the components of rows it holds (a planar
map keeps each body's height, roll and pitch), come from the step's fixed poses.
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
    #: (N, 6) bool, the pose components the map moves (the others come from the fixed poses)
    moved: torch.Tensor
    #: (N,) bool, the moved bodies whose poses also depend on the fixed poses (the links of a fixed-base robot
    #: whose joint-less root stands where the state puts it): the adjoint differentiates them in those
    hung: torch.Tensor
    #: whether translating q's bodies and the fixed poses together translates every pose the map gives (False
    #: when some body hangs from a frame fixed in the world, as a robot hung from its mount: see ``translated``)
    translation_invariant: bool

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

    def translated(self, origin: torch.Tensor) -> Kinematics:
        """This map in the frame whose origin is ``origin`` (3,) [m] in the world: the frames it reads as world
        poses (a robot's mount) moved by -origin; itself when ``translation_invariant``."""
        ...


class FreeBodies:
    """Free rigid bodies: q is the poses of the dynamic bodies, (A, 6 Nd), an identity map onto their rows; or,
    planar, their x, y and rotation-vector z components, (A, 3 Nd): each body moves in its plane z = const and turns
    about the vertical (its height, roll and pitch stay those of the start poses; with zero roll and pitch the
    rotation-vector z component is the yaw angle, so the map is linear).

    Args:
        dynamic: (Nd,) indices of the dynamic bodies.
        num_bodies: N.
        planar: the planar map.
    """

    def __init__(self, dynamic: torch.Tensor, num_bodies: int, planar: bool = False) -> None:
        self.dynamic = dynamic
        self.bodies = dynamic
        self.num_bodies = num_bodies
        self.planar = planar
        comps = torch.tensor([0, 1, 5] if planar else [0, 1, 2, 3, 4, 5])
        self._k = len(comps)
        self._rot = comps >= 3  # which of a body's coordinates are rotation-vector components
        self._trans = comps[comps < 3]  # the translation components the map moves
        self.num_coords = self._k * len(dynamic)
        self.coord_body = torch.arange(self.num_coords) // self._k
        self._d6 = (dynamic[:, None] * 6 + comps).reshape(-1)  # their entries of a (6N,) pose vector
        # those entries as one slice where they are consecutive (moving bodies numbered in a row, not planar): the
        # pullback then slices the Hessian instead of gathering it, which at 80 bodies copied 2 MB twice per evaluation
        lo = int(self._d6[0]) if len(self._d6) else 0
        self._span = (
            slice(lo, lo + len(self._d6))
            if torch.equal(self._d6, torch.arange(lo, lo + len(self._d6)))
            else None
        )
        self.moved = torch.zeros(num_bodies * 6, dtype=torch.bool)
        self.moved[self._d6] = True
        self.moved = self.moved.reshape(num_bodies, 6)
        self.hung = torch.zeros(num_bodies, dtype=torch.bool)

    def poses(self, q: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        A = q.shape[0]
        d6 = self._d6.to(q.device)
        out = fixed.reshape(A, -1).index_copy(1, d6, q)  # out of place: differentiable in q and fixed
        return out.reshape(fixed.shape)

    def coords(self, poses: torch.Tensor) -> torch.Tensor:
        return poses.reshape(poses.shape[0], -1)[:, self._d6.to(poses.device)]

    #: converged bodies may be frozen one by one (each coordinate moves one body)
    freezable = True
    translation_invariant = True

    def translated(self, origin: torch.Tensor) -> FreeBodies:
        return self

    def pullback(
        self,
        q: torch.Tensor,
        grad: torch.Tensor,
        hess: torch.Tensor | None,
        fixed: torch.Tensor | None = None,
        extra: Sequence[torch.Tensor] = (),
    ) -> tuple[torch.Tensor, torch.Tensor | None, tuple[torch.Tensor, ...]]:
        d6 = self._span if self._span is not None else self._d6.to(q.device)
        g = grad.reshape(grad.shape[0], -1)[:, d6]
        more = tuple(X[:, d6][:, :, d6] for X in extra)
        return g, (None if hess is None else hess[:, d6][:, :, d6]), more

    def push(self, q: torch.Tensor, v: torch.Tensor, fixed: torch.Tensor | None = None) -> torch.Tensor:
        out = v.new_zeros(v.shape[0], self.num_bodies * 6)
        out[:, self._d6.to(v.device)] = v
        return out.reshape(v.shape[0], self.num_bodies, 6)

    def extrapolate(self, q_t: torch.Tensor, q_p: torch.Tensor) -> torch.Tensor:
        # dropped for a body turning by 1 rad or more per step (its rotation vector would wrap)
        v = (q_t - q_p).reshape(q_t.shape[0], -1, self._k)
        rot = self._rot.to(q_t.device)
        v = torch.where((v[..., rot].abs() < 1.0).all(-1, keepdim=True), v, v * 0.0)
        return q_t + v.reshape(q_t.shape[0], -1)

    def carry(self, q: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        """(A, Q) with every body translated by ``shift`` (A, 3) (planar: its horizontal part)."""
        out = q.reshape(q.shape[0], -1, self._k).clone()
        t = self._trans.to(q.device)
        out[..., : len(t)] += shift[:, None, t]
        return out.reshape(q.shape[0], -1)
