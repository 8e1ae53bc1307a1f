"""IPC's log barrier between rigid bodies as a contact model: the experiments' ``ipc`` baseline.

Incremental Potential Contact (Li et al. 2020) as ipc-toolkit 1.6.1 defines it (``NormalCollisions`` with its
default collision set, ``BarrierPotential(dhat, kappa)``): over every vertex-face pair and every edge-edge pair of
two bodies closer than dhat,

    P = kappa sum_VF b(d^2; dhat^2) + kappa sum_EE m(c) b(d^2; dhat^2),    b(x; xh) = -(x - xh)^2 ln(x / xh)

on 0 < x < xh (0 beyond, +inf at x <= 0), d the distance between the two primitives (to the closest feature:
face, edge or vertex), and for edge pairs the mollifier m(c) = (2 - c / eps_x) c / eps_x for c < eps_x (1 above),
c = |ea x eb|^2, eps_x = 1e-3 |ea|^2 |eb|^2 at rest, which keeps nearly parallel edges smooth. (ipc-toolkit merges
the collisions a vertex-face or edge-edge pair reduces to, e.g. a vertex nearest to an edge found from both faces of
the edge, into one whose weight is their multiplicity: the same sum.) Everything is exactly zero beyond dhat, so no
force and no gradient reaches bodies that do not already nearly touch.

Each evaluation finds the pairs: bodies whose world bounding boxes come within dhat, then their vertices, faces and
edges within dhat of the other body's box, then every vertex-face and edge-edge combination of those within dhat.
Derivatives: the barrier of each primitive pair as a function of its four world points (the distance formula of its
closest-feature type, fixed per evaluation as in ipc-toolkit) by ``torch.func``, chained to the two bodies' poses
x = R(omega) X + t with the rotation's closed-form first and second derivatives. A body pair is infeasible (+inf)
when two of its triangles come within 1e-6 dhat of each other or intersect (the collision query of the hierarchy at
that margin: ipc-toolkit's barrier is finite at any positive distance, but within rounding of contact the distances
are noise; ipc-toolkit's continuous collision detection can keep primitives ``min_distance`` apart the same way;
the barrier itself is unchanged).

Lagged friction uses one contact per primitive pair: the closest points on the two bodies (material points),
the normal along the line between them, and the barrier's normal force kappa m |b'(d^2)| 2 d.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from .._validate import check_positive
from ..config import DEFAULT_CONTACT
from ..rotation import rotation_matrix
from ._primitives import CollisionQuery, Meshes, chain_to_poses, grouped_cross, near_pairs, primitives
from .bsh import BSH
from .model import ContactEval, LaggedContacts

__all__ = ["IpcContact", "ipc_barrier_derivatives"]

#: edge-edge mollifier threshold factor (ipc-toolkit's ``edge_edge_mollifier_threshold``)
_MOLLIFIER = 1e-3
#: sin^2 of the angle below which two edges are parallel (ipc-toolkit's ``edge_edge_distance_type``)
_PARALLEL = 2.5e-16


def ipc_barrier_derivatives(x: torch.Tensor, xhat: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """b(x; xhat) = -(x - xhat)^2 ln(x / xhat) and its first two derivatives in x, for 0 < x < xhat."""
    r = x - xhat
    ln = torch.log(x / xhat)
    return -r * r * ln, -2 * r * ln - r * r / x, -2 * ln - 4 * r / x + r * r / (x * x)


def _safe(den: torch.Tensor) -> torch.Tensor:
    return torch.where(den > 0, den, torch.ones_like(den))


def _point_line(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    e = b - a
    c = torch.linalg.cross(p - a, e)
    return (c * c).sum(-1) / _safe((e * e).sum(-1))


def _vf_distance2(x: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
    """Squared distance of point x[0] to the feature ``kind`` of the triangle x[1:4]: 0 its plane, 1-3 the lines
    of edges (1 2), (2 3), (3 1), 4-6 its vertices (one-hot (..., 7) ``kind``)."""
    p, t0, t1, t2 = x.unbind(-2)
    n = torch.linalg.cross(t1 - t0, t2 - t0)
    plane = ((p - t0) * n).sum(-1) ** 2 / _safe((n * n).sum(-1))
    d = torch.stack(
        [
            plane,
            _point_line(p, t0, t1),
            _point_line(p, t1, t2),
            _point_line(p, t2, t0),
            ((p - t0) ** 2).sum(-1),
            ((p - t1) ** 2).sum(-1),
            ((p - t2) ** 2).sum(-1),
        ],
        -1,
    )
    return (d * kind).sum(-1)


def _ee_distance2(x: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
    """Squared distance of edges x[0:2] and x[2:4] by the feature pair ``kind``: 0 line-line, 1-2 a0 / a1 to line b,
    3-4 b0 / b1 to line a, 5-8 the endpoint pairs (a0 b0), (a0 b1), (a1 b0), (a1 b1) (one-hot (..., 9))."""
    a0, a1, b0, b1 = x.unbind(-2)
    n = torch.linalg.cross(a1 - a0, b1 - b0)
    lines = ((b0 - a0) * n).sum(-1) ** 2 / _safe((n * n).sum(-1))
    d = torch.stack(
        [
            lines,
            _point_line(a0, b0, b1),
            _point_line(a1, b0, b1),
            _point_line(b0, a0, a1),
            _point_line(b1, a0, a1),
            ((a0 - b0) ** 2).sum(-1),
            ((a0 - b1) ** 2).sum(-1),
            ((a1 - b0) ** 2).sum(-1),
            ((a1 - b1) ** 2).sum(-1),
        ],
        -1,
    )
    return (d * kind).sum(-1)


def _mollifier(x: torch.Tensor, eps_x: torch.Tensor) -> torch.Tensor:
    """ipc-toolkit's edge-edge mollifier of c = |ea x eb|^2 (1 for vertex-face pairs, whose eps_x is 0)."""
    n = torch.linalg.cross(x[..., 1, :] - x[..., 0, :], x[..., 3, :] - x[..., 2, :])
    c = (n * n).sum(-1)
    s = c / _safe(eps_x)
    return torch.where(c < eps_x, (2.0 - s) * s, torch.ones_like(c))


