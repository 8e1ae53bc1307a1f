"""Differentiable rigid-body stepper: one step minimises the incremental potential (SPEC section 5).

For the dynamic bodies' generalised coordinates q (translation of the centre of mass, rotation vector), with all
other bodies at their end-of-step poses (static: fixed; kinematic: the action's target)::

    L(q) = sum_bodies [ (m |b|^2 + tr(A S A^T)) / (2 dt^2)  - (m g + f) . (t - t_t)  - tau . axial(R R_t^T) ]
           + P_contact(q) + D_friction(q; lagged at q_t)

with b = t - 2 t_t + t_{t-1}, A = R - R_t R_{t-1}^T R_t, S the body's second moment of mass (:mod:`rigid`), f and
tau the action's world-frame force and torque (axial(R R_t^T) is the rotation increment of the step, so tau does
the work tau . dtheta). Its stationarity is implicit Euler for rigid bodies with exact volumetric inertia: the
inertia term is 1/2 int rho |x(q) - x_pred|^2 dV for the material points' predicted positions under constant
linear and angular velocity (x_pred = R_t R_{t-1}^T R_t X + 2 t_t - t_{t-1}). SPEC's x-space form,
x_pred = 2 x_t - x_{t-1} (A = R - 2 R_t + R_{t-1}), predicts a point off the rotation group and damps spin by
about omega^3 dt^2 per step (10 rad/s fell to 5.8 rad/s in 1 s at dt = 0.01); the rotation-group prediction keeps
a spin about a principal axis exact and conserves the energy of torque-free tumbling.

Solver: Newton on the full Hessian (contact Hessians include the second-order rotation terms); where the Hessian is
not positive definite (second-order rotation terms of large contact forces: a rocking polyhedron, a tipping
stack) the saddle-free Newton direction (the Hessian's eigenvalues replaced by their magnitudes); then a
backtracking (Armijo) line search. Trial points where L is +inf (penetration within the margin) are rejected, so a
step never ends in penetration. Warm start: constant-velocity extrapolation (q_t if that is infeasible).
Converged when the undamped Newton step is at most ``newton_tol`` in every coordinate [m, rad] (at a positive
definite Hessian); a step that does not converge within ``max_newton_iter`` iterations raises :class:`StepError`.

Gradients: q* solves g(q*, theta) = dL/dq = 0, so dq*/dtheta = -H^-1 d2L/(dq dtheta) (implicit function theorem).
The backward of a step does one linear solve H lam = grad_out with the Hessian of the converged iterate and one
vector-Jacobian product -lam^T d2L/(dq dtheta) for theta = previous states, actions (forces, torques, kinematic
targets), masses, second moments and the friction coefficient.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import torch

from .contact._traverse import forest_of, penetrating, traverse
from .contact.mesh import _check_params
from .contact.scene import body_pairs, scatter_pair_derivatives
from .friction import LaggedFriction, friction_terms, lagged_friction
from .rotation import quaternion, quaternion_multiply, rotation_derivatives, rotation_matrix, rotation_vector
from .sim.bodies import RigidBody

__all__ = ["Scene", "State", "Action", "Params", "StepError", "step", "rollout", "recentre_rotation"]


@contextmanager
def _serial_torch():
    """Run torch's CPU ops of a step on one thread: its tensors are small (bodies, leaf pairs), and idle OpenMP
    workers spin-waiting between them cost 3-4x the step time on a loaded 2-core machine (measured); the contact
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


class StepError(RuntimeError):
    """A step's Newton solve did not converge, or its start was infeasible."""


