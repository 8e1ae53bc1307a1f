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

import math

import torch

from ._autograd import tracked

__all__ = [
    "rotation_matrix",
    "rotation_derivatives",
    "transform_points",
    "point_jacobian",
    "rot_second",
    "angle_factors",
]

_SMALL = 1e-4

# theta / sin(theta) as a power series in x = 1 - cos(theta): sum_k 2^k (k!)^2 / (2k + 1)! x^k (radius 2, theta = pi)
ANGLE_SERIES_X = 0.1  # below it the series (20 terms: exact to rounding), above the closed forms
ANGLE_SERIES = [2.0**k * math.factorial(k) ** 2 / math.factorial(2 * k + 1) for k in range(20)]
# (n, 3) by powers of x: the coefficients of f, df/dx = sum (j + 1) a_(j+1) x^j and d2f/dx2
_ANGLE_TABLE = torch.tensor(
    [
        [a, (j + 1) * b, (j + 2) * (j + 1) * c]
        for j, (a, b, c) in enumerate(
            zip(ANGLE_SERIES, ANGLE_SERIES[1:] + [0.0], ANGLE_SERIES[2:] + [0.0, 0.0], strict=True)
        )
    ],
    dtype=torch.float64,
)


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
    if (
        omega.dim() == 2
        and omega.device.type == "cpu"
        and omega.dtype == torch.float64
        and not tracked(omega)
    ):
        return rotation_derivatives(omega, 0)[0]  # numba kernel (no autograd needed)
    K = _hat(omega)
    a, b = _coefficients((omega * omega).sum(-1))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


_SERIES_T = 0.25  # below theta^2 = 0.25 the coefficient functions use their Taylor series (16 terms)
_N_TERMS = 16


def _series(t: torch.Tensor, offset: int):
    """f, f', f'' of f(t) = sum_k (-1)^k t^k / (2k + offset)! (A: offset 1, B: offset 2), by Horner."""
    import math

    c = [(-1.0) ** k / math.factorial(2 * k + offset) for k in range(_N_TERMS)]
    f = torch.full_like(t, c[-1])
    for k in range(_N_TERMS - 2, -1, -1):
        f = f * t + c[k]
    c1 = [(k + 1) * c[k + 1] for k in range(_N_TERMS - 1)]
    f1 = torch.full_like(t, c1[-1])
    for k in range(_N_TERMS - 3, -1, -1):
        f1 = f1 * t + c1[k]
    c2 = [(k + 1) * c1[k + 1] for k in range(_N_TERMS - 2)]
    f2 = torch.full_like(t, c2[-1])
    for k in range(_N_TERMS - 4, -1, -1):
        f2 = f2 * t + c2[k]
    return f, f1, f2


def _coefficient_derivatives(t: torch.Tensor):
    """A, A', A'', B, B', B'' as functions of t = theta^2 (derivatives with respect to t)."""
    small = t < _SERIES_T
    ts = torch.where(small, torch.ones_like(t), t)
    th = ts.sqrt()
    s, c = torch.sin(th), torch.cos(th)
    a = s / th
    a1 = (th * c - s) / (2.0 * th**3)
    a2 = (3.0 * s - 3.0 * th * c - ts * s) / (4.0 * th**5)
    b = (1.0 - c) / ts
    b1 = (th * s - 2.0 + 2.0 * c) / (2.0 * ts * ts)
    b2 = (ts * c - 5.0 * th * s + 8.0 - 8.0 * c) / (4.0 * ts**3)
    sa, sa1, sa2 = _series(t, 1)
    sb, sb1, sb2 = _series(t, 2)
    pick = lambda x, y: torch.where(small, x, y)  # noqa: E731
    return pick(sa, a), pick(sa1, a1), pick(sa2, a2), pick(sb, b), pick(sb1, b1), pick(sb2, b2)


