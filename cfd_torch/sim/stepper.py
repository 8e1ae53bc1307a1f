"""The simulator's public face: ``step`` and ``rollout`` (SPEC section 5).

    step(scene, state, action, params) -> State

reads like a table of contents: check the inputs, batch them, solve the step (:mod:`.solve` finds a feasible start
under :mod:`.feasibility`'s contract, :mod:`.newton` minimises the incremental potential of :mod:`.energy`,
:mod:`.adjoint` differentiates the solution), re-centre rotations. Every tensor may carry a leading batch
dimension B of independent scenes that share one :class:`Scene` (its bodies and settings); they are solved
together (one contact evaluation over all their body pairs, a Newton masked per scene) and each scene's result
equals stepping it alone.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterable, Sequence

import numpy as np
import torch

from .._autograd import outside_transforms, plain, refuse_derivative, refuse_transforms
from .._geometry import frame_origin
from .._validate import FLOATS, MAX_ROTATION, check_dense, check_rotation_length, is_int, narrowed
from ._checks import (
    check_ctrl,
    check_params,
    check_pose_range,
    check_state_tensor,
    check_targets_clear,
    first_row,
)
from .adjoint import StepFn
from .energy import end_poses, scene_pairs
from .feasibility import infeasible_pairs, infeasible_reason
from .scene import Scene
from .types import Action, Params, State, StepError, StepInfo, Trajectory

# contact forces (StepInfo's, pair_forces') are not differentiated (their Hessian-based derivative is not
# implemented): where the poses require grad, a backward through them raises, as a constant would drop their part of
# a loss's gradient silently
_NO_GRADIENT = (
    "{name} carries no gradient (contact forces are not differentiated); use it for logging, or .detach() it to "
    "leave it out of the loss"
)

__all__ = ["step", "rollout", "recentre_rotation", "pair_forces"]


def _whole_turns(w: torch.Tensor, toward: torch.Tensor) -> torch.Tensor:
    """Rotation vectors w (..., 3) as the equivalent w + 2 pi k w / |w| (k whole turns: the same rotation) closest to
    ``toward`` (..., 3): along w's axis, the norm |w| + 2 pi k nearest toward's component (k chosen without
    gradient; w's own gradient flows)."""
    n = torch.linalg.vector_norm(w, dim=-1, keepdim=True)
    some = n > 0
    u = w / torch.where(some, n, torch.ones_like(n))
    along = (toward.detach() * u.detach()).sum(-1, keepdim=True)
    k = torch.round((along - n.detach()) / (2.0 * math.pi))
    return torch.where(some & (k != 0), w + (2.0 * math.pi) * k * u, w)


# the most steps ``rollout`` takes as a count (its list of actions is made at once)
_MAX_ROLLOUT_STEPS = 10**9


def recentre_rotation(q: torch.Tensor) -> torch.Tensor:
    """Map rotation vectors with |omega| > pi to the equivalent omega (1 - 2 pi k / |omega|), k the whole turns
    that bring the norm to at most pi (the same rotation), differentiably; translations and rotation vectors of norm
    at most pi pass through unchanged.

    Raises:
        TypeError, ValueError: q is not a float32 or float64 tensor (..., 6) of finite values, or holds a rotation
            vector longer than 1e6 rad (the limit of every function taking poses: there its spacing exceeds
            1.2e-10 rad, and from about 1e15 rad it no longer says which rotation it is)."""
    if not isinstance(q, torch.Tensor):
        raise TypeError(f"q must be a torch.Tensor, got {type(q).__name__}")
    check_dense(q, "q")
    if q.dim() == 0 or q.shape[-1] != 6 or q.dtype not in FLOATS:
        raise ValueError(
            f"q must be a float32 or float64 tensor of poses (..., 6), got {q.dtype} of shape {tuple(q.shape)}"
        )
    with outside_transforms():  # (values read from the plain tensor: the check runs under torch.func.vmap)
        if not bool(torch.isfinite(plain(q)).all()):
            raise ValueError("q contains NaN or inf")
    check_rotation_length(
        q, "q", lambda m: f"index {tuple(int(i) for i in torch.nonzero(m)[0])}",
        "wrap rotation vectors while they are short (a step returns them re-centred)",
    )  # fmt: skip
    return _recentre(q)


def _recentre(q: torch.Tensor) -> torch.Tensor:
    w = q[..., 3:]
    return torch.cat([q[..., :3], _whole_turns(w, torch.zeros_like(w))], -1)


def _unwrap_previous(q_prev: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """q_prev (..., 6) with each rotation vector omega replaced by the equivalent omega + 2 pi k omega / |omega| (k
    whole turns, the same rotation) closest to q's, so that (q - q_prev) / dt stays the velocity after q was
    re-centred (also a target against the current pose: the step then turns the short way)."""
    return torch.cat([q_prev[..., :3], _whole_turns(q_prev[..., 3:], q[..., 3:])], -1)


def _shift(q: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Poses q (B, N, 6) with their translations moved by c (B, 1, 3)."""
    return torch.cat([q[..., :3] + c, q[..., 3:]], -1)


def _batch(x: torch.Tensor, B: int) -> torch.Tensor:
    return x.expand(B, *x.shape) if x.dim() == 2 else x


def _solve(
    scene: Scene, state: State, force, torque, target, ctrl, params: Params
) -> tuple[torch.Tensor, StepInfo]:
    """One step of the batch at once (float64, batched): the next poses and the (batched) StepInfo."""
    f64 = torch.float64
    S = params.second_moment.to(f64)
    q_t, q_p = state.q.to(f64), state.q_prev.to(f64)
    solved = torch.zeros(scene.num_bodies, 1, dtype=torch.bool, device=q_t.device)  # the rows the step solves
    solved[scene.kinematics.bodies] = True
    # their rotation vectors re-centred (|omega| <= pi, the same rotations), q_prev's on the same branch: Newton's
    # unknowns are the rotation vectors, and on a far branch (|omega| = 2 pi k + a) a turn of the body is a change of
    # the coordinates |omega| / a times larger, whose convergence to newton_tol float64 cannot resolve
    q_t = torch.where(solved, _recentre(q_t), q_t)
    q_p = torch.where(solved, _unwrap_previous(q_p, q_t), q_p)
    # The step is solved in a frame near its moving bodies (every translation shifted by c, exactly: see
    # _geometry.frame_origin), so that the incremental potential, whose terms are differences of positions, keeps
    # its digits far from the world origin; every term is translation-invariant, and the shift back is exact too.
    # A robot hung from its mount reads the mount as a world pose: then one frame serves a solve, and the step's
    # kinematics hang the robots from their mounts moved into it. Scenes whose own frames are the same share it;
    # scenes within _SHARED_FRAME_EXTENT of the batch's frame share that; farther apart, they are solved in groups,
    # each in the frame its scenes have alone (a batch frame between scenes 1 km apart made a scene fail that
    # steps alone).
    moving = q_t[:, scene.kinematics.bodies.to(q_t.device), :3].detach()
    if scene.kinematics.translation_invariant:
        c = frame_origin(moving, min_extent=1.0)[:, None]
    else:
        own = frame_origin(moving, min_extent=1.0)  # (B, 3): each scene's frame alone
        origin = own[0]
        if bool((own != origin).any()):
            origin = frame_origin(moving.reshape(1, -1, 3), min_extent=1.0)[0]
            if float((own - origin).abs().max()) > _SHARED_FRAME_EXTENT:
                return _solve_in_groups(scene, state, force, torque, target, ctrl, params, own)
        c = origin.expand(q_t.shape[0], 1, 3)
        scene = scene._in_frame(scene.kinematics.translated(origin))
    # the rows the step does not solve (static, kinematic), from the unshifted inputs: the shift's round trip is
    # exact only near the moving bodies
    held = end_poses(scene, q_t, target.to(f64))
    q_t, q_p, target = _shift(q_t, -c), _shift(q_p, -c), _shift(target.to(f64), -c)
    q, iters, fc, ff, nfc, work, seconds = StepFn.apply(
        scene, q_t, q_p, force.to(f64), torque.to(f64), target, params.mass.to(f64),
        0.5 * (S + S.transpose(-1, -2)), params.friction.to(f64), ctrl.to(f64), params.kp.to(f64),
        params.kv.to(f64),
    )  # fmt: skip
    moved = solved.clone()
    moved[scene.kinematic] = True
    q_next = scene.kinematics.poses(q, _shift(held, -c))
    q_next = _shift(torch.where(moved, _recentre(q_next), q_next), c)
    q_next = torch.where(solved, q_next, torch.where(moved, _recentre(held), held))
    ones = torch.ones_like(iters)
    # a differentiated step: a loss through the forces raises instead of dropping their part
    if q.requires_grad:
        fc = refuse_derivative(fc, q, _NO_GRADIENT.format(name="StepInfo.contact_force"))
        ff = refuse_derivative(ff, q, _NO_GRADIENT.format(name="StepInfo.friction_force"))
    return q_next, StepInfo(
        iters, int(work[0]), int(work[1]), int(work[2]), nfc, fc, ff, ones, float(seconds)
    )


# the farthest [m] a scene of a batch with a mounted robot may lie from the batch's frame to share it (beyond, the
# batch is solved in groups of scenes that share their own frames)
_SHARED_FRAME_EXTENT = 16.0


def _solve_in_groups(
    scene: Scene, state: State, force, torque, target, ctrl, params: Params, own: torch.Tensor
):
    """_solve for each group of scenes with the same frame origin ``own`` (B, 3), in that frame; the results
    reassembled in batch order."""
    _, group = torch.unique(own, dim=0, return_inverse=True)
    members = [torch.nonzero(group == g)[:, 0] for g in range(int(group.max()) + 1)]
    outs = []
    for idx in members:
        pick = lambda x, idx=idx: x.index_select(0, idx)  # noqa: E731
        try:
            part = State(pick(state.q), pick(state.q_prev))
            outs.append(
                _solve(scene, part, *map(pick, (force, torque, target, ctrl)), Params(*map(pick, params)))
            )
        # which scenes of the batch the group holds, the group's scene indices turned into the batch's
        except (StepError, ValueError) as err:
            batch = re.sub(
                r"\bscene (\d+)", lambda s, idx=idx: f"scene {int(idx[int(s.group(1))])}", str(err)
            )
            raise type(err)(
                f"scenes {idx.tolist()} of the batch, solved in their own frame: {batch}"
            ) from err
    back = torch.argsort(torch.cat(members))
    return torch.cat([q for q, _ in outs])[back], _joined([info for _, info in outs], back)


def _joined(infos: Sequence[StepInfo], order: torch.Tensor | None = None) -> StepInfo:
    """One StepInfo of the batch from the infos of its parts (per-scene fields concatenated, then taken in
    ``order``; counts and seconds summed)."""
    pick = (lambda x: x) if order is None else (lambda x: x[order])  # noqa: E731
    cat = lambda f: pick(torch.cat([getattr(i, f) for i in infos]))  # noqa: E731
    return StepInfo(
        cat("newton_iters"), sum(i.contact_evals for i in infos), sum(i.node_pairs for i in infos),
        sum(i.leaf_pairs for i in infos), cat("friction_contacts"), cat("contact_force"), cat("friction_force"),
        cat("substeps"), sum(i.seconds for i in infos),
    )  # fmt: skip


def _substeps(scene: Scene, state: State, force, torque, target, ctrl, params: Params, k: int):
    """The step as k equal sub-steps of dt / k (kinematic targets interpolated, the velocity carried over): the
    next poses, the previous poses that keep the velocity at the coarse step, and the StepInfo."""
    fine = scene.replace(dt=scene.dt / k)
    q, q_prev = state.q, state.q - (state.q - state.q_prev) / k
    kin = scene.kinematic.to(q.device)
    start = state.q[:, kin]
    infos = []
    for i in range(1, k + 1):
        # (on the branch of the kinematic bodies' poses now: the sub-steps re-centre them)
        tgt = _unwrap_previous(start + (i / k) * (target - start), q[:, kin])
        q_next, info = _solve(fine, State(q, q_prev), force, torque, tgt, ctrl, params)
        q, q_prev = q_next, _unwrap_previous(q, q_next)
        infos.append(info)
    info = infos[-1]._replace(
        newton_iters=sum(i.newton_iters for i in infos), contact_evals=sum(i.contact_evals for i in infos),
        node_pairs=sum(i.node_pairs for i in infos), leaf_pairs=sum(i.leaf_pairs for i in infos),
        substeps=torch.full_like(infos[-1].newton_iters, k), seconds=sum(i.seconds for i in infos),
    )  # fmt: skip
    return q, q - k * (q - q_prev), info


def _advance(scene: Scene, state: State, force, torque, target, ctrl, params: Params):
    """The step of a batch: next poses, previous poses (None: from the step itself) and StepInfo. A step that
    fails is retried in sub-steps (``scene.solver.substeps``); in a batch, each scene on its own, so that every
    scene's result is the one it gets alone. After a retry the StepInfo's ``seconds`` is the wall time of every
    attempt; its work counts are the attempt that succeeded."""
    start = time.perf_counter()
    try:
        q, info = _solve(scene, state, force, torque, target, ctrl, params)
        return q, None, info
    except StepError:
        if scene.solver.substeps == 1:
            raise
    B = state.q.shape[0]
    if B > 1:
        outs = []
        for b in range(B):
            one = slice(b, b + 1)
            try:
                q, q_prev, info = _advance(
                    scene, State(state.q[one], state.q_prev[one]), force[one], torque[one], target[one],
                    ctrl[one], Params(*(x[one] for x in params)),
                )  # fmt: skip
            except StepError as err:  # say which scene of the batch failed
                raise StepError(f"scene {b} of the batch: {err}") from err
            outs.append((q, _unwrap_previous(state.q[one], q) if q_prev is None else q_prev, info))
        info = _joined([o[2] for o in outs])._replace(seconds=time.perf_counter() - start)
        return torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs]), info
    k = 2
    while True:
        try:
            q, q_prev, info = _substeps(scene, state, force, torque, target, ctrl, params, k)
            return q, q_prev, info._replace(seconds=time.perf_counter() - start)
        except StepError as err:
            if 2 * k > scene.solver.substeps:
                tried = ", ".join(str(2**i) for i in range(1, k.bit_length()))
                raise StepError(f"{err} (the step failed whole and as {tried} sub-steps)") from err
            k *= 2


def _check_start(scene: Scene, state: State) -> None:
    """The scene and the start state a step or a rollout begins from (a clear error naming the argument)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a cfd_torch.Scene, got {type(scene).__name__}")
    if not isinstance(state, State):
        raise TypeError(f"state must be a cfd_torch.State, got {type(state).__name__}")
    N = scene.num_bodies
    check_state_tensor(state.q, "state.q", N)
    check_state_tensor(state.q_prev, "state.q_prev", N, like=state.q)
    if state.q.shape != state.q_prev.shape:
        raise ValueError(
            f"state.q {tuple(state.q.shape)} and state.q_prev {tuple(state.q_prev.shape)} differ"
        )
    B = state.q.shape[0] if state.q.dim() == 3 else 1
    if B == 0:
        raise ValueError("state.q: a batch of no scenes (shape (0, N, 6)); give at least one")
    check_pose_range(state.q, "state.q")
    check_pose_range(state.q_prev, "state.q_prev")
    if scene.planar:  # the planar map turns bodies about z: only from poses without roll and pitch
        dyn = scene.dynamic.to(state.q.device)
        for name, x in (("state.q", state.q), ("state.q_prev", state.q_prev)):
            if bool((x[..., dyn, 3:5].abs() > 1e-12).any()):
                raise ValueError(
                    f"{name}: a planar scene's dynamic bodies must have zero roll and pitch (rotation vectors "
                    "(0, 0, yaw))"
                )
    if scene.simulates_joints:  # state.q's link rows must be a configuration (q_prev's only approximate one)
        q64 = state.q.detach().to(torch.float64).reshape(B, N, 6)
        coords = scene.kinematics.coords(q64)
        scene.kinematics.check_rows(q64, coords, "state.q", torch.finfo(state.q.dtype).eps)
        # a joint within about newton_tol of a limit: the barrier's Newton step there is about that distance
        scene.kinematics.check_within_limits(q64, "state.q", 1e3 * scene.solver.newton_tol, coords)


def _checked_params(scene: Scene, state: State, params: Params | None) -> Params:
    """``params`` (default ``scene.params()``) checked against the (checked) start state and returned with a batch
    dimension (:func:`._checks.check_params`)."""
    if params is not None and not isinstance(params, Params):
        raise TypeError(f"params must be a cfd_torch.Params or None, got {type(params).__name__}")
    f64, dev = torch.float64, state.q.device
    batched = state.q.dim() == 3
    params = scene.params(f64, dev) if params is None else params
    B = state.q.shape[0] if batched else 1
    kin = scene.kinematics
    servos = kin.actuator_servo if scene.simulates_joints else None
    gains = scene.servo_gains(f64, dev)
    return check_params(params, B, len(kin.bodies), dev, batched, gains, kin.bodies.tolist(), servos)


def step(
    scene: Scene,
    state: State,
    action: Action | None = None,
    params: Params | None = None,
    *,
    return_info: bool = False,
) -> State | tuple[State, StepInfo]:
    """Advance the scene by one time step (differentiable by autograd).

    Args:
        scene: bodies and settings.
        state: State(q, q_prev), each ([B,] N, 6), float32 or float64 (solved in float64, returned in its dtype:
            a float32 state knows velocities only to its coordinates' spacing over dt, so slow motion is rounded
            away); translations within 1e30 m, rotation vectors no longer than 1e6 rad.
        action: an :class:`Action`: forces ([B,] N, 3), torques ([B,] N, 3), kinematic targets ([B,] K, 6: poses in
            the ranges of the state's), and for
            articulations actuator controls ``ctrl`` and kinematic joint targets ``joints`` (see :class:`Action`);
            unbatched fields are shared by a batch; None: nothing acts, kinematic bodies stay put.
        params: differentiable mass / second moment / friction coefficient / servo gains kp and kv, shared ((Nd,),
            (Nd, 3, 3), (), (U,), (U,)) or per scene ((B, Nd), ...) (default: ``scene.params()``), float32 or
            float64 whatever the state's dtype (the step runs in float64; each field's gradient comes back in its
            dtype).
        return_info: also return the :class:`StepInfo` (solver statistics, end-of-step forces).

    Returns:
        The next State(q_next, q): dynamic rows solved, kinematic rows at their targets (the step turns a
        kinematic body the short way to its target's rotation, whichever of the equivalent rotation vectors omega
        and omega - 2 pi omega / |omega| the target is written as), static rows unchanged, rotation vectors of the
        moving rows re-centred when |omega| > pi; with ``return_info``, (State, StepInfo).

    Raises:
        ValueError: bad shapes, dtypes, devices or NaN/inf inputs (naming the argument), a start state that
            penetrates, or a kinematic target that penetrates a static body.
        TypeError: an argument of the wrong type.
        StepError: the Newton solve stopped without converging (the message says why), also after the
            ``scene.solver.substeps`` retries; or, for a float32 state, the solution rounded to float32 falls
            within the contact margin.
        NotImplementedError: under ``torch.func`` transforms (vmap, grad, jacrev, ...) or forward-mode AD, which do
            not pass through a step (differentiate with ``torch.autograd``).
        RuntimeError: in a backward that records a graph (``create_graph=True``, second derivatives): the step's
            backward is a first-order adjoint.
    """
    if action is not None and not isinstance(action, Action):
        raise TypeError(f"action must be a cfd_torch.Action or None, got {type(action).__name__}")
    if params is not None and not isinstance(params, Params):
        raise TypeError(f"params must be a cfd_torch.Params or None, got {type(params).__name__}")
    if not isinstance(state, State):
        raise TypeError(f"state must be a cfd_torch.State, got {type(state).__name__}")
    if not isinstance(return_info, bool):  # ("no" would return the info)
        raise TypeError(f"return_info must be a bool, got {type(return_info).__name__}")
    # the step's Function is an old-style autograd Function around numba kernels, which the transforms cannot pass,
    # without a forward-mode rule
    refuse_transforms(
        "cfd_torch.step: torch.func transforms (grad, jacrev, vmap, jvp) and forward-mode AD do not pass through a "
        "simulation step; differentiate with torch.autograd (loss.backward() or torch.autograd.grad)",
        *state,
        *(() if action is None else action),
        *(() if params is None else params),
    )
    _check_start(scene, state)
    N = scene.num_bodies
    batched = state.q.dim() == 3
    B = state.q.shape[0] if batched else 1
    dtype, dev = state.q.dtype, state.q.device
    action = Action() if action is None else action
    force = action.force if action.force is not None else torch.zeros(N, 3, dtype=dtype, device=dev)
    torque = action.torque if action.torque is not None else torch.zeros(N, 3, dtype=dtype, device=dev)
    check_state_tensor(force, "action.force", N, 3, B if batched else 0, like=state.q)
    check_state_tensor(torque, "action.torque", N, 3, B if batched else 0, like=state.q)
    K = scene.num_kinematic_bodies
    kin = scene.kinematic.to(dev)
    target = action.target if action.target is not None else state.q[..., kin[:K], :]
    check_state_tensor(
        target, "action.target", K, 6, B if batched else 0, like=state.q, bodies=scene.kinematic[:K].tolist()
    )
    if action.target is not None:
        check_pose_range(target, "action.target", scene.kinematic[:K].tolist())
    U = scene.num_actuators
    ctrl = action.ctrl if action.ctrl is not None else torch.zeros(U, dtype=dtype, device=dev)
    check_ctrl(ctrl, U, B if batched else None, state.q)
    params = _checked_params(scene, state, params)
    target = _batch(target, B)
    if action.joints is not None and not scene.kinematic_articulations:
        raise ValueError(
            "action.joints drives kinematic robots (articulation(..., kinematic=True)), and this scene has none"
        )
    if scene.kinematic_articulations:  # the kinematic robots' links: forward kinematics of action.joints
        if action.joints is None:
            links = _batch(state.q[..., kin[K:], :], B)
        else:
            check_ctrl(
                action.joints, scene.num_kinematic_coords, B if batched else None, state.q, "action.joints"
            )
            # (a hinge target of 1e20 rad is no particular angle)
            far = action.joints.detach().abs() > MAX_ROTATION
            if bool(far.any()):
                raise ValueError(
                    f"action.joints has a coordinate beyond {MAX_ROTATION:g} (rad or m; first at "
                    f"{first_row(far, what='coordinate')}): beyond 1e6 rad a hinge angle's float64 spacing exceeds "
                    "1.2e-10 rad, too coarse to say which angle it is; wrap hinge targets to within a few turns"
                )
            joints = action.joints.expand(B, -1) if action.joints.dim() == 1 else action.joints
            links = scene.kinematic_link_poses(joints, _batch(state.q, B)).to(dtype)
        target = torch.cat([target, links], 1)
    if action.target is not None or action.joints is not None:
        # each target rotation on the rotation-vector branch of the body's pose now (the same rotation): the step
        # moves kinematic coordinates along straight lines (the path checks, the push-out continuation, sub-steps),
        # so a turn across |omega| = pi given as omega - 2 pi omega / |omega| would be a turn of almost 2 pi back
        target = _unwrap_previous(target, _batch(state.q, B)[:, kin].to(target.dtype))
        check_targets_clear(scene, _batch(state.q, B), target)
    st = State(_batch(state.q, B), _batch(state.q_prev, B))
    force, torque = _batch(force, B), _batch(torque, B)
    ctrl = ctrl.expand(B, U) if ctrl.dim() == 1 else ctrl
    q_next, q_prev_next, si = _advance(scene, st, force, torque, target, ctrl, params)
    q_next = q_next.to(dtype)
    if dtype != torch.float64:
        _check_rounded(scene, q_next)
    q_prev_next = _unwrap_previous(st.q, q_next) if q_prev_next is None else q_prev_next.to(dtype)
    nxt = State(q_next, q_prev_next)
    if not batched:
        nxt = State(nxt.q[0], nxt.q_prev[0])
        si = si._replace(**{f: getattr(si, f)[0] for f in _PER_SCENE})
    return (nxt, si) if return_info else nxt


def _check_rounded(scene: Scene, q: torch.Tensor) -> None:
    """The step's end poses ``q`` (B, N, 6), the float64 solution rounded to a float32 state: a StepError if the
    rounding moved bodies within the contact margin of each other (the solution's gap beyond the margin was below
    the float32 spacing of its coordinates), which the next step could not start from."""
    B = q.shape[0]
    bad = infeasible_pairs(scene, q.detach().to(torch.float64))
    if bool(bad.any()):
        b, k = (int(i) for i in torch.nonzero(bad)[0])
        i, j = scene.pairs[k].tolist()
        spacing = float(torch.finfo(q.dtype).eps * q[b, :, :3].detach().abs().max())
        where = f" (scene {b})" if B > 1 else ""
        raise StepError(
            f"the step's solution rounded to the state's {q.dtype} puts bodies {i} and {j} "
            f"{infeasible_reason(scene)}{where}: its coordinates are spaced up to {spacing:.2g} m apart there, "
            "more than the bodies' gap; step float64 states (or a scene nearer the origin)"
        )


_PER_SCENE = ("newton_iters", "friction_contacts", "contact_force", "friction_force", "substeps")


def rollout(
    scene: Scene,
    state: State,
    actions: Sequence[Action | None] | int,
    params: Params | None = None,
    *,
    progress: bool = False,
) -> Trajectory:
    """Step ``len(actions)`` times (or ``actions`` times with no action), differentiable by autograd.

    Args:
        scene, state: as in :func:`step`.
        actions: a sequence of T :class:`Action` (an item None: nothing acts in that step), or a number of steps T
            with no action.
        params: as in :func:`step`, shared by every step (default: ``scene.params()``).
        progress: show a tqdm progress bar over the steps.

    Returns:
        The :class:`Trajectory` of the T + 1 states, the first included: fields (T + 1, [B,] N, 6); ``traj[t]`` is
        a State.

    Raises:
        TypeError: ``actions`` a single Action (for T steps with one action: ``[action] * T``), a tensor, or
            anything else that is neither a sequence of actions nor a number.
        ValueError: a negative number of steps, or any of :func:`step`'s.
        StepError: a step failed (as in :func:`step`).
    """
    if is_int(actions) and not isinstance(actions, torch.Tensor):
        actions = int(actions)
    if isinstance(actions, (bool, torch.Tensor)) or not isinstance(actions, (int, Iterable)):
        got = (
            f"a tensor of shape {tuple(actions.shape)}"
            if isinstance(actions, torch.Tensor)
            else repr(actions)
        )
        raise TypeError(f"actions must be a sequence of Action (or None) or a number of steps, got {got}")
    if isinstance(actions, (Action, State, Params)):  # NamedTuples: iterating one would step with its fields
        raise TypeError(
            f"actions must be a sequence of Action (or None) or a number of steps, got a single "
            f"{type(actions).__name__} (for T steps with one action: [action] * T)"
        )
    # (a count the list of actions cannot hold raised an OverflowError)
    if isinstance(actions, int) and not 0 <= actions <= _MAX_ROLLOUT_STEPS:
        raise ValueError(f"actions must be a number of steps in [0, {_MAX_ROLLOUT_STEPS:.0e}], got {actions}")
    if not isinstance(progress, (bool, np.bool_)):
        raise TypeError(f"progress must be a bool, got {progress!r}")
    seq = [None] * actions if isinstance(actions, int) else list(actions)
    if not seq:  # no step checks the inputs: the start state and the parameters are checked here
        _check_start(scene, state)
        _checked_params(scene, state, params)
    it = seq
    if progress:
        from tqdm import tqdm

        it = tqdm(seq, desc="rollout")
    states = [state]
    for a in it:
        states.append(step(scene, states[-1], a, params))
    return Trajectory(torch.stack([s.q for s in states]), torch.stack([s.q_prev for s in states]))


def pair_forces(scene: Scene, q: torch.Tensor) -> torch.Tensor:
    """Contact forces between every two bodies at poses q ([B,] N, 6): F[..., i, j, :] (N, N, 6) is the generalised
    force of body i on body j, -dP_ij/dq_j (columns 0-2 the world-frame force [N], 3-5 conjugate to the rotation
    vector); zero for pairs without contact (static-static, kinematic-static, excluded). Not differentiable:
    where q requires grad, a backward through F raises (a constant would drop its part of a loss's gradient
    silently).

    Raises:
        TypeError: scene is not a Scene, or q not a tensor.
        ValueError: q of the wrong shape or dtype, with NaN/inf, a translation beyond 1e30 m or a rotation vector
            longer than 1e6 rad; some pair penetrates or is within the contact margin (its potential is +inf: no
            force); q is float32 and a force overflows it (pass q as float64)."""
    refuse_transforms(
        "cfd_torch.pair_forces: torch.func transforms (grad, jacrev, vmap, jvp) and forward-mode AD do not pass "
        "through it (contact forces are not differentiated); call it on plain tensors (q.detach())",
        q,
    )
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a cfd_torch.Scene, got {type(scene).__name__}")
    check_state_tensor(q, "q", scene.num_bodies)
    check_pose_range(q, "q")
    poses = (q if q.dim() == 3 else q[None]).detach().to(torch.float64)
    B, N = poses.shape[:2]
    pairs = scene_pairs(scene, B).to(poses.device)
    F = poses.new_zeros(B, N, N, 6)
    if pairs.shape[0]:
        ev = scene.contact_model.evaluate(poses, pairs, 1)
        bad = ~torch.isfinite(ev.value)
        if bool(bad.any()):
            first = ", ".join(
                f"({a}, {b})" + (f" of scene {c}" if B > 1 else "") for c, a, b in pairs[bad][:5].tolist()
            )
            raise ValueError(
                f"q: bodies penetrate ({infeasible_reason(scene)}), where the "
                f"potential is +inf and has no force: pairs {first}"
            )
        g = ev.grad
        s, i, j = pairs.unbind(1)
        F[s, i, j] = -g[:, 6:]
        F[s, j, i] = -g[:, :6]
    F = narrowed(F, q.dtype, "pair_forces' F", "q")
    F = F if q.dim() == 3 else F[0]
    if q.requires_grad and torch.is_grad_enabled():
        F = refuse_derivative(F, q, _NO_GRADIENT.format(name="pair_forces"))
    return F
