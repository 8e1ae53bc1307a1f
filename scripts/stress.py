"""Numerical-robustness sweep of the pair potential, the mesh potential and the stepper (outside the test suite).

Four sections, each seeded and reproducible; every case is one row of ``<out>/stress.json``.

**pair**: ``pair_potential_derivatives`` (value, gradient, Hessian) of random triangle pairs whose closest distance
is known by construction (triangle a in the half-space z <= 0, b in z >= gap, each touching its plane at a chosen
feature, so the distance is exactly the gap; the shared-plane pair is separated along x instead), for eight feature
configurations (vertex-face, edge-edge, face-face, edge-face, parallel edges, near-parallel edges, vertex-vertex,
coplanar side by side), over triangle sizes 1e-6..1e4 m, separations 1.01, 1.5 and 10 x the margin and 0.1, 1, 1e3
and 1e6 x the size (a separation not above the margin is skipped), probes at 0.5 and 0.99 x the margin (the value
must be +inf), margins 1e-6..1e-2, mu 1e-12..1e-2 (numba; the torch backend at mu 1e-8), float32 and float64
inputs, each pair randomly rotated and translated by 0, 1e2 or 1e5 m in a random direction. The reference is the
same input shifted next to the origin by an exactly representable offset (the geometry keeps its bits), solved by
the numba backend with tol 1e-15 and 500 iterations; float32 inputs are compared, with a float32 tolerance, against the
reference of their float32-rounded coordinates (the library solves float32 in float64). The library runs at its
defaults (tol 1e-12, max_iter 100). For one pair of every near-margin combination (separation up to 10 margins), of
every fourth other one, and for every pair whose reference is +inf beyond the margin, an arbitrary-precision
reference (mpmath, 50 digits: Newton on the 4-dim convex plane problem
``E(p) = lam/(1-|n|) + sum_k 1/(sg_k (n.x_k + d) - delta/2)`` from the float64 optimum, else from the construction's
mid-gap plane scaled as in SPEC section 2; then the envelope gradient and the implicit-function Hessian) measures the
accuracy of both the library and the tight reference. Errors are reported with the problem's condition
``kappa = (size + gap) / (gap - margin)`` (a rounding of the coordinates, eps x size, changes the gaps that the
potential depends on by eps x kappa relative), as ``err / max(eps_out, eps kappa)``.

**fuzz**: hypothesis-generated degenerate-but-valid pairs: slivers (a vertex close to the opposite edge) and needles
(one short edge) with aspect ratios 1..1e15 (those past the library's degeneracy threshold, 2 area <= 100 eps
longest edge^2, must raise ValueError: counted as *rejected*, not a failure), near-parallel pairs (tilt 1e-14..1e-2
rad), near-coplanar and shared-plane (exactly coplanar, side by side) pairs, random sizes, gaps from 0.3 to 1e6
margins, rotations, translations up to 1e5 m, mu, dtypes and backends. Properties: the value is finite and at least
12 mu when the triangles are separated beyond the margin (distance of the rounded input from the library's exact
closest points, ``cfd_torch._geometry``, and an edge-piercing test) and +inf within it; gradient and Hessian finite;
the gradient sums to zero over the six vertices per axis (translation invariance; within 1e-9 + 4 eps kappa of the
rows' magnitudes); value, gradient and Hessian agree with the centred tight-tolerance reference; no exception but
ValueError for degenerate triangles.

**mesh**: ``mesh_potential_derivatives`` (value, 12-gradient, 12 x 12 Hessian) of two icospheres (320 faces) and of a
ball above a box (refined), scaled by 1e-3..1e2 m, margin 1e-3 x scale, gaps 1.5 x margin, 0.01, 0.3 and 3 x scale,
random whole-configuration rotations, translated by 0, 1e2 or 1e5 m (float64 and float32 poses): non-finite output,
+inf at a feasible configuration, and the relative error against the same configuration shifted to the origin.

**step**: rollouts of three scenes (a ball dropped on a box floor, a box sliding with friction 0.5, two balls
colliding head-on without gravity) at body scales 1e-3..1e2 m. Every length scales with the body: dt = 0.01 s x
sqrt(scale) (free fall is self-similar then), margin 1e-3 m x scale (the default 1 mm margin would exceed a 1 mm
body's gaps), ccd_spacing 0.01 m x scale, newton_tol 1e-9 x scale, friction eps_v 1e-4 m/s x sqrt(scale) and the
contact stiffness mu = 1e-8 x scale^5 (a contact force mu / gap^2 then balances a weight ~ scale^3 at the same gap
relative to the body; with a fixed mu a 1 mm ball would hover 4 cm above the floor). Counted: StepError
(non-converged), non-finite poses, penetration (a body pair whose potential, evaluated by the scene's contact model,
is +inf after a step), and the largest translation difference, relative to the scale, between the rollout and the
same rollout translated by 1e3 m (rotations compared directly).

A case fails when: an output is NaN or inf at a feasible input (``nonfinite``), a feasible pair raises
PairSolveError or a step StepError (``unconverged``), a value is finite at an infeasible input or +inf at a feasible
one (``finite_infeasible`` / ``inf_feasible``), a value is below 12 mu (``wrong_value``), an error exceeds its
threshold (``error_value`` / ``error_grad`` / ``error_hess`` / ``translation``; the thresholds are the constants
below, each with its reason), a rollout penetrates (``penetration``) or any other exception (``exception``).

    python scripts/stress.py --out results/stress            # full run, about 2 min on 2 cores
    python scripts/stress.py --quick --out results/stress    # smoke run, under a minute
    python scripts/stress.py --sections pair fuzz --quick    # some sections only
    python scripts/stress.py --tiny --out /tmp/stress         # seconds: tests/test_stress_script.py

Writes ``<out>/stress.json`` (every case: parameters, outcome, errors) and ``<out>/stress.md`` (summary per section),
and prints the summary. Exit status 1 if any case failed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from fractions import Fraction
from pathlib import Path

import mpmath
import numpy as np
import torch
import trimesh
from _cli import nonnegative_int
from _provenance import git_revision
from tqdm import tqdm

from cfd_torch import (
    BSH,
    LAMBDA,
    Action,
    PairSolveError,
    Scene,
    StepError,
    mesh_potential_derivatives,
    pair_potential_derivatives,
    rigid_body,
    step,
)
from cfd_torch._geometry import frame_origin, segment_hits_triangle, triangle_closest_points
from cfd_torch.contact._pair_torch import _MARGIN_RES
from cfd_torch.rotation import quaternion, quaternion_multiply, rotation_vector

F64, F32 = torch.float64, torch.float32
EPS64 = float(torch.finfo(F64).eps)
EPS32 = float(torch.finfo(F32).eps)

# ------------------------------------------------------------------------------------------------- thresholds
# Against the centred reference (same bits of geometry, tol 1e-15): the library stops at tol 1e-12 (relative
# gradient of the plane problem), so its plane is off by up to ~1e-12 of its scale times the conditioning of the
# gaps; the value is stationary in the plane (error second order), the gradient n / s^2 and the Hessian first order.
# Rounding alone changes a gap by ~eps x size, i.e. the result by ~eps x kappa relative.
REF_TOL = {"value": 1e-10, "grad": 1e-7, "hess": 1e-6}
# per unit of eps x kappa (the rounding of the coordinates' digits that the gaps inherit), on top of the above
REF_KAPPA = {"value": 64.0, "grad": 256.0, "hess": 4096.0}
# float32 outputs are the float64 result rounded to float32: half an ulp per entry, 4 eps32 leaves room for a
# result that is itself at the float64 tolerance above
F32_TOL = 4 * EPS32
# Against the 50-digit mpmath reference: the float64 solve sees exact inputs; the gaps lose ~eps x kappa, so the
# error is bounded by a constant times eps x kappa (plus the solve tolerance, as above).
MP_TOL = {"value": 1e-10, "grad": 1e-7, "hess": 1e-6}
MP_KAPPA = {"value": 64.0, "grad": 256.0, "hess": 4096.0}
# The gradient sums to zero over the six vertices at the optimum (dE/dd = 0): a residual is the solve's tolerance
# (1e-12 of the sum of the magnitudes of dE/dd's terms) times |n|; 1e-9 of sum |g_k| leaves room for rounding. On
# top of it, like every other threshold here, the problem's conditioning: each vertex's row carries its gap's
# rounding, eps x kappa relative, and those errors do not cancel in the sum (measured up to 0.4 eps kappa, in pairs
# whose rows match the tight reference's to 1e-16).
SUM_TOL = 1e-9
SUM_KAPPA = 4.0
# mesh potential shifted to the origin (same relative geometry, exact shift): every leaf pair is solved in a frame
# centred near it and the traversal runs in body a's frame, so only rounding in different places differs
MESH_TOL = {"value": 1e-10, "grad": 1e-7, "hess": 1e-6}
# a rollout translated by 1e3 m: the poses carry the offset's rounding (ulp(1e3) = 1.1e-13 m) into every step, so
# differences of ~1e-13 / scale per step accumulate; 1e-6 of the scale after 40-60 steps is far above that and far
# below any visible effect
STEP_TOL = 1e-6
# the step's Newton tolerance scales with the body (1e-9 x scale) but not below 64 ulp of the 1e3 m offset of the
# translated rollout (7.3e-12 m): a 1 mm box there (scaled tolerance 1e-12 m = 9 ulp of its coordinates) could not
# resolve its Newton step above the rounding of its positions and stalled (200 iterations, |dL/dq| = 4e-14)
NEWTON_FLOOR = 64 * math.ulp(1e3)


def _rel(out: torch.Tensor, ref: torch.Tensor) -> float:
    """Normwise relative error max|out - ref| / max|ref| (0 when both are 0)."""
    out, ref = out.to(F64), ref.to(F64)
    scale = float(ref.abs().max())
    diff = float((out - ref).abs().max())
    if scale == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / scale


# ------------------------------------------------------------------------------------------- geometry helpers
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def exact_shift(X: torch.Tensor) -> torch.Tensor:
    """(K, 1, 3) offsets c with X - c exact in float64 and small: each pair's mean rounded to a multiple of the
    power of two g above its extent (X - c then keeps every bit of X and |X - c| < 1.5 g), or 0 on an axis where
    that would not be exact (a coordinate much smaller than g: the pair is within about g of the origin there)."""
    mean = X.mean(1, keepdim=True)
    extent = (X - mean).abs().amax((1, 2), keepdim=True).clamp_min(1e-300)
    g = torch.exp2(torch.ceil(torch.log2(extent)))
    c = torch.round(mean / g) * g
    inexact = ((X - c) + c != X).any(1, keepdim=True)
    c = torch.where(inexact, torch.zeros_like(c), c)
    assert bool(((X - c).abs() <= 4 * g).all()), "a pair far from the origin without an exact shift"
    return c


def distance(X: torch.Tensor) -> torch.Tensor:
    """(K,) distance between the two triangles of X (K, 6, 3) float64 (0 when an edge pierces the other)."""
    # heights within the rounding of the input's own coordinates (64 ulp of its largest, before the shift: a
    # coplanar pair placed at 1e5 m is coplanar to ~1e-11 m only) do not count as crossing the plane
    extent = X.abs().amax((1, 2))
    X = X - exact_shift(X)
    a, b = X[:, :3], X[:, 3:]
    d = triangle_closest_points(a, b).dist.clone()
    hit = torch.zeros_like(d, dtype=torch.bool)
    for t, o in ((a, b), (b, a)):
        nrm = torch.linalg.cross(o[:, 1] - o[:, 0], o[:, 2] - o[:, 0])
        edges = torch.stack([o[:, 1] - o[:, 0], o[:, 2] - o[:, 1], o[:, 0] - o[:, 2]], 1)
        aspect = (edges**2).sum(-1).amax(1) / nrm.norm(
            dim=-1
        )  # longest edge^2 / 2 area: the normal's conditioning
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        side = ((t - o[:, :1]) * nrm[:, None]).sum(-1)  # (K, 3) signed heights of t's vertices over o's plane
        for i in range(3):
            j = (i + 1) % 3
            # an edge crossing the plane (both ends clearly off it: an edge in the plane is the distance's case)
            crosses = (side[:, i] * side[:, j] < 0) & (
                torch.minimum(side[:, i].abs(), side[:, j].abs()) > 64 * EPS64 * extent * aspect
            )
            hit |= crosses & segment_hits_triangle(t[:, i], t[:, j], o)
    # the float test can misjudge edges that pass within rounding of the other triangle's boundary (10 km
    # triangles with nearly parallel edges 1.5 um apart): its hits are confirmed by exact predicates
    for k in torch.nonzero(hit)[:, 0].tolist():
        hit[k] = _pierces_exactly(X[k].tolist())
    d[hit] = 0.0
    return d


def _orient(a, b, c, d) -> Fraction:
    """Exact orientation determinant of four points (float coordinates, rational arithmetic)."""
    u, v, w = ([Fraction(x) - Fraction(y) for x, y in zip(p, d, strict=True)] for p in (a, b, c))
    return (
        u[0] * (v[1] * w[2] - v[2] * w[1])
        - u[1] * (v[0] * w[2] - v[2] * w[0])
        + u[2] * (v[0] * w[1] - v[1] * w[0])
    )


def _pierces_exactly(X: list) -> bool:
    """Whether an edge of one triangle of X (6 vertices) crosses the other triangle, its ends strictly on
    opposite sides of the other's plane (exact)."""
    for t, o in ((X[:3], X[3:]), (X[3:], X[:3])):
        for i in range(3):
            p, q = t[i], t[(i + 1) % 3]
            if _orient(*o, p) * _orient(*o, q) >= 0:
                continue
            s = [_orient(p, q, o[k], o[(k + 1) % 3]) for k in range(3)]
            if all(x >= 0 for x in s) or all(x <= 0 for x in s):
                return True
    return False


