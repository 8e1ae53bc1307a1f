"""The simulator's state, action, parameters and step statistics: NamedTuples of tensors.

Shapes: B scenes of a batch (absent for an unbatched call), N bodies, Nd dynamic bodies, K kinematic bodies.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._autograd import outside_transforms, plain
from .._validate import check_positive

__all__ = ["State", "Trajectory", "Action", "Params", "StepInfo", "StepError"]


class StepError(RuntimeError):
    """A step's Newton solve stopped without converging; the message says why (see ``NewtonResult.reason``)."""


class State(NamedTuple):
    """Simulator state: poses ([B,] N, 6) [translation m, rotation vector rad] now and one step earlier."""

    q: torch.Tensor
    q_prev: torch.Tensor

    def velocity(self, dt: float) -> torch.Tensor:
        """([B,] N, 6) backward-difference generalised velocity (q - q_prev) / dt.

        Raises:
            TypeError: q or q_prev is not a tensor.
            ValueError: dt is not a finite positive Python number (a tensor is refused too); q and q_prev differ in
                shape, dtype or device, hold NaN/inf, or give a velocity that overflows their dtype (a tiny dt)."""
        check_positive(dt, "dt")
        for name, x in (("q", self.q), ("q_prev", self.q_prev)):
            if not isinstance(x, torch.Tensor):
                raise TypeError(f"State.{name} must be a torch.Tensor, got {type(x).__name__}")
        q, q_prev = self.q, self.q_prev
        if q.shape != q_prev.shape or q.dtype != q_prev.dtype or q.device != q_prev.device:
            raise ValueError(
                f"State.q ({q.dtype} {tuple(q.shape)} on {q.device}) and State.q_prev ({q_prev.dtype} "
                f"{tuple(q_prev.shape)} on {q_prev.device}) must match in shape, dtype and device"
            )
        v = (q - q_prev) / dt
        with outside_transforms():  # (values read from the plain tensors: it may run under torch.func.vmap)
            if not bool(torch.isfinite(plain(v).detach()).all()):
                if not (bool(torch.isfinite(plain(q)).all()) and bool(torch.isfinite(plain(q_prev)).all())):
                    raise ValueError("State.q or State.q_prev contains NaN or inf")
                raise ValueError(f"the velocity (q - q_prev) / dt overflows {q.dtype} at dt = {dt:g}")
        return v


class Trajectory:
    """States of a rollout stacked along a leading time dimension: ``q`` and ``q_prev`` (T + 1, [B,] N, 6).

    ``traj[t]`` is the State at step t (a slice gives a Trajectory), ``len(traj)`` is T + 1, and iterating yields
    the States in order.
    """

    def __init__(self, q: torch.Tensor, q_prev: torch.Tensor) -> None:
        for name, x in (("q", q), ("q_prev", q_prev)):
            if not isinstance(x, torch.Tensor):
                raise TypeError(f"Trajectory.{name} must be a torch.Tensor, got {type(x).__name__}")
        if q.shape != q_prev.shape or q.dim() not in (3, 4) or q.shape[-1] != 6:
            raise ValueError(
                "Trajectory.q and q_prev must be (T + 1, [B,] N, 6) tensors of one shape, got "
                f"{tuple(q.shape)} and {tuple(q_prev.shape)}"
            )
        self.q = q
        self.q_prev = q_prev

    def __len__(self) -> int:
        return self.q.shape[0]

    def __getitem__(self, t):
        if isinstance(t, slice):
            return Trajectory(self.q[t], self.q_prev[t])
        return State(self.q[t], self.q_prev[t])

    def __iter__(self):
        return (State(q, qp) for q, qp in zip(self.q, self.q_prev, strict=True))

    def __repr__(self) -> str:
        return f"Trajectory(q={tuple(self.q.shape)}, q_prev={tuple(self.q_prev.shape)})"


