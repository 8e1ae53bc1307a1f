"""CPU kernel of :meth:`cfd_torch.contact.CfdContact.lagged`'s contact data (the formulas of ``cfd.py``'s module
docstring) from the leaf pairs' vertex forces, for the forward step (no autograd graph)."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy")
def lagged_contacts(g, lw, lp, Xa, Xb, R, t, ba, bb, active, num_pairs):
    """The lagged friction contacts of C leaf pairs.

    Args:
        g: (C, 2, 3, 3) the pair potential's vertex gradients (side, vertex, xyz).
        lw: (C,) inherited blend weights; lp: (C,) body pair of each.
        Xa, Xb: (C, 3, 3) body-frame triangles; R (B, 3, 3), t (B, 3) the body poses; ba, bb (C,) the leaf pairs'
            bodies' rows.
        active: drop contacts whose normal force is below this fraction of their body pair's largest (0: keep all).
        num_pairs: the number of body pairs.

    Returns:
        keep (K,) the kept leaf pairs' indices, X (K, 2, 3) body-frame force centres, x (K, 2, 3) their world
        positions, T (K, 3, 3) projectors I - n n^T, lam (K,) normal forces.
    """
    C = lw.shape[0]
    lam = np.empty(C)
    fa = np.empty((C, 3))
    fb = np.empty((C, 3))
    top = np.zeros(num_pairs)
    for c in range(C):
        sa = 0.0
        sb = 0.0
        for v in range(3):
            a = math.sqrt(g[c, 0, v, 0] ** 2 + g[c, 0, v, 1] ** 2 + g[c, 0, v, 2] ** 2)
            b = math.sqrt(g[c, 1, v, 0] ** 2 + g[c, 1, v, 1] ** 2 + g[c, 1, v, 2] ** 2)
            fa[c, v] = a
            fb[c, v] = b
            sa += a
            sb += b
        lam[c] = lw[c] * sa
        if lam[c] > top[lp[c]]:
            top[lp[c]] = lam[c]
    keep = np.nonzero(lam >= active * top[lp])[0] if active > 0.0 else np.arange(C)
    K = keep.shape[0]
    X = np.empty((K, 2, 3))
    x = np.empty((K, 2, 3))
    T = np.empty((K, 3, 3))
    out_lam = np.empty(K)
    n = np.empty(3)
    for k in range(K):
        c = keep[k]
        sa = fa[c, 0] + fa[c, 1] + fa[c, 2]
        sb = fb[c, 0] + fb[c, 1] + fb[c, 2]
        for i in range(3):
            X[k, 0, i] = (
                (fa[c, 0] / sa) * Xa[c, 0, i] + (fa[c, 1] / sa) * Xa[c, 1, i] + (fa[c, 2] / sa) * Xa[c, 2, i]
            )
            X[k, 1, i] = (
                (fb[c, 0] / sb) * Xb[c, 0, i] + (fb[c, 1] / sb) * Xb[c, 1, i] + (fb[c, 2] / sb) * Xb[c, 2, i]
            )
            n[i] = -(g[c, 0, 0, i] + g[c, 0, 1, i] + g[c, 0, 2, i])
        nn = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        for i in range(3):
            n[i] /= nn
        for i in range(3):
            for j in range(3):
                T[k, i, j] = (1.0 if i == j else 0.0) - n[i] * n[j]
        for s in range(2):
            b = ba[c] if s == 0 else bb[c]
            for i in range(3):
                x[k, s, i] = (
                    R[b, i, 0] * X[k, s, 0] + R[b, i, 1] * X[k, s, 1] + R[b, i, 2] * X[k, s, 2] + t[b, i]
                )
        out_lam[k] = lam[c]
    return keep, X, x, T, out_lam
