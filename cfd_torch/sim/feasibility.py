"""Feasibility of a step: where its Newton solve may start, which moves it may take, and whether its end is
reachable. One contract for all three:

* A configuration is **feasible** when every interacting body pair's potential is finite (no pair within the
  margin); the contact model's collision query decides (it agrees exactly with the potential's +inf).
* A **move** of the iterate q0 -> q1 (the warm start, a Newton trial) is accepted only if q1 is feasible and so is
  the straight path in q at points whose largest vertex displacement is at most ``scene.path_spacing`` apart
  (``ccd_spacing``, or half the thinnest moving body's thickness plus the margin where less; features
  thinner than about that plus the margin can still be jumped over in one move).
* The step's **solution must be reachable** from the start-of-step poses without passing through another body:
  each moving body, shrunk by ``reach_shrink`` about its centre of mass (an interpolated path is not the body's
  motion, and dipping a few millimetres into a support it rests or lands on is not tunnelling), must be clear of
  the bodies it interacts with at points ``path_spacing`` apart along the straight path in q (kinematic bodies
  from their start-of-step poses to their targets), or along a turn about its least-moving vertex (a body
  tipping over an edge); if neither is clear (a large tumbling step, or two moving bodies whose interpolations
  overlap after a legitimate collision), it is refused only if, for a pair that neither interpolation keeps
  clear, a centre of mass lying in its own solid passes through the other body (:func:`_crossing`). With a huge
  dt the minimiser can lie beyond an obstacle, or beyond another moving body, reached by iterates that went
  around it.
* A **kinematic body's motion** over the step (from its start-of-step pose to its target, the moving bodies at
  their start-of-step poses) is checked the same way: one that would pass through a moving body makes the start
  carry the bodies along or push them out of its way (:func:`cfd_torch.sim.solve.start`).
* A body wholly **inside another** (their surfaces clear: the potential is finite, and no force would push it out)
  is refused at the start of a step (:func:`contained`; kinematic targets too, where their motion crossed no
  surface).
* The Newton solve **starts** at a feasible configuration (:func:`cfd_torch.sim.solve.start` says how it is
  found); a start state that itself penetrates is a ``ValueError``.
"""

from __future__ import annotations

import numpy as np
import torch

from .._geometry import _AMBIGUOUS, ray_crossings_nb, segment_hits_triangle
from ..rotation import quaternion, quaternion_multiply, rotation_matrix, rotation_vector
from .energy import StepProblem
from .types import StepError

__all__ = [
    "infeasible_pairs",
    "infeasible_reason",
    "feasible",
    "penetrating",
    "displacement",
    "path_clear",
    "sweep_clear",
    "start_and_sweep",
    "reachable",
]


def infeasible_pairs(scene, poses: torch.Tensor, sel: torch.Tensor | None = None, shrink: float = 0.0):
    """(S, P') bool: the interacting pairs (or those selected by the (P,) mask ``sel``) whose potential is +inf in
    each of the S pose sets ``poses`` (S, N, 6), the moving bodies scaled by 1 - ``shrink``."""
    S = poses.shape[0]
    base = scene.pairs if sel is None else scene.pairs[sel]
    P = base.shape[0]
    if P == 0:
        return torch.zeros(S, 0, dtype=torch.bool, device=poses.device)
    s = torch.arange(S).repeat_interleave(P)
    pairs = torch.cat([s[:, None], base.repeat(S, 1)], 1)
    scale = None
    if shrink:
        scale = torch.ones(scene.num_bodies, dtype=torch.float64)
        scale[scene.kinematics.bodies] = 1.0 - shrink
    return scene.contact_model.infeasible(poses, pairs.to(poses.device), scale).reshape(S, P)


def feasible(scene, poses: torch.Tensor) -> torch.Tensor:
    """(S,) bool: whether each pose set (S, N, 6) is feasible."""
    return ~infeasible_pairs(scene, poses).any(1)