def rotation_derivatives(
    omega: torch.Tensor, order: int = 2
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """R (N, 3, 3), dR (N, 3, 3, 3) with dR[..., i] = dR/d omega_i, d2R (N, 3, 3, 3, 3) = d2R/d omega_i d omega_j.

    Closed form from R = I + A(t) K + B(t) K^2, t = |omega|^2, K = [omega]_x, dK/d omega_i = E_i = [e_i]_x::

        dR_i   = 2 w_i (A' K + B' K^2) + A E_i + B (E_i K + K E_i)
        d2R_ij = 4 w_i w_j (A'' K + B'' K^2) + 2 delta_ij (A' K + B' K^2)
                 + 2 w_i (A' E_j + B' (E_j K + K E_j)) + 2 w_j (A' E_i + B' (E_i K + K E_i))
                 + B (E_i E_j + E_j E_i)

    Args:
        omega: (N, 3) rotation vectors.
        order: 0 (R only), 1 (R, dR) or 2; derivatives above the order are None.

    On the CPU, for float64 inputs that no derivative flows through (no grad, torch.func transform or forward-mode
    tangent: ``_autograd.tracked``), a numba kernel computes the same formulas (a step
    calls this several times per Newton iteration for a handful of bodies: microseconds instead of a millisecond
    of small tensor ops); otherwise the tensor code below (any device, differentiable by autograd).
    """
    if omega.device.type == "cpu" and omega.dtype == torch.float64 and not tracked(omega):
        from ._rotation_numba import rotation_derivatives_cpu

        R, dR, d2R = rotation_derivatives_cpu(omega.detach().numpy(), order)
        return (
            torch.from_numpy(R),
            torch.from_numpy(dR) if dR is not None else None,
            torch.from_numpy(d2R) if d2R is not None else None,
        )
    return _rotation_derivatives_torch(omega, order)


def _rotation_derivatives_torch(omega: torch.Tensor, order: int = 2):
    """Tensor form of :func:`rotation_derivatives` (any device; differentiable)."""
    dt, dev = omega.dtype, omega.device
    K = _hat(omega)  # (N, 3, 3)
    K2 = K @ K
    t = (omega * omega).sum(-1)
    a, a1, a2, b, b1, b2 = (x[:, None, None] for x in _coefficient_derivatives(t))
    eye = torch.eye(3, dtype=dt, device=dev)
    R = eye + a * K + b * K2
    E = _hat(eye)  # (3, 3, 3): E[i] = [e_i]_x
    EK = E[None] @ K[:, None]  # (N, 3, 3, 3): E_i K
    KE = K[:, None] @ E[None]  # K E_i
    sym = EK + KE  # (N, i, 3, 3)
    w = omega
    lin = a1 * K + b1 * K2  # (N, 3, 3)
    dR = 2.0 * w[:, :, None, None] * lin[:, None] + a[:, None] * E[None] + b[:, None] * sym  # (N, i, 3, 3)
    EE = E[:, None] @ E[None, :]  # (i, j, 3, 3)
    quad = a2 * K + b2 * K2
    cross = a1[:, None] * E[None] + b1[:, None] * sym  # (N, i, 3, 3): A' E_i + B'(E_i K + K E_i)
    d2R = (
        4.0 * (w[:, :, None] * w[:, None, :])[..., None, None] * quad[:, None, None]
        + 2.0 * eye[None, :, :, None, None] * lin[:, None, None]
        + 2.0 * w[:, :, None, None, None] * cross[:, None, :]
        + 2.0 * w[:, None, :, None, None] * cross[:, :, None]
        + b[:, None, None] * (EE + EE.transpose(0, 1))[None]
    )  # (N, i, j, 3, 3)
    return (
        R,
        dR.permute(0, 2, 3, 1) if order >= 1 else None,
        d2R.permute(0, 3, 4, 1, 2) if order >= 2 else None,
    )


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """World coordinates ``R(omega) X + t`` of body-frame points.

    Args:
        pose: (..., 6) translation then rotation vector.
        points: (..., P, 3) body-frame points (broadcast with the pose's leading dims).
    """
    R = rotation_matrix(pose[..., 3:])
    return points @ R.transpose(-1, -2) + pose[..., None, :3]


def angle_factors(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """f(c) = theta / sin(theta) of c = cos(theta) in [-1, 1], and its first two derivatives in c.

    The rotation vector of a rotation matrix M (its log) is f(c) axial(M), c = (tr M - 1) / 2, axial(M) the axial
    vector of M's skew part (sin(theta) times the axis); for a linear function of M such as tau . log(M) the chain
    rule then needs only f, f' and f''. Closed forms, with s = sin(theta): f = theta / s, f' = (theta c - s) / s^3,
    f'' = (theta s^2 + 3 c (theta c - s)) / s^5; near c = 1 their power series in 1 - c (smooth through theta = 0).
    They grow without bound as theta -> pi, where the log map is singular (s is floored at 1e-8 there: finite)."""
    x = (1.0 - c).clamp(0.0, 2.0)
    small = x < ANGLE_SERIES_X
    # the series of f, df/dx and d2f/dx2 at once: powers x^0..x^(n-1) times their coefficients (d/dc = -d/dx)
    series = torch.linalg.vander(x, N=len(ANGLE_SERIES)) @ _ANGLE_TABLE.to(dtype=x.dtype, device=x.device)
    f0, f1, f2 = series[..., 0], -series[..., 1], series[..., 2]
    xs = torch.where(small, torch.ones_like(x), x)  # safe in the unused branch
    s2 = (xs * (2.0 - xs)).clamp_min(1e-16)
    sn = s2.sqrt()
    cs = 1.0 - xs
    th = torch.atan2(sn, cs)
    g0 = th / sn
    g1 = (th * cs - sn) / (s2 * sn)
    g2 = (th * s2 + 3.0 * cs * (th * cs - sn)) / (s2 * s2 * sn)
    return torch.where(small, f0, g0), torch.where(small, f1, g1), torch.where(small, f2, g2)


# ---------------------------------------------------------------------------------------------- quaternions
# (interpolating rotations in the simulator's path checks; not differentiated)
def quaternion(omega: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions [w, x, y, z] of rotation vectors (..., 3)."""
    t = torch.linalg.vector_norm(omega, dim=-1, keepdim=True)
    half = 0.5 * t
    # sin(t/2)/t, with its series near 0
    k = torch.where(
        t > 1e-8, torch.sin(half) / torch.where(t > 1e-8, t, torch.ones_like(t)), 0.5 - t * t / 48.0
    )
    return torch.cat([torch.cos(half), k * omega], -1)


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a b of (..., 4) quaternions (the rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def rotation_vector(quat: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors (norm <= pi) of (..., 4) unit quaternions."""
    q = torch.where(quat[..., :1] < 0, -quat, quat)  # the shorter of the two equal rotations
    v = q[..., 1:]
    s = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    k = torch.where(s > 1e-12, angle / torch.where(s > 1e-12, s, torch.ones_like(s)), 2.0 / q[..., :1])
    return k * v


def point_jacobian(dR: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """(E, 3, 3) d(R X)/d omega for per-element dR (E, 3, 3, 3) and body-frame points X (E, 3)."""
    return torch.einsum("eimk,em->eik", dR, X)


def rot_second(d2R: torch.Tensor, X: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(E, 3, 3) sum_i w_i d2(R X)_i / d omega d omega."""
    return torch.einsum("ei,eimkl,em->ekl", w, d2R, X)
