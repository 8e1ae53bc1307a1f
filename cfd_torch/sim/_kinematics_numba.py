"""CPU kernel of an articulation's forward kinematics to its links' state rows (the value of
:func:`cfd_torch.sim.articulation._fk_rows`, without derivatives), for the many small evaluations a step makes.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
    a = np.empty(3)
    out = np.empty((A, L, 6))
    for e in range(A):
        R[0] = R0[e]
        p[0] = p0[e]
        for f in range(1, F):
            j = joint[f]
            t = th[e, j] - ref[f]
            s, c = math.sin(t), math.cos(t)
            for i in range(3):
                for k in range(3):
                    Rj[i, k] = (1.0 if i == k else 0.0) + s * K[f, i, k] + (1.0 - c) * K2[f, i, k]
            for i in range(3):
                a[i] = anchor[f, i] - (
                    Rj[i, 0] * anchor[f, 0] + Rj[i, 1] * anchor[f, 1] + Rj[i, 2] * anchor[f, 2]
                )
                a[i] += t * slide[f, i]
            for i in range(3):
                pl[i] = po[f, i] + Ro[f, i, 0] * a[0] + Ro[f, i, 1] * a[1] + Ro[f, i, 2] * a[2]
                for k in range(3):
                    Rl[i, k] = Ro[f, i, 0] * Rj[0, k] + Ro[f, i, 1] * Rj[1, k] + Ro[f, i, 2] * Rj[2, k]
            b = parent[f]
            for i in range(3):
                p[f, i] = p[b, i] + R[b, i, 0] * pl[0] + R[b, i, 1] * pl[1] + R[b, i, 2] * pl[2]
                for k in range(3):
                    R[f, i, k] = R[b, i, 0] * Rl[0, k] + R[b, i, 1] * Rl[1, k] + R[b, i, 2] * Rl[2, k]
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
