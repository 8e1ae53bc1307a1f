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

from .._geometry import segment_hits_triangle_nb, tri_tri_closest_nb
from .._rotation_numba import add_rotation_terms

_JIT = {"cache": True, "error_model": "numpy"}
# Counters handed to other kernels start as np.int64(...), not as bare literals: type inference would first compile
# the callee for the literal (Literal[int](1)) and then again for int64, seconds of compile each on a cold cache.


@numba.njit(**_JIT)
def _grow(a):
    """a in a buffer twice its size."""
    b = np.empty((2 * a.shape[0],) + a.shape[1:], dtype=a.dtype)
    b[: a.shape[0]] = a
    return b


@numba.njit(**_JIT)
def _split_rule(leaf_i, leaf_j, radius_i, radius_j, split_both):
    """Which sides of a node pair to split: both non-leaves, or (``larger``) the larger non-leaf side, both
    non-leaves on a tie (a rule symmetric under swapping the two bodies)."""
    if split_both or radius_i == radius_j:
        return not leaf_i, not leaf_j
    si = (not leaf_i) and (leaf_j or radius_i > radius_j)
    return si, not si


@numba.njit(**_JIT)
def hessian_span(side):
    """The coordinates lo..hi-1 of a body pair's 12 whose Hessian is formed: ``side`` 0 all (0, 12), 1 body a's
    (0, 6), 2 body b's (6, 12)."""
    if side == 1:
        return 0, 6
    if side == 2:
        return 6, 12
    return 0, 12


# a far node pair's row in the far buffer F (20, capacity): its (Hessian) moments' factors
_F_AL, _F_Z, _F_BE, _F_CI, _F_CJ, _F_GU, _F_ROWS = 0, 1, 10, 11, 14, 17, 20


@numba.njit(nogil=True, **_JIT)
def _far_row(F, k, dr, d, inv_r, g1, g2, CI, CJ):
    """Write far node pair k's factors into column k of F (summed by :func:`_far_moments`)."""
    F[_F_AL, k] = g2 - g1 * inv_r
    for i in range(3):
        u = d[i] * inv_r
        F[_F_Z + i, k] = u
        F[_F_Z + 3 + i, k] = dr[3 + i]
        F[_F_Z + 6 + i, k] = dr[9 + i]
        F[_F_CI + i, k] = CI[i]
        F[_F_CJ + i, k] = CJ[i]
        F[_F_GU + i, k] = g1 * u
    F[_F_BE, k] = g1 * inv_r


@numba.njit(nogil=True, fastmath={"reassoc"}, **_JIT)
def _far_moments(F, nf, Z, M, zact, nz, lo, hi):
    """A body pair's far node pairs' Hessian as moments (expanded by :func:`_far_expand`), summed over the nf
    columns of F (:func:`_far_row`; the sums in any order: vectorised).

    The Hessian of f(r), r = |d|, d = x_a - x_b = R_a C_I + t_a - R_b C_J - t_b, in the 12 pose coordinates is
    (g2 - g1 / r) dr dr^T + (g1 / r) dd^T dd + g1 u . d2d with f' = g1, f'' = g2, u = d / r, dd = [I, A, -I, -B],
    A = dR_a C_I, B = dR_b C_J (each column k: dR[..., k] C) and dr = u^T dd = [u, u^T A, -u, -u^T B]. The body
    pair's rotation derivatives are the same for all its node pairs, and A, B, d2d are linear in the node centres,
    so the sums over node pairs need only:

        Z (9, 9)   = sum (g2 - g1 / r) z z^T, z = [u, u^T A, -u^T B]  (the upper triangle)
        M[0]       = sum g1 / r                   M[1:4] = sum (g1 / r) C_I       M[4:7] = sum (g1 / r) C_J
        M[7:16]    = sum (g1 / r) C_I C_I^T       M[16:25] = sum (g1 / r) C_I C_J^T  M[25:34] = sum (g1 / r) C_J C_J^T
        M[34:43]   = sum g1 u C_I^T               M[43:52] = sum g1 u C_J^T

    Only the moments of the coordinates lo..hi-1 are formed: the entries ``zact[:nz]`` of z, and the sums over C_I
    (body a, coordinates 0..5) or C_J (b, 6..11)."""
    on_a = lo == 0
    on_b = hi == 12
    for ia in range(nz):
        a = zact[ia]
        for ic in range(ia, nz):
            c = zact[ic]
            acc = 0.0
            for k in range(nf):
                acc += F[_F_AL, k] * F[_F_Z + a, k] * F[_F_Z + c, k]
            Z[a, c] = acc
    acc = 0.0
    for k in range(nf):
        acc += F[_F_BE, k]
    M[0] = acc
    for m in range(3):
        if on_a:
            acc = 0.0
            for k in range(nf):
                acc += F[_F_BE, k] * F[_F_CI + m, k]
            M[1 + m] = acc
        if on_b:
            acc = 0.0
            for k in range(nf):
                acc += F[_F_BE, k] * F[_F_CJ + m, k]
            M[4 + m] = acc
        for n in range(3):
            if on_a:
                acc = 0.0
                for k in range(nf):
                    acc += F[_F_BE, k] * F[_F_CI + m, k] * F[_F_CI + n, k]
                M[7 + 3 * m + n] = acc
            if on_a and on_b:
                acc = 0.0
                for k in range(nf):
                    acc += F[_F_BE, k] * F[_F_CI + m, k] * F[_F_CJ + n, k]
                M[16 + 3 * m + n] = acc
            if on_b:
                acc = 0.0
                for k in range(nf):
                    acc += F[_F_BE, k] * F[_F_CJ + m, k] * F[_F_CJ + n, k]
                M[25 + 3 * m + n] = acc
    for i in range(3):
        for m in range(3):
            if on_a:
                acc = 0.0
                for k in range(nf):
                    acc += F[_F_GU + i, k] * F[_F_CI + m, k]
                M[34 + 3 * i + m] = acc
            if on_b:
                acc = 0.0
                for k in range(nf):
                    acc += F[_F_GU + i, k] * F[_F_CJ + m, k]
                M[43 + 3 * i + m] = acc


