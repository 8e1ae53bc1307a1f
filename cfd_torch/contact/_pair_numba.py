"""Fused CPU kernel of the exact pair potential: start, damped Newton and closed-form derivatives in one pass.

One numba ``prange`` loop over chunks of pairs; each pair runs its own Levenberg-Marquardt iterations on the
4-vector p = (n, d) with a closed-form 4x4 Cholesky, so converged pairs cost nothing more and nothing is
allocated per pair. The maths is the one in ``pair_potential.py`` (module docstring); ``_pair_torch.py`` holds the
same solve as batched tensor code for other devices, and the tests check that the two agree.

Status codes written per pair: 0 converged, 1 infeasible (within the margin or intersecting: value +inf),
2 not converged within ``max_iter`` (the caller raises).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .._geometry import tri_tri_closest_nb

CONVERGED, INFEASIBLE, NOT_CONVERGED = 0, 1, 2

# error_model="numpy": IEEE division (1/0 = inf) without Python's per-division zero checks. No fastmath: no-NaN/no-inf
# assumptions would break the +inf barrier, and with FMA contraction and reciprocal multiplication the kernels
# compiled in a process rounded otherwise than the same kernels loaded from numba's cache (a fresh clone's first run
# was not reproduced by later ones); without them the two agree bit for bit, at the same speed.
_JIT = {"cache": True, "error_model": "numpy", "fastmath": False}
# The small helpers are inlined into numba's IR; the large ones (_eval, _refine, _eig4, _rotated_epp,
# _contact_frame) are plain calls that LLVM may inline: inlining those into the IR too made the pair solve take 44 s to
# compile instead of 18 s, for the same speed and bit-identical results.
_JIT_INLINE = {**_JIT, "inline": "always"}

_STALL_TOL = 1e-8  # a pair whose relative gradient is below this is done when no step can decrease E any more
_EPS_RES = 16 * 2.220446049250313e-16  # rounding of E, relative to the magnitudes it is computed from
_GRAD_EPS = 16 * 2.220446049250313e-16  # rounding noise of a gradient component, relative to its scale sc
_MARGIN_RES = (
    64 * 2.220446049250313e-16
)  # a closest distance and the start gaps formed from it: their rounding, relative to the coordinates
_WARM_ITER = 30  # iterations a warm-started solve gets before the cold start is tried
# E_pp with a Cholesky pivot below this fraction of its largest diagonal entry (condition ~1e8 and more: parallel
# edges, coplanar pairs, a vertex on a vertex, near the margin) is re-formed in its own eigenbasis for the Hessian
# (``_rotated_epp``); below it, the plain one loses at most ~1e-8 of the Schur complement to rounding
_ROT_COND = 1e-8
_REFINE_STEPS = 8  # eigenbasis Newton steps after convergence of an ill-conditioned pair (``_refine``)
_REFINE_HALVINGS = 20  # backtracking halvings of one such step
# ... for pairs whose gaps cancel more than this (``_conditioning``): below it the plain solve's derivatives are
# within a few eps kappa already (scripts/stress.py: 2.1 eps kappa at kappa 1e3-1e7)
_REFINE_KAPPA = 1e6


@numba.njit(**_JIT)
def _eval(X, p, half_delta, lam, g, H, sc, s):
    """E at p with its gradient g (4), Hessian H (4, 4), per-component scales sc (9) and gaps s (6).

    sc[:4] is each gradient component's rounding-noise scale (the magnitudes it is summed from, amplified by the
    cancellation in the gaps), sc[4:8] the plain sum of those magnitudes, what the convergence test measures the
    gradient against (near the margin the amplification reaches 2 (|n.x| + |d|) / s, and a test against it would
    stop with the plane, and the derivatives, off by that factor times the tolerance). sc[8] is the Newton
    decrement g^T H^-1 g that the gaps' own rounding gives, 2 sum_k (16 eps mag_k)^2 / s_k^3 (mag_k = |n.x_k| +
    |d| + delta/2 termwise): the gradient's noise from gap k is a multiple of abar_k, and H >= 2 abar_k abar_k^T /
    s_k^3, so its H^-1-norm is at most that. (A bound from the componentwise scales sc[:4] instead counts that
    noise in the directions where H is weak too, and near the margin it exceeded the true decrement by up to
    1e16: the solve stopped with the plane far from its optimum.)

    Returns (E, e_res): E = +inf outside the feasible set (g, H, sc then undefined), and the rounding resolution
    of E, sum_k eps (|n.x_k| + |d| + delta/2) / s_k^2 (each gap is a difference of terms of that size) plus the
    resolution of the sum itself."""
    n0, n1, n2, d = p[0], p[1], p[2], p[3]
    r = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not r < 1.0:
        return math.inf, 0.0
    for k in range(6):
        sg = 1.0 if k < 3 else -1.0
        sk = sg * (n0 * X[k, 0] + n1 * X[k, 1] + n2 * X[k, 2] + d) - half_delta
        if not sk > 0.0:
            return math.inf, 0.0
        s[k] = sk
    inv_r = 1.0 / r
    u0, u1, u2 = n0 * inv_r, n1 * inv_r, n2 * inv_r
    om = 1.0 - r
    inv_om = 1.0 / om
    gl = lam * inv_om * inv_om
    g0, g1, g2, g3 = gl * u0, gl * u1, gl * u2, 0.0
    sc0, sc1, sc2, sc3 = abs(g0), abs(g1), abs(g2), 0.0
    sp0, sp1, sp2, sp3 = sc0, sc1, sc2, 0.0
    # lambda Hn = lambda [2/(1-r)^3 u u^T + (I - u u^T) / ((1-r)^2 r)]
    c2 = gl * inv_r
    c12 = 2.0 * gl * inv_om - c2
    h00, h01, h02 = c12 * u0 * u0 + c2, c12 * u0 * u1, c12 * u0 * u2
    h11, h12, h22 = c12 * u1 * u1 + c2, c12 * u1 * u2, c12 * u2 * u2 + c2
    h03 = h13 = h23 = h33 = 0.0
    e = lam * inv_om
    e_res = e
    gn2 = 0.0
    for k in range(6):
        sg = 1.0 if k < 3 else -1.0
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        sk = s[k]
        inv = 1.0 / sk
        e += inv
        w1 = inv * inv
        w2 = 2.0 * w1 * inv
        # abar = sg [x; 1]; grad -= abar / s^2; hess += 2 abar abar^T / s^3 (sg^2 = 1).
        # sc: rounding-noise scale of each gradient component; s_k carries an absolute rounding error of about
        # eps (|n.x_k| + |d|), amplified in 1/s^2 by 2 (|n.x_k| + |d|) / s_k.
        mag = abs(n0 * x0) + abs(n1 * x1) + abs(n2 * x2) + abs(d) + half_delta
        e_res += mag * w1
        gn2 += mag * mag * w1 * inv
        sw = sg * w1
        aw = abs(w1) * (1.0 + 2.0 * mag * inv)
        g0 -= sw * x0
        g1 -= sw * x1
        g2 -= sw * x2
        g3 -= sw
        sc0 += aw * abs(x0)
        sc1 += aw * abs(x1)
        sc2 += aw * abs(x2)
        sc3 += aw
        sp0 += w1 * abs(x0)
        sp1 += w1 * abs(x1)
        sp2 += w1 * abs(x2)
        sp3 += w1
        wx0, wx1, wx2 = w2 * x0, w2 * x1, w2 * x2
        h00 += wx0 * x0
        h01 += wx0 * x1
        h02 += wx0 * x2
        h03 += wx0
        h11 += wx1 * x1
        h12 += wx1 * x2
        h13 += wx1
        h22 += wx2 * x2
        h23 += wx2
        h33 += w2
    g[0], g[1], g[2], g[3] = g0, g1, g2, g3
    sc[0], sc[1], sc[2], sc[3] = sc0, sc1, sc2, sc3
    sc[4], sc[5], sc[6], sc[7] = sp0, sp1, sp2, sp3
    sc[8] = 2.0 * _GRAD_EPS * _GRAD_EPS * gn2
    H[0, 0], H[0, 1], H[0, 2], H[0, 3] = h00, h01, h02, h03
    H[1, 0], H[1, 1], H[1, 2], H[1, 3] = h01, h11, h12, h13
    H[2, 0], H[2, 1], H[2, 2], H[2, 3] = h02, h12, h22, h23
    H[3, 0], H[3, 1], H[3, 2], H[3, 3] = h03, h13, h23, h33
    return e, _EPS_RES * e_res


@numba.njit(**_JIT_INLINE)
def _frame(X, c, Xc):
    """c (3) = ``_geometry.frame_origin`` of the pair X (6, 3) (its centroid rounded to a multiple of the power of
    two above its extent) and Xc = X - c, exact."""
    extent = 0.0
    for j in range(3):
        m = 0.0
        for v in range(6):
            m += X[v, j]
        m /= 6.0
        for v in range(6):
            extent = max(extent, abs(X[v, j] - m))
        c[j] = m
    g = math.ldexp(1.0, math.frexp(extent)[1])
    for j in range(3):
        c[j] = math.floor(c[j] / g + 0.5) * g
        for v in range(6):
            Xc[v, j] = X[v, j] - c[j]


@numba.njit(**_JIT)
def _eig4(A, V):
    """Eigenvectors of the symmetric A (4, 4) into the columns of V (cyclic Jacobi; A is overwritten)."""
    for i in range(4):
        for j in range(4):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(12):
        off = 0.0
        dia = 0.0
        for i in range(4):
            dia += A[i, i] * A[i, i]
            for j in range(i + 1, 4):
                off += A[i, j] * A[i, j]
        if not off > 1e-40 * dia:
            break
        for a in range(3):
            for b in range(a + 1, 4):
                apq = A[a, b]
                if apq == 0.0:
                    continue
                theta = (A[b, b] - A[a, a]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(4):  # A <- A J (columns a, b)
                    akp, akq = A[k, a], A[k, b]
                    A[k, a] = c * akp - sn * akq
                    A[k, b] = sn * akp + c * akq
                for k in range(4):  # A <- J^T A (rows a, b)
                    apk, aqk = A[a, k], A[b, k]
                    A[a, k] = c * apk - sn * aqk
                    A[b, k] = sn * apk + c * aqk
                for k in range(4):
                    vkp, vkq = V[k, a], V[k, b]
                    V[k, a] = c * vkp - sn * vkq
                    V[k, b] = sn * vkp + c * vkq


@numba.njit(**_JIT)
def _rotated_epp(Xo, s, p, lam, H, Q, B, Hq):
    """Q (4, 4) = eigenvectors of E_pp = H; B (6, 4) = Q^T [x_k; 1]; Hq = Q^T E_pp Q formed from B (its entries
    sum_k 2 B_ka B_kb / s_k^3 plus the regulariser's, rotated).

    E_pp's weak directions (the plane's tilt about a contact line or point, held by the far vertices and the
    regulariser) are combinations of its entries that cancel to 1e-20 of them and less near the margin: in
    (n, d) coordinates they round to nothing (or to an indefinite matrix), and the Hessian's Schur complement,
    whose largest terms are 1 / (s^4 times such an eigenvalue), comes out off by 1e-3 to 1. In the eigenbasis
    (accurate to eps in angle: the weak subspace is orthogonal to the stiff one) each entry is a sum of squares of
    the vertices' own components B_ka, which keep their digits."""
    for i in range(4):
        for j in range(4):
            Hq[i, j] = H[i, j]
    _eig4(Hq, Q)
    for k in range(6):
        for a in range(4):
            B[k, a] = Q[0, a] * Xo[k, 0] + Q[1, a] * Xo[k, 1] + Q[2, a] * Xo[k, 2] + Q[3, a]
    r = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    om = 1.0 - r
    gl = lam / (om * om)
    c2 = gl / r
    c12 = 2.0 * gl / om - c2
    for a in range(4):
        ua = (Q[0, a] * p[0] + Q[1, a] * p[1] + Q[2, a] * p[2]) / r  # (Q3^T u)_a
        for b in range(a, 4):
            ub = (Q[0, b] * p[0] + Q[1, b] * p[1] + Q[2, b] * p[2]) / r
            acc = c12 * ua * ub + c2 * (Q[0, a] * Q[0, b] + Q[1, a] * Q[1, b] + Q[2, a] * Q[2, b])
            for k in range(6):
                acc += 2.0 * B[k, a] * B[k, b] / (s[k] * s[k] * s[k])
            Hq[a, b] = acc
            Hq[b, a] = acc