def infeasible_reason(scene) -> str:
    """Where the scene's contact potential is +inf, for messages, from its model's ``margin``: "within the contact
    margin 0.001" (this library's potential, SDRS; IPC's minimum separation), "touching or intersecting" (a margin of
    0), or, for a model without one, where that model's potential is +inf."""
    margin = getattr(scene.contact_model, "margin", None)
    if margin is None:
        return "where the contact model's potential is +inf"
    return f"within the contact margin {margin:g}" if margin > 0 else "touching or intersecting"


def penetrating(scene, poses: torch.Tensor) -> str:
    """The (first five) body pairs, formatted, whose potential is +inf at the poses (N, 6); empty if none."""
    bad = infeasible_pairs(scene, poses[None])[0]
    return ", ".join(
        f"({int(i)}, {int(j)})" for i, j in scene.pairs[torch.nonzero(bad)[:5, 0].cpu()].tolist()
    )


# directions a ray is cast along when the first (away from the container's centre) grazes an edge or a vertex
_RAY_DIRECTIONS = np.array([[0.5773, 0.5774, 0.5773], [-0.2673, 0.5345, 0.8018], [0.8944, -0.4472, 0.0001]])
_RAY_DIRECTIONS /= np.linalg.norm(_RAY_DIRECTIONS, axis=1, keepdims=True)


def contained(
    scene, poses: torch.Tensor, sel: torch.Tensor | None = None, pairs: torch.Tensor | None = None
) -> list[tuple[int, int, int]]:
    """(s, i, j) for each pose set s of ``poses`` (S, N, 6) and interacting pair (of those the (P,) mask ``sel``
    selects, default all; or the body pairs ``pairs`` (P, 2), interacting or not) whose body i lies inside body j's
    solid, with i's surface clear of j's: the potential is
    finite there, and nothing else would notice. Body j must be a closed, consistently wound surface
    (``scene.closed``); its solid is where its winding number is positive (inside an outward-facing shell; inside an
    inward-facing one, a room or a cavity, is free space). The winding number is counted along a ray from one vertex
    of i through j's surface (its hierarchy prunes the triangles), only where that vertex is within j's extent of
    j's frame origin. Pairs whose surfaces cross are not reported (they penetrate: :func:`penetrating`)."""
    if pairs is None:
        pairs = scene.pairs if sel is None else scene.pairs[sel.cpu()]
    if pairs.shape[0] == 0 or not bool(scene.closed.any()):
        return []
    inner = torch.cat([pairs[:, 0], pairs[:, 1]])
    outer = torch.cat([pairs[:, 1], pairs[:, 0]])
    keep = scene.closed[outer]
    inner, outer = inner[keep], outer[keep]
    q = poses.detach().to("cpu", torch.float64)
    # (N, 3) one vertex of a face of each body, in its frame
    probe = torch.stack([b.bsh.vertices[b.bsh.faces[0, 0]] for b in scene.bodies]).to(torch.float64)
    R = rotation_matrix(q[..., 3:])  # (S, N, 3, 3)
    x = torch.einsum("snij,nj->sni", R, probe) + q[..., :3]  # (S, N, 3) each body's probe in the world
    xo = x[:, inner] - q[:, outer, :3]  # (S, C, 3)
    local = torch.einsum("scji,scj->sci", R[:, outer], xo)  # in the outer body's frame
    near = local.norm(dim=-1) <= scene.extent[outer]
    if not bool(near.any()):
        return []
    ss, cc = torch.nonzero(near, as_tuple=True)
    forest = scene.probe_forest
    roots = scene.probe_root[outer[cc]].numpy()
    origins = local[ss, cc].contiguous().numpy()
    dirs = origins - forest.centre[roots].numpy()  # away from the outer body's root centre: a short way out
    norm = np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = np.where(norm > 0, dirs / np.where(norm > 0, norm, 1.0), _RAY_DIRECTIONS[0])
    count = np.empty(len(roots), np.int64)
    args = [x.numpy() for x in (forest.centre, forest.radius, forest.child, forest.tri, forest.tris)]
    ray_crossings_nb(*args, roots, origins, dirs, count)
    for d in _RAY_DIRECTIONS:
        again = np.flatnonzero(count == _AMBIGUOUS)
        if len(again) == 0:
            break
        redo = np.empty(len(again), np.int64)
        ray_crossings_nb(*args, roots[again], origins[again], np.tile(d, (len(again), 1)), redo)
        count[again] = redo
    hit = np.flatnonzero((count != _AMBIGUOUS) & (count > 0))  # (still ambiguous: not reported)
    out = []
    for k in hit.tolist():  # (rare) pairs whose surfaces cross are penetration, reported as such elsewhere
        s, i, j = int(ss[k]), int(inner[cc[k]]), int(outer[cc[k]])
        row = torch.tensor([[0, min(i, j), max(i, j)]], device=poses.device)
        if not bool(scene.contact_model.infeasible(poses[s : s + 1].detach(), row).any()):
            out.append((s, i, j))
    return out