@numba.njit(nogil=True, **_JIT)
def _far_expand(hess, p, Z, M, dR, d2R, ba, bb, lo, hi):
    """Add the far node pairs' Hessian from their moments (:func:`_far_moments`) to the upper triangle of
    hess[p] over the coordinates lo..hi-1."""
    on_a = lo == 0
    on_b = hi == 12
    # the 12 coordinates as entries of z (sign, index): t_a = +u, omega_a = +u^T A, t_b = -u, omega_b = -u^T B
    zi = (0, 1, 2, 3, 4, 5, 0, 1, 2, 6, 7, 8)
    zs = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
    for a in range(lo, hi):
        for c in range(a, hi):
            i, j = zi[a], zi[c]
            hess[p, a, c] += zs[a] * zs[c] * (Z[i, j] if i <= j else Z[j, i])
    be = M[0]
    # sum (g1 / r) A = dR_a (sum (g1 / r) C_I) (3 x 3, rows xyz, columns omega_a), B likewise
    SA = np.empty((3, 3))
    SB = np.empty((3, 3))
    for i in range(3):
        for k in range(3):
            SA[i, k] = dR[ba, i, 0, k] * M[1] + dR[ba, i, 1, k] * M[2] + dR[ba, i, 2, k] * M[3]
            SB[i, k] = dR[bb, i, 0, k] * M[4] + dR[bb, i, 1, k] * M[5] + dR[bb, i, 2, k] * M[6]
    for i in range(3):
        if on_a:
            hess[p, i, i] += be  # t_a t_a: I
        if on_b:
            hess[p, 6 + i, 6 + i] += be  # t_b t_b: I
        if on_a and on_b:
            hess[p, i, 6 + i] -= be  # t_a t_b: -I
        for k in range(3):
            if on_a:
                hess[p, i, 3 + k] += SA[i, k]  # t_a omega_a: A
            if on_a and on_b:
                hess[p, i, 9 + k] -= SB[i, k]  # t_a omega_b: -B
                hess[p, 3 + k, 6 + i] -= SA[i, k]  # omega_a t_b: -A^T
            if on_b:
                hess[p, 6 + i, 9 + k] += SB[i, k]  # t_b omega_b: B
    # sum (g1 / r) A^T A, A^T B, B^T B: sum_i,m,n dR[i, m, k] dR'[i, n, l] (sum (g1 / r) C C'^T)[m, n]
    for k in range(3):
        for l in range(3):
            aa = 0.0
            ab = 0.0
            bb2 = 0.0
            for i in range(3):
                for m in range(3):
                    for n in range(3):
                        ab += dR[ba, i, m, k] * dR[bb, i, n, l] * M[16 + 3 * m + n]
                        if l >= k:
                            aa += dR[ba, i, m, k] * dR[ba, i, n, l] * M[7 + 3 * m + n]
                            bb2 += dR[bb, i, m, k] * dR[bb, i, n, l] * M[25 + 3 * m + n]
            if on_a and on_b:
                hess[p, 3 + k, 9 + l] -= ab  # omega_a omega_b: -A^T B
            if l >= k:
                if on_a:
                    hess[p, 3 + k, 3 + l] += aa
                if on_b:
                    hess[p, 9 + k, 9 + l] += bb2
    # g1 u . d2d: + sum_i,m d2R_a[i, m, k, l] (g1 u C_I^T)[i, m] on omega_a omega_a, - the same of b
    if on_a:
        add_rotation_terms(hess, p, 3, M[34:43].reshape((3, 3)), d2R, ba, 1.0)
    if on_b:
        add_rotation_terms(hess, p, 9, M[43:52].reshape((3, 3)), d2R, bb, -1.0)


@numba.njit(nogil=True, **_JIT)
def _add_entry_terms(hess, p, wd1, wd2, e, total, grads, lo, hi):
    """hess[p] += total d2w_e + dw_e grads^T + grads dw_e^T over the upper triangle of the coordinates lo..hi-1:
    the weight derivatives' part of the Hessian of the terms w_e f_k below weight table entry e, from their sums
    ``total`` (of f_k) and ``grads`` (12,) (of their gradients)."""
    for a in range(lo, hi):
        wa = wd1[e, a]
        ga = grads[a]
        for c in range(a, hi):
            hess[p, a, c] += total * wd2[e, a, c] + wa * grads[c] + ga * wd1[e, c]


@numba.njit(nogil=True, **_JIT)
def _expand_inherited(hess, p, wd1, wd2, ws, wds, first, last, lo, hi):
    """Add to hess[p] the weight derivatives' part of the far terms below each weight table entry e in
    first..last-1 (:func:`_add_entry_terms`), from their sums ws[e] (values) and wds[e] (f_k' dr_k)."""
    for e in range(first, last):
        if ws[e] != 0.0:  # (0: no far term below this entry)
            _add_entry_terms(hess, p, wd1, wd2, e, ws[e], wds[e], lo, hi)