@numba.njit(**_JIT_INLINE)
def _conditioning(Xo, p, s):
    """max_k |n| |x_k| / s_k (contact frame): how far a tilt of the plane by an ulp moves gap k, relative to the
    gap; about the problem's kappa = (size + gap) / (gap - margin)."""
    r = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    c = 0.0
    for k in range(6):
        c = max(c, r * math.sqrt(Xo[k, 0] * Xo[k, 0] + Xo[k, 1] * Xo[k, 1] + Xo[k, 2] * Xo[k, 2]) / s[k])
    return c


@numba.njit(**_JIT_INLINE)
def _ill_conditioned(H, L, Li):
    """Whether E_pp = H has a Cholesky pivot below _ROT_COND of its largest diagonal entry (or none); L, Li are
    overwritten with its factor."""
    if not _cholesky4(H, L, Li, 0.0):
        return True
    dmax = max(max(H[0, 0], H[1, 1]), max(H[2, 2], H[3, 3]))
    pmin = min(min(L[0, 0], L[1, 1]), min(L[2, 2], L[3, 3]))
    return pmin * pmin < _ROT_COND * dmax


@numba.njit(**_JIT_INLINE)
def _take(p, g, H, sc, s, p2, g2, H2, sc2, s2):
    """The trial's plane, derivatives, scales and gaps (p2, ...) copied into the current ones (p, ...): copied, not
    swapped, since numba reference-counts array variables reassigned in a loop at every iteration."""
    for i in range(4):
        p[i], g[i] = p2[i], g2[i]
        for j in range(4):
            H[i, j] = H2[i, j]
    for i in range(9):
        sc[i] = sc2[i]
    for i in range(6):
        s[i] = s2[i]


