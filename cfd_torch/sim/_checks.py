"""Input checks of the simulator's public functions: ValueErrors (TypeErrors for wrong types) naming the argument.

All of them but :func:`check_targets_clear` (one collision query, only when a target is given) are checks of types,
shapes, dtypes and devices plus one finiteness reduction per tensor, cheap next to a step.
"""

from __future__ import annotations

import torch

from .._autograd import outside_transforms, plain
from .._validate import FLOATS, check_dense, check_rotation_length, check_translation_range, max_coord
from .feasibility import contained, infeasible_reason
from .types import Params

__all__ = [
    "check_ctrl",
    "check_params",
    "check_pose_range",
    "check_state_tensor",
    "check_targets_clear",
    "first_row",
]


def check_state_tensor(
    x: object,
    name: str,
    n: int,
    cols: int = 6,
    batch: int | None = None,
    *,
    like: torch.Tensor | None = None,
    like_name: str = "state.q",
    bodies: list[int] | None = None,
) -> None:
    """x must be a finite float tensor of shape (n, cols) or (B, n, cols) (B = ``batch`` when given; ``batch=0``: no
    batch dimension allowed), with the dtype and device of ``like`` (named ``like_name``) when given. Devices and
    dtypes are compared before any value is read, so a tensor on another device fails here, not inside a kernel.
    ``bodies``: the scene's body of each of the n rows (default: row k is body k), for the messages."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    check_dense(x, name)
    ok = (
        x.shape[-2:] == (n, cols)
        and x.dim() in (2, 3)
        and (batch is None or x.dim() == 2 or (batch > 0 and x.shape[0] == batch))
    )
    if not ok:
        if batch == 0:
            want = f"({n}, {cols}) (state.q has no batch dimension)"
        else:
            want = f"({n}, {cols})" + (f" or ({batch}, {n}, {cols})" if batch else f" or (B, {n}, {cols})")
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    if x.dtype not in FLOATS:
        raise ValueError(f"{name} must be float32 or float64, got {x.dtype}")
    if like is not None:
        if x.device != like.device:
            raise ValueError(f"{name} is on {x.device} but {like_name} is on {like.device}: they must match")
        if x.dtype != like.dtype:
            raise ValueError(f"{name} is {x.dtype} but {like_name} is {like.dtype}: they must match")
    if x.device.type == "meta":
        raise ValueError(f"{name} is on the 'meta' device (shapes without data): a step needs its values")
    with outside_transforms():  # (values read from the plain tensor: the check runs under torch.func.vmap)
        bad = ~torch.isfinite(plain(x)).all(-1)
        if bool(bad.any()):
            raise ValueError(f"{name} contains NaN or inf (first at {first_row(bad, bodies)})")


def check_pose_range(x: torch.Tensor, name: str, bodies: list[int] | None = None) -> None:
    """Poses ``x`` ([B,] n, 6) must have translations within the contact functions' float64 limit (1e30 m) and
    rotation vectors no longer than ``MAX_ROTATION`` (a clear ValueError naming ``name`` and the first row;
    ``bodies``: the scene's body of each row, as in :func:`first_row`). The step computes in float64 whatever
    the dtype, so float32 poses get the float64 limit."""
    check_translation_range(x, name, lambda m: first_row(m, bodies), max_coord(torch.float64))
    check_rotation_length(x, name, lambda m: first_row(m, bodies))


def first_row(bad: torch.Tensor, bodies: list[int] | None = None, what: str = "body") -> str:
    """Where the (n,) or (B, n) mask ``bad`` is first True: "body i" or "scene b, body i" (``bodies``: the scene's
    body of each row, default the row itself; ``what``: what a row is, e.g. "actuator"); "index (...)" for more
    dimensions (vmap adds them in front)."""
    at = [int(i) for i in torch.nonzero(bad)[0]]
    if bad.dim() not in (1, 2):
        return f"index {tuple(at)}"
    row = at[-1] if bodies is None else bodies[at[-1]]
    return f"{what} {row}" if bad.dim() == 1 else f"scene {at[0]}, {what} {row}"


def check_params(
    params: Params,
    B: int,
    Nd: int,
    device: torch.device,
    batched: bool,
    gains: tuple[torch.Tensor, torch.Tensor],
    bodies: list[int] | None = None,
    servos: torch.Tensor | None = None,
) -> Params:
    """Finite, physical, on the state's device, each field shared or per scene; returned with a batch dimension B:
    mass > 0, friction >= 0, the symmetric part of S positive semi-definite with a positive definite inertia
    tr(S) I - S, servo gains >= 0 (None: ``gains``, the scene's (U,) kp and kv; ``servos`` (U,) bool: which
    actuators are servos, the others' entries unused: checked finite only). A message about values names the first
    offending scene (in a batch) and body (``bodies``: the scene's index of each of the Nd dynamic bodies) or
    actuator."""
    if not isinstance(params, Params):
        raise TypeError(f"params must be a cfd_torch.Params, got {type(params).__name__}")
    U = gains[0].shape[0]
    params = params._replace(
        kp=gains[0].to(device) if params.kp is None else params.kp,
        kv=gains[1].to(device) if params.kv is None else params.kv,
    )
    shapes = {"mass": (Nd,), "second_moment": (Nd, 3, 3), "friction": (), "kp": (U,), "kv": (U,)}
    for name in shapes:
        x = getattr(params, name)
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"params.{name} must be a torch.Tensor, got {type(x).__name__}")
        check_dense(x, f"params.{name}")
        if x.dtype not in FLOATS:
            raise ValueError(f"params.{name} must be float32 or float64, got {x.dtype}")
        if x.device != device:
            raise ValueError(f"params.{name} is on {x.device}, the state on {device}")
    fields = []
    shared = set()
    for name, shape in shapes.items():
        x = getattr(params, name)
        if x.shape == shape:
            x = x.expand(B, *shape)  # shared by the batch
            shared.add(name)
        elif x.shape != (B, *shape) or not batched:
            want = f"{shape} or {(B, *shape)}" if batched else f"{shape}"
            raise ValueError(f"params.{name} must have shape {want}, got {tuple(x.shape)}")
        fields.append(x)
    params = Params(*fields)

    def refuse(bad: torch.Tensor, message: str, name: str) -> None:
        """Raise ``message`` with where ``bad`` ((B,) or (B, K) over the scenes and the field's bodies or
        actuators) is first True; the scene only for a field given per scene in a batch."""
        if not bool(bad.any()):
            return
        if not batched or name in shared:
            bad = bad.any(0)  # alike in every scene
        if bad.dim() == 0:
            raise ValueError(message)
        what = {"friction": "scene", "kp": "actuator", "kv": "actuator"}.get(name, "body")
        raise ValueError(f"{message} (first at {first_row(bad, bodies if what == 'body' else None, what)})")

    for name in shapes:
        x = getattr(params, name).detach()
        refuse(
            ~torch.isfinite(x.flatten(-2)).all(-1) if name == "second_moment" else ~torch.isfinite(x),
            f"params.{name} contains NaN or inf",
            name,
        )
    refuse(params.mass.detach() <= 0, "params.mass must be positive", "mass")
    refuse(params.friction.detach() < 0, "params.friction must be >= 0", "friction")
    servo = torch.ones(U, dtype=torch.bool) if servos is None else servos
    for name in ("kp", "kv"):
        refuse(
            (getattr(params, name).detach() < 0) & servo.to(device),
            f"params.{name} must be >= 0 (a servo gain)",
            name,
        )
    refuse(
        ~_physical(params.second_moment),
        "params.second_moment must be positive semi-definite with a positive definite inertia",
        "second_moment",
    )
    return params


def _physical(S: torch.Tensor) -> torch.Tensor:
    """(...) bool: whether each (3, 3) second moment in ``S`` (..., 3, 3) is, in its symmetric part (what the step
    uses), positive semi-definite with a positive definite inertia tr(S) I - S."""
    shape = S.shape[:-2]
    S = S.detach().to(torch.float64).reshape(-1, 3, 3)
    S = 0.5 * (S + S.transpose(1, 2))
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    inertia = torch.diagonal(S, dim1=1, dim2=2).sum(-1)[:, None, None] * eye - S
    ok = (torch.linalg.eigvalsh(S) >= -1e-12 * S.abs().amax((1, 2))[:, None]).all(-1)
    return (ok & (torch.linalg.eigvalsh(inertia) > 0).all(-1)).reshape(shape)


def physical_second_moment(S: torch.Tensor) -> bool:
    """Whether every (3, 3) second moment in ``S`` (..., 3, 3) is, in its symmetric part (what the step uses),
    positive semi-definite with a positive definite inertia tr(S) I - S."""
    return bool(_physical(S).all())


def check_targets_clear(scene, q: torch.Tensor, target: torch.Tensor) -> None:
    """Raise a ValueError naming ``action.target`` if a kinematic body at its target is within the contact margin
    of (or intersects) a static body, or lies wholly inside one (or around one), the static bodies where ``q``
    (B, N, 6) has them: neither ever moves, so no step can resolve it. ``target`` (B, K, 6). One collision query
    over the kinematic-static pairs not excluded, then the inside test."""
    kin = scene.kinematic.tolist()
    static = torch.nonzero(scene.static_mask)[:, 0].tolist()
    excluded = {(min(a, b), max(a, b)) for a, b in scene.no_contact}
    pairs = [(min(k, s), max(k, s)) for k in kin for s in static if (min(k, s), max(k, s)) not in excluded]
    if not pairs:
        return
    B = q.shape[0]
    poses = q.detach().to(torch.float64).clone()
    poses[:, scene.kinematic.to(q.device)] = target.detach().to(torch.float64)
    base = torch.tensor(pairs, dtype=torch.long)
    rows = torch.cat([torch.arange(B).repeat_interleave(len(pairs))[:, None], base.repeat(B, 1)], 1)
    bad = scene.contact_model.infeasible(poses, rows.to(q.device)).cpu()

    def culprit(s: int, i: int, j: int) -> tuple[str, int, int, str]:
        """The message's head naming the kinematic body (or robot link) of the pair (i, j), it, the static body,
        and the scene (s) where there are several."""
        k, st = (i, j) if scene.bodies[i].kind == "kinematic" else (j, i)
        link = k in scene.kinematic[scene.num_kinematic_bodies :].tolist()
        head = f"{'action.joints' if link else 'action.target'}: kinematic {'robot link' if link else 'body'} {k}"
        return head, k, st, f" in scene {s}" if B > 1 else ""

    if bool(bad.any()):
        head, _, st, where = culprit(*rows[int(torch.nonzero(bad)[0, 0])].tolist())
        raise ValueError(
            f"{head} at its target penetrates static body {st} ({infeasible_reason(scene)}){where}; neither "
            "moves, so no step can resolve it"
        )
    inside = contained(scene, poses, pairs=base)
    if inside:
        s, i, j = inside[0]
        head, k, st, where = culprit(s, i, j)
        raise ValueError(
            f"{head} at its target lies {'inside' if k == i else 'around'} static body {st}{where} (their surfaces "
            "do not touch)"
        )


def check_ctrl(ctrl, U: int, B: int | None, like: torch.Tensor, name: str = "action.ctrl") -> None:
    """action.ctrl (or another per-scene vector ``name``): a float tensor (U,) or, in a batch of B scenes (``B``
    None: the state has no batch dimension), (B, U) of finite values, on the state's device and dtype."""
    what = "the scene's actuators" if name == "action.ctrl" else "the kinematic robots' coordinates"
    if not isinstance(ctrl, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(ctrl).__name__}")
    check_dense(ctrl, name)
    if not ctrl.is_floating_point():
        raise ValueError(f"{name} must be a float tensor, got {ctrl.dtype}")
    if ctrl.device != like.device or ctrl.dtype != like.dtype:
        raise ValueError(
            f"{name} is {ctrl.dtype} on {ctrl.device}, state.q {like.dtype} on {like.device}: they must match"
        )
    if B is None and ctrl.shape != (U,):
        raise ValueError(
            f"{name} must have shape ({U},) ({what}; state.q has no batch dimension), got {tuple(ctrl.shape)}"
        )
    if B is not None and ctrl.shape not in ((U,), (B, U)):
        raise ValueError(f"{name} must have shape ({U},) or ({B}, {U}) ({what}), got {tuple(ctrl.shape)}")
    bad = ~torch.isfinite(ctrl)
    if bool(bad.any()):
        row = "actuator" if name == "action.ctrl" else "coordinate"
        raise ValueError(f"{name} contains NaN or inf (first at {first_row(bad, what=row)})")