# the buffers' first capacities (the kernels grow them as needed; passed by the callers: numba dispatches a call
# that leaves out arguments with defaults through its slow path, about half a millisecond per call)
STACK_CAP, TABLE_CAP, LEAF_CAP = 1024, 256, 256
# the kernels' status codes
_DONE, _FULL_STACK, _FULL_LEAVES, _FULL_WEIGHTS, _HIT, _FULL_FAR = 0, 1, 2, 3, 4, 5


@numba.njit(nogil=True, **_JIT)
def _pair_nodes(p, ba, bb, centre, radius, child, R, dR, d2R, t, mu, eps_p, min_width, split_both, order, value,
                grad, hess, lo, hi, sI, sJ, sK, top, LI, LJ, lp, lwid, n_leaf, wv, wd1, wd2, ws, wds, nw, dd, dr, d2r,
                d, F, nf, n_pairs):  # fmt: skip
    """Traverse body pair p (bodies ba, bb) from its stack (sI, sJ, sK, ``top`` entries), accumulating its central
    terms into value[p], grad[p], hess[p] (the upper triangle of its coordinates lo..hi-1: 0..11, or one body's
    0..5 or 6..11, :func:`hessian_span`) but for its far node pairs' Hessians, whose factors are appended to F from
    column nf (order 2; :func:`_far_moments` sums them); leaves are appended from index n_leaf, weight table entries
    from nw (their Hessians over lo..hi-1).
    The far node pairs below a table entry e (an ancestor in the blend band) add their central terms' sums to
    ws[e] (the values) and wds[e] (their radial derivatives times dr), expanded with the entry's weight
    derivatives once per entry by :func:`_expand_inherited`.

    Returns (status, top, n_leaf, nw, n_pairs, nf): status ``_DONE``, or which buffer is full (the stack, the
    leaves, the weight table, the far buffer), checked before a node pair is taken off the stack (each needs at most
    3 more stack entries, one leaf, one table entry and one far column): the caller grows that buffer and calls
    again with the returned state,
    which goes on where this call stopped. The buffers are arguments, never reassigned here: numba
    reference-counts an array variable reassigned inside a loop at every iteration, which cost three times the
    traversal's own work."""
    while top > 0:
        if top + 3 > sI.shape[0]:
            return _FULL_STACK, top, n_leaf, nw, n_pairs, nf
        if n_leaf == LI.shape[0]:
            return _FULL_LEAVES, top, n_leaf, nw, n_pairs, nf
        if nw == wv.shape[0]:
            return _FULL_WEIGHTS, top, n_leaf, nw, n_pairs, nf
        if order >= 2 and nf == F.shape[1]:
            return _FULL_FAR, top, n_leaf, nw, n_pairs, nf
        top -= 1
        I, J, wid = sI[top], sJ[top], sK[top]
        W = wv[wid]
        n_pairs += 1
        CI = (centre[I, 0], centre[I, 1], centre[I, 2])  # (tuples: no array views in the loop)
        CJ = (centre[J, 0], centre[J, 1], centre[J, 2])
        r2 = 0.0
        for i in range(3):
            xa = R[ba, i, 0] * CI[0] + R[ba, i, 1] * CI[1] + R[ba, i, 2] * CI[2] + t[ba, i]
            xb = R[bb, i, 0] * CJ[0] + R[bb, i, 1] * CJ[1] + R[bb, i, 2] * CJ[2] + t[bb, i]
            dx = xa - xb
            d[i] = dx
            r2 += dx * dx
        r = math.sqrt(r2)
        inv_r = 1.0 / r
        d1 = radius[I] + radius[J]
        width = max(eps_p * d1, min_width)  # the blend band: at least BAND_MARGINS margins wide
        s = (r - d1) / width
        if s <= 0.0:
            phi = phi1 = phi2 = 0.0
        elif s >= 1.0:
            phi, phi1, phi2 = 1.0, 0.0, 0.0
        else:
            iw = 1.0 / width
            phi = s * s * s * (s * (6.0 * s - 15.0) + 10.0)
            phi1 = 30.0 * s * s * (s - 1.0) ** 2 * iw
            phi2 = 60.0 * s * (s - 1.0) * (2.0 * s - 1.0) * iw * iw
        # s <= 0 (spheres overlap): phi = phi' = phi'' = 0, no central term and an unchanged weight, so the
        # distance's derivatives are not needed (most node pairs near contact)
        # far (phi = 1, phi' = phi'' = 0): the term is W P_c(r), whose Hessian is formed from its blocks below,
        # without d2r
        plain = s >= 1.0
        if order >= 1 and s > 0.0:
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
            if order >= 2 and not plain:
                for a in range(lo, hi):  # the upper triangle (the only one read)
                    for c in range(a, hi):
                        d2r[a, c] = (
                            dd[0, a] * dd[0, c] + dd[1, a] * dd[1, c] + dd[2, a] * dd[2, c] - dr[a] * dr[c]
                        ) * inv_r
                for kk in range(3):
                    for ll in range(kk, 3):
                        acc_a = 0.0
                        acc_b = 0.0
                        for i in range(3):
                            ui = d[i] * inv_r
                            for m in range(3):
                                acc_a += ui * d2R[ba, i, m, kk, ll] * CI[m]
                                acc_b += ui * d2R[bb, i, m, kk, ll] * CJ[m]
                        if lo == 0:
                            d2r[3 + kk, 3 + ll] += acc_a
                        if hi == 12:
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
                    grad[p, a] += g * wd1[wid, a] + W * g1 * dr[a]
                if order >= 2:  # the upper triangle (mirrored when the body pair is done)
                    g2 = phi2 * pc + 2.0 * phi1 * pc1 + phi * pc2
                    if plain:
                        _far_row(F, nf, dr, d, inv_r, W * g1, W * g2, CI, CJ)
                        nf += 1
                        if wid != 0:  # an ancestor in the band: the weight's derivatives, summed per entry
                            ws[wid] += g
                            for a in range(lo, hi):
                                wds[wid, a] += g1 * dr[a]
                    # (else: a node pair in the band, 0 < s < 1; its Hessian term is added below, in one pass
                    # with its children's weight's Hessian)
        if s >= 1.0:
            continue
        # inherited weight W (1 - phi) and its derivatives (product rule), a new table entry; unchanged for
        # s <= 0
        if s > 0.0:
            h = 1.0 - phi
            if order >= 2:
                # the central term's Hessian (its upper triangle: mirrored when the body pair is done) and the
                # children's weight's (W (1 - phi)), from the same products; the weight tables' Hessians are
                # read only in their upper triangles
                if wid == 0:  # weight 1, no derivatives (no ancestor in the band): most node pairs
                    for a in range(lo, hi):
                        ga = g2 * dr[a]
                        pa = phi2 * dr[a]
                        for c in range(a, hi):
                            d2 = d2r[a, c]
                            hess[p, a, c] += ga * dr[c] + g1 * d2
                            wd2[nw, a, c] = (
                                h * wd2[wid, a, c]
                                - phi1 * (wd1[wid, a] * dr[c] + dr[a] * wd1[wid, c])
                                - W * (pa * dr[c] + phi1 * d2)
                            )
                else:
                    for a in range(lo, hi):
                        ga = g2 * dr[a]
                        pa = phi2 * dr[a]
                        for c in range(a, hi):
                            d2 = d2r[a, c]
                            cr = wd1[wid, a] * dr[c] + dr[a] * wd1[wid, c]
                            hess[p, a, c] += g * wd2[wid, a, c] + g1 * cr + W * (ga * dr[c] + g1 * d2)
                            wd2[nw, a, c] = h * wd2[wid, a, c] - phi1 * cr - W * (pa * dr[c] + phi1 * d2)
            if order >= 1:
                for a in range(12):
                    wd1[nw, a] = h * wd1[wid, a] - W * phi1 * dr[a]
            wv[nw] = W * h
            if order >= 2:
                ws[nw] = 0.0
                for a in range(12):
                    wds[nw, a] = 0.0
            wid = nw
            nw += 1
        leaf_i = child[I, 0] < 0
        leaf_j = child[J, 0] < 0
        if leaf_i and leaf_j:
            LI[n_leaf], LJ[n_leaf], lp[n_leaf], lwid[n_leaf] = I, J, p, wid
            n_leaf += 1
            continue
        si, sj = _split_rule(leaf_i, leaf_j, radius[I], radius[J], split_both)
        ni = 2 if si else 1
        nj = 2 if sj else 1
        for a in range(ni):
            ci = child[I, a] if si else I
            for b in range(nj):
                cj = child[J, b] if sj else J
                sI[top], sJ[top], sK[top] = ci, cj, wid
                top += 1
    return _DONE, top, n_leaf, nw, n_pairs, nf


