"""Exact closest points between two triangles in 3D (and a batched segment-triangle crossing test,
:func:`segment_hits_triangle`, at the end of the torch section).

Two forms of one algorithm:

- :func:`triangle_closest_points`: batched and branch-free in torch, for any float dtype and device.
- :func:`tri_tri_closest_nb`: scalar numba kernel for one pair, allocation-free, callable from ``njit`` and
  ``prange`` code.

Method. Two solid triangles that do not intersect have their closest points on one of 15 features: a vertex
of one triangle against the other triangle (6) or an edge of one against an edge of the other (9) (Ericson,
Real-Time Collision Detection, 5.1.5 ClosestPtPointTriangle and 5.1.9 ClosestPtSegmentSegment). Each feature
is solved exactly and the smallest distance wins; on an exact tie the first feature in this order wins:
``a0-B, a1-B, a2-B, A-b0, A-b1, A-b2``, then the edge pairs ``(a_i a_i+1, b_j b_j+1)`` with ``(i, j)`` in
row-major order. Both forms use the same formulas in the same order, so they return the same points.

Robustness:

- Everything is computed relative to the first vertex of triangle a, so rounding errors scale with the size
  of the configuration (triangle extents plus gap), not with its distance from the world origin. The
  returned distance is computed in that frame; ``|qa - qb|`` recomputed from the returned world points
  differs from it by the rounding of world coordinates.
- Segment-segment gets the line-line parameter from cross products, ``s = ((p2 - p1) x d2).n / |n|^2`` with
  ``n = d1 x d2``, rather than from Ericson's Gram determinant ``a e - b^2``: the relative error of ``|n|^2``
  is ``O(eps / sin(angle))`` instead of ``O(eps / sin(angle)^2)``, so nearly parallel edges that cross stay
  accurate. Segments count as parallel only when ``sin(angle) <= eps`` and as points when
  ``|d|^2 <= eps^2 (|d1|^2 + |d2|^2)`` (relative epsilons, ``eps`` of the dtype); any parameter then does,
  and Ericson's clamping that follows picks the right end.
- Point-triangle is Ericson's Voronoi-region test. In the face region the barycentric weights are clamped to
  be non-negative, so the point lies in the triangle even where rounding makes the region tests disagree; a
  zero-area triangle falls back to its first vertex there. The edge pairs cover every vertex-edge distance,
  so the minimum stays exact for degenerate (zero-area, zero-length) triangles.

Intersecting triangles are outside the contract: the result is the minimum over the 15 features, which is
positive when an edge pierces the other triangle's interior. Callers detect intersection separately.
Non-finite input gives unspecified output.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

__all__ = ["TriangleClosestPoints", "segment_hits_triangle", "tri_tri_closest_nb", "triangle_closest_points"]


class TriangleClosestPoints(NamedTuple):
    """Closest points of K triangle pairs.

    Attributes:
        dist: (K,) distance between the two triangles [length units of the input].
        qa: (K, 3) closest point on triangle a.
        qb: (K, 3) closest point on triangle b.
    """

    dist: Tensor
    qa: Tensor
    qb: Tensor


# ------------------------------------------------------------------------------------------------------------
# torch


# Vectors are (x, y, z) tuples of broadcastable tensors: every op then runs on contiguous memory (several
# times faster than strided components of (..., 3) tensors) and broadcasting stands in for expand/repeat.
Vec = tuple[Tensor, Tensor, Tensor]


def _sub(u: Vec, v: Vec) -> Vec:
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


def _dot(u: Vec, v: Vec) -> Tensor:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u: Vec, v: Vec) -> Vec:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _axpy(p: Vec, d: Vec, s: Tensor) -> Vec:
    """p + d * s."""
    return (p[0] + d[0] * s, p[1] + d[1] * s, p[2] + d[2] * s)


def _where(cond: Tensor, u: Vec, v: Vec) -> Vec:
    return (torch.where(cond, u[0], v[0]), torch.where(cond, u[1], v[1]), torch.where(cond, u[2], v[2]))


def _safe_div(num: Tensor, den: Tensor, ok: Tensor) -> Tensor:
    """num / den where ok, else 0, without producing inf/nan (nor their gradients) where not ok."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _closest_point_triangle(p: Vec, a: Vec, b: Vec, c: Vec) -> Vec:
    """Closest point to p on triangle abc (Ericson 5.1.5), branch-free.

    Args:
        p, a, b, c: query point and triangle vertices, components broadcastable to a common shape S.

    Returns:
        Closest point on the triangle, components of shape S.
    """
    ab = _sub(b, a)
    ac = _sub(c, a)
    ap = _sub(p, a)
    d1 = _dot(ab, ap)
    d2 = _dot(ac, ap)
    bp = _sub(p, b)
    d3 = _dot(ab, bp)
    d4 = _dot(ac, bp)
    cp = _sub(p, c)
    d5 = _dot(ab, cp)
    d6 = _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    # Ericson tests the regions in the order A, B, AB, C, AC, BC, face and returns at the first hit; apply
    # them in reverse so the earliest test overrides.
    vap, vbp, vcp = va.clamp_min(0), vb.clamp_min(0), vc.clamp_min(0)
    den = vap + vbp + vcp
    ok = den > 0
    q = _axpy(_axpy(a, ab, _safe_div(vbp, den, ok)), ac, _safe_div(vcp, den, ok))

    e43 = d4 - d3
    e56 = d5 - d6
    den = e43 + e56
    q = _where((va <= 0) & (e43 >= 0) & (e56 >= 0), _axpy(b, _sub(c, b), _safe_div(e43, den, den > 0)), q)
    den = d2 - d6
    q = _where((vb <= 0) & (d2 >= 0) & (d6 <= 0), _axpy(a, ac, _safe_div(d2, den, den > 0)), q)
    q = _where((d6 >= 0) & (d5 <= d6), c, q)
    den = d1 - d3
    q = _where((vc <= 0) & (d1 >= 0) & (d3 <= 0), _axpy(a, ab, _safe_div(d1, den, den > 0)), q)
    q = _where((d3 >= 0) & (d4 <= d3), b, q)
    return _where((d1 <= 0) & (d2 <= 0), a, q)