def _disk(rng, r):
    t = rng.uniform(0, 2 * np.pi)
    return r * math.sqrt(rng.uniform(0, 1)) * np.array([math.cos(t), math.sin(t)])


def _well_shaped(rng, s):
    """Three xy points of a random well-shaped triangle of circumradius ~s about the origin."""
    t0 = rng.uniform(0, 2 * np.pi)
    ang = t0 + np.array([0.0, 2.1, 4.2]) + rng.uniform(-0.3, 0.3, 3)
    return s * np.stack([np.cos(ang), np.sin(ang)], 1) * rng.uniform(0.7, 1.0, (3, 1))


def _unit2(rng):
    t = rng.uniform(0, 2 * np.pi)
    return np.array([math.cos(t), math.sin(t)])


def _z(xy, z):
    return np.concatenate([xy, np.full((len(xy), 1), 0.0) + np.asarray(z, dtype=float).reshape(-1, 1)], 1)


FEATURES = (
    "vertex-face",
    "edge-edge",
    "face-face",
    "edge-face",
    "parallel-edges",
    "near-parallel-edges",
    "vertex-vertex",
    "coplanar",
)


def feature_pair(kind: str, s: float, gap: float, rng: np.random.Generator) -> np.ndarray:
    """(6, 3) a (rows 0-2) in z <= 0 and b (rows 3-5) in z >= gap with distance exactly ``gap`` (up to the
    rounding of the coordinates): the touching features lie in z = 0 and z = gap, one above the other. The
    coplanar pair lies in z = 0 with a in x <= 0 and b in x >= gap."""
    up = lambda: s * rng.uniform(0.3, 1.0)  # noqa: E731
    if kind in ("vertex-face", "face-face", "edge-face"):
        A = _z(_well_shaped(rng, s), 0.0)
        w = rng.dirichlet([2.0, 2.0, 2.0])
        p = w @ A[:, :2]  # inside a's face
        if kind == "vertex-face":
            B = _z(np.stack([p, p + _disk(rng, s), p + _disk(rng, s)]), [gap, gap + up(), gap + up()])
        elif kind == "face-face":
            xy = _well_shaped(rng, s * rng.uniform(0.2, 0.5)) + p
            B = _z(xy, gap)
        else:
            u = _unit2(rng) * s * rng.uniform(0.05, 0.15)
            B = _z(np.stack([p - u, p + u, p + _disk(rng, s)]), [gap, gap, gap + up()])
        return np.concatenate([A, B])
    if kind in ("edge-edge", "parallel-edges", "near-parallel-edges"):
        u = _unit2(rng)
        la, lb = s * rng.uniform(0.5, 1.0), s * rng.uniform(0.5, 1.0)
        if kind == "edge-edge":
            v = np.array([-u[1], u[0]]) * math.cos(rng.uniform(-1.0, 1.0)) + u * math.sin(rng.uniform(-1, 1))
            v /= np.linalg.norm(v)
        elif kind == "parallel-edges":
            v = u
        else:
            t = 10 ** rng.uniform(-10, -3)
            v = u * math.cos(t) + np.array([-u[1], u[0]]) * math.sin(t)
        c = u * la * rng.uniform(-0.4, 0.4)  # a point on a's edge where b's edge crosses it
        A = _z(np.stack([-u * la / 2, u * la / 2, _disk(rng, s)]), [0.0, 0.0, -up()])
        tb = rng.uniform(-0.4, 0.4) * lb
        B = _z(
            np.stack([c - v * (lb / 2 + tb), c + v * (lb / 2 - tb), c + _disk(rng, s)]),
            [gap, gap, gap + up()],
        )
        return np.concatenate([A, B])
    if kind == "vertex-vertex":
        A = _z(np.stack([np.zeros(2), _disk(rng, s), _disk(rng, s)]), [0.0, -up(), -up()])
        B = _z(np.stack([np.zeros(2), _disk(rng, s), _disk(rng, s)]), [gap, gap + up(), gap + up()])
        return np.concatenate([A, B])
    if kind == "coplanar":
        ya, yb = s * rng.uniform(0.3, 1.0), s * rng.uniform(0.3, 1.0)
        A = np.array([[0.0, -ya / 2, 0.0], [0.0, ya / 2, 0.0], [-up(), s * rng.uniform(-0.5, 0.5), 0.0]])
        off = rng.uniform(-0.4, 0.4) * min(ya, yb)
        B = np.array(
            [
                [gap, off - yb / 2, 0.0],
                [gap, off + yb / 2, 0.0],
                [gap + up(), s * rng.uniform(-0.5, 0.5), 0.0],
            ]
        )
        return np.concatenate([A, B])
    raise ValueError(kind)