@numba.njit(nogil=True, **_JIT)  # (called from several Python threads at once, on disjoint body pairs)
def traverse_nodes(centre, radius, child, pair_body, pair_root, R, dR, d2R, t, mu, eps, min_width, split_both,
                   order, value, grad, hess, hside, stack_cap, table_cap, leaf_cap):  # fmt: skip
    """Accumulate central terms into value (P,), grad (P, 12), hess (P, 12, 12); return the leaf pairs.

    ``hside`` (P,) int64: which of each body pair's Hessian blocks to form (:func:`hessian_span`): 0 all, 1 body
    a's only (coordinates 0..5), 2 body b's only (6..11); the other rows and columns of hess[p] are left as they
    are. Values and gradients are always whole.

    Inherited weights live in a table, not on the stack: entry 0 is the weight 1 (zero derivatives) that every
    node pair starts with, and a node pair in the blend band (0 < s < 1) that descends appends its children's weight
    W (1 - phi) with its gradient and Hessian; stack entries and leaves carry an entry's index. Node pairs whose
    spheres overlap (s <= 0, most of them near contact) pass their parent's index on without copying anything.
    Body pair after body pair is traversed by :func:`_pair_nodes`; ``stack_cap``, ``table_cap`` and ``leaf_cap``
    are the buffers' first sizes (``STACK_CAP``, ``TABLE_CAP``, ``LEAF_CAP``; doubled whenever one is full).

    Returns:
        (LI, LJ, lp, lwid, wv, wd1, wd2, n_leaf, n_pairs): leaf node ids, body pair and weight entry (valid up to
        index n_leaf); the weight table: value (M,), gradient (M, 12) (order >= 1) and Hessian (M, 12, 12)
        (order >= 2) of the inherited weight (1 - phi) prod.
    """
    P = pair_body.shape[0]
    sI = np.empty(stack_cap, np.int64)
    sJ = np.empty(stack_cap, np.int64)
    sK = np.empty(stack_cap, np.int64)
    # (np.empty: an entry is written where it is made, over what is read of it; entry 0 is the weight 1)
    wv = np.empty(table_cap)
    wd1 = np.empty((table_cap if order >= 1 else 1, 12))
    wd2 = np.empty((table_cap if order >= 2 else 1, 12, 12))
    ws = np.empty(table_cap if order >= 2 else 1)
    wds = np.empty((table_cap if order >= 2 else 1, 12))
    wv[0] = 1.0
    wd1[0] = 0.0
    wd2[0] = 0.0
    nw = np.int64(1)
    LI = np.empty(leaf_cap, np.int64)
    LJ = np.empty(leaf_cap, np.int64)
    lp = np.empty(leaf_cap, np.int64)
    lwid = np.empty(leaf_cap, np.int64)
    n_leaf = np.int64(0)
    n_pairs = np.int64(0)
    dd = np.zeros((3, 12))
    dr = np.zeros(12)
    d2r = np.zeros((12, 12))
    d = np.zeros(3)
    for k in range(3):
        dd[k, k] = 1.0
        dd[k, 6 + k] = -1.0
    Z = np.zeros((9, 9))
    Mom = np.zeros(52)
    F = np.empty((_F_ROWS, stack_cap if order >= 2 else 0))  # the far node pairs' factors, one column each
    zact = np.empty(9, np.int64)  # the entries of _far_moments' z that the body pair's Hessian span needs
    for p in range(P):
        ba, bb = pair_body[p, 0], pair_body[p, 1]
        lo, hi = hessian_span(hside[p])
        nz = np.int64(0)
        for a in range(9):
            if (3 <= a < 6 and lo != 0) or (a >= 6 and hi != 12):
                continue
            zact[nz] = a
            nz += 1
        sI[0], sJ[0], sK[0] = pair_root[p, 0], pair_root[p, 1], 0
        top = np.int64(1)
        nf = np.int64(0)
        first = nw  # the weight table entries of this body pair: first..nw-1
        while True:
            status, top, n_leaf, nw, n_pairs, nf = _pair_nodes(
                p, ba, bb, centre, radius, child, R, dR, d2R, t, mu, eps[p], min_width, split_both, order, value,
                grad, hess, lo, hi, sI, sJ, sK, top, LI, LJ, lp, lwid, n_leaf, wv, wd1, wd2, ws, wds, nw, dd, dr,
                d2r, d, F, nf, n_pairs,
            )  # fmt: skip
            if status == _DONE:
                break
            if status == _FULL_FAR:
                G = np.empty((_F_ROWS, 2 * F.shape[1] + 1))
                G[:, :nf] = F[:, :nf]
                F = G
            elif status == _FULL_STACK:
                sI, sJ, sK = _grow(sI), _grow(sJ), _grow(sK)
            elif status == _FULL_LEAVES:
                LI, LJ, lp, lwid = _grow(LI), _grow(LJ), _grow(lp), _grow(lwid)
            else:
                wv = _grow(wv)
                if order >= 1:
                    wd1 = _grow(wd1)
                if order >= 2:
                    wd2 = _grow(wd2)
                    ws = _grow(ws)
                    wds = _grow(wds)
        if order >= 2 and nw > first:
            _expand_inherited(hess, p, wd1, wd2, ws, wds, first, nw, lo, hi)
        if nf:
            _far_moments(F, nf, Z, Mom, zact, nz, lo, hi)
            _far_expand(hess, p, Z, Mom, dR, d2R, ba, bb, lo, hi)
        if order >= 2:  # central terms were accumulated into the upper triangle
            for a in range(lo, hi):
                for c in range(a + 1, hi):
                    hess[p, c, a] = hess[p, a, c]
    return LI, LJ, lp, lwid, wv, wd1, wd2, n_leaf, n_pairs


