"""Exact closest points between two triangles in 3D.

Two forms of one algorithm:

- :func:`triangle_closest_points`: batched and branch-free in torch, for any float dtype and device.
- :func:`tri_tri_closest_nb`: scalar numba kernel for one pair, allocation-free, callable from ``njit`` and
  ``prange`` code.

Method. Two solid triangles that do not intersect have their closest points on one of 15 features: a vertex of one
triangle against the other triangle (6) or an edge of one against an edge of the other (9) (Ericson, Real-Time
Collision Detection, 5.1.5 ClosestPtPointTriangle and 5.1.9 ClosestPtSegmentSegment). Each feature is solved
exactly and the smallest distance wins; on an exact tie the first feature in this order wins:
``a0-B, a1-B, a2-B, A-b0, A-b1, A-b2`` then the edge pairs ``(a_i a_i+1, b_j b_j+1)`` for ``i, j`` in row-major
order. Both forms follow the same order and the same formulas, so they agree to rounding.

Robustness:

- Everything is computed relative to the first vertex of triangle a, so rounding errors scale with the size of the
  configuration (triangle extents plus gap), not with the distance of the pair from the world origin. The returned
  distance is computed in that frame; ``|qa - qb|`` recomputed from the returned world points differs from it by
  rounding of the world coordinates.
- Segment-segment solves the line-line parameter with the cross product, ``s = ((p2 - p1) x d2).n / |n|^2`` with
  ``n = d1 x d2``, rather than with Ericson's Gram determinant ``a e - b^2``: the relative error of ``|n|^2`` is
  ``O(eps / sin(angle))`` instead of ``O(eps / sin(angle)^2)``, so nearly parallel edges that cross stay accurate.
  Segments are treated as parallel only below ``sin(angle) <= eps`` and as points below
  ``|d|^2 <= eps^2 (|d1|^2 + |d2|^2)`` (relative epsilons, ``eps`` of the dtype); any parameter then works, and the
  clamping that follows (Ericson's) picks the right one.
- Point-triangle is Ericson's Voronoi-region test. In the face region the barycentric weights are clamped to be
  non-negative, so the point always lies in the triangle even when rounding makes the region tests disagree; a
  zero-area triangle falls back to its first vertex there. Edge pairs cover every vertex-edge distance, so the minimum
  is still exact for degenerate (zero-area, zero-length) triangles.

Intersecting triangles are outside the contract: the result is the minimum over the 15 features, which is positive
when an edge pierces the other triangle's interior. Callers detect intersection separately. Non-finite input gives
unspecified output.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

__all__ = ["TriangleClosestPoints", "triangle_closest_points", "tri_tri_closest_nb"]


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


# ----------------------------------------------------------------------------------------------------------------------
# torch


def _dot(u: Tensor, v: Tensor) -> Tensor:
    # Written out (not .sum(-1)) so the summation order matches the numba kernel.
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def _cross(u: Tensor, v: Tensor) -> Tensor:
    ux, uy, uz = u.unbind(-1)
    vx, vy, vz = v.unbind(-1)
    return torch.stack((uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx), dim=-1)


def _safe_div(num: Tensor, den: Tensor, ok: Tensor) -> Tensor:
    """num / den where ok, else 0, without producing inf/nan (nor their gradients) where not ok."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _closest_point_triangle(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Closest point to p on triangle abc (Ericson 5.1.5), branch-free.

    Args:
        p, a, b, c: (..., 3) query point and triangle vertices.

    Returns:
        (..., 3) closest point on the triangle.
    """
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = _dot(ab, ap)
    d2 = _dot(ac, ap)
    bp = p - b
    d3 = _dot(ab, bp)
    d4 = _dot(ac, bp)
    cp = p - c
    d5 = _dot(ab, cp)
    d6 = _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    # Ericson tests the regions in the order A, B, AB, C, AC, BC, face and returns at the first hit; apply them in
    # reverse so the earliest test overrides.
    vap, vbp, vcp = va.clamp_min(0), vb.clamp_min(0), vc.clamp_min(0)
    den = vap + vbp + vcp
    ok = den > 0
    q = a + ab * _safe_div(vbp, den, ok)[..., None] + ac * _safe_div(vcp, den, ok)[..., None]

    e43 = d4 - d3
    e56 = d5 - d6
    den = e43 + e56
    in_bc = (va <= 0) & (e43 >= 0) & (e56 >= 0)
    q = torch.where(in_bc[..., None], b + (c - b) * _safe_div(e43, den, den > 0)[..., None], q)

    den = d2 - d6
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    q = torch.where(in_ac[..., None], a + ac * _safe_div(d2, den, den > 0)[..., None], q)

    in_c = (d6 >= 0) & (d5 <= d6)
    q = torch.where(in_c[..., None], c, q)

    den = d1 - d3
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    q = torch.where(in_ab[..., None], a + ab * _safe_div(d1, den, den > 0)[..., None], q)

    in_b = (d3 >= 0) & (d4 <= d3)
    q = torch.where(in_b[..., None], b, q)

    in_a = (d1 <= 0) & (d2 <= 0)
    return torch.where(in_a[..., None], a, q)


def _closest_segment_segment(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Closest points of segments p1q1 and p2q2 (Ericson 5.1.9), branch-free.

    Args:
        p1, q1, p2, q2: (..., 3) segment end points.
        eps: machine epsilon of the dtype.

    Returns:
        c1, c2: (..., 3) closest points on the first and on the second segment.
    """
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
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
    s = _safe_div(_dot(_cross(p2 - p1, d2), n), nn, line).clamp(0, 1)
    t = _safe_div(b * s + f, e, ~deg2)
    s_lo = _safe_div(-c, a, ~deg1).clamp(0, 1)  # closest on segment 1 to p2 (t = 0)
    s_hi = _safe_div(b - c, a, ~deg1).clamp(0, 1)  # closest on segment 1 to q2 (t = 1)
    s = torch.where(t < 0, s_lo, torch.where(t > 1, s_hi, s))
    t = t.clamp(0, 1)

    t_pt = _safe_div(f, e, ~deg2).clamp(0, 1)  # closest on segment 2 to p1 (s = 0)
    zero = torch.zeros_like(s)
    s = torch.where(deg1, zero, torch.where(deg2, s_lo, s))
    t = torch.where(deg2, zero, torch.where(deg1, t_pt, t))
    return p1 + d1 * s[..., None], p2 + d2 * t[..., None]