def _energy(x: torch.Tensor, kind: torch.Tensor, eps_x: torch.Tensor, edge: torch.Tensor, xhat: float):
    """kappa-free barrier of one primitive pair at its world points x (4, 3): vertex-face (``edge`` 0) or edge-edge
    (``edge`` 1, mollified), ``kind`` one-hot over 9 features (vertex-face pairs use the first 7)."""
    d2 = torch.where(edge > 0, _ee_distance2(x, kind), _vf_distance2(x, kind[..., :7]))
    return _mollifier(x, eps_x) * ipc_barrier_derivatives(d2, xhat)[0]


def _classify_vf(x: torch.Tensor) -> torch.Tensor:
    """(C,) the closest feature (0-6, as ``_vf_distance2``) of triangles x[:, 1:4] to points x[:, 0], by
    ipc-toolkit's rule (``point_triangle_distance_type``), ties included: a point whose projection lies on an edge's
    line or beyond it, within the edge's span, is that edge's (tested in the order ab, bc, ca); else a vertex whose
    two edges' spans it lies beyond; else the plane. (At a tie the distances agree but the Hessians do not.)"""
    p, a, b, c = x.unbind(1)
    n = torch.linalg.cross(b - a, c - a)
    along = []  # each edge's parameter of the point along it
    kind = torch.zeros(len(x), dtype=torch.long, device=x.device)
    found = torch.zeros(len(x), dtype=torch.bool, device=x.device)
    for k, (e0, e1) in enumerate(((a, b), (b, c), (c, a))):
        e = e1 - e0
        out = torch.linalg.cross(e, n)  # in the plane, away from the triangle
        s = ((p - e0) * e).sum(-1) / (e * e).sum(-1)
        beyond = ((p - e0) * out).sum(-1) >= 0
        along.append(s)
        hit = ~found & (s > 0) & (s < 1) & beyond
        kind, found = torch.where(hit, k + 1, kind), found | hit
    for k, (after, before) in enumerate(((0, 2), (1, 0), (2, 1))):  # vertex a: before edge ab, after edge ca
        hit = ~found & (along[after] <= 0) & (along[before] >= 1)
        kind, found = torch.where(hit, k + 4, kind), found | hit
    return kind