@numba.njit(**_JIT)
def _plane_separated(A, B, margin) -> bool:
    """Whether every vertex of triangle B lies more than ``margin`` to one side of triangle A's plane (then their
    distance exceeds the margin: a cheap exact rejection before the closest-feature distance). The comparison
    allows 1e-9 of the coordinates' extent for the rounding of the plane (a degenerate A: no rejection)."""
    e1 = (A[1, 0] - A[0, 0], A[1, 1] - A[0, 1], A[1, 2] - A[0, 2])
    e2 = (A[2, 0] - A[0, 0], A[2, 1] - A[0, 1], A[2, 2] - A[0, 2])
    n0 = e1[1] * e2[2] - e1[2] * e2[1]
    n1 = e1[2] * e2[0] - e1[0] * e2[2]
    n2 = e1[0] * e2[1] - e1[1] * e2[0]
    norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not norm > 0.0:
        return False
    lo = math.inf
    hi = -math.inf
    extent = 0.0
    for v in range(3):
        d0, d1, d2 = B[v, 0] - A[0, 0], B[v, 1] - A[0, 1], B[v, 2] - A[0, 2]
        h = (n0 * d0 + n1 * d1 + n2 * d2) / norm
        lo = min(lo, h)
        hi = max(hi, h)
        extent = max(extent, abs(d0) + abs(d1) + abs(d2))
    for v in range(1, 3):
        extent = max(extent, abs(A[v, 0] - A[0, 0]) + abs(A[v, 1] - A[0, 1]) + abs(A[v, 2] - A[0, 2]))
    bound = margin + 1e-9 * extent
    return lo > bound or hi < -bound


@numba.njit(**_JIT)
def _triangles_intersect(A, B) -> bool:
    """Whether an edge of one triangle pierces the other (two intersecting triangles always have one that does,
    unless they are coplanar, when their distance is 0)."""
    for i in range(3):
        j = i + 1 if i < 2 else 0
        if segment_hits_triangle_nb(A[i], A[j], B, 0.0) or segment_hits_triangle_nb(B[i], B[j], A, 0.0):
            return True
    return False