def place(
    L: np.ndarray, rng: np.random.Generator, offset: float
) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """(6, 3) float64: the local pair rotated at random (Q) and translated by ``offset`` in a random direction (T);
    returns the pair, Q and T."""
    Q = random_rotation(rng)
    d = rng.standard_normal(3)
    T = offset * d / np.linalg.norm(d)
    return torch.from_numpy((L @ Q.T) + T), Q, T


def design_plane(
    kind: str, gap: float, margin: float, Q: np.ndarray, T: np.ndarray, c: torch.Tensor
) -> torch.Tensor:
    """(4,) the spec's feasible start for the constructed pair in the frame shifted by c (1, 3): the mid-gap plane
    of the construction (normal -e_z, or -e_x for the coplanar pair), scaled by (delta/2 + 1) / (gap/2 + 1)."""
    n = -np.eye(3)[0 if kind == "coplanar" else 2]
    alpha = (margin / 2 + 1) / (gap / 2 + 1)
    nw = Q @ n
    d = gap / 2 - float(nw @ (T - c.reshape(3).numpy()))
    return torch.tensor([*(alpha * nw), alpha * d], dtype=F64)


# ------------------------------------------------------------------------------------------ mpmath reference
def mp_pair(X: torch.Tensor, margin: float, starts: list[torch.Tensor], dps: int = 50):
    """50-digit solve of the plane problem of one pair X (6, 3) float64 (exact inputs) from the first feasible
    plane (4,) of ``starts``.

    Returns (E*, dE/dx (18,), d2P/dx2 (18, 18)) as float64 tensors (mu = 1), or None if no start is feasible."""
    mp = mpmath.mp
    mp.dps = dps
    x = [[mp.mpf(float(v)) for v in row] for row in X.tolist()]
    sg = [1, 1, 1, -1, -1, -1]
    h = mp.mpf(margin) / 2
    lam = mp.mpf(LAMBDA)

    def gaps(p):
        n, d = p[:3], p[3]
        r = mp.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
        if r >= 1:
            return None
        s = [sg[k] * (n[0] * x[k][0] + n[1] * x[k][1] + n[2] * x[k][2] + d) - h for k in range(6)]
        if min(s) <= 0:
            return None
        return r, s

    def energy(p):
        rs = gaps(p)
        if rs is None:
            return None
        r, s = rs
        return lam / (1 - r) + mp.fsum(1 / sk for sk in s)

    def derivs(p):
        r, s = gaps(p)
        n = p[:3]
        u = [ni / r for ni in n]
        g = mp.matrix(4, 1)
        H = mp.matrix(4, 4)
        for i in range(3):
            g[i] = lam / (1 - r) ** 2 * u[i]
            for j in range(3):
                H[i, j] = lam * (
                    2 / (1 - r) ** 3 * u[i] * u[j] + ((i == j) - u[i] * u[j]) / ((1 - r) ** 2 * r)
                )
        for k in range(6):
            ab = [sg[k] * x[k][0], sg[k] * x[k][1], sg[k] * x[k][2], mp.mpf(sg[k])]
            for i in range(4):
                g[i] -= ab[i] / s[k] ** 2
                for j in range(4):
                    H[i, j] += 2 * ab[i] * ab[j] / s[k] ** 3
        return g, H

    for p0 in starts:
        p = [mp.mpf(float(v)) for v in p0.tolist()]
        E = energy(p) if all(math.isfinite(v) for v in p0.tolist()) else None
        if E is not None:
            break
    else:
        return None
    for _ in range(200):
        g, H = derivs(p)
        dp = mp.lu_solve(H, g)
        dec = sum(g[i] * dp[i] for i in range(4))
        if dec <= E * mp.mpf(10) ** (-2 * dps + 8):
            break
        t = mp.mpf(1)
        while True:
            q = [p[i] - t * dp[i] for i in range(4)]
            Eq = energy(q)
            if Eq is not None and Eq <= E:
                break
            t /= 2
            if t < mp.mpf(10) ** -30:
                q, Eq = p, E
                break
        if q == p:
            break
        p, E = q, Eq
    r, s = gaps(p)
    n = p[:3]
    gx = [-sg[k] * n[i] / s[k] ** 2 for k in range(6) for i in range(3)]
    _, Hpp = derivs(p)
    Exx = mp.zeros(18, 18)
    Exp = mp.zeros(18, 4)
    for k in range(6):
        for i in range(3):
            for j in range(3):
                Exx[3 * k + i, 3 * k + j] = 2 * n[i] * n[j] / s[k] ** 3
            xk1 = [x[k][0], x[k][1], x[k][2], mp.mpf(1)]
            for j in range(4):
                Exp[3 * k + i, j] = -sg[k] * (i == j) / s[k] ** 2 + 2 * n[i] * xk1[j] / s[k] ** 3
    Hx = Exx - Exp * mp.inverse(Hpp) * Exp.T
    to = lambda m, shape: torch.tensor([float(v) for v in m], dtype=F64).reshape(shape)  # noqa: E731
    return (
        torch.tensor(float(E), dtype=F64),
        to(gx, (18,)),
        to([Hx[i, j] for i in range(18) for j in range(18)], (18, 18)),
    )


