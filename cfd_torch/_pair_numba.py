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

from ._geometry import tri_tri_closest_nb

CONVERGED, INFEASIBLE, NOT_CONVERGED = 0, 1, 2

_STALL_TOL = 1e-8  # a pair whose relative gradient is below this is done when no step can decrease E any more
_EPS_RES = 16 * 2.220446049250313e-16  # rounding of E, relative to the magnitudes it is computed from
_GRAD_EPS = 16 * 2.220446049250313e-16  # rounding noise of a gradient component, relative to its scale sc


@numba.njit(cache=True, inline="always")
def _energy(X, n0, n1, n2, d, half_delta, lam):
    """E(p) or +inf outside the feasible set."""
    r = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not r < 1.0:
        return math.inf
    e = lam / (1.0 - r)
    for i in range(6):
        sg = 1.0 if i < 3 else -1.0
        s = sg * (n0 * X[i, 0] + n1 * X[i, 1] + n2 * X[i, 2] + d) - half_delta
        if not s > 0.0:
            return math.inf
        e += 1.0 / s
    return e


@numba.njit(cache=True, inline="always")
def _grad_hess(X, p, half_delta, lam, g, H, sc, s):
    """Gradient g (4), Hessian H (4, 4), per-component rounding scale sc (4) and gaps s (6) of E at p.

    Returns the rounding resolution of E at p: sum_k eps (|n.x_k| + |d| + delta/2) / s_k^2 (each gap s_k is the
    difference of terms of that size) plus the resolution of the sum itself."""
    n0, n1, n2, d = p[0], p[1], p[2], p[3]
    r = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    u0, u1, u2 = n0 / r, n1 / r, n2 / r
    om = 1.0 - r
    gl = lam / (om * om)
    g[0], g[1], g[2], g[3] = gl * u0, gl * u1, gl * u2, 0.0
    sc[0], sc[1], sc[2], sc[3] = abs(g[0]), abs(g[1]), abs(g[2]), 0.0
    # lambda Hn = lambda [2/(1-r)^3 u u^T + (I - u u^T) / ((1-r)^2 r)]
    c1 = 2.0 * lam / (om * om * om)
    c2 = gl / r
    u = (u0, u1, u2)
    for i in range(3):
        for j in range(3):
            H[i, j] = (c1 - c2) * u[i] * u[j]
        H[i, i] += c2
        H[i, 3] = 0.0
        H[3, i] = 0.0
    H[3, 3] = 0.0
    e_res = lam / om
    for k in range(6):
        sg = 1.0 if k < 3 else -1.0
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        sk = sg * (n0 * x0 + n1 * x1 + n2 * x2 + d) - half_delta
        s[k] = sk
        w1 = 1.0 / (sk * sk)
        w2 = 2.0 * w1 / sk
        # abar = sg [x; 1]; grad -= abar / s^2; hess += 2 abar abar^T / s^3 (sg^2 = 1).
        # sc: rounding-noise scale of each gradient component; s_k carries an absolute rounding error of about
        # eps (|n.x_k| + |d|), amplified in 1/s^2 by 2 (|n.x_k| + |d|) / s_k.
        mag = abs(n0 * x0) + abs(n1 * x1) + abs(n2 * x2) + abs(d) + half_delta
        amp = 1.0 + 2.0 * mag / sk
        e_res += mag * w1
        a = (x0, x1, x2, 1.0)
        for i in range(4):
            gi = sg * a[i] * w1
            g[i] -= gi
            sc[i] += abs(gi) * amp
            for j in range(i, 4):
                H[i, j] += w2 * a[i] * a[j]
    for i in range(4):
        for j in range(i):
            H[i, j] = H[j, i]
    return _EPS_RES * e_res


@numba.njit(cache=True, inline="always")
def _cholesky4(A, L, damp):
    """L L^T = A + damp diag(A); returns False if not positive definite."""
    for j in range(4):
        acc = A[j, j] * (1.0 + damp)
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:
            return False
        ljj = math.sqrt(acc)
        L[j, j] = ljj
        for i in range(j + 1, 4):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / ljj
        for i in range(j):
            L[i, j] = 0.0
    return True


@numba.njit(cache=True, inline="always")
def _chol_solve4(L, b, x):
    """x = (L L^T)^-1 b."""
    for i in range(4):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    for i in range(3, -1, -1):
        acc = x[i]
        for k in range(i + 1, 4):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]


