"""CPU kernel of an articulation's forward kinematics to its links' state rows (the value of
:func:`cfd_torch.sim.articulation._fk_rows`, without derivatives), for the many small evaluations a step makes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .._rotation_numba import rotation_derivatives_kernel


@numba.njit(cache=True, error_model="numpy")
def _joint_transform(f, t, Ro, po, K, K2, anchor, slide, Rj, Rl, pl):
    """Frame f's local transform at joint value t (already minus ref): Rj = I + sin t K + (1 - cos t) K2, Rl = Ro Rj,
    pl = po + Ro (anchor - Rj anchor + t slide), written into Rj, Rl (3, 3) and pl (3,)."""
    s, c = math.sin(t), math.cos(t)
    for i in range(3):
        for k in range(3):
            Rj[i, k] = (1.0 if i == k else 0.0) + s * K[f, i, k] + (1.0 - c) * K2[f, i, k]
    a0, a1, a2 = anchor[f, 0], anchor[f, 1], anchor[f, 2]
    x0 = a0 - (Rj[0, 0] * a0 + Rj[0, 1] * a1 + Rj[0, 2] * a2) + t * slide[f, 0]
    x1 = a1 - (Rj[1, 0] * a0 + Rj[1, 1] * a1 + Rj[1, 2] * a2) + t * slide[f, 1]
    x2 = a2 - (Rj[2, 0] * a0 + Rj[2, 1] * a1 + Rj[2, 2] * a2) + t * slide[f, 2]
    for i in range(3):
        pl[i] = po[f, i] + Ro[f, i, 0] * x0 + Ro[f, i, 1] * x1 + Ro[f, i, 2] * x2
        for k in range(3):
            Rl[i, k] = Ro[f, i, 0] * Rj[0, k] + Ro[f, i, 1] * Rj[1, k] + Ro[f, i, 2] * Rj[2, k]


@numba.njit(cache=True, error_model="numpy")
def _attach(R, p, b, f, Rl, pl):
    """Frame f from its parent b: R[f] = R[b] Rl, p[f] = p[b] + R[b] pl."""
    for i in range(3):
        p[f, i] = p[b, i] + R[b, i, 0] * pl[0] + R[b, i, 1] * pl[1] + R[b, i, 2] * pl[2]
        for k in range(3):
            R[f, i, k] = R[b, i, 0] * Rl[0, k] + R[b, i, 1] * Rl[1, k] + R[b, i, 2] * Rl[2, k]


@numba.njit(cache=True, error_model="numpy")
def _rotvec(M, w_out):
    """The rotation vector of the rotation M (3, 3) into w_out (3,): Shepperd's quaternion, then
    2 atan2(|v|, w) v / |v| (as :func:`cfd_torch.sim.articulation._quat_from_matrix` and
    :func:`cfd_torch.rotation.rotation_vector`)."""
    r00, r11, r22 = M[0, 0], M[1, 1], M[2, 2]
    tr = r00 + r11 + r22
    best, kk = tr, 0
    if r00 > best:
        best, kk = r00, 1
    if r11 > best:
        best, kk = r11, 2
    if r22 > best:
        kk = 3
    if kk == 0:
        s0 = math.sqrt(max(1.0 + tr, 1e-20)) * 2.0
        w, x, y, z = (
            0.25 * s0,
            (M[2, 1] - M[1, 2]) / s0,
            (M[0, 2] - M[2, 0]) / s0,
            (M[1, 0] - M[0, 1]) / s0,
        )
    elif kk == 1:
        s1 = math.sqrt(max(1.0 + r00 - r11 - r22, 1e-20)) * 2.0
        w, x, y, z = (
            (M[2, 1] - M[1, 2]) / s1,
            0.25 * s1,
            (M[0, 1] + M[1, 0]) / s1,
            (M[0, 2] + M[2, 0]) / s1,
        )
    elif kk == 2:
        s2 = math.sqrt(max(1.0 - r00 + r11 - r22, 1e-20)) * 2.0
        w, x, y, z = (
            (M[0, 2] - M[2, 0]) / s2,
            (M[0, 1] + M[1, 0]) / s2,
            0.25 * s2,
            (M[1, 2] + M[2, 1]) / s2,
        )
    else:
        s3 = math.sqrt(max(1.0 - r00 - r11 + r22, 1e-20)) * 2.0
        w, x, y, z = (
            (M[1, 0] - M[0, 1]) / s3,
            (M[0, 2] + M[2, 0]) / s3,
            (M[1, 2] + M[2, 1]) / s3,
            0.25 * s3,
        )
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    sv = math.sqrt(x * x + y * y + z * z)
    k = 2.0 * math.atan2(sv, w) / sv if sv > 1e-12 else 2.0 / w
    w_out[0] = k * x
    w_out[1] = k * y
    w_out[2] = k * z


@numba.njit(cache=True, error_model="numpy")
def fk_rows(R0, p0, th, parent, joint, Ro, po, K, K2, anchor, slide, ref, link, com):
    """(A, L, 6) link rows [centre of mass, rotation vector] of A configurations.

    Frames in level order (frame 0 the base at R0 (A, 3, 3), p0 (A, 3); frame f >= 1 hangs from frame parent[f] <
    f by its joint joint[f] with the local transform of :func:`_chain`: Ro Rj(t), po + Ro (anchor - Rj(t) anchor +
    t slide), t = th[joint] - ref, Rj = I + sin t K + (1 - cos t) K2); link (L,) each link's frame, com (L, 3) its
    centre of mass in that frame. Rotation vectors as in :func:`_quat_from_matrix` and
    :func:`cfd_torch.rotation.rotation_vector` (Shepperd's quaternion, then 2 atan2(|v|, w) v / |v|).
    """
    A = th.shape[0]
    F = parent.shape[0]
    L = link.shape[0]
    R = np.empty((F, 3, 3))
    p = np.empty((F, 3))
    Rl = np.empty((3, 3))
    Rj = np.empty((3, 3))
    pl = np.empty(3)
    out = np.empty((A, L, 6))
    for e in range(A):
        R[0] = R0[e]
        p[0] = p0[e]
        for f in range(1, F):
            _joint_transform(f, th[e, joint[f]] - ref[f], Ro, po, K, K2, anchor, slide, Rj, Rl, pl)
            _attach(R, p, parent[f], f, Rl, pl)
        for n in range(L):
            M = R[link[n]]
            for i in range(3):
                out[e, n, i] = p[link[n], i] + M[i, 0] * com[n, 0] + M[i, 1] * com[n, 1] + M[i, 2] * com[n, 2]
            _rotvec(M, out[e, n, 3:])
    return out


@numba.njit(cache=True, error_model="numpy")
def chain(R0, p0, dR0, d2R0, th, first, parent, joint, Ro, po, K, K2, anchor, slide, ref, link, order):
    """The link frames and their derivatives in the Q coordinates (the recursion of :func:`_chain`): R (A, L, 3, 3),
    p (A, L, 3), dR (A, L, Q, 3, 3), dp (A, L, Q, 3) and, at order 2, d2R (A, L, Q, Q, 3, 3), d2p (A, L, Q, Q, 3).

    The base: R0 (A, 3, 3), p0 (A, 3) and its derivatives dR0 (A, Q, 3, 3), d2R0 (A, Q, Q, 3, 3) (zero for a fixed
    base; a floating base's translation coordinates are 0..2, so dp0 is their identity); ``first`` the coordinate
    of joint 0 (6 for a floating base, else 0). Frame tables as in :func:`fk_rows`."""
    A, Q = th.shape[0], dR0.shape[1]
    F, L = parent.shape[0], link.shape[0]
    q2 = Q if order >= 2 else 0
    R = np.zeros((F, 3, 3))
    p = np.zeros((F, 3))
    dR = np.zeros((F, Q, 3, 3))
    dp = np.zeros((F, Q, 3))
    d2R = np.zeros((F, q2, q2, 3, 3))
    d2p = np.zeros((F, q2, q2, 3))
    oR = np.empty((A, L, 3, 3))
    op = np.empty((A, L, 3))
    odR = np.empty((A, L, Q, 3, 3))
    odp = np.empty((A, L, Q, 3))
    od2R = np.empty((A, L, q2, q2, 3, 3))
    od2p = np.empty((A, L, q2, q2, 3))
    Rl = np.empty((3, 3))
    Rl1 = np.empty((3, 3))
    Rl2 = np.empty((3, 3))
    Rj = np.empty((3, 3))
    Rj1 = np.empty((3, 3))
    Rj2 = np.empty((3, 3))
    pl = np.empty(3)
    pl1 = np.empty(3)
    pl2 = np.empty(3)
    RpRl1 = np.empty((3, 3))
    Rppl1 = np.empty(3)
    RpRl2 = np.empty((3, 3))
    Rppl2 = np.empty(3)
    a = np.empty(3)
    for e in range(A):
        R[0] = R0[e]
        p[0] = p0[e]
        dR[0] = dR0[e]
        dp[0] = 0.0
        if first == 6:
            for k in range(3):
                dp[0, k, k] = 1.0
        if order >= 2:
            d2R[0] = d2R0[e]
            d2p[0] = 0.0
        for f in range(1, F):
            b = parent[f]
            jq = first + joint[f]  # this frame's own coordinate
            t = th[e, joint[f]] - ref[f]
            _joint_transform(f, t, Ro, po, K, K2, anchor, slide, Rj, Rl, pl)
            s, c = math.sin(t), math.cos(t)
            for i in range(3):
                for k in range(3):
                    Rj1[i, k] = c * K[f, i, k] + s * K2[f, i, k]
                    Rj2[i, k] = c * K2[f, i, k] - s * K[f, i, k]
            for i in range(3):  # pl' = Ro (slide - Rj' anchor)
                a[i] = slide[f, i] - (
                    Rj1[i, 0] * anchor[f, 0] + Rj1[i, 1] * anchor[f, 1] + Rj1[i, 2] * anchor[f, 2]
                )
            for i in range(3):
                pl1[i] = Ro[f, i, 0] * a[0] + Ro[f, i, 1] * a[1] + Ro[f, i, 2] * a[2]
            for i in range(3):
                a[i] = -(Rj2[i, 0] * anchor[f, 0] + Rj2[i, 1] * anchor[f, 1] + Rj2[i, 2] * anchor[f, 2])
            for i in range(3):
                pl2[i] = Ro[f, i, 0] * a[0] + Ro[f, i, 1] * a[1] + Ro[f, i, 2] * a[2]
                for k in range(3):
                    Rl1[i, k] = Ro[f, i, 0] * Rj1[0, k] + Ro[f, i, 1] * Rj1[1, k] + Ro[f, i, 2] * Rj1[2, k]
                    Rl2[i, k] = Ro[f, i, 0] * Rj2[0, k] + Ro[f, i, 1] * Rj2[1, k] + Ro[f, i, 2] * Rj2[2, k]
            _attach(R, p, b, f, Rl, pl)
            for i in range(3):
                Rppl1[i] = R[b, i, 0] * pl1[0] + R[b, i, 1] * pl1[1] + R[b, i, 2] * pl1[2]
                Rppl2[i] = R[b, i, 0] * pl2[0] + R[b, i, 1] * pl2[1] + R[b, i, 2] * pl2[2]
                for k in range(3):
                    RpRl1[i, k] = R[b, i, 0] * Rl1[0, k] + R[b, i, 1] * Rl1[1, k] + R[b, i, 2] * Rl1[2, k]
                    RpRl2[i, k] = R[b, i, 0] * Rl2[0, k] + R[b, i, 1] * Rl2[1, k] + R[b, i, 2] * Rl2[2, k]
            # dR_a = dRp_a Rl + E_a Rp Rl',  dp_a = dpp_a + dRp_a pl + E_a Rp pl'
            for q in range(Q):
                for i in range(3):
                    dp[f, q, i] = (
                        dp[b, q, i] + dR[b, q, i, 0] * pl[0] + dR[b, q, i, 1] * pl[1] + dR[b, q, i, 2] * pl[2]
                    )
                    for k in range(3):
                        dR[f, q, i, k] = (
                            dR[b, q, i, 0] * Rl[0, k] + dR[b, q, i, 1] * Rl[1, k] + dR[b, q, i, 2] * Rl[2, k]
                        )
            for i in range(3):
                dp[f, jq, i] += Rppl1[i]
                for k in range(3):
                    dR[f, jq, i, k] += RpRl1[i, k]
            if order < 2:
                continue
            # d2R_ab = d2Rp_ab Rl + E_b dRp_a Rl' + E_a dRp_b Rl' + E_a E_b Rp Rl''  (d2p alike)
            for q in range(Q):
                for r in range(Q):
                    for i in range(3):
                        d2p[f, q, r, i] = (
                            d2p[b, q, r, i]
                            + d2R[b, q, r, i, 0] * pl[0]
                            + d2R[b, q, r, i, 1] * pl[1]
                            + d2R[b, q, r, i, 2] * pl[2]
                        )
                        for k in range(3):
                            d2R[f, q, r, i, k] = (
                                d2R[b, q, r, i, 0] * Rl[0, k]
                                + d2R[b, q, r, i, 1] * Rl[1, k]
                                + d2R[b, q, r, i, 2] * Rl[2, k]
                            )
            for q in range(Q):
                for i in range(3):
                    x = dR[b, q, i, 0] * pl1[0] + dR[b, q, i, 1] * pl1[1] + dR[b, q, i, 2] * pl1[2]
                    d2p[f, q, jq, i] += x
                    d2p[f, jq, q, i] += x
                    for k in range(3):
                        X = (
                            dR[b, q, i, 0] * Rl1[0, k]
                            + dR[b, q, i, 1] * Rl1[1, k]
                            + dR[b, q, i, 2] * Rl1[2, k]
                        )
                        d2R[f, q, jq, i, k] += X
                        d2R[f, jq, q, i, k] += X
            for i in range(3):
                d2p[f, jq, jq, i] += Rppl2[i]
                for k in range(3):
                    d2R[f, jq, jq, i, k] += RpRl2[i, k]
        for n in range(L):
            g = link[n]
            oR[e, n] = R[g]
            op[e, n] = p[g]
            odR[e, n] = dR[g]
            odp[e, n] = dp[g]
            if order >= 2:
                od2R[e, n] = d2R[g]
                od2p[e, n] = d2p[g]
    return oR, op, odR, odp, od2R, od2p


@numba.njit(cache=True, error_model="numpy")
def _solve3(M, b, transpose, x):
    """x (3,) = M^-1 b, or M^-T b with ``transpose`` (M (3, 3)): Gaussian elimination with partial pivoting."""
    a = np.empty((3, 4))
    for i in range(3):
        for k in range(3):
            a[i, k] = M[k, i] if transpose else M[i, k]
        a[i, 3] = b[i]
    for c in range(3):
        piv = c
        for r in range(c + 1, 3):
            if abs(a[r, c]) > abs(a[piv, c]):
                piv = r
        if piv != c:
            for k in range(4):
                a[c, k], a[piv, k] = a[piv, k], a[c, k]
        for r in range(c + 1, 3):
            f = a[r, c] / a[c, c]
            for k in range(c, 4):
                a[r, k] -= f * a[c, k]
    for r in range(2, -1, -1):
        s = a[r, 3]
        for k in range(r + 1, 3):
            s -= a[r, k] * x[k]
        x[r] = s / a[r, r]


@numba.njit(cache=True, error_model="numpy")
def row_derivatives(R, dR, dp, d2R, d2p, com, g, lo, ca, cb, want_second):
    """The Jacobian J (A, 6 (L - lo), Q) of the link rows [R com + p, log R] of links lo.. in the coordinates and,
    with ``want_second``, the contraction sum_k g_k d2 row_k / dq dq (A, Q, Q) for row gradients g (A, L - lo, 6):
    the formulas of :func:`cfd_torch.sim.articulation._fk_derivatives`, from :func:`chain`'s frames R (A, L, 3, 3)
    and derivatives dR (A, L, Q, 3, 3), dp (A, L, Q, 3), d2R (A, L, Q, Q, 3, 3), d2p (A, L, Q, Q, 3); com (L, 3);
    ``ca``, ``cb`` the exponential's series coefficients (``cfd_torch._rotation_numba``)."""
    A, L, Q = dR.shape[0], dR.shape[1], dR.shape[2]
    La = L - lo
    order = 2 if want_second else 1
    w = np.empty((A * La, 3))
    for e in range(A):
        for n in range(La):
            _rotvec(R[e, lo + n], w[e * La + n])
    Re = np.empty((A * La, 3, 3))
    dE = np.empty((A * La, 3, 3, 3))
    d2E = np.empty((A * La if want_second else 0, 3, 3, 3, 3))
    rotation_derivatives_kernel(w, ca, cb, Re, dE, d2E, order)
    J = np.zeros((A, 6 * La, Q))
    second = np.zeros((A, Q if want_second else 0, Q if want_second else 0))
    G = np.empty((3, 3))
    Om = np.empty((3, Q))
    v = np.empty(3)
    x = np.empty(3)
    P = np.empty((3, 3))
    C = np.empty((3, 3))
    N = np.empty((3, 3))
    ON = np.empty((Q, 3))
    S = np.empty((3, 3))
    for e in range(A):
        for n in range(La):
            m = e * La + n
            k = lo + n
            M = R[e, k]
            # G e_i = vee(E_i Re^T), vee(S) = (S21 - S12, S02 - S20, S10 - S01) / 2
            for i in range(3):
                for r in range(3):
                    for c in range(3):
                        S[r, c] = (
                            dE[m, r, 0, i] * Re[m, c, 0]
                            + dE[m, r, 1, i] * Re[m, c, 1]
                            + dE[m, r, 2, i] * Re[m, c, 2]
                        )
                G[0, i] = 0.5 * (S[2, 1] - S[1, 2])
                G[1, i] = 0.5 * (S[0, 2] - S[2, 0])
                G[2, i] = 0.5 * (S[1, 0] - S[0, 1])
            for q in range(Q):
                D = dR[e, k, q]
                # V = vee(dR_q R^T): the world angular velocity of coordinate q; dw/dq = G^-1 V
                s21 = D[2, 0] * M[1, 0] + D[2, 1] * M[1, 1] + D[2, 2] * M[1, 2]
                s12 = D[1, 0] * M[2, 0] + D[1, 1] * M[2, 1] + D[1, 2] * M[2, 2]
                s02 = D[0, 0] * M[2, 0] + D[0, 1] * M[2, 1] + D[0, 2] * M[2, 2]
                s20 = D[2, 0] * M[0, 0] + D[2, 1] * M[0, 1] + D[2, 2] * M[0, 2]
                s10 = D[1, 0] * M[0, 0] + D[1, 1] * M[0, 1] + D[1, 2] * M[0, 2]
                s01 = D[0, 0] * M[1, 0] + D[0, 1] * M[1, 1] + D[0, 2] * M[1, 2]
                v[0], v[1], v[2] = 0.5 * (s21 - s12), 0.5 * (s02 - s20), 0.5 * (s10 - s01)
                _solve3(G, v, False, x)
                for i in range(3):
                    Om[i, q] = x[i]
                    J[e, 6 * n + i, q] = (
                        dp[e, k, q, i] + D[i, 0] * com[k, 0] + D[i, 1] * com[k, 1] + D[i, 2] * com[k, 2]
                    )
                    J[e, 6 * n + 3 + i, q] = x[i]
            if not want_second:
                continue
            gx0, gx1, gx2 = g[e, n, 0], g[e, n, 1], g[e, n, 2]
            v[0], v[1], v[2] = g[e, n, 3], g[e, n, 4], g[e, n, 5]
            _solve3(G, v, True, x)  # h = G^-T g_w
            h0, h1, h2 = x[0], x[1], x[2]
            # P = [h]_x R / 2, C = P + g_x com^T
            for c in range(3):
                P[0, c] = 0.5 * (-h2 * M[1, c] + h1 * M[2, c])
                P[1, c] = 0.5 * (h2 * M[0, c] - h0 * M[2, c])
                P[2, c] = 0.5 * (-h1 * M[0, c] + h0 * M[1, c])
            for c in range(3):
                C[0, c] = P[0, c] + gx0 * com[k, c]
                C[1, c] = P[1, c] + gx1 * com[k, c]
                C[2, c] = P[2, c] + gx2 * com[k, c]
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for r in range(3):
                        for c in range(3):
                            s += d2E[m, r, c, i, j] * P[r, c]
                    N[i, j] = s
            for a in range(Q):  # ON = Om^T N
                for j in range(3):
                    ON[a, j] = Om[0, a] * N[0, j] + Om[1, a] * N[1, j] + Om[2, a] * N[2, j]
            for a in range(Q):
                for b in range(Q):
                    B = d2R[e, k, a, b]
                    s = -(ON[a, 0] * Om[0, b] + ON[a, 1] * Om[1, b] + ON[a, 2] * Om[2, b])
                    for r in range(3):
                        s += B[r, 0] * C[r, 0] + B[r, 1] * C[r, 1] + B[r, 2] * C[r, 2]
                    s += d2p[e, k, a, b, 0] * gx0 + d2p[e, k, a, b, 1] * gx1 + d2p[e, k, a, b, 2] * gx2
                    second[e, a, b] += s
    return J, second
