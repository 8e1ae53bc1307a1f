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
coordinate at a positive definite Hessian (never in a majorized iteration: its step is shorter than Newton's).

Scenes that converged or failed stop costing: each evaluation covers only the scenes still iterating.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import NamedTuple

import torch

from .energy import EnergyEval

__all__ = ["Stop", "NewtonResult", "newton"]

_LINE_SEARCH_TRIES = 60


class Stop(enum.IntEnum):
    """Why a scene's Newton solve stopped."""

    CONVERGED = 0
    LINE_SEARCH_FAILED = 1  # no trial along the direction was finite, decreasing and reachable
    MAX_ITER = 2  # the iteration cap was reached
    INFEASIBLE_START = 3  # the energy at the start is +inf


class NewtonResult(NamedTuple):
    """Per scene (B of them).

    Attributes:
        q: (B, Q) the last iterate.
        at: the order-2 evaluation at q (exact Hessian, contact Hessian, forces, ...).
        iters: (B,) Newton iterations.
        reason: (B,) codes of :class:`Stop`.
        alpha: (B,) the last line search's step.
        work: (evaluations, node pairs, leaf pairs) of the energy evaluations this solve made (``first`` excluded).
    """

    q: torch.Tensor
    at: EnergyEval
    iters: torch.Tensor
    reason: torch.Tensor
    alpha: torch.Tensor
    work: tuple[int, int, int]


def _assign(cur: EnergyEval, idx: torch.Tensor, ev: EnergyEval) -> None:
    """Write the rows ``ev`` (order 2, scenes ``idx``) into the per-scene evaluation ``cur`` (in place)."""
    for mine, new in zip(cur, ev, strict=True):
        if isinstance(mine, torch.Tensor) and new is not None:
            mine[idx] = new


def _rows(ev: EnergyEval, sel: torch.Tensor) -> EnergyEval:
    return EnergyEval(*(x[sel] if isinstance(x, torch.Tensor) else x for x in ev))


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
) -> NewtonResult:
    """Minimise B independent energies from feasible starts.

    Args:
        energy: (q (A, Q), scenes (A,) indices, order) -> EnergyEval of those scenes.
        q: (B, Q) starts; ``first`` their order-2 evaluation (all B scenes).
        tol: convergence threshold on the Newton step [coordinate units].
        max_iter: iteration cap.
        max_move: largest vertex displacement of one iteration [m].
        free_move: moves whose vertex displacement is at most this need no ``move_ok`` check [m].
        move_ok: (q0, q1, scenes) -> (A,) bool: whether the move q0 -> q1 of those scenes is free of tunnelling.
        displacement: (q0, q1, scenes) -> (A,) largest vertex displacement of the move [m].
        majorize: (B,) bool, the scenes whose iteration after a rejected full step uses the energy's majorizer
            (``EnergyEval.majorizer_gap``); default: all, if the energy has one.
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
    reason = torch.full((B,), int(Stop.MAX_ITER), dtype=torch.long, device=dev)
    alpha_last = torch.ones(B, dtype=q.dtype, device=dev)
    majorized = torch.zeros(B, dtype=torch.bool, device=dev)  # this iteration follows a rejected full step
    active = torch.isfinite(cur.value)
    reason[~active] = int(Stop.INFEASIBLE_START)
    for it in range(1, max_iter + 1):
        idx = torch.nonzero(active)[:, 0]
        if idx.numel() == 0:
            break
        iters[idx] = it
        L, g, H = cur.value[idx], cur.grad[idx], cur.hess[idx]
        maj = majorized[idx] & majorize[idx]
        Hd = torch.where(maj[:, None, None], H + cur.majorizer_gap[idx], H) if bool(maj.any()) else H
        chol, info = torch.linalg.cholesky_ex(Hd)
        pd = info == 0
        p = torch.cholesky_solve(-g[:, :, None], chol)[:, :, 0]
        if not bool(pd.all()):
            bad = torch.nonzero(~pd)[:, 0]
            ev, V = torch.linalg.eigh(Hd[bad])
            floor = torch.maximum(cur.h_floor[idx][bad], 1e-12 * ev.abs().amax(1))
            mag = torch.maximum(ev.abs(), floor[:, None])
            p[bad] = -(V @ ((V.transpose(1, 2) @ g[bad][:, :, None])[:, :, 0] / mag)[:, :, None])[:, :, 0]
        done = pd & ~maj & (p.abs().amax(1) <= tol)
        if bool(done.any()):
            reason[idx[done]] = int(Stop.CONVERGED)
            active[idx[done]] = False
            keep = ~done
            idx, L, g, p = idx[keep], L[keep], g[keep], p[keep]
            if idx.numel() == 0:
                break
        q0 = q[idx]
        reach = displacement(q0, q0 + p, idx)
        over = reach > max_move
        p = torch.where(over[:, None], p * (max_move / torch.where(over, reach, 1.0))[:, None], p)
        reach = torch.where(over, torch.full_like(reach, max_move), reach)
        slope = (g * p).sum(1)
        noise = 1e-12 * cur.scale[idx]  # rounding level of L: the full step must not be rejected for noise
        alpha = torch.ones_like(L)
        pending = torch.ones_like(L, dtype=torch.bool)
        taken = torch.full_like(L, -1, dtype=torch.long)  # the try at which each scene's step was accepted
        full = None
        for k in range(_LINE_SEARCH_TRIES):
            sub = torch.nonzero(pending)[:, 0]
            if sub.numel() == 0:
                break
            q_try = q0[sub] + alpha[sub, None] * p[sub]
            # the full step is usually accepted: evaluate it with derivatives at once, backtrack value-only
            ev = energy(q_try, idx[sub], 2 if k == 0 else 0)
            evals, nodes, leaves = evals + 1, nodes + ev.node_pairs, leaves + ev.leaf_pairs
            if k == 0:
                full = ev
            L_try = ev.value
            ok = torch.isfinite(L_try) & (L_try <= L[sub] + 1e-4 * alpha[sub] * slope[sub] + noise[sub])
            if bool(ok.any()):
                cand = sub[ok]
                near = alpha[cand] * reach[cand] <= free_move
                clear = near.clone()
                if not bool(near.all()):
                    far = cand[~near]
                    clear[~near] = move_ok(q0[far], q0[far] + alpha[far, None] * p[far], idx[far])
                acc = cand[clear]
                pending[acc] = False
                taken[acc] = k
                q[idx[acc]] = q0[acc] + alpha[acc, None] * p[acc]
            alpha[pending] = alpha[pending] * 0.5
        alpha_last[idx] = torch.where(taken >= 0, alpha, alpha * 2.0)
        failed = taken < 0
        if bool(failed.any()):
            reason[idx[failed]] = int(Stop.LINE_SEARCH_FAILED)
            active[idx[failed]] = False
        first_try = taken == 0
        if bool(first_try.any()):
            _assign(cur, idx[first_try], _rows(full, first_try))
        later = taken > 0
        if bool(later.any()):
            ev = energy(q[idx[later]], idx[later], 2)
            evals, nodes, leaves = evals + 1, nodes + ev.node_pairs, leaves + ev.leaf_pairs
            _assign(cur, idx[later], ev)
        majorized[idx] = later
    return NewtonResult(q, cur, iters, reason, alpha_last, (evals, nodes, leaves))