@numba.njit(**_JIT)
def _refine(Xo, p, half_delta, lam, e, e_res, g, H, sc, s, p2, g2, H2, sc2, s2, Q, B, Hq, L, Li, m, step):
    """Newton steps in E_pp's eigenbasis from a converged plane p of an ill-conditioned pair (``_rotated_epp``);
    returns the refined (e, e_res), with p, g, H, sc, s at the refined plane.

    In (n, d) coordinates the gradient's component along E_pp's weak directions is a difference of terms
    x_k / s_k^2 that cancel to far below their rounding, so the solve stops with the plane off along them: for
    parallel edges or coplanar triangles of 10 km at a few um that left the derivatives 300-14,000 eps kappa off
    (kappa = (size + gap) / (gap - margin), how much the input's rounding moves them). Projected on the eigenbasis
    from B = Q^T [x_k; 1], whose weak components keep their digits, the gradient is accurate there, and one to
    three such steps (at most _REFINE_STEPS, each backtracked until E does not rise beyond its rounding) bring
    the derivatives to about eps kappa."""
    for _it in range(_REFINE_STEPS):
        _rotated_epp(Xo, s, p, lam, H, Q, B, Hq)
        r = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        gl = lam / ((1.0 - r) * (1.0 - r) * r)
        for a in range(4):  # Q^T grad E, the regulariser's part plus - sum_k sg_k B_ka / s_k^2
            acc = gl * (Q[0, a] * p[0] + Q[1, a] * p[1] + Q[2, a] * p[2])
            for k in range(6):
                sg = 1.0 if k < 3 else -1.0
                acc -= sg * B[k, a] / (s[k] * s[k])
            m[a] = -acc
        shift = 0.0
        factored = _cholesky4(Hq, L, Li, shift)
        while not factored and shift < 1.0:
            shift = 16 * 2.220446049250313e-16 if shift == 0.0 else shift * 16.0
            factored = _cholesky4(Hq, L, Li, shift)
        if not factored:
            break
        _chol_solve4(L, Li, m, step)  # in the eigenbasis
        big = 0.0
        for i in range(4):  # the step in (n, d), into m
            m[i] = Q[i, 0] * step[0] + Q[i, 1] * step[1] + Q[i, 2] * step[2] + Q[i, 3] * step[3]
            big = max(big, abs(m[i]))
        if not big > 4 * 2.220446049250313e-16 * r:  # the normal's direction is resolved to an ulp
            break
        t = 1.0
        ok = False
        for _half in range(
            _REFINE_HALVINGS
        ):  # backtrack to a feasible plane whose E stays within its rounding
            for i in range(4):
                p2[i] = p[i] + t * m[i]
            e_new, e_res_new = _eval(Xo, p2, half_delta, lam, g2, H2, sc2, s2)
            if e_new <= e + e_res:
                ok = True
                break
            t *= 0.5
        if not ok:
            break
        _take(p, g, H, sc, s, p2, g2, H2, sc2, s2)
        e, e_res = e_new, e_res_new
    return e, e_res


