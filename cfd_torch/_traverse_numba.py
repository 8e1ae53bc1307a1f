"""CPU kernel of the BSH node-pair traversal (the same recursion and product rule as ``mesh_potential._traverse``).

Depth-first with an explicit stack, one body pair after another: each stack entry carries its node pair, body
pair, inherited weight W and, for order >= 1, the weight's gradient (12) and Hessian (12 x 12) in the pair's pose
coordinates [t_a, omega_a, t_b, omega_b]. Central terms are accumulated in place; leaf pairs that need the exact
potential are returned with their weights, to be solved in one batch by the pair kernel. The tensor traversal in
``mesh_potential.py`` does the same breadth-first on any device; the tests check that both agree.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_JIT = {"cache": True, "error_model": "numpy"}


@numba.njit(**_JIT)
def _grow(a, n):
    b = np.empty((max(2 * a.shape[0], n),) + a.shape[1:], dtype=a.dtype)
    b[: a.shape[0]] = a
    return b


@numba.njit(**_JIT)
def traverse_nodes(centre, radius, child, pair_body, pair_root, R, dR, d2R, t, mu, eps, split_both, order,
                   value, grad, hess):  # fmt: skip
    """Accumulate central terms into value (P,), grad (P, 12), hess (P, 12, 12); return the leaf pairs.

    Returns:
        (LI, LJ, lp, lw, ldw, ld2w, n_leaf, n_pairs): leaf node ids, body pair, weight (1 - phi) prod, and its
        gradient (L, 12) and Hessian (L, 12, 12) (zeros below ``order``), valid up to index n_leaf.
    """
    P = pair_body.shape[0]
    cap = 1024
    sI = np.empty(cap, np.int64)
    sJ = np.empty(cap, np.int64)
    sP = np.empty(cap, np.int64)
    sW = np.empty(cap)
    sdW = np.zeros((cap, 12))
    sd2W = np.zeros((cap, 12, 12))
    lcap = 256
    LI = np.empty(lcap, np.int64)
    LJ = np.empty(lcap, np.int64)
    lp = np.empty(lcap, np.int64)
    lw = np.empty(lcap)
    ldw = np.zeros((lcap, 12))
    ld2w = np.zeros((lcap, 12, 12))
    n_leaf = 0
    n_pairs = 0
    dd = np.zeros((3, 12))
    dr = np.zeros(12)
    d2r = np.zeros((12, 12))
    W1 = np.zeros(12)
    W2 = np.zeros((12, 12))
    ca = np.zeros(3)
    cb = np.zeros(3)
    for k in range(3):
        dd[k, k] = 1.0
        dd[k, 6 + k] = -1.0
    for p in range(P):
        ba, bb = pair_body[p, 0], pair_body[p, 1]
        top = 0
        sI[0], sJ[0], sP[0], sW[0] = pair_root[p, 0], pair_root[p, 1], p, 1.0
        if order >= 1:
            sdW[0, :] = 0.0
        if order >= 2:
            sd2W[0, :, :] = 0.0
        top = 1
        while top > 0:
            top -= 1
            I, J, W = sI[top], sJ[top], sW[top]
            if order >= 1:
                W1[:] = sdW[top]
            if order >= 2:
                W2[:, :] = sd2W[top]
            n_pairs += 1
            CI = centre[I]
            CJ = centre[J]
            dx = 0.0
            r2 = 0.0
            d = np.empty(3)
            for i in range(3):
                ca[i] = R[ba, i, 0] * CI[0] + R[ba, i, 1] * CI[1] + R[ba, i, 2] * CI[2] + t[ba, i]
                cb[i] = R[bb, i, 0] * CJ[0] + R[bb, i, 1] * CJ[1] + R[bb, i, 2] * CJ[2] + t[bb, i]
                dx = ca[i] - cb[i]
                d[i] = dx
                r2 += dx * dx
            r = math.sqrt(r2)
            inv_r = 1.0 / r
            d1 = radius[I] + radius[J]
            width = eps * d1
            s = (r - d1) / width
            tt = min(max(s, 0.0), 1.0)
            phi = tt * tt * tt * (tt * (6.0 * tt - 15.0) + 10.0)
            phi1 = 30.0 * tt * tt * (tt - 1.0) ** 2 / width
            phi2 = 60.0 * tt * (tt - 1.0) * (2.0 * tt - 1.0) / (width * width)
            if order >= 1:
                u0, u1, u2 = d[0] * inv_r, d[1] * inv_r, d[2] * inv_r
                for i in range(3):
                    for kk in range(3):
                        dd[i, 3 + kk] = (
                            dR[ba, i, 0, kk] * CI[0] + dR[ba, i, 1, kk] * CI[1] + dR[ba, i, 2, kk] * CI[2]
                        )
                        dd[i, 9 + kk] = -(
                            dR[bb, i, 0, kk] * CJ[0] + dR[bb, i, 1, kk] * CJ[1] + dR[bb, i, 2, kk] * CJ[2]
                        )
                for c in range(12):
                    dr[c] = u0 * dd[0, c] + u1 * dd[1, c] + u2 * dd[2, c]
                if order >= 2:
                    for a in range(12):
                        for c in range(a, 12):
                            v = (
                                dd[0, a] * dd[0, c]
                                + dd[1, a] * dd[1, c]
                                + dd[2, a] * dd[2, c]
                                - dr[a] * dr[c]
                            ) * inv_r
                            d2r[a, c] = v
                            d2r[c, a] = v
                    for kk in range(3):
                        for ll in range(3):
                            acc_a = 0.0
                            acc_b = 0.0
                            for i in range(3):
                                ui = d[i] * inv_r
                                for m in range(3):
                                    acc_a += ui * d2R[ba, i, m, kk, ll] * CI[m]
                                    acc_b += ui * d2R[bb, i, m, kk, ll] * CJ[m]
                            d2r[3 + kk, 3 + ll] += acc_a
                            d2r[9 + kk, 9 + ll] -= acc_b
            # central term W * phi * P_c(r)
            if phi > 0.0:
                sq = math.sqrt(inv_r)
                ir = sq * sq
                pc = 12.0 * mu * (1.0 + sq) ** 2
                pc1 = -12.0 * mu * (ir * sq + ir * ir)
                pc2 = 12.0 * mu * (1.5 * ir * ir * sq + 2.0 * ir * ir * ir)
                g = phi * pc
                value[p] += W * g
                if order >= 1:
                    g1 = phi1 * pc + phi * pc1
                    for a in range(12):
                        grad[p, a] += g * W1[a] + W * g1 * dr[a]
                    if order >= 2:
                        g2 = phi2 * pc + 2.0 * phi1 * pc1 + phi * pc2
                        for a in range(12):
                            for c in range(12):
                                hess[p, a, c] += (
                                    g * W2[a, c]
                                    + g1 * (W1[a] * dr[c] + dr[a] * W1[c])
                                    + W * (g2 * dr[a] * dr[c] + g1 * d2r[a, c])
                                )
            if s >= 1.0:
                continue
            # inherited weight W (1 - phi) and its derivatives (product rule)
            h = 1.0 - phi
            if order >= 2:
                for a in range(12):
                    for c in range(12):
                        W2[a, c] = (
                            h * W2[a, c]
                            - phi1 * (W1[a] * dr[c] + dr[a] * W1[c])
                            - W * (phi2 * dr[a] * dr[c] + phi1 * d2r[a, c])
                        )
            if order >= 1:
                for a in range(12):
                    W1[a] = h * W1[a] - W * phi1 * dr[a]
            W = W * h
            leaf_i = child[I, 0] < 0
            leaf_j = child[J, 0] < 0
            if leaf_i and leaf_j:
                if n_leaf == LI.shape[0]:
                    LI, LJ, lp, lw = _grow(LI, 0), _grow(LJ, 0), _grow(lp, 0), _grow(lw, 0)
                    ldw, ld2w = _grow(ldw, 0), _grow(ld2w, 0)
                LI[n_leaf], LJ[n_leaf], lp[n_leaf], lw[n_leaf] = I, J, p, W
                if order >= 1:
                    ldw[n_leaf] = W1
                if order >= 2:
                    ld2w[n_leaf] = W2
                n_leaf += 1
                continue
            if split_both:
                si, sj = not leaf_i, not leaf_j
            else:
                si = (not leaf_i) and (leaf_j or radius[I] >= radius[J])
                sj = not si
            ni = 2 if si else 1
            nj = 2 if sj else 1
            if top + 4 > sI.shape[0]:
                sI, sJ, sP, sW = (
                    _grow(sI, top + 4),
                    _grow(sJ, top + 4),
                    _grow(sP, top + 4),
                    _grow(sW, top + 4),
                )
                sdW, sd2W = _grow(sdW, top + 4), _grow(sd2W, top + 4)
            for a in range(ni):
                ci = child[I, a] if si else I
                for b in range(nj):
                    cj = child[J, b] if sj else J
                    sI[top], sJ[top], sP[top], sW[top] = ci, cj, p, W
                    if order >= 1:
                        sdW[top] = W1
                    if order >= 2:
                        sd2W[top] = W2
                    top += 1
    return LI, LJ, lp, lw, ldw, ld2w, n_leaf, n_pairs


@numba.njit(**_JIT)
def accumulate_leaves(lp, lw, ldw, ld2w, pv, gx, Hx, Xa, Xb, ba, bb, dR, d2R, order, value, grad, hess):
    """Add the leaf terms w * P_exact to value/grad/hess of their body pairs.

    Chain rule to pose space with x_v = R X_v + t: J (18, 12) has identity blocks for the translations and
    dR[..., k] X_v for the rotations; hess_q = J^T hess_x J + sum_v grad_x_v . d2R X_v (rotation blocks). Then the
    product rule with the weight: value w P, grad P dw + w gq, hess P d2w + dw gq^T + gq dw^T + w hq.
    """
    L = lp.shape[0]
    J = np.zeros((18, 12))
    T = np.empty((18, 12))
    gq = np.empty(12)
    hq = np.empty((12, 12))
    for e in range(L):
        p = lp[e]
        w = lw[e]
        P = pv[e]
        value[p] += w * P
        if order < 1 or not math.isfinite(P):
            continue
        J[:, :] = 0.0
        for v in range(6):
            body = ba[e] if v < 3 else bb[e]
            X = Xa[e, v] if v < 3 else Xb[e, v - 3]
            col_t = 0 if v < 3 else 6
            for i in range(3):
                row = 3 * v + i
                J[row, col_t + i] = 1.0
                for k in range(3):
                    J[row, col_t + 3 + k] = (
                        dR[body, i, 0, k] * X[0] + dR[body, i, 1, k] * X[1] + dR[body, i, 2, k] * X[2]
                    )
        for c in range(12):
            acc = 0.0
            for a in range(18):
                acc += gx[e, a] * J[a, c]
            gq[c] = acc
        for c in range(12):
            grad[p, c] += P * ldw[e, c] + w * gq[c]
        if order < 2:
            continue
        for a in range(18):
            for c in range(12):
                acc = 0.0
                for b in range(18):
                    acc += Hx[e, a, b] * J[b, c]
                T[a, c] = acc
        for a in range(12):
            for c in range(12):
                acc = 0.0
                for b in range(18):
                    acc += J[b, a] * T[b, c]
                hq[a, c] = acc
        for v in range(6):
            body = ba[e] if v < 3 else bb[e]
            X = Xa[e, v] if v < 3 else Xb[e, v - 3]
            off = 3 if v < 3 else 9
            for k in range(3):
                for l2 in range(3):
                    acc = 0.0
                    for i in range(3):
                        gi = gx[e, 3 * v + i]
                        for m in range(3):
                            acc += gi * d2R[body, i, m, k, l2] * X[m]
                    hq[off + k, off + l2] += acc
        for a in range(12):
            for c in range(12):
                hess[p, a, c] += P * ld2w[e, a, c] + ldw[e, a] * gq[c] + gq[a] * ldw[e, c] + w * hq[a, c]
