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
from ..rotation import rotation_derivatives

__all__ = ["friction_terms", "friction_by_pair"]

# positions in a flattened 12 x 12 Hessian over [q_a, q_b] of entry (k, l) of its rotation-rotation block of body a,
# then b, for each (k, l) in turn
_ROT_BLOCKS = torch.tensor([12 * (o + k) + o + l for k in range(3) for l in range(3) for o in (3, 9)])


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

    The tensors are small (C of a few hundred to thousands, float64) and most of the algebra is on 3-vectors and
    3 x 3 matrices, for which torch's CPU kernels (bmm, einsum, broadcasting along a dimension of size 3) cost far
    more per element than on long rows. So the per-contact quantities are kept component-major and contiguous
    ((3, C), (3, 3, C), ...: every op runs along the contacts), and only the (C, 12, 12) Hessians are formed
    contact-major, by one batched matmul. Large temporaries are few (sums accumulate in place, d2R is gathered a
    (9, 2C) slice at a time): within a step, the page faults of fresh buffers cost as much as the arithmetic.
    Every sum runs in the order of the plain per-contact matrix products (``R @ X``, ``J_c^T @ gu``,
    ``(J_c^T @ Hu) @ J_c``, ...), so the results are theirs, bit for bit.
    """
    C, M = rows.shape[0], poses.shape[0]
    R, dR, d2R = rotation_derivatives(poses[:, 3:], order)
    # Per-pose rows gathered for both points of every contact (point s C + c: contact c's point on the body of
    # pose row rows[c, s]): for each m, the coefficients of X_m in the world position x = R X + t of a body-frame
    # point, R[i, m] (3, by i), and at order >= 1 in its rotation Jacobian, dR[i, m, k] = d x_i / d omega_k (9, by
    # (i, k)); then t (3).
    per_m = torch.cat([R.transpose(1, 2)] + ([dR.transpose(1, 2).reshape(M, 3, 9)] if order >= 1 else []), -1)
    W = per_m.shape[-1]  # 3 or 12 per m
    point = rows.T.reshape(1, 2 * C)

    def gather(table: torch.Tensor) -> torch.Tensor:  # (n, M) per-pose rows -> (n, 2C) per contact point
        return torch.gather(table, 1, point.expand(table.shape[0], 2 * C))

    at = gather(torch.cat([per_m.reshape(M, 3 * W), poses[:, :3]], 1).T.contiguous())  # (3 W + 3, 2C)
    X = data.X.permute(2, 1, 0).reshape(3, 2 * C)
    per_m = at[: 3 * W].view(3, W, 2 * C)
    TX = per_m[0] * X[0]
    TX += per_m[1] * X[1]
    TX += per_m[2] * X[2]  # (W, 2C): R X, then d(R X) / d omega
    x = (TX[:3] + at[3 * W :]).view(3, 2, C)  # x[i, s, c]
    d = x - data.x_t.permute(2, 1, 0)  # (3, 2, C) each point's displacement over the step
    rel = d[:, 0] - d[:, 1]  # (3, C)
    tangent = data.tangent.permute(1, 2, 0).contiguous()  # (3, 3, C)
    u = tangent[:, 0] * rel[0] + tangent[:, 1] * rel[1] + tangent[:, 2] * rel[2]  # (3, C)
    y = torch.linalg.vector_norm(u.T.contiguous(), dim=-1)  # along rows of 3: rounded as in the (C, 3) form
    slip = y >= e
    ys = torch.where(slip, y, torch.full_like(y, e))  # safe in the unused branch
    f0 = torch.where(slip, y, -(y**3) / (3 * e * e) + y * y / e + e / 3)
    w = mu_f * data.normal_force
    value = w * f0
    if order == 0:
        return value, None, None
    f1_y = torch.where(slip, 1.0 / ys, -y / (e * e) + 2.0 / e)  # f1(y) / y, finite at y = 0
    gu = (w * f1_y) * u  # (3, C) dD/du = dD/d(relative displacement) (u lies in the plane)
    J = TX[3:].view(3, 3, 2, C)  # J[i, k, s, c] = d x_i / d omega_k of each point

    def pullback(v: torch.Tensor) -> torch.Tensor:
        """(3, C) -> (C, 12): J_c^T v with J_c = [I, J_a, -I, -J_b] (3, 12) = d u / d [q_a, q_b]."""
        vJ = v[0] * J[0] + v[1] * J[1] + v[2] * J[2]  # (3, 2, C)
        return torch.cat([v.T, vJ[:, 0].T, -v.T, -vJ[:, 1].T], 1)

    grad = pullback(gu)
    if order == 1:
        return value, grad, None
    # second-order rotation terms sum_i g_i d2(R X)_i / d omega d omega of each point (g = gu at a, -gu at b), for
    # the two rotation blocks: sum_m X_m sum_i g_i d2R[i, m, k, l], gathering a (9, 2C) slice of d2R at a time
    g = torch.cat([gu, -gu], 1)  # (3, 2C)
    d2R = d2R.reshape(M, 81).T.contiguous()  # (81, M): d2R[i, m, (k, l)]

    def gd2(m: int) -> torch.Tensor:  # (9, 2C): sum_i g_i d2R[i, m, (k, l)] of each point
        s = g[0] * gather(d2R[9 * m : 9 * m + 9])
        s += g[1] * gather(d2R[27 + 9 * m : 36 + 9 * m])
        s += g[2] * gather(d2R[54 + 9 * m : 63 + 9 * m])
        return s

    rot = X[0] * gd2(0)
    rot += X[1] * gd2(1)
    rot += X[2] * gd2(2)  # (9, 2C): by (k, l), then point
    # (f1' - f1/y) / y^2: -1 / (e^2 y) below e, -1 / y^3 above; times u u^T it vanishes like y at y = 0
    yq = torch.where(y > 0, y, torch.ones_like(y))
    c2 = torch.where(slip, -1.0 / ys**3, -1.0 / (e * e * yq))
    Hu = (w * f1_y) * tangent + ((w * c2) * u)[:, None] * u  # (3, 3, C)
    # J_c^T Hu J_c = (J_c^T Hu) J_c, J_c^T Hu = [Hu; J_a^T Hu; -Hu; -J_b^T Hu] (12, 3): one batched matmul
    JH = J[0, :, None] * Hu[0, None, :, None]
    JH += J[1, :, None] * Hu[1, None, :, None]
    JH += J[2, :, None] * Hu[2, None, :, None]  # (3, 3, 2, C): J_a^T Hu, J_b^T Hu
    Hu, Ja, Jb, JaH, JbH = (
        m.permute(2, 0, 1) for m in (Hu, J[:, :, 0], J[:, :, 1], JH[:, :, 0], JH[:, :, 1])
    )
    eye = torch.eye(3, dtype=u.dtype, device=u.device).expand(C, 3, 3)  # (C, 3, 3) views from here
    JcHu = torch.cat([Hu, JaH, -Hu, -JbH], 1)  # (C, 12, 3)
    Jc = torch.cat([eye, Ja, -eye, -Jb], 2)  # (C, 3, 12)
    hess = torch.bmm(JcHu, Jc)  # (C, 12, 12)
    hess.view(C, 144).index_add_(1, _ROT_BLOCKS.to(hess.device), rot.view(18, C).T)
    if majorizer_gap:
        v = pullback(u)  # (C, 12) J_c^T u
        return value, grad, hess, (-w * c2)[:, None, None] * v[:, :, None] * v[:, None, :]
    return value, grad, hess


def friction_by_pair(
    data: LaggedContacts,
    poses: torch.Tensor,
    rows: torch.Tensor,
    mu_f: torch.Tensor,
    e: float,
    order: int,
    majorizer_gap: bool = False,
):
    """:func:`friction_terms` summed over the contacts of each body pair.

    Returns:
        (F,) the body pairs with contacts (the distinct ``data.pair``, ascending), their values (F,), gradients
        (F, 12) and Hessians (F, 12, 12) (None below the order), and with ``majorizer_gap`` the gaps (F, 12, 12).

    On the CPU in float64 with no autograd wanted, one numba loop adds each contact to its pair (the per-contact
    Hessians are never formed); otherwise :func:`friction_terms`, then sums.
    """
    pair, slot = torch.unique(data.pair, return_inverse=True)
    F = pair.shape[0]
    mu = torch.as_tensor(mu_f, dtype=poses.dtype, device=poses.device).expand(data.pair.shape[0])
    inputs = (poses, mu, data.X, data.x_t, data.tangent, data.normal_force)
    graph = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
    if poses.device.type == "cpu" and poses.dtype == torch.float64 and not graph:
        from ._friction_numba import friction_by_pair as kernel

        R, dR, d2R = rotation_derivatives(poses[:, 3:], order)
        if dR is None:  # (typed placeholders: the kernel reads them only at the orders that need them)
            dR = poses.new_zeros(1, 3, 3, 3)
        if d2R is None:
            d2R = poses.new_zeros(1, 3, 3, 3, 3)
        np_ = lambda x: x.contiguous().numpy()  # noqa: E731
        value, grad, hess, gap = kernel(
            np_(slot), F, np_(R), np_(dR), np_(d2R),
            np_(poses[:, :3]), np_(rows), np_(data.X), np_(data.x_t), np_(data.tangent), np_(data.normal_force),
            np_(mu), float(e), int(order), bool(majorizer_gap and order >= 2),
        )  # fmt: skip
        out = [pair, torch.from_numpy(value)]
        out += [
            torch.from_numpy(grad) if order >= 1 else None,
            torch.from_numpy(hess) if order >= 2 else None,
        ]
        if majorizer_gap:
            out.append(torch.from_numpy(gap) if order >= 2 else None)
        return tuple(out)
    v, g, h, *gap = friction_terms(data, poses, rows, mu_f, e, order, majorizer_gap=majorizer_gap)

    def per_pair(x):
        return None if x is None else x.new_zeros(F, *x.shape[1:]).index_add_(0, slot, x)

    out = [pair, per_pair(v), per_pair(g), per_pair(h)]
    if majorizer_gap:
        out.append(per_pair(gap[0]) if gap else None)
    return tuple(out)