def _closest_segment_segment(p1: Vec, q1: Vec, p2: Vec, q2: Vec, eps: float) -> tuple[Vec, Vec]:
    """Closest points of segments p1q1 and p2q2 (Ericson 5.1.9), branch-free.

    Args:
        p1, q1, p2, q2: segment end points, components broadcastable to a common shape S.
        eps: machine epsilon of the dtype.

    Returns:
        c1, c2: closest points on the first and on the second segment, components of shape S.
    """
    d1 = _sub(q1, p1)
    d2 = _sub(q2, p2)
    r = _sub(p1, p2)
    a = _dot(d1, d1)
    e = _dot(d2, d2)
    f = _dot(d2, r)
    c = _dot(d1, r)
    b = _dot(d1, d2)
    tiny = eps * eps
    deg1 = a <= tiny * (a + e)  # first segment is a point
    deg2 = e <= tiny * (a + e)  # second segment is a point

    n = _cross(d1, d2)
    nn = _dot(n, n)
    line = nn > tiny * a * e  # not parallel: sin(angle) > eps
    s = _safe_div(_dot(_cross(_sub(p2, p1), d2), n), nn, line).clamp(0, 1)
    t = _safe_div(b * s + f, e, ~deg2)
    s_lo = _safe_div(-c, a, ~deg1).clamp(0, 1)  # closest on segment 1 to p2 (t = 0)
    s_hi = _safe_div(b - c, a, ~deg1).clamp(0, 1)  # closest on segment 1 to q2 (t = 1)
    s = torch.where(t < 0, s_lo, torch.where(t > 1, s_hi, s))
    t = t.clamp(0, 1)

    t_pt = _safe_div(f, e, ~deg2).clamp(0, 1)  # closest on segment 2 to p1 (s = 0)
    zero = torch.zeros_like(s)
    s = torch.where(deg1, zero, torch.where(deg2, s_lo, s))
    t = torch.where(deg2, zero, torch.where(deg1, t_pt, t))
    return _axpy(p1, d1, s), _axpy(p2, d2, t)


