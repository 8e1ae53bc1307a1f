"""The incremental potential of one step, evaluated purely: everything the Newton solve needs, returned.

For the step's unknowns q (the kinematics map's coordinates; for free bodies the dynamic bodies' poses), with all
other bodies at their end-of-step poses (static: fixed; kinematic: the action's target)::

    L(q) = sum_dynamic [ (m |b|^2 + tr(A S A^T)) / (2 dt^2)  - (m g + f) . (t - t_t)  - tau . log(R R_t^T) ]
           + P_contact(poses(q)) + D_friction(poses(q); lagged at q_t)

with b = t - 2 t_t + t_{t-1} - t_shift, A = R - R_pred, S the body's second moment of mass (:mod:`.bodies`), f and
tau the action's world-frame force and torque (log(R R_t^T) is the rotation vector of the step's rotation increment,
so tau does the work tau . dtheta; axial(R R_t^T), its sine times the axis, would weaken the torque by cos(dtheta)
and reverse it beyond a quarter turn per step). Its stationarity is implicit Euler for rigid bodies with exact
volumetric inertia: the inertia term is 1/2 int rho |x(q) - x_pred|^2 dV for the material points' predicted
positions, x_pred = R_pred X + 2 t_t - t_{t-1}: constant linear velocity, and the torque-free rotation of the
discrete rigid body (:func:`predicted_rotation`; in planar scenes, constant angular velocity about z,
R_t R_{t-1}^T R_t); an articulated link's prediction comes from its joints (t_shift and R_pred of
:meth:`~cfd_torch.sim.articulation.ArticulatedKinematics.predict`; t_shift is zero for free bodies). SPEC's x-space
form, x_pred = 2 x_t - x_{t-1} (A = R - 2 R_t + R_{t-1}), predicts a point off the rotation group and
damps spin by about omega^3 dt^2 per step.

A batch of B independent scenes is one evaluation: their body pairs go to the contact model together (no pair
between two scenes exists, not even in the far field), and every output has a leading scene dimension.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from .._autograd import tracked
from ..contact.model import LaggedContacts, sum_pairs
from ..rotation import angle_factors, rotation_derivatives, rotation_matrix
from .friction import friction_by_pair
from .types import StepError

__all__ = [
    "StepProblem",
    "JointInputs",
    "EnergyEval",
    "BatchRows",
    "batch_rows",
    "incremental_potential",
    "select_scenes",
    "body_terms",
    "predicted_rotation",
    "scene_pairs",
    "end_poses",
]


class StepProblem(NamedTuple):
    """The fixed data of one step of B scenes (float64, detached).

    Attributes:
        scene: the :class:`cfd_torch.Scene` (shared by the batch).
        fixed: (B, N, 6) end-of-step poses of the bodies the kinematics map does not move (its rows are ignored).
        q_t, q_p: (B, N, 6) poses at the start of the step and one step earlier.
        force, torque: (B, N, 3) the action's world-frame forces and torques.
        mass: (B, Nd); second_moment: (B, Nd, 3, 3) symmetric; friction: (B,) Coulomb's coefficient.
        friction_on: (B,) bool, the scenes with friction terms (a positive coefficient, or one whose gradient is
            asked for).
        lagged: the lagged friction contacts of the batch's pairs (``scene_pairs(scene, B)``) in the scenes with
            friction, or None when none has.
        gravity: (3,).
        joint: the joint-space inputs of scenes with articulations (:class:`JointInputs`), else None.
        r_pred: (B, Nd, 3, 3) each moving body's predicted orientation (:func:`predicted_rotation`; an articulated
            link's: :meth:`~cfd_torch.sim.articulation.ArticulatedKinematics.predict`, a rotation to first order).
        t_shift: (B, Nd, 3) each moving body's predicted centre of mass minus the constant-velocity one, 2 t_t -
            t_{t-1} (zero for free bodies), or None for zero.
    """

    scene: object
    fixed: torch.Tensor
    q_t: torch.Tensor
    q_p: torch.Tensor
    force: torch.Tensor
    torque: torch.Tensor
    mass: torch.Tensor
    second_moment: torch.Tensor
    friction: torch.Tensor
    friction_on: torch.Tensor
    lagged: LaggedContacts | None
    gravity: torch.Tensor
    joint: JointInputs | None = None
    r_pred: torch.Tensor | None = None
    t_shift: torch.Tensor | None = None


class JointInputs(NamedTuple):
    """The coordinates one and two steps earlier (B, Q) and the actuators' terms (:meth:`ArticulatedKinematics
    .drive`): per joint (B, J) the motors' torque and the servos' stiffness and damping, per actuator (B, U) each
    servo's gain and target."""

    q_t: torch.Tensor
    q_p: torch.Tensor
    torque: torch.Tensor
    stiffness: torch.Tensor
    damping: torch.Tensor
    servo_gain: torch.Tensor
    servo_target: torch.Tensor


class EnergyEval(NamedTuple):
    """L and what the solver needs of it, for A scenes (derivative fields None below the order asked for).

    Attributes:
        value: (A,) L, +inf where some pair is infeasible.
        grad: (A, Q) dL/dq.
        hess: (A, Q, Q) d2L/dq2 (exact; friction's exact Hessian).
        contact_hess: (A, 6N, 6N) the contact Hessian over all bodies' poses (its cross blocks with the bodies the
            map does not move feed the adjoint; an evaluation with ``moving_hessian`` may leave them zero).
        scale: (A,) the magnitude L is computed from (|L| plus each body's own terms and the contact and friction
            terms it takes part in): the line search treats differences below 1e-12 of it as rounding.
        majorizer_gap: (A, Q, Q) friction's quadratic majorizer minus its exact Hessian (positive semi-definite),
            or None without friction.
        h_floor: (A,) a tenth of the smallest eigenvalue of the moving bodies' inertia Hessians (pose space: the
            coordinates' own for free bodies): the saddle-free direction's floor on eigenvalue magnitudes.
        contact_force, friction_force: (A, N, 6) -dP/dpose and -dD/dpose.
        node_pairs, leaf_pairs: the contact model's work in this evaluation.
        body_value: (A, M) each moving body's own terms (inertia, gravity, actuation), or None (an energy
            without the split: the Newton solve then freezes no body).
        pair_value: (A, P) each interacting body pair's contact and friction terms (0 for pairs not evaluated).
        warm: the contact model's warm-start data of this evaluation (with ``scene_ids``), or None.
        barrier_value: (A,) the terms that are +inf somewhere: contact and friction (the sum of ``pair_value``) and
            joint limits; or None (an energy without them: Newton then takes no step within tol as barrier-limited).

    With ``active`` (a subset of the moving bodies), L is the sum of the terms that involve an active body (their
    own terms, and the pairs with at least one of them), and grad / hess are exact in the active bodies'
    coordinates only: the rest of L is constant while the other bodies stay put.
    """

    value: torch.Tensor
    grad: torch.Tensor | None
    hess: torch.Tensor | None
    contact_hess: torch.Tensor | None
    scale: torch.Tensor
    majorizer_gap: torch.Tensor | None
    h_floor: torch.Tensor | None
    contact_force: torch.Tensor | None
    friction_force: torch.Tensor | None
    node_pairs: int
    leaf_pairs: int
    body_value: torch.Tensor | None = None
    pair_value: torch.Tensor | None = None
    warm: object | None = None
    barrier_value: torch.Tensor | None = None


class BatchRows(NamedTuple):
    """What every evaluation of one :class:`StepProblem` reads of it the same way (:func:`batch_rows`; a Newton
    solve evaluates it some twenty times).

    Attributes:
        dyn: (Nd,) the moving bodies.
        pairs: (B P, 3) the batch's interacting body pairs (:func:`scene_pairs`).
        pair_moving: (B P, 2) each pair's two bodies as moving-body indices (Nd for a body that does not move).
        body: the moving bodies' rows (B Nd, ...) of q_t, q_p, r_pred, force, torque, mass, second_moment and
            t_shift (None for None), as :func:`body_terms` takes them.
        contact_rows, contact_friction: per lagged friction contact, its bodies' rows (C, 2) of the (B N, 6) poses
            and its scene's coefficient (C,); None without.
    """

    dyn: torch.Tensor
    pairs: torch.Tensor
    pair_moving: torch.Tensor
    body: tuple[torch.Tensor | None, ...]
    contact_rows: torch.Tensor | None
    contact_friction: torch.Tensor | None


def batch_rows(prob: StepProblem, device: torch.device) -> BatchRows:
    """The :class:`BatchRows` of ``prob`` on ``device`` (the device of the coordinates it is evaluated at)."""
    scene = prob.scene
    B, N = prob.q_t.shape[:2]
    dyn = scene.kinematics.bodies.to(device)
    Nd = len(dyn)
    pairs = scene_pairs(scene, B).to(device)
    moving = torch.full((N,), Nd, dtype=torch.long, device=device)
    moving[dyn] = torch.arange(Nd, device=device)
    rows = lambda x: None if x is None else x.reshape(B * Nd, *x.shape[2:])  # noqa: E731
    body = (
        rows(prob.q_t[:, dyn]), rows(prob.q_p[:, dyn]), rows(prob.r_pred), rows(prob.force[:, dyn]),
        rows(prob.torque[:, dyn]), rows(prob.mass[:, :, None])[:, 0], rows(prob.second_moment), rows(prob.t_shift),
    )  # fmt: skip
    frows = mu = None
    if prob.lagged is not None:
        cc = pairs[prob.lagged.pair]  # (C, 3) each contact's scene and bodies
        frows = cc[:, :1] * N + cc[:, 1:]
        mu = prob.friction[cc[:, 0]]
    return BatchRows(dyn, pairs, moving[pairs[:, 1:]], body, frows, mu)


def scene_pairs(scene, num_scenes: int) -> torch.Tensor:
    """(num_scenes P, 3) rows (s, i, j): the scene's interacting body pairs, repeated for each pose set s."""
    P = scene.pairs.shape[0]
    s = torch.arange(num_scenes).repeat_interleave(P)
    return torch.cat([s[:, None], scene.pairs.repeat(num_scenes, 1)], 1)


def end_poses(scene, q_t: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, N, 6) the end-of-step poses of the bodies the step does not solve for: the start poses q_t (B, N, 6),
    kinematic rows at their targets (B, K, 6) (differentiable in both)."""
    if len(scene.kinematic) == 0:
        return q_t
    kin = scene.kinematic.to(q_t.device)
    mask = torch.zeros(scene.num_bodies, 1, dtype=torch.bool, device=q_t.device)
    mask[kin] = True
    rows = torch.zeros_like(q_t).index_add(1, kin, target)
    return torch.where(mask, rows, q_t)


def select_scenes(prob: StepProblem, idx: torch.Tensor) -> StepProblem:
    """The sub-problem of the scenes ``idx`` (A,) (lagged contacts renumbered)."""
    lag = prob.lagged
    if lag is not None:
        P = prob.scene.pairs.shape[0]
        pos = torch.full((prob.q_t.shape[0],), -1, dtype=torch.long, device=idx.device)
        pos[idx] = torch.arange(len(idx), device=idx.device)
        s = pos[lag.pair // P] if P else lag.pair
        keep = s >= 0
        lag = LaggedContacts(
            (s * P + lag.pair % P)[keep],
            lag.X[keep],
            lag.x_t[keep],
            lag.tangent[keep],
            lag.normal_force[keep],
        )
    take = (
        prob.fixed,
        prob.q_t,
        prob.q_p,
        prob.force,
        prob.torque,
        prob.mass,
        prob.second_moment,
        prob.friction,
        prob.friction_on,
    )
    joint = None if prob.joint is None else JointInputs(*(x[idx] for x in prob.joint))
    shift = None if prob.t_shift is None else prob.t_shift[idx]
    return StepProblem(prob.scene, *(x[idx] for x in take), lag, prob.gravity, joint, prob.r_pred[idx], shift)


def _axial(M: torch.Tensor) -> torch.Tensor:
    """(..., 3) axial vector of the skew part of (..., 3, 3) M (last two dims)."""
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    )


# the Newton solve of the discrete rigid body's equation: iterations, and its tolerance on the residual relative to
# tr(S), in units of the dtype's epsilon
_MV_ITERS = 50
_MV_TOL = 64.0
# hat matrices of the unit vectors: _HATS[k] v = e_k x v
_HATS = torch.tensor(
    [
        [[0, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 0]],
    ],
    dtype=torch.float64,
)


def _mv_residual(F, S, M):
    """The residual axial(F S - S F^T - M) (E, 3) of the discrete rigid body's equation at F (E, 3, 3), and its
    Jacobian (E, 3, 3) along right perturbations F exp(d^)."""
    FS = F @ S
    r = _axial(FS - FS.transpose(1, 2) - M)
    Y = F[:, None] @ _HATS.to(F) @ S[:, None]
    Y = Y - Y.transpose(2, 3)  # (E, 3, 3, 3): d(F S - S F^T) along d_k
    return r, _axial(Y).transpose(1, 2)


class FreeRotationError(StepError):
    """:func:`predicted_rotation` found no free rotation for the body in row ``row`` of its inputs (None when the
    error was raised again with more context). Built as any exception, from its message: ``type(err)(message)``
    and pickling keep working."""

    def __init__(self, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.row = row

    def __reduce__(self):
        return type(self), (str(self), self.row)


def free_rotation_message(where: str = "") -> str:
    """The message of a :class:`FreeRotationError` (``where``: the body, and the scene in a batch)."""
    return (
        f"the free rotation of a body{where} over the step (the discrete rigid body's equation) has no solution "
        "Newton's method finds: the body turns more than about pi / 2 rad per step; reduce dt"
    )


def predicted_rotation(
    q_t: torch.Tensor,
    q_p: torch.Tensor,
    S: torch.Tensor,
    gyroscopic: bool = True,
    solved: torch.Tensor | None = None,
) -> torch.Tensor:
    """(E, 3, 3) the rotation each of E bodies (poses (E, 6) now and a step earlier, second moments S (E, 3, 3))
    reaches at the end of the step if no force acts: R_t F, with F the body-frame increment of the Moser-Veselov
    discrete rigid body, F S - S F^T = S F0 - F0^T S (F0 = R_{t-1}^T R_t, the previous step's increment), which
    carries the gyroscopic torque (I omega) x omega (I = tr(S) 1 - S) and conserves angular momentum. The inertia
    term 1/2 |(R - R_pred) S^(1/2)|^2 / dt^2 is smallest at this prediction, so a free body follows the discrete
    rigid body exactly. For an isotropic S (a sphere, a cube) F = F0: the constant-velocity prediction
    R_t R_{t-1}^T R_t, to the last bit.

    Solved by Newton's method from F = F0 (updates F exp(d^)); differentiable by autograd (one Newton step from the
    converged F carries the implicit function's first derivatives). A :class:`FreeRotationError` (a StepError)
    naming the first input row that does not converge (a body turning more than about pi / 2 rad per step).
    ``gyroscopic=False`` (planar scenes, whose bodies turn about z only: the constraint takes the gyroscopic torque,
    and a constant rate about z is exact): F = F0. ``solved``: this function's
    result for the same inputs, computed before (the step's backward reuses its forward's): the iterations start
    there and end at once."""
    Rt, Rp = rotation_matrix(q_t[:, 3:]), rotation_matrix(q_p[:, 3:])
    base = Rt @ Rp.transpose(1, 2) @ Rt
    if not gyroscopic:
        return base
    F0 = Rp.transpose(1, 2) @ Rt
    M = S @ F0 - F0.transpose(1, 2) @ S
    trace = S.diagonal(dim1=1, dim2=2).sum(1).detach()
    tol = _MV_TOL * torch.finfo(S.dtype).eps * trace
    F = F0.detach() if solved is None else Rt.detach().transpose(1, 2) @ solved.detach()
    moved = torch.full((F.shape[0],), solved is not None, dtype=torch.bool, device=F.device)
    with torch.no_grad():
        Sd, Md = S.detach(), M.detach()
        bad = torch.zeros_like(moved)  # bodies whose Newton iterations found no root (a singular Jacobian)
        for _ in range(_MV_ITERS):
            r, jac = _mv_residual(F, Sd, Md)
            off = (r.abs().amax(1) > tol) & ~bad
            if not bool(off.any()):
                break
            moved = moved | off
            d, info = torch.linalg.solve_ex(jac, r)
            bad = bad | (off & (info != 0))
            F = F @ rotation_matrix(-torch.where((off & ~bad)[:, None], d, torch.zeros_like(d)))
        else:
            bad = bad | (_mv_residual(F, Sd, Md)[0].abs().amax(1) > tol)
        # the discrete rigid body conserves tr(F S) (its kinetic energy): the equation has other roots beyond about
        # pi / 2 rad of turn per step, where Newton can land
        drift = ((F - F0.detach()) * Sd.transpose(1, 2)).sum((1, 2))  # tr((F - F0) S)
        bad = bad | ~(drift.abs() <= 1e-9 * trace)
        if bool(bad.any()):
            raise FreeRotationError(free_rotation_message(), int(torch.nonzero(bad)[0, 0]))
    if any(tracked(x) for x in (q_t, q_p, S)):  # one more step, differentiable, from the converged F
        r, jac = _mv_residual(F, S, M)
        return Rt @ (F @ rotation_matrix(-torch.linalg.solve(jac, r)))
    if not bool(moved.any()):
        return base
    return torch.where(moved[:, None, None], Rt @ F, base)


def _numba_body_terms(*xs) -> bool:
    """Whether :func:`body_terms` can run as its numba kernel: CPU float64 tensors, none of them tracked (a graph to
    record, a torch.func transform or a forward-mode tangent: ``_autograd.tracked``)."""
    ts = [x for x in xs if isinstance(x, torch.Tensor)]
    if not all(x.device.type == "cpu" and x.dtype == torch.float64 for x in ts):
        return False
    return not any(tracked(x) for x in ts)


def body_terms(q, q_t, q_p, r_pred, force, torque, mass, S, gravity, dt, order, t_shift=None):
    """Inertia, gravity and actuation of E dynamic bodies (pose rows (E, 6)): values (E,), grad (E, 6), Hessian
    (E, 6, 6). ``r_pred`` (E, 3, 3): the predicted rotations (:func:`predicted_rotation`); ``t_shift`` (E, 3): the
    predicted centres of mass minus 2 t_t - t_{t-1} (None: zero).

    Differentiable (by autograd) in everything but q, which the adjoint needs for d2L / dq dtheta.

    E is a handful of bodies, so the cost is the number of tensor ops: R and its derivatives go through the
    products they share as one stack of 3 x 3 matrices Rk = [R, dR_k (k = 0..2), d2R_kl (kl = 00..22)] (up to the
    order), each product summing in the same order as the per-term products would. On the CPU in float64 without
    a graph to record, one numba loop (``_body_numba``) computes the same.
    """
    E = q.shape[0]
    if t_shift is None:
        t_shift = q.new_zeros(E, 3)
    if _numba_body_terms(q, q_t, q_p, r_pred, force, torque, mass, S, gravity, t_shift):
        from ._body_numba import body_terms_kernel

        value = q.new_empty(E)
        grad = q.new_empty(E if order >= 1 else 0, 6)
        hess = q.new_empty(E if order >= 2 else 0, 6, 6)
        g = gravity.numpy() if isinstance(gravity, torch.Tensor) else np.asarray(gravity, dtype=np.float64)
        body_terms_kernel(
            q.contiguous().numpy(), q_t.contiguous().numpy(), q_p.contiguous().numpy(), r_pred.contiguous().numpy(),
            t_shift.contiguous().numpy(), force.contiguous().numpy(),
            torque.contiguous().numpy(), mass.contiguous().numpy(), S.contiguous().numpy(), g, float(dt), order,
            value.numpy(), grad.numpy(), hess.numpy(),
        )  # fmt: skip
        return value, (grad if order >= 1 else None), (hess if order >= 2 else None)
    R, dR, d2R = rotation_derivatives(q[:, 3:], order)
    Rt = rotation_matrix(q_t[:, 3:])
    b = q[:, :3] - 2.0 * q_t[:, :3] + q_p[:, :3] - t_shift
    A = R - r_pred
    AS = A @ S  # (E, 3, 3)
    pull = mass[:, None] * gravity + force  # (E, 3)
    inv = 1.0 / (dt * dt)
    Rk = R  # (E, 3 K, 3): the K matrices stacked
    if order >= 1:
        Rk = [R, dR.permute(0, 3, 1, 2).reshape(E, 9, 3)]
        Rk = torch.cat(Rk + ([d2R.permute(0, 3, 4, 1, 2).reshape(E, 27, 3)] if order >= 2 else []), 1)
    K = Rk.shape[1] // 3
    # The torque's work over the step, tau . log(R R_t^T) = f(c) a with a = tau . axial(R R_t^T) and c = (tr(R R_t^T)
    # - 1) / 2 (:func:`angle_factors`), and its derivatives by the chain rule through a and c, both linear in R: a_k,
    # c_k of dR_k R_t^T and a_kl, c_kl of d2R_kl R_t^T
    P = (Rk @ Rt.transpose(1, 2)).view(E, K, 3, 3)
    a = (torque[:, None] * _axial(P)).sum(-1)  # (E, K)
    c = 0.5 * torch.diagonal(P, dim1=2, dim2=3).sum(-1)  # (E, K)
    f0, f1, f2 = angle_factors(c[:, 0] - 0.5)
    value = 0.5 * inv * (mass * (b * b).sum(1) + (AS * A).sum((1, 2)))
    value = value - (pull * (q[:, :3] - q_t[:, :3])).sum(1) - f0 * a[:, 0]
    if order == 0:
        return value, None, None
    # d/d omega of tr(A S A^T) / 2 and its second derivatives' d2R part: sum_ij (A S)_ij (dR_k, d2R_kl)_ij
    dAS = (AS.reshape(E, 1, 9) @ Rk[:, 3:].reshape(E, K - 1, 9).transpose(1, 2))[:, 0]  # (E, K - 1)
    g_t = inv * mass[:, None] * b - pull
    a0, ak, ck = a[:, :1], a[:, 1:4], c[:, 1:4]
    g_w = inv * dAS[:, :3] - (f1[:, None] * ck * a0 + f0[:, None] * ak)
    grad = torch.cat([g_t, g_w], 1)
    if order == 1:
        return value, grad, None
    H = q.new_zeros(E, 6, 6)
    H[:, :3, :3] = inv * mass[:, None, None] * torch.eye(3, dtype=q.dtype, device=q.device)
    H_ww = dAS[:, 3:].view(E, 3, 3) + torch.einsum("nijk,njm,niml->nkl", dR, S, dR)
    akl, ckl = a[:, 4:].view(E, 3, 3), c[:, 4:].view(E, 3, 3)
    cc = ck[:, :, None] * ck[:, None, :]
    ca = ck[:, :, None] * ak[:, None, :]
    W_ww = f2[:, None, None] * cc * a0[:, :, None] + f1[:, None, None] * (
        ckl * a0[:, :, None] + ca + ca.transpose(1, 2)
    )
    H[:, 3:, 3:] = inv * H_ww - (W_ww + f0[:, None, None] * akl)
    return value, grad, H


def incremental_potential(
    prob: StepProblem,
    q: torch.Tensor,
    order: int,
    active: torch.Tensor | None = None,
    scene_ids: torch.Tensor | None = None,
    warm: object | None = None,
    batch: BatchRows | None = None,
    moving_hessian: bool = False,
) -> EnergyEval:
    """L of every scene of ``prob`` at q (B, Q), with derivatives up to ``order`` (0, 1 or 2); with ``active``
    (B, M) bool over the moving bodies, only the terms that involve an active body (see :class:`EnergyEval`).
    ``scene_ids`` (B,) name the scenes stably across calls (their pairs' ids for the contact model's warm start,
    ``warm`` from an earlier evaluation of the same step). ``batch``: ``batch_rows(prob, q.device)``, when the
    caller evaluates ``prob`` many times (default: computed here). ``moving_hessian``: the contact model may leave
    out the blocks of ``contact_hess`` of the bodies that do not move (``ContactModel.partial_hessian``); ``hess``
    is the same either way."""
    scene = prob.scene
    B, N = prob.q_t.shape[:2]
    c = batch_rows(prob, q.device) if batch is None else batch
    dyn = c.dyn  # the moving bodies: inertia, gravity, actuation
    Nd = len(dyn)
    kin = scene.kinematics
    poses = kin.poses(q, prob.fixed)  # (B, N, 6)
    q_t, q_p, r_pred, force, torque, mass, S, t_shift = c.body
    vb, g_b, h_b = body_terms(
        poses[:, dyn].reshape(B * Nd, 6), q_t, q_p, r_pred, force, torque, mass, S, prob.gravity, scene.dt, order,
        t_shift,
    )  # fmt: skip
    # each body's "local" energy: its own terms plus the contact and friction terms it takes part in (the sum of
    # their magnitudes sets the line search's rounding scale)
    body_value = vb.reshape(B, Nd)
    if active is not None:
        vb = torch.where(active.reshape(-1), vb, torch.zeros_like(vb))
    local = q.new_zeros(B, N)
    local[:, dyn] = vb.reshape(B, Nd)
    value = vb.reshape(B, Nd).sum(1)
    pairs = c.pairs
    P = scene.pairs.shape[0]
    pair_value = q.new_zeros(B * P)
    on = None  # (B P,) the pairs evaluated: all, or those with an active body
    if active is not None and P:
        act = torch.cat([active, active.new_zeros(B, 1)], 1)  # column Nd: "not a moving body"
        on = act[pairs[:, 0], c.pair_moving[:, 0]] | act[pairs[:, 0], c.pair_moving[:, 1]]
    G = Hc = ce = None
    node_pairs = leaf_pairs = 0
    if pairs.shape[0]:
        sel = pairs if on is None else pairs[on]
        kw = {}
        if moving_hessian and order >= 2 and getattr(scene.contact_model, "partial_hessian", False):
            moves = c.pair_moving < Nd
            kw["hessian_of"] = moves if on is None else moves[on]
        if scene_ids is None or not getattr(scene.contact_model, "warm_start", False):
            ce = scene.contact_model.evaluate(poses, sel, order, **kw)
        else:
            rows = torch.arange(pairs.shape[0], device=q.device)
            rows = rows if on is None else rows[on]
            ids = scene_ids.to(q.device)[rows // P] * P + rows % P
            ce = scene.contact_model.evaluate(poses, sel, order, ids=ids, warm=warm, **kw)
        node_pairs, leaf_pairs = ce.node_pairs, ce.leaf_pairs
        v = ce.value
        if on is None:
            pair_value = pair_value + v
        else:
            pair_value[on] = v
        local.index_put_((sel[:, 0], sel[:, 1]), v, accumulate=True)
        local.index_put_((sel[:, 0], sel[:, 2]), v, accumulate=True)
        if on is None:
            value = value + v.reshape(B, -1).sum(1)
        else:
            value = value + torch.zeros_like(value).index_add_(0, sel[:, 0], v)
        G, Hc = sum_pairs(B, N, sel, ce.grad, ce.hess)
    elif order:
        G = q.new_zeros(B, N, 6)
        Hc = q.new_zeros(B, 6 * N, 6 * N) if order > 1 else None
    Gf = Hf = gap = None
    lag = prob.lagged
    if lag is not None:
        fp, vf, gf, hf, *gap_c = friction_by_pair(
            lag, poses.reshape(B * N, 6), c.contact_rows, c.contact_friction, scene.friction.eps_v * scene.dt,
            order, majorizer_gap=order >= 2,
        )  # fmt: skip
        cp = pairs[fp]  # (F, 3) the body pairs with contacts, each one's terms summed over its contacts
        if on is not None:  # the contacts of pairs without an active body do not count
            vf = torch.where(on[fp], vf, torch.zeros_like(vf))
        pair_value = pair_value.index_add(0, fp, vf)
        local.index_put_((cp[:, 0], cp[:, 1]), vf, accumulate=True)
        local.index_put_((cp[:, 0], cp[:, 2]), vf, accumulate=True)
        value = value + torch.zeros_like(value).index_add_(0, cp[:, 0], vf)
        if order:
            Gf, Hf = sum_pairs(B, N, cp, gf, hf)
            if order >= 2:
                gap = sum_pairs(B, N, cp, None, gap_c[0])[1]
    jv = jg = jh = None
    pair_value = pair_value.reshape(B, P)
    barrier = pair_value.sum(1)
    if prob.joint is not None:
        jq = prob.joint
        jv, jg, jh, jl = kin.joint_terms(q, jq, scene.dt, order)
        value = value + jv
        barrier = barrier + jl
    scale = value.abs() + local.abs().sum(1) + (0.0 if jv is None else jv.abs())
    if order == 0:
        return EnergyEval(
            value, None, None, None, scale, None, None, None, None, node_pairs, leaf_pairs, body_value,
            pair_value, ce.warm if ce is not None else None, barrier,
        )  # fmt: skip
    Gp = G if Gf is None else G + Gf
    Hp = None
    if order >= 2:
        # the body terms' 6 x 6 blocks added on the diagonal in place (Hc stays the contacts' own)
        Hp = Hc.clone() if Hf is None else Hc + Hf
        Hp.view(B, N, 6, N, 6)[:, dyn, :, dyn, :] += h_b.reshape(B, Nd, 6, 6).transpose(0, 1)
    Gb = q.new_zeros(B, N, 6)
    Gb[:, dyn] = g_b.reshape(B, Nd, 6)
    # the gap majorizer and (for articulations) the inertia are pulled back with the same Jacobian
    extra = []
    if order >= 2 and gap is not None:
        extra.append(gap)
    if (
        order >= 2 and prob.joint is not None
    ):  # the inertia alone, pulled back on its own for the articulations
        Hb = q.new_zeros(B, N, 6, N, 6)
        Hb[:, dyn, :, dyn, :] = h_b.reshape(B, Nd, 6, 6).transpose(0, 1)
        extra.append(Hb.reshape(B, 6 * N, 6 * N))
    grad, hess, pulled = kin.pullback(q, Gb + Gp, Hp, prob.fixed, extra)
    if jg is not None:
        grad = grad + jg
        hess = None if hess is None else hess + jh
    h_floor = gap_q = None
    if order >= 2:
        if gap is not None:
            gap_q = pulled[0]
        if prob.joint is None:
            h_floor = 0.1 * torch.linalg.eigvalsh(h_b).reshape(B, -1).amin(1)
        else:  # the inertia of the coordinates themselves (links chained through the forward kinematics)
            h_floor = 0.1 * torch.linalg.eigvalsh(pulled[-1]).amin(1)
    return EnergyEval(
        value, grad, hess, Hc, scale, gap_q, h_floor, -G, -Gf if Gf is not None else torch.zeros_like(G),
        node_pairs, leaf_pairs, body_value, pair_value, ce.warm if ce is not None else None, barrier,
    )  # fmt: skip