def _classify_ee(x: torch.Tensor) -> torch.Tensor:
    """(C,) the closest feature pair (0-8, as ``_ee_distance2``) of segments x[:, 0:2] and x[:, 2:4], by
    ipc-toolkit's rule (``edge_edge_distance_type``), ties included: edges with sin^2 of their angle below
    ``_PARALLEL`` are parallel, classified by where edge b's ends project onto edge a."""
    a0, a1, b0, b1 = x.unbind(1)
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    a, b, c, d, e = (u * u).sum(-1), (u * v).sum(-1), (v * v).sum(-1), (u * w).sum(-1), (v * w).sum(-1)
    den = a * c - b * b
    n = torch.linalg.cross(u, v)
    parallel = (n * n).sum(-1) < _PARALLEL * a * c
    # closest points' parameters s on a, t = tn / td on b; s clamped first
    sn = b * e - c * d
    s0, s1 = sn <= 0, sn >= den
    tn = torch.where(s0, e, torch.where(s1, e + b, a * e - b * d))
    td = torch.where(s0 | s1, c, den)
    kind = torch.where(s0, 1, torch.where(s1, 2, 0))
    at_b0 = torch.where(-d <= 0, 5, torch.where(-d >= a, 7, 3))
    at_b1 = torch.where(b - d <= 0, 6, torch.where(b - d >= a, 8, 4))
    kind = torch.where(tn <= 0, at_b0, torch.where(tn >= td, at_b1, kind))
    # parallel: b's ends at alpha, beta along a; ea: 0 a0, 1 a1, 2 inside a; eb: 0 b0, 1 b1, 2 inside b
    alpha, beta = ((b0 - a0) * u).sum(-1) / a, ((b1 - a0) * u).sum(-1) / a
    beta_on_a = (beta >= 0) & (beta <= 1)
    ea = torch.where(
        alpha < 0, torch.where(beta_on_a, 2, 0), torch.where(alpha > 1, torch.where(beta_on_a, 2, 1), 2)
    )
    eb_below = torch.where(beta <= alpha, 0, torch.where(beta <= 1, 1, 2))
    eb_above = torch.where(beta >= alpha, 0, torch.where(beta >= 0, 1, 2))
    eb = torch.where(alpha < 0, eb_below, torch.where(alpha > 1, eb_above, 0))
    by_ends = torch.where(eb < 2, torch.where(ea < 2, 5 + 2 * ea + eb, 3 + eb), 1 + ea)
    return torch.where(parallel, by_ends, kind)