# ------------------------------------------------------------------------------------------------ pair sweep
def _solve_rows(X: torch.Tensor, dtype, **kw):
    """pair_potential_derivatives of the rows of X (K, 6, 3) in ``dtype``, batched; a batch that raises is split in
    halves until the rows that raise are found. Returns value (K,), grad (K, 18), hess (K, 18, 18), plane (K, 4) as
    float64 (NaN where a row raised) and per row None or what it raised ("rejected" for a degenerate triangle)."""
    K = X.shape[0]
    Xi = X.to(dtype)
    try:
        d = pair_potential_derivatives(Xi[:, :3], Xi[:, 3:], **kw)
        return d.value.to(F64), d.grad.to(F64), d.hessian.to(F64), [None] * K, d.plane.to(F64)
    except Exception as e:  # noqa: BLE001 (every failure is a result here)
        if K == 1:
            if isinstance(e, PairSolveError):
                err = "PairSolveError"
            elif isinstance(e, ValueError) and "degenerate" in str(e):
                err = "rejected"
            else:
                err = f"{type(e).__name__}: {e}"
            nan = math.nan
            return (torch.full((1,), nan, dtype=F64), torch.full((1, 18), nan, dtype=F64),
                    torch.full((1, 18, 18), nan, dtype=F64), [err], torch.full((1, 4), nan, dtype=F64))  # fmt: skip
    h = K // 2
    lo, hi = _solve_rows(X[:h], dtype, **kw), _solve_rows(X[h:], dtype, **kw)
    return tuple(lo[i] + hi[i] if i == 3 else torch.cat([lo[i], hi[i]]) for i in range(5))


def judge_pair(
    v, g, h, err, vr, gr, hr, feasible: bool | None, mu: float, kappa: float, dtype, ref_err
) -> tuple[str, dict]:
    """Outcome and errors of one pair against its reference (vr, gr, hr at mu = 1 scaled by mu)."""
    if err is not None:
        if err == "rejected":
            return "rejected", {}
        return ("unconverged" if err == "PairSolveError" else "exception"), {"error": err}
    if math.isnan(v) or not (torch.isfinite(g).all() and torch.isfinite(h).all()):
        return "nonfinite", {}
    if feasible is None:  # within rounding of the margin: either answer is right
        return "ok", {"borderline": True}
    if not feasible:
        if math.isfinite(v):
            return "finite_infeasible", {"error": f"value {v!r} within the margin"}
        return ("ok" if float(g.abs().max()) == 0.0 else "nonfinite"), {}
    if math.isinf(v):
        return "inf_feasible", {}
    if v < 12 * mu * (1 - 1e-12):
        return "wrong_value", {"error": f"value {v!r} below 12 mu"}
    if ref_err is not None:
        return "reference_" + ref_err, {}
    e = {
        "value": _rel(torch.tensor(v, dtype=F64), vr * mu),
        "grad": _rel(g, gr * mu),
        "hess": _rel(h, hr * mu),
    }
    out = dict(e)
    for k in ("value", "grad", "hess"):
        limit = REF_TOL[k] + REF_KAPPA[k] * EPS64 * kappa
        if dtype == F32:
            limit += F32_TOL
        if not e[k] <= limit:
            return f"error_{k}", out
    return "ok", out


def margin_band(X: torch.Tensor, reach: torch.Tensor, margin: float) -> torch.Tensor:
    """(K,) the gap about the margin within which either answer (finite or +inf) is right for the pairs X (K, 6, 3):
    the geometry's rounding, 64 eps of ``reach`` (K,) (the pair's extent plus its distance), or the library's
    (``clear_of_margin``: 64 eps of the coordinates' magnitude in the pair's own frame, under which it calls a pair
    infeasible), whichever is larger."""
    framed = X - frame_origin(X)[:, None]
    return torch.maximum(64 * EPS64 * reach, _MARGIN_RES * framed.abs().flatten(1).amax(1).clamp_min(margin))


