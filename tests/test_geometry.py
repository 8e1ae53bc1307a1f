"""Closest points between two triangles: torch and numba against a brute-force oracle (float64).

The oracle solves the closest-point problem on every pair of faces (vertex, edge or interior) of the two
triangles without constraints, clamps each solution into both triangles and keeps the best: the optimum of the
convex problem is the unconstrained optimum of some face pair, and every clamped candidate is a feasible pair
of points, so the minimum is exact. It is itself checked against scipy's SLSQP, and the results against a
separating-plane certificate.
"""

from __future__ import annotations

import itertools

import numba
import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from cfd_torch._geometry import TriangleClosestPoints, tri_tri_closest_nb, triangle_closest_points

EPS = np.finfo(np.float64).eps
RTOL = 1e-10
ATOL = 1e-14

# ------------------------------------------------------------------------------------------------------------
# Oracle and checks

_FACES = [(0,), (1,), (2,), (0, 1), (1, 2), (0, 2), (0, 1, 2)]


def _clamp_simplex(x: np.ndarray) -> np.ndarray:
    """Clamp affine coordinates (N, m) (weights of vertices 1..m; vertex 0 gets the rest) into the simplex."""
    x = np.maximum(x, 0.0)
    s = x.sum(axis=1, keepdims=True)
    return np.where(s > 1.0, x / np.where(s > 1.0, s, 1.0), x)


