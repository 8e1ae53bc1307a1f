"""Rotation vectors (exponential map of SO(3)) and their first and second derivatives.

Poses are ``(..., 6)`` tensors: translation (3) then rotation vector omega (3); a body-frame point X maps to
``x = R(omega) X + t``. Because x is linear in X, every derivative of x with respect to omega is a derivative of R
applied to X, so the per-body tensors ``dR[..., i] = dR/d omega_i`` and ``d2R[..., i, j]`` carry all the
kinematics the contact derivatives need (the "second-order rotation terms").

Rodrigues: R = I + A(t) K + B(t) K^2 with K = [omega]_x, t = |omega|^2, A = sin(theta)/theta,
B = (1 - cos(theta))/theta^2; below t = 1e-4 both use their Taylor series (polynomials in t, exact to rounding),
so R and its derivatives are smooth through omega = 0.
"""

from __future__ import annotations

import torch

__all__ = ["rotation_matrix", "rotation_derivatives", "transform_points"]

_SMALL = 1e-4


def _coefficients(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    small = t < _SMALL
    ts = torch.where(small, torch.ones_like(t), t)  # double-where: no NaN derivatives on the unused branch
    th = ts.sqrt()
    a_big = torch.sin(th) / th
    b_big = (1.0 - torch.cos(th)) / ts
    a_small = 1.0 - t / 6.0 + t * t / 120.0 - t**3 / 5040.0 + t**4 / 362880.0
    b_small = 0.5 - t / 24.0 + t * t / 720.0 - t**3 / 40320.0 + t**4 / 3628800.0
    return torch.where(small, a_small, a_big), torch.where(small, b_small, b_big)


def _hat(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    x, y, zz = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack(
        [torch.stack([z, -zz, y], -1), torch.stack([zz, z, -x], -1), torch.stack([-y, x, z], -1)], -2
    )


def rotation_matrix(omega: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices of rotation vectors ``omega`` (..., 3); differentiable to any order."""
    K = _hat(omega)
    a, b = _coefficients((omega * omega).sum(-1))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _single(w: torch.Tensor) -> torch.Tensor:
    return rotation_matrix(w)


def rotation_derivatives(omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """R (N, 3, 3), dR (N, 3, 3, 3) with dR[..., i] = dR/d omega_i, d2R (N, 3, 3, 3, 3) = d2R/d omega_i d omega_j.

    Args:
        omega: (N, 3) rotation vectors.
    """
    R = rotation_matrix(omega)
    jac = torch.func.jacfwd(_single)
    dR = torch.func.vmap(jac)(omega)
    d2R = torch.func.vmap(torch.func.jacfwd(jac))(omega)
    return R, dR, d2R


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """World coordinates ``R(omega) X + t`` of body-frame points.

    Args:
        pose: (..., 6) translation then rotation vector.
        points: (..., P, 3) body-frame points (broadcast with the pose's leading dims).
    """
    R = rotation_matrix(pose[..., 3:])
    return points @ R.transpose(-1, -2) + pose[..., None, :3]
