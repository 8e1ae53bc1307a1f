"""CPU kernel of :func:`cfd_torch.rotation.rotation_derivatives` (same formulas, same series switch-over).

A step evaluates R, dR and d2R of a handful of bodies several times per Newton iteration; as torch code that is
about 150 small tensor ops (about 1 ms), as one numba loop a few microseconds.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .rotation import ANGLE_SERIES, ANGLE_SERIES_X

_SERIES_T = 0.25
_N_TERMS = 16


def _series_coefficients(offset: int) -> np.ndarray:
    """(3, N) coefficients of f, f', f'' of f(t) = sum_k (-1)^k t^k / (2k + offset)!, by powers of t."""
    c = np.array([(-1.0) ** k / math.factorial(2 * k + offset) for k in range(_N_TERMS)])
    c1 = np.zeros(_N_TERMS)
    c1[: _N_TERMS - 1] = [(k + 1) * c[k + 1] for k in range(_N_TERMS - 1)]
    c2 = np.zeros(_N_TERMS)
    c2[: _N_TERMS - 2] = [(k + 1) * c1[k + 1] for k in range(_N_TERMS - 2)]
    return np.stack([c, c1, c2])


_CA = _series_coefficients(1)
_CB = _series_coefficients(2)
_ANGLE = np.array(ANGLE_SERIES)


@numba.njit(cache=True)
def _horner(c, t):
    f = 0.0
    for k in range(c.shape[0] - 1, -1, -1):
        f = f * t + c[k]
    return f


@numba.njit(cache=True)
def angle_factors_kernel(c):
    """f(c) = theta / sin(theta) of c = cos(theta) and its first two derivatives in c: the same formulas and
    switch-over as :func:`cfd_torch.rotation.angle_factors`."""
    x = min(max(1.0 - c, 0.0), 2.0)
    n = _ANGLE.shape[0]
    if x < ANGLE_SERIES_X:
        f0 = f1 = f2 = 0.0
        for j in range(n - 1, -1, -1):
            f0 = f0 * x + _ANGLE[j]
            if j + 1 < n:
                f1 = f1 * x + (j + 1) * _ANGLE[j + 1]
            if j + 2 < n:
                f2 = f2 * x + (j + 2) * (j + 1) * _ANGLE[j + 2]
        return f0, -f1, f2
    s2 = max(x * (2.0 - x), 1e-16)
    sn = math.sqrt(s2)
    cs = 1.0 - x
    th = math.atan2(sn, cs)
    return th / sn, (th * cs - sn) / (s2 * sn), (th * s2 + 3.0 * cs * (th * cs - sn)) / (s2 * s2 * sn)


