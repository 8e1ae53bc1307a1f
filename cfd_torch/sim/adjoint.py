"""One step as an autograd Function: the forward solves, the backward is one adjoint solve per scene.

q* solves g(q*, theta) = dL/dq = 0, so dq*/dtheta = -H^-1 d2L/(dq dtheta) (implicit function theorem). The backward
does one linear solve H lam = grad_out with the Hessian of the converged iterate (positive definite: Newton stops
only there) and one vector-Jacobian product -lam^T d2L/(dq dtheta) for theta = previous states, actions (forces,
torques, kinematic targets), masses, second moments and the friction coefficient. Reverse mode through a rollout is
ordinary autograd chaining of these steps.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

import torch

from ..contact.pair import PairSolveError
from .energy import StepProblem, body_terms, scatter_pairs, scene_pairs
from .feasibility import solve_step
from .friction import friction_terms
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


def _lagged(scene, q_t: torch.Tensor, create_graph: bool = False):
    """The lagged friction contacts of the batch's pairs at the start-of-step poses q_t (B, N, 6)."""
    pairs = scene_pairs(scene, q_t.shape[0]).to(q_t.device)
    return scene.contact_model.lagged(q_t, pairs, scene.friction.active, create_graph=create_graph)


class StepFn(torch.autograd.Function):
    """(scene, q_t, q_p, force, torque, target, mass, S, mu_f) -> q* (B, Q) and, not differentiable, the solver's
    statistics: Newton iterations (B,), contact and friction forces (B, N, 6), friction contacts (B,), counts (3,)
    (contact evaluations, node pairs, leaf pairs) and the forward's wall time (1,)."""

    @staticmethod
    def forward(ctx, scene, q_t, q_p, force, torque, target, mass, S, mu_f):
        t0 = time.perf_counter()
        with _serial_torch():
            fixed = q_t.clone()
            if len(scene.kinematic):
                fixed[:, scene.kinematic.to(q_t.device)] = target
            lagged = None
            # friction off costs nothing, unless its coefficient needs a gradient (at mu_f = 0 the term is zero but
            # its derivative is not)
            if bool((mu_f > 0).any()) or ctx.needs_input_grad[8]:
                lagged = _lagged(scene, q_t)
            gravity = torch.tensor(scene.gravity, dtype=q_t.dtype, device=q_t.device)
            prob = StepProblem(scene, fixed, q_t, q_p, force, torque, mass, S, mu_f, lagged, gravity)
            tally = [0, 0, 0]
            try:
                res = solve_step(prob, tally)
            except PairSolveError as err:  # a leaf pair's plane solve at some trial point: the step failed
                raise StepError(f"the step failed: {err}") from err
        ctx.scene, ctx.friction = scene, lagged is not None
        ctx.save_for_backward(
            res.q, res.hess, res.contact_hess, q_t, q_p, force, torque, target, mass, S, mu_f
        )
        B = q_t.shape[0]
        if lagged is None:
            n_fc = torch.zeros(B, dtype=torch.long, device=q_t.device)
        else:
            P = scene.pairs.shape[0]
            n_fc = torch.bincount(lagged.pair // max(P, 1), minlength=B)
        stats = torch.tensor(tally, dtype=torch.long)
        extras = (res.iters, res.contact_force, res.friction_force, n_fc, stats)
        ctx.mark_non_differentiable(*extras)
        seconds = torch.tensor([time.perf_counter() - t0], dtype=torch.float64)
        ctx.mark_non_differentiable(seconds)
        return (res.q, *extras, seconds)

    @staticmethod
    def backward(ctx, gout, *_):
        if torch.is_grad_enabled():  # create_graph=True
            raise RuntimeError(
                "cfd_torch.step: second derivatives through a simulation step are not implemented (the step's "
                "backward is a first-order adjoint); do not use create_graph=True through step()"
            )
        with _serial_torch():
            return StepFn._backward(ctx, gout)

    @staticmethod
    def _backward(ctx, gout):
        # lam = H^-1 v (H symmetric positive definite), dtheta = -lam^T dg/dtheta, with g = J^T g_pose(theta) for
        # the pose-space gradient g_pose of body, friction and contact terms: lam^T g = (J lam) . g_pose.
        # dg/dtheta: autograd through the closed-form body and friction gradients (functions of theta at fixed q*),
        # and, for the contact term, the cross blocks of the contact Hessian with the poses the map does not move.
        scene = ctx.scene
        q, H, Hc, q_t, q_p, force, torque, target, mass, S, mu_f = ctx.saved_tensors
        B, N = q_t.shape[:2]
        dyn = scene.kinematics.bodies.to(q.device)
        Nd = len(dyn)
        chol, _ = torch.linalg.cholesky_ex(H)
        lam = torch.cholesky_solve(gout.to(H.dtype)[:, :, None], chol)[:, :, 0]
        Jlam = scene.kinematics.push(q, lam)  # (B, N, 6)
        with torch.enable_grad():
            th = [x.detach().requires_grad_(True) for x in (q_t, q_p, force, torque, target, mass, S, mu_f)]
            tq_t, tq_p, tf, ttau, ttarget, tmass, tS, tmu = th
            fixed = tq_t.clone()
            if len(scene.kinematic):
                fixed[:, scene.kinematic.to(q.device)] = ttarget
            poses_next = scene.kinematics.poses(q, fixed)
            gravity = torch.tensor(scene.gravity, dtype=q.dtype, device=q.device)
            rows = lambda x: x.reshape(B * Nd, *x.shape[2:])  # noqa: E731
            _, g_b, _ = body_terms(
                rows(poses_next[:, dyn].detach()), rows(tq_t[:, dyn]), rows(tq_p[:, dyn]), rows(tf[:, dyn]),
                rows(ttau[:, dyn]), tmass.reshape(-1), rows(tS), gravity, scene.dt, 1,
            )  # fmt: skip
            s = (g_b.reshape(B, Nd, 6) * Jlam[:, dyn]).sum()
            if ctx.friction:
                lagged = _lagged(scene, tq_t, create_graph=True)
                cp = scene_pairs(scene, B).to(q.device)[lagged.pair]
                frows = cp[:, :1] * N + cp[:, 1:]
                _, gf, _ = friction_terms(
                    lagged, poses_next.reshape(B * N, 6), frows, tmu[cp[:, 0]], scene.friction.eps_v * scene.dt, 1,
                    reduce=False,
                )  # fmt: skip
                Gf, _ = scatter_pairs(B, N, cp, gf, None)
                s = s + (Gf * Jlam).sum()
            # contact: d(g)/d(pose_j) for a pose the map does not move is the cross block of the contact Hessian
            cross = (Hc @ Jlam.reshape(B, 6 * N, 1)).reshape(B, N, 6)
            s = s + (cross.detach() * poses_next).sum()
            grads = torch.autograd.grad(-s, th, allow_unused=True)
        out = [
            None if gth is None else gth.to(x.dtype)
            for gth, x in zip(grads, (q_t, q_p, force, torque, target, mass, S, mu_f), strict=True)
        ]
        return (None, *out)