@numba.njit(**_JIT)
def _pair_hits(ba, bb, sa, sb, centre, radius, child, tri, tris, R, t, margin, eps_p, min_width, split_both, sI, sJ,
               top, A, B, q):  # fmt: skip
    """Whether body pair (ba, bb) has a triangle pair within ``margin``: (``_HIT`` or ``_DONE``, top), searched from
    its stack (sI, sJ, ``top`` entries); ``_FULL_STACK`` when the stack is full (the caller grows it and calls again
    with the returned top; the stack is never reassigned here, see :func:`_pair_nodes`)."""
    while top > 0:
        if top + 3 > sI.shape[0]:
            return _FULL_STACK, top
        top -= 1
        I, J = sI[top], sJ[top]
        CI = (centre[I, 0], centre[I, 1], centre[I, 2])  # (tuples: no array views in the loop)
        CJ = (centre[J, 0], centre[J, 1], centre[J, 2])
        r2 = 0.0
        for i in range(3):
            dx = (sa * (R[ba, i, 0] * CI[0] + R[ba, i, 1] * CI[1] + R[ba, i, 2] * CI[2]) + t[ba, i]) - (
                sb * (R[bb, i, 0] * CJ[0] + R[bb, i, 1] * CJ[1] + R[bb, i, 2] * CJ[2]) + t[bb, i]
            )
            r2 += dx * dx
        d1 = sa * radius[I] + sb * radius[J]
        r = math.sqrt(r2)
        if r - d1 >= max(eps_p * d1, min_width):  # the potential's far field: central term only, finite
            continue
        # (a relative slack of 1e-9 covers the rounding of the world centres)
        if r - d1 > margin + 1e-9 * (r + d1):
            continue
        leaf_i = child[I, 0] < 0
        leaf_j = child[J, 0] < 0
        if leaf_i and leaf_j:
            ti, tj = tri[I], tri[J]
            for v in range(3):
                for i in range(3):
                    A[v, i] = (
                        sa
                        * (
                            R[ba, i, 0] * tris[ti, v, 0]
                            + R[ba, i, 1] * tris[ti, v, 1]
                            + R[ba, i, 2] * tris[ti, v, 2]
                        )
                        + t[ba, i]
                    )
                    B[v, i] = (
                        sb
                        * (
                            R[bb, i, 0] * tris[tj, v, 0]
                            + R[bb, i, 1] * tris[tj, v, 1]
                            + R[bb, i, 2] * tris[tj, v, 2]
                        )
                        + t[bb, i]
                    )
            if _plane_separated(A, B, margin) or _plane_separated(B, A, margin):
                continue  # one triangle lies beyond the other's plane by more than the margin (most resting pairs)
            # (the closest-feature distance is positive when an edge pierces the other triangle's interior)
            if not math.sqrt(tri_tri_closest_nb(A, B, q)) > margin or _triangles_intersect(A, B):
                return _HIT, top
            continue
        si, sj = _split_rule(leaf_i, leaf_j, radius[I], radius[J], split_both)  # as the potential's
        for a in range(2 if si else 1):
            ci = child[I, a] if si else I
            for b in range(2 if sj else 1):
                sI[top], sJ[top] = ci, child[J, b] if sj else J
                top += 1
    return _DONE, top


@numba.njit(**_JIT)
def penetrating_pairs(centre, radius, child, tri, tris, pair_body, pair_root, R, t, scale, margin, eps, min_width,
                      split_both, out, stack_cap):  # fmt: skip
    """Mark in ``out`` (P,) int8 the body pairs that have a triangle pair within ``margin`` (or intersecting).

    Exactly the pairs whose BSH potential is +inf: the potential descends every node pair whose spheres overlap,
    and a pair of leaves is infeasible when the triangles' distance is <= margin or they intersect (the plane
    solve's own tests: its start needs the distance, and no plane separates intersecting triangles).
    Here a node pair is descended only where the potential descends it too (s < 1: sphere gap below the band width,
    with the same split rule, so both reach a leaf pair through the same ancestors) and its spheres are within
    ``margin`` of each other (every triangle pair below two spheres farther apart than that is farther apart
    too); a body pair stops at its first hit. No weights, no plane solves: a collision query, for the
    feasibility checks of the simulator's start and paths.
    ``scale`` (Nb,) scales each body about its origin (1: as it is; the simulator's reachability check shrinks the
    moving bodies). ``stack_cap``: the stack's first size (``STACK_CAP``; doubled whenever it is full).
    """
    P = pair_body.shape[0]
    sI = np.empty(stack_cap, np.int64)
    sJ = np.empty(stack_cap, np.int64)
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    q = np.empty(6)
    for p in range(P):
        ba, bb = pair_body[p, 0], pair_body[p, 1]
        sI[0], sJ[0] = pair_root[p, 0], pair_root[p, 1]
        top = np.int64(1)
        while True:
            status, top = _pair_hits(ba, bb, scale[ba], scale[bb], centre, radius, child, tri, tris, R, t, margin,
                                     eps[p], min_width, split_both, sI, sJ, top, A, B, q)  # fmt: skip
            if status != _FULL_STACK:
                break
            sI, sJ = _grow(sI), _grow(sJ)
        out[p] = 1 if status == _HIT else 0