@dataclass(frozen=True, eq=False)
class Scene:
    """Bodies and every physical and numerical parameter of a simulation (one config object).

    Attributes:
        bodies: the N bodies (:func:`cfd_torch.rigid_body`), in state order.
        dt: time step [s].
        gravity: (3,) gravitational acceleration [m/s^2].
        mu: contact coefficient (stiffness scale of the potential) [J].
        margin: delta, the minimum distance the barrier keeps between bodies [m].
        eps: relative width of the hierarchy's blend band.
        split: BSH split rule, "both" or "larger".
        friction: Coulomb coefficient mu_f; 0 turns friction off (no lagged data, no cost).
        friction_eps_v: slip velocity below which friction is in its smoothed static regime [m/s].
        friction_active: friction acts on the leaf pairs whose lagged normal force is at least this fraction of the
            largest in their body pair (0: on all of them). The others carry almost none of the load (a ball
            resting on a 12-triangle box: 6 of 3,583 leaf pairs carry all but 1.2e-6 of the normal force) and only
            cost time.
        exclude: body pairs (i, j) with no contact between them (e.g. joined bodies).
        newton_tol: convergence: the undamped Newton step is at most this in every coordinate [m, rad].
        max_newton_iter: Newton iterations before :class:`StepError` (the hardest steps of the stress sweep,
            scripts/stress_step.py, took 72).
        pair_tol, pair_max_iter: inner plane-solve settings of the exact leaf pairs.
        ccd_spacing: [m] no tunnelling: a move of the iterate (warm start, Newton trial) is accepted only if the
            straight path to it stays feasible at points at most this far apart (largest vertex displacement),
            and one Newton iteration moves no vertex more than 20 times this. Features thinner than about this
            (plus the margin) can still be jumped over in one move.
    """

    bodies: tuple[RigidBody, ...]
    dt: float = 0.01
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    mu: float = 1e-8
    margin: float = 1e-3
    eps: float = 0.01
    split: str = "both"
    friction: float = 0.0
    friction_eps_v: float = 1e-4
    friction_active: float = 1e-6
    exclude: tuple[tuple[int, int], ...] = field(default=())
    newton_tol: float = 1e-9
    max_newton_iter: int = 200
    pair_tol: float = 1e-12
    pair_max_iter: int = 100
    ccd_spacing: float = 0.01

    def __post_init__(self) -> None:
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "exclude", tuple(tuple(p) for p in self.exclude))
        if not self.bodies or not all(isinstance(b, RigidBody) for b in self.bodies):
            raise ValueError("bodies must be a non-empty sequence of RigidBody (see cfd_torch.rigid_body)")
        _check_params(self.mu, self.margin, self.eps, self.split)
        for name in ("dt", "newton_tol", "friction_eps_v", "pair_tol", "ccd_spacing"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < math.inf):
                raise ValueError(f"{name} must be a finite positive number, got {v!r}")
        if not (isinstance(self.friction, (int, float)) and 0 <= self.friction < math.inf):
            raise ValueError(f"friction must be a finite number >= 0, got {self.friction!r}")
        if not (isinstance(self.friction_active, (int, float)) and 0 <= self.friction_active < 1):
            raise ValueError(f"friction_active must be a number in [0, 1), got {self.friction_active!r}")
        if len(self.gravity) != 3 or not all(math.isfinite(float(x)) for x in self.gravity):
            raise ValueError(f"gravity must be 3 finite numbers, got {self.gravity!r}")
        if not any(b.kind == "dynamic" for b in self.bodies):
            raise ValueError("a scene needs at least one dynamic body")

    # ------------------------------------------------------------------ layout (computed once per scene)
    @property
    def num_bodies(self) -> int:
        return len(self.bodies)

    @cached_property
    def dynamic(self) -> torch.Tensor:
        """(Nd,) indices of the dynamic bodies."""
        return torch.tensor([i for i, b in enumerate(self.bodies) if b.kind == "dynamic"], dtype=torch.long)

    @cached_property
    def kinematic(self) -> torch.Tensor:
        """(K,) indices of the kinematic bodies (the order of ``Action.target``)."""
        return torch.tensor([i for i, b in enumerate(self.bodies) if b.kind == "kinematic"], dtype=torch.long)

    @cached_property
    def pairs(self) -> torch.Tensor:
        """(P, 2) body pairs with contact: at least one dynamic body, not excluded."""
        N = self.num_bodies
        fixed = torch.tensor([b.kind != "dynamic" for b in self.bodies])
        return body_pairs(N, fixed, self.exclude)

    @cached_property
    def _tables(self):
        uniq: dict[int, int] = {}
        for b in self.bodies:
            uniq.setdefault(id(b.bsh), len(uniq))
        bshes = tuple({id(b.bsh): b.bsh for b in self.bodies}.values())
        which = torch.tensor([uniq[id(b.bsh)] for b in self.bodies], dtype=torch.long)
        return bshes, which

    def _layout(self, device: torch.device):
        """Concatenated hierarchies (float64 forest), interacting body pairs (P, 2) and their root nodes (P, 2)."""
        bshes, which = self._tables
        forest = forest_of(bshes, torch.float64, device)
        pairs = self.pairs.to(device)
        return forest, pairs, forest.roots[which.to(device)[pairs]]

    def _lagged_friction(self, q_t: torch.Tensor, create_graph: bool = False) -> LaggedFriction:
        """Lagged friction data at the start-of-step poses ``q_t`` (N, 6), with this scene's contact settings."""
        forest, pairs, roots = self._layout(q_t.device)
        return lagged_friction(
            forest, pairs, roots, q_t, mu=self.mu, margin=self.margin, eps=self.eps, split=self.split,
            tol=self.pair_tol, max_iter=self.pair_max_iter, active=self.friction_active, create_graph=create_graph,
        )  # fmt: skip

    def params(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> Params:
        """The scene's differentiable physical parameters as tensors (set requires_grad for their gradients)."""
        d = self.dynamic.tolist()
        return Params(
            torch.tensor([self.bodies[i].mass for i in d], dtype=dtype, device=device),
            torch.stack([self.bodies[i].second_moment for i in d]).to(dtype=dtype, device=device),
            torch.tensor(float(self.friction), dtype=dtype, device=device),
        )

    def initial_state(self, poses: torch.Tensor, velocities: torch.Tensor | None = None) -> State:
        """State at rest (or moving with constant generalised ``velocities`` (N, 6)) at ``poses`` (N, 6)."""
        _check_state_tensor(poses, "poses", self.num_bodies)
        if velocities is None:
            return State(poses, poses.clone())
        _check_state_tensor(velocities, "velocities", self.num_bodies)
        v = velocities.clone()
        v[[i for i, b in enumerate(self.bodies) if b.kind != "dynamic"]] = 0.0
        return State(poses, poses - self.dt * v)


class State(NamedTuple):
    """Simulator state: poses (N, 6) [translation m, rotation vector rad] now and one step earlier."""

    q: torch.Tensor
    q_prev: torch.Tensor

    def velocity(self, dt: float) -> torch.Tensor:
        """(N, 6) backward-difference generalised velocity (q - q_prev) / dt."""
        return (self.q - self.q_prev) / dt


class Action(NamedTuple):
    """What acts on a step.

    Attributes:
        force: (N, 3) world-frame forces on the bodies' centres of mass [N] (rows of non-dynamic bodies ignored).
        torque: (N, 3) world-frame torques [N m] (rows of non-dynamic bodies ignored).
        target: (K, 6) end-of-step poses of the K kinematic bodies (``Scene.kinematic`` order); None keeps
            them where they are.
    """

    force: torch.Tensor | None = None
    torque: torch.Tensor | None = None
    target: torch.Tensor | None = None


class Params(NamedTuple):
    """Differentiable physical parameters (Nd dynamic bodies): mass (Nd,), second_moment (Nd, 3, 3), friction ()."""

    mass: torch.Tensor
    second_moment: torch.Tensor
    friction: torch.Tensor


def _check_state_tensor(x: object, name: str, n: int, cols: int = 6) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.shape != (n, cols):
        raise ValueError(f"{name} must have shape ({n}, {cols}), got {tuple(x.shape)}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {x.dtype}")
    bad = ~torch.isfinite(x).all(1)
    if bool(bad.any()):
        raise ValueError(f"{name} contains NaN or inf (first at body {int(torch.nonzero(bad)[0])})")


def recentre_rotation(q: torch.Tensor) -> torch.Tensor:
    """Map rotation vectors with |omega| > pi to the equivalent omega (1 - 2 pi / |omega|) (same rotation, norm
    below pi), differentiably; translations and small rotation vectors pass through unchanged."""
    w = q[..., 3:]
    n = torch.linalg.vector_norm(w, dim=-1, keepdim=True)
    big = n > math.pi
    ns = torch.where(big, n, torch.ones_like(n))
    w = torch.where(big, w * (1.0 - 2.0 * math.pi / ns), w)
    return torch.cat([q[..., :3], w], -1)


def _unwrap_previous(q_prev: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """q_prev with each rotation vector replaced by the equivalent omega + 2 pi k omega/|omega| (k in -1, 0, 1;
    the same rotation) closest to q's, so that (q - q_prev) / dt stays the velocity after q was re-centred."""
    w = q_prev[..., 3:]
    n = torch.linalg.vector_norm(w, dim=-1, keepdim=True)
    u = w / torch.where(n > 0, n, torch.ones_like(n))
    cands = torch.stack([w - 2.0 * math.pi * u, w, w + 2.0 * math.pi * u])  # (3, N, 3)
    k = torch.linalg.vector_norm(cands - q[..., 3:].detach(), dim=-1).argmin(0)  # (N,)
    w = torch.where((n > 0) & (k[:, None] != 1), cands[k, torch.arange(len(k))], w)
    return torch.cat([q_prev[..., :3], w], -1)


def _check_params_tensors(params: Params, device: torch.device) -> None:
    """Finite, physical, on the state's device: mass > 0, friction >= 0, the symmetric part of S positive
    semi-definite with a positive definite inertia tr(S) I - S."""
    for name, x in (
        ("mass", params.mass),
        ("second_moment", params.second_moment),
        ("friction", params.friction),
    ):
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise ValueError(f"params.{name} must be a floating-point tensor")
        if x.device != device:
            raise ValueError(f"params.{name} is on {x.device}, the state on {device}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"params.{name} contains NaN or inf")
    if not bool((params.mass > 0).all()):
        raise ValueError("params.mass must be positive")
    if float(params.friction.detach()) < 0:
        raise ValueError("params.friction must be >= 0")
    S = params.second_moment.detach().to(torch.float64)
    S = 0.5 * (S + S.transpose(1, 2))  # the step uses the symmetric part
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    inertia = torch.diagonal(S, dim1=1, dim2=2).sum(-1)[:, None, None] * eye - S
    if bool((torch.linalg.eigvalsh(S) < -1e-12 * S.abs().amax((1, 2))[:, None]).any()) or not bool(
        (torch.linalg.eigvalsh(inertia) > 0).all()
    ):
        raise ValueError(
            "params.second_moment must be positive semi-definite with a positive definite inertia"
        )


def _symmetric(S: torch.Tensor) -> torch.Tensor:
    return 0.5 * (S + S.transpose(-1, -2))


def _axial(M: torch.Tensor) -> torch.Tensor:
    """(..., 3) axial vector of the skew part of (..., 3, 3) M (last two dims)."""
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    )


def _body_terms(q, q_t, q_p, force, torque, mass, S, gravity, dt, order):
    """Inertia, gravity and actuation of the dynamic bodies: per-body values (Nd,), grad (Nd, 6), per-body Hessian
    (Nd, 6, 6).

    Differentiable (by autograd) in everything but q, which the adjoint needs for d2L / dq dtheta.
    """
    R, dR, d2R = rotation_derivatives(q[:, 3:], order)
    Rt, Rp = rotation_matrix(q_t[:, 3:]), rotation_matrix(q_p[:, 3:])
    b = q[:, :3] - 2.0 * q_t[:, :3] + q_p[:, :3]
    A = R - Rt @ Rp.transpose(1, 2) @ Rt  # R minus the predicted rotation R_t R_{t-1}^T R_t
    AS = A @ S  # (Nd, 3, 3)
    pull = mass[:, None] * gravity + force  # (Nd, 3)
    inv = 1.0 / (dt * dt)
    value = 0.5 * inv * (mass * (b * b).sum(1) + (AS * A).sum((1, 2)))
    value = value - (pull * (q[:, :3] - q_t[:, :3])).sum(1) - (torque * _axial(R @ Rt.transpose(1, 2))).sum(1)
    if order == 0:
        return value, None, None
    dRRt = torch.einsum("nijk,nlj->nkil", dR, Rt)  # (Nd, k, 3, 3): dR_k R_t^T
    g_t = inv * mass[:, None] * b - pull
    g_w = inv * torch.einsum("nijk,nij->nk", dR, AS) - (torque[:, None, :] * _axial(dRRt)).sum(-1)
    grad = torch.cat([g_t, g_w], 1)
    if order == 1:
        return value, grad, None
    Nd = q.shape[0]
    H = q.new_zeros(Nd, 6, 6)
    H[:, :3, :3] = inv * mass[:, None, None] * torch.eye(3, dtype=q.dtype, device=q.device)
    d2RRt = torch.einsum("nijkl,nmj->nklim", d2R, Rt)  # (Nd, k, l, 3, 3)
    H[:, 3:, 3:] = inv * (
        torch.einsum("nijkl,nij->nkl", d2R, AS) + torch.einsum("nijk,njm,niml->nkl", dR, S, dR)
    ) - (torque[:, None, None, :] * _axial(d2RRt)).sum(-1)
    return value, grad, H


class _Problem:
    """One step's incremental potential over the dynamic coordinates (float64, detached)."""

    def __init__(
        self, scene: Scene, poses_next: torch.Tensor, q_t, q_p, force, torque, mass, S, mu_f, lagged
    ):
        self.scene = scene
        self.dyn = scene.dynamic.to(q_t.device)
        self.poses_next = poses_next  # (N, 6) with dynamic rows to be filled
        self.q_t_full = q_t
        self.args = (q_t[self.dyn], q_p[self.dyn], force[self.dyn], torque[self.dyn], mass, S)
        self.gravity = torch.tensor(scene.gravity, dtype=q_t.dtype, device=q_t.device)
        self.mu_f = mu_f
        self.lagged = lagged
        self.forest, self.pairs, self.pair_root = scene._layout(q_t.device)
        self.N, self.Nd = scene.num_bodies, len(self.dyn)
        self.d6 = (self.dyn[:, None] * 6 + torch.arange(6, device=q_t.device)).reshape(-1)
        self.dynamic_mask = torch.zeros(self.N, dtype=torch.bool, device=q_t.device)
        self.dynamic_mask[self.dyn] = True
        self.static_mask = torch.tensor([b.kind == "static" for b in scene.bodies], device=q_t.device)
        # (Nd,) farthest vertex of each dynamic body from its origin: bounds vertex displacements
        self.extent = torch.tensor(
            [float(scene.bodies[i].bsh.vertices.norm(dim=1).max()) for i in scene.dynamic.tolist()],
            dtype=q_t.dtype, device=q_t.device,
        )  # fmt: skip
        self.stats = {"contact_evals": 0, "leaf_pairs": 0, "node_pairs": 0}

    def traverse(self, poses: torch.Tensor, order: int, sel: torch.Tensor | None = None):
        """The scene's BSH potential of the body pairs (all, or those selected by the (P,) mask ``sel``)."""
        s = self.scene
        pairs, roots = (self.pairs, self.pair_root) if sel is None else (self.pairs[sel], self.pair_root[sel])
        return traverse(
            self.forest, pairs, roots, poses, mu=s.mu, margin=s.margin, eps=s.eps, split=s.split, order=order,
            tol=s.pair_tol, max_iter=s.pair_max_iter,
        )  # fmt: skip

    def infeasible(
        self, poses: torch.Tensor, sel: torch.Tensor | None = None, shrink: float = 0.0
    ) -> torch.Tensor:
        """(P,) bool (or (sel.sum(),)): the body pairs whose potential is +inf at ``poses`` (within the margin or
        intersecting), by a collision query on the CPU (no weights or plane solves; (N, 6) poses travel), with the
        dynamic bodies scaled by 1 - ``shrink`` about their centres of mass."""
        s, cpu = self.scene, torch.device("cpu")
        forest, pairs, roots = s._layout(cpu)
        if sel is not None:
            sel = sel.to(cpu)
            pairs, roots = pairs[sel], roots[sel]
        scale = None
        if shrink:
            scale = torch.ones(self.N, dtype=torch.float64)
            scale[self.dyn.to(cpu)] = 1.0 - shrink
        out = penetrating(
            forest, pairs, roots, poses.detach().to(cpu, torch.float64), margin=s.margin, eps=s.eps, split=s.split,
            tol=s.pair_tol, max_iter=s.pair_max_iter, scale=scale,
        )  # fmt: skip
        return out.to(poses.device)

    def feasible(self, q: torch.Tensor) -> bool:
        """Whether the dynamic coordinates q give a finite energy (no pair within the margin)."""
        return len(self.pairs) == 0 or not bool(self.infeasible(self.full(q)).any())

    def penetrating(self, poses: torch.Tensor) -> str:
        """The body pairs (formatted) whose potential is +inf at ``poses`` (within the margin or intersecting);
        empty when there are none."""
        bad = [tuple(int(x) for x in self.pairs[k]) for k in torch.nonzero(self.infeasible(poses))[:5, 0]]
        return ", ".join(f"({i}, {j})" for i, j in bad)

    def full(self, q: torch.Tensor) -> torch.Tensor:
        poses = self.poses_next.clone()
        poses[self.dyn] = q
        return poses

    def contact(self, poses: torch.Tensor, order: int):
        if len(self.pairs) == 0:
            z = poses.new_zeros(())
            n6 = 6 * self.N
            return (
                z,
                (poses.new_zeros(self.N, 6) if order else None),
                (poses.new_zeros(n6, n6) if order > 1 else None),
            )
        v, g, h, st = self.traverse(poses, order)
        self.stats["contact_evals"] += 1
        self.stats["leaf_pairs"] += st["leaf_pairs"]
        self.stats["node_pairs"] += st["node_pairs"]
        self.local.index_add_(0, self.pairs[:, 0], v)
        self.local.index_add_(0, self.pairs[:, 1], v)
        G, H = scatter_pair_derivatives(self.N, self.pairs, g, h)
        if G is not None:
            self.contact_grad = G
        return v.sum(), G, H

    def __call__(self, q: torch.Tensor, order: int):
        """L, grad (6 Nd,), Hessian (6 Nd, 6 Nd), and the contact Hessian over all bodies (6N, 6N) (its cross
        blocks with non-dynamic bodies feed the adjoint; friction's enter there by autograd)."""
        poses = self.full(q)
        vb, g_b, h_b = _body_terms(q, *self.args, self.gravity, self.scene.dt, order)
        # each body's "local" energy: its own terms plus the contact and friction terms it takes part in (the
        # sum of their magnitudes sets the line search's rounding tolerance)
        self.local = poses.new_zeros(self.N)
        self.local[self.dyn] = vb
        vc, Gc, Hc = self.contact(poses, order)
        value = vb.sum() + vc
        if not torch.isfinite(value):
            return value, None, None, None
        if self.lagged is not None:
            e = self.scene.friction_eps_v * self.scene.dt
            vf, gf, hf, *gap = friction_terms(
                self.lagged, poses, self.mu_f, e, order, reduce=False, majorizer_gap=order >= 2
            )
            self.local.index_add_(0, self.lagged.body[:, 0], vf)
            self.local.index_add_(0, self.lagged.body[:, 1], vf)
            value = value + vf.sum()
        if order == 0:
            return value, None, None, None
        G = Gc
        H = Hc
        if self.lagged is not None:
            Gf, Hf = scatter_pair_derivatives(self.N, self.lagged.body, gf, hf)
            self.friction_grad = Gf
            G = G + Gf
            if order >= 2:
                H = H + Hf
        grad = g_b.reshape(-1) + G.reshape(-1)[self.d6]
        if order == 1:
            return value, grad, None, None
        H = H[self.d6][:, self.d6] + torch.block_diag(*h_b)
        if self.lagged is not None:  # the friction majorizer's Hessian: H + gap (see _newton)
            gap = scatter_pair_derivatives(self.N, self.lagged.body, gf, gap[0])[1]
            self.majorizer_gap = (H, gap[self.d6][:, self.d6])
        # floor of the saddle-free direction's eigenvalue magnitudes: a tenth of the smallest inertia eigenvalue,
        # so a direction whose curvature crosses zero is not taken as an arbitrarily long step
        self.h_floor = 0.1 * float(torch.linalg.eigvalsh(h_b).min())
        return value, grad, H, Hc


def _newton(prob: _Problem, q: torch.Tensor, tol: float, max_iter: int, first: tuple | None = None):
    """Newton (saddle-free where the Hessian is indefinite) with a backtracking line search from a feasible q.

    Returns q*, H(q*), the contact Hessian Hc(q*) and the number of iterations; raises StepError. ``first``: the
    order-2 evaluation at q, if already done."""
    L, g, H, Hc = prob(q, 2) if first is None else first
    if H is None:  # (the feasibility checks passed q; they and the potential agree up to rounding)
        raise StepError("infeasible Newton start (non-finite energy)")
    majorize = False
    for it in range(1, max_iter + 1):
        # direction: Newton where H is positive definite; else saddle-free Newton (eigenvalues by magnitude), which
        # moves along negative curvature (a rocking polyhedron, a tipping stack) at its natural scale. In the
        # iteration after a rejected full step, friction enters by its quadratic majorizer (an iteratively
        # reweighted least-squares step): the exact Hessian has no curvature along a slipping contact's slip, so
        # its steps cross the tip of the friction cone and get cut back iteration after iteration (a tumbling pile
        # of boxes: 117 iterations, 22 with the majorizer after rejections, 14 without friction; the majorizer in
        # every iteration converges only linearly at the end). H itself stays exact: the adjoint uses it
        Hd = H
        gap = getattr(prob, "majorizer_gap", None)
        if majorize and gap is not None and gap[0] is H:
            Hd = H + gap[1]
        chol, info = torch.linalg.cholesky_ex(Hd)
        if int(info) == 0:
            p = torch.cholesky_solve(-g[:, None], chol)[:, 0]
            indefinite = False
        else:
            ev, V = torch.linalg.eigh(Hd)
            mag = ev.abs().clamp_min(max(prob.h_floor, 1e-12 * float(ev.abs().max())))
            p = -(V @ ((V.T @ g) / mag))
            indefinite = True
        # (never in a majorized iteration: its step is shorter than Newton's; the next one checks the exact step)
        if not indefinite and Hd is H and float(p.abs().max()) <= tol:
            return q, H, Hc, it
        # no tunnelling: one iteration moves no vertex more than 20 ccd_spacing (the path is checked below)
        reach = _displacement(prob, p.reshape(-1, 6))
        if reach > 20.0 * prob.scene.ccd_spacing:
            p = p * (20.0 * prob.scene.ccd_spacing / reach)
            reach = 20.0 * prob.scene.ccd_spacing
        # backtracking (Armijo) line search; +inf trial energies (penetration) are rejected
        slope = float(g @ p)
        L0 = float(L)
        # rounding level of L: near convergence the predicted decrease g.p falls below it, and the (reliable) full
        # Newton step must not be rejected for noise
        noise = 1e-12 * (abs(L0) + float(prob.local.abs().sum()))
        alpha, accepted, full = 1.0, False, None
        for k in range(60):
            q_try = q + alpha * p.reshape(-1, 6)
            # the full step is usually accepted: evaluate it with derivatives at once, backtrack value-only
            full = prob(q_try, 2) if k == 0 else None
            L_try = float(full[0] if full is not None else prob(q_try, 0)[0])
            if math.isfinite(L_try) and L_try <= L0 + 1e-4 * alpha * slope + noise:
                if alpha * reach <= prob.scene.ccd_spacing or _path_feasible(prob, q, q_try):
                    accepted = True
                    break
            alpha *= 0.5
        if not accepted:
            break
        majorize = k > 0
        q = q_try
        L, g, H, Hc = full if full is not None else prob(q, 2)
    gn = float(g.abs().max())
    raise StepError(
        f"step did not converge in {max_iter} Newton iterations (newton_tol={tol}): max |dL/dq| = {gn:.3e}, "
        f"last line search step {alpha:.1e}; try a smaller dt or a larger max_newton_iter"
    )


def _feasible(prob: _Problem, q: torch.Tensor) -> bool:
    return prob.feasible(q)


def _start(prob: _Problem, q_t_dyn: torch.Tensor, q_p_dyn: torch.Tensor) -> tuple[torch.Tensor, tuple | None]:
    """A feasible start for the step's Newton solve (and its order-2 evaluation when already done).

    Tried in order: constant-velocity extrapolation; q_t; the dynamic bodies translated with each kinematic body's
    displacement (a pusher carrying what it touches); and, when a kinematic body moves into a dynamic one within
    the step, a continuation: the kinematic motion is split into fractions (adaptively halved), and the step's
    problem is solved (loosely) at each fraction from the previous solution, so the pushed bodies make room. Only
    the final solve, at the real targets, is the step; the continuation just finds where it may start.
    """
    v = q_t_dyn - q_p_dyn
    extrap = q_t_dyn + torch.where((v[:, 3:].abs() < 1.0).all(1, keepdim=True), v, v * 0.0)
    if _feasible(prob, q_t_dyn):
        first = prob(extrap, 2)  # the usual start: evaluated with derivatives at once, for the Newton solve
        if bool(torch.isfinite(first[0])) and _path_feasible(prob, q_t_dyn, extrap):
            return extrap, first
        return q_t_dyn, None
    scene = prob.scene
    bad = prob.penetrating(prob.q_t_full)
    if bad:
        raise ValueError(
            f"state.q: bodies penetrate (are within the margin {scene.margin} of each other): pairs {bad}"
        )
    kin = scene.kinematic.to(q_t_dyn.device)
    if len(kin) == 0:
        raise StepError("infeasible step start (non-finite energy at the start-of-step poses)")
    shift = prob.poses_next[kin, :3] - prob.q_t_full[kin, :3]  # (K, 3)
    for k in range(len(kin)):
        cand = q_t_dyn.clone()
        cand[:, :3] += shift[k]
        if _feasible(prob, cand):
            return cand, None
    target = prob.poses_next.clone()
    origin = prob.q_t_full[kin]
    q, done, inc = q_t_dyn, 0.0, 0.5
    try:
        while done < 1.0:
            frac = min(1.0, done + inc)
            prob.poses_next = target.clone()
            prob.poses_next[kin] = origin + frac * (target[kin] - origin)
            if _feasible(prob, q):
                q = _newton(prob, q, max(scene.newton_tol, 1e-7), scene.max_newton_iter)[0]
                done, inc = frac, inc * 2.0
            else:
                inc *= 0.5
                if inc < 1e-4:
                    raise StepError(
                        f"the kinematic targets: bodies penetrate (within the margin {scene.margin}): pairs "
                        f"{prob.penetrating(prob.full(q))}, "
                        "and pushing them out of the way failed; move kinematic bodies less per step"
                    )
    finally:
        prob.poses_next = target
    return q, None


def _displacement(prob: _Problem, dq: torch.Tensor) -> float:
    """Largest vertex displacement [m] of a change dq (Nd, 6) of the dynamic poses (bound: |dt| + |dw| r_max)."""
    return float((dq[:, :3].norm(dim=1) + dq[:, 3:].norm(dim=1) * prob.extent).max())


def _path_feasible(prob: _Problem, q0: torch.Tensor, q1: torch.Tensor) -> bool:
    """Whether the straight path q0 -> q1 (q0 feasible) is feasible at points at most ccd_spacing apart; the end
    point itself is checked by the caller."""
    n = math.ceil(_displacement(prob, q1 - q0) / prob.scene.ccd_spacing)
    return all(_feasible(prob, q0 + (k / n) * (q1 - q0)) for k in range(1, n))


def _pivot_path(prob: _Problem, q0: torch.Tensor, q1: torch.Tensor):
    """Each dynamic body's motion q0 -> q1 as a rotation about, and a straight motion of, its vertex that moves
    least (a body tipping over an edge turns about that edge); returns s -> (Nd, 6) poses."""
    R0, R1 = rotation_matrix(q0[:, 3:]), rotation_matrix(q1[:, 3:])
    pivots = []
    for i, k in enumerate(prob.scene.dynamic.tolist()):
        X = prob.scene.bodies[k].bsh.vertices.to(q0)
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


# the reachability check shrinks the moving bodies by this fraction about their centres of mass: an interpolated
# path is not the body's actual motion, and the few millimetres by which it may dip into a support it is resting
# on or landing on (a box landing on an edge, a pole tipping over) are not tunnelling; passing through a static
# body still is, for the shrunken body as for the real one
_REACH_SHRINK = 0.1


def _static_path_feasible(prob: _Problem, q0: torch.Tensor, q1: torch.Tensor) -> bool:
    """Whether the dynamic bodies, shrunk by _REACH_SHRINK, can move q0 -> q1 without crossing a static body
    (checked every ccd_spacing): along the straight path in q, or else each body turning about its least-moving
    vertex (the straight path of a body tipping over an edge dips the edge into the support by about
    r dtheta^2 / 8)."""
    a, b = prob.pairs[:, 0], prob.pairs[:, 1]
    sel = (prob.static_mask[a] ^ prob.static_mask[b]) & (prob.dynamic_mask[a] | prob.dynamic_mask[b])
    if not bool(sel.any()):
        return True
    n = math.ceil(_displacement(prob, q1 - q0) / prob.scene.ccd_spacing)
    if n <= 1:
        return True
    for path in (lambda s: q0 + s * (q1 - q0), _pivot_path(prob, q0, q1)):
        if not any(
            bool(prob.infeasible(prob.full(path(k / n)), sel, _REACH_SHRINK).any()) for k in range(1, n)
        ):
            return True
    # neither interpolation is clear (a body tumbling onto a support with a large rotation in the step dips deep
    # into it along both): tunnelling only if some body's centre of mass crosses a static surface on its way
    return not _centre_crosses_static(prob, q0, q1)


def _centre_crosses_static(prob: _Problem, q0: torch.Tensor, q1: torch.Tensor) -> bool:
    """Whether the segment from some dynamic body's centre of mass at q0 to that at q1 crosses a triangle of a
    static body (Moller-Trumbore, exact; both ends are outside every body)."""
    a, b = q0[:, :3], q1[:, :3]  # (Nd, 3): dynamic frames sit at the centres of mass
    d = b - a
    for j in torch.nonzero(prob.static_mask).flatten().tolist():
        pose = prob.poses_next[j]
        tri = prob.scene.bodies[j].bsh.triangles.to(q0) @ rotation_matrix(pose[3:]).T + pose[:3]  # (T, 3, 3)
        v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        pvec = torch.linalg.cross(
            d[:, None, :].expand(-1, len(tri), -1), e2[None].expand(len(d), -1, -1), dim=-1
        )
        det = (e1[None] * pvec).sum(-1)  # (Nd, T)
        ok = det.abs() > 1e-300
        inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
        tvec = a[:, None, :] - v0[None]
        u = (tvec * pvec).sum(-1) * inv
        qvec = torch.linalg.cross(tvec, e1[None].expand_as(tvec), dim=-1)
        v = (d[:, None, :] * qvec).sum(-1) * inv
        t = (e2[None] * qvec).sum(-1) * inv
        if bool((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)).any()):
            return True
    return False


def _solve_step(prob: _Problem, q_t_dyn: torch.Tensor, q_p_dyn: torch.Tensor):
    """Feasible start, then Newton; returns q*, H(q*), the contact Hessian Hc(q*) and the number of iterations."""
    q, first = _start(prob, q_t_dyn, q_p_dyn)
    q, H, Hc, it = _newton(prob, q, prob.scene.newton_tol, prob.scene.max_newton_iter, first)
    # the Newton path is feasible; each body's own motion (straight from q_t) must not cross a static body either:
    # with a huge dt the minimiser can lie beyond an obstacle, reached by iterates that went around it. (Pairs of
    # moving bodies are not checked: their straight interpolation may overlap after a legitimate collision.)
    if not _static_path_feasible(prob, q_t_dyn, q):
        raise StepError(
            f"the step's solution is not reachable from the start-of-step poses without penetration (it moves "
            f"{_displacement(prob, q - q_t_dyn):.3g} m, through a static body): reduce dt"
        )
    return q, H, Hc, it


class _StepFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scene, info, q_t, q_p, force, torque, target, mass, S, mu_f):
        with _serial_torch():
            return _StepFn._forward(ctx, scene, info, q_t, q_p, force, torque, target, mass, S, mu_f)

    @staticmethod
    def _forward(ctx, scene, info, q_t, q_p, force, torque, target, mass, S, mu_f):
        dyn = scene.dynamic.to(q_t.device)
        poses_next = q_t.clone()
        if len(scene.kinematic):
            poses_next[scene.kinematic.to(q_t.device)] = target
        lagged = None
        # friction off costs nothing, unless its coefficient needs a gradient (at mu_f = 0 the term is zero but its
        # derivative is not)
        if float(mu_f) > 0.0 or ctx.needs_input_grad[9]:
            lagged = scene._lagged_friction(q_t)
        prob = _Problem(scene, poses_next, q_t, q_p, force, torque, mass, S, mu_f, lagged)
        q, H, Hc, iters = _solve_step(prob, q_t[dyn], q_p[dyn])
        info.update(prob.stats)
        info["newton_iters"] = iters
        # generalised forces at the end-of-step poses (the last full evaluation was at q*)
        n6 = (scene.num_bodies, 6)
        info["contact_force"] = -getattr(prob, "contact_grad", q_t.new_zeros(n6)).detach().clone()
        info["friction_force"] = -getattr(prob, "friction_grad", q_t.new_zeros(n6)).detach().clone()
        info["friction_contacts"] = 0 if lagged is None else int(lagged.normal_force.numel())
        ctx.scene, ctx.friction = scene, lagged is not None
        ctx.save_for_backward(q, H, Hc, q_t, q_p, force, torque, target, mass, S, mu_f)
        return q

    @staticmethod
    def backward(ctx, gout):
        if torch.is_grad_enabled():  # create_graph=True
            raise RuntimeError(
                "cfd_torch.step: second derivatives through a simulation step are not implemented (the step's "
                "backward is a first-order adjoint); do not use create_graph=True through step()"
            )
        with _serial_torch():
            return _StepFn._backward(ctx, gout)

    @staticmethod
    def _backward(ctx, gout):
        # q* solves g(q*, theta) = 0  =>  dq*/dtheta = -H^-1 dg/dtheta; for an upstream gradient v:
        #   lam = H^-1 v (H symmetric),   dtheta = -lam^T dg/dtheta   (one solve, one vector-Jacobian product).
        # dg/dtheta: autograd through the closed-form body and friction gradients (functions of theta at fixed q*),
        # and, for the contact term, the cross blocks of the contact Hessian with the non-dynamic end-of-step poses.
        scene = ctx.scene
        q, H, Hc, q_t, q_p, force, torque, target, mass, S, mu_f = ctx.saved_tensors
        dyn = scene.dynamic.to(q.device)
        chol, info = torch.linalg.cholesky_ex(H)
        v = gout.reshape(-1, 1).to(H.dtype)
        lam = torch.cholesky_solve(v, chol) if int(info) == 0 else torch.linalg.solve(H, v)
        lam = lam.reshape(-1, 6)
        N = scene.num_bodies
        with torch.enable_grad():
            th = [x.detach().requires_grad_(True) for x in (q_t, q_p, force, torque, target, mass, S, mu_f)]
            tq_t, tq_p, tf, ttau, ttarget, tmass, tS, tmu = th
            poses_next = tq_t.clone()
            if len(scene.kinematic):
                poses_next[scene.kinematic.to(q.device)] = ttarget
            poses_next[dyn] = q
            gravity = torch.tensor(scene.gravity, dtype=q.dtype, device=q.device)
            _, g_b, _ = _body_terms(
                q, tq_t[dyn], tq_p[dyn], tf[dyn], ttau[dyn], tmass, tS, gravity, scene.dt, 1
            )
            s = (g_b * lam).sum()
            if ctx.friction:
                lagged = scene._lagged_friction(tq_t, create_graph=True)
                _, gf, _ = friction_terms(lagged, poses_next, tmu, scene.friction_eps_v * scene.dt, 1)
                Gf, _ = scatter_pair_derivatives(N, lagged.body, gf, None)
                s = s + (Gf[dyn] * lam).sum()
            # contact: d(g_dyn)/d(pose_j) for non-dynamic j is the cross block of the contact Hessian
            lam_full = q.new_zeros(N, 6)
            lam_full[dyn] = lam
            cross = (Hc @ lam_full.reshape(-1)).reshape(N, 6)
            s = s + (cross.detach() * poses_next).sum()
            grads = torch.autograd.grad(-s, th, allow_unused=True)
        out = [
            None if gth is None else gth.to(x.dtype)
            for gth, x in zip(grads, (q_t, q_p, force, torque, target, mass, S, mu_f), strict=True)
        ]
        # the dynamic rows of poses_next are q* itself (not theta): the cross term above only reaches non-dynamic
        # poses through poses_next; dynamic rows of q_t/q_p enter through the body and friction terms.
        return (None, None, *out)


