"""Newton's method on a batch of independent energies, masked per scene, that says why it stopped.

Direction: Newton where the Hessian is positive definite; else saddle-free Newton (the Hessian's eigenvalues
replaced by their magnitudes, floored), which moves along negative curvature (a rocking polyhedron, a tipping
stack) at its natural scale. In the iteration after a rejected full step, friction enters by its quadratic
majorizer (an iteratively reweighted least-squares step): the exact Hessian has no curvature along a slipping
contact's slip, so its steps cross the tip of the friction cone and get cut back iteration after iteration; the
majorizer in every iteration converges only linearly at the end. The returned Hessian is always the exact one.

Step: one iteration moves no vertex more than ``max_move``; then a backtracking (Armijo) line search in which a
trial is accepted only if its energy is finite, decreases enough (up to the energy's rounding scale) and the move
to it passes ``move_ok`` (no tunnelling). Converged when the undamped Newton step is at most ``tol`` in every
coordinate at a positive definite Hessian (never in a majorized iteration: its step is shorter than Newton's) and
the step is not barrier-limited (its decrement -g.p a sizeable part of the contact and joint-limit energy, with a
curvature no inertia holds: a body within about ``tol`` of the contact margin, or a joint of its limit, takes steps
of a fixed fraction of its gap, within ``tol`` with the balance still far; ``_BARRIER_DECREMENT``); that
last step is then taken too (unchecked when it moves no vertex more than ``final_move``, else through the line
search as one more iteration), so a force too weak to move a body by ``tol`` in one step still moves it: near the
solution Newton's step is the remaining correction, however small, and dropping it would stop every body whose
acceleration times dt^2 is below ``tol``.

Scenes that converged or failed stop costing: each evaluation covers only the scenes still iterating. Within a
scene, bodies stop costing too (with ``pair_bodies``): a body whose Newton step is within ``tol`` while every
body its Hessian couples it to (contact within the blend band; the far field's coupling is below 1e-6 of their own
curvature) is also within ``tol`` is frozen, and the evaluations that follow cover only the terms of the bodies
still iterating (their own terms and their pairs). Nothing freezes in a scene expected to converge in its next
iteration (largest step^3 <= tol x previous largest step^2, Newton's quadratic rate; in the first iteration, a
largest step within about 2,000 tol): there a freeze would only add
the whole evaluation that ends it. A scene converges only at an evaluation of all its bodies: when
the bodies still iterating converge, the scene is evaluated whole, and bodies whose step is then above ``tol``
iterate again; else that evaluation's step (at most ``tol`` per coordinate, the frozen bodies' included) is the
final step. Frozen bodies keep their coordinates, so the result satisfies the same test as without freezing.
With ``pair_bodies``, the line search also splits each scene into islands of coupled bodies, each backtracking on
its own (one body's tight contact does not shorten the steps of bodies far from it); the full step, tried first, is
taken by every island whenever the whole step passes the scene's own test, as an unsplit search would take it.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import NamedTuple

import torch

from .energy import EnergyEval

__all__ = ["Stop", "NewtonResult", "newton"]

_LINE_SEARCH_TRIES = 60
_ISLAND_TRIES = 20  # an island that finds no step within this many halvings hands its scene to a whole search
# a Newton step within tol is limited by a barrier's curvature, not converged, where its decrement -g.p exceeds
# _BARRIER_DECREMENT of the barriers' energy (contact, friction, joint limits: ``EnergyEval.barrier_value``),
# _BARRIER_DECREMENT_L of L's magnitude (``EnergyEval.scale``) and _BARRIER_CURVATURE times the least share the
# bodies' inertia could have of it: on E = c / gap (this library's pair potential near its margin) Newton's step is
# gap / 2 and its decrement E / 2 (IPC's log barrier and the joint limits': the gap and about a tenth of E), a
# curvature no inertia holds (a box started 1e-9 m above the margin: 3e-3, 1e-3 and 4e20). At a solution the
# decrement is the step's own p^T H p: in every test and benchmark scene under 1e-8 of the contact energy and 2e-9
# of L's magnitude; where a loose tol makes it larger, the inertia holds it (a cube's first step at tol 1e-4: 150
# times the least inertia share, its translation's against its rotation's curvature)
_BARRIER_DECREMENT, _BARRIER_DECREMENT_L, _BARRIER_CURVATURE = 1e-5, 1e-6, 1e6
# with friction's stiffness beside the barrier (a box started 1e-11 m above the margin, friction 0.5: the decrement
# 9e-6 of the barriers' energy at its third step) the steps within tol still grow (by 1.5x there): a step within tol
# no shorter than the one before, with a decrement above this fraction of the barriers' energy, is not converged
_BARRIER_GROWING = 1e-10


class Stop(enum.IntEnum):
    """Why a scene's Newton solve stopped."""

    CONVERGED = 0
    LINE_SEARCH_FAILED = 1  # no trial along the direction was finite, decreasing and reachable
    MAX_ITER = 2  # the iteration cap was reached
    INFEASIBLE_START = 3  # the energy at the start is +inf
    NONFINITE = 4  # the gradient or Hessian at an iterate is not finite (a term overflows float64)


