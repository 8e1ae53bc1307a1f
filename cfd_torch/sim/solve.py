"""One step's solve: a feasible start, Newton on the incremental potential, and the reachability of its end.

The start (the configuration the Newton solve begins from, feasible by :mod:`.feasibility`'s contract): the
constant-velocity extrapolation if it and the path to it are feasible; else q_t; else (a kinematic body moved into
or through a dynamic one) the moving bodies carried with each kinematic body's displacement, or a continuation:
the kinematic motion split into fractions (adaptively halved), the step's problem solved loosely at each fraction
from the previous solution, so the pushed bodies make room. Only the final solve, at the real targets, is the
step.
"""

from __future__ import annotations

import torch

from .energy import EnergyEval, StepProblem, batch_rows, incremental_potential, select_scenes
from .feasibility import (
    contained,
    displacement,
    feasible,
    infeasible_reason,
    path_clear,
    penetrating,
    reachable,
    start_and_sweep,
    sweep_clear,
)
from .newton import NewtonResult, Stop, _assign, _rows, newton
from .types import StepError

__all__ = ["solve_step", "start"]

Work = tuple[int, int, int]  # energy evaluations, node pairs, leaf pairs

# Newton's converged step (at most newton_tol per coordinate) is taken unchecked when it moves no vertex more than
# this fraction of the contact margin (far from where the barrier could be crossed), else through the line search
_FINAL_MOVE = 1e-2
# a failed solve's message names the moving bodies' mass ratio from this span up
_MASS_SPAN_HINT = 1e3


def _add(a: Work, b: Work) -> Work:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _work(ev: EnergyEval) -> Work:
    return (1, ev.node_pairs, ev.leaf_pairs)


class WarmStarts:
    """The contact model's warm-start data over one step's evaluations: each leaf pair's latest plane (sorted keys
    (W,), planes (W, 4); see :class:`cfd_torch.contact.ContactModel`). Only the speed of the plane solves depends
    on it, not their result (to their tolerance)."""

    def __init__(self) -> None:
        self.data: tuple[torch.Tensor, torch.Tensor] | None = None

    def update(self, new) -> None:
        """Merge ``new`` (keys, planes) of an evaluation: its planes replace those with the same keys."""
        if new is None or new[0].numel() == 0:
            return
        if self.data is None:
            self.data = new
            return
        if new[0].device.type == "cpu":  # both tables are sorted: a linear merge (numba)
            from ..contact._traverse_numba import warm_merge

            self.data = tuple(
                torch.from_numpy(x)
                for x in warm_merge(
                    new[0].contiguous().numpy(), new[1].contiguous().numpy(), self.data[0].contiguous().numpy(),
                    self.data[1].contiguous().numpy(),
                )
            )  # fmt: skip
            return
        keys = torch.cat([new[0], self.data[0]])
        planes = torch.cat([new[1], self.data[1]])
        keys, order = torch.sort(keys, stable=True)  # the new entry first among equal keys
        first = torch.ones_like(keys, dtype=torch.bool)
        first[1:] = keys[1:] != keys[:-1]
        self.data = (keys[first], planes[order][first])


def _energy(prob: StepProblem, warm: WarmStarts | None = None, moving_hessian: bool = False):
    """(q (A, Q), scenes (A,), order, active (A, M) | None) -> L of those scenes of ``prob`` (the leaf pairs'
    plane solves warm-started from ``warm``, which each evaluation updates; ``moving_hessian``: see
    :func:`incremental_potential`)."""
    B = prob.q_t.shape[0]
    every = torch.arange(B, device=prob.q_t.device)
    rows = batch_rows(prob, prob.q_t.device)  # (what the evaluations of all B scenes share)

    def energy(
        q: torch.Tensor, scenes: torch.Tensor, order: int, active: torch.Tensor | None = None
    ) -> EnergyEval:
        whole = len(scenes) == B and bool((scenes == every).all())
        if active is not None and bool(active.all()):
            active = None
        sub, batch = (prob, rows) if whole else (select_scenes(prob, scenes), None)
        if warm is None:
            return incremental_potential(sub, q, order, active, batch=batch, moving_hessian=moving_hessian)
        ev = incremental_potential(
            sub,
            q,
            order,
            active,
            scene_ids=scenes,
            warm=warm.data,
            batch=batch,
            moving_hessian=moving_hessian,
        )
        warm.update(ev.warm)
        return ev

    return energy