@numba.njit(nogil=True, **_JIT)  # (called from several threads at once, on the leaves of disjoint body pairs)
def accumulate_leaves_lowrank(lp, lwid, wv, wd1, wd2, pv, gx, WT, S, Pl, Xa, Xb, ba, bb, dR, d2R, mu, order, value,
                              grad, hess, hside):  # fmt: skip
    """Add the leaf terms w * P_exact to value/grad/hess of their body pairs, from the leaf Hessians' factors.

    Chain rule to pose space with x_v = R X_v + t: J (18, 12) has identity blocks for the translations and
    dR[..., k] X_v for the rotations; hess_q = J^T hess_x J + sum_v grad_x_v . d2R X_v (rotation blocks). Then the
    product rule with the weight: value w P, grad P dw + w gq, hess P d2w + dw gq^T + gq dw^T + w hq, the leaf's
    weight w, dw, d2w being entry ``lwid`` of the weight table (wv, wd1, wd2) of :func:`traverse_nodes`: w hq is
    added leaf by leaf, the weight derivatives' part once per table entry from the sums of P and gq over its leaves.

    hess_x = mu (D - W W^T) (``_pair_numba.solve_pairs`` with ``lowrank``): D is block diagonal, 2 n n^T / s_v^3
    per vertex v, and W (18, 4). With J_v = [I | A_v] (A_v = dR X_v) the vertex's rows of the (18, 12) pose
    Jacobian, J^T hess_x J = sum_v (2 mu / s_v^3) d_v d_v^T - mu U U^T with d_v = J_v^T n and U = J^T W (12, 4):
    about a fifth of the work of the dense products. The second-order rotation term uses G = sum_v g_v X_v^T per side,
    summed (weighted) over the body pair's leaves and contracted with its d2R once. Only the Hessian blocks of
    ``hside`` (P,) (:func:`traverse_nodes`) are formed.
    """
    L = lp.shape[0]
    A = np.empty((6, 3, 3))
    gq = np.empty(12)
    U = np.empty((12, 4))
    T = 0  # the weight table entries the leaves use
    if order >= 2:
        for e in range(L):
            T = max(T, lwid[e] + 1)
    Ps = np.zeros(T)  # per weight table entry: the sum of its leaves' P ...
    gqs = np.zeros((T, 12))  # ... and of their gq
    entry_pair = np.full(T, -1, np.int64)  # the body pair of each entry with leaves (-1: none)
    dv = np.empty(6)
    touched = np.zeros(hess.shape[0], np.bool_)  # the body pairs whose Hessian rows received a leaf
    G2 = np.zeros((hess.shape[0], 2, 3, 3))  # per body pair and side: sum of w G_s (below)
    sides = np.zeros((hess.shape[0], 2), np.int64)  # each body pair's rows of dR / d2R
    for e in range(L):
        p = lp[e]
        wid = lwid[e]
        w = wv[wid]
        P = pv[e]
        value[p] += w * P
        if order < 1 or not math.isfinite(P):
            continue
        for v in range(6):
            body = ba[e] if v < 3 else bb[e]
            X = Xa[e, v] if v < 3 else Xb[e, v - 3]
            for i in range(3):
                for k in range(3):
                    A[v, i, k] = (
                        dR[body, i, 0, k] * X[0] + dR[body, i, 1, k] * X[1] + dR[body, i, 2, k] * X[2]
                    )
        for c in range(12):
            gq[c] = 0.0
        for v in range(6):
            o = 0 if v < 3 else 6
            for i in range(3):
                gi = gx[e, 3 * v + i]
                gq[o + i] += gi
                for k in range(3):
                    gq[o + 3 + k] += A[v, i, k] * gi
        for c in range(12):
            grad[p, c] += P * wd1[wid, c] + w * gq[c]
        if order < 2:
            continue
        n0, n1, n2 = Pl[e, 0], Pl[e, 1], Pl[e, 2]
        lo, hi = hessian_span(hside[p])
        # w hq straight into the pair's upper triangle (w = 1 for most leaves near contact: no ancestor in the band)
        hl = hess[p]
        wmu = w * mu
        for a in range(lo, hi):
            for m in range(4):
                U[a, m] = 0.0
        for v in range(6):
            o = 0 if v < 3 else 6
            if o < lo or o >= hi:  # a body whose Hessian blocks are not formed
                continue
            sv = S[e, v]
            cv = w * (2.0 * mu / (sv * sv * sv))
            dv[0], dv[1], dv[2] = n0, n1, n2
            for k in range(3):
                dv[3 + k] = A[v, 0, k] * n0 + A[v, 1, k] * n1 + A[v, 2, k] * n2
            for a in range(6):
                for c in range(a, 6):
                    hl[o + a, o + c] += cv * dv[a] * dv[c]
            for m in range(4):
                w0, w1, w2 = WT[e, m, 3 * v], WT[e, m, 3 * v + 1], WT[e, m, 3 * v + 2]
                U[o, m] += w0
                U[o + 1, m] += w1
                U[o + 2, m] += w2
                for k in range(3):
                    U[o + 3 + k, m] += A[v, 0, k] * w0 + A[v, 1, k] * w1 + A[v, 2, k] * w2
        for a in range(lo, hi):
            for c in range(a, hi):
                acc = U[a, 0] * U[c, 0] + U[a, 1] * U[c, 1] + U[a, 2] * U[c, 2] + U[a, 3] * U[c, 3]
                hl[a, c] -= wmu * acc
        # the second-order rotation terms: the body pair's d2R are shared by its leaves, so only w G_s,
        # G_s = sum_v g_v X_v^T (3 x 3) per side, is summed here and contracted once per pair below
        sides[p, 0], sides[p, 1] = ba[e], bb[e]
        for side in range(2):
            if 6 * side < lo or 6 * side >= hi:
                continue
            for i in range(3):
                for m in range(3):
                    acc = 0.0
                    for v in range(3 * side, 3 * side + 3):
                        X = Xa[e, v] if side == 0 else Xb[e, v - 3]
                        acc += gx[e, 3 * v + i] * X[m]
                    G2[p, side, i, m] += w * acc
        if wid != 0:
            Ps[wid] += P
            for a in range(12):
                gqs[wid, a] += gq[a]
            entry_pair[wid] = p
        touched[p] = True
    for k in range(T):  # P d2w + dw gq^T + gq dw^T, summed over each entry's leaves (upper triangles)
        p = entry_pair[k]
        if p >= 0:
            lo, hi = hessian_span(hside[p])
            _add_entry_terms(hess, p, wd1, wd2, k, Ps[k], gqs[k], lo, hi)
    if order >= 2:  # the rotation terms; the leaf terms were added to the upper triangles: mirror them
        for p in range(hess.shape[0]):
            if touched[p]:
                lo, hi = hessian_span(hside[p])
                for side in range(2):
                    if lo <= 6 * side < hi:
                        add_rotation_terms(
                            hess, p, 3 if side == 0 else 9, G2[p, side], d2R, sides[p, side], 1.0
                        )
                for a in range(lo, hi):
                    for c in range(a + 1, hi):
                        hess[p, c, a] = hess[p, a, c]


