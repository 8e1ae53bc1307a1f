"""CPU kernel of the lagged friction potential, summed per body pair (the closed form of
:func:`cfd_torch.sim.friction.friction_terms`, whose docstring defines every quantity).

One loop over the contacts; each contact's value, gradient and Hessian over [q_a, q_b] is added to its body pair's
slot, so the (C, 12, 12) per-contact Hessians are never stored (on a foot resting on a floor C is a few thousand
and the body pairs a handful).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .._rotation_numba import add_rotation_terms


@numba.njit(cache=True, error_model="numpy")
def friction_by_pair(slot, F, R, dR, d2R, t, rows, X, x_t, T, lam, mu, e, order, want_gap):
    """Per body pair f < F: the sums over its contacts c (``slot[c] == f``) of the friction potential's value (F,),
    gradient (F, 12) and Hessian (F, 12, 12) over [q_a, q_b], and with ``want_gap`` the majorizer gap (F, 12, 12).

    R (M, 3, 3), dR (M, 3, 3, 3), d2R (M, 3, 3, 3, 3): rotations of the pose rows and their derivatives, [i, m, k(, l)]
    = d(R_im) / d omega_k (d omega_l); t (M, 3) translations; rows (C, 2) each contact's pose rows; X, x_t (C, 2, 3)
    body-frame points and their start-of-step world positions; T (C, 3, 3) tangent projectors; lam, mu (C,) normal
    forces and friction coefficients; e the slip threshold eps_v dt; order 0, 1 or 2.
    """
    C = slot.shape[0]
    value = np.zeros(F)
    grad = np.zeros((F if order >= 1 else 0, 12))
    hess = np.zeros((F if order >= 2 else 0, 12, 12))
    gap = np.zeros((F if order >= 2 and want_gap else 0, 12, 12))
    J = np.zeros((2, 3, 3))  # d x_s / d omega_s of each side's point
    Jc = np.zeros((3, 12))  # d rel / d [q_a, q_b] = [I, J_a, -I, -J_b]
    M = np.zeros((3, 12))  # Hu Jc
    Hu = np.zeros((3, 3))
    g = np.zeros(3)
    rel = np.zeros(3)
    u = np.zeros(3)
    v = np.zeros(12)
    G2 = np.zeros((F if order >= 2 else 0, 2, 3, 3))  # per pair and side: sum of +-g X^T
    Gc = np.zeros((3, 3))  # one contact's +-g X^T
    first = np.full(F, -1)  # a contact of each pair (its pose rows are the pair's)
    for i in range(3):
        Jc[i, i] = 1.0
        Jc[i, 6 + i] = -1.0
    for c in range(C):
        f = slot[c]
        if first[f] < 0:
            first[f] = c
        for i in range(3):
            rel[i] = 0.0
        for s in range(2):
            r = rows[c, s]
            sign = 1.0 if s == 0 else -1.0
            for i in range(3):
                x = R[r, i, 0] * X[c, s, 0] + R[r, i, 1] * X[c, s, 1] + R[r, i, 2] * X[c, s, 2] + t[r, i]
                rel[i] += sign * (x - x_t[c, s, i])
        for i in range(3):
            u[i] = T[c, i, 0] * rel[0] + T[c, i, 1] * rel[1] + T[c, i, 2] * rel[2]
        y = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
        slip = y >= e
        w = mu[c] * lam[c]
        if slip:
            value[f] += w * y
        else:
            value[f] += w * (-(y * y * y) / (3.0 * e * e) + y * y / e + e / 3.0)
        if order < 1:
            continue
        f1_y = 1.0 / y if slip else -y / (e * e) + 2.0 / e
        for i in range(3):
            g[i] = w * f1_y * u[i]  # dD / d rel
        for s in range(2):
            r = rows[c, s]
            for i in range(3):
                for k in range(3):
                    J[s, i, k] = (
                        dR[r, i, 0, k] * X[c, s, 0]
                        + dR[r, i, 1, k] * X[c, s, 1]
                        + dR[r, i, 2, k] * X[c, s, 2]
                    )
        for k in range(3):
            grad[f, k] += g[k]
            grad[f, 6 + k] -= g[k]
            grad[f, 3 + k] += J[0, 0, k] * g[0] + J[0, 1, k] * g[1] + J[0, 2, k] * g[2]
            grad[f, 9 + k] -= J[1, 0, k] * g[0] + J[1, 1, k] * g[1] + J[1, 2, k] * g[2]
        if order < 2:
            continue
        for i in range(3):
            for k in range(3):
                Jc[i, 3 + k] = J[0, i, k]
                Jc[i, 9 + k] = -J[1, i, k]
        yq = y if y > 0.0 else 1.0
        c2 = -1.0 / (y * y * y) if slip else -1.0 / (e * e * yq)
        a = w * f1_y
        b = w * c2
        # Hu = a T + b u u^T (3 x 3, symmetric); hess += Jc^T Hu Jc with Jc = [I, J_a, -I, -J_b]: the rows of
        # M = Hu Jc are [Hu, Hu J_a, -Hu, -Hu J_b], those of Jc^T M are [M, J_a^T M, -M, -J_b^T M]
        for i in range(3):
            for j in range(3):
                Hu[i, j] = a * T[c, i, j] + b * u[i] * u[j]
        for i in range(3):
            for k in range(3):
                M[i, k] = Hu[i, k]
                M[i, 6 + k] = -Hu[i, k]
                M[i, 3 + k] = Hu[i, 0] * J[0, 0, k] + Hu[i, 1] * J[0, 1, k] + Hu[i, 2] * J[0, 2, k]
                M[i, 9 + k] = -(Hu[i, 0] * J[1, 0, k] + Hu[i, 1] * J[1, 1, k] + Hu[i, 2] * J[1, 2, k])
        # (the upper triangles, mirrored at the end)
        for q in range(12):
            for i in range(3):
                if q >= i:
                    hess[f, i, q] += M[i, q]
                if q >= 6 + i:
                    hess[f, 6 + i, q] -= M[i, q]
                if q >= 3 + i:
                    hess[f, 3 + i, q] += J[0, 0, i] * M[0, q] + J[0, 1, i] * M[1, q] + J[0, 2, i] * M[2, q]
                if q >= 9 + i:
                    hess[f, 9 + i, q] -= J[1, 0, i] * M[0, q] + J[1, 1, i] * M[1, q] + J[1, 2, i] * M[2, q]
        # second-order rotation terms sum_m X_m sum_i g_i d2R[i, m, k, l] (g at a's point, -g at b's): where the
        # contact's pose rows are its pair's first contact's (always, for body pairs), only G_s = sum_c (+-g) X^T
        # (3 x 3) is summed per contact and contracted with d2R once per pair
        shared = rows[c, 0] == rows[first[f], 0] and rows[c, 1] == rows[first[f], 1]
        for s in range(2):
            sign = 1.0 if s == 0 else -1.0
            for i in range(3):
                for m in range(3):
                    Gc[i, m] = sign * g[i] * X[c, s, m]
            if shared:
                for i in range(3):
                    for m in range(3):
                        G2[f, s, i, m] += Gc[i, m]
            else:
                add_rotation_terms(hess, f, 3 if s == 0 else 9, Gc, d2R, rows[c, s], 1.0)
        if want_gap:  # (-w c2) v v^T, v = Jc^T u
            for p in range(12):
                v[p] = Jc[0, p] * u[0] + Jc[1, p] * u[1] + Jc[2, p] * u[2]
            for p in range(12):
                bp = b * v[p]
                for q in range(p, 12):
                    gap[f, p, q] -= bp * v[q]
    if order >= 2:
        for f in range(F):  # each pair's rotation terms, then the lower triangles
            for s in range(2):
                add_rotation_terms(hess, f, 3 if s == 0 else 9, G2[f, s], d2R, rows[first[f], s], 1.0)
            for p in range(12):
                for q in range(p + 1, 12):
                    hess[f, q, p] = hess[f, p, q]
                    if want_gap:
                        gap[f, q, p] = gap[f, p, q]
    return value, grad, hess, gap
