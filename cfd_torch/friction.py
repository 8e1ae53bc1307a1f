"""Lagged, IPC-style smoothed Coulomb friction on the near leaf pairs of the contact hierarchy (SPEC section 5).

Lagged data, from the start-of-step configuration q_t, for every exact leaf pair c (triangles ta of body a and tb of
body b, inherited blend weight w_c = product of the ancestors' (1 - phi)):

    f_k      = |dP/dx_k|  for the six vertices (the pair potential's vertex forces, all along the plane normal)
    lambda_c = w_c sum_{k in ta} f_k            normal force magnitude [N] (equal on both sides at the optimum)
    n_c      = unit normal of the force on ta;  T_c = I - n_c n_c^T  (projector onto the contact plane)
    X_a      = sum_{k in ta} (f_k / sum f) X_k  body-frame force centre on ta (same on tb): one material point per
                                                side, so the contact point moves rigidly with its body.

Dissipative potential of the step (u_c = tangential relative displacement of the two contact points)::

    D(q) = sum_c mu_f lambda_c f0(|u_c|),  u_c = T_c [(x_a(q) - x_a(q_t)) - (x_b(q) - x_b(q_t))],
    f0(y) = -y^3 / (3 e^2) + y^2 / e + e / 3   (y < e),   y  (y >= e),     e = eps_v dt,
    f1 = f0' = -y^2 / e^2 + 2 y / e  (y < e),   1  (y >= e)

so the friction force is -mu_f lambda f1(|u|) u / |u|: Coulomb's bound mu_f lambda beyond a slip of eps_v, and a
stiff smooth (C1) static regime below. f0(|u|) is convex in u, its u-Hessian

    H_u = mu_f lambda [ (f1 / y) T + (f1' - f1 / y) u u^T / y^2 ]

is positive semi-definite. The lagged data are differentiable functions of q_t (through the pair potential's
second-order autograd, the blend weights through their closed-form gradient), so the step's adjoint sees how
friction depends on the previous state; only the discrete leaf set is fixed.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .contact._traverse import point_jacobian, rot_second, traverse
from .contact.pair import pair_potential, pair_potential_derivatives
from .rotation import rotation_derivatives, rotation_matrix

__all__ = ["LaggedFriction", "lagged_friction", "friction_terms"]


class LaggedFriction(NamedTuple):
    """Per-contact data of the lagged friction (C leaf pairs).

    Attributes:
        body: (C, 2) body indices (a, b).
        X: (C, 2, 3) body-frame contact points on a and b.
        x_t: (C, 2, 3) their world positions at q_t.
        tangent: (C, 3, 3) projector onto the contact plane.
        normal_force: (C,) lambda_c [N].
    """

    body: torch.Tensor
    X: torch.Tensor
    x_t: torch.Tensor
    tangent: torch.Tensor
    normal_force: torch.Tensor


def lagged_friction(
    forest,
    pairs: torch.Tensor,
    pair_root: torch.Tensor,
    q_t: torch.Tensor,
    *,
    mu: float,
    margin: float,
    eps: float,
    split: str,
    tol: float,
    max_iter: int,
    active: float = 0.0,
    create_graph: bool = False,
) -> LaggedFriction:
    """Lagged friction data at the poses ``q_t`` (N, 6) float64.

    Args:
        forest, pairs, pair_root: the scene's concatenated hierarchies and interacting body pairs.
        active: keep the leaf pairs whose normal force is at least this fraction of the largest in their body pair
            (0 keeps all). The selection is made on the closed-form forces, so the forward pass and the adjoint's
            differentiable re-computation select the same contacts.
        create_graph: keep the data differentiable with respect to ``q_t`` (for the step's adjoint): the plane
            solves by their implicit second-order autograd, the blend weights to first order.
    """
    with torch.no_grad():
        LI, LJ, lp, lw, dlw = traverse(
            forest, pairs, pair_root, q_t.detach(), mu=mu, margin=margin, eps=eps, split=split,
            order=1 if create_graph else 0, tol=tol, max_iter=max_iter, leaves_only=True,
        )  # fmt: skip
        ba, bb = pairs[lp, 0], pairs[lp, 1]
        Xa, Xb = forest.tris[forest.tri[LI]], forest.tris[forest.tri[LJ]]  # (C, 3, 3) body frame

        def world(q):  # the contacts' triangles at poses q, and the rotations
            R = rotation_matrix(q[:, 3:])
            return (
                Xa @ R[ba].transpose(1, 2) + q[ba, None, :3],
                Xb @ R[bb].transpose(1, 2) + q[bb, None, :3],
                R,
            )

        wa, wb, R = world(q_t.detach())
        # vertex forces in closed form (envelope theorem; no autograd)
        g = pair_potential_derivatives(
            wa, wb, mu=mu, margin=margin, hessian=False, tol=tol, max_iter=max_iter
        ).grad.reshape(-1, 2, 3, 3)  # fmt: skip
        ga, gb = g[:, 0], g[:, 1]
        if active > 0 and lp.numel():
            lam = lw * torch.linalg.vector_norm(ga, dim=-1).sum(1)
            top = torch.zeros(pairs.shape[0], dtype=lam.dtype, device=lam.device)
            top = top.scatter_reduce(0, lp, lam, "amax")
            keep = lam >= active * top[lp]
            LI, LJ, lp, lw, ba, bb, Xa, Xb, ga, gb = (
                x[keep] for x in (LI, LJ, lp, lw, ba, bb, Xa, Xb, ga, gb)
            )
            dlw = dlw[keep] if dlw is not None else None
    if create_graph:
        # the same data as differentiable functions of q_t: blend weights to first order (exact gradient, as the
        # adjoint needs), vertex forces by the pair potential's implicit second-order autograd
        dq = torch.cat([q_t[ba], q_t[bb]], 1)
        lw = lw + ((dq - dq.detach()) * dlw).sum(1)
        with torch.enable_grad():
            wa, wb, R = world(q_t)
            P = pair_potential(wa, wb, mu=mu, margin=margin, tol=tol, max_iter=max_iter)
            ga, gb = torch.autograd.grad(P.sum(), (wa, wb), create_graph=True)
    fa = torch.linalg.vector_norm(ga, dim=-1)  # (C, 3)
    fb = torch.linalg.vector_norm(gb, dim=-1)
    sa, sb = fa.sum(1), fb.sum(1)
    lam = lw * sa
    pa = ((fa / sa[:, None])[:, :, None] * Xa).sum(1)
    pb = ((fb / sb[:, None])[:, :, None] * Xb).sum(1)
    n = -ga.sum(1)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    T = torch.eye(3, dtype=n.dtype, device=n.device) - n[:, :, None] * n[:, None, :]
    t = q_t[:, :3] if create_graph else q_t[:, :3].detach()
    xa = torch.einsum("cij,cj->ci", R[ba], pa) + t[ba]
    xb = torch.einsum("cij,cj->ci", R[bb], pb) + t[bb]
    data = LaggedFriction(
        torch.stack([ba, bb], 1), torch.stack([pa, pb], 1), torch.stack([xa, xb], 1), T, lam
    )
    return data


def friction_terms(
    data: LaggedFriction,
    poses: torch.Tensor,
    mu_f: torch.Tensor,
    e: float,
    order: int,
    reduce: bool = True,
    majorizer_gap: bool = False,
):
    """Value, gradient and Hessian of the lagged friction potential D at ``poses``.

    Args:
        data: lagged contacts (C of them).
        poses: (N, 6) end-of-step poses of all bodies.
        mu_f: () friction coefficient.
        e: slip threshold eps_v dt [m].
        order: 0, 1 or 2.
        reduce: return the total value (); else the per-contact values (C,).
        majorizer_gap: at order 2, also return the positive semi-definite (C, 12, 12) difference between the Hessian
            of the quadratic majorizer of f0 at |u| (curvature f1 / y in every direction of the plane) and the exact
            one (which has curvature f1' <= f1 / y along u: none at all when slipping). Newton directions from the
            majorizer do not step across the tip of the friction cone u = 0 (iteratively reweighted least squares).

    Returns:
        value, per-contact gradient (C, 12) over [q_a, q_b] and Hessian (C, 12, 12) (None below the order), and
        with ``majorizer_gap`` the gap (C, 12, 12).
    """
    ba, bb = data.body[:, 0], data.body[:, 1]
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
    value = (w * f0).sum() if reduce else w * f0
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
