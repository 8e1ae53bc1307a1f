"""The BSH traversal engine: the potential of many body pairs at once, and the collision query.

Private to :mod:`cfd_torch.contact`; the public faces are :func:`cfd_torch.mesh_potential`,
:func:`cfd_torch.contact_potential` and :class:`cfd_torch.contact.CfdContact`.

For two bodies with hierarchies a and b at poses q_a, q_b (translation, rotation vector), the potential is the
recursion of SPEC section 4, started at the two roots::

    P(I, J) = P_c(r)                                  if s >= 1       (far: no descent)
            = phi P_c(r) + (1 - phi) F(I, J)          otherwise, phi = Phi(s) for s > 0 else 0
    F(I, J) = P_exact(tri_I, tri_J)                   if both are leaves
            = sum of P over the child pairs           otherwise (split both, or the larger)

with r = |c_I - c_J| (world centres), d1 = R_I + R_J, s = (r - d1) / w, w = max(eps d1, 2 delta) (eps one number,
or one per body pair: ``Scene(pair_eps=...)``): the band is
never narrower than twice the margin delta (:func:`cfd_torch.contact.central.band_width`), so that a far pair
(s >= 1, central term only, finite) has its spheres at least 2 delta apart and no triangle pair below it within
the margin; a narrower band (eps d1 < delta: d1 < 0.1 m at the defaults) left the potential finite and flat up to
a jump to +inf where the meshes were already within the margin (a barrier without a barrier's growth).

Unrolled, P is a sum of terms ``w * V`` where V is P_c(r) or P_exact and w is the node pair's own phi (central
terms) times the (1 - phi) of all its ancestors. The traversal is breadth-first and batched: the frontier of node
pairs of all body pairs is a set of tensors, classified per level; each frontier element carries its inherited
weight W with its gradient and Hessian in the 12 pose coordinates of its body pair, so the weights' derivatives
enter the result exactly (product rule). Leaf pairs of all levels are solved in one batch at the end
(``pair_potential_derivatives``) and chained to pose space with the second-order rotation terms::

    grad_q = J^T grad_x,   hess_q = J^T hess_x J + sum_k grad_x_k . d2x_k/dq2,   x_k = R(omega) X_k + t.

Coordinates of a body pair's derivatives: [t_a, omega_a, t_b, omega_b]."""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch

from .._threads import parallel_kernels, start_numba_pool
from ..rotation import point_jacobian, rot_second, rotation_derivatives
from .bsh import BSH
from .central import BAND_MARGINS
from .pair import pair_potential_derivatives


# ---------------------------------------------------------------------------------------------- the forest
class Forest(NamedTuple):
    centre: torch.Tensor  # (M, 3) body-frame node centres of all hierarchies
    radius: torch.Tensor  # (M,)
    child: torch.Tensor  # (M, 2) global ids, -1 for leaves
    tri: torch.Tensor  # (M,) global triangle ids, -1 for internal nodes
    tris: torch.Tensor  # (T, 3, 3) body-frame triangles
    roots: torch.Tensor  # (H,) root id of each hierarchy


_FOREST_CACHE: OrderedDict = OrderedDict()
_FOREST_CACHE_SIZE = 8
_FOREST_LOCK = threading.Lock()
_QUERY_SLACK = 1e-9  # the CPU collision query's margin is the potential's times 1 + this


def forest_of(bshes: tuple[BSH, ...], dtype: torch.dtype, device: torch.device) -> Forest:
    """:func:`build_forest`, cached for the last few hierarchy tuples (the function API's repeated calls)."""
    key = (tuple(id(b) for b in bshes), dtype, device)
    # under the lock: threads stepping scenes at once could evict an entry between a hit and its move_to_end
    with _FOREST_LOCK:
        hit = _FOREST_CACHE.get(key)
        if hit is not None and all(x is y for x, y in zip(hit[0], bshes, strict=True)):
            _FOREST_CACHE.move_to_end(key)
            return hit[1]
    f = build_forest(bshes, dtype, device)
    with _FOREST_LOCK:
        _FOREST_CACHE[key] = (bshes, f)
        if len(_FOREST_CACHE) > _FOREST_CACHE_SIZE:
            _FOREST_CACHE.popitem(last=False)
    return f