def _coords(prob: StepProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """The coordinates (B, Q) of the start-of-step poses and of those one step earlier: the joint inputs' where the
    scene has them (recovering joint values from link rows costs a few dozen tensor operations), else mapped."""
    if prob.joint is not None:
        return prob.joint.q_t, prob.joint.q_p
    kin = prob.scene.kinematics
    return kin.coords(prob.q_t), kin.coords(prob.q_p)


def _pair_bodies(scene) -> torch.Tensor:
    """(P, 2) each interacting pair's bodies as indices into the moving bodies (-1: a body that does not move)."""
    pos = torch.full((scene.num_bodies,), -1, dtype=torch.long)
    pos[scene.kinematics.bodies] = torch.arange(len(scene.kinematics.bodies))
    return pos[scene.pairs]


def _newton(
    prob: StepProblem, q: torch.Tensor, first: EnergyEval | None, tol: float, warm: WarmStarts | None = None
) -> tuple[NewtonResult, Work]:
    s = prob.scene.solver
    # Newton reads the Hessian of the moving bodies only (the adjoint's cross blocks come from solve_step's end)
    energy = _energy(prob, warm, moving_hessian=s.fast)
    work: Work = (0, 0, 0)
    if first is None:
        first = energy(q, torch.arange(q.shape[0], device=q.device), 2)
        work = _work(first)
    majorize = None
    if prob.lagged is not None:  # the scenes with friction (their coefficient, or its gradient, asked for it)
        majorize = prob.friction_on
    block = pair_bodies = None
    if s.fast and prob.scene.kinematics.freezable:  # converged bodies freeze, islands search apart
        block = prob.scene.kinematics.coord_body.to(q.device)
        pair_bodies = _pair_bodies(prob.scene).to(q.device)
    res = newton(
        energy, q, first, tol=tol, max_iter=s.max_newton_iter, max_move=20.0 * s.ccd_spacing,
        free_move=prob.scene.path_spacing, move_ok=lambda a, b, sc: path_clear(prob, a, b, sc),
        displacement=lambda a, b, sc: displacement(prob, a, b, sc), majorize=majorize, block=block,
        pair_bodies=pair_bodies, final_move=_FINAL_MOVE * prob.scene.contact.margin,
    )  # fmt: skip
    return res, _add(work, res.work)


def _kinematic_pairs(scene) -> torch.Tensor:
    """(P,) bool: the interacting pairs with a kinematic body."""
    kin = torch.zeros(scene.num_bodies, dtype=torch.bool)
    kin[scene.kinematic] = True
    return kin[scene.pairs[:, 0]] | kin[scene.pairs[:, 1]]


def _continuation(prob: StepProblem, q: torch.Tensor, where: str = "") -> tuple[torch.Tensor, Work]:
    """Scene 0 of ``prob`` (one scene): push the moving bodies out of a kinematic body's way, moving the kinematic
    bodies to their targets in stages (the stage doubled after a solved one, halved after an infeasible one), each
    stage solved from the last solution carried along the last stage's motion (a secant predictor: without it a
    stage could only advance a pusher until it touched the bodies where they were) where that start is feasible and
    its path clear, else from the last solution. ``where``: the scene, for the errors (" (scene b)" in a batch)."""
    scene = prob.scene
    kin = scene.kinematic.to(q.device)
    target = prob.fixed.clone()
    origin = prob.q_t[:, kin]
    done, inc = 0.0, 0.5
    tol = max(scene.solver.newton_tol, 1e-7)
    work: Work = (0, 0, 0)
    before = target.clone()
    before[:, kin] = origin
    kp = _kinematic_pairs(scene)
    rate = None  # d q / d frac over the last stage: the predictor of the next stage's solution
    while done < 1.0:
        frac = min(1.0, done + inc)
        fixed = target.clone()
        fixed[:, kin] = origin + frac * (target[:, kin] - origin)
        sub = prob._replace(fixed=fixed)
        p0 = scene.kinematics.poses(q, before)
        q1 = q
        ok = False
        # the moving bodies carried along the last stage's motion, their paths checked too
        if rate is not None:
            q1 = q + (frac - done) * rate
            p1 = scene.kinematics.poses(q1, fixed)
            ok = bool(feasible(scene, p1)[0]) and bool(sweep_clear(scene, p0, p1)[0])
        if not ok:  # the moving bodies where they are: only the kinematic bodies' paths move
            q1 = q
            p1 = scene.kinematics.poses(q, fixed)
            ok = bool(feasible(scene, p1)[0]) and bool(sweep_clear(scene, p0, p1, kp)[0])
        if ok:
            before = fixed
            res, w = _newton(sub, q1, None, tol)
            work = _add(work, w)
            if int(res.reason[0]) != Stop.CONVERGED:
                why = Stop(int(res.reason[0]))
                raise StepError(
                    f"pushing bodies out of a kinematic body's way{where}: the solve at {frac:.3g} of the kinematic "
                    f"motion stopped: {why.name}"
                    + (
                        f" (max_newton_iter={scene.solver.max_newton_iter} iterations per solve)"
                        if why == Stop.MAX_ITER
                        else ""
                    )
                )
            rate = (res.q - q) / (frac - done)
            q = res.q
            done, inc = frac, inc * 2.0
        else:
            inc *= 0.5
            if inc < 1e-4:
                raise StepError(
                    f"the kinematic targets{where}: bodies penetrate ({infeasible_reason(scene)}): pairs "
                    f"{penetrating(scene, scene.kinematics.poses(q, fixed)[0])}, and pushing them out of the way "
                    "failed; move kinematic bodies less per step"
                )
    return q, work


def _refuse_contained(
    scene, poses: torch.Tensor, name: str, scenes: torch.Tensor | None = None, sel: torch.Tensor | None = None
) -> None:
    """ValueError naming ``name`` if a body lies wholly inside another at ``poses`` (S, N, 6) (of ``scenes``; the
    pairs ``sel``)."""
    inside = contained(scene, poses, sel)
    if inside:
        s, i, j = inside[0]
        b = s if scenes is None else int(scenes[s])
        raise ValueError(
            f"{name}: body {i} lies inside body {j} (their surfaces do not touch, so the contact potential cannot "
            f"push it out)" + (f" (scene {b})" if poses.shape[0] > 1 or b > 0 else "")
        )


def start(prob: StepProblem, warm: WarmStarts | None = None) -> tuple[torch.Tensor, EnergyEval | None, Work]:
    """A feasible start (B, Q) for every scene, its order-2 evaluation where already done (None if not), and the
    work spent (``warm``: the step's warm starts, updated by the evaluation of the usual start)."""
    scene = prob.scene
    kin = scene.kinematics
    q_t, q_p = _coords(prob)
    extrap = kin.extrapolate(q_t, q_p)
    B = q_t.shape[0]
    dev = q_t.device
    _refuse_contained(scene, prob.q_t, "state.q")
    at_targets = kin.poses(q_t, prob.fixed)
    ok_t = feasible(scene, at_targets)
    kin_idx = scene.kinematic.to(dev)
    if len(kin_idx):  # a kinematic body that moves through a moving body: its end pose alone does not show it
        moved = ok_t & (prob.fixed[:, kin_idx] != prob.q_t[:, kin_idx]).flatten(1).any(1)
        if bool(moved.any()):
            m = torch.nonzero(moved)[:, 0]
            p1 = kin.poses(q_t[m], prob.fixed[m])
            p0 = p1.clone()
            p0[:, kin_idx] = prob.q_t[m][:, kin_idx]
            kp = _kinematic_pairs(scene)
            # the start itself too (at its target the kinematic body may be clear of what it penetrates now)
            start_bad, ok_t[m] = start_and_sweep(scene, p0, p1, kp)
            if bool(start_bad.any()):
                k = int(torch.nonzero(start_bad)[0, 0])
                raise ValueError(
                    f"state.q: bodies penetrate ({infeasible_reason(scene)}): pairs {penetrating(scene, p0[k])}"
                    + (f" (scene {int(m[k])})" if B > 1 else "")
                )
            # a kinematic body that ends inside a moving one without crossing a surface on the way (a move
            # shorter than path_spacing): nothing could push that body out
            clear = m[ok_t[m]]
            _refuse_contained(scene, p1[ok_t[m]], "action.target", clear, kp)
    work: Work = (0, 0, 0)
    if bool(ok_t.all()):
        all_ = torch.arange(B, device=dev)
        # the usual start: evaluated with derivatives at once, for Newton (the moving bodies' Hessian)
        ev = _energy(prob, warm, moving_hessian=scene.solver.fast)(extrap, all_, 2)
        work = _work(ev)
        good = torch.isfinite(ev.value) & path_clear(prob, q_t, extrap, all_)
        if bool(good.all()):
            return extrap, ev, work
        return torch.where(good[:, None], extrap, q_t), None, work
    q0 = q_t.clone()
    zero = torch.zeros(1, dtype=torch.long, device=dev)
    for b in torch.nonzero(ok_t)[:, 0].tolist():  # the scenes that start as usual
        one = select_scenes(prob, torch.tensor([b], device=dev))
        e = incremental_potential(one, extrap[b : b + 1], 0)
        work = _add(work, _work(e))
        if bool(torch.isfinite(e.value[0])) and bool(
            path_clear(one, q_t[b : b + 1], extrap[b : b + 1], zero)[0]
        ):
            q0[b] = extrap[b]
    for b in torch.nonzero(~ok_t)[:, 0].tolist():
        bad = penetrating(scene, prob.q_t[b])
        if bad:
            raise ValueError(
                f"state.q: bodies penetrate ({infeasible_reason(scene)}): "
                f"pairs {bad}" + (f" (scene {b})" if B > 1 else "")
            )
        where = f" (scene {b})" if B > 1 else ""
        if len(kin_idx) == 0:
            raise StepError(f"infeasible step start (non-finite energy at the start-of-step poses){where}")
        shift = prob.fixed[b, kin_idx, :3] - prob.q_t[b, kin_idx, :3]  # (K, 3)
        p0 = kin.poses(q_t[b : b + 1], prob.fixed[b : b + 1])
        p0[:, kin_idx] = prob.q_t[b : b + 1, kin_idx]
        for k in range(len(kin_idx)):
            cand = kin.carry(q_t[b : b + 1], shift[k : k + 1])
            p1 = kin.poses(cand, prob.fixed[b : b + 1])
            if bool(feasible(scene, p1)[0]) and bool(sweep_clear(scene, p0, p1)[0]):
                q0[b] = cand[0]
                break
        else:
            q, w = _continuation(select_scenes(prob, torch.tensor([b], device=dev)), q_t[b : b + 1], where)
            q0[b], work = q[0], _add(work, w)
    return q0, None, work


def _settings(prob: StepProblem, b: int) -> str:
    """The settings that scale scene b's incremental potential terms, for the overflow errors (the friction
    coefficient the step used: the scene's, or the one passed in ``Params``)."""
    scene = prob.scene
    return (
        f"(dt={scene.dt:g}, contact stiffness mu={scene.contact.stiffness:g}, friction coefficient "
        f"{float(prob.friction[b]):g}: check them, the masses and the action (forces, torques, controls))"
    )


def solve_step(prob: StepProblem, exact_end: bool = False) -> tuple[NewtonResult, Work]:
    """Feasible start, Newton, reachability: the step's NewtonResult and the work spent (energy evaluations, node
    pairs, leaf pairs); raises StepError saying why it failed.

    ``exact_end``: the result's ``at`` is evaluated at the returned q (one more evaluation of the scenes that took
    Newton's converged step after their last evaluation): the adjoint's Hessian is then that of the solution. Newton
    takes that step, up to ``newton_tol``, unevaluated; friction's Hessian varies on the scale of its slip threshold
    eps_v dt (1e-6 m at the defaults), so at a sticking contact the Hessian before the step gave gradients up to
    1e-2 relative off (a session-45 audit). With ``exact_end`` the result's ``at.contact_hess`` is whole (the cross
    blocks with the bodies that do not move, which the adjoint reads and Newton's evaluations leave out where the
    contact model allows: a scene that did not step is evaluated again at its point)."""
    warm = WarmStarts() if prob.scene.solver.fast else None
    if (
        warm is not None and prob.lagged is not None
    ):  # the lagged contacts' planes at q_t, where the model made them
        warm.update(prob.lagged.warm)
    q0, first, work = start(prob, warm)
    s = prob.scene.solver
    res, w = _newton(prob, q0, first, s.newton_tol, warm)
    work = _add(work, w)
    B = q0.shape[0]
    for b in range(B):
        r = Stop(int(res.reason[b]))
        if r == Stop.CONVERGED:
            continue
        where = f" (scene {b})" if B > 1 else ""
        if r == Stop.INFEASIBLE_START:
            if prob.scene.simulates_joints:  # a joint at or beyond its limit: say which
                prob.scene.kinematics.check_within_limits(prob.q_t.detach(), "state.q")
            raise StepError(
                f"infeasible Newton start (non-finite energy){where}: bodies penetrate, or a term overflows float64 "
                f"{_settings(prob, b)}"
            )
        if r == Stop.NONFINITE:
            raise StepError(
                f"non-finite gradient or Hessian at Newton iteration {int(res.iters[b])}{where}: a term of the "
                f"incremental potential overflows float64 {_settings(prob, b)}"
            )
        what = {
            Stop.LINE_SEARCH_FAILED: f"the line search failed at Newton iteration {int(res.iters[b])} (no finite, "
            "decreasing, reachable trial along the direction)",
            Stop.MAX_ITER: f"the step did not converge in {s.max_newton_iter} Newton iterations",
        }[r]
        # the gradient of the whole energy at the last iterate (``res.at`` may cover only the bodies still
        # iterating, where a frozen body's gradient lacks its contacts: a resting body's reads as its weight)
        sel = torch.tensor([b], device=q0.device)
        gmax = float(_energy(prob)(res.q[sel], sel, 1).grad[0].abs().max())
        m = prob.mass[b]  # (a scene has at least one dynamic body)
        span = float(m.max() / m.min())
        ratio = (
            f"; the moving bodies' masses span {span:.0e}x: a light body pressed by a much heavier one (a ratio "
            "of 1e5 stalled Newton in a session-53 audit) needs a smaller dt, or masses closer together"
            if span >= _MASS_SPAN_HINT else ""
        )  # fmt: skip
        raise StepError(
            f"{what}{where} (newton_tol={s.newton_tol}): max |dL/dq| = {gmax:.3e}, last line search step "
            f"{float(res.alpha[b]):.1e}; try a smaller dt (a heavy or fast body), a contact margin and stiffness "
            f"suited to the bodies' scale, a larger max_newton_iter, or, if ccd_spacing={s.ccd_spacing:g} is small "
            f"against the bodies' motion, a larger one (an iteration moves a vertex at most 20 x ccd_spacing){ratio}"
        )
    q_t = _coords(prob)[0]
    ok, blocked = reachable(prob, q_t, res.q)
    if not bool(ok.all()):
        b = int(torch.nonzero(~ok)[0, 0])
        i, j, moved = blocked[b]
        raise StepError(
            f"the step's solution is not reachable from the start-of-step poses without penetration (body {i}'s "
            f"centre of mass passes through body {j}, moving {moved:.3g} m relative to it"
            f"{f', scene {b}' if B > 1 else ''}): reduce dt, or let the step retry in sub-steps "
            "(SolverConfig.substeps)"
        )
    partial = bool(
        s.fast and getattr(prob.scene.contact_model, "partial_hessian", False) and prob.scene.pairs.shape[0]
    )
    if exact_end and (partial or bool(res.stepped.any())):
        at = EnergyEval(*(x.clone() if isinstance(x, torch.Tensor) else x for x in res.at))
        stepped = res.stepped.clone()
        at_q = res.at_q.clone()
        redo = torch.zeros_like(stepped)  # the scenes whose ``at`` Newton left without its cross blocks
        if bool(stepped.any()):
            sc = torch.nonzero(stepped)[:, 0]
            ev = _energy(prob, warm)(res.q[sc], sc, 2)
            work = _add(work, _work(ev))
            # (a scene whose Hessian there is not positive definite, which Newton's test held a step of at most tol
            # before, keeps the evaluation at that point)
            ok = torch.isfinite(ev.value) & (torch.linalg.cholesky_ex(ev.hess)[1] == 0)
            _assign(at, sc[ok], _rows(ev, ok))
            stepped[sc[ok]] = False
            at_q[sc[ok]] = res.q[sc[ok]]
            redo[sc[~ok]] = True
        if partial:
            redo = redo | ~res.stepped
        if bool(redo.any()):
            sc = torch.nonzero(redo)[:, 0]
            ev = _energy(prob, warm)(at_q[sc], sc, 2)
            work = _add(work, _work(ev))
            _assign(at, sc, ev)
        res = res._replace(at=at, stepped=stepped, at_q=at_q)
    return res, work