def triangle_closest_points(tri_a: Tensor, tri_b: Tensor) -> TriangleClosestPoints:
    """Closest points between K pairs of solid triangles.

    Exact up to rounding for non-intersecting pairs: the minimum over the 6 vertex-triangle and 9 edge-edge
    features (see the module docstring for robustness and for intersecting input). Computes in the input
    dtype on the input device, without host synchronisation. Autograd passes through (piecewise smooth, no
    nan/inf gradients from unselected branches) but is only checked at generic configurations; ``dist`` has
    a zero gradient where it is exactly 0.

    Args:
        tri_a: (K, 3, 3) vertices of triangles a (vertex index, then xyz).
        tri_b: (K, 3, 3) vertices of triangles b, same dtype and device.

    Returns:
        TriangleClosestPoints ``(dist, qa, qb)``: dist (K,) distance, qa (K, 3) point on triangle a,
        qb (K, 3) point on triangle b, with ``|qa - qb| = dist`` up to rounding.

    Raises:
        ValueError: on a shape other than (K, 3, 3), a non-float dtype, or mismatched dtype, device or K.
    """
    from ._validate import check_dense  # (_validate imports this module's kernels)

    for name, tri in (("tri_a", tri_a), ("tri_b", tri_b)):
        if not isinstance(tri, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(tri).__name__}")
        check_dense(tri, name)
        if tri.dim() != 3 or tri.shape[1:] != (3, 3):
            raise ValueError(f"{name} must have shape (K, 3, 3), got {tuple(tri.shape)}")
        if not tri.is_floating_point():
            raise ValueError(f"{name} must have a floating dtype, got {tri.dtype}")
    if tri_b.dtype != tri_a.dtype:
        raise ValueError(f"tri_b dtype {tri_b.dtype} differs from tri_a dtype {tri_a.dtype}")
    if tri_b.device != tri_a.device:
        raise ValueError(f"tri_b device {tri_b.device} differs from tri_a device {tri_a.device}")
    if tri_b.shape[0] != tri_a.shape[0]:
        raise ValueError(f"tri_b has K={tri_b.shape[0]} pairs, tri_a has K={tri_a.shape[0]}")

    k = tri_a.shape[0]
    eps = torch.finfo(tri_a.dtype).eps
    origin = tri_a[:, 0]  # (K, 3)
    # Components relative to the origin, each (K, 3) over the vertices.
    ax, ay, az = (tri_a - origin[:, None]).permute(2, 0, 1).contiguous().unbind(0)
    bx, by, bz = (tri_b - origin[:, None]).permute(2, 0, 1).contiguous().unbind(0)
    a: Vec = (ax, ay, az)
    b: Vec = (bx, by, bz)

    def vertex(v: Vec, i: int) -> Vec:  # vertex i of every triangle, components (K, 1)
        return (v[0][:, i : i + 1], v[1][:, i : i + 1], v[2][:, i : i + 1])

    def unsqueeze(v: Vec, dim: int) -> Vec:
        return (v[0].unsqueeze(dim), v[1].unsqueeze(dim), v[2].unsqueeze(dim))

    def roll(v: Vec) -> Vec:  # vertex i + 1 in place of vertex i
        return (v[0].roll(-1, 1), v[1].roll(-1, 1), v[2].roll(-1, 1))

    def features(vt: Vec, tv: Vec, ee: Vec) -> Vec:  # the 15 features in order, components (K, 15)
        x, y, z = (torch.cat((vt[i], tv[i], ee[i].reshape(k, 9)), dim=1) for i in range(3))
        return (x, y, z)

    # Vertex-triangle: the 3 vertices of a against b, then the 3 vertices of b against a; components (K, 3).
    q_ab = _closest_point_triangle(a, vertex(b, 0), vertex(b, 1), vertex(b, 2))
    q_ba = _closest_point_triangle(b, vertex(a, 0), vertex(a, 1), vertex(a, 2))
    # Edge-edge: edge i of a is (a_i, a_i+1), edge j of b likewise; components (K, 3, 3) over (i, j).
    c1, c2 = _closest_segment_segment(
        unsqueeze(a, 2), unsqueeze(roll(a), 2), unsqueeze(b, 1), unsqueeze(roll(b), 1), eps
    )

    qa_all = features(a, q_ba, c1)
    qb_all = features(q_ab, b, c2)
    diff = _sub(qa_all, qb_all)
    d2_all = _dot(diff, diff)  # (K, 15)
    idx = d2_all.argmin(dim=1, keepdim=True)  # (K, 1), first minimum on ties
    d2 = d2_all.gather(1, idx)[:, 0]
    qa = torch.cat([x.gather(1, idx) for x in qa_all], dim=1) + origin
    qb = torch.cat([x.gather(1, idx) for x in qb_all], dim=1) + origin
    pos = d2 > 0
    dist = torch.where(pos, torch.where(pos, d2, torch.ones_like(d2)).sqrt(), torch.zeros_like(d2))
    return TriangleClosestPoints(dist, qa, qb)


