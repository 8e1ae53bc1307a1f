"""One step as an autograd Function: the forward solves, the backward is one adjoint solve per scene.

q* solves g(q*, theta) = dL/dq = 0, so dq*/dtheta = -H^-1 d2L/(dq dtheta) (implicit function theorem). The backward
does one linear solve H lam = grad_out with the Hessian of the converged iterate (positive definite: Newton stops
only there) and one vector-Jacobian product -lam^T d2L/(dq dtheta) for theta = previous states, actions (forces,
torques, kinematic targets, controls), masses, second moments, the friction coefficient and the servo gains.
Reverse mode through a rollout is ordinary autograd chaining of these steps.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import NamedTuple

import torch

from .._autograd import refuse_batched
from ..contact.model import LaggedContacts, sum_pairs
from ..contact.pair import PairSolveError
from .energy import (
    FreeRotationError,
    JointInputs,
    StepProblem,
    body_terms,
    end_poses,
    free_rotation_message,
    predicted_rotation,
    scene_pairs,
)
from .friction import friction_terms
from .solve import solve_step
from .types import StepError

__all__ = ["StepFn"]


@contextmanager
def _serial_torch():
    """Run torch's CPU ops of a step on one thread: its tensors are small (bodies, leaf pairs), and idle OpenMP
    workers spin-waiting between them cost several times the step time on a loaded 2-core machine; the contact
    kernels keep numba's own parallelism."""
    n = torch.get_num_threads()
    if n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _lagged(scene, q_t: torch.Tensor, on: torch.Tensor, create_graph: bool = False) -> LaggedContacts:
    """The lagged friction contacts of the scenes ``on`` (B,) bool at the start-of-step poses q_t (B, N, 6),
    indexed into the pairs of all B scenes (``scene_pairs(scene, B)``)."""
    B, P = q_t.shape[0], scene.pairs.shape[0]
    idx = torch.nonzero(on)[:, 0]
    pairs = scene_pairs(scene, len(idx)).to(q_t.device)
    model = scene.contact_model
    kw = {}
    if scene.solver.fast and getattr(model, "warm_start", False) and not create_graph:
        # the leaf pairs' planes at q_t start the plane solves of the step's first evaluation (the pairs' ids as
        # in the step's evaluations: scene * P + pair)
        rows = torch.arange(pairs.shape[0], device=q_t.device)
        kw["ids"] = idx[rows // P] * P + rows % P
    lag = model.lagged(q_t[idx], pairs, scene.friction.active, create_graph=create_graph, **kw)
    if len(idx) < B and P:  # renumber into the pairs of all B scenes
        lag = lag._replace(pair=idx[lag.pair // P] * P + lag.pair % P)
    return lag


class _Prediction(NamedTuple):
    """Where the inertia terms put each moving body without forces: its orientation (B, Nd, 3, 3) (a rotation for
    free bodies, a first-order correction of one for articulated links) and the shift of its centre of mass from
    2 t_t - t_{t-1} (B, Nd, 3) or None (free bodies); each body's rotation predicted as a free body's (B, Nd, 3, 3)
    (the backward starts its solve there); with articulations, their coordinates at the two earlier states (B,
    Q)."""

    rotation: torch.Tensor
    free_rotation: torch.Tensor
    shift: torch.Tensor | None = None
    coords_t: torch.Tensor | None = None
    coords_p: torch.Tensor | None = None


def _joint_inputs(scene, pred: _Prediction, ctrl, kp, kv) -> JointInputs | None:
    """The joint-space inputs of a scene with simulated articulations (coordinates of the two earlier states, from
    the prediction, and the actuators' terms for the controls ``ctrl`` and servo gains ``kp``, ``kv``), None
    without."""
    if not scene.simulates_joints:
        return None
    return JointInputs(pred.coords_t, pred.coords_p, *scene.kinematics.drive(ctrl, kp, kv))


def _predicted(
    scene,
    q_t: torch.Tensor,
    q_p: torch.Tensor,
    fixed: torch.Tensor,
    mass: torch.Tensor,
    S: torch.Tensor,
    solved=None,
) -> _Prediction:
    """The moving bodies' predictions: free bodies' rotations by :func:`~cfd_torch.sim.energy.predicted_rotation`
    (without the gyroscopic term in planar scenes), articulated links' by the joints
    (:meth:`~cfd_torch.sim.articulation.ArticulatedKinematics.predict`, at the end-of-step poses ``fixed`` of the
    bodies the map does not move); ``solved``: the forward's rotations, which the backward starts from."""
    kin = scene.kinematics
    dyn = kin.bodies.to(q_t.device)
    B, Nd = q_t.shape[0], len(dyn)
    try:
        r = predicted_rotation(
            q_t[:, dyn].reshape(B * Nd, 6),
            q_p[:, dyn].reshape(B * Nd, 6),
            S.reshape(B * Nd, 3, 3),
            not scene.planar,
            None if solved is None else solved.reshape(B * Nd, 3, 3),
        ).reshape(B, Nd, 3, 3)
    except FreeRotationError as err:  # name the body (and the scene, in a batch)
        b, i = divmod(err.row, Nd)
        where = f" (body {int(dyn[i])}{f', scene {b}' if B > 1 else ''})"
        raise FreeRotationError(free_rotation_message(where), err.row) from None
    if not scene.simulates_joints:
        return _Prediction(r, r)
    th_t = kin.coords(q_t)
    th_p = kin.coords(q_p, near=th_t)  # on the same branch where link poses do not tell joint values apart
    rot, shift = kin.predict(q_t, q_p, th_t, th_p, fixed, r, mass, S)
    return _Prediction(rot, r, shift, th_t, th_p)


class StepFn(torch.autograd.Function):
    """(scene, q_t, q_p, force, torque, target, mass, S, mu_f, ctrl, kp, kv) -> q* (B, Q) and, not differentiable,
    the solver's statistics: Newton iterations (B,), contact and friction forces (B, N, 6), friction contacts (B,),
    work (3,) (energy evaluations, node pairs, leaf pairs) and the forward's wall time (1,)."""

    @staticmethod
    def forward(ctx, scene, q_t, q_p, force, torque, target, mass, S, mu_f, ctrl, kp, kv):
        t0 = time.perf_counter()
        B = q_t.shape[0]
        with _serial_torch():
            fixed = end_poses(scene, q_t, target)
            # friction off costs nothing, unless its coefficient needs a gradient (at mu_f = 0 the term is zero but
            # its derivative is not)
            on = (mu_f > 0) | ctx.needs_input_grad[8]
            lagged = _lagged(scene, q_t, on) if bool(on.any()) else None
            gravity = torch.tensor(scene.gravity, dtype=q_t.dtype, device=q_t.device)
            pred = _predicted(scene, q_t, q_p, fixed, mass, S)
            joint = _joint_inputs(scene, pred, ctrl, kp, kv)
            prob = StepProblem(
                scene, fixed, q_t, q_p, force, torque, mass, S, mu_f, on, lagged, gravity, joint, pred.rotation,
                pred.shift,
            )  # fmt: skip
            try:
                res, work = solve_step(prob, exact_end=any(ctx.needs_input_grad))
            except PairSolveError as err:  # a leaf pair's plane solve at some trial point: the step failed
                raise StepError(f"the step failed: {err}") from err
        # the adjoint needs the contact Hessian's cross blocks with the pose components that depend on the inputs
        # at fixed coordinates: those the map does not move, and those of bodies hung from a fixed pose
        kin = scene.kinematics
        hung = kin.hung[:, None].expand(-1, 6)
        rows6 = torch.nonzero((~kin.moved | hung).reshape(-1))[:, 0].to(q_t.device)
        cross = res.at.contact_hess[:, rows6]  # (B, F, 6 N)
        # and, where the map's Jacobian depends on a fixed pose, the contact gradient it pulls back
        contact_grad = -res.at.contact_force if bool(kin.hung.any()) else None
        ctx.scene, ctx.friction_on = scene, on if lagged is not None else None
        ctx.save_for_backward(
            res.q, res.at.hess, cross, rows6, q_t, q_p, force, torque, target, mass, S, mu_f, ctrl, kp, kv,
            pred.free_rotation, contact_grad,
        )  # fmt: skip
        if lagged is None:
            n_fc = torch.zeros(B, dtype=torch.long, device=q_t.device)
        else:
            n_fc = torch.bincount(lagged.pair // max(scene.pairs.shape[0], 1), minlength=B)
        extras = (res.iters, res.at.contact_force, res.at.friction_force, n_fc, torch.tensor(work))
        seconds = torch.tensor([time.perf_counter() - t0], dtype=torch.float64)
        ctx.mark_non_differentiable(*extras, seconds)
        return (res.q, *extras, seconds)

    @staticmethod
    def backward(ctx, gout, *_):
        refuse_batched(
            "cfd_torch.step: batched gradients (autograd.grad(..., is_grads_batched=True), "
            "autograd.functional.jacobian(..., vectorize=True)) do not pass through a simulation step's adjoint; "
            "use vectorize=False, or one backward per output vector",
            gout,
        )
        if torch.is_grad_enabled():  # create_graph=True
            raise RuntimeError(
                "cfd_torch.step: second derivatives through a simulation step are not implemented (the step's "
                "backward is a first-order adjoint); do not use create_graph=True through step(), nor "
                "torch.autograd.functional's jvp, hvp, vhp or hessian, which differentiate a backward (for a "
                "Jacobian use torch.autograd.functional.jacobian or one backward per output vector)"
            )
        with _serial_torch():
            return StepFn._backward(ctx, gout)

    @staticmethod
    def _backward(ctx, gout):
        # lam = H^-1 v (H symmetric positive definite), dtheta = -lam^T dg/dtheta, with g = J^T g_pose(theta) for
        # the pose-space gradient g_pose of body, friction and contact terms: lam^T g = (J lam) . g_pose.
        # dg/dtheta at fixed q*: autograd through the closed-form body and friction gradients; for the contact term,
        # the contact Hessian's cross blocks with the pose components that depend on theta (those the map does not
        # move, and the links hung from a fixed-base robot's joint-less root), times their derivatives. Where J
        # itself depends on theta (a hung robot's Jacobian turns with its root's row), (dJ/dtheta)^T g_pose too:
        # J lam is then formed in the graph, and the contact gradient at q* enters as a constant.
        scene = ctx.scene
        q, H, cross, rows6, q_t, q_p, force, torque, target, mass, S, mu_f, ctrl, kp, kv, r_free, contact_grad = (
            ctx.saved_tensors
        )  # fmt: skip
        # q is this Function's output: unpacked, it carries this node as its grad_fn, and a graph built from it
        # would reach the whole rollout behind it, which autograd.grad below would walk at every step (a 200-step
        # rollout's backward took 4x longer than 200 times one step's)
        q = q.detach()
        B, N = q_t.shape[:2]
        kin = scene.kinematics
        dyn = kin.bodies.to(q.device)
        Nd = len(dyn)
        chol, info = torch.linalg.cholesky_ex(H)
        if bool((info != 0).any()):  # cannot happen: Newton converges only at a positive definite Hessian
            raise RuntimeError("cfd_torch.step backward: the step's Hessian is not positive definite")
        lam = torch.cholesky_solve(gout.to(H.dtype)[:, :, None], chol)[:, :, 0]
        inputs = (q_t, q_p, force, torque, target, mass, S, mu_f, ctrl, kp, kv)
        with torch.enable_grad():
            th = [x.detach().requires_grad_(True) for x in inputs]
            tq_t, tq_p, tf, ttau, ttarget, tmass, tS, tmu, tctrl, tkp, tkv = th
            fixed = end_poses(scene, tq_t, ttarget)
            poses_next = kin.poses(q, fixed)
            # J lam and the moving bodies' poses depend on the inputs (through the fixed poses) only for links hung
            # from a joint-less root: elsewhere they are constants (no graph to build and walk)
            hung = contact_grad is not None
            Jlam = kin.push(q, lam, fixed if hung else fixed.detach())  # (B, N, 6)
            moving = poses_next[:, dyn] if hung else poses_next[:, dyn].detach()
            gravity = torch.tensor(scene.gravity, dtype=q.dtype, device=q.device)
            rows = lambda x: x.reshape(B * Nd, *x.shape[2:])  # noqa: E731
            pred = _predicted(scene, tq_t, tq_p, fixed, tmass, tS, r_free)
            _, g_b, _ = body_terms(
                rows(moving), rows(tq_t[:, dyn]), rows(tq_p[:, dyn]), rows(pred.rotation),
                rows(tf[:, dyn]), rows(ttau[:, dyn]), tmass.reshape(-1), rows(tS), gravity, scene.dt, 1,
                None if pred.shift is None else rows(pred.shift),
            )  # fmt: skip
            s = (g_b.reshape(B, Nd, 6) * Jlam[:, dyn]).sum()
            joint = _joint_inputs(scene, pred, tctrl, tkp, tkv)
            if joint is not None:
                _, g_j, _, _ = kin.joint_terms(q, joint, scene.dt, 1)
                s = s + (g_j * lam).sum()
            if ctx.friction_on is not None:
                lagged = _lagged(scene, tq_t, ctx.friction_on, create_graph=True)
                cp = scene_pairs(scene, B).to(q.device)[lagged.pair]
                frows = cp[:, :1] * N + cp[:, 1:]
                _, gf, _ = friction_terms(
                    lagged,
                    poses_next.reshape(B * N, 6),
                    frows,
                    tmu[cp[:, 0]],
                    scene.friction.eps_v * scene.dt,
                    1,
                )
                Gf, _ = sum_pairs(B, N, cp, gf, None)
                s = s + (Gf * Jlam).sum()
            # contact: lam^T J^T H_c d(pose)/dtheta over the pose components rows6 that depend on theta
            c = (cross @ Jlam.detach().reshape(B, 6 * N, 1))[:, :, 0]  # (B, F)
            s = s + (c * poses_next.reshape(B, 6 * N)[:, rows6]).sum()
            if hung:  # and lam^T (dJ/dtheta)^T g_contact
                s = s + (contact_grad * Jlam).sum()
            grads = torch.autograd.grad(-s, th, allow_unused=True)
        out = [None if gth is None else gth.to(x.dtype) for gth, x in zip(grads, inputs, strict=True)]
        return (None, *out)