def displacement(prob: StepProblem, q0: torch.Tensor, q1: torch.Tensor, scenes: torch.Tensor) -> torch.Tensor:
    """(A,) largest vertex displacement [m] of the moves q0 -> q1 (A, Q) (bound |dt| + |dw| r_max per body)."""
    scene = prob.scene
    kin = scene.kinematics
    dyn = kin.bodies.to(q0.device)
    fixed = prob.fixed[scenes]
    A = q0.shape[0]
    ends = kin.poses(torch.cat([q0, q1]), torch.cat([fixed, fixed]))[:, dyn]  # both ends in one map
    d = ends[A:] - ends[:A]  # (A, Nd, 6)
    r = scene.extent.to(q0)[dyn]
    return (d[..., :3].norm(dim=-1) + d[..., 3:].norm(dim=-1) * r).amax(1)


# the most pieces one path of a path check is cut into: a move of 100 m per step at the default 1 mm margin, a
# few hundred MB of collision queries for a few bodies; a longer path is refused before its samples are made
MAX_PATH_SAMPLES = 100_000


def _pieces(dist: torch.Tensor, spacing: float) -> torch.Tensor:
    """(A,) int64: the pieces at most ``spacing`` long that the straight paths of lengths ``dist`` (A,) are cut into
    (at least 1); a StepError where a path needs more than MAX_PATH_SAMPLES (the count is checked as a float: past
    2^63 an int64 wraps, and a wrapped count would check the path at one point)."""
    n = torch.ceil(dist / spacing)
    over = ~(n <= MAX_PATH_SAMPLES)  # (NaN too)
    if bool(over.any()):
        k = int(torch.nonzero(over)[0, 0])
        raise StepError(
            f"a body would move {float(dist[k]):.3g} m in one step (its largest vertex displacement): the "
            f"no-tunnelling path check would take {float(n[k]):.3g} samples path_spacing = {spacing:.3g} m apart, "
            f"more than {MAX_PATH_SAMPLES:,}; lower dt or the bodies' velocities (state.q - state.q_prev), move "
            "kinematic targets (action.target) less per step, or raise ccd_spacing where it sets path_spacing "
            "(Scene.path_spacing)"
        )
    return n.long().clamp_min(1)


def _spaced(dist: torch.Tensor, spacing: float, x0: torch.Tensor, x1: torch.Tensor):
    """Points of the straight paths x0 -> x1 (A, ...) of lengths ``dist`` (A,) at most ``spacing`` apart, ends
    excluded: the points (S, ...) and the index of each one's path (S,)."""
    n = _pieces(dist, spacing)
    path = torch.repeat_interleave(torch.arange(len(n), device=x0.device), n - 1)
    first = torch.cumsum(n - 1, 0) - (n - 1)
    k = torch.arange(len(path), device=x0.device) - first[path] + 1
    frac = (k.to(x0.dtype) / n[path].to(x0.dtype)).reshape((-1,) + (1,) * (x0.dim() - 1))
    return x0[path] + frac * (x1[path] - x0[path]), path