def _oracle(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest points by enumeration of the 7 x 7 face pairs. A, B: (N, 3, 3). Returns dist, qa, qb."""
    o = A[:, :1]  # work relative to A0, like the implementations
    A, B = A - o, B - o
    n = A.shape[0]
    best = np.full(n, np.inf)
    qa = np.zeros((n, 3))
    qb = np.zeros((n, 3))
    for fa, fb in itertools.product(_FACES, _FACES):
        a0, b0 = A[:, fa[0]], B[:, fb[0]]
        ea = A[:, list(fa[1:])] - a0[:, None]  # (N, ma, 3)
        eb = B[:, list(fb[1:])] - b0[:, None]  # (N, mb, 3)
        ma, mb = ea.shape[1], eb.shape[1]
        if ma + mb:
            m = np.concatenate((ea, -eb), axis=1).transpose(0, 2, 1)  # (N, 3, ma + mb)
            # Least squares by SVD, applied as V (U^T rhs / S): forming pinv(m) first loses the in-plane
            # accuracy that tiny gaps between nearly parallel edges need.
            u, sv, vt = np.linalg.svd(m, full_matrices=False)
            keep = sv > 8 * EPS * sv[:, :1]
            y = np.einsum("nij,ni->nj", u, b0 - a0) / np.where(keep, sv, 1.0)
            x = np.einsum("nji,nj->ni", vt, np.where(keep, y, 0.0))
        else:
            x = np.zeros((n, 0))
        pa = a0 + np.einsum("nm,nmj->nj", _clamp_simplex(x[:, :ma]), ea)
        pb = b0 + np.einsum("nm,nmj->nj", _clamp_simplex(x[:, ma:]), eb)
        d = np.linalg.norm(pa - pb, axis=1)
        better = d < best
        best = np.where(better, d, best)
        qa[better], qb[better] = pa[better], pb[better]
    return best, qa + o[:, 0], qb + o[:, 0]


def _coord_mag(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.maximum(np.abs(A).max(axis=(1, 2)), np.abs(B).max(axis=(1, 2)))


def _size(T: np.ndarray) -> np.ndarray:
    return np.linalg.norm(T - T[:, [1, 2, 0]], axis=2).max(axis=1)


def _assert_in_triangle(q: np.ndarray, T: np.ndarray, mag: np.ndarray, name: str) -> None:
    """Barycentric check of q (N, 3) in triangles T (N, 3, 3), tolerance scaled by the coordinate rounding."""
    e = np.stack((T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), 1)  # (N, 2, 3)
    r = q - T[:, 0]
    uv = np.linalg.solve(e @ e.transpose(0, 2, 1), (e @ r[:, :, None]))[..., 0]
    e1, e2 = e[:, 0], e[:, 1]
    res = np.linalg.norm(r - uv[:, :1] * e1 - uv[:, 1:] * e2, axis=1)
    size = _size(T)
    tol = 1e-9 + 64 * EPS * mag / size
    w = np.stack((1 - uv.sum(1), uv[:, 0], uv[:, 1]), 1)
    bad = (w.min(1) < -tol) | (res > 64 * EPS * mag + 1e-12 * size)
    assert not bad.any(), f"{name} outside its triangle: w={w[bad][:3]}, res={res[bad][:3]}"


def _check(A, B, dist, qa, qb, ref, name, in_triangle=True):
    """dist vs the reference, |qa - qb| = dist, qa in A and qb in B."""
    mag = _coord_mag(A, B)
    err = np.abs(dist - ref)
    bad = err > RTOL * ref + ATOL
    assert not bad.any(), f"{name}: dist {dist[bad][:3]} vs ref {ref[bad][:3]}, err {err[bad][:3]}"
    gap = np.linalg.norm(qa - qb, axis=1)
    bad = np.abs(gap - dist) > RTOL * dist + 8 * EPS * mag
    assert not bad.any(), f"{name}: |qa - qb| {gap[bad][:3]} != dist {dist[bad][:3]}"
    if in_triangle:
        _assert_in_triangle(qa, A, mag, f"{name} qa")
        _assert_in_triangle(qb, B, mag, f"{name} qb")


@numba.njit(parallel=True)
def _nb_batch(A, B):
    n = A.shape[0]
    d2 = np.empty(n)
    q = np.empty((n, 6))
    for k in numba.prange(n):
        d2[k] = tri_tri_closest_nb(A[k], B[k], q[k])
    return d2, q


def _run_both(A: np.ndarray, B: np.ndarray):
    """Torch and numba results as numpy: (dist, qa, qb) each."""
    res = triangle_closest_points(torch.from_numpy(A), torch.from_numpy(B))
    d2, q = _nb_batch(np.ascontiguousarray(A), np.ascontiguousarray(B))
    return (res.dist.numpy(), res.qa.numpy(), res.qb.numpy()), (np.sqrt(d2), q[:, :3], q[:, 3:])


def _check_all(A, B, name, exact=None, unique=False, in_triangle=True):
    """Both implementations against the oracle (and a closed form if given) and against each other."""
    ref, _, _ = _oracle(A, B)
    (dt, qat, qbt), (dn, qan, qbn) = _run_both(A, B)
    _check(A, B, dt, qat, qbt, ref, f"{name} torch", in_triangle)
    _check(A, B, dn, qan, qbn, ref, f"{name} numba", in_triangle)
    np.testing.assert_allclose(dn, dt, rtol=1e-13, atol=2 * EPS * _coord_mag(A, B).max(), err_msg=name)
    if unique:  # closest points are unique: both implementations find the same ones
        tol = 1e-6 * _size(A).max() + 1e-12 * _coord_mag(A, B).max()
        np.testing.assert_allclose(qan, qat, atol=tol, rtol=0, err_msg=name)
        np.testing.assert_allclose(qbn, qbt, atol=tol, rtol=0, err_msg=name)
    if exact is not None:
        tol = RTOL * exact + 64 * EPS * (_coord_mag(A, B) + exact)
        assert np.all(np.abs(ref - exact) <= tol), f"{name}: oracle {ref[:3]} vs closed form {exact[:3]}"
    return dt


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.diag(r))


# ------------------------------------------------------------------------------------------------------------
# Oracle self-check


def test_oracle_matches_slsqp():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((8, 3, 3))
    B = rng.standard_normal((8, 3, 3)) + 3 * rng.standard_normal((8, 1, 3))
    ref, qa, qb = _oracle(A, B)
    for k in range(8):

        def f(x, k=k):
            pa = A[k, 0] + x[0] * (A[k, 1] - A[k, 0]) + x[1] * (A[k, 2] - A[k, 0])
            pb = B[k, 0] + x[2] * (B[k, 1] - B[k, 0]) + x[3] * (B[k, 2] - B[k, 0])
            return float(((pa - pb) ** 2).sum())

        cons = [
            {"type": "ineq", "fun": lambda x: 1 - x[0] - x[1]},
            {"type": "ineq", "fun": lambda x: 1 - x[2] - x[3]},
        ]
        opts = {"ftol": 1e-15}
        x0s = rng.uniform(0, 0.5, (4, 4))
        best = min(
            minimize(f, x0, method="SLSQP", bounds=[(0, 1)] * 4, constraints=cons, options=opts).fun
            for x0 in x0s
        )
        assert abs(np.sqrt(max(best, 0.0)) - ref[k]) <= 1e-6 * ref[k]
        assert ref[k] <= np.sqrt(best) + 1e-12  # the oracle is never beaten
        assert abs(np.linalg.norm(qa[k] - qb[k]) - ref[k]) <= 1e-14 * ref[k]


# ------------------------------------------------------------------------------------------------------------
# Adversarial constructions: canonical frame, triangle size s, distance g; then a random rigid motion.


def _vertex_face(s, g):
    A = [(-s, -s, 0), (2 * s, -s, 0), (-s, 2 * s, 0)]
    B = [(0.1 * s, 0.2 * s, g), (1.1 * s, 0.2 * s, g + s), (0.1 * s, 1.2 * s, g + 0.5 * s)]
    return A, B, g, True


def _face_vertex(s, g):
    A, B, d, u = _vertex_face(s, g)
    return B, A, d, u


def _vertex_edge(s, g):
    A = [(-s, 0, 0), (s, 0, 0), (0, -s, 0)]
    B = [(0.2 * s, 0, g), (1.2 * s, s, g + s), (-0.8 * s, s, g + 0.5 * s)]
    return A, B, g, True


def _edge_edge_cross(s, g):
    A = [(-s, 0, 0), (s, 0, 0), (0, 0.3 * s, -s)]
    B = [(0.37 * s, -0.8 * s, g), (0.37 * s, 1.1 * s, g), (0.6 * s, 0, g + s)]
    return A, B, g, True


def _edge_edge_near_parallel(delta):
    def make(s, g):
        A = [(-s, 0, 0), (s, 0, 0), (0, 0.3 * s, -s)]
        B = [(-0.5 * s, -delta * s, g), (1.5 * s, delta * s, g), (0.5 * s, 0.3 * s, g + s)]
        return A, B, g, True

    return make


def _edge_edge_parallel(s, g):
    A = [(-s, 0, 0), (s, 0, 0), (0, 0.3 * s, -s)]
    B = [(-0.5 * s, 0, g), (1.5 * s, 0, g), (0.5 * s, 0.3 * s, g + s)]
    return A, B, g, False


def _edge_edge_parallel_apart(s, g):
    A = [(-s, 0, 0), (s, 0, 0), (0, 0.3 * s, -s)]
    B = [(2 * s, 0, g), (3 * s, 0, g), (2.5 * s, 0.3 * s, g + s)]
    return A, B, np.hypot(s, g), True


def _faces_parallel_offset(s, g):
    A = [(0, 0, 0), (s, 0, 0), (0, s, 0)]
    B = [(0.3 * s, 0.3 * s, g), (1.3 * s, 0.3 * s, g), (0.3 * s, 1.3 * s, g)]
    return A, B, g, False


def _faces_stacked(s, g):
    A = [(0, 0, 0), (s, 0, 0), (0, s, 0)]
    B = [(0, 0, g), (s, 0, g), (0, s, g)]
    return A, B, g, False


def _faces_star(s, g):  # B is A turned by 180 degrees about its centroid: a star of David seen from above
    A = [(0, 0, 0), (s, 0, 0), (0, s, 0)]
    c = s / 3
    B = [(2 * c - x, 2 * c - y, g) for x, y, _ in A]
    return A, B, g, False


def _coplanar_edge_edge(s, g):
    A = [(-s, 0, 0), (0, -s, 0), (0, s, 0)]
    B = [(g, -0.5 * s, 0), (g, 0.5 * s, 0), (g + s, 0, 0)]
    return A, B, g, False


def _coplanar_vertex_edge(s, g):
    A = [(-s, 0, 0), (0, -s, 0), (0, s, 0)]
    B = [(g, 0.2 * s, 0), (g + s, -s, 0), (g + s, s, 0)]
    return A, B, g, True


def _coplanar_vertex_vertex(s, g):
    A = [(0, 0, 0), (-s, -0.5 * s, 0), (-s, 0.5 * s, 0)]
    B = [(g, 0, 0), (g + s, -0.5 * s, 0), (g + s, 0.5 * s, 0)]
    return A, B, g, True


CASES = {
    "vertex_face": _vertex_face,
    "face_vertex": _face_vertex,
    "vertex_edge": _vertex_edge,
    "edge_edge_cross": _edge_edge_cross,
    "edge_edge_near_parallel_1e-4": _edge_edge_near_parallel(1e-4),
    "edge_edge_near_parallel_1e-8": _edge_edge_near_parallel(1e-8),
    "edge_edge_near_parallel_1e-12": _edge_edge_near_parallel(1e-12),
    "edge_edge_parallel": _edge_edge_parallel,
    "edge_edge_parallel_apart": _edge_edge_parallel_apart,
    "faces_parallel_offset": _faces_parallel_offset,
    "faces_stacked": _faces_stacked,
    "faces_star": _faces_star,
    "coplanar_edge_edge": _coplanar_edge_edge,
    "coplanar_vertex_edge": _coplanar_vertex_edge,
    "coplanar_vertex_vertex": _coplanar_vertex_vertex,
}
SCALES = (1e-7, 1.0)
GAPS = (1e-9, 1e-6, 1e-3, 1.0, 1e4)


@pytest.mark.parametrize("case", list(CASES))
def test_adversarial(case):
    rng = np.random.default_rng(list(CASES).index(case))
    As, Bs, exact, unique = [], [], [], None
    for s, g in itertools.product(SCALES, GAPS):
        a, b, d, unique = CASES[case](s, g)
        for swap, _ in itertools.product((False, True), range(3)):  # each construction both ways round
            R, t = _random_rotation(rng), s * rng.standard_normal(3)
            a_, b_ = (b, a) if swap else (a, b)
            a_, b_ = np.asarray(a_, float), np.asarray(b_, float)
            # rotate the vertex order too, so every feature index takes its turn
            roll_a, roll_b = rng.integers(3), rng.integers(3)
            As.append(np.roll(a_, roll_a, axis=0) @ R.T + t)
            Bs.append(np.roll(b_, roll_b, axis=0) @ R.T + t)
            exact.append(d)
    A, B = np.stack(As), np.stack(Bs)
    _check_all(A, B, case, exact=np.asarray(exact), unique=unique)


def test_unrotated_axis_aligned():
    """The constructions exactly as written (exact zeros, exactly parallel edges and faces)."""
    for case, make in CASES.items():
        items = [make(s, g) for s, g in itertools.product(SCALES, GAPS)]
        A = np.asarray([it[0] for it in items], float)
        B = np.asarray([it[1] for it in items], float)
        exact = np.asarray([it[2] for it in items], float)
        _check_all(A, B, case, exact=exact, unique=items[0][3])
        _check_all(B, A, case + " swapped", exact=exact, unique=items[0][3])


def test_translation_invariance():
    """Rounding follows the size of the configuration, not its distance from the origin. On a 2^-30 grid a
    translation by multiples of 2^10 is exact, and so are all differences to the first vertex of a: dist must
    not change at all."""
    rng = np.random.default_rng(99)
    items = [make(1.0, g) for make in CASES.values() for g in (2.0**-30, 2.0**-20, 2.0**-10, 1.0)]
    A = np.round(np.asarray([it[0] for it in items], float) * 2**30) / 2**30
    B = np.round(np.asarray([it[1] for it in items], float) * 2**30) / 2**30
    shift = 1024.0 * rng.integers(-8, 9, (len(items), 1, 3))
    (dt0, _, _), (dn0, _, _) = _run_both(A, B)
    (dt1, qat, qbt), (dn1, qan, qbn) = _run_both(A + shift, B + shift)
    assert np.array_equal(dt0, dt1) and np.array_equal(dn0, dn1)
    _check(A + shift, B + shift, dt1, qat, qbt, _oracle(A, B)[0], "translated torch")
    _check(A + shift, B + shift, dn1, qan, qbn, _oracle(A, B)[0], "translated numba")


# ------------------------------------------------------------------------------------------------------------
# Random pairs


def _random_pairs(rng, n, scale_lo=1e-7, scale_hi=1.0, gap_lo=1e-9, gap_hi=1e4):
    """Random triangle pairs separated along a random direction by a log-uniform gap (distance >= gap)."""
    sa = np.exp(rng.uniform(np.log(scale_lo), np.log(scale_hi), n))[:, None, None]
    sb = sa * np.exp(rng.uniform(-2, 2, n))[:, None, None]
    A, B = sa * rng.standard_normal((n, 3, 3)), sb * rng.standard_normal((n, 3, 3))
    return _separate(rng, A, B, gap_lo, gap_hi)


def _separate(rng, A, B, gap_lo, gap_hi):
    """Move B along a random direction u until a plane normal to u separates it from A by a random gap."""
    n = A.shape[0]
    gap = np.exp(rng.uniform(np.log(gap_lo), np.log(gap_hi), n))
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    shift = gap + (A @ u[:, :, None]).max(axis=(1, 2)) - (B @ u[:, :, None]).min(axis=(1, 2))
    return A, B + shift[:, None, None] * u[:, None, :]


def test_random_prescribed_distance():
    """Generic pairs moved to an exact distance g along their closest direction (the Minkowski difference then
    touches the ball of radius g exactly there), g log-uniform in [1e-9, 1e4]."""
    rng = np.random.default_rng(1)
    n = 3000
    A, B = _random_pairs(rng, n, scale_lo=1e-3, gap_lo=0.5, gap_hi=2.0)
    d, qa, qb = _oracle(A, B)
    g = np.exp(rng.uniform(np.log(1e-9), np.log(1e4), n))
    mag = _coord_mag(A, B)  # the move below rounds B at this magnitude: g is exact up to that
    B = B - ((1 - g / d)[:, None] * (qb - qa))[:, None, :]
    dt = _check_all(A, B, "random prescribed", unique=True)
    assert np.all(np.abs(dt - g) <= RTOL * g + 64 * EPS * (mag + g))


def test_random_batch_10000():
    rng = np.random.default_rng(2)
    A, B = _random_pairs(rng, 10000)
    (dt, qat, qbt), (dn, qan, qbn) = _run_both(A, B)
    mag = _coord_mag(A, B)
    # Same formulas in the same order: the points are bitwise equal; dist only differs through torch's
    # vectorised sqrt, which is not correctly rounded (within 1 ulp).
    assert np.array_equal(qan, qat) and np.array_equal(qbn, qbt)
    np.testing.assert_allclose(dn, dt, rtol=4 * EPS, atol=0)

    # Separating-plane certificate: the plane through qa normal to qa - qb has A on one side and B on the
    # other, so dist is also a lower bound. The direction qa - qb carries world rounding, hence the
    # extent * mag / dist term.
    nrm = (qat - qbt) / dt[:, None]
    o = A[:, :1]
    lower = ((A - o) @ nrm[:, :, None]).min(axis=(1, 2)) - ((B - o) @ nrm[:, :, None]).max(axis=(1, 2))
    extent = np.maximum(_size(A), _size(B)) + dt
    assert np.all(lower >= dt - RTOL * dt - 64 * EPS * mag * (1 + extent / dt))

    sub = rng.choice(10000, 1000, replace=False)
    ref, _, _ = _oracle(A[sub], B[sub])
    _check(A[sub], B[sub], dt[sub], qat[sub], qbt[sub], ref, "batch torch")
    _check(A[sub], B[sub], dn[sub], qan[sub], qbn[sub], ref, "batch numba")


# ------------------------------------------------------------------------------------------------------------
# Degenerate and intersecting input, dtypes, devices, API


def test_degenerate_triangles():
    """Zero-area and zero-size triangles: finite, exact (edge pairs cover every vertex-edge distance)."""
    rng = np.random.default_rng(3)
    n = 200
    A = rng.standard_normal((n, 3, 3))
    B = rng.standard_normal((n, 3, 3))
    A_seg = A.copy()
    A_seg[:, 2] = A[:, 0] + rng.uniform(-1, 2, (n, 1)) * (A[:, 1] - A[:, 0])  # collinear, some outside [0, 1]
    A_pt = np.repeat(A[:, :1], 3, axis=1)  # a point
    A_rep = A.copy()
    A_rep[:, 2] = A[:, 1]  # a repeated vertex
    B_seg = np.repeat(B[:, :2], [2, 1], axis=1)
    B_pt = np.repeat(B[:, :1], 3, axis=1)
    B_short = B.copy()
    B_short[:, 1] = B[:, 0] + 1e-9 * (B[:, 1] - B[:, 0])  # a very short edge
    for name, a, b in [
        ("segment-triangle", A_seg, B),
        ("point-triangle", A_pt, B),
        ("repeated vertex", A_rep, B),
        ("segment-segment", A_seg, B_seg),
        ("point-segment", A_pt, B_seg),
        ("point-point", A_pt, B_pt),
        ("short edge", A, B_short),
    ]:
        a, b = _separate(rng, a, b, 1e-9, 10.0)
        for x, y in ((a, b), (b, a)):
            dt = _check_all(x, y, name, in_triangle=False)
            assert np.isfinite(dt).all()


def test_intersecting_is_min_over_features():
    """Documented: for intersecting pairs the result is the minimum over the 15 features, not 0."""
    A = np.array([[[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]]])
    B = np.array([[[0.1, 0.2, -0.5], [0.2, 0.1, 0.5], [0.3, 0.3, 0.6]]])  # edge b0 b1 pierces A's interior
    (dt, qat, qbt), (dn, _, _) = _run_both(A, B)
    assert np.isfinite(dt).all() and dt[0] > 0.1
    assert dn[0] == pytest.approx(dt[0], rel=1e-13)
    assert np.linalg.norm(qat - qbt) == pytest.approx(dt[0], rel=1e-13)


def test_float32_and_grad():
    rng = np.random.default_rng(4)
    A, B = _random_pairs(rng, 500, scale_lo=0.1, gap_lo=1e-2, gap_hi=10.0)
    ref = triangle_closest_points(torch.from_numpy(A), torch.from_numpy(B))
    a32 = torch.from_numpy(A).float().requires_grad_()
    b32 = torch.from_numpy(B).float().requires_grad_()
    res = triangle_closest_points(a32, b32)
    assert isinstance(res, TriangleClosestPoints)
    assert all(x.dtype == torch.float32 for x in res)
    assert res.dist.shape == (500,) and res.qa.shape == (500, 3) and res.qb.shape == (500, 3)
    mag = torch.from_numpy(_coord_mag(A, B))
    assert torch.all((res.dist.double() - ref.dist).abs() <= 1e-5 * mag)
    (res.dist.sum() + res.qa.sum() + res.qb.sum()).backward()
    assert torch.isfinite(a32.grad).all() and torch.isfinite(b32.grad).all()
    assert a32.grad.abs().sum() > 0

    # Where the closest feature is unique the gradient of dist is that of the feature distance.
    A, B, _, _ = _edge_edge_cross(1.0, 0.3)
    a = torch.tensor([A], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([B], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, y: triangle_closest_points(x, y).dist, (a, b))
    # Touching (dist exactly 0): the gradient is defined as 0 rather than nan.
    A, B, _, _ = _coplanar_vertex_vertex(1.0, 0.0)
    a = torch.tensor([A], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([B], dtype=torch.float64, requires_grad=True)
    res = triangle_closest_points(a, b)
    assert res.dist.item() == 0.0
    res.dist.sum().backward()
    assert torch.isfinite(a.grad).all() and torch.isfinite(b.grad).all()


def test_empty_and_validation():
    z = torch.zeros(0, 3, 3, dtype=torch.float64)
    res = triangle_closest_points(z, z)
    assert res.dist.shape == (0,) and res.qa.shape == (0, 3)
    x = torch.zeros(2, 3, 3)
    with pytest.raises(ValueError, match="tri_a"):
        triangle_closest_points(torch.zeros(2, 3), x)
    with pytest.raises(ValueError, match="tri_b"):
        triangle_closest_points(x, torch.zeros(2, 3, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match="dtype"):
        triangle_closest_points(x, x.double())
    with pytest.raises(ValueError, match="K="):
        triangle_closest_points(x, torch.zeros(3, 3, 3))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(5)
    A, B = _random_pairs(rng, 10000)
    cpu = triangle_closest_points(torch.from_numpy(A), torch.from_numpy(B))
    gpu = triangle_closest_points(torch.from_numpy(A).cuda(), torch.from_numpy(B).cuda())
    assert gpu.dist.is_cuda
    torch.testing.assert_close(gpu.dist.cpu(), cpu.dist, rtol=1e-12, atol=0)
    gpu32 = triangle_closest_points(torch.from_numpy(A).float().cuda(), torch.from_numpy(B).float().cuda())
    assert gpu32.dist.dtype == torch.float32


# ------------------------------------------------------------------------------------------------------------
# Segment-triangle crossing: torch against the numba kernel of the collision query


def _segment_cases(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) starts, (N, 3) ends, (N, 3, 3) triangles: generic, near-degenerate and borderline configurations."""
    P, Q, T = [], [], []

    def add(p, q, t):
        P.append(np.asarray(p, float).reshape(-1, 3))
        Q.append(np.asarray(q, float).reshape(-1, 3))
        T.append(np.asarray(t, float).reshape(-1, 3, 3))

    n = 4000
    # generic, at several scales and offsets from the origin
    for scale, offset in ((1.0, 0.0), (1e-6, 0.0), (1e3, 0.0), (1.0, 1e4)):
        add(offset + scale * rng.normal(size=(n, 3)), offset + scale * rng.normal(size=(n, 3)),
            offset + scale * rng.normal(size=(n, 3, 3)))  # fmt: skip
    # segments through the triangle's interior (hits) and short of it (t just outside [0, 1])
    t = rng.normal(size=(n, 3, 3))
    w = rng.dirichlet(np.ones(3), size=n)
    x = np.einsum("nk,nkc->nc", w, t)  # a point of the triangle
    d = rng.normal(size=(n, 3))
    s = rng.uniform(0.0, 1.0, size=(n, 1))
    add(x - s * d, x + (1.0 - s) * d, t)
    add(x + 1e-9 * d, x + d, t)  # the start just beside the plane
    # an endpoint on the plane (as rounding puts it), inside and outside the triangle
    w2 = rng.normal(size=(n, 3))
    w2 /= w2.sum(1, keepdims=True)
    on_plane = np.einsum("nk,nkc->nc", w2, t)
    add(on_plane, on_plane + rng.normal(size=(n, 3)), t)
    add(on_plane + rng.normal(size=(n, 3)), on_plane, t)
    # exact borderlines: the triangle (0,0,0), (1,0,0), (0,1,0) and vertical segments on a grid that includes its
    # edges and vertices (u, v or u + v exactly 0 or 1), ends exactly on the plane z = 0, parallel segments
    # (det exactly 0) and zero-length ones
    unit = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    g = np.arange(-0.25, 1.5, 0.25)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    for z0, z1 in ((1.0, -1.0), (0.0, -1.0), (1.0, 0.0), (0.5, 0.25), (0.0, 0.0)):
        m = len(xy)
        add(np.c_[xy, np.full(m, z0)], np.c_[xy, np.full(m, z1)], np.broadcast_to(unit, (m, 3, 3)))
    m = len(xy)
    add(
        np.c_[xy, np.zeros(m)], np.c_[xy[::-1], np.zeros(m)], np.broadcast_to(unit, (m, 3, 3))
    )  # in the plane
    add(
        np.c_[xy, np.ones(m)], np.c_[xy[::-1], np.ones(m)], np.broadcast_to(unit, (m, 3, 3))
    )  # parallel above
    # near-degenerate triangles: needles and almost collinear triples, with segments through their middle
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    for eps in (1e-8, 1e-12, 1e-15, 0.0):
        c = 0.5 * (a + b) + eps * rng.normal(size=(n, 3))
        tri = np.stack([a, b, c], 1)
        mid = (a + b + c) / 3.0
        dd = rng.normal(size=(n, 3))
        add(mid - dd, mid + dd, tri)
    # nearly parallel segments crossing the triangle's interior
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    along = (t[:, 1] - t[:, 0]) + 1e-12 * nrm
    add(x - along, x + along, t)
    return np.concatenate(P), np.concatenate(Q), np.concatenate(T)


def test_segment_hits_triangle_matches_the_numba_kernel():
    from cfd_torch._geometry import segment_hits_triangle, segment_hits_triangle_nb

    def _segment_hits_triangle(p, q, t):  # the collision query's form: only exactly parallel segments refused
        return segment_hits_triangle_nb(p, q, t, 0.0)

    P, Q, T = _segment_cases(np.random.default_rng(11))
    expected = np.array([_segment_hits_triangle(P[i], Q[i], T[i]) for i in range(len(P))])
    got = segment_hits_triangle(torch.from_numpy(P), torch.from_numpy(Q), torch.from_numpy(T))
    assert got.dtype == torch.bool and got.shape == (len(P),)
    assert 0.1 < expected.mean() < 0.9  # both outcomes well represented
    mismatch = np.nonzero(got.numpy() != expected)[0]
    assert len(mismatch) == 0, f"{len(mismatch)} of {len(P)} differ, first at {mismatch[:5]}"

    # leading dimensions broadcast: (Nd, 1, 3) segments against (1, T, 3, 3) triangles
    p, q, t = (torch.from_numpy(x[:60]) for x in (P, Q, T))
    grid = segment_hits_triangle(p[:6, None], q[:6, None], t[None, :10])
    assert grid.shape == (6, 10)
    for i in range(6):
        for j in range(10):
            assert bool(grid[i, j]) == _segment_hits_triangle(P[i], Q[i], T[j])


def test_segment_hits_triangle_validation():
    from cfd_torch._geometry import segment_hits_triangle

    p, t = torch.zeros(4, 3), torch.eye(3).expand(4, 3, 3)
    with pytest.raises(ValueError, match="p must"):
        segment_hits_triangle(torch.zeros(4, 2), p, t)
    with pytest.raises(ValueError, match="tri must"):
        segment_hits_triangle(p, p, torch.zeros(4, 3))
    with pytest.raises(ValueError, match="q must"):
        segment_hits_triangle(p, p.long(), t)
    with pytest.raises(ValueError, match="dtype"):
        segment_hits_triangle(p, p.double(), t)
    with pytest.raises(ValueError, match="broadcast"):
        segment_hits_triangle(p, p, t[:3])


# ------------------------------------------------------------------------------------------------------------
# Rotation derivatives: the torch path against the numba kernel


def test_rotation_derivatives_torch_path_matches_numba():
    from cfd_torch._rotation_numba import rotation_derivatives_cpu
    from cfd_torch.rotation import _rotation_derivatives_torch, rotation_derivatives

    rng = np.random.default_rng(12)
    axes = rng.normal(size=(400, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    norms = np.concatenate(
        [
            [0.0, 1e-12, 1e-9, 1e-9, 1e-6, 1e-3],
            np.sqrt(0.25)
            * (1.0 + np.array([-1e-12, 0.0, 1e-12, -1e-6, 1e-6])),  # the series switch at |w|^2 = 0.25
            rng.uniform(0.01, 3.0, size=300),  # moderate
            np.pi - np.logspace(-12, -1, 40),  # near pi, from below
            [np.pi, np.pi + 1e-9, np.pi + 1e-3],
            rng.uniform(3.5, 10.0, size=46),  # beyond pi (not wrapped)
        ]
    )
    assert len(norms) == len(axes)
    omega = axes * norms[:, None]
    w = torch.from_numpy(omega)
    for order in (0, 1, 2):
        ref = rotation_derivatives_cpu(omega, order)
        got = _rotation_derivatives_torch(w, order)
        via_grad = rotation_derivatives(
            w.clone().requires_grad_(True), order
        )  # the dispatch takes the torch path
        for k in range(3):
            if k > order:
                assert ref[k] is None and got[k] is None
                continue
            assert got[k].shape == ref[k].shape
            err = float((got[k] - torch.from_numpy(ref[k])).abs().max())
            assert err <= 1e-14, f"order {order}, output {k}: max error {err:.3e}"
            assert torch.equal(via_grad[k].detach(), got[k])