def pair_section(cfg: dict, rng: np.random.Generator) -> list[dict]:
    combos = []
    skipped = 0
    for size in cfg["sizes"]:
        for margin in cfg["margins"]:
            seps = [(f"{f:g} margin", f * margin) for f in cfg["sep_margin"]]
            seps += [(f"{f:g} size", f * size) for f in cfg["sep_size"]]
            skipped += sum(g <= margin for _, g in seps)
            seps = [(n, g) for n, g in seps if g > margin] + [
                (f"{f:g} margin", f * margin) for f in (0.5, 0.99)
            ]
            for sep_name, gap in seps:
                for dtype in (F64, F32):
                    combos.append((size, margin, sep_name, gap, dtype))
    no = len(cfg["offsets"])
    # 1. geometry, exact distances and the references of every combination (numba, tol 1e-15, mu = 1)
    groups: dict = {}  # (margin, dtype) -> list of (combo index, rows) to solve together
    data = []
    n_mp = 0
    for ci, (size, margin, _, gap, dtype) in enumerate(tqdm(combos, desc="pair references")):
        kinds = [k for k in FEATURES for _ in range(no)]
        offs = [o for _ in FEATURES for o in cfg["offsets"]]
        placed = [place(feature_pair(k, size, gap, rng), rng, o) for k, o in zip(kinds, offs, strict=True)]
        Xin = torch.stack([p[0] for p in placed]).to(dtype).to(F64)  # (K, 6, 3) the input's bits, in float64
        shift = exact_shift(Xin)
        Xc = Xin - shift
        dist = distance(Xin)
        band = margin_band(Xin, size + dist, margin)
        feas = [
            None if abs(float(dk) - margin) <= float(bk) else bool(dk > margin)
            for dk, bk in zip(dist, band, strict=True)
        ]
        kappa = ((size + dist) / (dist - margin).abs().clamp_min(1e-300)).tolist()
        vr, gr, hr, errr, pr = _solve_rows(
            Xc, F64, mu=1.0, margin=margin, tol=1e-15, max_iter=500, backend="numba"
        )
        # 50 digits: one pair of every near-margin combination and of every mp_every-th other, and every pair whose
        # reference is +inf at a distance beyond the margin (is it feasible?)
        picks = set()
        if gap > margin and (gap <= 10 * margin or ci % cfg["mp_every"] == 0):
            picks.add(int(rng.integers(len(kinds))))
        picks |= {k for k in range(len(kinds)) if feas[k] and errr[k] is None and math.isinf(float(vr[k]))}
        mp_ref = {}
        for k in sorted(picks):
            starts = [pr[k], design_plane(kinds[k], gap, margin, placed[k][1], placed[k][2], shift[k])]
            mp_ref[k] = mp_pair(Xc[k], margin, starts)
            n_mp += 1
        data.append((Xin, kinds, offs, dist, feas, kappa, (vr, gr, hr, errr), mp_ref))
        groups.setdefault((margin, dtype), []).append(ci)
    # 2. the library at its defaults, every (margin, dtype) group in one call per mu and backend
    rows: list[dict] = []
    # mu only scales the result (P = mu E): every mu on the numba backend, the middle one on the (slower) torch one
    mid = cfg["mus"][len(cfg["mus"]) // 2]
    calls = [(key, mu, "numba") for key in groups for mu in cfg["mus"]] + [
        (key, mid, "torch") for key in groups
    ]
    for (margin, dtype), mu, backend in tqdm(calls, desc="pair solves"):
        cis = groups[(margin, dtype)]
        X = torch.cat([data[ci][0] for ci in cis])
        kw = {"mu": mu, "margin": margin, "backend": backend}
        v, g, h, err, _ = _solve_rows(X, dtype, **kw)
        start = 0
        for ci in cis:
            size, _, sep_name, gap, _ = combos[ci]
            Xin, kinds, offs, dist, feas, kappa, (vr, gr, hr, errr), mp_ref = data[ci]
            for k in range(len(kinds)):
                i = start + k
                outcome, e = judge_pair(
                    float(v[i]),
                    g[i],
                    h[i],
                    err[i],
                    vr[k],
                    gr[k],
                    hr[k],
                    feas[k],
                    mu,
                    kappa[k],
                    dtype,
                    errr[k],
                )
                row = {
                    "section": "pair", "feature": kinds[k], "size": size, "separation": sep_name, "gap": gap,
                    "distance": float(dist[k]), "margin": margin, "mu": mu, "dtype": str(dtype).removeprefix("torch."),
                    "backend": backend, "offset": offs[k], "kappa": kappa[k], "outcome": outcome,
                    **{(n if n in ("error", "borderline") else f"err_{n}"): x for n, x in e.items()},
                }  # fmt: skip
                mp = mp_ref.get(k, "absent")
                if mp is None:
                    row["mp_unavailable"] = True
                elif mp != "absent":
                    Em, gm, hm = mp
                    row["mp_true_value"] = float(Em) * mu
                    if errr[k] is None and math.isfinite(float(vr[k])):  # how good the reference itself is
                        mr = {"value": _rel(vr[k], Em), "grad": _rel(gr[k], gm), "hess": _rel(hr[k], hm)}
                        row.update({f"mp_ref_{n}": x for n, x in mr.items()})
                    if math.isfinite(float(v[i])):
                        me = {
                            "value": _rel(v[i], Em * mu),
                            "grad": _rel(g[i], gm * mu),
                            "hess": _rel(h[i], hm * mu),
                        }
                        row.update({f"mp_{n}": x for n, x in me.items()})
                        eps_out = EPS32 if dtype == F32 else EPS64
                        row["mp_cond"] = {n: x / max(eps_out, EPS64 * kappa[k]) for n, x in me.items()}
                        for n in ("value", "grad", "hess"):
                            limit = (
                                MP_TOL[n] + MP_KAPPA[n] * EPS64 * kappa[k] + (F32_TOL if dtype == F32 else 0)
                            )
                            if row["outcome"] == "ok" and not me[n] <= limit:
                                row["outcome"] = f"mp_error_{n}"
                                break
                if row["outcome"] not in ("ok", "rejected"):
                    row["reproducer"] = {"X": Xin[k].tolist(), **kw}
                rows.append(row)
            start += len(kinds)
    tqdm.write(
        f"pair: {len(rows)} cases, {skipped} (size, margin, separation) combinations skipped, {n_mp} mpmath"
    )
    return rows


# ----------------------------------------------------------------------------------------- hypothesis fuzzing
def fuzz_section(cfg: dict, seed: int) -> list[dict]:
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import strategies as st

    rows: list[dict] = []

    def flat_triangle(draw, s, aspect, kind):
        """xy (3, 2) of a sliver (a vertex 1/aspect of the size off the opposite edge) or a needle (one edge
        1/aspect of the others), longest edge ~s, a random in-plane rotation."""
        h = s / aspect
        if kind == "sliver":
            t = draw(st.floats(0.05, 0.95))
            P = np.array([[-s / 2, 0.0], [s / 2, 0.0], [(t - 0.5) * s, h]])
        elif kind == "needle":
            P = np.array([[0.0, 0.0], [s, -h / 2], [s, h / 2]])
        else:
            P = _well_shaped(np.random.default_rng(draw(st.integers(0, 2**31))), s)
        a = draw(st.floats(0, 2 * math.pi))
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return P @ R.T

    @st.composite
    def cases(draw):
        mode = draw(st.sampled_from(["stacked", "near-parallel", "near-coplanar", "shared-plane"]))
        shape_a = draw(st.sampled_from(["sliver", "needle", "plain"]))
        shape_b = draw(st.sampled_from(["sliver", "needle", "plain"]))
        size = 10 ** draw(st.floats(-6, 4))
        aspect_a = 10 ** draw(st.floats(0, 15))
        aspect_b = 10 ** draw(st.floats(0, 15))
        margin = 10 ** draw(st.floats(-6, -2))
        gap = margin * 10 ** draw(st.floats(math.log10(0.3), 6))
        mu = 10 ** draw(st.floats(-12, -2))
        tilt = 10 ** draw(st.floats(-14, -2))
        offset = draw(st.sampled_from([0.0, 1.0, 1e3, 1e5]))
        dtype = draw(st.sampled_from(["float64", "float64", "float32"]))
        backend = draw(st.sampled_from(["numba", "torch"]))
        rot_seed = draw(st.integers(0, 2**31))
        A2 = flat_triangle(draw, size, aspect_a, shape_a)
        B2 = flat_triangle(draw, size * 10 ** draw(st.floats(-1, 1)), aspect_b, shape_b)
        if mode in ("stacked", "near-parallel"):
            # a in z = 0; b's lowest vertex at height gap above a point of a, b flat (stacked: tilted by up to
            # 1 rad, near-parallel: by the tiny tilt) and rising from that vertex
            w = np.array([draw(st.floats(0.01, 1)) for _ in range(3)])
            p = (w / w.sum()) @ A2
            k = int(
                np.argmin(B2 @ np.array([1.0, 0.3]))
            )  # b's "lowest" vertex: the first along this direction
            B2 = B2 - B2[k] + p
            ang = tilt if mode == "near-parallel" else draw(st.floats(0.0, 1.0))
            lift = (
                np.linalg.norm(B2 - p, axis=1)
                * math.sin(ang)
                * np.array([draw(st.floats(0, 1)) for _ in range(3)])
            )
            lift[k] = 0.0
            L = np.concatenate([_z(A2, 0.0), _z(B2, gap + lift)])
        else:
            # side by side in z = 0 (shared plane) or b tilted out of it (near-coplanar): a in x <= 0 touching
            # x = 0 at its rightmost vertex, b in x >= gap touching x = gap at its leftmost vertex, at a common y
            A2 = A2 - A2[np.argmax(A2[:, 0])] * np.array([1.0, 0.0])
            B2 = B2 - B2[np.argmin(B2[:, 0])] * np.array([1.0, 0.0]) + np.array([gap, 0.0])
            ia, ib = np.argmax(A2[:, 0]), np.argmin(B2[:, 0])
            B2[:, 1] += A2[ia, 1] - B2[ib, 1]
            z = np.zeros(3)
            if mode == "near-coplanar":
                z = (B2[:, 0] - gap) * math.sin(tilt) * np.array([draw(st.floats(-1, 1)) for _ in range(3)])
            L = np.concatenate([_z(A2, 0.0), np.concatenate([B2, z[:, None]], 1)])
        return {
            "mode": mode, "shape_a": shape_a, "shape_b": shape_b, "size": size, "aspect_a": aspect_a,
            "aspect_b": aspect_b, "margin": margin, "gap": gap, "mu": mu, "tilt": tilt, "offset": offset,
            "dtype": dtype, "backend": backend, "L": L, "rot_seed": rot_seed,
        }  # fmt: skip

    def check(case: dict) -> dict:
        rng = np.random.default_rng(case["rot_seed"])
        dtype = F32 if case["dtype"] == "float32" else F64
        X = place(case["L"], rng, case["offset"])[0][None].to(dtype).to(F64)  # (1, 6, 3) the input's bits
        margin, mu = case["margin"], case["mu"]
        row = {"section": "fuzz", **{k: v for k, v in case.items() if k not in ("L", "rot_seed")}}
        row["reproducer"] = {"X": X[0].tolist(), "mu": mu, "margin": margin, "backend": case["backend"]}
        d = float(distance(X)[0])
        row["distance"] = d
        extent = float((X[0] - X[0].mean(0)).abs().max())
        band = float(margin_band(X, torch.tensor([extent + d], dtype=F64), margin)[0])
        feasible = None if abs(d - margin) <= band else d > margin
        kappa = (extent + d) / max(abs(d - margin), 1e-300)
        row["kappa"] = kappa
        kw = {"mu": mu, "margin": margin, "backend": case["backend"]}
        try:
            v, g, h, err, _ = _solve_rows(X, dtype, **kw)
        except Exception as e:  # noqa: BLE001 (every failure is a result here)
            row["outcome"], row["error"] = "exception", f"{type(e).__name__}: {e}"
            return row
        if err[0] == "rejected":
            row["outcome"] = "rejected"
            return row
        Xc = X - exact_shift(X)
        vr, gr, hr, errr, _ = _solve_rows(
            Xc, F64, mu=1.0, margin=margin, tol=1e-15, max_iter=500, backend="numba"
        )
        outcome, e = judge_pair(
            float(v[0]), g[0], h[0], err[0], vr[0], gr[0], hr[0], feasible, mu, kappa, dtype, errr[0]
        )
        row.update({(n if n in ("error", "borderline") else f"err_{n}"): x for n, x in e.items()})
        if outcome == "ok" and feasible:
            gs = g[0].reshape(6, 3)
            row["err_sum"] = float(gs.sum(0).abs().max() / gs.abs().sum(0).max().clamp_min(1e-300))
            if not row["err_sum"] <= SUM_TOL + SUM_KAPPA * EPS64 * kappa + (F32_TOL if dtype == F32 else 0.0):
                outcome = "error_sum"
        row["outcome"] = outcome
        if outcome in ("ok", "rejected"):
            del row["reproducer"]
        return row

    @settings(
        max_examples=cfg["fuzz_examples"],
        deadline=None,
        database=None,
        derandomize=True,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(cases())
    def prop(case):
        rows.append(check(case))
        bar.update(1)

    with tqdm(total=cfg["fuzz_examples"], desc="fuzz") as bar:
        prop()
    return rows


# ------------------------------------------------------------------------------------------------ mesh sweep
def _compose(Q: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Pose (6,) of a body after the world rotation Q (3, 3) about the origin: R -> Q R, t -> Q t."""
    qQ = quaternion(rotation_vector_from_matrix(Q))
    w = rotation_vector(quaternion_multiply(qQ, quaternion(pose[3:])))
    return torch.cat([Q @ pose[:3], w])


def rotation_vector_from_matrix(Q: torch.Tensor) -> torch.Tensor:
    from scipy.spatial.transform import Rotation

    return torch.from_numpy(Rotation.from_matrix(Q.numpy()).as_rotvec())


def mesh_section(cfg: dict, rng: np.random.Generator) -> list[dict]:
    ball_mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    box_mesh = trimesh.creation.box((2.0, 2.0, 0.5))
    rows = []
    combos = [
        (pair, scale, gf, dtype)
        for pair in ("ball-ball", "ball-box")
        for scale in cfg["scales"]
        for gf in cfg["mesh_gaps"]
        for dtype in (F64, F32)
    ]
    cache: dict = {}
    for pair, scale, gf, dtype in tqdm(combos, desc="mesh"):
        key = (pair, scale)
        if key not in cache:
            ball = BSH.from_trimesh(ball_mesh.copy().apply_scale(scale))
            other = (
                ball
                if pair == "ball-ball"
                else BSH.from_trimesh(box_mesh.copy().apply_scale(scale), max_edge=0.1 * scale)
            )
            cache[key] = (ball, other)
        ball, other = cache[key]
        margin = 1e-3 * scale
        gap = gf * margin if gf < 0.01 else gf * scale  # 1.5e-3 -> 1.5 margins
        # b = the ball above a (a ball or the box's top face, z = 0.25 scale), a random spin of the ball
        za = 0.0
        zb = (
            1.0 if pair == "ball-ball" else 0.75
        ) * scale + gap  # centre distance 2 R, or box half-height + R
        pa = torch.tensor([0.0, 0.0, za, *rng.uniform(-1, 1, 3)], dtype=F64)
        if pair == "ball-box":
            pa[3:] = 0.0
        pb = torch.tensor(
            [*(rng.uniform(-0.3, 0.3, 2) * scale * (pair == "ball-box")), zb, *rng.uniform(-2, 2, 3)]
        )
        pb = pb.to(F64)
        Q = torch.from_numpy(random_rotation(rng))
        pa, pb = _compose(Q, pa), _compose(Q, pb)
        for offset in cfg["offsets"]:
            d = rng.standard_normal(3)
            T = torch.from_numpy(offset * d / np.linalg.norm(d))
            qa = torch.cat([pa[:3] + T, pa[3:]]).to(dtype)
            qb = torch.cat([pb[:3] + T, pb[3:]]).to(dtype)
            q = torch.stack([qa, qb]).to(F64)  # the input's bits
            c = exact_shift(q[None, :, :3])[0]  # (1, 3)
            qr = torch.cat([q[:, :3] - c, q[:, 3:]], 1)
            kw = {"mu": 1e-8, "margin": margin}
            row = {
                "section": "mesh", "pair": pair, "scale": scale, "gap": gap, "margin": margin, "offset": offset,
                "dtype": str(dtype).removeprefix("torch."),
            }  # fmt: skip
            try:
                ref = mesh_potential_derivatives(
                    ball if pair == "ball-ball" else other, qr[0], ball, qr[1], **kw
                )
                out = mesh_potential_derivatives(ball if pair == "ball-ball" else other, qa, ball, qb, **kw)
            except PairSolveError as e:
                row.update(outcome="unconverged", error=str(e))
                rows.append(row)
                continue
            except Exception as e:  # noqa: BLE001
                row.update(outcome="exception", error=f"{type(e).__name__}: {e}")
                rows.append(row)
                continue
            v, g, h = out.value.to(F64), out.grad.to(F64), out.hessian.to(F64)
            row["leaf_pairs"] = int(out.stats.get("leaf_pairs", -1))
            if torch.isnan(v) or not (torch.isfinite(g).all() and torch.isfinite(h).all()):
                row["outcome"] = "nonfinite"
            elif bool(torch.isinf(v)) != bool(torch.isinf(ref.value)) or (
                dtype == F64 and bool(torch.isinf(v))
            ):
                row["outcome"] = "inf_feasible" if bool(torch.isinf(v)) else "finite_infeasible"
            elif bool(torch.isinf(v)):
                row["outcome"] = "ok"
                row["infeasible_after_rounding"] = True
            else:
                e = {"value": _rel(v, ref.value), "grad": _rel(g, ref.grad), "hess": _rel(h, ref.hessian)}
                row.update({f"err_{n}": x for n, x in e.items()})
                row["outcome"] = "ok"
                for n in ("value", "grad", "hess"):
                    if not e[n] <= MESH_TOL[n] + (F32_TOL if dtype == F32 else 0.0):
                        row["outcome"] = f"error_{n}"
                        break
            if row["outcome"] != "ok":
                row["reproducer"] = {"pose_a": qa.tolist(), "pose_b": qb.tolist(), **kw}
            rows.append(row)
    return rows


# --------------------------------------------------------------------------------------------- stepper sweep
def _scene(kind: str, scale: float):
    s = scale
    kw = {
        "dt": 0.01 * math.sqrt(s),
        "margin": 1e-3 * s,
        "mu": 1e-8 * s**5,
        "ccd_spacing": 0.01 * s,
        "newton_tol": max(1e-9 * s, NEWTON_FLOOR),
        "friction_eps_v": 1e-4 * math.sqrt(s),
    }
    floor = rigid_body(trimesh.creation.box((4 * s, 4 * s, 0.2 * s)), kind="static")
    ball = rigid_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1 * s))
    if kind == "ball-drop":
        scene = Scene([floor, ball], **kw)
        q = [[0, 0, -0.1 * s, 0, 0, 0], [0.01 * s, 0, 0.25 * s, 0.3, 0.2, 0.1]]
        v = [[0.0] * 6, [0.0] * 6]
    elif kind == "box-slide":
        box = rigid_body(trimesh.creation.box((0.2 * s, 0.15 * s, 0.1 * s)))
        scene = Scene([floor, box], friction=0.5, **kw)
        q = [[0, 0, -0.1 * s, 0, 0, 0], [0, 0, 0.05 * s + 2e-3 * s, 0, 0, 0]]
        v = [[0.0] * 6, [math.sqrt(s), 0, 0, 0, 0, 0]]
    elif kind == "ball-collide":
        scene = Scene([ball, ball], gravity=(0.0, 0.0, 0.0), **kw)
        q = [[-0.15 * s, 0, 0, 0, 0, 0], [0.15 * s, 0.02 * s, 0, 0.5, 0, 0]]
        v = [[2 * math.sqrt(s), 0, 0, 0, 0, 0], [-2 * math.sqrt(s), 0, 0, 0, 0, 0]]
    else:
        raise ValueError(kind)
    return scene, torch.tensor(q, dtype=F64), torch.tensor(v, dtype=F64)


def _run_steps(scene: Scene, q0: torch.Tensor, v0: torch.Tensor, steps: int):
    """Poses after each step (T + 1, N, 6), and (outcome, error) of the first failure."""
    state = scene.initial_state(q0, v0)
    qs = [state.q]
    pairs = torch.cat([torch.zeros(len(scene.pairs), 1, dtype=torch.long), scene.pairs], 1)
    try:
        for _ in range(steps):
            state = step(scene, state, Action())
            qs.append(state.q)
            if not bool(torch.isfinite(state.q).all()):
                return torch.stack(qs), "nonfinite", "non-finite poses"
            value = scene.contact_model.evaluate(state.q.detach()[None], pairs, 0).value
            if bool(torch.isinf(value).any()):
                return torch.stack(qs), "penetration", f"pairs {scene.pairs[torch.isinf(value)].tolist()}"
    except StepError as e:
        return torch.stack(qs), "unconverged", str(e)
    except Exception as e:  # noqa: BLE001
        return torch.stack(qs), "exception", f"{type(e).__name__}: {e}"
    return torch.stack(qs), "ok", None


def step_section(cfg: dict) -> list[dict]:
    rows = []
    combos = [(k, s) for k in ("ball-drop", "box-slide", "ball-collide") for s in cfg["step_scales"]]
    for kind, scale in tqdm(combos, desc="step"):
        scene, q0, v0 = _scene(kind, scale)
        T = torch.tensor([1e3, -1e3, 1e3], dtype=F64)  # exactly representable
        t0 = time.perf_counter()
        qs, outcome, error = _run_steps(scene, q0, v0, cfg["steps"])
        q1 = q0.clone()
        q1[:, :3] += T
        qs1, outcome1, error1 = _run_steps(scene, q1, v0, cfg["steps"])
        row = {
            "section": "step", "scene": kind, "scale": scale, "dt": scene.dt, "margin": scene.margin,
            "mu": scene.contact.stiffness, "steps": cfg["steps"], "outcome": outcome, "error": error,
            "outcome_translated": outcome1, "error_translated": error1, "steps_done": len(qs) - 1,
            "wall_s": time.perf_counter() - t0,
        }  # fmt: skip
        if outcome == "ok" and outcome1 != "ok":
            row["outcome"], row["error"] = outcome1, f"translated by 1e3 m: {error1}"
        n = min(len(qs), len(qs1))
        dq = qs1[:n, :, :3] - T - qs[:n, :, :3]
        row["translation_diff"] = float(dq.abs().max() / scale)
        row["rotation_diff"] = float((qs1[:n, :, 3:] - qs[:n, :, 3:]).abs().max())
        moved = qs[-1, scene.dynamic, :3] - q0[scene.dynamic, :3]
        row["moved"] = float(moved.norm(dim=1).max() / scale)
        if row["outcome"] == "ok" and not max(row["translation_diff"], row["rotation_diff"]) <= STEP_TOL:
            row["outcome"] = "translation"
        rows.append(row)
        tqdm.write(
            f"{kind} scale {scale:g}: {row['outcome']} ({row['steps_done']} steps, moved {row['moved']:.3g} scales, "
            f"translated diff {row['translation_diff']:.2e}, {row['wall_s']:.0f} s)"
        )
    return rows


# ----------------------------------------------------------------------------------------------------- report
FULL = {
    "sizes": [1e-6, 1e-4, 1e-2, 1.0, 1e2, 1e4],
    "margins": [1e-6, 1e-4, 1e-2],
    "sep_margin": [1.01, 1.5, 10.0],
    "sep_size": [0.1, 1.0, 1e3, 1e6],
    "mus": [1e-12, 1e-8, 1e-2],
    "offsets": [0.0, 1e2, 1e5],
    "mp_every": 4,
    "fuzz_examples": 1000,
    "scales": [1e-3, 1e-2, 1e-1, 1.0, 1e1, 1e2],
    "mesh_gaps": [1.5e-3, 0.01, 0.3, 3.0],
    "step_scales": [1e-3, 1e-2, 1e-1, 1.0, 1e1, 1e2],
    "steps": 50,
}
QUICK = {
    "sizes": [1e-6, 1.0, 1e4],
    "margins": [1e-6, 1e-2],
    "sep_margin": [1.01],
    "sep_size": [1.0, 1e6],
    "mus": [1e-8],
    "offsets": [0.0, 1e5],
    "mp_every": 8,
    "fuzz_examples": 150,
    "scales": [1e-3, 1e2],
    "mesh_gaps": [1.5e-3, 0.3],
    "step_scales": [1e-3, 1e2],
    "steps": 15,
}
# tests/test_stress_script.py: the script end to end in seconds, on well-conditioned cases only
TINY = {
    "sizes": [1.0],
    "margins": [1e-3],
    "sep_margin": [],
    "sep_size": [1.0],
    "mus": [1e-8],
    "offsets": [1e5],
    "mp_every": 1,
    "fuzz_examples": 15,
    "scales": [1.0],
    "mesh_gaps": [0.3],
    "step_scales": [1.0],
    "steps": 3,
}
SECTIONS = ("pair", "fuzz", "mesh", "step")
ERRORS = {
    "pair": ("value", "grad", "hess"),
    "fuzz": ("value", "grad", "hess", "sum"),
    "mesh": ("value", "grad", "hess"),
}


def summarise(rows: list[dict], sections, revision, wall: dict) -> str:
    lines = [
        f"Numerical-robustness sweep (cfd_torch {revision}): "
        f"{sum(r['outcome'] not in ('ok', 'rejected') for r in rows)} failures in {len(rows)} cases.",
        "",
        "| section | cases | ok | rejected | failures (by kind) | worst error vs reference (value / grad / hess) | "
        "wall (s) |",
        "|---|---:|---:|---:|---|---|---:|",
    ]
    for sec in sections:
        rs = [r for r in rows if r["section"] == sec]
        c = Counter(r["outcome"] for r in rs)
        fails = ", ".join(f"{k} {n}" for k, n in sorted(c.items()) if k not in ("ok", "rejected")) or "0"
        if sec == "step":
            worst = "translated 1e3 m: " + (
                f"{max((max(r['translation_diff'], r['rotation_diff']) for r in rs), default=0):.1e} of the scale"
            )
        else:
            worst = " / ".join(
                f"{max((r.get(f'err_{n}', 0.0) for r in rs if r['outcome'] == 'ok'), default=0.0):.1e}"
                for n in ERRORS[sec]
            )
            if sec == "fuzz":
                worst += " (last: vertex-sum residual)"
        lines.append(
            f"| {sec} | {len(rs)} | {c['ok']} | {c['rejected']} | {fails} | {worst} | {wall.get(sec, 0):.0f} |"
        )
    mp_rows = [r for r in rows if "mp_value" in r]
    if mp_rows:
        lines += [
            "",
            f"Against the 50-digit mpmath reference ({len(mp_rows)} pair cases; "
            "kappa = (size + gap) / (gap - margin)):",
            "",
        ]
        lines += [
            "| dtype | kappa | cases | library: worst value / grad / hess | worst / max(eps_out, eps kappa) | "
            "tight reference (tol 1e-15): worst value / grad / hess |",
            "|---|---|---:|---|---|---|",
        ]
        for dt in ("float64", "float32"):
            for lo, hi in ((0, 1e3), (1e3, 1e7), (1e7, math.inf)):
                sel = [r for r in mp_rows if r["dtype"] == dt and lo <= r["kappa"] < hi]
                if not sel:
                    continue
                w = " / ".join(f"{max(r[f'mp_{n}'] for r in sel):.1e}" for n in ("value", "grad", "hess"))
                wc = " / ".join(f"{max(r['mp_cond'][n] for r in sel):.2g}" for n in ("value", "grad", "hess"))
                wr = " / ".join(
                    f"{max((r.get(f'mp_ref_{n}', 0.0) for r in sel), default=0.0):.1e}"
                    for n in ("value", "grad", "hess")
                )
                lines.append(f"| {dt} | [{lo:g}, {hi:g}) | {len(sel)} | {w} | {wc} | {wr} |")
    pair_rows = [r for r in rows if r["section"] == "pair" and r["outcome"] == "ok" and "err_value" in r]
    if pair_rows:
        lines += [
            "",
            "Pair section, worst error vs the centred reference by size (float64 / float32 inputs):",
            "",
        ]
        lines += [
            "| size (m) | float64 value / grad / hess | float32 value / grad / hess |",
            "|---:|---|---|",
        ]
        for size in sorted({r["size"] for r in pair_rows}):
            cells = []
            for dt in ("float64", "float32"):
                sel = [r for r in pair_rows if r["size"] == size and r["dtype"] == dt]
                cells.append(
                    " / ".join(
                        f"{max((r[f'err_{n}'] for r in sel), default=0):.1e}"
                        for n in ("value", "grad", "hess")
                    )
                )
            lines.append(f"| {size:g} | {cells[0]} | {cells[1]} |")
    fails = [r for r in rows if r["outcome"] not in ("ok", "rejected")]
    if fails:
        lines += ["", "Failures (first 30; every one is in stress.json with a reproducer):", ""]
        for r in fails[:30]:
            desc = {k: v for k, v in r.items() if k not in ("reproducer", "mp_cond")}
            lines.append(f"- {json.dumps(desc)}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/stress"))
    ap.add_argument(
        "--quick", action="store_true", help="a smoke run of under a minute (16 s on an idle machine)"
    )
    ap.add_argument(
        "--tiny", action="store_true", help="a few seconds per section (the test suite's smoke test)"
    )
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    ap.add_argument("--seed", type=nonnegative_int, default=0, help="seed of every random draw")
    args = ap.parse_args(argv)
    cfg = dict(TINY if args.tiny else QUICK if args.quick else FULL)
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    rows: list[dict] = []
    wall: dict = {}
    for sec in args.sections:
        t0 = time.perf_counter()
        if sec == "pair":
            rows += pair_section(cfg, rng)
        elif sec == "fuzz":
            rows += fuzz_section(cfg, args.seed)
        elif sec == "mesh":
            rows += mesh_section(cfg, rng)
        else:
            rows += step_section(cfg)
        wall[sec] = time.perf_counter() - t0
    revision = git_revision()
    text = summarise(rows, args.sections, revision, wall)
    out = {
        "cfd_torch_commit": revision,
        "torch": torch.__version__,
        "mode": "tiny" if args.tiny else "quick" if args.quick else "full",
        "seed": args.seed,
        "config": cfg,
        "thresholds": {
            "reference": REF_TOL,
            "reference_per_eps_kappa": REF_KAPPA,
            "float32_extra": F32_TOL,
            "mpmath": MP_TOL,
            "mpmath_per_eps_kappa": MP_KAPPA,
            "vertex_sum": SUM_TOL,
            "vertex_sum_per_eps_kappa": SUM_KAPPA,
            "mesh": MESH_TOL,
            "step_translation": STEP_TOL,
        },  # fmt: skip
        "wall_s": wall,
        "failures": sum(r["outcome"] not in ("ok", "rejected") for r in rows),
        "cases": rows,
    }
    (args.out / "stress.json").write_text(json.dumps(out, indent=1, default=float))
    (args.out / "stress.md").write_text(text)
    print(text)
    return int(out["failures"] > 0)


if __name__ == "__main__":
    sys.exit(main())