def frame_origin(X: Tensor, min_extent: float = 0.0) -> Tensor:
    """(K, 3) an origin near each point set X (K, V, 3): its centroid rounded to a multiple of g, the power of two
    above its extent about the centroid (at least ``min_extent``). Then X - origin is exact wherever the set is (its
    bits are those of X, its magnitude at most 1.5 g), so whatever is computed from it sees the same digits of the
    geometry at any offset, and a set near the world origin (|centroid| < g / 2) keeps its coordinates. Used for
    each pair of the pair solve (``contact._pair_numba._frame`` computes the same in the kernel) and for each step's
    moving bodies."""
    mean = X.mean(1)
    extent = (X - mean[:, None, :]).abs().amax((1, 2)).clamp_min(min_extent)
    _, e = torch.frexp(extent)
    g = torch.ldexp(torch.ones_like(extent), e)[:, None]  # 2^e > extent
    return torch.floor(mean / g + 0.5) * g


def segment_hits_triangle(p: Tensor, q: Tensor, tri: Tensor) -> Tensor:
    """Whether the segments p -> q cross the triangles (Moller-Trumbore), batched and branch-free.

    The convention and the arithmetic of the collision query's numba kernel
    (:func:`segment_hits_triangle_nb`), operation for operation, so the two agree exactly: with
    ``d = q - p``, ``det = e1 . (d x e2)`` (e1, e2 the edges from vertex 0), the barycentric ``u``, ``v`` and the
    segment parameter ``t`` (each a dot product times ``1 / det``), a hit is ``det != 0``, ``0 <= u <= 1``,
    ``v >= 0``, ``u + v <= 1`` and ``0 <= t <= 1`` (the bounds included: an endpoint on the triangle, a segment
    through an edge or a vertex counts). A segment parallel to the plane (``det`` exactly 0) never counts, even
    one lying in the triangle (its distance, 0, is the caller's test for that). Not differentiable (a boolean).

    Args:
        p: (..., 3) segment starts.
        q: (..., 3) segment ends.
        tri: (..., 3, 3) triangle vertices (vertex index, then xyz); all leading dims broadcast.

    Returns:
        (...) bool, the broadcast leading shape.

    Raises:
        ValueError: a shape other than (..., 3) / (..., 3, 3), a non-float dtype, mismatched dtypes or devices, or
            leading dims that do not broadcast.
    """
    from ._validate import check_dense  # (_validate imports this module's kernels)

    for name, x, tail in (("p", p, (3,)), ("q", q, (3,)), ("tri", tri, (3, 3))):
        if not isinstance(x, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        check_dense(x, name)
        if x.dim() < len(tail) or tuple(x.shape[-len(tail) :]) != tail:
            want = "(..., 3)" if len(tail) == 1 else "(..., 3, 3)"
            raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise ValueError(f"{name} must have a floating dtype, got {x.dtype}")
    if not (p.dtype == q.dtype == tri.dtype):
        raise ValueError(f"p, q and tri must share a dtype, got {p.dtype}, {q.dtype} and {tri.dtype}")
    if not (p.device == q.device == tri.device):
        raise ValueError(f"p, q and tri must be on one device, got {p.device}, {q.device} and {tri.device}")
    try:
        torch.broadcast_shapes(p.shape[:-1], q.shape[:-1], tri.shape[:-2])
    except RuntimeError as err:
        raise ValueError(
            f"the leading dims of p {tuple(p.shape[:-1])}, q {tuple(q.shape[:-1])} and tri {tuple(tri.shape[:-2])} "
            "do not broadcast"
        ) from err

    def vec(x: Tensor) -> Vec:
        return (x[..., 0], x[..., 1], x[..., 2])

    t0, t1, t2 = vec(tri[..., 0, :]), vec(tri[..., 1, :]), vec(tri[..., 2, :])
    pp, qq = vec(p), vec(q)
    e1, e2, d = _sub(t1, t0), _sub(t2, t0), _sub(qq, pp)
    pv = _cross(d, e2)
    det = _dot(e1, pv)
    nonzero = det != 0.0
    inv = 1.0 / torch.where(nonzero, det, torch.ones_like(det))
    tv = _sub(pp, t0)
    u = _dot(tv, pv) * inv
    qv = _cross(tv, e1)
    v = _dot(d, qv) * inv
    t = _dot(e2, qv) * inv
    # the kernel's early returns, negated as written there (u < 0 or u > 1 -> miss; ...), so NaN behaves the same
    return nonzero & ~((u < 0.0) | (u > 1.0)) & ~((v < 0.0) | (u + v > 1.0)) & (t >= 0.0) & (t <= 1.0)


# ------------------------------------------------------------------------------------------------------------
# numba: the same formulas on scalars, in the same order.

_EPS64 = float(np.finfo(np.float64).eps)
_TINY64 = _EPS64 * _EPS64
_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}