class NewtonResult(NamedTuple):
    """Per scene (B of them).

    Attributes:
        q: (B, Q) the last iterate.
        at: the order-2 evaluation at q (exact Hessian, contact Hessian, forces, ...); of a scene that did not
            converge, it may cover only the bodies still iterating (a frozen body's rows lack its contacts).
        iters: (B,) Newton iterations.
        reason: (B,) codes of :class:`Stop`.
        alpha: (B,) the last line search's step.
        work: (evaluations, node pairs, leaf pairs) of the energy evaluations this solve made (``first`` excluded).
        stepped: (B,) bool, the scenes that took the converged step after ``at``'s evaluation (q is up to ``tol``
            per coordinate from ``at``'s point there).
        at_q: (B, Q) the point of ``at``'s evaluation (q where not ``stepped``).
    """

    q: torch.Tensor
    at: EnergyEval
    iters: torch.Tensor
    reason: torch.Tensor
    alpha: torch.Tensor
    work: tuple[int, int, int]
    stepped: torch.Tensor
    at_q: torch.Tensor


def _assign(cur: EnergyEval, idx: torch.Tensor, ev: EnergyEval) -> None:
    """Write the rows ``ev`` (order 2, scenes ``idx``) into the per-scene evaluation ``cur`` (in place)."""
    for mine, new in zip(cur, ev, strict=True):
        if isinstance(mine, torch.Tensor) and new is not None:
            mine[idx] = new


def _rows(ev: EnergyEval, sel: torch.Tensor) -> EnergyEval:
    """The rows ``sel`` (A,) bool of ``ev`` (``ev`` itself when they are all of it: read it only)."""
    if bool(sel.all()):
        return ev
    return EnergyEval(*(x[sel] if isinstance(x, torch.Tensor) else x for x in ev))


