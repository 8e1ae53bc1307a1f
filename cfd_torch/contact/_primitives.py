"""Shared machinery of the locally supported baseline models (IPC, SDRS): which primitives of two rigid bodies can
be within reach of each other, the chain rule from the primitives' world points to the bodies' poses, and the
hierarchies' collision query at a fixed margin (their +inf).

Broad phase, for body pairs (s, i, j) of pose sets s: the bodies' world bounding boxes; pairs whose boxes come
within ``reach`` are near, and only primitives (vertices, edges, faces) touching the overlap of the two boxes grown
by ``reach`` can be within reach of the other body. Everything is batched over pairs (grouped index arithmetic, no
loop over pairs).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..config import DEFAULT_CONTACT
from ..rotation import rotation_matrix
from ._traverse import build_forest, penetrating
from .bsh import unique_hierarchies


class Meshes(NamedTuple):
    """N bodies' meshes concatenated: body-frame vertices X (V, 3), faces F (F, 3) and edges E (E, 2) as global
    vertex indices, the body of each vertex (V,), and each body's first vertex, face and edge ((N + 1,) each)."""

    X: torch.Tensor
    F: torch.Tensor
    E: torch.Tensor
    vbody: torch.Tensor
    vstart: torch.Tensor
    fstart: torch.Tensor
    estart: torch.Tensor

    @staticmethod
    def build(bshes) -> Meshes:
        X, F, E, vb = [], [], [], []
        vs, fs, es = [0], [0], [0]
        for k, b in enumerate(bshes):
            V = b.vertices.to(torch.float64)
            Fk = b.faces.to(torch.long)
            Ek = torch.sort(Fk[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1).values.unique(dim=0)
            X.append(V)
            F.append(Fk + vs[-1])
            E.append(Ek + vs[-1])
            vb.append(torch.full((len(V),), k))
            vs.append(vs[-1] + len(V))
            fs.append(fs[-1] + len(Fk))
            es.append(es[-1] + len(Ek))
        return Meshes(
            torch.cat(X), torch.cat(F), torch.cat(E), torch.cat(vb), torch.tensor(vs), torch.tensor(fs),
            torch.tensor(es),
        )  # fmt: skip


class CollisionQuery:
    """The hierarchies' collision query at a fixed ``margin``: (P,) bool, the body pairs (rows (s, i, j)) with two
    triangles within ``margin`` of each other or intersecting, at poses (S, N, 6); ``scale`` (N,) scales each body
    about its origin first. Runs on the CPU (numba), the hierarchies concatenated on first use."""

    def __init__(self, bshes, margin: float) -> None:
        self._bshes, self._which = unique_hierarchies(bshes)
        self.margin = float(margin)
        self._forest = None

    def __call__(
        self, poses: torch.Tensor, pairs: torch.Tensor, scale: torch.Tensor | None = None
    ) -> torch.Tensor:
        if pairs.shape[0] == 0:
            return torch.zeros(0, dtype=torch.bool, device=poses.device)
        if self._forest is None:
            forest = build_forest(self._bshes, torch.float64, torch.device("cpu"))
            self._forest = (forest, forest.roots[self._which])
        forest, roots = self._forest
        cpu = torch.device("cpu")
        S, N = poses.shape[:2]
        p = pairs.to(cpu)
        sc = None if scale is None else scale.to(cpu, torch.float64).repeat(S)
        c = DEFAULT_CONTACT  # (the query's traversal settings: only which pairs are within the margin counts)
        out = penetrating(
            forest, p[:, :1] * N + p[:, 1:], roots[p[:, 1:]], poses.detach().to(cpu, torch.float64).reshape(S * N, 6),
            margin=self.margin, eps=c.eps, split=c.split, tol=c.pair_tol, max_iter=c.pair_max_iter, scale=sc,
        )  # fmt: skip
        return out.to(poses.device)


class Near(NamedTuple):
    """The near body pairs of an evaluation: world vertices W (S, V, 3) of every body, the near pairs (Q,) (indices
    into the asked pairs), their pose set s (Q,) and bodies i, j (Q,), and the grown overlap box lo, hi (Q, 3)."""

    W: torch.Tensor
    pair: torch.Tensor
    s: torch.Tensor
    i: torch.Tensor
    j: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor


def near_pairs(meshes: Meshes, poses: torch.Tensor, pairs: torch.Tensor, reach: float) -> Near:
    """The body pairs (rows (s, i, j) of ``pairs``) whose world boxes at ``poses`` (S, N, 6) come within ``reach``."""
    dev = poses.device
    S, N = poses.shape[:2]
    X, vbody = meshes.X.to(dev), meshes.vbody.to(dev)
    table = poses.reshape(S * N, 6).detach()
    R, t = rotation_matrix(table[:, 3:]), table[:, :3]
    rows = torch.arange(S, device=dev)[:, None] * N + vbody[None]
    W = torch.einsum("svij,vj->svi", R[rows], X) + t[rows]
    idx = vbody[None, :, None].expand(S, -1, 3)
    lo = W.new_full((S, N, 3), float("inf")).scatter_reduce(1, idx, W, "amin")
    hi = W.new_full((S, N, 3), -float("inf")).scatter_reduce(1, idx, W, "amax")
    s, i, j = pairs.unbind(1)
    near = ((lo[s, i] <= hi[s, j] + reach) & (lo[s, j] <= hi[s, i] + reach)).all(1)
    q = torch.nonzero(near)[:, 0]
    sq, iq, jq = s[q], i[q], j[q]
    return Near(
        W,
        q,
        sq,
        iq,
        jq,
        torch.maximum(lo[sq, iq], lo[sq, jq]) - reach,
        torch.minimum(hi[sq, iq], hi[sq, jq]) + reach,
    )


def ranges(start: torch.Tensor, count: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For groups g with items start[g] .. start[g] + count[g] - 1: (group of each item, item), concatenated."""
    g = torch.repeat_interleave(torch.arange(len(count), device=count.device), count)
    first = torch.cumsum(count, 0) - count
    return g, start[g] + torch.arange(int(count.sum()), device=count.device) - first[g]


def grouped_cross(ga: torch.Tensor, gb: torch.Tensor, groups: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All index pairs (ia, ib) with ga[ia] == gb[ib] (group ids in [0, groups))."""
    order = torch.argsort(gb, stable=True)
    cb = torch.bincount(gb, minlength=groups)
    start = torch.cumsum(cb, 0) - cb
    rep = cb[ga]
    ia = torch.repeat_interleave(torch.arange(len(ga), device=ga.device), rep)
    offs = torch.arange(int(rep.sum()), device=ga.device) - (torch.cumsum(rep, 0) - rep)[ia]
    return ia, order[start[ga[ia]] + offs]


def primitives(
    near: Near, body: torch.Tensor, start: torch.Tensor, index: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per near pair q, the primitives of its body ``body[q]`` touching its grown overlap box: (q of each, primitive
    id). ``start`` (N + 1,) the bodies' first primitives; ``index`` (M, k) the primitives' vertex ids (None: the
    primitives are the vertices)."""
    start = start.to(body.device)
    g, item = ranges(start[body], start[body + 1] - start[body])
    ids = item[:, None] if index is None else index.to(body.device)[item]
    pts = near.W[near.s[g][:, None], ids]
    keep = ((pts.amin(1) <= near.hi[g]) & (pts.amax(1) >= near.lo[g])).all(1)
    return g[keep], item[keep]


def chain_to_poses(
    gx: torch.Tensor,
    Hx: torch.Tensor | None,
    X: torch.Tensor,
    side: torch.Tensor,
    rows: torch.Tensor,
    poses: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Pose-space gradient (C, 12) and Hessian (C, 12, 12) over [q_i, q_j] of C functions of K points each, from
    their point gradients gx (C, K, 3) and Hessians Hx (C, K, 3, K, 3) (None: no Hessian): point k is
    x = R(omega) X + t of body ``side`` (C, K) (0: i, 1: j), whose row of ``poses`` (S, N, 6) flattened is ``rows``
    (C, K). J^T g, and J^T H J plus g . d2x / domega2 (the rotation's second derivatives)."""
    from ..rotation import rotation_derivatives

    S, N = poses.shape[:2]
    C, K = gx.shape[:2]
    f64 = gx.dtype
    _, dR, d2R = rotation_derivatives(poses.reshape(S * N, 6)[:, 3:].detach(), 1 if Hx is None else 2)
    dRX = torch.einsum("ckijl,ckj->ckil", dR[rows], X)  # (C, K, 3, 3): dx / domega_l
    eye = torch.eye(3, dtype=f64, device=gx.device).expand(C, K, 3, 3)
    J6 = torch.cat([eye, dRX], -1)  # (C, K, 3, 6)
    on_j = side[..., None, None].to(f64)
    J = torch.cat([J6 * (1 - on_j), J6 * on_j], -1)  # (C, K, 3, 12)
    grad = torch.einsum("cki,ckiq->cq", gx, J)
    if Hx is None:
        return grad, None
    hess = torch.einsum("ckimj,ckia,cmjb->cab", Hx, J, J)
    second = torch.einsum("cki,ckijab,ckj->ckab", gx, d2R[rows], X)  # (C, K, 3, 3)
    for s in (0, 1):
        o = 6 * s + 3
        hess[:, o : o + 3, o : o + 3] += (second * (side == s)[..., None, None].to(f64)).sum(1)
    return grad, hess
