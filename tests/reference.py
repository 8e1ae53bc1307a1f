"""Independent naive reference of the exact pair potential, for tests only.

Per pair, in NumPy/SciPy, sharing no code with the library: the start is the max-margin separating plane found by
SciPy's SLSQP (not closest points), the solve is undamped Newton with a backtracking line search and a Newton-
decrement stopping rule (not LM with a relative-gradient test), and the derivatives are finite differences of the
value or formulas re-derived here.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

LAM = 12.0
SIGN = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])


def _energy(p: np.ndarray, X: np.ndarray, delta: float) -> float:
    n, d = p[:3], p[3]
    r = np.linalg.norm(n)
    s = SIGN * (X @ n + d) - delta / 2
    if r >= 1 or np.any(s <= 0):
        return np.inf
    return LAM / (1 - r) + np.sum(1 / s)


def _grad_hess(p: np.ndarray, X: np.ndarray, delta: float):
    n, d = p[:3], p[3]
    r = np.linalg.norm(n)
    u = n / r
    s = SIGN * (X @ n + d) - delta / 2
    A = SIGN[:, None] * np.hstack([X, np.ones((6, 1))])  # (6, 4)
    g = -(A / s[:, None] ** 2).sum(0)
    g[:3] += LAM * u / (1 - r) ** 2
    H = (A.T * (2 / s**3)) @ A
    H[:3, :3] += LAM * (2 / (1 - r) ** 3 * np.outer(u, u) + (np.eye(3) - np.outer(u, u)) / ((1 - r) ** 2 * r))
    return g, H


def max_margin_plane(X: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit-normal plane maximising the smaller vertex distance t (SLSQP); t > 0 iff the triangles separate."""
    ca, cb = X[:3].mean(0), X[3:].mean(0)
    n0 = (ca - cb) / np.linalg.norm(ca - cb)
    z0 = np.concatenate([n0, [-n0 @ (ca + cb) / 2], [0.0]])
    cons = [
        {"type": "ineq", "fun": lambda z: SIGN * (X @ z[:3] + z[3]) - z[4]},
        {"type": "ineq", "fun": lambda z: 1.0 - z[:3] @ z[:3]},
    ]
    res = minimize(
        lambda z: -z[4], z0, constraints=cons, method="SLSQP", options={"ftol": 1e-15, "maxiter": 500}
    )
    z = res.x
    nn = np.linalg.norm(z[:3])
    return np.concatenate([z[:3], [z[3]]]) / nn, float(np.min(SIGN * (X @ z[:3] + z[3])) / nn)


def reference_pair(tri_a: np.ndarray, tri_b: np.ndarray, *, mu: float, margin: float):
    """Return (value, plane) of the pair potential; value is +inf when no plane clears the margin."""
    X = np.vstack([tri_a, tri_b]).astype(np.float64)
    plane, t = max_margin_plane(X)
    if not t > margin / 2 * (1 + 1e-6):
        return np.inf, None
    c = 0.5 * (margin / (2 * t) + 1.0)  # c t > delta/2 and c < 1: strictly feasible
    p = c * plane
    e = _energy(p, X, margin)
    assert np.isfinite(e)
    for _ in range(500):
        g, H = _grad_hess(p, X, margin)
        step = np.linalg.solve(H, -g)
        dec2 = -g @ step  # Newton decrement squared ~ 2 (E - E*)
        if dec2 <= 1e-30 * e:
            break
        a = 1.0
        while True:
            e_new = _energy(p + a * step, X, margin)
            if e_new <= e - 0.25 * a * dec2 or a < 1e-20:
                break
            a *= 0.5
        if a < 1e-20:
            break
        p, e = p + a * step, e_new
    return mu * e, p


def reference_grad(tri_a: np.ndarray, tri_b: np.ndarray, *, mu: float, margin: float) -> np.ndarray:
    """(18,) gradient from the reference plane via the envelope theorem, re-derived: dE/dx_k = -sg_k n / s_k^2."""
    X = np.vstack([tri_a, tri_b])
    _, p = reference_pair(tri_a, tri_b, mu=mu, margin=margin)
    s = SIGN * (X @ p[:3] + p[3]) - margin / 2
    return (mu * (-(SIGN / s**2)[:, None] * p[:3][None, :])).reshape(18)