def _coupling(H: torch.Tensor, onehot: torch.Tensor, width: int | None = None) -> torch.Tensor:
    """(A, M, M) bool: the bodies the Hessians H (A, Q, Q) couple (their block's magnitude above 1e-6 of the
    smaller of their own curvatures); ``onehot`` (Q, M) maps coordinates to bodies; ``width``: each body's
    number of coordinates where they come in consecutive runs of that many (free bodies), summed by blocks then
    (two products with ``onehot`` cost O(Q^2 M): 1.7 ms at 80 cubes)."""
    A, Q = H.shape[:2]
    if width is not None:
        C = H.abs().reshape(A, Q // width, width, Q // width, width).sum((2, 4))
    else:
        C = onehot.T @ H.abs() @ onehot
    d = torch.diagonal(C, dim1=1, dim2=2)
    return C > 1e-6 * torch.minimum(d[:, :, None], d[:, None, :])


def _islands(
    coupled: torch.Tensor, act: torch.Tensor, split: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The islands of the bodies ``act`` (A, M) of A scenes under the coupling ``coupled`` (A, M, M), taken
    transitively (all one island in the scenes not ``split`` (A,)): (G,) each island's scene and (G, M) its
    bodies."""
    A, M = act.shape
    R = (coupled | ~split[:, None, None]) & act[:, :, None] & act[:, None, :]
    R = R | torch.diag_embed(act)
    for _ in range(max(1, (M - 1).bit_length())):  # transitive closure by squaring, up to its fixed point
        Rd = R.double()
        closed = (Rd @ Rd) > 0
        if torch.equal(closed, R):
            break
        R = closed
    first = torch.where(R, torch.arange(M, device=R.device), M).amin(2)  # (A, M) smallest body of each island
    lead = act & (first == torch.arange(M, device=R.device))  # (A, M): the bodies that name an island
    gs, gb = torch.nonzero(lead, as_tuple=True)
    return gs, R[gs, gb]


def _call(energy, q, scenes, order, active):
    """energy(q, scenes, order[, active]): the active set is passed only when some body is frozen."""
    return energy(q, scenes, order) if active is None else energy(q, scenes, order, active)


class _Incidence(NamedTuple):
    """The interacting pairs at each moving body, sorted by body: body m's are ``pair[offset[m]:offset[m + 1]]``,
    each with its other body ``partner`` (M for one that does not move)."""

    offset: torch.Tensor  # (M + 1,)
    pair: torch.Tensor  # (E,)
    partner: torch.Tensor  # (E,)


def _incidence(pair_moving: torch.Tensor, M: int) -> _Incidence:
    """The incidence of the pairs ``pair_moving`` (P, 2) (moving-body indices, M for a body that does not move)."""
    ends = pair_moving.reshape(-1)  # (2P,): end e of pair p at 2p + e
    order = torch.argsort(ends, stable=True)
    order = order[ends[order] < M]
    count = torch.bincount(ends[order], minlength=M)
    offset = torch.cat([count.new_zeros(1), count.cumsum(0)])
    return _Incidence(offset, order // 2, pair_moving.reshape(-1)[order ^ 1])


def _restricted(
    ev: EnergyEval,
    rows: torch.Tensor,
    act: torch.Tensor,
    pairs: torch.Tensor | _Incidence,
    others: torch.Tensor | None = None,
):
    """The value and rounding scale of the terms of ``ev``'s scenes ``rows`` (A,) (evaluated over a superset of
    bodies) that involve the bodies ``act`` (A, M): their own terms and their pairs', except pairs with a body of
    ``others`` (A, M) (an island's energy leaves out its far-field pairs with the other islands, which they move);
    third, with ``others``, the value with those pairs included (else None). Only the per-body and per-pair values
    are read (not the rows of the whole evaluation).

    ``pairs``: each pair's bodies (P, 2) as moving-body indices (M for a body that does not move), summed through
    (A, P) masks; or their :class:`_Incidence`, summed by index over the pairs at the bodies of ``act`` only (the
    A islands of a scene whose every body is its own island read each pair twice, not A times: O(M P) per scene
    instead of O(M^2 P)). The two differ by rounding."""
    A, M = act.shape
    own_terms = torch.where(act, ev.body_value[rows], 0.0)
    own = own_terms.sum(1)
    ext = torch.cat([act, act.new_zeros(A, 1)], 1)  # column M: a body that does not move
    oth = None if others is None else torch.cat([others, others.new_zeros(A, 1)], 1)
    every = None
    if isinstance(pairs, torch.Tensor):
        on = ext[:, pairs[:, 0]] | ext[:, pairs[:, 1]]  # (A, P)
        pair_value = ev.pair_value[rows]
        if oth is not None:
            every = own + torch.where(on, pair_value, 0.0).sum(1)
            on = on & ~(oth[:, pairs[:, 0]] | oth[:, pairs[:, 1]])
        pv = torch.where(on, pair_value, 0.0)
        value = own + pv.sum(1)
        return value, value.abs() + own_terms.abs().sum(1) + 2.0 * pv.abs().sum(1), every
    # (row, pair) entries: the pairs at each row's bodies, a pair of two of them once (at its first body)
    gi, mi = torch.nonzero(act, as_tuple=True)
    start, count = pairs.offset[mi], pairs.offset[mi + 1] - pairs.offset[mi]
    first = torch.repeat_interleave(count.cumsum(0) - count, count)
    pos = torch.arange(first.numel(), device=act.device) - first + torch.repeat_interleave(start, count)
    e_row, e_body = torch.repeat_interleave(gi, count), torch.repeat_interleave(mi, count)
    e_pair, e_partner = pairs.pair[pos], pairs.partner[pos]
    once = ~ext[e_row, e_partner] | (e_body < e_partner)
    e_row, e_pair, e_partner = e_row[once], e_pair[once], e_partner[once]
    pv = ev.pair_value[rows[e_row], e_pair]

    def total(x: torch.Tensor) -> torch.Tensor:
        return own.new_zeros(A).index_add(0, e_row, x)

    if oth is not None:
        every = own + total(pv)
        pv = torch.where(oth[e_row, e_partner], 0.0, pv)
    value = own + total(pv)
    return value, value.abs() + own_terms.abs().sum(1) + 2.0 * total(pv.abs()), every


# a scene of M moving bodies and P interacting pairs sums its islands' energies by index above M P of this (through
# (islands, P) masks below it, fewer tensor operations): the choice depends on the scene alone, not on its batch. On
# the CPU only: index_add on a GPU adds in no fixed order, and a step would not repeat bit for bit
_DENSE_ISLANDS = 50_000


def newton(
    energy: Callable[[torch.Tensor, torch.Tensor, int], EnergyEval],
    q: torch.Tensor,
    first: EnergyEval,
    *,
    tol: float,
    max_iter: int,
    max_move: float,
    free_move: float,
    move_ok: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    displacement: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    majorize: torch.Tensor | None = None,
    block: torch.Tensor | None = None,
    pair_bodies: torch.Tensor | None = None,
    final_move: float = 0.0,
) -> NewtonResult:
    """Minimise B independent energies from feasible starts.

    Args:
        energy: (q (A, Q), scenes (A,) indices, order[, active]) -> EnergyEval of those scenes; ``active``
            (A, M) bool, passed only while some body is frozen: the moving bodies whose terms to evaluate.
        q: (B, Q) starts; ``first`` their order-2 evaluation (all B scenes).
        tol: convergence threshold on the Newton step [coordinate units].
        max_iter: iteration cap.
        max_move: largest vertex displacement of one iteration [m].
        free_move: moves whose vertex displacement is at most this need no ``move_ok`` check [m].
        move_ok: (q0, q1, scenes) -> (A,) bool: whether the move q0 -> q1 of those scenes is free of tunnelling.
        displacement: (q0, q1, scenes) -> (A,) largest vertex displacement of the move [m].
        majorize: (B,) bool, the scenes whose iteration after a rejected full step uses the energy's majorizer
            (``EnergyEval.majorizer_gap``); default: all, if the energy has one.
        block: (Q,) the moving body (0..M-1) each coordinate belongs to; with ``pair_bodies`` (P, 2), each
            interacting pair's two bodies (moving-body index, -1 for a body that does not move), converged bodies
            are frozen (module docstring). None: every body iterates until the scene converges.
        final_move: the converged step (at most ``tol`` per coordinate) is taken unchecked when it moves no vertex
            more than this [m] (keep it far below the contact margin), and through the line search when it moves
            some vertex further; 0 never takes it.

    Returns ``at``, the evaluation before that final step: its derivatives differ from those at ``q`` by the
    step's O(tol) change.
    """
    B = q.shape[0]
    dev = q.device
    q = q.clone()
    cur = EnergyEval(*(x.clone() if isinstance(x, torch.Tensor) else x for x in first))
    evals = nodes = leaves = 0  # (``first`` is the caller's)
    if first.majorizer_gap is None:
        majorize = torch.zeros(B, dtype=torch.bool, device=dev)
    elif majorize is None:
        majorize = torch.ones(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    # each scene's previous largest step; before the first, a notional 1e5 tol: a first step within about 2,000 tol
    # (a scene at rest, a warm start nearly right: Sort's cubes resting on their floor take steps of 2e-7 m) is
    # expected to converge in the next iteration
    last_step = torch.full((B,), 1e5 * tol, dtype=q.dtype, device=dev)
    reason = torch.full((B,), int(Stop.MAX_ITER), dtype=torch.long, device=dev)
    alpha_last = torch.ones(B, dtype=q.dtype, device=dev)
    stepped = torch.zeros(B, dtype=torch.bool, device=dev)
    at_q = q.clone()  # where a stepped scene's ``cur`` was evaluated (the others': q)
    majorized = torch.zeros(B, dtype=torch.bool, device=dev)  # this iteration follows a rejected full step
    active = torch.isfinite(cur.value)
    reason[~active] = int(Stop.INFEASIBLE_START)
    M = int(block.max()) + 1 if block is not None and block.numel() else 0
    # (one moving body: nothing to freeze or split, and the bookkeeping would only cost)
    freeze = M > 1 and pair_bodies is not None and first.body_value is not None
    act = torch.ones(B, M, dtype=torch.bool, device=dev)  # the bodies iterating
    whole = torch.ones(B, dtype=torch.bool, device=dev)  # cur evaluated every body of the scene
    # a scene whose whole evaluation did not confirm its frozen bodies' convergence iterates whole from then on
    # (freezing again could cycle: the bodies' coupled steps are within tol one by one, not together)
    may_freeze = torch.ones(B, dtype=torch.bool, device=dev)
    # scenes whose islands' separate steps ended infeasible together search whole from then on
    split = torch.ones(B, dtype=torch.bool, device=dev)
    if freeze:
        onehot = (block[:, None] == torch.arange(M, device=dev)).to(q.dtype)  # (Q, M)
        per_body = block.numel() // M  # the coordinates per body, where every body has that many in a row
        width = per_body if torch.equal(block, torch.arange(block.numel(), device=dev) // per_body) else None
        pairs = torch.where(pair_bodies >= 0, pair_bodies, M)  # (P, 2), M: a body that does not move
        if M * pairs.shape[0] > _DENSE_ISLANDS and pairs.device.type == "cpu":
            pairs = _incidence(pairs, M)
    for it in range(1, max_iter + 1):
        idx = torch.nonzero(active)[:, 0]
        if idx.numel() == 0:
            break
        iters[idx] = it
        L, g, H = cur.value[idx], cur.grad[idx], cur.hess[idx]
        maj = majorized[idx] & majorize[idx]
        Hd = torch.where(maj[:, None, None], H + cur.majorizer_gap[idx], H) if bool(maj.any()) else H
        fin = torch.isfinite(g).all(1) & torch.isfinite(Hd).flatten(1).all(1)
        # no direction from scenes whose derivatives overflowed: stop them (the factorisations would raise or
        # return NaN)
        if not bool(fin.all()):
            reason[idx[~fin]] = int(Stop.NONFINITE)
            active[idx[~fin]] = False
            idx, L, g, H, Hd, maj = idx[fin], L[fin], g[fin], H[fin], Hd[fin], maj[fin]
            if idx.numel() == 0:
                continue
        act_i = act[idx] if freeze else None
        if freeze and not bool(act_i.all()):  # frozen coordinates: identity rows, no step
            cm = act_i[:, block]  # (A, Q)
            eye = torch.eye(Hd.shape[1], dtype=Hd.dtype, device=dev)
            Hd = torch.where(cm[:, :, None] & cm[:, None, :], Hd, eye)
            g = torch.where(cm, g, torch.zeros((), dtype=g.dtype, device=dev))
        chol, info = torch.linalg.cholesky_ex(Hd)
        pd = info == 0
        p = torch.cholesky_solve(-g[:, :, None], chol)[:, :, 0]
        if not bool(pd.all()):
            bad = torch.nonzero(~pd)[:, 0]
            ev, V = torch.linalg.eigh(Hd[bad])
            floor = torch.maximum(cur.h_floor[idx][bad], 1e-12 * ev.abs().amax(1))
            mag = torch.maximum(ev.abs(), floor[:, None])
            p[bad] = -(V @ ((V.transpose(1, 2) @ g[bad][:, :, None])[:, :, 0] / mag)[:, :, None])[:, :, 0]
        p_max = p.abs().amax(1)
        newton_step = pd & ~maj
        small = newton_step & (p_max <= tol)
        if cur.barrier_value is not None and cur.h_floor is not None and bool(small.any()):
            # a step within tol next to a barrier (a pair within about tol of the contact margin, a joint of its
            # limit) is not convergence: there Newton's step is a fixed fraction of the gap, the balance however far
            dec = -(g * p).sum(1)
            walls = cur.barrier_value[idx]
            inertia = 10.0 * cur.h_floor[idx] * (p * p).sum(1)  # the least the bodies' inertia adds to dec
            stiff = (walls > 0) & (dec > _BARRIER_CURVATURE * inertia)
            barrier = (
                stiff & (dec > _BARRIER_DECREMENT * walls) & (dec > _BARRIER_DECREMENT_L * cur.scale[idx])
            )
            # friction's stiffness (large lagged forces next to the margin) shortens those steps and their
            # decrement, but they still grow from one iteration to the next, where Newton's converging steps shrink
            growing = stiff & (dec > _BARRIER_GROWING * walls) & (p_max >= last_step[idx])
            small = small & ~(barrier | growing)
        # the next step if Newton converges quadratically (|p_next| ~ |p|^2 |p| / |p_last|^2): a scene expected to
        # converge in its next iteration does not freeze bodies, which would cost it a whole evaluation more
        soon = newton_step & (p_max**3 <= tol * last_step[idx] ** 2)
        last_step[idx] = p_max
        whole_i = whole[idx]
        done = small & whole_i
        long_step = torch.zeros_like(small)  # converged steps that go through the line search
        if bool(done.any()):
            if final_move > 0:
                dpos = torch.nonzero(done)[:, 0]
                dn = idx[dpos]
                q_fin = q[dn] + p[dpos]
                take = displacement(q[dn], q_fin, dn) <= final_move
                at_q[dn[take]] = q[dn[take]]
                q[dn[take]] = q_fin[take]
                stepped[dn[take]] = True
                # a converged step that moves some vertex further (a tol loose against the contact margin) is
                # taken by the line search below, like any other step (dropping it would stop slow bodies); taken
                # whole, the scene has converged there
                small[dpos[~take]] = False
                done[dpos[~take]] = False
                long_step[dpos[~take]] = True
            reason[idx[done]] = int(Stop.CONVERGED)
            active[idx[done]] = False
        check = small & ~whole_i  # the bodies iterating converged: evaluate the whole scene
        if bool(check.any()):
            sc = idx[check]
            act[sc] = True
            whole[sc] = True
            may_freeze[sc] = False
            ev = _call(energy, q[sc], sc, 2, None)
            evals, nodes, leaves = evals + 1, nodes + ev.node_pairs, leaves + ev.leaf_pairs
            _assign(cur, sc, ev)
        keep = ~small
        if freeze and bool(keep.any()):
            # freeze the bodies within tol whose coupled bodies are all within tol
            k = torch.nonzero(keep)[:, 0]
            sc = idx[k]
            ak = act_i[k]  # (a scene evaluated whole above converged: not one of these)
            pb = (p[k].abs()[:, :, None] * onehot).amax(1)  # (A, M) largest step per body
            coupled = _coupling(H[k], onehot, width)  # (A, M, M), also the line search's islands below
            moving = ak & (pb > tol)
            frz = ak & ~moving & ~(coupled & moving[:, None, :]).any(2) & may_freeze[sc, None]
            frz = frz & (ak & ~frz).any(1, keepdim=True)  # never the last body still iterating
            frz = frz & ~soon[k, None]
            if bool(frz.any()):
                act[sc] = ak & ~frz
                whole[sc] = whole_i[k] & ~frz.any(1)
                p[k] = torch.where(frz[:, block], torch.zeros((), dtype=p.dtype, device=dev), p[k])
                # the energies of the scenes that froze a body now cover the bodies still iterating (the others'
                # stay as evaluated: a scene's path must not depend on the batch it is in)
                f = frz.any(1)
                value, scale, _ = _restricted(cur, sc[f], act[sc[f]], pairs)
                cur.value[sc[f]], cur.scale[sc[f]] = value, scale
                L = L.clone()
                L[k[f]] = value
        if bool(small.any()):
            idx, L, g, p, long_step = idx[keep], L[keep], g[keep], p[keep], long_step[keep]
            if idx.numel() == 0:
                continue
        # line search groups: the islands of coupled bodies of each scene (each scene whole without freezing)
        A = idx.numel()
        q0 = q[idx]
        if freeze:
            act_i = act[idx]
            gs, gm = _islands(coupled, act_i, split[idx])
            gp = p[gs] * gm[:, block].to(p.dtype)  # (G, Q) each island's part of the step
        else:
            gs = torch.arange(A, device=dev)
            gm = None
            gp = p
        sg, q0g = idx[gs], q0[gs]  # each island's scene and start
        reach = displacement(q0g, q0g + gp, sg)
        over = reach > max_move
        gp = torch.where(over[:, None], gp * (max_move / torch.where(over, reach, 1.0))[:, None], gp)
        reach = torch.where(over, torch.full_like(reach, max_move), reach)
        slope = (g[gs] * gp).sum(1)
        scale_i = cur.scale[idx]
        if freeze:
            others = act_i[gs] & ~gm  # (G, M) the bodies of the other islands of each island's scene
            L0, scale0, every0 = _restricted(cur, sg, gm, pairs, others)
            cross0 = every0 - L0  # its pairs with the other islands
        else:
            L0, scale0 = L, scale_i
        noise = 1e-12 * scale0  # rounding level of L: the full step must not be rejected for noise
        G = gs.numel()
        several = torch.bincount(gs, minlength=A) > 1  # (A,) the scenes split into several islands
        many = several[gs]  # (G,) the island is one of several in its scene
        alpha = torch.ones(G, dtype=q.dtype, device=dev)
        pending = torch.ones(G, dtype=torch.bool, device=dev)
        taken = torch.full((G,), -1, dtype=torch.long, device=dev)  # the try at which each group was accepted
        full = None
        for k in range(_LINE_SEARCH_TRIES):
            sub = torch.nonzero(pending)[:, 0]
            if sub.numel() == 0:
                break
            step_ = torch.where((pending | (taken >= 0))[:, None], alpha[:, None] * gp, 0.0)
            q_try = q0.index_add(0, gs, step_)  # (A, Q): every group at its trial (or accepted) step
            gsub = gs[sub]
            rows = torch.unique(gsub)  # the scenes with groups pending
            pos = torch.full((A,), -1, dtype=torch.long, device=dev)
            pos[rows] = torch.arange(rows.numel(), device=dev)
            psub = pos[gsub]  # each pending group's row of the evaluation
            on = gm_sub = None
            if freeze:
                gm_sub = gm[sub]
                on = torch.zeros(rows.numel(), M, dtype=torch.bool, device=dev)
                on.index_put_((psub,), gm_sub, accumulate=True)
            # the full step is usually accepted: evaluate it with derivatives at once, backtrack value-only
            ev = _call(energy, q_try[rows], idx[rows], 2 if k == 0 else 0, on)
            evals, nodes, leaves = evals + 1, nodes + ev.node_pairs, leaves + ev.leaf_pairs
            if k == 0:
                full = ev
            if freeze:
                L_try, _, with_others = _restricted(ev, psub, gm_sub, pairs, others[sub])
                # feasible: all its pairs finite, those with the other islands too
                feas = torch.isfinite(with_others)
                # slack: the change of its pairs with the other islands, whose own part of it the island's energy
                # cannot show (a body at rest pulled only by the far field of another island)
                slack = torch.where(feas, (with_others - L_try - cross0[sub]).abs(), 0.0)
            else:
                L_try = ev.value[psub]
                feas = torch.isfinite(L_try)
                slack = torch.zeros_like(L_try)
            # an island's decrease is measured without its far-field pairs with the other islands (they move those
            # too); an island whose predicted decrease is below L's rounding is accepted when feasible
            slope_sub, noise_sub = slope[sub], noise[sub]
            tiny = (-slope_sub <= noise_sub) & many[sub]
            ok = feas & ((L_try <= L0[sub] + 1e-4 * alpha[sub] * slope_sub + noise_sub + slack) | tiny)
            whole_only = None  # (at the full step) the islands accepted only for the whole step's sake
            if freeze and k == 0:
                # the whole step (every island's full step, as one scene's search would try it) passes the scene's
                # own test: its islands take it. An island's test cannot tell its own part of the change of its
                # pairs with the other islands from theirs, and rejects the full step of a body driven only by the
                # far field of an island that moves toward it
                total = torch.zeros(A, dtype=q.dtype, device=dev).index_add(0, gs, slope)
                lim = L + 1e-4 * total + 1e-12 * scale_i
                passed = (ev.value[pos] <= lim)[gsub]  # NaN and +inf fail
                whole_only = passed & ~ok
                ok = ok | passed
            if bool(ok.any()):
                cand = sub[ok]
                near = alpha[cand] * reach[cand] <= free_move
                clear = near.clone()
                if not bool(near.all()):
                    far = cand[~near]
                    q_far = q0[gs[far]]
                    clear[~near] = move_ok(q_far, q_far + alpha[far, None] * gp[far], idx[gs[far]])
                    if whole_only is not None and bool(whole_only.any()):
                        # an island whose path is blocked leaves the whole step untaken: the islands that took it
                        # only for the whole step's sake search on their own
                        blocked = torch.zeros(A, dtype=torch.bool, device=dev)
                        blocked[gs[cand[~clear]]] = True
                        clear = clear & ~(whole_only[ok] & blocked[gs[cand]])
                acc = cand[clear]
                pending[acc] = False
                taken[acc] = k
            alpha[pending] = alpha[pending] * 0.5
            if k + 1 == _ISLAND_TRIES:  # islands that backtrack this far: their scene searches whole
                pending = pending & ~many
        step_ = torch.where((taken >= 0)[:, None], alpha[:, None] * gp, 0.0)
        q_new = q0.index_add(0, gs, step_)
        a_done = torch.where(taken >= 0, alpha, alpha * 2.0)
        alpha_last[idx] = torch.full((A,), 2.0, dtype=q.dtype, device=dev).scatter_reduce(
            0, gs, a_done, "amin"
        )
        failed = torch.zeros(A, dtype=torch.bool, device=dev).index_put_((gs,), taken < 0, accumulate=True)
        # a split scene whose island found no step is not a failure: it keeps q0 (and its evaluation there) and
        # searches whole from the next iteration
        retry = failed & several
        # each island's path was checked with the others at q0: the islands' moves together must be clear too
        joint = several & ~failed
        if bool(joint.any()):
            jt = torch.nonzero(joint)[:, 0]
            far = displacement(q0[jt], q_new[jt], idx[jt]) > free_move
            if bool(far.any()):
                jf = jt[far]
                clear = move_ok(q0[jf], q_new[jf], idx[jf])
                retry[jf[~clear]] = True
        split[idx[retry]] = False
        failed = failed & ~retry
        q_new[retry] = q0[retry]
        later = torch.zeros(A, dtype=torch.bool, device=dev).index_put_((gs,), taken > 0, accumulate=True)
        later = later & ~retry
        first_try = ~failed & ~later & ~retry
        # each island's step decreased its own energy: together they must not raise the scene's (islands judged
        # uncoupled at q0 can move into each other's blend band; accepting that can cycle between a split and a
        # whole iteration forever); a scene whose islands did raise it keeps q0 and searches whole from then on
        lim = L + 1e-12 * scale_i
        rose = first_try & several & ~(full.value <= lim) if full is not None else torch.zeros_like(first_try)
        if bool(rose.any()):
            q_new[rose] = q0[rose]
            split[idx[rose]] = False
            first_try = first_try & ~rose
        q[idx[~failed]] = q_new[~failed]
        if bool(failed.any()):
            reason[idx[failed]] = int(Stop.LINE_SEARCH_FAILED)
            active[idx[failed]] = False
        if bool(first_try.any()):
            _assign(cur, idx[first_try], _rows(full, first_try))
            # the converged step taken whole: cur is the evaluation at the solution
            ended = first_try & long_step
            reason[idx[ended]] = int(Stop.CONVERGED)
            active[idx[ended]] = False
        later = later & ~failed
        if bool(later.any()):
            ev = _call(energy, q[idx[later]], idx[later], 2, act[idx[later]] if freeze else None)
            evals, nodes, leaves = evals + 1, nodes + ev.node_pairs, leaves + ev.leaf_pairs
            # islands accepted at different tries that ended up in contact, or that together raised the energy
            bad = ~torch.isfinite(ev.value) | (several[later] & ~(ev.value <= lim[later]))
            if bool(bad.any()):
                lb = torch.nonzero(later)[:, 0][bad]
                q[idx[lb]] = q0[lb]
                split[idx[lb]] = False
                ev = _rows(ev, ~bad)
                later[lb] = False
            if bool(later.any()):
                _assign(cur, idx[later], ev)
        majorized[idx] = later
    at_q = torch.where(stepped[:, None], at_q, q)
    return NewtonResult(q, cur, iters, reason, alpha_last, (evals, nodes, leaves), stepped, at_q)