def build_forest(bshes: tuple[BSH, ...], dtype: torch.dtype, device: torch.device) -> Forest:
    """Concatenate hierarchies into one node table."""
    node_off = tri_off = 0
    centre, radius, child, tri, tris, roots = [], [], [], [], [], []
    for b in bshes:
        centre.append(b.centre)
        radius.append(b.radius)
        child.append(torch.where(b.child >= 0, b.child + node_off, b.child))
        tri.append(torch.where(b.tri >= 0, b.tri + tri_off, b.tri))
        tris.append(b.triangles)
        roots.append(node_off)
        node_off += b.num_nodes
        tri_off += b.num_faces
    return Forest(
        torch.cat(centre).to(dtype=dtype, device=device),
        torch.cat(radius).to(dtype=dtype, device=device),
        torch.cat(child).to(device),
        torch.cat(tri).to(device),
        torch.cat(tris).to(dtype=dtype, device=device),
        torch.tensor(roots, device=device),
    )


def _product(a, da, d2a, b, db, d2b):
    """Value, gradient, Hessian of a * b (None derivatives are skipped)."""
    val = a * b
    grad = hess = None
    if da is not None:
        grad = b[:, None] * da + a[:, None] * db
    if d2a is not None:
        outer = da[:, :, None] * db[:, None, :]
        hess = b[:, None, None] * d2a + a[:, None, None] * d2b + outer + outer.transpose(1, 2)
    return val, grad, hess


def _radial(f0, f1, f2, dr, d2r):
    """Gradient and Hessian of f(r) from f', f'' and the derivatives of r."""
    grad = f1[:, None] * dr if dr is not None else None
    hess = None
    if d2r is not None:
        hess = f2[:, None, None] * dr[:, :, None] * dr[:, None, :] + f1[:, None, None] * d2r
    return grad, hess


def _smoothstep_derivs(s: torch.Tensor):
    t = s.clamp(0.0, 1.0)
    phi = t * t * t * (t * (6.0 * t - 15.0) + 10.0)
    d1 = 30.0 * t * t * (t - 1.0) ** 2
    d2 = 60.0 * t * (t - 1.0) * (2.0 * t - 1.0)
    return phi, d1, d2


def _central_derivs(r: torch.Tensor, mu: float):
    ir = 1.0 / r
    sq = torch.sqrt(ir)
    p = 12.0 * mu * (1.0 + sq) ** 2
    p1 = -12.0 * mu * (ir * sq + ir * ir)
    p2 = 12.0 * mu * (1.5 * ir * ir * sq + 2.0 * ir * ir * ir)
    return p, p1, p2


# ---------------------------------------------------------------------------------------------- traversal
def _segment_add(out: torch.Tensor, seg: torch.Tensor, x: torch.Tensor, n: int) -> None:
    """out[seg[e]] += x[e]. index_add_ serialises when few segments receive many rows; a one-hot matrix
    product (few segments) or a plain sum (one segment) does the same reduction with BLAS."""
    if n == 1:
        out[0] += x.sum(0)
    elif n <= 64 and x.dim() > 1:  # (values may be +inf: 0 * inf in the one-hot product would be NaN)
        onehot = (seg[None, :] == torch.arange(n, device=seg.device)[:, None]).to(x.dtype)  # (n, E)
        out += (onehot @ x.reshape(x.shape[0], -1)).reshape(out.shape)
    else:
        out.index_add_(0, seg, x)


def _cat(xs) -> torch.Tensor:
    """torch.cat without the copy of a single tensor (the CPU traversal returns its leaves in one piece)."""
    return xs[0] if len(xs) == 1 else torch.cat(xs)


_POOL: ThreadPoolExecutor | None = (
    None  # threads for the node traversal of many body pairs (numba releases the GIL)
)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(4)
    return _POOL


# Fewer body pairs than this are traversed by one thread, and so are body pairs whose earlier evaluation in the step
# had fewer feasible leaf pairs than _THREAD_MIN_LEAVES: a woken pool thread competes with the OpenMP threads that
# torch and numba leave spinning, so on this project's 2-core machine two threads made an Ant step (9 body pairs,
# about 2,700 leaf pairs) 15 % slower (110 ms against 94), left ten cubes on a floor (66 body pairs, about 900) as
# they were, and made a 16-ball rack step (136 body pairs, about 13,000) 11 % faster.
_THREAD_MIN_PAIRS = 32
_THREAD_MIN_LEAVES = 6000


def _node_threads(P: int, leaves: int | None = None) -> int:
    """How many threads traverse P body pairs: numba's thread count (at most 4), from _THREAD_MIN_PAIRS pairs and,
    when an earlier evaluation's count of leaf pairs is known (``leaves``), from _THREAD_MIN_LEAVES of them."""
    import numba

    if (
        P < _THREAD_MIN_PAIRS
        or (leaves is not None and leaves < _THREAD_MIN_LEAVES)
        or not parallel_kernels()
    ):
        return 1  # (in a fork() child the pool's threads, like OpenMP's, are gone)
    start_numba_pool()  # (numba.get_num_threads starts it)
    return min(numba.get_num_threads(), 4)