@numba.njit(**_JIT)
def _closest_point_triangle_nb(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point (qx, qy, qz) to p on triangle abc; scalar twin of :func:`_closest_point_triangle`."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        den = d1 - d3
        v = d1 / den if den > 0.0 else 0.0
        return ax + abx * v, ay + aby * v, az + abz * v
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        den = d2 - d6
        w = d2 / den if den > 0.0 else 0.0
        return ax + acx * w, ay + acy * w, az + acz * w
    va = d3 * d6 - d5 * d4
    e43 = d4 - d3
    e56 = d5 - d6
    if va <= 0.0 and e43 >= 0.0 and e56 >= 0.0:
        den = e43 + e56
        w = e43 / den if den > 0.0 else 0.0
        return bx + (cx - bx) * w, by + (cy - by) * w, bz + (cz - bz) * w
    va = max(va, 0.0)
    vb = max(vb, 0.0)
    vc = max(vc, 0.0)
    den = va + vb + vc
    if den > 0.0:
        v = vb / den
        w = vc / den
    else:
        v = 0.0
        w = 0.0
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@numba.njit(**_JIT)
def _closest_segment_segment_nb(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z):
    """Segment parameters (s, t) of the closest points; scalar twin of :func:`_closest_segment_segment`."""
    d1x, d1y, d1z = q1x - p1x, q1y - p1y, q1z - p1z
    d2x, d2y, d2z = q2x - p2x, q2y - p2y, q2z - p2z
    rx, ry, rz = p1x - p2x, p1y - p2y, p1z - p2z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    deg1 = a <= _TINY64 * (a + e)
    deg2 = e <= _TINY64 * (a + e)
    if deg1 and deg2:
        return 0.0, 0.0
    if deg1:
        return 0.0, min(max(f / e, 0.0), 1.0)
    c = d1x * rx + d1y * ry + d1z * rz
    if deg2:
        return min(max(-c / a, 0.0), 1.0), 0.0
    b = d1x * d2x + d1y * d2y + d1z * d2z
    nx = d1y * d2z - d1z * d2y
    ny = d1z * d2x - d1x * d2z
    nz = d1x * d2y - d1y * d2x
    nn = nx * nx + ny * ny + nz * nz
    s = 0.0
    if nn > _TINY64 * a * e:
        # ((p2 - p1) x d2) . n / |n|^2
        wx, wy, wz = -rx, -ry, -rz
        cx = wy * d2z - wz * d2y
        cy = wz * d2x - wx * d2z
        cz = wx * d2y - wy * d2x
        s = min(max((cx * nx + cy * ny + cz * nz) / nn, 0.0), 1.0)
    t = (b * s + f) / e
    if t < 0.0:
        return min(max(-c / a, 0.0), 1.0), 0.0
    if t > 1.0:
        return min(max((b - c) / a, 0.0), 1.0), 1.0
    return s, t


@numba.njit(**_JIT)
def tri_tri_closest_nb(A, B, out):
    """Closest points between two solid triangles; scalar twin of :func:`triangle_closest_points`.

    Allocation-free (scalar locals only), for use inside ``njit``/``prange`` kernels. Same features, formulas,
    tie order and caveats as the torch version (see the module docstring).

    Args:
        A: (3, 3) float64 vertices of triangle a (rows are vertices).
        B: (3, 3) float64 vertices of triangle b.
        out: (6,) float64 output: closest point on a in ``out[0:3]``, on b in ``out[3:6]``.

    Returns:
        Squared distance between the triangles (computed relative to ``A[0]``).
    """
    ox, oy, oz = A[0, 0], A[0, 1], A[0, 2]
    best = np.inf
    first = True
    sax = say = saz = sbx = sby = sbz = 0.0

    # Vertices of A against B, then vertices of B against A.
    for side in range(2):
        pts = A if side == 0 else B
        tri = B if side == 0 else A
        tax, tay, taz = tri[0, 0] - ox, tri[0, 1] - oy, tri[0, 2] - oz
        tbx, tby, tbz = tri[1, 0] - ox, tri[1, 1] - oy, tri[1, 2] - oz
        tcx, tcy, tcz = tri[2, 0] - ox, tri[2, 1] - oy, tri[2, 2] - oz
        for i in range(3):
            px, py, pz = pts[i, 0] - ox, pts[i, 1] - oy, pts[i, 2] - oz
            qx, qy, qz = _closest_point_triangle_nb(px, py, pz, tax, tay, taz, tbx, tby, tbz, tcx, tcy, tcz)
            dx, dy, dz = px - qx, py - qy, pz - qz
            d2 = dx * dx + dy * dy + dz * dz
            if first or d2 < best:
                first = False
                best = d2
                if side == 0:
                    sax, say, saz, sbx, sby, sbz = px, py, pz, qx, qy, qz
                else:
                    sax, say, saz, sbx, sby, sbz = qx, qy, qz, px, py, pz

    # Edge pairs (A_i A_i+1, B_j B_j+1), row-major.
    for i in range(3):
        i1 = i + 1 if i < 2 else 0
        p1x, p1y, p1z = A[i, 0] - ox, A[i, 1] - oy, A[i, 2] - oz
        q1x, q1y, q1z = A[i1, 0] - ox, A[i1, 1] - oy, A[i1, 2] - oz
        for j in range(3):
            j1 = j + 1 if j < 2 else 0
            p2x, p2y, p2z = B[j, 0] - ox, B[j, 1] - oy, B[j, 2] - oz
            q2x, q2y, q2z = B[j1, 0] - ox, B[j1, 1] - oy, B[j1, 2] - oz
            s, t = _closest_segment_segment_nb(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z)
            c1x = p1x + (q1x - p1x) * s
            c1y = p1y + (q1y - p1y) * s
            c1z = p1z + (q1z - p1z) * s
            c2x = p2x + (q2x - p2x) * t
            c2y = p2y + (q2y - p2y) * t
            c2z = p2z + (q2z - p2z) * t
            dx, dy, dz = c1x - c2x, c1y - c2y, c1z - c2z
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best:
                best = d2
                sax, say, saz, sbx, sby, sbz = c1x, c1y, c1z, c2x, c2y, c2z

    out[0] = sax + ox
    out[1] = say + oy
    out[2] = saz + oz
    out[3] = sbx + ox
    out[4] = sby + oy
    out[5] = sbz + oz
    return best


@numba.njit(**_JIT)
def segment_hits_triangle_nb(P, Q, T, sin_min) -> bool:
    """Whether the segment PQ crosses the triangle T (3, 3) (Moller-Trumbore; :func:`segment_hits_triangle`'s
    convention and arithmetic, operation for operation). A segment whose sine of angle with the triangle's plane
    is at most ``sin_min`` never counts: 0 refuses only an exactly parallel one (det = 0); a positive value also
    refuses nearly parallel ones, whose crossing rounding can fake."""
    e1x, e1y, e1z = T[1, 0] - T[0, 0], T[1, 1] - T[0, 1], T[1, 2] - T[0, 2]
    e2x, e2y, e2z = T[2, 0] - T[0, 0], T[2, 1] - T[0, 1], T[2, 2] - T[0, 2]
    dx, dy, dz = Q[0] - P[0], Q[1] - P[1], Q[2] - P[2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz  # = -d . (e1 x e2) = -|d| (2 area) sin(angle)
    if det == 0.0:
        return False
    if sin_min > 0.0:
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        if not abs(det) > sin_min * math.sqrt((dx * dx + dy * dy + dz * dz) * (nx * nx + ny * ny + nz * nz)):
            return False
    inv = 1.0 / det
    tx, ty, tz = P[0] - T[0, 0], P[1] - T[0, 1], P[2] - T[0, 2]
    u = (tx * px + ty * py + tz * pz) * inv
    if u < 0.0 or u > 1.0:
        return False
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return False
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return 0.0 <= t <= 1.0


_AMBIGUOUS = -(2**62)  # ray_crossings_nb: the ray grazed an edge or a vertex


@numba.njit(cache=True, error_model="numpy")
def ray_crossings_nb(centre, radius, child, tri, tris, roots, origins, dirs, out):
    """out[k] = the winding number of the surface of hierarchy ``roots[k]`` (node table ``centre``, ``radius``,
    ``child``, ``tri`` over body-frame triangles ``tris``) about ``origins[k]``, counted along the ray
    ``origins[k] + s dirs[k]`` (unit), s > 0: +1 for each triangle it crosses from the back (leaving an outward-facing
    surface), -1 from the front; or _AMBIGUOUS when the ray passes within 1e-9 relative of a triangle's edge or
    vertex, or starts on a triangle: the caller retries along another direction. Möller-Trumbore per leaf,
    spheres the ray misses pruned. (For a closed surface: 1 inside an outward-facing one, 0 outside it, -1 inside
    an inward-facing one.)"""
    stack = np.empty(256, np.int64)
    for k in range(roots.shape[0]):
        ox, oy, oz = origins[k, 0], origins[k, 1], origins[k, 2]
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        count = 0
        top = 1
        stack[0] = roots[k]
        while top > 0:
            top -= 1
            n = stack[top]
            wx, wy, wz = centre[n, 0] - ox, centre[n, 1] - oy, centre[n, 2] - oz
            proj = wx * dx + wy * dy + wz * dz
            w2 = wx * wx + wy * wy + wz * wz
            r = radius[n] * (1.0 + 1e-9)
            if proj < 0.0:
                if w2 > r * r:
                    continue
            elif w2 - proj * proj > r * r:
                continue
            if child[n, 0] < 0:
                t = tris[tri[n]]
                e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
                e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
                px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
                det = e1x * px + e1y * py + e1z * pz
                scale = math.sqrt((e1x * e1x + e1y * e1y + e1z * e1z) * (e2x * e2x + e2y * e2y + e2z * e2z))
                if abs(det) <= 1e-12 * scale:  # the ray is parallel to the triangle's plane
                    continue
                sx, sy, sz = ox - t[0, 0], oy - t[0, 1], oz - t[0, 2]
                u = (sx * px + sy * py + sz * pz) / det
                qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
                v = (dx * qx + dy * qy + dz * qz) / det
                s = (e2x * qx + e2y * qy + e2z * qz) / det
                lo = -1e-9
                if u < lo or v < lo or u + v > 1.0 - lo:
                    continue
                if s < -1e-9 * math.sqrt(scale):
                    continue
                if u <= -lo or v <= -lo or u + v >= 1.0 + lo or s <= 1e-9 * math.sqrt(scale):
                    count = _AMBIGUOUS
                    break
                count += 1 if det < 0.0 else -1  # det = -d . (e1 x e2): negative leaving an outward face
            else:
                if top + 2 > stack.shape[0]:
                    grown = np.empty(2 * stack.shape[0], np.int64)
                    grown[:top] = stack[:top]
                    stack = grown
                stack[top] = child[n, 0]
                stack[top + 1] = child[n, 1]
                top += 2
        out[k] = count
