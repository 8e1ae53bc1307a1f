"""CPU kernel of an articulation's forward kinematics to its links' state rows (the value of
:func:`cfd_torch.sim.articulation._fk_rows`, without derivatives), for the many small evaluations a step makes.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
            out[e, n, 3] = k * x
            out[e, n, 4] = k * y
            out[e, n, 5] = k * z
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