@numba.njit(nogil=True, **_JIT)  # (called from several threads at once)
def leaf_inputs(tris, tri, LI, LJ, lp, pair_body, R, t, ids, wkeys, wplanes, M):
    """The inputs of L leaf pairs' plane solves, in one pass.

    Leaf pair l joins node LI[l] of body pair lp[l]'s body a and node LJ[l] of its body b (rows pair_body[lp] of
    the rotations R (2 P, 3, 3) and translations t (2 P, 3)). Returns the body-frame triangles Xa, Xb (L, 3, 3)
    (``tris[tri[node]]``), the six vertices X (L, 6, 3) at the poses (R X + t) and, where ``ids`` (P,) is not empty,
    each leaf pair's warm-start key (ids[lp] M + LI) M + LJ (L,) with the plane (L, 4) stored under that key in
    ``wkeys`` (W,) sorted / ``wplanes`` (W, 4), and whether there is one (L,) int8."""
    L = LI.shape[0]
    Xa = np.empty((L, 3, 3))
    Xb = np.empty((L, 3, 3))
    X = np.empty((L, 6, 3))
    warm = ids.shape[0] > 0
    keys = np.empty(L if warm else 0, dtype=np.int64)
    P0 = np.zeros((L if warm else 0, 4))
    has0 = np.zeros(L if warm else 0, dtype=np.int8)
    W = wkeys.shape[0]
    for l in range(L):
        p = lp[l]
        for side in range(2):
            b = pair_body[p, side]
            T = tris[tri[LI[l]]] if side == 0 else tris[tri[LJ[l]]]
            for v in range(3):
                x0, x1, x2 = T[v, 0], T[v, 1], T[v, 2]
                if side == 0:
                    Xa[l, v, 0], Xa[l, v, 1], Xa[l, v, 2] = x0, x1, x2
                else:
                    Xb[l, v, 0], Xb[l, v, 1], Xb[l, v, 2] = x0, x1, x2
                for i in range(3):
                    X[l, 3 * side + v, i] = R[b, i, 0] * x0 + R[b, i, 1] * x1 + R[b, i, 2] * x2 + t[b, i]
        if warm:
            k = (ids[p] * M + LI[l]) * M + LJ[l]
            keys[l] = k
            lo, hi = 0, W
            while lo < hi:  # the first stored key >= k
                mid = (lo + hi) // 2
                if wkeys[mid] < k:
                    lo = mid + 1
                else:
                    hi = mid
            if lo < W and wkeys[lo] == k:
                has0[l] = 1
                for i in range(4):
                    P0[l, i] = wplanes[lo, i]
    return Xa, Xb, X, keys, P0, has0


@numba.njit(nogil=True, **_JIT)  # (called from several threads at once)
def warm_table(keys, value, plane, centre):
    """The warm-start table of solved leaf pairs: the keys (K,) of those with a finite value, sorted, and their
    planes (K, 4) moved from frames centred at ``centre`` (L, 3) to the frame of the solve's input (n, d - n.c)."""
    idx = np.nonzero(np.isfinite(value))[0]
    order = idx[np.argsort(keys[idx], kind="mergesort")]
    K = order.shape[0]
    out_k = np.empty(K, dtype=np.int64)
    out_p = np.empty((K, 4))
    for m in range(K):
        l = order[m]
        out_k[m] = keys[l]
        n0, n1, n2 = plane[l, 0], plane[l, 1], plane[l, 2]
        out_p[m, 0], out_p[m, 1], out_p[m, 2] = n0, n1, n2
        out_p[m, 3] = plane[l, 3] - (n0 * centre[l, 0] + n1 * centre[l, 1] + n2 * centre[l, 2])
    return out_k, out_p


@numba.njit(nogil=True, **_JIT)
def warm_merge(new_keys, new_planes, old_keys, old_planes):
    """Two warm-start tables (sorted distinct keys (W,), planes (W, 4)) merged into one, sorted, where a key in
    both keeps the new plane."""
    n, m = new_keys.shape[0], old_keys.shape[0]
    keys = np.empty(n + m, dtype=np.int64)
    planes = np.empty((n + m, 4))
    i = j = k = 0
    while i < n or j < m:
        if j == m or (i < n and new_keys[i] <= old_keys[j]):
            if j < m and new_keys[i] == old_keys[j]:
                j += 1  # the old entry of the same key is dropped
            keys[k] = new_keys[i]
            for c in range(4):
                planes[k, c] = new_planes[i, c]
            i += 1
        else:
            keys[k] = old_keys[j]
            for c in range(4):
                planes[k, c] = old_planes[j, c]
            j += 1
        k += 1
    return keys[:k], planes[:k]