class _LeafStage:
    """The leaf pairs of the CPU traversal's parts: their plane solves (warm-started), their warm-start table and
    their terms added to their body pairs' value, gradient and Hessian (``accumulate_leaves_lowrank``), run for
    each part in the thread that traversed it (``serial``: a pool thread, whose plane solves run on it alone).
    What the parts share, read only."""

    def __init__(self, forest, mu, margin, tol, max_iter, order, warm):
        self.forest, self.mu, self.margin, self.tol, self.max_iter, self.order = (
            forest, mu, margin, tol, max_iter, order
        )  # fmt: skip
        self.warm = warm

    def run(self, out, pb, rows, hs, v, g, h, poses, serial: bool):
        """Solve and add the leaf pairs of one part (``out``: its ``traverse_nodes`` result; its body pairs ``pb``,
        rows ``rows`` of the whole (None: all), Hessian spans ``hs``, sums v, g, h; ``poses``: the traversal's
        arrays R, dR, d2R, t); returns its warm-start table (keys, planes) with warm starts, else None."""
        from ._traverse_numba import accumulate_leaves_lowrank, leaf_inputs, warm_table
        from .pair import _solve

        LI, LJ, lp, lwid, wv, wd1, wd2, n, _ = out
        if n == 0:
            return None
        LI, LJ, lp, lwid = LI[:n], LJ[:n], lp[:n], lwid[:n]
        z = torch.zeros(0, dtype=v.dtype)
        warm = self.warm
        if warm is None:
            ids, wkeys, wplanes = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4))
        else:
            ids = (warm[0] if rows is None else warm[0][rows]).contiguous().numpy()
            wkeys, wplanes = warm[1].contiguous().numpy(), warm[2].contiguous().numpy()
        pbn = pb.numpy()
        Rn, dRn, d2Rn, tn = poses
        Xa, Xb, X, keys, P0, has0 = leaf_inputs(
            self.forest.tris.numpy(), self.forest.tri.numpy(), LI, LJ, lp, pbn, Rn, tn, ids, wkeys,
            wplanes, self.forest.centre.shape[0],
        )  # fmt: skip
        order = self.order
        # (X from the library's own meshes: no input checks)
        sol = _solve(
            torch.from_numpy(X), mu=float(self.mu), margin=float(self.margin), tol=float(self.tol),
            max_iter=int(self.max_iter), want_grad=order >= 1, want_hess=order >= 2, backend="numba", lowrank=True,
            start=(torch.from_numpy(P0), torch.from_numpy(has0)) if warm is not None and wkeys.shape[0] else None,
            serial=serial,
        )  # fmt: skip
        pv, Pl = sol.value.numpy(), sol.plane.contiguous().numpy()
        table = warm_table(keys, pv, Pl, sol.centre.numpy()) if warm is not None else None
        WT, gaps = sol.hess if sol.hess is not None else (z.reshape(0, 4, 18), z.reshape(0, 6))
        gx = sol.grad if sol.grad is not None else z.reshape(0, 18)
        accumulate_leaves_lowrank(
            lp, lwid, wv, wd1, wd2, pv, gx.numpy(), WT.numpy(), gaps.numpy(), Pl, Xa, Xb, pbn[lp, 0], pbn[lp, 1],
            dRn, d2Rn, float(self.mu), int(order), v.numpy(), g.numpy(), h.numpy(), hs.contiguous().numpy(),
        )  # fmt: skip
        return table


def _merge_warm(tables: list) -> tuple[torch.Tensor, torch.Tensor]:
    """The parts' warm-start tables (sorted keys, planes; None for a part without leaf pairs) as one, sorted by key
    (the parts' keys are disjoint: their body pairs are)."""
    from ._traverse_numba import warm_merge

    tables = [x for x in tables if x is not None]
    if not tables:
        return torch.zeros(0, dtype=torch.int64), torch.zeros(0, 4, dtype=torch.float64)
    keys, planes = tables[0]
    for k, p in tables[1:]:
        keys, planes = warm_merge(k, p, keys, planes)
    return torch.from_numpy(keys), torch.from_numpy(planes)