@numba.njit(**_JIT)
def _contact_frame(Xc, p, half_delta, o, Xo):
    """o (3) = the vertices of Xc (6, 3) averaged with weights (min_j |s_j| / |s_k|)^3 (the gaps' weights in E_pp,
    2 / s_k^3, normalised) at the plane p, a point in the contact region; Xo = Xc - o, and p (4) moved to the frame
    at o (d + n.o).

    The solve and the derivatives are formed there: a gap n.x + d of a pair in contact at a distance R from the
    origin is a difference of terms of size R (absolute rounding eps R, which near the margin was 1e3-1e4 times the
    rounding of the contact's own geometry), and E_pp's entries x x^T / s^3 are then R^2 / s^3, which buries the
    plane's tilt about the contact (set by the far vertices and the regulariser) in their rounding. o need not be
    exact: Xc - o rounds to eps |Xc - o|, a backward error of an ulp of the geometry; ``_pair_torch.contact_frame``
    is the same."""
    m = math.inf
    for k in range(6):
        sg = 1.0 if k < 3 else -1.0
        sk = abs(sg * (p[0] * Xc[k, 0] + p[1] * Xc[k, 1] + p[2] * Xc[k, 2] + p[3]) - half_delta)
        Xo[k, 0] = sk  # (scratch)
        m = min(m, sk)
    wsum = 0.0
    o0 = o1 = o2 = 0.0
    for k in range(6):
        a = Xo[k, 0]
        w = 1.0 if a <= m else (m / a) ** 3
        wsum += w
        o0 += w * Xc[k, 0]
        o1 += w * Xc[k, 1]
        o2 += w * Xc[k, 2]
    o[0], o[1], o[2] = o0 / wsum, o1 / wsum, o2 / wsum
    if not (math.isfinite(o[0]) and math.isfinite(o[1]) and math.isfinite(o[2])):
        o[0] = o[1] = o[2] = 0.0
    for k in range(6):
        for j in range(3):
            Xo[k, j] = Xc[k, j] - o[j]
    p[3] += p[0] * o[0] + p[1] * o[1] + p[2] * o[2]


# Dekker's splitter for float64 (2^27 + 1): x = hi + lo exactly, each half with at most 26 significant bits
_SPLIT = 134217729.0


@numba.njit(cache=True, error_model="numpy")
def _two_prod(a, b):
    """a b = p + e exactly (Dekker's product; no FMA contraction here: the error term must be rounded as
    written)."""
    t = _SPLIT * a
    ah = t - (t - a)
    al = a - ah
    t = _SPLIT * b
    bh = t - (t - b)
    bl = b - bh
    p = a * b
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@numba.njit(cache=True, error_model="numpy")
def _dot2(a, b, c, d):
    """a b - c d to about an ulp of the result, however much the two products cancel."""
    p, ep = _two_prod(a, b)
    q, eq = _two_prod(c, d)
    return (p - q) + (ep - eq)


@numba.njit(cache=True, error_model="numpy")
def _cross2(ax, ay, az, bx, by, bz):
    """a x b, each component to about an ulp of itself (nearly parallel a and b included)."""
    return _dot2(ay, bz, az, by), _dot2(az, bx, ax, bz), _dot2(ax, by, ay, bx)