def step(
    scene: Scene,
    state: State,
    action: Action | None = None,
    params: Params | None = None,
    *,
    info: dict | None = None,
) -> State:
    """Advance the scene by one time step (differentiable by autograd).

    Args:
        scene: bodies and parameters.
        state: State(q (N, 6), q_prev (N, 6)), float32 or float64 (solved in float64, returned in its dtype).
        action: forces, torques and kinematic targets (defaults: none, kinematic bodies stay put).
        params: differentiable mass / second moment / friction coefficient (default: ``scene.params()``).
        info: if a dict, receives solver statistics ("newton_iters", "contact_evals", "leaf_pairs", ...) and the
            end-of-step generalised forces on every body, "contact_force" and "friction_force" (N, 6): -dP/dq and
            -dD/dq; columns 0-2 are world-frame forces [N], columns 3-5 are conjugate to the rotation vector (the
            world torque when the rotation vector is zero).

    Returns:
        The next State(q_next, q): dynamic rows solved, kinematic rows at their targets, static rows unchanged,
        rotation vectors re-centred when |omega| > pi.

    Raises:
        ValueError: bad shapes, dtypes or NaN/inf inputs (naming the argument), or a start state that penetrates.
        StepError: the Newton solve did not converge.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a cfd_torch.Scene, got {type(scene).__name__}")
    if not isinstance(state, State):
        raise TypeError(f"state must be a cfd_torch.State, got {type(state).__name__}")
    N = scene.num_bodies
    _check_state_tensor(state.q, "state.q", N)
    _check_state_tensor(state.q_prev, "state.q_prev", N)
    dtype, dev = state.q.dtype, state.q.device
    action = Action() if action is None else action
    f64 = torch.float64
    force = action.force if action.force is not None else torch.zeros(N, 3, dtype=f64, device=dev)
    torque = action.torque if action.torque is not None else torch.zeros(N, 3, dtype=f64, device=dev)
    _check_state_tensor(force, "action.force", N, 3)
    _check_state_tensor(torque, "action.torque", N, 3)
    K = len(scene.kinematic)
    kin = scene.kinematic.to(dev)
    target = action.target if action.target is not None else state.q[kin]
    _check_state_tensor(target, "action.target", K)
    params = scene.params(f64, dev) if params is None else params
    Nd = len(scene.dynamic)
    if params.mass.shape != (Nd,) or params.second_moment.shape != (Nd, 3, 3) or params.friction.shape != ():
        raise ValueError(
            f"params must hold mass ({Nd},), second_moment ({Nd}, 3, 3) and friction (), got "
            f"{tuple(params.mass.shape)}, {tuple(params.second_moment.shape)}, {tuple(params.friction.shape)}"
        )
    _check_params_tensors(params, dev)
    info = {} if info is None else info
    q_t, q_p = state.q.to(f64), state.q_prev.to(f64)
    q_dyn = _StepFn.apply(
        scene, info, q_t, q_p, force.to(f64), torque.to(f64), target.to(f64), params.mass.to(f64),
        _symmetric(params.second_moment.to(f64)), params.friction.to(f64),
    )  # fmt: skip
    dyn = scene.dynamic.to(dev)
    q_next = q_t.clone()
    if K:
        q_next = q_next.index_put((kin,), target.to(f64))
    q_next = q_next.index_put((dyn,), recentre_rotation(q_dyn))
    return State(q_next.to(dtype), _unwrap_previous(state.q, q_next.to(dtype)))


def rollout(
    scene: Scene,
    state: State,
    actions: Sequence[Action | None] | int,
    params: Params | None = None,
    *,
    progress: bool = False,
) -> list[State]:
    """Step ``len(actions)`` times (or ``actions`` times with no action); returns the T + 1 states, first included."""
    seq = [None] * actions if isinstance(actions, int) else list(actions)
    states = [state]
    it = seq
    if progress:
        from tqdm import tqdm

        it = tqdm(seq, desc="rollout")
    for a in it:
        states.append(step(scene, states[-1], a, params))
    return states