def triangle_closest_points(tri_a: Tensor, tri_b: Tensor) -> TriangleClosestPoints:
    """Closest points between K pairs of solid triangles.

    Exact up to rounding for non-intersecting pairs: the minimum over the 6 vertex-triangle and 9 edge-edge
    features (see the module docstring for robustness and for intersecting input). Computes in the input dtype on
    the input device with no host synchronisation. Autograd passes through (piecewise smooth, no nan/inf gradients
    from unselected branches) but is not validated; ``dist`` has a zero gradient where it is exactly 0.

    Args:
        tri_a: (K, 3, 3) vertices of triangles a (vertex index, then xyz).
        tri_b: (K, 3, 3) vertices of triangles b, same dtype and device.

    Returns:
        TriangleClosestPoints ``(dist, qa, qb)``: dist (K,) distance, qa (K, 3) point on triangle a, qb (K, 3) point
        on triangle b, with ``|qa - qb| = dist`` up to rounding.

    Raises:
        ValueError: on a shape other than (K, 3, 3), a non-float dtype, or mismatched dtype, device or K.
    """
    for name, tri in (("tri_a", tri_a), ("tri_b", tri_b)):
        if not isinstance(tri, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(tri).__name__}")
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
    origin = tri_a[:, :1, :]  # (K, 1, 3)
    a = tri_a - origin
    b = tri_b - origin

    # Vertex-triangle: the 3 vertices of a against b, then the 3 vertices of b against a.
    p = torch.cat((a, b), dim=1)  # (K, 6, 3)
    t0, t1, t2 = (torch.cat((b[:, i : i + 1].expand(k, 3, 3), a[:, i : i + 1].expand(k, 3, 3)), 1) for i in range(3))
    q = _closest_point_triangle(p, t0, t1, t2)  # (K, 6, 3)
    qa_vt = torch.cat((a, q[:, 3:]), dim=1)
    qb_vt = torch.cat((q[:, :3], b), dim=1)

    # Edge-edge: edge i of a is (a_i, a_i+1); pairs (i, j) row-major.
    a_next = a.roll(-1, dims=1)
    b_next = b.roll(-1, dims=1)
    c1, c2 = _closest_segment_segment(
        a[:, :, None].expand(k, 3, 3, 3).reshape(k, 9, 3),
        a_next[:, :, None].expand(k, 3, 3, 3).reshape(k, 9, 3),
        b[:, None].expand(k, 3, 3, 3).reshape(k, 9, 3),
        b_next[:, None].expand(k, 3, 3, 3).reshape(k, 9, 3),
        eps,
    )

    qa_all = torch.cat((qa_vt, c1), dim=1)  # (K, 15, 3)
    qb_all = torch.cat((qb_vt, c2), dim=1)  # (K, 15, 3)
    diff = qa_all - qb_all
    d2_all = _dot(diff, diff)  # (K, 15)
    idx = d2_all.argmin(dim=1, keepdim=True)  # (K, 1), first minimum on ties
    d2 = d2_all.gather(1, idx)[:, 0]
    gidx = idx[:, :, None].expand(k, 1, 3)
    qa = qa_all.gather(1, gidx)[:, 0] + origin[:, 0]
    qb = qb_all.gather(1, gidx)[:, 0] + origin[:, 0]
    pos = d2 > 0
    dist = torch.where(pos, torch.where(pos, d2, torch.ones_like(d2)).sqrt(), torch.zeros_like(d2))
    return TriangleClosestPoints(dist, qa, qb)


# ----------------------------------------------------------------------------------------------------------------------
# numba: the same formulas on scalars, in the same order.

_EPS64 = float(np.finfo(np.float64).eps)
_TINY64 = _EPS64 * _EPS64
_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}


@numba.njit(**_JIT)
def _closest_point_triangle_nb(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point to p on triangle abc; scalar twin of :func:`_closest_point_triangle`. Returns (qx, qy, qz)."""
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
def _closest_segment_segment_nb(
    p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z
):
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
        P = A if side == 0 else B
        T = B if side == 0 else A
        tax, tay, taz = T[0, 0] - ox, T[0, 1] - oy, T[0, 2] - oz
        tbx, tby, tbz = T[1, 0] - ox, T[1, 1] - oy, T[1, 2] - oz
        tcx, tcy, tcz = T[2, 0] - ox, T[2, 1] - oy, T[2, 2] - oz
        for i in range(3):
            px, py, pz = P[i, 0] - ox, P[i, 1] - oy, P[i, 2] - oz
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