@numba.njit(cache=True)
def rotation_derivatives_kernel(omega, ca, cb, R, dR, d2R, order):
    """Fill R (N, 3, 3), dR (N, 3, 3, 3) [.., i] = dR/d omega_i and d2R (N, 3, 3, 3, 3) up to ``order``."""
    E = np.zeros((3, 3, 3))
    E[0, 2, 1], E[0, 1, 2] = 1.0, -1.0
    E[1, 0, 2], E[1, 2, 0] = 1.0, -1.0
    E[2, 1, 0], E[2, 0, 1] = 1.0, -1.0
    K = np.empty((3, 3))
    K2 = np.empty((3, 3))
    lin = np.empty((3, 3))
    quad = np.empty((3, 3))
    sym = np.empty((3, 3, 3))
    cross = np.empty((3, 3, 3))
    for n in range(omega.shape[0]):
        w0, w1, w2 = omega[n, 0], omega[n, 1], omega[n, 2]
        w = (w0, w1, w2)
        K[0, 0], K[0, 1], K[0, 2] = 0.0, -w2, w1
        K[1, 0], K[1, 1], K[1, 2] = w2, 0.0, -w0
        K[2, 0], K[2, 1], K[2, 2] = -w1, w0, 0.0
        for r in range(3):
            for c in range(3):
                s = 0.0
                for m in range(3):
                    s += K[r, m] * K[m, c]
                K2[r, c] = s
        t = w0 * w0 + w1 * w1 + w2 * w2
        if t < _SERIES_T:
            a, a1, a2 = _horner(ca[0], t), _horner(ca[1], t), _horner(ca[2], t)
            b, b1, b2 = _horner(cb[0], t), _horner(cb[1], t), _horner(cb[2], t)
        else:
            th = math.sqrt(t)
            sn, cs = math.sin(th), math.cos(th)
            a = sn / th
            a1 = (th * cs - sn) / (2.0 * th**3)
            a2 = (3.0 * sn - 3.0 * th * cs - t * sn) / (4.0 * th**5)
            b = (1.0 - cs) / t
            b1 = (th * sn - 2.0 + 2.0 * cs) / (2.0 * t * t)
            b2 = (t * cs - 5.0 * th * sn + 8.0 - 8.0 * cs) / (4.0 * t**3)
        for r in range(3):
            for c in range(3):
                R[n, r, c] = (1.0 if r == c else 0.0) + a * K[r, c] + b * K2[r, c]
        if order < 1:
            continue
        for r in range(3):
            for c in range(3):
                lin[r, c] = a1 * K[r, c] + b1 * K2[r, c]
                quad[r, c] = a2 * K[r, c] + b2 * K2[r, c]
        for i in range(3):
            for r in range(3):
                for c in range(3):
                    ek = 0.0
                    for m in range(3):
                        ek += E[i, r, m] * K[m, c] + K[r, m] * E[i, m, c]
                    sym[i, r, c] = ek
                    cross[i, r, c] = a1 * E[i, r, c] + b1 * ek
                    dR[n, r, c, i] = 2.0 * w[i] * lin[r, c] + a * E[i, r, c] + b * ek
        if order < 2:
            continue
        for i in range(3):
            for j in range(3):
                for r in range(3):
                    for c in range(3):
                        ee = 0.0
                        for m in range(3):
                            ee += E[i, r, m] * E[j, m, c] + E[j, r, m] * E[i, m, c]
                        v = (
                            4.0 * w[i] * w[j] * quad[r, c]
                            + 2.0 * w[i] * cross[j, r, c]
                            + 2.0 * w[j] * cross[i, r, c]
                        )
                        v += b * ee
                        if i == j:
                            v += 2.0 * lin[r, c]
                        d2R[n, r, c, i, j] = v


def rotation_derivatives_cpu(omega: np.ndarray, order: int = 2):
    """R, dR, d2R (numpy float64) of (N, 3) rotation vectors; dR / d2R are None below ``order``."""
    N = omega.shape[0]
    R = np.empty((N, 3, 3))
    dR = np.empty((N, 3, 3, 3)) if order >= 1 else np.empty((0, 3, 3, 3))
    d2R = np.empty((N, 3, 3, 3, 3)) if order >= 2 else np.empty((0, 3, 3, 3, 3))
    rotation_derivatives_kernel(np.ascontiguousarray(omega, dtype=np.float64), _CA, _CB, R, dR, d2R, order)
    return R, (dR if order >= 1 else None), (d2R if order >= 2 else None)


@numba.njit(cache=True, nogil=True)
def add_rotation_terms(hess, p, o, G, d2R, body, sign):
    """The second-order rotation terms of a gradient on body-frame points: hess[p, o + k, o + l] += sign
    sum_{i,m} G[i, m] d2R[body, i, m, k, l] for l >= k (the upper triangle of the rotation block at ``o``), where
    G (3, 3) = sum over the points of (world-frame gradient) (body-frame point)^T."""
    for k in range(3):
        for l in range(k, 3):
            acc = 0.0
            for i in range(3):
                for m in range(3):
                    acc += G[i, m] * d2R[body, i, m, k, l]
            hess[p, o + k, o + l] += sign * acc