@numba.njit(cache=True, error_model="numpy")
def _sat_start(X, delta, p):
    """The mid-gap plane along the separating axis with the largest separation, scaled like the closest-point
    start; returns that separation. Axes (26): the triangles' normals, the 9 cross products of their edges, the 6
    in-plane edge normals (which separate coplanar triangles) and, for each edge of a and vertex of b, the
    perpendicular from the edge's line to the vertex (the separating axis of parallel edges, whose cross product
    is rounding). Cross products are formed to an ulp of their components, so nearly parallel edges keep their
    common perpendicular. Computed from projections of the vertices, the plane keeps its digits where the closest
    points' difference does not (large triangles a few margins apart: the closest-point direction, a difference of
    two nearly equal points, tilts the plane by more than the gap)."""
    best = -math.inf
    for c in range(26):
        if c < 2:  # face normals
            o = 3 * c
            ax, ay, az = X[o + 1, 0] - X[o, 0], X[o + 1, 1] - X[o, 1], X[o + 1, 2] - X[o, 2]
            bx, by, bz = X[o + 2, 0] - X[o, 0], X[o + 2, 1] - X[o, 1], X[o + 2, 2] - X[o, 2]
        elif (
            11 <= c < 17
        ):  # a face normal x one of its edges: the in-plane axes that separate coplanar triangles
            o, i = 3 * ((c - 11) // 3), (c - 11) % 3
            px, py, pz = X[o + 1, 0] - X[o, 0], X[o + 1, 1] - X[o, 1], X[o + 1, 2] - X[o, 2]
            qx, qy, qz = X[o + 2, 0] - X[o, 0], X[o + 2, 1] - X[o, 1], X[o + 2, 2] - X[o, 2]
            ax, ay, az = _cross2(px, py, pz, qx, qy, qz)  # the face's normal
            j = o + (i + 1) % 3
            bx, by, bz = X[j, 0] - X[o + i, 0], X[j, 1] - X[o + i, 1], X[j, 2] - X[o + i, 2]
        else:  # edge i of a with edge j of b (2..10), or with vertex j of b (17..25)
            i, j = ((c - 2) // 3, (c - 2) % 3) if c < 11 else ((c - 17) // 3, (c - 17) % 3)
            ax, ay, az = (
                X[(i + 1) % 3, 0] - X[i, 0],
                X[(i + 1) % 3, 1] - X[i, 1],
                X[(i + 1) % 3, 2] - X[i, 2],
            )
            if c < 11:
                bx = X[3 + (j + 1) % 3, 0] - X[3 + j, 0]
                by = X[3 + (j + 1) % 3, 1] - X[3 + j, 1]
                bz = X[3 + (j + 1) % 3, 2] - X[3 + j, 2]
            else:  # edge x (vertex - edge start) x edge: the vertex's offset perpendicular to the edge
                wx, wy, wz = X[3 + j, 0] - X[i, 0], X[3 + j, 1] - X[i, 1], X[3 + j, 2] - X[i, 2]
                vx, vy, vz = _cross2(wx, wy, wz, ax, ay, az)
                ax, ay, az, bx, by, bz = vx, vy, vz, ax, ay, az
        ux, uy, uz = _cross2(ax, ay, az, bx, by, bz)
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        if not norm > 0.0:
            continue
        ux, uy, uz = ux / norm, uy / norm, uz / norm
        amin, amax, bmin, bmax = math.inf, -math.inf, math.inf, -math.inf
        for k in range(6):
            t = ux * X[k, 0] + uy * X[k, 1] + uz * X[k, 2]
            if k < 3:
                amin, amax = min(amin, t), max(amax, t)
            else:
                bmin, bmax = min(bmin, t), max(bmax, t)
        sep, sgn, mid = amin - bmax, 1.0, 0.5 * (amin + bmax)  # a on the positive side
        if bmin - amax > sep:
            sep, sgn, mid = bmin - amax, -1.0, 0.5 * (bmin + amax)
        if sep > best:
            best = sep
            alpha = sgn * (0.5 * delta + 1.0) / (0.5 * sep + 1.0)
            p[0], p[1], p[2] = alpha * ux, alpha * uy, alpha * uz
            p[3] = -alpha * mid
    return best


@numba.njit(**_JIT_INLINE)
def _clear_of_margin(dist, delta, Xc):
    """Whether the pair's closest distance exceeds the margin by more than its rounding (``_MARGIN_RES`` of the
    coordinates' magnitude; ``_pair_torch.clear_of_margin``): closer pairs are infeasible (no resolvable minimum)."""
    scale = delta
    for v in range(6):
        for c in range(3):
            scale = max(scale, abs(Xc[v, c]))
    return dist - delta > _MARGIN_RES * scale


@numba.njit(**_JIT_INLINE)
def _rel_grad(g, sc):
    """max_i |g_i| / sc_i, the relative gradient (an exactly zero component with zero scale counts as 0)."""
    rel = 0.0
    for i in range(4):
        r_i = abs(g[i]) / sc[i] if sc[i] > 0.0 else 0.0
        if r_i > rel:
            rel = r_i
    return rel


@numba.njit(**_JIT_INLINE)
def _cholesky4(A, L, Li, damp):
    """L L^T = A + damp diag(A), Li = 1 / diag(L); returns False if not positive definite."""
    for j in range(4):
        acc = A[j, j] * (1.0 + damp)
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:
            return False
        ljj = math.sqrt(acc)
        L[j, j] = ljj
        inv = 1.0 / ljj
        Li[j] = inv
        for i in range(j + 1, 4):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc * inv
        for i in range(j):
            L[i, j] = 0.0
    return True


@numba.njit(**_JIT_INLINE)
def _chol_solve4(L, Li, b, x):
    """x = (L L^T)^-1 b."""
    for i in range(4):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc * Li[i]
    for i in range(3, -1, -1):
        acc = x[i]
        for k in range(i + 1, 4):
            acc -= L[k, i] * x[k]
        x[i] = acc * Li[i]


@numba.njit(parallel=True, **_JIT)
def solve_pairs(X, C, mu, delta, lam, tol, max_iter, want_grad, want_hess, P, val, grad, hess, status, resid,
                lowrank, WTo, So, P0, has0, O):  # fmt: skip
    """Solve K pair problems and write their value / plane / derivatives in place.

    Each pair is moved to the frame centred at its C[k] (``_geometry.frame_origin``, computed here: x - C[k] is
    exact), so the gaps n.x + d carry no cancellation against a large offset and the result does not depend on
    where the pair is, and then solved in its contact frame at C[k] + O[k] (``_contact_frame``: about a point of
    the contact, the gaps of a pair near the margin keep the digits of the contact's own geometry). Output planes
    are in the contact frame; the derivatives in x do not depend on the frame.

    Args:
        X: (K, 6, 3) float64 vertices a0, a1, a2, b0, b1, b2.
        C: (K, 3) out: the frame origin of each pair.
        mu, delta, lam: contact coefficient, margin, normal-regulariser weight.
        tol: relative gradient tolerance: max_i |dE/dp_i| / (sum of |terms| of dE/dp_i) <= tol.
        max_iter: Newton iteration cap.
        want_grad, want_hess: whether to fill ``grad`` (K, 18) and ``hess`` (K, 18, 18).
        P: (K, 4) out: optimal plane (n, d) in the pair's contact frame; val: (K,) out: mu E(p*) or +inf;
        status: (K,) int8 out; resid: (K,) out: final relative gradient.
        lowrank: with ``want_hess``, write the Hessian's factors instead of ``hess``: hess = mu (D - W W^T) with
            W^T = L^-1 E_px into ``WTo`` (K, 4, 18) (E_pp = L L^T) and the vertex gaps s_k into ``So`` (K, 6)
            (D is block diagonal, 2 n n^T / s_k^3, n = P[:, :3]); zeros where infeasible.
        P0, has0: (K, 4) planes (in the input's frame) to start from where has0 (K,) is set (a warm start, e.g.
            the pair's optimum at nearby vertices) and the plane is strictly feasible; the closest-point start
            otherwise. Empty (0, 4) and (0,) for none. The optimum does not depend on the start (to the tolerance).
        O: (K, 3) out: the contact frame's origin (``_contact_frame``) relative to C[k], where the pair was solved
            and its derivatives formed (arbitrary where infeasible).
    """
    K = X.shape[0]
    nchunks = min(K, 256)
    for c in numba.prange(nchunks):
        _solve_range(c * K // nchunks, (c + 1) * K // nchunks, X, C, mu, delta, lam, tol, max_iter, want_grad,
                     want_hess, P, val, grad, hess, status, resid, lowrank, WTo, So, P0, has0, O)  # fmt: skip


@numba.njit(nogil=True, **_JIT)  # (called from several threads at once)
def solve_pairs_serial(X, C, mu, delta, lam, tol, max_iter, want_grad, want_hess, P, val, grad, hess, status, resid,
                       lowrank, WTo, So, P0, has0, O):  # fmt: skip
    """:func:`solve_pairs` on the calling thread (the same results)."""
    # lo as int64, not the literal 0: the parallel kernel's specialisation of _solve_range, not a second ~40 s compile
    _solve_range(np.int64(0), X.shape[0], X, C, mu, delta, lam, tol, max_iter, want_grad, want_hess, P, val, grad, hess,
                 status, resid, lowrank, WTo, So, P0, has0, O)  # fmt: skip


@numba.njit(**_JIT)
def _solve_range(lo, hi, X, C, mu, delta, lam, tol, max_iter, want_grad, want_hess, P, val, grad, hess, status, resid,
                 lowrank, WTo, So, P0, has0, O):  # fmt: skip
    """The pairs lo..hi-1 of :func:`solve_pairs` (its arguments), one after the other: the whole solve, compiled
    once for the parallel kernel and its serial twin (a prange body this size took numba minutes to compile)."""
    half_delta = 0.5 * delta
    g, g2 = np.empty(4), np.empty(4)
    sc, sc2 = np.empty(9), np.empty(9)
    H, H2 = np.empty((4, 4)), np.empty((4, 4))
    p2 = np.empty(4)
    s2 = np.empty(6)
    L = np.empty((4, 4))
    Li = np.empty(4)
    step = np.empty(4)
    p = np.empty(4)
    s = np.empty(6)
    q = np.empty(6)
    WT = np.empty((4, 18))
    m = np.empty(4)
    Xc = np.empty((6, 3))  # the pair in its frame at C[k] (exact)
    Q = np.empty((4, 4))
    B = np.empty((6, 4))
    Hq2 = np.empty((4, 4))
    # ... and in the contact frame at C[k] + O[k] (_contact_frame), where it is solved
    Xk = np.empty((6, 3))
    for k in range(lo, hi):
        _frame(X[k], C[k], Xc)
        warm_k = has0.shape[0] > 0 and has0[k] != 0
        e = math.inf
        e_res = 0.0
        st = NOT_CONVERGED
        # a warm start (if strictly feasible) with at most _WARM_ITER iterations, else (or if that does not
        # converge) the cold start
        for attempt in range(2 if warm_k else 1):
            cold = attempt == 1 or not warm_k
            e = math.inf
            e_res = 0.0
            if not cold:
                for i in range(4):
                    p[i] = P0[k, i]
                p[3] += P0[k, 0] * C[k, 0] + P0[k, 1] * C[k, 1] + P0[k, 2] * C[k, 2]
                _contact_frame(Xc, p, half_delta, O[k], Xk)
                e, e_res = _eval(Xk, p, half_delta, lam, g, H, sc, s)
                if e == math.inf:
                    continue
            else:
                # ---- strictly feasible start from the exact closest points (SPEC section 2)
                dist = math.sqrt(tri_tri_closest_nb(Xc[0:3], Xc[3:6], q))
                if _clear_of_margin(dist, delta, Xc):
                    alpha = (half_delta + 1.0) / (0.5 * dist + 1.0) / dist
                    d = 0.0
                    for i in range(3):
                        ni = alpha * (q[i] - q[3 + i])
                        p[i] = ni
                        d -= ni * 0.5 * (q[i] + q[3 + i])
                    p[3] = d
                    _contact_frame(Xc, p, half_delta, O[k], Xk)
                    e, e_res = _eval(Xk, p, half_delta, lam, g, H, sc, s)
                    if e == math.inf and _sat_start(Xc, delta, p) > delta:
                        _contact_frame(Xc, p, half_delta, O[k], Xk)
                        e, e_res = _eval(Xk, p, half_delta, lam, g, H, sc, s)
                if e == math.inf:
                    break
            cap = max_iter if cold else min(max_iter, _WARM_ITER)
            # ---- damped Newton (Levenberg-Marquardt on the diagonal). Converged when any of:
            #   rel <= tol                    relative gradient (each component against its scale sc[4:]);
            #   dec2 <= tol^2 E               Newton decrement g^T H^-1 g ~ 2 (E - E*), undamped;
            #   dec2 <= noise2                the decrement the gradient's own rounding noise eps*sc would give:
            #                                 nothing representable is left (stiff near-margin pairs).
            damp = 0.0
            st = NOT_CONVERGED
            for _it in range(cap + 1):
                if (
                    abs(g[0]) <= tol * sc[4]
                    and abs(g[1]) <= tol * sc[5]
                    and abs(g[2]) <= tol * sc[6]
                    and abs(g[3]) <= tol * sc[7]
                ):
                    st = CONVERGED
                    break
                if _it == cap:
                    break
                accepted = False
                done = False
                for _try in range(60):
                    if _cholesky4(H, L, Li, damp):
                        for i in range(4):
                            m[i] = -g[i]
                        _chol_solve4(L, Li, m, step)
                        dec2 = -(g[0] * step[0] + g[1] * step[1] + g[2] * step[2] + g[3] * step[3])
                        if damp == 0.0 and dec2 <= 1e-4 * e:  # (the noise floor is far below 1e-4 E)
                            for i in range(4):  # m = L^-1 (eps sc_plain): the sums' own rounding
                                acc = _GRAD_EPS * sc[4 + i]
                                for t in range(i):
                                    acc -= L[i, t] * m[t]
                                m[i] = acc * Li[i]
                            # + the gaps' rounding (sc[8], see _eval)
                            noise2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3] + sc[8]
                            if dec2 <= tol * tol * e or dec2 <= noise2:
                                done = True
                                break
                        for i in range(4):
                            p2[i] = p[i] + step[i]
                        e_new, e_res_new = _eval(Xk, p2, half_delta, lam, g2, H2, sc2, s2)
                        # Accept a decrease; or, when the predicted decrease is below E's resolution, a step that
                        # keeps E within that resolution (the quadratic endgame of Newton).
                        if e_new <= e or (dec2 <= e_res and e_new <= e + e_res):
                            accepted = True
                            break
                    damp = 1e-4 if damp == 0.0 else damp * 10.0
                if done:
                    st = CONVERGED
                    break
                if not accepted:
                    if _rel_grad(g, sc) <= _STALL_TOL:  # no representable decrease is left
                        st = CONVERGED
                    break
                # the trial's E, derivatives and gaps become current
                _take(p, g, H, sc, s, p2, g2, H2, sc2, s2)
                e, e_res = e_new, e_res_new
                damp = 0.0 if damp <= 1e-3 else damp * 0.1
            if st == CONVERGED and _cholesky4(H, L, Li, 0.0):
                # the Newton step from the converged plane is taken too (if E stays within its resolution):
                # the tests above bound E's error, and this makes the plane's, which the derivatives depend on,
                # quadratically small (a nearly flat E leaves the plane loose at the tests' tolerance)
                for i in range(4):
                    m[i] = -g[i]
                _chol_solve4(L, Li, m, step)
                for i in range(4):
                    p2[i] = p[i] + step[i]
                e_new, e_res_new = _eval(Xk, p2, half_delta, lam, g2, H2, sc2, s2)
                if e_new <= e + e_res:
                    for i in range(4):
                        p[i], g[i], sc[i], sc[4 + i] = p2[i], g2[i], sc2[i], sc2[4 + i]
                        for j in range(4):
                            H[i, j] = H2[i, j]
                    for i in range(6):
                        s[i] = s2[i]
                    e, e_res = e_new, e_res_new
            if st == NOT_CONVERGED and not cold:
                continue  # the warm start's iterations are spent: solve again from the cold start
            if st == NOT_CONVERGED and _rel_grad(g, sc) <= _STALL_TOL:
                # at the iteration cap: in the endgame, steps that change E by less than its rounding are accepted,
                # and a badly conditioned pair can keep taking them without its gradient reaching tol; below
                # _STALL_TOL it is as converged as a stalled pair
                st = CONVERGED
            break
        if e == math.inf:
            status[k] = INFEASIBLE
            val[k] = math.inf
            resid[k] = 0.0
            for i in range(4):
                P[k, i] = 0.0
            if want_grad:
                for i in range(18):
                    grad[k, i] = 0.0
            if want_hess and lowrank:
                for i in range(4):
                    for j in range(18):
                        WTo[k, i, j] = 0.0
                for i in range(6):
                    So[k, i] = math.inf
            elif want_hess:
                for i in range(18):
                    for j in range(18):
                        hess[k, i, j] = 0.0
            continue
        if st == CONVERGED and _conditioning(Xk, p, s) > _REFINE_KAPPA and _ill_conditioned(H, L, Li):
            e, e_res = _refine(Xk, p, half_delta, lam, e, e_res, g, H, sc, s, p2, g2, H2, sc2, s2, Q, B, Hq2, L,
                               Li, m, step)  # fmt: skip
        status[k] = st
        resid[k] = _rel_grad(g, sc)
        val[k] = mu * e
        for i in range(4):
            P[k, i] = p[i]
        if not (want_grad or want_hess):
            continue
        n = (p[0], p[1], p[2])
        if want_grad:
            # dP/dx_k = -mu sg_k n / s_k^2 (envelope theorem)
            for kk in range(6):
                sg = 1.0 if kk < 3 else -1.0
                w1 = mu * sg / (s[kk] * s[kk])
                for j in range(3):
                    grad[k, 3 * kk + j] = -w1 * n[j]
        if want_hess:
            # hess_x P = mu (E_xx - E_xp E_pp^-1 E_px): with E_pp = L L^T and W = E_xp L^-T,
            # the Schur complement is E_xx - W W^T. E_xx is block diagonal 2 n n^T / s^3.
            rot = _ill_conditioned(H, L, Li)
            if rot:  # ill-conditioned: E_pp and E_px in E_pp's eigenbasis (_rotated_epp)
                _rotated_epp(Xk, s, p, lam, H, Q, B, H2)
                shift = 0.0
                while not _cholesky4(H2, L, Li, shift) and shift < 1.0:
                    shift = 16 * 2.220446049250313e-16 if shift == 0.0 else shift * 16.0
            il0, il1, il2, il3 = Li[0], Li[1], Li[2], Li[3]
            for kk in range(6):
                sg = 1.0 if kk < 3 else -1.0
                inv = 1.0 / s[kk]
                w1 = inv * inv
                w2 = 2.0 * w1 * inv
                xa, xb, xc = Xk[kk, 0], Xk[kk, 1], Xk[kk, 2]
                for j in range(3):
                    row = 3 * kk + j
                    # E_xp row: -sg e_j^T [I|0] / s^2 + 2 n_j [x^T | 1] / s^3
                    nw = n[j] * w2
                    m0, m1, m2, m3 = nw * xa, nw * xb, nw * xc, nw
                    if rot:  # Q^T (2 n_j [x; 1] / s^3 - sg e_j / s^2), from B = Q^T [x; 1]
                        m0 = nw * B[kk, 0] - sg * w1 * Q[j, 0]
                        m1 = nw * B[kk, 1] - sg * w1 * Q[j, 1]
                        m2 = nw * B[kk, 2] - sg * w1 * Q[j, 2]
                        m3 = nw * B[kk, 3] - sg * w1 * Q[j, 3]
                    elif j == 0:
                        m0 -= sg * w1
                    elif j == 1:
                        m1 -= sg * w1
                    else:
                        m2 -= sg * w1
                    # forward substitution, stored transposed: WT[:, row] = L^-1 m
                    t0 = m0 * il0
                    t1 = (m1 - L[1, 0] * t0) * il1
                    t2 = (m2 - L[2, 0] * t0 - L[2, 1] * t1) * il2
                    t3 = (m3 - L[3, 0] * t0 - L[3, 1] * t1 - L[3, 2] * t2) * il3
                    WT[0, row], WT[1, row], WT[2, row], WT[3, row] = t0, t1, t2, t3
            if lowrank:
                for i in range(4):
                    for j in range(18):
                        WTo[k, i, j] = WT[i, j]
                for i in range(6):
                    So[k, i] = s[i]
                continue
            # rows written in order (contiguous, vectorisable): hess = mu (E_xx - W W^T)
            hk = hess[k]
            # (products before scaling by -mu keep the result exactly symmetric)
            for a_ in range(18):
                wa0, wa1, wa2, wa3 = WT[0, a_], WT[1, a_], WT[2, a_], WT[3, a_]
                for b_ in range(18):
                    hk[a_, b_] = -mu * (wa0 * WT[0, b_] + wa1 * WT[1, b_] + wa2 * WT[2, b_] + wa3 * WT[3, b_])
            for kk in range(6):
                c = 2.0 * mu / (s[kk] * s[kk] * s[kk])
                for i in range(3):
                    for j in range(3):
                        hk[3 * kk + i, 3 * kk + j] += c * (n[i] * n[j])


# Numba's worker threads compete with torch's for the cores and cost up to milliseconds to wake: small batches run
# serially, larger ones in parallel. 2,000: a step of a ball on a 12-triangle box (3,583 leaf pairs per evaluation,
# torch serial inside the step) took a median 20-24 ms with the parallel kernel against 26 ms serial (2 cores).
PARALLEL_MIN_PAIRS = 2000