def _closest_points(
    x: torch.Tensor, kind: torch.Tensor, edge: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The closest points (C, 3) of the two primitives of each pair (its first and its second primitive), for its
    feature ``kind`` (C,) long; differentiable in the world points x (C, 4, 3)."""

    def on_line(p, a, b):
        e = b - a
        return a + (((p - a) * e).sum(-1) / (e * e).sum(-1))[:, None] * e

    p, t0, t1, t2 = x.unbind(1)
    n = torch.linalg.cross(t1 - t0, t2 - t0)
    vf_second = torch.stack(
        [p - (((p - t0) * n).sum(-1) / (n * n).sum(-1))[:, None] * n, on_line(p, t0, t1), on_line(p, t1, t2),
         on_line(p, t2, t0), t0, t1, t2, p, p], 1,
    )  # fmt: skip
    a0, a1, b0, b1 = p, t0, t1, t2
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    a, b, c, d, e = (u * u).sum(-1), (u * v).sum(-1), (v * v).sum(-1), (u * w).sum(-1), (v * w).sum(-1)
    den = _safe(a * c - b * b)
    sl, tl = (b * e - c * d) / den, (a * e - b * d) / den
    ee_first = torch.stack(
        [a0 + sl[:, None] * u, a0, a1, on_line(b0, a0, a1), on_line(b1, a0, a1), a0, a0, a1, a1], 1
    )
    ee_second = torch.stack(
        [b0 + tl[:, None] * v, on_line(a0, b0, b1), on_line(a1, b0, b1), b0, b1, b0, b1, b0, b1], 1
    )
    pick = lambda y: y.gather(1, kind[:, None, None].expand(-1, 1, 3))[:, 0]  # noqa: E731
    is_edge = edge[:, None] > 0
    return torch.where(is_edge, pick(ee_first), p), torch.where(is_edge, pick(ee_second), pick(vf_second))


class _Collisions(NamedTuple):
    """The primitive pairs within dhat of one evaluation (C of them), and the body pairs near enough to have some.

    Attributes:
        near: (Q,) the asked pairs whose bodies' boxes come within dhat (the only ones that can have collisions
            or intersect).
        pair: (C,) each primitive pair's body pair (index into the asked pairs).
        X: (C, 4, 3) its body-frame points: a vertex-face pair's vertex then the face, an edge-edge pair's edge of
            body i then that of body j.
        side: (C, 4) on which body of the pair each point lies (0: i, 1: j).
        edge: (C,) 0 vertex-face, 1 edge-edge.
        kind: (C,) the closest feature (``_vf_distance2`` / ``_ee_distance2``).
        eps_x: (C,) the mollifier's threshold (0 for vertex-face pairs).
        x: (C, 4, 3) the world points; d2: (C,) the squared distances.
    """

    near: torch.Tensor
    pair: torch.Tensor
    X: torch.Tensor
    side: torch.Tensor
    edge: torch.Tensor
    kind: torch.Tensor
    eps_x: torch.Tensor
    x: torch.Tensor
    d2: torch.Tensor


# the separation below which IpcContact calls a body pair infeasible, as a fraction of dhat
_MIN_SEPARATION = 1e-6


class IpcContact:
    """IPC's log barrier between N bodies (a :class:`cfd_torch.contact.ContactModel`; see the module docstring).

    Args:
        bshes: the N bodies' hierarchies (their meshes: vertices, faces, and the edges of the faces).
        dhat: activation distance [m]: the potential, its forces and its gradients are exactly zero beyond it.
        stiffness: kappa [N / m^3] (b is in m^4: the force of a primitive pair at d = dhat / 2 is about
            kappa 4.3 dhat^3).
    """

    warm_start = False

    def __init__(
        self, bshes: Sequence[BSH], dhat: float = DEFAULT_CONTACT.dhat, stiffness: float = 1e6
    ) -> None:
        if not all(isinstance(b, BSH) for b in bshes) or not bshes:
            raise ValueError("bshes must be a non-empty sequence of cfd_torch.BSH")
        check_positive(dhat, "dhat")
        check_positive(stiffness, "stiffness")
        self.dhat, self.stiffness = float(dhat), float(stiffness)
        self.num_bodies = len(bshes)
        self.bshes = tuple(bshes)  # one per body, in the scene's order
        self._meshes = Meshes.build(bshes)
        #: the gap below which the potential is +inf: IPC's barrier is finite at any positive distance, but within
        #: rounding of contact its distances are noise and its Newton steps fall below the coordinates' spacing (a
        #: ball thrown at a wall whose start landed one ulp short of it never moved again): a minimum separation
        self.margin = _MIN_SEPARATION * self.dhat
        self._query = CollisionQuery(bshes, self.margin)

    # -- the collision query: triangles within the minimum separation or intersecting
    def infeasible(
        self, poses: torch.Tensor, pairs: torch.Tensor, scale: torch.Tensor | None = None
    ) -> torch.Tensor:
        return self._query(poses, pairs, scale)

    # -- the primitive pairs within dhat
    def _collisions(self, poses: torch.Tensor, pairs: torch.Tensor) -> _Collisions:
        dev = poses.device
        m = self._meshes
        h = self.dhat
        near = near_pairs(m, poses, pairs, h)
        Q = len(near.pair)
        Fv, Ev = m.F.to(dev), m.E.to(dev)
        out = []
        for a_body, b_body, side_a in ((near.i, near.j, 0), (near.j, near.i, 1)):  # vertices against faces
            gv, v = primitives(near, a_body, m.vstart, None)
            gf, f = primitives(near, b_body, m.fstart, Fv)
            ia, ib = grouped_cross(gv, gf, Q)
            ids = torch.cat([v[ia][:, None], Fv[f[ib]]], 1)  # (C, 4) vertex, face
            out.append(
                (gv[ia], ids, torch.tensor([side_a, 1 - side_a, 1 - side_a, 1 - side_a], device=dev), 0)
            )
        ge_i, e_i = primitives(near, near.i, m.estart, Ev)
        ge_j, e_j = primitives(near, near.j, m.estart, Ev)
        ia, ib = grouped_cross(ge_i, ge_j, Q)
        out.append(
            (ge_i[ia], torch.cat([Ev[e_i[ia]], Ev[e_j[ib]]], 1), torch.tensor([0, 0, 1, 1], device=dev), 1)
        )
        g = torch.cat([o[0] for o in out])
        ids = torch.cat([o[1] for o in out])
        side = torch.cat([o[2].expand(len(o[0]), 4) for o in out])
        edge = torch.cat([torch.full((len(o[0]),), o[3], device=dev, dtype=torch.long) for o in out])
        x = near.W[near.s[g][:, None], ids]
        kind = torch.where(edge > 0, _classify_ee(x), _classify_vf(x)) if len(g) else edge
        one_hot = torch.nn.functional.one_hot(kind, 9).to(x.dtype)
        d2 = torch.where(edge > 0, _ee_distance2(x, one_hot), _vf_distance2(x, one_hot[..., :7]))
        keep = d2 < h * h
        g, ids, side, edge, kind, x, d2 = (y[keep] for y in (g, ids, side, edge, kind, x, d2))
        Xb = m.X.to(dev)[ids]
        ea, eb = Xb[:, 1] - Xb[:, 0], Xb[:, 3] - Xb[:, 2]
        eps_x = torch.where(
            edge > 0, _MOLLIFIER * (ea * ea).sum(-1) * (eb * eb).sum(-1), torch.zeros_like(d2)
        )
        return _Collisions(near.pair, near.pair[g], Xb, side, edge, kind, eps_x, x, d2)

    def evaluate(
        self,
        poses: torch.Tensor,
        pairs: torch.Tensor,
        order: int,
        ids: torch.Tensor | None = None,
        warm: object | None = None,
    ) -> ContactEval:
        P = pairs.shape[0]
        f64 = torch.float64
        poses = poses.detach().to(f64)
        value = poses.new_zeros(P)
        grad = poses.new_zeros(P, 12) if order >= 1 else None
        hess = poses.new_zeros(P, 12, 12) if order >= 2 else None
        if P == 0:
            return ContactEval(value, grad, hess, 0, 0)
        col = self._collisions(poses, pairs)
        C = len(col.pair)
        xhat = self.dhat * self.dhat
        kind = torch.nn.functional.one_hot(col.kind, 9).to(f64)
        edge = col.edge.to(f64)
        if C:
            e = self.stiffness * _energy(col.x, kind, col.eps_x, edge, xhat)
            value.index_add_(0, col.pair, e)
        if order >= 1 and C:
            fn = lambda x, k, ex, ed: self.stiffness * _energy(x, k, ex, ed, xhat)  # noqa: E731
            gx = torch.func.vmap(torch.func.grad(fn))(col.x, kind, col.eps_x, edge)  # (C, 4, 3)
            N = poses.shape[1]
            body = pairs[col.pair][:, 1:].gather(1, col.side)  # (C, 4) the body of each point
            rows = pairs[col.pair][:, :1] * N + body
            Hx = torch.func.vmap(torch.func.hessian(fn))(col.x, kind, col.eps_x, edge) if order >= 2 else None
            g, H = chain_to_poses(gx, Hx, col.X, col.side, rows, poses)
            grad.index_add_(0, col.pair, g)
            if H is not None:
                hess.index_add_(0, col.pair, H)
        if len(col.near):  # touching or intersecting triangles: +inf (as ``infeasible``)
            bad = self.infeasible(poses, pairs[col.near])
            inf = col.near[bad]
            value[inf] = float("inf")
            for d in (grad, hess):  # no force from an infeasible pair, as this library's potential
                if d is not None:
                    d[inf] = 0.0
        return ContactEval(value, grad, hess, 0, C)

    def lagged(
        self, poses: torch.Tensor, pairs: torch.Tensor, active: float, create_graph: bool = False
    ) -> LaggedContacts:
        S, N = poses.shape[:2]
        with torch.no_grad():
            col = self._collisions(poses.detach().to(torch.float64), pairs)
        body = pairs[col.pair][:, 1:].gather(1, col.side)
        rows = pairs[col.pair][:, :1] * N + body  # (C, 4)
        table = poses.reshape(S * N, 6) if create_graph else poses.reshape(S * N, 6).detach()
        R = rotation_matrix(table[:, 3:])
        x = torch.einsum("cpij,cpj->cpi", R[rows], col.X) + table[rows, :3]  # world points (C, 4, 3)
        first, second = _closest_points(x, col.kind, col.edge)
        # the first primitive lies on body i unless it is a vertex of body j (then swap)
        swap = (col.side[:, 0] == 1)[:, None]
        xi, xj = torch.where(swap, second, first), torch.where(swap, first, second)
        diff = xi - xj
        d = torch.linalg.vector_norm(diff, dim=-1)
        n = diff / d[:, None]
        xhat = self.dhat * self.dhat
        m = _mollifier(x, col.eps_x)
        lam = self.stiffness * m * ipc_barrier_derivatives(d * d, xhat)[1].abs() * 2 * d
        pc = pairs[col.pair]
        bi, bj = pc[:, 0] * N + pc[:, 1], pc[:, 0] * N + pc[:, 2]
        Xi = torch.einsum("cji,cj->ci", R[bi], xi - table[bi, :3])
        Xj = torch.einsum("cji,cj->ci", R[bj], xj - table[bj, :3])
        keep = torch.ones_like(d, dtype=torch.bool)
        if active > 0 and len(d):
            top = d.new_zeros(pairs.shape[0]).scatter_reduce(0, col.pair, lam.detach(), "amax")
            keep = lam.detach() >= active * top[col.pair]
        T = torch.eye(3, dtype=n.dtype, device=n.device) - n[:, :, None] * n[:, None, :]
        return LaggedContacts(
            col.pair[keep], torch.stack([Xi, Xj], 1)[keep], torch.stack([xi, xj], 1)[keep], T[keep], lam[keep]
        )
