"""CPU kernel of :func:`cfd_torch.sim.energy.body_terms` (inertia, gravity and actuation of the moving bodies).

The tensor form is about 40 small tensor operations per call (0.2-0.4 ms for a handful of bodies, called at every
energy evaluation); this is one loop over the bodies. Same formulas, summed in the same order where it matters
(each product of 3 x 3 matrices entry by entry); the tests check the two agree to rounding.
"""

from __future__ import annotations

import numba
import numpy as np

from .._rotation_numba import _CA, _CB, angle_factors_kernel, rotation_derivatives_kernel


@numba.njit(cache=True)
def _axial_of_product(M, Rt, tau):
    """tau . axial(M Rt^T) for 3 x 3 M and Rt: axial(X) = (X21 - X12, X02 - X20, X10 - X01) / 2."""
    x21 = x12 = x02 = x20 = x10 = x01 = 0.0
    for m in range(3):
        x21 += M[2, m] * Rt[1, m]
        x12 += M[1, m] * Rt[2, m]
        x02 += M[0, m] * Rt[2, m]
        x20 += M[2, m] * Rt[0, m]
        x10 += M[1, m] * Rt[0, m]
        x01 += M[0, m] * Rt[1, m]
    return 0.5 * (tau[0] * (x21 - x12) + tau[1] * (x02 - x20) + tau[2] * (x10 - x01))


@numba.njit(cache=True)
def _half_trace_of_product(M, Rt):
    """tr(M Rt^T) / 2 for 3 x 3 M and Rt."""
    acc = 0.0
    for i in range(3):
        for m in range(3):
            acc += M[i, m] * Rt[i, m]
    return 0.5 * acc


@numba.njit(cache=True)
def body_terms_kernel(
    q, q_t, q_p, r_pred, t_shift, force, torque, mass, S, gravity, dt, order, value, grad, hess
):
    """Fill value (E,), grad (E, 6) (order >= 1) and hess (E, 6, 6) (order >= 2) of E bodies (pose rows (E, 6);
    predicted rotations r_pred (E, 3, 3), centres of mass 2 q_t - q_p + t_shift (E, 3))."""
    E = q.shape[0]
    R = np.empty((E, 3, 3))
    dR = np.empty((E if order >= 1 else 0, 3, 3, 3))
    d2R = np.empty((E if order >= 2 else 0, 3, 3, 3, 3))
    rotation_derivatives_kernel(q[:, 3:].copy(), _CA, _CB, R, dR, d2R, order)
    Rt = np.empty((E, 3, 3))
    none1 = np.empty((0, 3, 3, 3))
    none2 = np.empty((0, 3, 3, 3, 3))
    rotation_derivatives_kernel(q_t[:, 3:].copy(), _CA, _CB, Rt, none1, none2, 0)
    inv = 1.0 / (dt * dt)
    A = np.empty((3, 3))
    AS = np.empty((3, 3))
    Mk = np.empty((3, 3))
    b = np.empty(3)
    pull = np.empty(3)
    ak = np.empty(3)
    ck = np.empty(3)
    for e in range(E):
        # A = R - R_pred, AS = A S
        for i in range(3):
            for j in range(3):
                A[i, j] = R[e, i, j] - r_pred[e, i, j]
        for i in range(3):
            for j in range(3):
                AS[i, j] = A[i, 0] * S[e, 0, j] + A[i, 1] * S[e, 1, j] + A[i, 2] * S[e, 2, j]
        m = mass[e]
        bb = 0.0
        lin = 0.0
        for i in range(3):
            b[i] = q[e, i] - 2.0 * q_t[e, i] + q_p[e, i] - t_shift[e, i]
            bb += b[i] * b[i]
            pull[i] = m * gravity[i] + force[e, i]
            lin += pull[i] * (q[e, i] - q_t[e, i])
        asa = 0.0
        for i in range(3):
            for j in range(3):
                asa += AS[i, j] * A[i, j]
        # the torque's work tau . log(R R_t^T) = f(c) a (energy.body_terms): a, c of R, then of dR_k
        tau = torque[e]
        a0 = _axial_of_product(R[e], Rt[e], tau)
        f0, f1, f2 = angle_factors_kernel(_half_trace_of_product(R[e], Rt[e]) - 0.5)
        value[e] = 0.5 * inv * (m * bb + asa) - lin - f0 * a0
        if order == 0:
            continue
        for i in range(3):
            grad[e, i] = inv * m * b[i] - pull[i]
        for k in range(3):
            acc = 0.0
            for i in range(3):
                for j in range(3):
                    Mk[i, j] = dR[e, i, j, k]
                    acc += AS[i, j] * dR[e, i, j, k]
            ak[k] = _axial_of_product(Mk, Rt[e], tau)
            ck[k] = _half_trace_of_product(Mk, Rt[e])
            grad[e, 3 + k] = inv * acc - (f1 * ck[k] * a0 + f0 * ak[k])
        if order == 1:
            continue
        for i in range(6):
            for j in range(6):
                hess[e, i, j] = 0.0
        for i in range(3):
            hess[e, i, i] = inv * m
        for k in range(3):
            for l in range(3):
                acc = 0.0  # sum_ij (A S)_ij d2R_kl,ij
                for i in range(3):
                    for j in range(3):
                        Mk[i, j] = d2R[e, i, j, k, l]
                        acc += AS[i, j] * d2R[e, i, j, k, l]
                quad = 0.0  # sum_ijm dR_k,ij S_jm dR_l,im
                for i in range(3):
                    for j in range(3):
                        for mm in range(3):
                            quad += dR[e, i, j, k] * S[e, j, mm] * dR[e, i, mm, l]
                w = f2 * ck[k] * ck[l] * a0 + f1 * (
                    _half_trace_of_product(Mk, Rt[e]) * a0 + ck[k] * ak[l] + ck[l] * ak[k]
                )
                hess[e, 3 + k, 3 + l] = inv * (acc + quad) - (w + f0 * _axial_of_product(Mk, Rt[e], tau))