@numba.njit(cache=True, parallel=True)
def solve_pairs(X, mu, delta, lam, tol, max_iter, want_grad, want_hess, P, val, grad, hess, status, resid):
    """Solve K pair problems and write their value / plane / derivatives in place.

    Args:
        X: (K, 6, 3) float64 vertices a0, a1, a2, b0, b1, b2.
        mu, delta, lam: contact coefficient, margin, normal-regulariser weight.
        tol: relative gradient tolerance: max_i |dE/dp_i| / (sum of |terms| of dE/dp_i) <= tol.
        max_iter: Newton iteration cap.
        want_grad, want_hess: whether to fill ``grad`` (K, 18) and ``hess`` (K, 18, 18).
        P: (K, 4) out: optimal plane (n, d); val: (K,) out: mu E(p*) or +inf;
        status: (K,) int8 out; resid: (K,) out: final relative gradient.
    """
    K = X.shape[0]
    half_delta = 0.5 * delta
    nchunks = min(K, 256)
    for c in numba.prange(nchunks):
        g = np.empty(4)
        sc = np.empty(4)
        H = np.empty((4, 4))
        L = np.empty((4, 4))
        step = np.empty(4)
        p = np.empty(4)
        s = np.empty(6)
        q = np.empty(6)
        W = np.empty((18, 4))
        m = np.empty(4)
        lo = c * K // nchunks
        hi = (c + 1) * K // nchunks
        for k in range(lo, hi):
            Xk = X[k]
            # ---- strictly feasible start from the exact closest points (SPEC section 2)
            dist = math.sqrt(tri_tri_closest_nb(Xk[0:3], Xk[3:6], q))
            e = math.inf
            if dist > delta:
                alpha = (half_delta + 1.0) / (0.5 * dist + 1.0) / dist
                d = 0.0
                for i in range(3):
                    ni = alpha * (q[i] - q[3 + i])
                    p[i] = ni
                    d -= ni * 0.5 * (q[i] + q[3 + i])
                p[3] = d
                e = _energy(Xk, p[0], p[1], p[2], p[3], half_delta, lam)
            if e == math.inf:
                status[k] = INFEASIBLE
                val[k] = math.inf
                resid[k] = 0.0
                for i in range(4):
                    P[k, i] = 0.0
                if want_grad:
                    for i in range(18):
                        grad[k, i] = 0.0
                if want_hess:
                    for i in range(18):
                        for j in range(18):
                            hess[k, i, j] = 0.0
                continue
            # ---- damped Newton (Levenberg-Marquardt on the diagonal). Converged when any of:
            #   rel <= tol                    relative gradient (each component against its rounding scale sc);
            #   dec2 <= tol^2 E               Newton decrement g^T H^-1 g ~ 2 (E - E*), undamped;
            #   dec2 <= noise2                the decrement the gradient's own rounding noise eps*sc would give:
            #                                 nothing representable is left (stiff near-margin pairs).
            damp = 0.0
            st = NOT_CONVERGED
            rel = math.inf
            for _it in range(max_iter + 1):
                e_res = _grad_hess(Xk, p, half_delta, lam, g, H, sc, s)
                rel = 0.0
                for i in range(4):
                    r_i = abs(g[i]) / sc[i] if sc[i] > 0.0 else 0.0  # 0/0: an exact zero component
                    if r_i > rel:
                        rel = r_i
                if rel <= tol:
                    st = CONVERGED
                    break
                if _it == max_iter:
                    break
                accepted = False
                done = False
                for _try in range(60):
                    if _cholesky4(H, L, damp):
                        for i in range(4):
                            m[i] = -g[i]
                        _chol_solve4(L, m, step)
                        dec2 = -(g[0] * step[0] + g[1] * step[1] + g[2] * step[2] + g[3] * step[3])
                        for i in range(4):  # m = L^-1 (eps sc): noise2 = |m|^2
                            acc = _GRAD_EPS * sc[i]
                            for t in range(i):
                                acc -= L[i, t] * m[t]
                            m[i] = acc / L[i, i]
                        noise2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3]
                        if damp == 0.0 and (dec2 <= tol * tol * e or dec2 <= noise2):
                            done = True
                            break
                        e_new = _energy(
                            Xk,
                            p[0] + step[0],
                            p[1] + step[1],
                            p[2] + step[2],
                            p[3] + step[3],
                            half_delta,
                            lam,
                        )
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
                    if rel <= _STALL_TOL:  # no representable decrease is left
                        st = CONVERGED
                    break
                for i in range(4):
                    p[i] += step[i]
                e = e_new
                damp = 0.0 if damp <= 1e-3 else damp * 0.1
            status[k] = st
            resid[k] = rel
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
                _cholesky4(H, L, 0.0)
                for kk in range(6):
                    sg = 1.0 if kk < 3 else -1.0
                    w1 = 1.0 / (s[kk] * s[kk])
                    w2 = 2.0 * w1 / s[kk]
                    for j in range(3):
                        row = 3 * kk + j
                        # E_xp row: -sg e_j^T [I|0] / s^2 + 2 n_j [x^T | 1] / s^3
                        for cc in range(3):
                            m[cc] = n[j] * Xk[kk, cc] * w2
                        m[3] = n[j] * w2
                        m[j] -= sg * w1
                        # forward substitution: W[row] = L^-1 m
                        for i in range(4):
                            acc = m[i]
                            for t in range(i):
                                acc -= L[i, t] * W[row, t]
                            W[row, i] = acc / L[i, i]
                for a_ in range(18):
                    for b_ in range(a_, 18):
                        acc = (
                            W[a_, 0] * W[b_, 0]
                            + W[a_, 1] * W[b_, 1]
                            + W[a_, 2] * W[b_, 2]
                            + W[a_, 3] * W[b_, 3]
                        )
                        ka, kb = a_ // 3, b_ // 3
                        if ka == kb:
                            acc -= n[a_ - 3 * ka] * n[b_ - 3 * kb] * 2.0 / (s[ka] * s[ka] * s[ka])
                        hess[k, a_, b_] = -mu * acc
                        hess[k, b_, a_] = -mu * acc