def _traverse_cpu(
    forest,
    pair_body,
    pair_root,
    R,
    dR,
    d2R,
    t,
    mu,
    eps,
    min_width,
    split,
    order,
    value,
    grad,
    hess,
    hside,
    hint,
    leaf_stage=None,
):
    """Node traversal by the numba kernel (accumulates central terms in place); returns the leaf pairs (their
    weights' Hessians are not kept: ``ld2w`` is None), the node pairs and -1 (levels: not counted).
    ``hint``: the leaf pairs of earlier evaluations of the same step, or None (see :func:`_node_threads`).
    ``leaf_stage``: a :class:`_LeafStage`: each part's leaf pairs are then solved and added to value, grad and
    hess in the thread that traversed it, and the result is (leaf pairs, node pairs, warm-start table (keys,
    planes) of the solved leaf pairs).

    Several body pairs are traversed by up to four threads, each taking every n-th pair (the kernel is serial
    within a body pair); the results are the same as one thread's, their leaves in another order."""
    from ._traverse_numba import LEAF_CAP, STACK_CAP, TABLE_CAP, traverse_nodes

    Nb = R.shape[0]
    dt = R.dtype
    dRn = (dR if dR is not None else torch.zeros(Nb, 3, 3, 3, dtype=dt)).contiguous().numpy()
    d2Rn = (d2R if d2R is not None else torch.zeros(Nb, 3, 3, 3, 3, dtype=dt)).contiguous().numpy()
    common = (
        R.contiguous().numpy(),
        dRn,
        d2Rn,
        t.contiguous().numpy(),
        float(mu),
    )
    P = pair_body.shape[0]

    def run(rows: torch.Tensor | None):
        pb, pr = (pair_body, pair_root) if rows is None else (pair_body[rows], pair_root[rows])
        ep = eps if rows is None else eps[rows]
        hs = hside if rows is None else hside[rows]
        n = pb.shape[0]
        v = value if rows is None else torch.zeros(n, dtype=dt)
        # the kernel only writes grad / hess at order >= 1 / 2; below that it gets empty placeholders
        g = grad if rows is None and grad is not None else torch.zeros(n if order >= 1 else 0, 12, dtype=dt)
        h = (
            hess
            if rows is None and hess is not None
            else torch.zeros(n if order >= 2 else 0, 12, 12, dtype=dt)
        )
        out = traverse_nodes(
            forest.centre.numpy(), forest.radius.numpy(), forest.child.numpy(), pb.numpy(),
            pr.contiguous().numpy(), *common, ep.contiguous().numpy(), float(min_width), split == "both",
            int(order), v.numpy(), g.numpy(), h.numpy(), hs.contiguous().numpy(), STACK_CAP, table_cap, LEAF_CAP,
        )  # fmt: skip
        table = (
            leaf_stage.run(out, pb, rows, hs, v, g, h, common[:4], k > 1) if leaf_stage is not None else None
        )
        return out, v, g, h, table

    k = _node_threads(P, hint)
    # the weight tables' first capacity: about a part's leaf pairs in the step's earlier evaluations (a rack of balls
    # on a table: 8,192 entries a thread, which doubling from TABLE_CAP wrote and copied several times over)
    table_cap = TABLE_CAP if not hint else max(TABLE_CAP, 1 << max(0, (hint // k).bit_length()))
    if k == 1:
        parts = [(None, run(None))]
    else:
        chunks = [torch.arange(i, P, k) for i in range(k)]
        parts = list(zip(chunks, _pool().map(run, chunks), strict=True))
    if leaf_stage is not None:
        n_leaf = n_pairs = 0
        for rows, ((*_, n_l, n_p), v, g, h, _t) in parts:
            if rows is not None:
                value[rows] = v
                if grad is not None:
                    grad[rows] = g
                if hess is not None:
                    hess[rows] = h
            n_leaf, n_pairs = n_leaf + int(n_l), n_pairs + int(n_p)
        return n_leaf, n_pairs, _merge_warm([x[1][4] for x in parts])
    cols: list[list[torch.Tensor]] = [[] for _ in range(6)]  # LI, LJ, lp, lwid, wv, wd1
    n_pairs = 0
    offset = 0  # each part's first entry in the concatenated weight table (wv, wd1)
    for rows, ((LI, LJ, lp, lwid, wv, wd1, _, n, n_p), *_) in parts:  # (leaves only: the sums are not read)
        lp_t = torch.from_numpy(lp[:n])
        for c, x in zip(
            cols,
            (torch.from_numpy(LI[:n]), torch.from_numpy(LJ[:n]), lp_t if rows is None else rows[lp_t],
             torch.from_numpy(lwid[:n]) + offset, torch.from_numpy(wv), torch.from_numpy(wd1)),
            strict=True,
        ):  # fmt: skip
            c.append(x)
        offset += wv.shape[0]
        n_pairs += int(n_p)
    LI, LJ, lp, wid, wv, wd1 = (_cat(c) for c in cols)
    leaves = []
    if wid.numel():
        leaves.append((LI, LJ, lp, wv[wid], wd1[wid] if order >= 1 else None, None))
    return leaves, n_pairs, -1


def _pair_eps(eps: float | torch.Tensor, P: int, device: torch.device) -> torch.Tensor:
    """(P,) float64 blend widths, one per body pair, from one for all (a number) or one each (a (P,) tensor)."""
    e = torch.as_tensor(eps, dtype=torch.float64, device=device)
    if e.dim() == 0:
        return e.expand(P).contiguous()
    if e.shape != (P,):
        raise ValueError(f"eps must be a number or one per body pair ({P},), got shape {tuple(e.shape)}")
    return e.contiguous()


def traverse(
    forest: Forest,
    pair_body: torch.Tensor,
    pair_root: torch.Tensor,
    pose: torch.Tensor,
    *,
    mu: float,
    margin: float,
    eps: float | torch.Tensor,
    split: str,
    order: int,
    tol: float,
    max_iter: int,
    backend: str = "auto",
    leaves_only: bool = False,
    warm: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    hessian_of: torch.Tensor | None = None,
):
    """BSH potential of P body pairs at once.

    Args:
        forest: concatenated hierarchies.
        pair_body: (P, 2) indices into ``pose`` of each pair's bodies a and b.
        pair_root: (P, 2) root node ids of each pair's hierarchies.
        pose: (Nb, 6) body poses (float64).
        eps: the blend width, one for all pairs or (P,) one per pair.
        order: 0 value, 1 value + gradient, 2 value + gradient + Hessian.
        backend: "auto" (numba depth-first kernel on CPU, breadth-first tensors elsewhere) or "torch".
        leaves_only: only traverse the nodes and return the exact leaf pairs instead (with the gradient of their
            inherited weight when order >= 1).
        warm: warm-start the leaf pairs' plane solves (numba kernels only): (ids (P,) a stable identifier of each
            body pair across calls, keys (W,) sorted, planes (W, 4)) from an earlier call; a leaf pair is keyed by
            (id, leaf I, leaf J). The optimum does not depend on the start, to the plane solve's tolerance.
        hessian_of: (P, 2) bool, whose Hessian blocks each body pair needs (order 2): where exactly one body is
            True, the numba kernels form only its 6 x 6 block and leave hess[p]'s other rows and columns zero (the
            tensor path forms every block). None: all.

    Returns:
        value (P,), grad (P, 12) | None, hess (P, 12, 12) | None, stats dict (with ``warm``, also this call's
        (keys, planes) of its feasible leaf pairs, for the next); with ``leaves_only`` the leaf
        pairs (LI (L,), LJ (L,) node ids, lp (L,) body-pair index, lw (L,) inherited blend weight, dlw (L, 12) | None
        its gradient over the pair's [q_a, q_b]).
    """
    dt, dev = pose.dtype, pose.device
    P = pair_body.shape[0]
    R, dR, d2R = rotation_derivatives(pose[:, 3:], order)
    # Each body pair is evaluated in the frame of its body a's translation: (a, b) at (0, t_b - t_a), exact for
    # nearby bodies far from the origin, so neither the node pairs' distances and blend weights nor the leaf pairs
    # lose digits to the position of the pair (the derivatives in the translations are the same in every frame).
    side = pair_body.reshape(-1)
    R = R[side]
    dR = dR[side] if dR is not None else None
    d2R = d2R[side] if d2R is not None else None
    t = pose[pair_body, :3]  # (P, 2, 3)
    t = torch.stack([torch.zeros_like(t[:, 0]), t[:, 1] - t[:, 0]], 1).reshape(-1, 3)
    pair_body = torch.arange(2 * P, device=dev).reshape(P, 2)
    value = torch.zeros(P, dtype=dt, device=dev)
    grad = torch.zeros(P, 12, dtype=dt, device=dev) if order >= 1 else None
    hess = torch.zeros(P, 12, 12, dtype=dt, device=dev) if order >= 2 else None
    min_width = BAND_MARGINS * float(margin)
    eps = _pair_eps(eps, P, dev)
    hside = torch.zeros(
        P, dtype=torch.int64
    )  # hessian_span's code: 0 both bodies, 1 body a only, 2 body b only
    if hessian_of is not None and order >= 2 and P:
        if hessian_of.shape != (P, 2) or hessian_of.dtype != torch.bool:
            raise ValueError(f"hessian_of must be ({P}, 2) bool")
        h = hessian_of.cpu()
        hside = torch.where(h[:, 0] & ~h[:, 1], 1, torch.where(h[:, 1] & ~h[:, 0], 2, 0))

    if dev.type == "cpu" and backend != "torch":
        known = warm[1].numel() if warm is not None and warm[1].numel() else None  # the step's leaf pairs
        if not leaves_only:  # the leaf pairs solved and summed in the traversal's threads
            stage = _LeafStage(forest, mu, margin, tol, max_iter, order, warm)
            n_leaf, n_pairs, warm_out = _traverse_cpu(
                forest, pair_body, pair_root, R, dR, d2R, t, mu, eps, min_width, split, order, value, grad, hess,
                hside, hint=known, leaf_stage=stage,
            )  # fmt: skip
            return _finish(value, grad, hess, n_pairs, n_leaf, -1, warm_out if warm is not None else None)
        leaves, n_pairs, levels = _traverse_cpu(
            forest, pair_body, pair_root, R, dR, d2R, t, mu, eps, min_width, split, order, value, grad, hess, hside,
            hint=known,
        )  # fmt: skip
        I = pair_root[:0, 0]  # skip the tensor traversal below
    else:
        leaves, n_pairs, levels = [], 0, 0
        eye = torch.eye(3, dtype=dt, device=dev)
        # frontier
        I, J, pid = pair_root[:, 0], pair_root[:, 1], torch.arange(P, device=dev)
        W = torch.ones(P, dtype=dt, device=dev)
        dW = torch.zeros(P, 12, dtype=dt, device=dev) if order >= 1 else None
        d2W = torch.zeros(P, 12, 12, dtype=dt, device=dev) if order >= 2 else None
    while I.numel():
        levels += 1
        n_pairs += I.numel()
        ba, bb = pair_body[pid, 0], pair_body[pid, 1]
        CI, CJ = forest.centre[I], forest.centre[J]
        d = torch.einsum("eij,ej->ei", R[ba], CI) + t[ba] - torch.einsum("eij,ej->ei", R[bb], CJ) - t[bb]
        r = torch.linalg.vector_norm(d, dim=-1)
        # r = 0 (coincident centres) lies on the near side (phi = 0, every term below zero): any finite u there
        r_safe = torch.where(r > 0, r, torch.ones_like(r))
        d1 = forest.radius[I] + forest.radius[J]
        width = torch.clamp(eps[pid] * d1, min=min_width)
        s = (r - d1) / width
        dr = d2r = None
        if order >= 1:
            u = d / r_safe[:, None]
            dd = torch.cat(
                [
                    eye.expand(len(I), 3, 3),
                    point_jacobian(dR[ba], CI),
                    -eye.expand(len(I), 3, 3),
                    -point_jacobian(dR[bb], CJ),
                ],
                -1,
            )  # (E, 3, 12)  fmt: skip
            dr = torch.einsum("ei,eik->ek", u, dd)
            if order >= 2:
                d2r = (torch.einsum("eik,eil->ekl", dd, dd) - dr[:, :, None] * dr[:, None, :]) / r_safe[
                    :, None, None
                ]
                d2r[:, 3:6, 3:6] += rot_second(d2R[ba], CI, u)
                d2r[:, 9:12, 9:12] -= rot_second(d2R[bb], CJ, u)
        phi, phi1, phi2 = _smoothstep_derivs(s)
        phi1, phi2 = phi1 / width, phi2 / (width * width)
        # Every element is evaluated unmasked (cheaper than gathering subsets): the central term W phi P_c(r)
        # is zero where phi = 0 (near), the inherited weight W (1 - phi) is zero where phi = 1 (far).
        pc, pc1, pc2 = _central_derivs(torch.where(s > 0, r, d1), mu)  # (finite where phi = 0)
        g = phi * pc
        g1 = phi1 * pc + phi * pc1
        g2 = phi2 * pc + 2.0 * phi1 * pc1 + phi * pc2
        dg, d2g = _radial(g, g1, g2, dr, d2r)
        v, gv, hv = _product(W, dW, d2W, g, dg, d2g)
        _segment_add(value, pid, v, P)
        if gv is not None:
            _segment_add(grad, pid, gv, P)
        if hv is not None:
            _segment_add(hess, pid, hv, P)
        fine = s < 1  # 1 - phi > 0: descend (or solve the leaf pair)
        if not bool(fine.any()):
            break
        h = 1.0 - phi
        dh, d2h = _radial(h, -phi1, -phi2, dr, d2r)
        W, dW, d2W = _product(W, dW, d2W, h, dh, d2h)
        leaf_i, leaf_j = forest.child[I, 0] < 0, forest.child[J, 0] < 0
        both = leaf_i & leaf_j
        lm = fine & both
        if bool(lm.any()):
            leaves.append(
                (I[lm], J[lm], pid[lm], W[lm], dW[lm] if dW is not None else None,
                 d2W[lm] if d2W is not None else None)
            )  # fmt: skip
        go = fine & ~both
        If, Jf, pf, leaf_i, leaf_j = I[go], J[go], pid[go], leaf_i[go], leaf_j[go]
        Wf = W[go]
        dWf = dW[go] if dW is not None else None
        d2Wf = d2W[go] if d2W is not None else None
        # children: candidate (side-I option, side-J option) pairs with validity masks
        if split == "both":
            split_i, split_j = ~leaf_i, ~leaf_j
        else:
            ri, rj = forest.radius[If], forest.radius[Jf]  # (ties: both, as the numba traversal)
            split_i = ~leaf_i & (leaf_j | (ri >= rj))
            split_j = ~leaf_j & (leaf_i | (rj >= ri))
        ci = torch.stack([torch.where(split_i, forest.child[If, 0], If), forest.child[If, 1]], 1)  # (E, 2)
        cj = torch.stack([torch.where(split_j, forest.child[Jf, 0], Jf), forest.child[Jf, 1]], 1)
        vi = torch.stack([torch.ones_like(split_i), split_i], 1)
        vj = torch.stack([torch.ones_like(split_j), split_j], 1)
        cand_i = ci[:, :, None].expand(-1, 2, 2)
        cand_j = cj[:, None, :].expand(-1, 2, 2)
        valid = (vi[:, :, None] & vj[:, None, :]).reshape(-1)
        parent = torch.arange(If.numel(), device=dev)[:, None].expand(-1, 4).reshape(-1)[valid]
        I = cand_i.reshape(-1)[valid]
        J = cand_j.reshape(-1)[valid]
        pid = pf[parent]
        W = Wf[parent]
        dW = dWf[parent] if dWf is not None else None
        d2W = d2Wf[parent] if d2Wf is not None else None

    if leaves_only:
        if not leaves:
            e = pair_root.new_zeros(0)
            return e, e, e, value.new_zeros(0), (value.new_zeros(0, 12) if order >= 1 else None)
        cols = list(zip(*leaves, strict=True))
        return (*(_cat(x) for x in cols[:4]), _cat(cols[4]) if order >= 1 else None)
    n_leaf = 0
    pv = None
    warm_out = (pair_root.new_zeros(0), value.new_zeros(0, 4))  # (the tensor path keeps no warm starts)
    if leaves:
        LI, LJ, lp, lw, ldw, ld2w = (_cat(x) if x[0] is not None else None for x in zip(*leaves, strict=True))
        n_leaf = LI.numel()
        # the tensor path (the CPU kernels' leaf pairs are solved and summed in _traverse_cpu)
        ba, bb = pair_body[lp, 0], pair_body[lp, 1]
        Xa, Xb = forest.tris[forest.tri[LI]], forest.tris[forest.tri[LJ]]  # (L, 3, 3) body frame
        wa = Xa @ R[ba].transpose(1, 2) + t[ba][:, None, :]
        wb = Xb @ R[bb].transpose(1, 2) + t[bb][:, None, :]
        if order == 0:
            from .pair import pair_potential

            with torch.no_grad():
                pv = pair_potential(wa, wb, mu=mu, margin=margin, tol=tol, max_iter=max_iter, backend=backend)
            gq = hq = None
        else:
            der = pair_potential_derivatives(
                wa,
                wb,
                mu=mu,
                margin=margin,
                hessian=order >= 2,
                tol=tol,
                max_iter=max_iter,
                backend=backend,
            )
            pv = der.value
            # J (L, 18, 12): x_k = R X_k + t
            L_ = n_leaf
            Jx = torch.zeros(L_, 6, 3, 12, dtype=dt, device=dev)
            Jx[:, :3, :, 0:3] = eye
            Jx[:, 3:, :, 6:9] = eye
            Jx[:, :3, :, 3:6] = torch.einsum("eimk,evm->evik", dR[ba], Xa)
            Jx[:, 3:, :, 9:12] = torch.einsum("eimk,evm->evik", dR[bb], Xb)
            Jx = Jx.reshape(L_, 18, 12)
            gx = der.grad  # (L, 18)
            gq = torch.einsum("ei,eik->ek", gx, Jx)
            hq = None
            if order >= 2:
                hq = Jx.transpose(1, 2) @ der.hessian @ Jx
                g6 = gx.reshape(L_, 6, 3)
                hq[:, 3:6, 3:6] += torch.einsum("evi,eimkl,evm->ekl", g6[:, :3], d2R[ba], Xa)
                hq[:, 9:12, 9:12] += torch.einsum("evi,eimkl,evm->ekl", g6[:, 3:], d2R[bb], Xb)
    if leaves and pv is not None:
        v, gv, hv = _product(lw, ldw, ld2w, pv, gq, hq)
        _segment_add(value, lp, v, P)
        inf = torch.isinf(pv)
        if gv is not None:
            gv = torch.where(inf[:, None], torch.zeros((), dtype=dt, device=dev), gv)
            _segment_add(grad, lp, gv, P)
        if hv is not None:
            hv = torch.where(inf[:, None, None], torch.zeros((), dtype=dt, device=dev), hv)
            _segment_add(hess, lp, hv, P)
    return _finish(value, grad, hess, n_pairs, n_leaf, levels, warm_out if warm is not None else None)


def _finish(value, grad, hess, n_pairs: int, n_leaf: int, levels: int, warm_out):
    """``traverse``'s result: derivatives zero where a pair's value is +inf, the stats, and the warm-start table
    when one was asked for (``warm_out`` not None)."""
    infp = torch.isinf(value) if grad is not None else None
    if infp is not None and bool(infp.any()):
        zero = torch.zeros((), dtype=value.dtype, device=value.device)
        grad = torch.where(infp[:, None], zero, grad)
        if hess is not None:
            hess = torch.where(infp[:, None, None], zero, hess)
    stats = {"node_pairs": int(n_pairs), "leaf_pairs": int(n_leaf), "levels": int(levels)}
    if warm_out is not None:
        return value, grad, hess, stats, warm_out
    return value, grad, hess, stats


def penetrating(
    forest: Forest,
    pair_body: torch.Tensor,
    pair_root: torch.Tensor,
    pose: torch.Tensor,
    *,
    margin: float,
    eps: float | torch.Tensor,
    split: str,
    tol: float,
    max_iter: int,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """(P,) bool: the body pairs whose BSH potential is +inf at ``pose`` (some triangle pair within the margin; on
    CPU within the margin times 1 + 1e-9, erring toward infeasible: the query measures distances in the world frame,
    the plane solve about the pair's own origin, and at a gap of exactly one margin their roundings disagree).

    On CPU a collision query (``_traverse_numba.penetrating_pairs``: the node pairs the potential descends whose
    spheres are within the margin, no weights or plane solves); elsewhere the potential itself at order 0
    (``tol`` and ``max_iter`` are only used there). ``scale`` (Nb,): each body scaled about its origin first (CPU only).
    """
    if scale is not None and pose.device.type != "cpu":
        raise NotImplementedError("scaled collision queries run on CPU only")
    if pose.device.type == "cpu":
        sc = torch.ones(pose.shape[0], dtype=torch.float64) if scale is None else scale.to(torch.float64)
        from ._traverse_numba import STACK_CAP, penetrating_pairs

        R = rotation_derivatives(pose[:, 3:].to(torch.float64), 0)[0]
        out = torch.empty(pair_body.shape[0], dtype=torch.int8)
        penetrating_pairs(
            forest.centre.to(torch.float64).numpy(), forest.radius.to(torch.float64).numpy(),
            forest.child.numpy(), forest.tri.numpy(), forest.tris.to(torch.float64).numpy(), pair_body.numpy(),
            pair_root.contiguous().numpy(), R.contiguous().numpy(),
            pose[:, :3].to(torch.float64).contiguous().numpy(), sc.contiguous().numpy(),
            float(margin) * (1.0 + _QUERY_SLACK), _pair_eps(eps, pair_body.shape[0], torch.device("cpu")).numpy(),
            BAND_MARGINS * float(margin), split == "both", out.numpy(), STACK_CAP,
        )  # fmt: skip
        return out.bool()
    value = traverse(
        forest, pair_body, pair_root, pose, mu=1.0, margin=margin, eps=eps, split=split, order=0, tol=tol,
        max_iter=max_iter,
    )[0]  # fmt: skip
    return torch.isinf(value)