class Action(NamedTuple):
    """What acts on a step (None: nothing).

    Attributes:
        force: ([B,] N, 3) world-frame forces on the bodies' centres of mass [N] (rows of non-dynamic bodies
            ignored).
        torque: ([B,] N, 3) world-frame torques [N m] (rows of non-dynamic bodies ignored).
        target: ([B,] K, 6) end-of-step poses of the K kinematic bodies (``Scene.num_kinematic_bodies``, in
            ``Scene.kinematic`` order; kinematic robots' links are posed by ``joints``); None keeps them where they
            are.
        ctrl: ([B,] U) controls of the simulated articulations' actuators (``Scene.num_actuators``), in the scene's
            articulation order then MJCF order, clipped to their ctrlrange (motor: joint torque gear * ctrl;
            position: a PD servo toward ctrl / gear with ``Params.kp`` and ``kv``,
            :class:`~cfd_torch.sim.articulation.Articulation`); None: zero.
        joints: ([B,] Qk) end-of-step coordinates of the kinematic robots (``articulation(..., kinematic=True)``,
            ``Scene.num_kinematic_coords``), per robot in scene order its base pose (floating bases) then its joint
            values: their links are posed there exactly, by forward kinematics (differentiable); None keeps them
            where they are.
    """

    force: torch.Tensor | None = None
    torque: torch.Tensor | None = None
    target: torch.Tensor | None = None
    ctrl: torch.Tensor | None = None
    joints: torch.Tensor | None = None


class Params(NamedTuple):
    """Differentiable physical parameters, per scene or shared by a batch.

    Attributes:
        mass: ([B,] Nd) masses of the dynamic bodies [kg].
        second_moment: ([B,] Nd, 3, 3) second moments of mass about the centres of mass, body frame [kg m^2]
            (the step uses their symmetric part).
        friction: ([B]) Coulomb's coefficient; it overrides the scene's ``FrictionConfig.coefficient`` (its default):
            friction is computed wherever it is positive or requires grad.
        kp, kv: ([B,] U) the position actuators' (servos') stiffness and damping gains, in ``Action.ctrl``'s order
            (a servo's joint torque is gear kp ctrl - kp gear^2 theta - kv gear^2 theta_dot; motors' entries are
            unused); None: the MJCF's (``Scene.params()`` fills them in).
    """

    mass: torch.Tensor
    second_moment: torch.Tensor
    friction: torch.Tensor
    kp: torch.Tensor | None = None
    kv: torch.Tensor | None = None


class StepInfo(NamedTuple):
    """Solver statistics and end-of-step forces of one step (``step(..., return_info=True)``).

    Attributes:
        newton_iters: ([B]) Newton iterations of each scene's solve (after a sub-step retry, this and the other
            work counts are the sub-steps' that succeeded; ``seconds`` includes the failed attempts). A step
            whose kinematic bodies' targets overlap dynamic bodies first pushes them out of the way in stages, one
            Newton solve each: those iterations are not counted here, their evaluations are in ``contact_evals``.
        contact_evals: evaluations of the incremental potential, each one contact-model call over the scenes still
            iterating (line-search trials included).
        node_pairs: hierarchy node pairs visited over those evaluations.
        leaf_pairs: exact leaf pairs solved over those evaluations.
        friction_contacts: ([B]) lagged friction contacts of each scene.
        contact_force: ([B,] N, 6) -dP/dq at the solve's last evaluated iterate (the end-of-step poses but for
            Newton's last step, at most ``newton_tol`` per coordinate: relative differences around 1e-6 from
            ``pair_forces`` at the returned poses): columns 0-2 world-frame forces [N], columns 3-5
            conjugate to the rotation vector (the world torque when the rotation vector is zero); float64, the
            solve's precision, whatever the state's dtype. Not differentiated: in a step that records a graph, a
            backward through it (or through ``friction_force``) raises RuntimeError.
        friction_force: ([B,] N, 6) -dD/dq of the lagged friction potential, same layout and dtype.
        substeps: ([B]) sub-steps each scene's step took (1 unless it was retried after a StepError,
            ``SolverConfig.substeps``).
        seconds: wall time of the forward solve [s], every attempt of a retried step included.
    """

    newton_iters: torch.Tensor
    contact_evals: int
    node_pairs: int
    leaf_pairs: int
    friction_contacts: torch.Tensor
    contact_force: torch.Tensor
    friction_force: torch.Tensor
    substeps: torch.Tensor
    seconds: float


def allow_in_torch_load(*classes: type) -> None:
    """Let ``torch.load`` (``weights_only=True``, torch's default from 2.6) rebuild ``classes``: plain containers of
    tensors and numbers (torch before 2.4 has no allowlist and loads them anyway)."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is not None:
        add(list(classes))


allow_in_torch_load(State, Trajectory, Action, Params, StepInfo)