def _samples(prob: StepProblem, q0, q1, scenes):
    """Points of the straight paths q0 -> q1 at most the scene's path_spacing apart, ends excluded: (S, Q)
    coordinates, the scene of each (S,) and the index of its path (S,)."""
    qs, path = _spaced(displacement(prob, q0, q1, scenes), prob.scene.path_spacing, q0, q1)
    return qs, scenes[path], path


def sweep_clear(scene, p0: torch.Tensor, p1: torch.Tensor, sel: torch.Tensor | None = None) -> torch.Tensor:
    """(S,) bool: whether the straight paths of every body's pose p0 -> p1 (S, N, 6) are feasible at points at most
    path_spacing apart (ends excluded; p0 feasible, p1 checked by the caller), for the pairs the (P,) mask ``sel``
    selects (default all). The kinematic bodies' own motion over a step is checked this way: the Newton moves hold
    them at their targets."""
    return _sweep(scene, p0, p1, sel, start=False)[1]


def start_and_sweep(
    scene, p0: torch.Tensor, p1: torch.Tensor, sel: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(S,) bool twice: whether each start p0 (S, N, 6) is infeasible for the selected pairs, and whether its path
    to p1 is clear (as :func:`sweep_clear`), in one collision query."""
    return _sweep(scene, p0, p1, sel, start=True)


def _sweep(scene, p0: torch.Tensor, p1: torch.Tensor, sel: torch.Tensor | None, start: bool):
    """(S,) bool or None, (S,) bool: the starts' infeasibility (with ``start``) and the paths' clearance."""
    d = p1 - p0
    r = scene.extent.to(p0)
    dist = (d[..., :3].norm(dim=-1) + d[..., 3:].norm(dim=-1) * r).amax(1)
    ps, path = _spaced(dist, scene.path_spacing, p0, p1)
    S = len(p0)
    clear = torch.ones(S, dtype=torch.bool, device=p0.device)
    query = torch.cat([p0, ps]) if start else ps
    if len(query) == 0:
        return None, clear
    bad = infeasible_pairs(scene, query, sel).any(1)
    start_bad, bad = (bad[:S], bad[S:]) if start else (None, bad)
    clear[path[bad]] = False
    return start_bad, clear


def path_clear(prob: StepProblem, q0: torch.Tensor, q1: torch.Tensor, scenes: torch.Tensor) -> torch.Tensor:
    """(A,) bool: whether the straight paths q0 -> q1 (q0 feasible; q1 checked by the caller) are feasible at
    points at most path_spacing apart, all samples of all scenes in one collision query."""
    qs, sc, path = _samples(prob, q0, q1, scenes)
    clear = torch.ones(len(q0), dtype=torch.bool, device=q0.device)
    if len(qs):
        bad = ~feasible(prob.scene, prob.scene.kinematics.poses(qs, prob.fixed[sc]))
        clear[path[bad]] = False
    return clear


def _pivot_path(prob: StepProblem, q0: torch.Tensor, q1: torch.Tensor):
    """The moving bodies' motion q0 -> q1 (Nd, 6) as a rotation about, and a straight motion of, each
    body's vertex that moves least (a body tipping over an edge turns about that edge); returns s -> (Nd, 6)."""
    scene = prob.scene
    R0, R1 = rotation_matrix(q0[:, 3:]), rotation_matrix(q1[:, 3:])
    pivots = []
    for i, k in enumerate(scene.kinematics.bodies.tolist()):
        X = scene.bodies[k].bsh.vertices.to(q0)
        d = (X @ (R1[i] - R0[i]).T + (q1[i, :3] - q0[i, :3])).norm(dim=1)
        pivots.append(X[int(d.argmin())])
    P = torch.stack(pivots)  # (Nd, 3) body frame
    x0 = torch.einsum("nij,nj->ni", R0, P) + q0[:, :3]
    x1 = torch.einsum("nij,nj->ni", R1, P) + q1[:, :3]
    Q0 = quaternion(q0[:, 3:])
    dQ = quaternion_multiply(quaternion(q1[:, 3:]), torch.cat([Q0[:, :1], -Q0[:, 1:]], 1))  # q1 q0^-1
    w = rotation_vector(dQ)  # the relative rotation, |w| <= pi

    def at(s: float) -> torch.Tensor:
        rv = rotation_vector(quaternion_multiply(quaternion(s * w), Q0))
        t = x0 + s * (x1 - x0) - torch.einsum("nij,nj->ni", rotation_matrix(rv), P)
        return torch.cat([t, rv], 1)

    return at


def _moving(scene) -> torch.Tensor:
    """(N,) bool: the bodies the step's kinematics map moves (dynamic bodies and simulated links)."""
    moving = torch.zeros(scene.num_bodies, dtype=torch.bool)
    moving[scene.kinematics.bodies] = True
    return moving


def _crossing(
    prob: StepProblem, sel: torch.Tensor, p0: torch.Tensor, p1: torch.Tensor
) -> tuple[int, int, float] | None:
    """The first pair (i, j) of the pairs ``sel`` (P,) in which body i's centre of mass passes through body j on
    the way from the poses p0 to p1 (N, 6), with how far it moves relative to j [m], or None. Against a static or
    kinematic body j: the segment between i's centres, in j's frame, crosses j's surface (exact segment-triangle
    tests; both ends are outside). Between two moving bodies: the straight relative motion of their centres
    passes a centre that lies in its own solid (``inner_radius`` > 0) within the other body's ``inner_radius`` (a
    ball inside that body whatever it turns: a body may spin through a large angle in such a step; a ring's or a
    bowl's centre of mass, outside its solid, may lie inside another body's ball). A moving body's frame sits at
    its centre of mass."""
    scene = prob.scene
    dev = p0.device
    moving = _moving(scene)
    pairs = scene.pairs[sel]
    both = moving[pairs[:, 0]] & moving[pairs[:, 1]]
    if bool(both.any()):
        i, j = pairs[both, 0], pairs[both, 1]
        r0 = p0[i.to(dev), :3] - p0[j.to(dev), :3]
        d = p1[i.to(dev), :3] - p1[j.to(dev), :3] - r0
        s = ((-r0 * d).sum(1) / (d * d).sum(1).clamp_min(1e-300)).clamp(0.0, 1.0)
        closest = (r0 + s[:, None] * d).norm(dim=1)
        ri, rj = scene.inner_radius.to(p0)[i.to(dev)], scene.inner_radius.to(p0)[j.to(dev)]
        i_in_j = (closest < rj) & (ri > 0)
        j_in_i = (closest < ri) & (rj > 0)
        hit = torch.nonzero(i_in_j | j_in_i)[:, 0]
        if len(hit):
            k = int(hit[0])
            moved = float(d[k].norm())
            return (int(i[k]), int(j[k]), moved) if bool(i_in_j[k]) else (int(j[k]), int(i[k]), moved)
    one = pairs[~both]
    inner = torch.where(moving[one[:, 0]], one[:, 0], one[:, 1])
    outer = torch.where(moving[one[:, 0]], one[:, 1], one[:, 0])
    ends = []
    for p in (p0, p1):  # the moving body's centre in the other body's frame at that end
        R = rotation_matrix(p[outer.to(dev), 3:])
        ends.append(torch.einsum("kji,kj->ki", R, p[inner.to(dev), :3] - p[outer.to(dev), :3]))
    c0, c1 = ends
    # only segments that come within the other body's extent of its frame origin can reach its surface
    d = c1 - c0
    s = ((-c0 * d).sum(1) / (d * d).sum(1).clamp_min(1e-300)).clamp(0.0, 1.0)
    near = ((c0 + s[:, None] * d).norm(dim=1) <= scene.extent.to(p0)[outer.to(dev)]).cpu()
    for j in torch.unique(outer[near]).tolist():
        k = torch.nonzero(near & (outer == j))[:, 0]
        tri = scene.bodies[j].bsh.triangles.to(p0)  # (T, 3, 3), j's frame
        K, T = len(k), tri.shape[0]
        hit = segment_hits_triangle(
            c0[k.to(dev), None].expand(K, T, 3),
            c1[k.to(dev), None].expand(K, T, 3),
            tri[None].expand(K, T, 3, 3),
        ).any(1)
        if bool(hit.any()):
            first = int(k[int(torch.nonzero(hit)[0, 0])])
            return int(inner[first]), j, float(d[first].norm())
    return None


def reachable(
    prob: StepProblem, q0: torch.Tensor, q1: torch.Tensor
) -> tuple[torch.Tensor, dict[int, tuple[int, int, float]]]:
    """(B,) bool: whether each scene's moving bodies get from q0 to q1 (B, Q) without passing through another body
    (see the module's contract), and for each scene refused a pair (i, j) whose body i's centre of mass passes
    through body j, with how far it moves relative to j [m] (:func:`_crossing`)."""
    scene = prob.scene
    B = q0.shape[0]
    a, b = scene.pairs[:, 0], scene.pairs[:, 1]
    moving = _moving(scene)
    sel = moving[a] | moving[b]
    ok = torch.ones(B, dtype=torch.bool, device=q0.device)
    blocked: dict[int, tuple[int, int, float]] = {}
    if not bool(sel.any()):
        return ok, blocked
    scenes = torch.arange(B, device=q0.device)
    n = _pieces(displacement(prob, q0, q1, scenes), scene.path_spacing)
    shrink = scene.solver.reach_shrink
    kin = scene.kinematics
    dyn = kin.bodies.to(q0.device)
    k_idx = scene.kinematic.to(q0.device)
    for i in torch.nonzero(n > 1)[:, 0].tolist():
        k = torch.arange(1, int(n[i]), device=q0.device, dtype=q0.dtype)[:, None] / float(n[i])
        fixed = prob.fixed[i].expand(len(k), -1, -1).clone()
        # kinematic bodies move from their start-of-step poses to their targets along the same path
        k_start, k_end = prob.q_t[i, k_idx], prob.fixed[i, k_idx]
        fixed[:, k_idx] = k_start + k[:, :, None] * (k_end - k_start)
        straight = q0[i] + k * (q1[i] - q0[i])  # (n - 1, Q)
        # (P',) the pairs sel infeasible somewhere on the path
        bad = infeasible_pairs(scene, kin.poses(straight, fixed), sel, shrink).any(0)
        if not bool(bad.any()):
            continue
        p0 = kin.poses(q0[i : i + 1], prob.fixed[i : i + 1])[0]
        p0[k_idx] = k_start
        p1 = kin.poses(q1[i : i + 1], prob.fixed[i : i + 1])[0]
        at = _pivot_path(prob, p0[dyn], p1[dyn])
        pivot = fixed.clone()
        pivot[:, dyn] = torch.stack([at(float(s)) for s in k[:, 0]])
        bad = bad & infeasible_pairs(scene, pivot, sel, shrink).any(0)
        if not bool(bad.any()):
            continue
        # (only the pairs that neither interpolation keeps clear)
        pick = sel.clone()
        pick[torch.nonzero(sel)[:, 0]] = bad.cpu()
        pair = _crossing(prob, pick, p0, p1)
        if pair is not None:
            ok[i] = False
            blocked[i] = pair
    return ok, blocked
