"""Lagged, IPC-style smoothed Coulomb friction over a contact model's lagged contacts (SPEC section 5).

Dissipative potential of the step (u_c = tangential relative displacement of the two contact points)::

    D(q) = sum_c mu_f lambda_c f0(|u_c|),  u_c = T_c [(x_a(q) - x_a(q_t)) - (x_b(q) - x_b(q_t))],
    f0(y) = -y^3 / (3 e^2) + y^2 / e + e / 3   (y < e),   y  (y >= e),     e = eps_v dt,
    f1 = f0' = -y^2 / e^2 + 2 y / e  (y < e),   1  (y >= e)

so the friction force is -mu_f lambda f1(|u|) u / |u|: Coulomb's bound mu_f lambda beyond a slip of eps_v, and a
stiff smooth (C1) static regime below. f0(|u|) is convex in u, its u-Hessian

    H_u = mu_f lambda [ (f1 / y) T + (f1' - f1 / y) u u^T / y^2 ]

is positive semi-definite.
"""

from __future__ import annotations

import torch

from ..contact.model import LaggedContacts
from ..rotation import point_jacobian, rot_second, rotation_derivatives

__all__ = ["friction_terms"]


def friction_terms(
    data: LaggedContacts,
    poses: torch.Tensor,
    rows: torch.Tensor,
    mu_f: torch.Tensor,
    e: float,
    order: int,
    majorizer_gap: bool = False,
):
    """Value, gradient and Hessian of the lagged friction potential D at ``poses``.

    Args:
        data: lagged contacts (C of them).
        poses: (M, 6) end-of-step poses of all bodies (a table of the batch's scenes).
        rows: (C, 2) rows of ``poses`` of each contact's bodies a and b.
        mu_f: () or (C,) friction coefficient.
        e: slip threshold eps_v dt [m].
        order: 0, 1 or 2.
        majorizer_gap: at order 2, also return the positive semi-definite (C, 12, 12) difference between the Hessian
            of the quadratic majorizer of f0 at |u| (curvature f1 / y in every direction of the plane) and the exact
            one (which has curvature f1' <= f1 / y along u: none at all when slipping). Newton directions from the
            majorizer do not step across the tip of the friction cone u = 0 (iteratively reweighted least squares).

    Returns:
        per-contact value (C,), gradient (C, 12) over [q_a, q_b] and Hessian (C, 12, 12) (None below the order), and
        with ``majorizer_gap`` the gap (C, 12, 12).
    """
    ba, bb = rows[:, 0], rows[:, 1]
    R, dR, d2R = rotation_derivatives(poses[:, 3:], order)
    t = poses[:, :3]
    Xa, Xb = data.X[:, 0], data.X[:, 1]
    xa = torch.einsum("cij,cj->ci", R[ba], Xa) + t[ba]
    xb = torch.einsum("cij,cj->ci", R[bb], Xb) + t[bb]
    u = torch.einsum("cij,cj->ci", data.tangent, (xa - data.x_t[:, 0]) - (xb - data.x_t[:, 1]))  # (C, 3)
    y = torch.linalg.vector_norm(u, dim=-1)
    slip = y >= e
    ys = torch.where(slip, y, torch.full_like(y, e))  # safe in the unused branch
    f0 = torch.where(slip, y, -(y**3) / (3 * e * e) + y * y / e + e / 3)
    w = mu_f * data.normal_force
    value = w * f0
    if order == 0:
        return value, None, None
    f1_y = torch.where(slip, 1.0 / ys, -y / (e * e) + 2.0 / e)  # f1(y) / y, finite at y = 0
    gu = (w * f1_y)[:, None] * u  # (C, 3) dD/du = dD/d(relative displacement) (u lies in the plane)
    C = u.shape[0]
    eye = torch.eye(3, dtype=u.dtype, device=u.device).expand(C, 3, 3)
    Ja = torch.cat([eye, point_jacobian(dR[ba], Xa)], -1)  # (C, 3, 6)
    Jb = torch.cat([eye, point_jacobian(dR[bb], Xb)], -1)
    Jc = torch.cat([Ja, -Jb], -1)  # (C, 3, 12)
    grad = torch.einsum("ci,cik->ck", gu, Jc)
    if order == 1:
        return value, grad, None
    # (f1' - f1/y) / y^2: -1 / (e^2 y) below e, -1 / y^3 above; times u u^T it vanishes like y at y = 0
    yq = torch.where(y > 0, y, torch.ones_like(y))
    c2 = torch.where(slip, -1.0 / ys**3, -1.0 / (e * e * yq))
    Hu = (w * f1_y)[:, None, None] * data.tangent + (w * c2)[:, None, None] * u[:, :, None] * u[:, None, :]
    hess = torch.einsum("cik,cij,cjl->ckl", Jc, Hu, Jc)
    hess[:, 3:6, 3:6] += rot_second(d2R[ba], Xa, gu)
    hess[:, 9:12, 9:12] -= rot_second(d2R[bb], Xb, gu)
    if majorizer_gap:
        v = torch.einsum("ci,cik->ck", u, Jc)  # (C, 12) J^T u
        return value, grad, hess, (-w * c2)[:, None, None] * v[:, :, None] * v[:, None, :]
    return value, grad, hess
