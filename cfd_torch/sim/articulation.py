"""Articulated bodies: a tree of links joined by hinge and slide joints, on a floating or fixed base.

Every link is a body of the scene (a state row: the pose of its centre-of-mass frame, one contact hierarchy, exact
mass properties), so contact, inertia and friction see links exactly as they see free rigid bodies. What differs is
the step's unknowns: the base pose (translation and rotation vector of the root link's frame, floating bases only)
and one value per joint. :class:`ArticulatedKinematics` maps them to the link poses by forward kinematics, with its
closed-form first and second derivatives (forward mode along the tree, then the log map's derivatives), and adds
the joint-space terms of the incremental potential: armature, damping, springs, limits and actuation.

Forward kinematics (MuJoCo's `mj_kinematics`): the frame of link i, whose MJCF body has joints 1..k, is

    T_i = T_parent(i) [R(quat_i), pos_i] J_1(theta_1) .. J_k(theta_k),
    J = translate(c) rotate(a, theta - ref) translate(-c)     (hinge through anchor c along unit axis a, link frame)
    J = translate(a (theta - ref))                            (slide)

(the root's parent: the base; a fixed base whose root has joints hangs from its mount), and its state row is the
pose of its centre of mass, (p_i + R_i com_i, log R_i). The joint values of a state are recovered from each link's
frame in its parent's (:func:`_joint_values`: a hinge's angle in the turn centred on its range, or on its ref
without one).

Joint-space terms, for each joint with value theta (theta_t, theta_p: one and two steps earlier)::

    armature a (theta - 2 theta_t + theta_p)^2 / (2 dt^2)  +  damping d (theta - theta_t)^2 / (2 dt)
    + stiffness k (theta - springref)^2 / 2  +  sum over its servos kp gear^2 (theta - ctrl / gear)^2 / 2
    + limit barrier  -  tau (theta - theta_t)

with the servos' kv gear^2 added to the damping and tau the motors' torque (:meth:`ArticulatedKinematics.drive`).
A hinge's differences in time, and on a hinge without a range its spring's and servos' differences, are taken
mod 2 pi: the link poses tell its angle only up to whole turns, and a servo or spring then pulls the short way
round (in MuJoCo, whose qpos counts turns, a servo past pi pulls back the same way; from a state written a turn
away, MuJoCo's the long way). On a limited hinge the range fixes the angle, and they pull through the range.

The limit barrier is kappa b(x / w) on the distance x to each limit, with b(s) = -(s - 1)^2 ln s for 0 < s < 1
(zero beyond, C2 at s = 1, +inf at s <= 0): a joint never reaches its limit, whatever the torque.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from ..contact.bsh import BSH
from ..rotation import rotation_derivatives, rotation_matrix, rotation_vector
from .bodies import RigidBody
from .mjcf import load_mjcf, matrix_to_quat, quat_to_matrix

__all__ = ["Articulation", "articulation", "ArticulatedKinematics"]

#: the limit barrier's activation width (rad for hinges, m for slides; a joint whose range is narrower than ten
#: times it gets a tenth of its range) and stiffness [N m or N]
LIMIT_WIDTH = 0.02
LIMIT_STIFFNESS = 1.0


class Articulation:
    """A robot: links (bodies of the scene) in a tree of hinge and slide joints, on a floating or fixed base.

    Build it with :func:`articulation` from MJCF. A link carries the joints of its MJCF body (any number of hinges
    and slides, at most three hinges and three slides; MuJoCo composes them in MJCF order), the root link too when
    the base is fixed (the Gymnasium hopper's and swimmer's planar root joints, a cart's slide). Each joint moves a
    frame: frame 0 is the base (the root link's frame when the root has no joints; otherwise the world frame the
    robot is mounted in, at ``mount``), frame j + 1 the frame after joint j; a link's frame is the frame after its
    last joint.

    ``friction``: the MJCF geoms' shared sliding friction coefficient, None where they differ (the Scene has one
    coefficient, ``Scene(friction=...)``, 0 by default: pass this one to simulate the model's).

    Attributes (numpy, float64): per link (L) ``names``, ``parent``, ``offset_R`` (L, 3, 3) and ``offset_p``
    (L, 3) (link frame in its parent's at the joints' ``ref``; the root's: in the mount frame), ``com`` (L, 3),
    ``link_joints`` (the joints of each link), ``bodies`` (the L RigidBody links, centre-of-mass frames; a fixed
    base's joint-less root is a static body in its link frame); ``floating``, ``root_moves`` (a fixed base whose
    root has joints), ``mount`` (6,) (the pose of the world frame such a robot hangs from); per joint (J, link
    order then MJCF order) ``joint_names``, ``joint_kind`` "hinge" or "slide", ``joint_link``, ``axis`` and
    ``anchor`` (J, 3) in the link frame, ``ref`` (MuJoCo's qpos0: the transform is that of q - ref),
    ``lower``/``upper`` limits (+-inf: none), ``damping``, ``armature``, ``stiffness``, ``springref``,
    ``pd_stiffness`` and ``pd_damping`` (the position actuators' kp gear^2 and kv gear^2); per actuator
    ``actuator_joint``, ``gear``, ``ctrl_gain`` (1 for a motor, kp for a position actuator), ``ctrl_lower``,
    ``ctrl_upper`` (the control's clip; a motor's forcerange narrows it). An actuator's torque on its joint is
    MuJoCo's:

        motor:     tau = gear clip(ctrl)
        position:  tau = gear kp clip(ctrl) - kp gear^2 theta - kv gear^2 theta_dot

    The position actuator's stiffness and damping are implicit in the step (terms of the incremental potential, as
    the joint's own spring and damping), so a stiff PD target is stable at any dt.

    Joint values are recovered from the link poses of a state (the state rows are the links' poses): a hinge's in
    the turn centred on its range (so the whole range is inside it; a range of a whole turn or more is dropped, with
    a warning), or on its ref without one; for a link with three hinges at one anchor, whose two solutions give the
    same pose, the one with every joint of the link (hinges and slides) within its range, else the one nearer ref
    (the step reads the state a step earlier on the branch of the state now). Hinge axes that cannot be told apart
    (consecutive parallel hinges of one link) and more than three hinges or slides on a link are refused.
    """

    def __init__(self, model, *, max_edge: float | None = None, mount=None, kinematic: bool = False) -> None:
        links = model.links
        L = len(links)
        self.name = model.name
        self.friction = model.friction
        if not isinstance(kinematic, bool):
            raise ValueError(f"kinematic must be a bool, got {kinematic!r}")
        self.kinematic = kinematic
        self.floating = bool(model.floating)
        self.root_moves = bool(links[0].joints)
        if self.floating and self.root_moves:
            raise ValueError(
                f"articulation: the root link {links[0].name!r} has a free joint and other joints"
            )
        try:
            self.mount = np.zeros(6) if mount is None else np.asarray(mount, dtype=float).reshape(-1)
        except (TypeError, ValueError):  # (numpy's "could not convert string to float" named nothing)
            raise ValueError(
                f"mount must be a finite pose (translation, rotation vector) of 6 values, got {mount!r}"
            ) from None
        if self.mount.shape != (6,) or not np.isfinite(self.mount).all():
            raise ValueError(
                f"mount must be a finite pose (translation, rotation vector) of 6 values, got {mount!r}"
            )
        if mount is not None and not self.root_moves:
            raise ValueError(
                "mount places a fixed base whose root has joints; this robot's base is "
                + ("floating" if self.floating else "its root link, placed by the state's row")
            )
        self.names = tuple(link.name for link in links)
        self.parent = np.array([link.parent for link in links], dtype=np.int64)
        self.offset_R = np.stack([quat_to_matrix(link.quat) for link in links])
        self.offset_p = np.stack([np.asarray(link.pos, float) for link in links])
        self.com = np.stack([np.asarray(link.com, float) for link in links])
        joints, joint_link, link_joints = [], [], []
        for k, link in enumerate(links):
            kinds = [j.kind for j in link.joints]
            if kinds.count("hinge") > 3 or kinds.count("slide") > 3:
                raise ValueError(
                    f"articulation: link {link.name!r} has {kinds.count('hinge')} hinges and "
                    f"{kinds.count('slide')} slides; at most three of each per link are supported"
                )
            if k > 0 and not link.joints:
                raise ValueError(f"articulation: link {link.name!r} has no joint (weld it into its parent)")
            link_joints.append(tuple(range(len(joints), len(joints) + len(link.joints))))
            joints += list(link.joints)
            joint_link += [k] * len(link.joints)
        self.link_joints = tuple(link_joints)
        J = len(joints)
        self.joint_link = np.array(joint_link, dtype=np.int64)
        self.joint_kind = tuple(j.kind for j in joints)
        self.axis = np.array([np.asarray(j.axis, float) / np.linalg.norm(j.axis) for j in joints]).reshape(
            J, 3
        )
        self.anchor = np.array([np.asarray(j.pos, float) for j in joints]).reshape(J, 3)
        self.ref = np.array([float(getattr(j, "ref", 0.0)) for j in joints])
        self.joint_names = tuple(j.name for j in joints)
        rng = [j.range if j.range is not None else (-math.inf, math.inf) for j in joints]
        self.lower = np.array([r[0] for r in rng], dtype=float)
        self.upper = np.array([r[1] for r in rng], dtype=float)
        self.hinge = hinge = np.array([k == "hinge" for k in self.joint_kind], dtype=bool)
        limited = np.isfinite(self.lower) & np.isfinite(self.upper)
        for j in np.nonzero(hinge & limited & (self.upper - self.lower >= 2 * math.pi))[0]:
            warnings.warn(
                f"articulation: hinge joint {self.joint_names[j]!r} has the range [{self.lower[j]:.6g}, "
                f"{self.upper[j]:.6g}] rad, a whole turn or more: its angle is read from the link poses, which "
                "repeat every turn, so its limits cannot be told apart; it is simulated without limits",
                UserWarning,
                stacklevel=3,
            )
            self.lower[j], self.upper[j] = -math.inf, math.inf
            limited[j] = False
        #: hinges without a range: their springs and servos pull the short way round (differences mod 2 pi)
        self.free_hinge = hinge & ~limited
        # the window of a hinge's angle as read from link poses: centre + (-pi, pi], centred on its range (which then
        # lies inside it) or, without one, on its ref
        self.centre = self.ref.copy()
        both = hinge & limited
        self.centre[both] = 0.5 * (self.lower[both] + self.upper[both])
        self.damping = np.array([j.damping for j in joints], dtype=float)
        self.armature = np.array([j.armature for j in joints], dtype=float)
        self.stiffness = np.array([j.stiffness for j in joints], dtype=float)
        self.springref = np.array([j.springref for j in joints], dtype=float)
        ours = {name: i for i, name in enumerate(self.joint_names)}
        act_joint, gear, kp, kv, lo, hi = [], [], [], [], [], []
        self.pd_stiffness = np.zeros(J)
        self.pd_damping = np.zeros(J)
        for a in model.actuators:
            if a.kind not in ("motor", "position"):
                raise ValueError(
                    f"articulation: actuator {a.name!r} is a {a.kind!r} actuator; motor and position actuators "
                    "are supported"
                )
            r = a.ctrlrange if a.ctrlrange is not None else (-math.inf, math.inf)
            if a.forcerange is not None:
                if a.kind == "position":
                    raise ValueError(
                        f"articulation: position actuator {a.name!r} has a forcerange; its PD force is implicit in "
                        "the step (stiffness and damping of the joint) and cannot be clipped"
                    )
                r = (max(r[0], a.forcerange[0]), min(r[1], a.forcerange[1]))  # a motor's force is its control
            j = ours[model.joints[a.joint].name]
            act_joint.append(j)
            gear.append(a.gear)
            lo.append(r[0])
            hi.append(r[1])
            if a.kind == "motor":
                kp.append(0.0)
                kv.append(0.0)
            else:  # tau = gear kp ctrl - (kp gear^2) theta - (kv gear^2) theta_dot
                kp.append(a.kp)
                kv.append(a.kv)
                self.pd_stiffness[j] += a.kp * a.gear**2
                self.pd_damping[j] += a.kv * a.gear**2
        self.actuator_joint = np.array(act_joint, dtype=np.int64)
        self.gear = np.array(gear, dtype=float)
        self.servo = np.array([m.kind == "position" for m in model.actuators], dtype=bool)
        self.kp = np.array(kp, dtype=float)
        self.kv = np.array(kv, dtype=float)
        self.ctrl_gain = np.where(self.servo, self.kp, 1.0)
        self.ctrl_lower = np.array(lo, dtype=float)
        self.ctrl_upper = np.array(hi, dtype=float)
        static_root = not (self.floating or self.root_moves)
        bodies = []
        for k, link in enumerate(links):
            V = np.asarray(link.mesh.vertices, dtype=np.float64)
            F = np.asarray(link.mesh.faces, dtype=np.int64)
            if len(F) == 0:  # every link is a body of the scene, with a hierarchy over its surface
                raise ValueError(
                    f"link '{link.name}' has no geoms: every link needs a collision surface; give its MJCF body a geom "
                    "(a body welded to its parent without a joint is merged into it instead)"
                )
            if k == 0 and static_root:
                bodies.append(
                    RigidBody(BSH.build(V, F, max_edge=max_edge), "static", 0.0, torch.zeros(3, 3, dtype=torch.float64),
                              torch.zeros(3, dtype=torch.float64))
                )  # fmt: skip
                self.com[0] = 0.0  # a static body keeps its mesh's (the link's) frame
                continue
            S = np.asarray(link.second_moment, dtype=np.float64)
            if (
                kinematic
            ):  # posed by the action, massless to the step; its row is still its centre-of-mass pose
                mass, S = 0.0, np.zeros((3, 3))
            else:
                mass, S = float(link.mass), 0.5 * (S + S.T)
            bodies.append(
                RigidBody(
                    BSH.build(V - self.com[k], F, max_edge=max_edge), "kinematic" if kinematic else "dynamic",
                    mass, torch.from_numpy(S).clone(), torch.from_numpy(self.com[k].copy()),
                )
            )  # fmt: skip
        self.bodies = tuple(bodies)
        self.num_links = L
        self.num_joints = J
        self.num_actuators = len(self.gear)
        #: the first link that moves (a fixed base's joint-less root does not)
        self.first_moving = 1 if static_root else 0
        #: coordinates of the step: the base pose (6, floating only), then the joints
        self.num_coords = (6 if self.floating else 0) + J
        # frames: 0 the base, j + 1 after joint j; a link's frame is the one after its last joint
        self.link_frame = np.array([js[-1] + 1 if js else 0 for js in self.link_joints], dtype=np.int64)
        self.frame_parent = np.zeros(J + 1, dtype=np.int64)
        self.frame_R = np.tile(np.eye(3), (J + 1, 1, 1))
        self.frame_p = np.zeros((J + 1, 3))
        for k, js in enumerate(self.link_joints):
            for m, j in enumerate(js):
                if m == 0:  # the first joint of a link: from its parent link's frame (the root's: the mount)
                    self.frame_parent[j + 1] = 0 if k == 0 else self.link_frame[self.parent[k]]
                    self.frame_R[j + 1], self.frame_p[j + 1] = self.offset_R[k], self.offset_p[k]
                else:
                    self.frame_parent[j + 1] = j
        self._groups = _joint_groups(self)  # links by joint pattern, for recovering joint values
        self._levels, self._level_back = _levels(self)  # the frame tree by depth, for the forward kinematics
        self._fk_table = _fk_table(self)  # the same flattened, for the numba kernel of the link rows

    @property
    def model_base(self) -> torch.Tensor:
        """(6,) float64, the pose of the root link's frame that the MJCF gives (translation, rotation vector): pass
        it as ``poses(joints, base)`` to place the robot where MuJoCo would (``poses``' default is the origin)."""
        quat = torch.as_tensor(matrix_to_quat(self.offset_R[0]), dtype=torch.float64)
        return torch.cat(
            [torch.as_tensor(self.offset_p[0], dtype=torch.float64), rotation_vector(quat[None])[0]]
        )

    def poses(self, joints: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
        """([B,] L, 6) state rows of the links (centre-of-mass poses) for joint values ([B,] J) and the base pose
        ([B,] 6) of the root link's frame (translation, rotation vector; a fixed base: where its root stands,
        default the origin, not the MJCF's pose: that is :attr:`model_base`). A fixed base whose root has joints
        hangs from its ``mount``: ``base`` must be None."""
        single = isinstance(joints, torch.Tensor) and joints.dim() == 1
        th = joints[None] if single else joints
        _check_float(th, "joints", (None, self.num_joints), f"([B,] {self.num_joints})")
        if base is not None:
            b = base[None] if isinstance(base, torch.Tensor) and base.dim() == 1 else base
            _check_float(b, "base", (None, 6), "([B,] 6) (translation, rotation vector)", th.dtype)
            if b.shape[0] not in (1, th.shape[0]):
                raise ValueError(f"base has {b.shape[0]} rows for {th.shape[0]} sets of joints")
        if self.root_moves and base is not None:
            raise ValueError(
                f"base: {self.name!r} is mounted where its root's joints hang from (articulation(..., mount=)); "
                "pass base=None"
            )
        b = (th.new_zeros(th.shape[0], 6) if base is None else b).expand(th.shape[0], 6)
        if self.floating:
            rows = _fk_rows(self, torch.cat([b, th], 1), None)
        else:
            rows = _fk_rows(self, th, b)
            if not self.root_moves:
                rows = torch.cat([b[:, None], rows[:, 1:]], 1)
        return rows[0] if single else rows

    def moving_rows(self, coords: torch.Tensor, root: torch.Tensor | None) -> torch.Tensor:
        """(A, L - first_moving, 6) the state rows of the links that move, for coordinates (A, Qa) (the base pose
        if floating, then the joints), a joint-less fixed root at ``root`` (A, 6) (ignored otherwise: may be
        None). Differentiable in both."""
        _check_float(coords, "coords", (None, self.num_coords), f"(A, {self.num_coords})")
        if not self.floating and not self.root_moves:
            _check_float(root, "root", (coords.shape[0], 6), f"({coords.shape[0]}, 6)", coords.dtype)
        return _moving_rows(self, coords, root)

    def coords(self, rows: torch.Tensor, near: torch.Tensor | None = None) -> torch.Tensor:
        """([A,] Qa) the coordinates (base pose if floating, then the joints) of the link rows ([A,] L, 6), as
        :meth:`poses` gives them: the inverse of the forward kinematics; where several coordinates give the same
        rows (three hinges at one anchor), the one nearest ``near`` ([A,] Qa) if given, else the one with every
        joint within its range. Rows that no coordinates give (a link moved off its joint) are read as the
        nearest fit: :meth:`ArticulatedKinematics.check_rows` tells."""
        L, Q = self.num_links, self.num_coords
        single = isinstance(rows, torch.Tensor) and rows.dim() == 2
        _check_float(rows[None] if single else rows, "rows", (None, L, 6), f"([A,] {L}, 6)")
        r = rows[None] if single else rows
        if near is not None:
            near = near[None] if single and isinstance(near, torch.Tensor) else near
            _check_float(near, "near", (r.shape[0], Q), f"([A,] {Q}) like rows", r.dtype)
        out = _joint_values(self, r, near)
        return out[0] if single else out


def articulation(
    source, *, max_edge: float | None = None, mount=None, kinematic: bool = False, **mjcf_options
) -> Articulation:
    """An :class:`Articulation` from an MJCF or URDF file or string (:func:`cfd_torch.sim.mjcf.load_mjcf`; its
    options pass through). A free joint on the root body makes a floating base; without one the base is fixed: a
    joint-less root stands where the state puts it, a root with joints (a cart's slide, a planar robot's root
    joints) hangs from the MJCF's world frame placed at ``mount`` (translation, rotation vector; default the
    origin).

    ``kinematic=True`` makes a robot whose coordinates follow the action exactly (a pusher): its moving links are
    kinematic bodies, posed each step by forward kinematics of ``Action.joints``, pushing the dynamic bodies
    through contact and differentiable in those coordinates; its actuators, masses, limits and damping play no
    part (its mesh geoms' masses are not read: ``mesh_masses=False``, so an open mesh loads).

    Args:
        source: MJCF or URDF text, or the path of such a file.
        max_edge: if given, each link's mesh is refined (midpoint splits) until no triangle edge is longer [m]
            (:meth:`cfd_torch.BSH.build`).
        mount: the (6,) pose of the world frame a fixed-base robot hangs from; default the origin.
        kinematic: a robot posed by ``Action.joints`` (above).
        **mjcf_options: :func:`cfd_torch.sim.mjcf.load_mjcf`'s (e.g. ``meshdir``, ``sphere_subdivisions``).

    Raises:
        ValueError: as :func:`cfd_torch.sim.mjcf.load_mjcf` (a feature outside the supported set, naming it; a
            model MuJoCo cannot read), or a bad ``max_edge`` or ``mount``.
        TypeError: ``source`` or an option of the wrong type.
    """
    return Articulation(
        load_mjcf(source, **{"mesh_masses": not kinematic, **mjcf_options}),
        max_edge=max_edge,
        mount=mount,
        kinematic=kinematic,
    )


# ------------------------------------------------------------------------------------------- forward kinematics
class _Level(NamedTuple):
    """The joint frames at one depth of the frame tree (n of them)."""

    frames: torch.Tensor  # (n,) frame indices
    parent: torch.Tensor  # (n,) their parents' positions in the level above
    joint: torch.Tensor  # (n,) their joint indices (frame - 1)
    Ro: torch.Tensor  # (n, 3, 3) the frame in its parent's at the joint's ref
    po: torch.Tensor  # (n, 3)
    K: torch.Tensor  # (n, 3, 3) [axis]_x for hinges, 0 for slides
    K2: torch.Tensor  # (n, 3, 3) K @ K
    anchor: torch.Tensor  # (n, 3) hinge anchor (link frame)
    slide: torch.Tensor  # (n, 3) slide axis, 0 for hinges
    ref: torch.Tensor  # (n,) the joint value of the MJCF pose

    def to(self, dtype: torch.dtype, device: torch.device) -> _Level:
        return _Level(
            *(x.to(device) for x in self[:3]), *(x.to(dtype=dtype, device=device) for x in self[3:])
        )


def _skew(a: np.ndarray) -> np.ndarray:
    """(n, 3, 3) [a]_x of (n, 3) vectors."""
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    return K - K.transpose(0, 2, 1)


def _levels(art: Articulation) -> tuple[tuple[_Level, ...], torch.Tensor]:
    """The frame tree by depth (frame 0 excluded; float64 CPU tensors) and the permutation (J + 1,) from level
    order (frame 0, then level by level) back to frame order."""
    F = art.num_joints + 1
    depth = np.zeros(F, dtype=np.int64)
    for f in range(1, F):  # parents come before children
        depth[f] = depth[art.frame_parent[f]] + 1
    hinge = np.array([k == "hinge" for k in art.joint_kind], dtype=float).reshape(-1, 1)
    K = _skew(art.axis * hinge)
    order, above, levels = [0], np.array([0]), []
    for d in range(1, int(depth.max(initial=0)) + 1):
        frames = np.flatnonzero(depth == d)
        j = frames - 1
        fields = (
            frames, np.searchsorted(above, art.frame_parent[frames]), j,  # ``above`` is sorted
            art.frame_R[frames], art.frame_p[frames], K[j], K[j] @ K[j], (art.anchor * hinge)[j],
            (art.axis * (1.0 - hinge))[j], art.ref[j],
        )  # fmt: skip
        levels.append(_Level(*(torch.from_numpy(np.ascontiguousarray(x)) for x in fields)))
        order += list(frames)
        above = frames
    return tuple(levels), torch.from_numpy(np.argsort(order))


def _fk_table(art: Articulation) -> tuple[np.ndarray, ...]:
    """The frame tree in level order as flat arrays for :func:`cfd_torch.sim._kinematics_numba.fk_rows`: each frame's
    parent (its level-order index; frame 0, the base, is its own), joint, Ro, po, K, K2, anchor, slide, ref, then
    each link's frame (level-order index) and centre of mass."""
    F = art.num_joints + 1
    parent, joint = np.zeros(F, dtype=np.int64), np.zeros(F, dtype=np.int64)
    ref = np.zeros(F)
    mats = {name: np.zeros((F, 3, 3)) for name in ("Ro", "K", "K2")}
    vecs = {name: np.zeros((F, 3)) for name in ("po", "anchor", "slide")}
    above, at = 0, 1  # level-order index of the level above's first frame, and of the next frame
    for lv in art._levels:
        n = len(lv.frames)
        sl = slice(at, at + n)
        parent[sl] = above + lv.parent.numpy()
        joint[sl] = lv.joint.numpy()
        ref[sl] = lv.ref.numpy()
        for name in mats:
            mats[name][sl] = getattr(lv, name).numpy()
        for name in vecs:
            vecs[name][sl] = getattr(lv, name).numpy()
        above, at = at, at + n
    link = art._level_back.numpy()[np.asarray(art.link_frame)]
    return (
        parent, joint, mats["Ro"], vecs["po"], mats["K"], mats["K2"], vecs["anchor"], vecs["slide"], ref, link,
        np.ascontiguousarray(art.com, dtype=np.float64),
    )  # fmt: skip


def _quat_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """(A, 4) unit quaternions [w, x, y, z] (w >= 0) of rotation matrices (A, 3, 3) (Shepperd's method; every
    branch finite, so autograd through the unused ones is harmless)."""
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = r00 + r11 + r22
    d = torch.stack([tr, r00, r11, r22], 1)
    k = d.argmax(1)
    s0 = torch.sqrt((1.0 + tr).clamp_min(1e-20)) * 2.0
    s1 = torch.sqrt((1.0 + r00 - r11 - r22).clamp_min(1e-20)) * 2.0
    s2 = torch.sqrt((1.0 - r00 + r11 - r22).clamp_min(1e-20)) * 2.0
    s3 = torch.sqrt((1.0 - r00 - r11 + r22).clamp_min(1e-20)) * 2.0
    a21, a12, a02, a20, a10, a01 = R[:, 2, 1], R[:, 1, 2], R[:, 0, 2], R[:, 2, 0], R[:, 1, 0], R[:, 0, 1]
    q0 = torch.stack([0.25 * s0, (a21 - a12) / s0, (a02 - a20) / s0, (a10 - a01) / s0], 1)
    q1 = torch.stack([(a21 - a12) / s1, 0.25 * s1, (a01 + a10) / s1, (a02 + a20) / s1], 1)
    q2 = torch.stack([(a02 - a20) / s2, (a01 + a10) / s2, 0.25 * s2, (a12 + a21) / s2], 1)
    q3 = torch.stack([(a10 - a01) / s3, (a02 + a20) / s3, (a12 + a21) / s3, 0.25 * s3], 1)
    q = torch.where(
        (k == 0)[:, None], q0, torch.where((k == 1)[:, None], q1, torch.where((k == 2)[:, None], q2, q3))
    )
    return torch.where(q[:, :1] < 0, -q, q)


def _vee(S: torch.Tensor) -> torch.Tensor:
    """(..., 3) the axial vector of the skew part of (..., 3, 3) matrices."""
    return 0.5 * torch.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]], -1
    )


def _remounted(art: Articulation, translation: np.ndarray) -> Articulation:
    """A copy of ``art`` hung from its mount moved to ``translation`` (3,) (its rotation kept)."""
    out = copy.copy(art)
    out.mount = np.concatenate([translation, art.mount[3:]])
    return out


def _base_and_joints(art: Articulation, q: torch.Tensor, root: torch.Tensor | None):
    """The base frame's pose (A, 6) (a floating base's coordinates, the mount of a root with joints, else ``root``)
    and the joint values (A, J) of coordinates q (A, Qa)."""
    if art.floating:
        return q[:, :6], q[:, 6:]
    if art.root_moves:
        return torch.as_tensor(art.mount, dtype=q.dtype, device=q.device).expand(q.shape[0], 6), q
    return root, q


def _numba_path(q: torch.Tensor, root: torch.Tensor | None) -> bool:
    """Whether the numba kinematics may serve: CPU float64 inputs of which no autograd graph is wanted."""
    graph = torch.is_grad_enabled() and (q.requires_grad or (root is not None and root.requires_grad))
    return q.device.type == "cpu" and q.dtype == torch.float64 and not graph


def _chain(art: Articulation, q: torch.Tensor, root: torch.Tensor | None, order: int) -> list[torch.Tensor]:
    """The link frames and, up to ``order``, their derivatives in the coordinates q (A, Q) (base pose first if
    floating; a fixed base's frame 0 is root (A, 6), or the mount if its root has joints): R (A, L, 3, 3),
    p (A, L, 3), dR (A, L, Q, 3, 3), dp (A, L, Q, 3), d2R (A, L, Q, Q, 3, 3), d2p (A, L, Q, Q, 3).

    Forward mode along the frame tree, one depth at a time. A joint's frame is its parent frame's times its local
    transform G(theta) = [Ro Rj(t), po + Ro (c - Rj(t) c + s t)], t = theta - ref (hinge: Rj = I + sin K +
    (1 - cos) K^2, K = [axis]_x, anchor c; slide: Rj = I, axis s), so with E_a = 1 when coordinate a is the
    frame's own joint::

        R = Rp Rl,                        p = pp + Rp pl
        dR_a = dRp_a Rl + E_a Rp Rl',     dp_a = dpp_a + dRp_a pl + E_a Rp pl'
        d2R_ab = d2Rp_ab Rl + E_b dRp_a Rl' + E_a dRp_b Rl' + E_a E_b Rp Rl''     (d2p_ab alike)

    A floating root is [exp(w), t]: its derivatives are those of :func:`cfd_torch.rotation.rotation_derivatives`
    and the identity; a fixed root has none.
    """
    if order and _numba_path(q, root):
        return _chain_numba(art, q, root, order)
    levels = [lv.to(q.dtype, q.device) for lv in art._levels]
    back = art._level_back.to(q.device)
    A, Q = q.shape
    base, th = _base_and_joints(art, q, root)
    if order and art.floating:
        R0, dE, d2E = rotation_derivatives(base[:, 3:], order)
    else:
        R0 = rotation_matrix(base[:, 3:])
    out = [[R0[:, None]], [base[:, None, :3]]]
    if order:
        dR0, dp0 = q.new_zeros(A, 1, Q, 3, 3), q.new_zeros(A, 1, Q, 3)
        if art.floating:
            dR0[:, 0, 3:6] = dE.permute(0, 3, 1, 2)
            dp0[:, 0, :3] = torch.eye(3, dtype=q.dtype, device=q.device)
        out += [[dR0], [dp0]]
    if order >= 2:
        d2R0, d2p0 = q.new_zeros(A, 1, Q, Q, 3, 3), q.new_zeros(A, 1, Q, Q, 3)
        if art.floating:
            d2R0[:, 0, 3:6, 3:6] = d2E.permute(0, 3, 4, 1, 2)
        out += [[d2R0], [d2p0]]
    first = 6 if art.floating else 0
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    mv = lambda M, v: (M @ v[..., None])[..., 0]  # noqa: E731  (batched matrix-vector products)
    for lv in levels:
        Rp, pp = out[0][-1][:, lv.parent], out[1][-1][:, lv.parent]  # (A, n, 3, 3), (A, n, 3)
        t = th[:, lv.joint] - lv.ref  # (A, n)
        s, c = torch.sin(t)[..., None, None], torch.cos(t)[..., None, None]
        Rj = eye + s * lv.K + (1.0 - c) * lv.K2
        Rl = lv.Ro @ Rj
        pl = lv.po + mv(lv.Ro, lv.anchor - mv(Rj, lv.anchor) + t[..., None] * lv.slide)
        out[0].append(Rp @ Rl)
        out[1].append(pp + mv(Rp, pl))
        if not order:
            continue
        E = torch.nn.functional.one_hot(first + lv.joint, Q).to(q.dtype)  # (n, Q)
        dRp, dpp = out[2][-1][:, lv.parent], out[3][-1][:, lv.parent]  # (A, n, Q, 3, 3), (A, n, Q, 3)
        Rj1 = c * lv.K + s * lv.K2
        Rl1, pl1 = lv.Ro @ Rj1, mv(lv.Ro, lv.slide - mv(Rj1, lv.anchor))
        out[2].append(dRp @ Rl[:, :, None] + E[..., None, None] * (Rp @ Rl1)[:, :, None])
        out[3].append(dpp + mv(dRp, pl[:, :, None]) + E[..., None] * mv(Rp, pl1)[:, :, None])
        if order < 2:
            continue
        d2Rp, d2pp = out[4][-1][:, lv.parent], out[5][-1][:, lv.parent]  # (A, n, Q, Q, 3, 3), (A, n, Q, Q, 3)
        Rj2 = c * lv.K2 - s * lv.K
        Rl2, pl2 = lv.Ro @ Rj2, -mv(lv.Ro, mv(Rj2, lv.anchor))
        EE = E[:, :, None] * E[:, None, :]  # (n, Q, Q)
        X = (dRp @ Rl1[:, :, None])[:, :, :, None] * E[
            :, None, :, None, None
        ]  # (A, n, Q, Q, 3, 3) E_b dRp_a Rl'
        x = mv(dRp, pl1[:, :, None])[:, :, :, None] * E[:, None, :, None]  # (A, n, Q, Q, 3) E_b dRp_a pl'
        out[4].append(
            d2Rp @ Rl[:, :, None, None]
            + X
            + X.transpose(2, 3)
            + EE[..., None, None] * (Rp @ Rl2)[:, :, None, None]
        )
        out[5].append(
            d2pp
            + mv(d2Rp, pl[:, :, None, None])
            + x
            + x.transpose(2, 3)
            + EE[..., None] * mv(Rp, pl2)[:, :, None, None]
        )
    link = torch.as_tensor(art.link_frame, device=q.device)
    return [torch.cat(parts, 1)[:, back][:, link] for parts in out]


def _chain_numba(
    art: Articulation, q: torch.Tensor, root: torch.Tensor | None, order: int
) -> list[torch.Tensor]:
    """:func:`_chain` at order 1 or 2 by the numba kernel (CPU, float64, no autograd)."""
    from ._kinematics_numba import chain

    A, Q = q.shape
    base, th = _base_and_joints(art, q, root)
    dR0 = q.new_zeros(A, Q, 3, 3)
    d2R0 = q.new_zeros(A, Q if order >= 2 else 0, Q if order >= 2 else 0, 3, 3)
    if art.floating:
        R0, dE, d2E = rotation_derivatives(base[:, 3:], order)
        dR0[:, 3:6] = dE.permute(0, 3, 1, 2)
        if order >= 2:
            d2R0[:, 3:6, 3:6] = d2E.permute(0, 3, 4, 1, 2)
    else:
        R0 = rotation_matrix(base[:, 3:])
    parent, joint, Ro, po, K, K2, anchor, slide, ref, link, _ = art._fk_table
    out = chain(
        R0.contiguous().numpy(), base[:, :3].contiguous().numpy(), dR0.numpy(), d2R0.numpy(),
        th.contiguous().numpy(), 6 if art.floating else 0, parent, joint, Ro, po, K, K2, anchor, slide, ref, link,
        int(order),
    )  # fmt: skip
    return [torch.from_numpy(x) for x in out[: 4 if order < 2 else 6]]


def _check_float(x, name: str, shape: tuple, want: str, dtype: torch.dtype | None = None) -> None:
    """Raise ValueError naming ``name`` unless x is a finite float tensor (of ``dtype`` if given) whose shape
    matches ``shape`` (None: any size), described as ``want``."""
    if (
        not isinstance(x, torch.Tensor)
        or not x.is_floating_point()
        or (dtype is not None and x.dtype != dtype)
        or x.dim() != len(shape)
        or any(n is not None and m != n for m, n in zip(x.shape, shape, strict=True))
    ):
        got = (x.dtype, tuple(x.shape)) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{name} must be a {dtype or 'float'} tensor of shape {want}, got {got}")
    if not bool(torch.isfinite(x.detach()).all()):
        raise ValueError(f"{name} contains NaN or inf")


def _moving_rows(art: Articulation, coords: torch.Tensor, root: torch.Tensor | None) -> torch.Tensor:
    """:meth:`Articulation.moving_rows` without its checks (the step's own calls)."""
    return _fk_rows(art, coords, None if art.floating else root)[:, art.first_moving :]


def _fk_frames(art: Articulation, q: torch.Tensor, root: torch.Tensor | None):
    """Link frames (R (A, L, 3, 3), p (A, L, 3)) for coordinates q (A, Qa) (base pose first if floating) and, for a
    fixed base with a joint-less root, the root link frame's pose root (A, 6) (a root with joints hangs from the
    articulation's mount)."""
    R, p = _chain(art, q, root, 0)
    return R, p


def _fk_rows(art: Articulation, q: torch.Tensor, root: torch.Tensor | None) -> torch.Tensor:
    """(A, L, 6) the links' centre-of-mass poses (translation, rotation vector). On the CPU in float64 with no
    autograd wanted, one numba loop (the step's many evaluations and checks call this; the torch form below costs
    a few dozen small tensor operations)."""
    if _numba_path(q, root):
        from ._kinematics_numba import fk_rows

        base, th = _base_and_joints(art, q, root)
        R0 = rotation_matrix(base[:, 3:])
        return torch.from_numpy(
            fk_rows(
                R0.contiguous().numpy(),
                base[:, :3].contiguous().numpy(),
                th.contiguous().numpy(),
                *art._fk_table,
            )
        )
    R, p = _fk_frames(art, q, root)
    A, L = R.shape[:2]
    com = torch.as_tensor(art.com, dtype=q.dtype, device=q.device)
    t = p + (R @ com[None, :, :, None])[..., 0]
    w = rotation_vector(_quat_from_matrix(R.reshape(A * L, 3, 3))).reshape(A, L, 3)
    return torch.cat([t, w], -1)


def _fk_derivatives(
    art: Articulation, q: torch.Tensor, root: torch.Tensor | None, lo: int, g: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The Jacobian J (A, 6 (L - lo), Q) of the rows of links lo.. (:func:`_fk_rows`) in q (A, Q) and, for row
    gradients g (A, L - lo, 6), the contraction sum_k g_k d2 row_k / dq dq (A, Q, Q).

    Centre of mass x = p + R com: its derivatives are those of p and R applied to com. Rotation vector w = log R:
    differentiating R(q) = exp(w(q)) with the exponential's derivatives E_i = dexp/dw_i, E_ij
    (:func:`cfd_torch.rotation.rotation_derivatives`)::

        dR_a = sum_i E_i w_i,a                     =>  vee(dR_a R^T) = G w_a,  G e_i = vee(E_i R^T)
        d2R_ab = sum_ij E_ij w_i,a w_j,b + sum_i E_i w_i,ab
                                                   =>  G w_ab = vee(M_ab R^T),  M_ab = d2R_ab - sum_ij E_ij w_i,a w_j,b

    (G: the left Jacobian of exp, invertible for |w| <= pi; E_i R^T and M_ab R^T are skew). Contracted with
    g_w and h = G^-T g_w: g_w . w_ab = h . vee(M_ab R^T) = <M_ab, P> with P = [h]_x R / 2.

    Where the numba kinematics serve (:func:`_numba_path`, and g wants no graph), one numba loop
    (``_kinematics_numba.row_derivatives``) evaluates these formulas; else the tensor form below.
    """
    chain = _chain(art, q, root, 1 if g is None else 2)
    if _numba_path(q, root) and (g is None or not (torch.is_grad_enabled() and g.requires_grad)):
        from .._rotation_numba import _CA, _CB
        from ._kinematics_numba import row_derivatives

        R, _, dR, dp, *second = (x.contiguous().numpy() for x in chain)
        gn = g.contiguous().numpy() if g is not None else np.zeros((0, 0, 6))
        d2R, d2p = second if g is not None else (np.zeros((0,) * 6), np.zeros((0,) * 5))
        J, S = row_derivatives(R, dR, dp, d2R, d2p, art._fk_table[-1], gn, lo, _CA, _CB, g is not None)
        return torch.from_numpy(J), (torch.from_numpy(S) if g is not None else None)
    R, p, dR, dp = (x[:, lo:] for x in chain[:4])
    A, La, Q = dR.shape[:3]
    com = torch.as_tensor(art.com[lo:], dtype=q.dtype, device=q.device)  # (La, 3)
    w = rotation_vector(_quat_from_matrix(R.reshape(A * La, 3, 3)))
    Re, dE, d2E = rotation_derivatives(w, 1 if g is None else 2)
    G = _vee(dE.permute(0, 3, 1, 2) @ Re.transpose(-1, -2)[:, None]).transpose(-1, -2).reshape(A, La, 3, 3)
    V = _vee(dR @ R.transpose(-1, -2)[:, :, None])  # (A, La, Q, 3): world angular velocities
    Om = torch.linalg.solve(G, V.transpose(-1, -2))  # (A, La, 3, Q) = dw/dq
    Jx = dp + (dR @ com[:, None, :, None])[..., 0]  # (A, La, Q, 3)
    J = torch.cat([Jx.transpose(-1, -2), Om], -2).reshape(A, 6 * La, Q)
    if g is None:
        return J, None
    d2R, d2p = (x[:, lo:] for x in chain[4:])
    gx, gw = g[..., :3], g[..., 3:]
    h = torch.linalg.solve(G.transpose(-1, -2), gw[..., None])[..., 0]  # (A, La, 3)
    z = torch.zeros_like(h[..., 0])
    H = torch.stack(
        [torch.stack([z, -h[..., 2], h[..., 1]], -1), torch.stack([h[..., 2], z, -h[..., 0]], -1),
         torch.stack([-h[..., 1], h[..., 0], z], -1)], -2,
    )  # fmt: skip
    P = 0.5 * H @ R  # (A, La, 3, 3)
    C = P + gx[..., :, None] * com[:, None, :]  # g_x . d2R com = <d2R, g_x com^T>
    N = torch.einsum("emnij,emn->eij", d2E, P.reshape(A * La, 3, 3)).reshape(A, La, 3, 3)
    second = (
        torch.einsum("alxymn,almn->axy", d2R, C)
        + torch.einsum("alxym,alm->axy", d2p, gx)
        - torch.einsum("alix,alij,aljy->axy", Om, N, Om)
    )
    return J, second


class _Group(NamedTuple):
    """Links whose joints follow one pattern of kinds (n links, k joints each), for recovering joint values."""

    kinds: tuple[str, ...]
    links: torch.Tensor  # (n,)
    joints: torch.Tensor  # (n, k) joint indices, in order


def _joint_groups(art: Articulation) -> tuple[_Group, ...]:
    """The links with joints grouped by pattern; refuses links whose joint values cannot be told apart from their
    pose (consecutive parallel hinges, dependent slide axes)."""
    patterns: dict[tuple[str, ...], list[int]] = {}
    for k, js in enumerate(art.link_joints):
        if js:
            patterns.setdefault(tuple(art.joint_kind[j] for j in js), []).append(k)
        hinges = [art.axis[j] for j in js if art.joint_kind[j] == "hinge"]
        if any(abs(float(u @ v)) > 1.0 - 1e-9 for u, v in zip(hinges, hinges[1:], strict=False)):
            raise ValueError(
                f"articulation: link {art.names[k]!r} has two consecutive parallel hinges; their angles cannot be "
                "told apart"
            )
        slides = np.array([art.axis[j] for j in js if art.joint_kind[j] == "slide"]).reshape(-1, 3)
        if len(slides) and np.linalg.matrix_rank(slides, tol=1e-9) < len(slides):
            raise ValueError(f"articulation: link {art.names[k]!r} has slides along dependent axes")
    return tuple(
        _Group(
            kinds,
            torch.tensor(links),
            torch.tensor([art.link_joints[k] for k in links]).reshape(len(links), -1),
        )
        for kinds, links in patterns.items()
    )


def _rot(a: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations by angles t (...) about unit axes a (..., 3)."""
    z = torch.zeros_like(a[..., 0])
    K = torch.stack(
        [torch.stack([z, -a[..., 2], a[..., 1]], -1), torch.stack([a[..., 2], z, -a[..., 0]], -1),
         torch.stack([-a[..., 1], a[..., 0], z], -1)], -2,
    )  # fmt: skip
    s, c = torch.sin(t)[..., None, None], torch.cos(t)[..., None, None]
    return torch.eye(3, dtype=a.dtype, device=a.device) + s * K + (1.0 - c) * (K @ K)


def _angle_about(a: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(...) the angle of the rotation about unit axes a (..., 3) that takes u to v (their parts normal to a)."""
    u = u - (u * a).sum(-1, keepdim=True) * a
    v = v - (v * a).sum(-1, keepdim=True) * a
    return torch.atan2((a * torch.linalg.cross(u, v)).sum(-1), (u * v).sum(-1))


def _wrap(t: torch.Tensor) -> torch.Tensor:
    return torch.remainder(t + math.pi, 2 * math.pi) - math.pi


def _hinge_angles(R: torch.Tensor, ax: list[torch.Tensor]) -> list[list[torch.Tensor]]:
    """The angle lists [t_1 .. t_h] (each (A, n)) with R = Rot(a_1, t_1) .. Rot(a_h, t_h), h = len(ax) <= 3
    (R (A, n, 3, 3), axes (n, 3)): one list for one or two hinges, two for three (the middle angle solves
    P cos t_2 + Q sin t_2 = a_1^T R a_3 - C, which has two solutions, the first with |t_2 - phi| the smaller)."""
    mv = lambda M, x: (M @ x[..., None])[..., 0]  # noqa: E731
    Rt = R.transpose(-1, -2)
    if len(ax) == 1:
        (a,) = ax
        return [[torch.atan2((_vee(R) * a).sum(-1), 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0))]]
    if len(ax) == 2:  # R b = Rot(a, t1) b and R^T a = Rot(b, -t2) a
        a, b = (x.expand(R.shape[:-1]) for x in ax)
        return [[_angle_about(a, b, mv(R, b)), _angle_about(b, mv(Rt, a), a)]]
    a, b, c = (x.expand(R.shape[:-1]) for x in ax)
    # a^T R c = a^T Rot(b, t2) c = P cos t2 + Q sin t2 + C
    ab, bc = (a * b).sum(-1), (b * c).sum(-1)
    P, Qs, C = (a * c).sum(-1) - ab * bc, (a * torch.linalg.cross(b, c)).sum(-1), ab * bc
    d = (a * mv(R, c)).sum(-1)
    phi = torch.atan2(Qs, P)
    off = torch.acos(((d - C) / torch.sqrt(P * P + Qs * Qs)).clamp(-1.0, 1.0))
    out = []
    for t2 in (_wrap(phi + off), _wrap(phi - off)):
        B = _rot(b, t2)  # then R c = Rot(a, t1) B c and R^T a = Rot(c, -t3) B^T a
        out.append(
            [_angle_about(a, mv(B, c), mv(R, c)), t2, _angle_about(c, mv(Rt, a), mv(B.transpose(-1, -2), a))]
        )
    return out


def _joint_values(art: Articulation, rows: torch.Tensor, near: torch.Tensor | None = None) -> torch.Tensor:
    """(A, Qa) the coordinates whose forward kinematics gives the link rows (A, L, 6) (base pose if floating, then
    the joints).

    Per link, the transform M = (T_parent Offset)^-1 T_link = J_1 .. J_k of its joints: the hinges' angles from M's
    rotation (:func:`_hinge_angles`), then the slides from its translation, which is affine in them once the
    hinges are known: p_M = sum_hinges R_<i (c_i - Rot_i c_i) + sum_slides R_<i s_i x_i (R_<i: the rotation of the
    joints before i), solved in least squares. Of a three-hinge link's two solutions (t1, t2, t3) and (t1 + pi,
    pi - t2, t3 + pi) (for orthogonal axes), the one whose translation fits (where the anchors tell them apart),
    else, with ``near`` (A, Qa) given, the one nearer those coordinates (the state a step earlier read near the
    state now: a joint turning through the middle hinge's pi / 2 keeps one branch), else the one with every joint of
    the link (hinges and slides) within its range, else the one nearer ref (the sum of the three angles'
    distances)."""
    dt, dev = rows.dtype, rows.device
    as_t = lambda x: torch.as_tensor(x, dtype=dt, device=dev)  # noqa: E731
    mv = lambda M, x: (M @ x[..., None])[..., 0]  # noqa: E731
    A, L = rows.shape[:2]
    R = rotation_matrix(rows[..., 3:].reshape(A * L, 3)).reshape(A, L, 3, 3)  # (2-D: the numba kernel serves)
    p = rows[..., :3] - mv(R, as_t(art.com)[None])
    # the frame each link hangs from: its parent link's, the root's the mount (a root without joints: unused)
    par = torch.as_tensor(np.maximum(art.parent, 0), device=dev)
    Rp, pp = R[:, par], p[:, par]
    if art.root_moves:
        Rp[:, 0] = rotation_matrix(as_t(art.mount[3:]))
        pp[:, 0] = as_t(art.mount[:3])
    F = Rp @ as_t(art.offset_R)  # the links' frames at the joints' ref, (A, L, 3, 3)
    RM = F.transpose(-1, -2) @ R
    pM = mv(F.transpose(-1, -2), p - pp - mv(Rp, as_t(art.offset_p)))
    th = rows.new_zeros(A, art.num_joints)
    if near is not None:
        near = near[:, 6:] if art.floating else near
    lower, upper, ref, centre = as_t(art.lower), as_t(art.upper), as_t(art.ref), as_t(art.centre)
    axis, anchor = as_t(art.axis), as_t(art.anchor)
    for g in art._groups:
        links, joints = g.links.to(dev), g.joints.to(dev)
        hinge_at = [i for i, kind in enumerate(g.kinds) if kind == "hinge"]
        target = pM[:, links]
        candidates = []
        for angles in (
            _hinge_angles(RM[:, links], [axis[joints[:, i]] for i in hinge_at]) if hinge_at else [[]]
        ):
            values = dict(zip(hinge_at, angles, strict=True))
            Racc = torch.eye(3, dtype=dt, device=dev).expand(A, len(links), 3, 3)
            rest, cols = target, []
            for i, kind in enumerate(g.kinds):
                ax = axis[joints[:, i]]
                if kind == "hinge":
                    c = anchor[joints[:, i]]
                    Rj = _rot(ax, values[i])
                    rest = rest - mv(Racc, c - mv(Rj, c))
                    Racc = Racc @ Rj
                else:
                    cols.append(mv(Racc, ax))
            if cols:
                Cm = torch.stack(cols, -1)  # (A, n, 3, s)
                Ct = Cm.transpose(-1, -2)
                x = torch.linalg.solve(Ct @ Cm, mv(Ct, rest))
                rest = rest - mv(Cm, x)
                values.update(
                    {i: x[..., k] for k, i in enumerate(i for i in range(len(g.kinds)) if i not in values)}
                )
            candidates.append((torch.stack([values[i] for i in range(len(g.kinds))], -1), rest.norm(dim=-1)))
        vals, res = candidates[0]
        if len(candidates) == 2:  # where the translation does not tell them apart
            other, res2 = candidates[1]
            hj = joints[:, hinge_at]  # (n, 3)
            h_1, h_2 = vals[..., hinge_at], other[..., hinge_at]  # the hinges' angles from ref
            if near is not None:  # the one nearer the given values
                d_1, d_2 = (_wrap(h + ref[hj] - near[:, hj]).abs().sum(-1) for h in (h_1, h_2))
                prefer = d_2 < d_1
            else:  # the one with every joint of the link (hinges and slides) within range, else the one nearer ref
                is_h = torch.as_tensor(art.hinge, device=dev)[joints]  # (n, k)
                w_1, w_2 = (
                    torch.where(
                        is_h, centre[joints] + _wrap(v + ref[joints] - centre[joints]), v + ref[joints]
                    )
                    for v in (vals, other)
                )
                in_1, in_2 = (((w >= lower[joints]) & (w <= upper[joints])).all(-1) for w in (w_1, w_2))
                d_1, d_2 = (_wrap(h).abs().sum(-1) for h in (h_1, h_2))
                prefer = torch.where(in_1 != in_2, in_2, d_2 < d_1)
            tol = 1e-9 * (1.0 + target.norm(dim=-1) + anchor[joints].norm(dim=-1).amax(-1))
            second = torch.where((res - res2).abs() > tol, res2 < res, prefer)
            vals = torch.where(second[..., None], other, vals)
        th[:, joints] = vals + ref[joints]
    th = torch.where(torch.as_tensor(art.hinge, device=dev), centre + _wrap(th - centre), th)
    if not art.floating:
        return th
    return torch.cat([p[:, 0], rows[:, 0, 3:], th], 1)


# ------------------------------------------------------------------------------------------- joint-space terms
def _limit_barrier(x: torch.Tensor, w: torch.Tensor, order: int):
    """kappa b(x / w) and its first two derivatives in x (+inf for x <= 0; 0 for x >= w), w per joint."""
    k = LIMIT_STIFFNESS
    s = x / w
    inside = (s > 0) & (s < 1)
    ss = torch.where(inside, s, torch.full_like(s, 0.5))
    ln = torch.log(ss)
    v = torch.where(inside, -k * (ss - 1) ** 2 * ln, torch.zeros_like(s))
    v = torch.where(s <= 0, torch.full_like(s, math.inf), v)
    g = torch.where(inside, -k * (2 * (ss - 1) * ln + (ss - 1) ** 2 / ss) / w, torch.zeros_like(s))
    h = torch.where(
        inside, -k * (2 * ln + 4 * (ss - 1) / ss - (ss - 1) ** 2 / ss**2) / (w * w), torch.zeros_like(s)
    )
    return v, g, h


class JointDrive(NamedTuple):
    """What the actuators add to the joint terms: per joint (A, J) the motors' torque and the servos' summed
    stiffness and damping; per actuator (A, U) each servo's gain kp gear^2 (zero for motors) and target angle
    ctrl / gear."""

    torque: torch.Tensor
    stiffness: torch.Tensor
    damping: torch.Tensor
    servo_gain: torch.Tensor
    servo_target: torch.Tensor


class ArticulatedKinematics:
    """The kinematics map of a scene with articulations (:class:`cfd_torch.sim.kinematics.Kinematics`): q = the
    free dynamic bodies' poses (6 each), then per articulation its base pose (floating) and joint values.

    Args:
        free: (Nf,) rows of the free dynamic bodies.
        arts: the articulations, with ``rows`` (the first row of each, links consecutive).
        num_bodies: N.
    """

    #: converged bodies are not frozen one by one (an articulation's coordinates move all its links)
    freezable = False

    def __init__(
        self, free: torch.Tensor, arts: Sequence[Articulation], first_rows: Sequence[int], num_bodies: int
    ):
        self.free = free
        self.arts = tuple(arts)
        self.first = tuple(int(r) for r in first_rows)
        self.num_bodies = num_bodies
        # a fixed base whose root has joints hangs from its mount, a pose in the world frame
        self.translation_invariant = not any(art.root_moves for art in self.arts)
        moving, start = [int(i) for i in free], 6 * len(free)
        coord_body = [k // 6 for k in range(6 * len(free))]
        self.coord_slices = []
        for art, r in zip(self.arts, self.first, strict=True):
            lo = art.first_moving
            owner = len(moving)
            moving += list(range(r + lo, r + art.num_links))
            self.coord_slices.append(slice(start, start + art.num_coords))
            coord_body += [owner] * art.num_coords
            start += art.num_coords
        self.bodies = torch.tensor(moving, dtype=torch.long)
        self.moved = torch.zeros(num_bodies, 6, dtype=torch.bool)
        self.moved[self.bodies] = True
        self.hung = torch.zeros(num_bodies, dtype=torch.bool)
        for art, r in zip(self.arts, self.first, strict=True):
            if art.first_moving:  # a joint-less root: the links hang from its (fixed) row
                self.hung[r + art.first_moving : r + art.num_links] = True
        self.coord_body = torch.tensor(coord_body, dtype=torch.long)
        self.num_coords = start
        self._f6 = (free[:, None] * 6 + torch.arange(6)).reshape(-1)
        # joint coordinates of all articulations (indices into q) and their per-joint data
        jidx, hinge, free_hinge, data = (
            [],
            [],
            [],
            {k: [] for k in ("lower", "upper", "damping", "armature", "stiffness", "springref")},
        )  # fmt: skip
        act = {k: [] for k in ("joint", "gear", "servo", "ctrl_lower", "ctrl_upper", "kp", "kv")}
        for art, sl in zip(self.arts, self.coord_slices, strict=True):
            j0 = sl.start + (6 if art.floating else 0)
            act["joint"] += list(len(jidx) + art.actuator_joint)
            jidx += list(range(j0, j0 + art.num_joints))
            hinge += art.hinge.tolist()
            free_hinge += art.free_hinge.tolist()
            for key, vals in data.items():
                vals += list(getattr(art, key))
            for key, vals in act.items():
                vals += [] if key == "joint" else list(getattr(art, key))
        self.joint_index = torch.tensor(jidx, dtype=torch.long)
        self.hinge = torch.tensor(hinge, dtype=torch.bool)
        self.free_hinge = torch.tensor(free_hinge, dtype=torch.bool)  # hinges without a range
        self.joint_data = {k: torch.tensor(v, dtype=torch.float64) for k, v in data.items()}
        # the limit barrier's width per joint: LIMIT_WIDTH, or a tenth of a narrower range (a gripper's 4 cm slide)
        span = self.joint_data["upper"] - self.joint_data["lower"]
        self.joint_data["limit_width"] = torch.clamp(0.1 * span, max=LIMIT_WIDTH)
        # the actuators of all articulations (U): joint (into joint_index), gear, servo (position actuator or
        # motor), the control's clip and the MJCF's servo gains (zero for motors)
        self.actuator_joint = torch.tensor(act.pop("joint"), dtype=torch.long)
        self.actuator_servo = torch.tensor(act.pop("servo"), dtype=torch.bool)
        self.actuator_data = {k: torch.tensor(v, dtype=torch.float64) for k, v in act.items()}

    def translated(self, origin: torch.Tensor) -> ArticulatedKinematics:
        """This map in the frame whose origin is ``origin`` (3,) [m] in the world: a copy whose robots hung from
        their mounts hang from the mounts moved by -origin (the other bases are coordinates or fixed poses, which
        move with the frame); itself if no robot hangs from a mount."""
        if self.translation_invariant:
            return self
        d = origin.detach().to("cpu", torch.float64).numpy()
        out = copy.copy(self)
        out.arts = tuple(_remounted(a, a.mount[:3] - d) if a.root_moves else a for a in self.arts)
        return out

    # -- the map
    def poses(self, q: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        out = fixed.clone()
        A = q.shape[0]
        out[:, self.free.to(q.device)] = q[:, : 6 * len(self.free)].reshape(A, -1, 6)
        for art, r, sl in zip(self.arts, self.first, self.coord_slices, strict=True):
            lo = art.first_moving
            out[:, r + lo : r + art.num_links] = _moving_rows(art, q[:, sl], fixed[:, r])
        return out

    def coords(self, poses: torch.Tensor, near: torch.Tensor | None = None) -> torch.Tensor:
        """The :class:`~cfd_torch.sim.kinematics.Kinematics` map's inverse; ``near`` (A, Q): coordinates to stay
        near where link poses do not tell joint values apart (:meth:`Articulation.coords`)."""
        parts = [poses[:, self.free.to(poses.device)].reshape(poses.shape[0], -1)]
        for art, r, sl in zip(self.arts, self.first, self.coord_slices, strict=True):
            parts.append(
                _joint_values(art, poses[:, r : r + art.num_links], None if near is None else near[:, sl])
            )
        return torch.cat(parts, 1)

    def check_rows(self, poses: torch.Tensor, q: torch.Tensor, name: str, eps: float) -> None:
        """Raise ValueError naming ``name`` where the link rows of ``poses`` (A, N, 6) are not the forward kinematics
        of the coordinates q (A, Q) recovered from them (:meth:`coords`) to 1e-5 [m, rad] plus the rounding of rows
        given with machine epsilon ``eps``: rows moved off their joints (a link displaced from its hinge, turned
        about an axis it has no joint for) would otherwise be read as some other configuration, silently."""
        fk = self.poses(q, poses)
        for art, r in zip(self.arts, self.first, strict=True):
            rows = slice(r + art.first_moving, r + art.num_links)
            given, want = poses[:, rows], fk[:, rows]
            off_t = (given[..., :3] - want[..., :3]).norm(dim=-1)  # (A, L)
            off_r = (
                (rotation_matrix(given[..., 3:]) - rotation_matrix(want[..., 3:])).flatten(-2).norm(dim=-1)
            )
            tol_t = 1e-5 + 64.0 * eps * given[..., :3].norm(dim=-1)
            bad = (off_t > tol_t) | (off_r > 1e-5 + 64.0 * eps)
            if bool(bad.any()):
                a, k = (int(i) for i in torch.nonzero(bad)[0])
                raise ValueError(
                    f"{name}: the link rows of articulation {art.name!r} do not fit its joints: link "
                    f"{art.first_moving + k} (row {r + art.first_moving + k}) is {float(off_t[a, k]):.3g} m and "
                    f"{float(off_r[a, k]):.3g} (rotation) from the forward kinematics of the joint values its rows "
                    "imply; pose articulations with Articulation.poses"
                    + (f" (scene {a})" if poses.shape[0] > 1 else "")
                )

    def check_within_limits(
        self, poses: torch.Tensor, name: str, margin: float = 0.0, coords: torch.Tensor | None = None
    ) -> None:
        """Raise ValueError naming the first joint of the poses (A, N, 6) (``name``: the argument) at or beyond one
        of its limits, where the step's limit barrier is infinite (MuJoCo accepts such a state and pushes it
        back), or within ``margin`` of one [rad or m] (``coords``: the poses' coordinates, if computed)."""
        th = (self.coords(poses) if coords is None else coords)[:, self.joint_index.to(poses.device)]
        lo = self.joint_data["lower"].to(dtype=th.dtype, device=th.device)
        hi = self.joint_data["upper"].to(dtype=th.dtype, device=th.device)
        outside = (th <= lo) | (th >= hi)
        bad = outside | (th <= lo + margin) | (th >= hi - margin)
        if bool(bad.any()):
            a, j = (int(i) for i in torch.nonzero(bad)[0])
            names = [(f"{art.name}/{n}", i) for i, art in enumerate(self.arts) for n in art.joint_names]
            if bool(outside[a, j]):
                where, why = (
                    "outside its range",
                    "the step's limits are barriers; start a joint inside its range",
                )
            else:
                where = f"within {margin:.3g} of a limit of its range"
                why = (
                    "there the limit barrier's Newton step is below the convergence threshold and the step would "
                    "end where it began; start it further inside"
                )
            raise ValueError(
                f"{name}: joint {names[j][0]!r} (articulation {names[j][1]}) is at {float(th[a, j]):.10g}, {where} "
                f"({float(lo[j]):.6g}, {float(hi[j]):.6g}) ({why})"
                + (f" (scene {a})" if th.shape[0] > 1 else "")
            )

    def _derivatives(self, q: torch.Tensor, fixed: torch.Tensor, grad: torch.Tensor | None):
        """Per articulation: its moving rows [r0, r1), its coordinates' slice, the Jacobian (A, 6 La, Qa) of those
        rows and, for pose-space gradients grad (A, N, 6), sum_k grad_k d2 row_k / dqa dqa (A, Qa, Qa)."""
        out = []
        for art, r, sl in zip(self.arts, self.first, self.coord_slices, strict=True):
            lo = art.first_moving
            g = None if grad is None else grad[:, r + lo : r + art.num_links]
            J, second = _fk_derivatives(art, q[:, sl], None if art.floating else fixed[:, r], lo, g)
            out.append((r + lo, r + art.num_links, sl, J, second))
        return out

    def pullback(self, q, grad, hess, fixed, extra=()):
        A, N = grad.shape[:2]
        J = grad.new_zeros(A, 6 * N, self.num_coords)
        nf = 6 * len(self.free)
        if nf:
            J[:, self._f6.to(q.device), torch.arange(nf, device=q.device)] = 1.0
        second = grad.new_zeros(A, self.num_coords, self.num_coords)
        want = hess is not None and bool((grad != 0).any())  # a pure Hessian pull-back needs no d2pose/dq2
        for r0, r1, sl, Ja, S in self._derivatives(q, fixed, grad if want else None):
            J[:, 6 * r0 : 6 * r1, sl] = Ja
            if S is not None:
                second[:, sl, sl] = S
        Jt = J.transpose(1, 2)
        gq = (Jt @ grad.reshape(A, 6 * N)[..., None])[..., 0]
        more = tuple(Jt @ X @ J for X in extra)
        return gq, (None if hess is None else Jt @ hess @ J + second), more

    def push(self, q, v, fixed):
        A = q.shape[0]
        out = v.new_zeros(A, self.num_bodies, 6)
        out[:, self.free.to(v.device)] = v[:, : 6 * len(self.free)].reshape(A, -1, 6)
        for r0, r1, sl, Ja, _ in self._derivatives(q, fixed, None):
            out[:, r0:r1] = (Ja @ v[:, sl, None])[..., 0].reshape(A, r1 - r0, 6)
        return out

    def extrapolate(self, q_t: torch.Tensor, q_p: torch.Tensor) -> torch.Tensor:
        v = q_t - q_p
        hinge = self.joint_index[self.hinge].to(q_t.device)
        v[:, hinge] = torch.remainder(v[:, hinge] + math.pi, 2 * math.pi) - math.pi
        for sl, art in zip(self.coord_slices, self.arts, strict=True):  # bases: like free bodies
            if art.floating:
                w = v[:, sl.start + 3 : sl.start + 6]
                v[:, sl.start : sl.start + 6] *= (w.abs() < 1.0).all(-1, keepdim=True).to(v.dtype)
        nf = 6 * len(self.free)
        vf = v[:, :nf].reshape(v.shape[0], -1, 6)
        v[:, :nf] = (vf * (vf[..., 3:].abs() < 1.0).all(-1, keepdim=True).to(v.dtype)).reshape(v.shape[0], -1)
        return q_t + v

    def predict(
        self,
        q_t: torch.Tensor,
        q_p: torch.Tensor,
        th_t: torch.Tensor,
        th_p: torch.Tensor,
        fixed: torch.Tensor,
        rotation: torch.Tensor,
        mass: torch.Tensor,
        S: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The inertia terms' prediction for the links: where their material points X go without forces.

        Args: the poses q_t, q_p (A, N, 6) now and a step earlier and their coordinates th_t, th_p (A, Q); the
        end-of-step poses of the bodies the map does not move, ``fixed`` (A, N, 6) (a fixed base's root); each
        moving body's free prediction of its rotation, ``rotation`` (A, M, 3, 3) (:func:`~cfd_torch.sim.energy
        .predicted_rotation`); masses (A, M) and second moments (A, M, 3, 3). Differentiable by autograd.

        Returns the orientations (A, M, 3, 3) and the shifts of the centres of mass from 2 t_t - t_{t-1} (A, M, 3)
        of the predictions (the free bodies' rotations as given, their shifts zero).

        The discrete Euler-Lagrange equations of the joints (the variational integrator whose free bodies are the
        Moser-Veselov ones) take the constraint forces where the step starts: J_t^T M (X(q) - X_free) = dt^2 f, with
        X_free each link's free-body prediction (its centre of mass at constant velocity, its rotation the discrete
        rigid body's), J the Jacobian of X in q and M the links' mass. The step's energy, 1/2 |X(q) - X_pred|_M^2 / dt^2
        + V(q), is stationary where J(q)^T M (X(q) - X_pred) = dt^2 f, with the constraint forces at its end. With
        X_pred = X_free the difference is a force of order dt that makes spinning links lag (a bar at 5 rad/s on its
        hinge, without gravity, slows to 3.8 rad/s in 2 s at dt = 0.01). Here X_pred = X_hat + J_t delta: X_hat =
        X(q_hat), the links at the joints extrapolated at constant velocity (hinges mod 2 pi; a floating base where its
        root link's free prediction puts it), moved by the joints' Coriolis and gyroscopic increment delta = (J_t^T M
        J_t)^-1 J_t^T M (X_free - X_hat), the M-projection of X_free - X_hat onto the joints' tangent space at q_t. Then
        J_t^T M (X_pred - X_free) = 0, X_pred lies within O(dt^3) of the joints' manifold, and the two stationarity
        conditions differ by (J(q) - J_t)^T M (X(q) - X_pred) / dt^2: of order dt^2 without forces (a free spin on one
        hinge, on the link's principal axes or not, keeps its rate to rounding; chains keep their energy to a few 1e-3
        over 10 s at dt = 0.01), of order dt times the forces' acceleration with them, as in any implicit Euler step.
        (X_hat with the force J_t^T M (X_hat - X_free) / dt^2 in the energy instead would differ by (J(q) - J_t)^T M
        (X(q) - X_hat) / dt^2, of order dt, which feeds energy into fast chains.) Per link, M (X_hat - X_free) is m
        (t_hat - t_free) and (R_hat - R_free) S, and J_t delta moves the centre of mass by its translation part and the
        orientation by sum_k dR/dw_k (J_t delta)_w,k."""
        A, dev = q_t.shape[0], q_t.device
        nf = len(self.free)
        th_hat = self.extrapolate(th_t, th_p)  # (its floating bases' coordinates are not used)
        hat_rows, t_free = [], []
        slot = nf
        for art, r, sl in zip(self.arts, self.first, self.coord_slices, strict=True):
            lo = art.first_moving
            rows = slice(r + lo, r + art.num_links)
            t_free.append(2.0 * q_t[:, rows, :3] - q_p[:, rows, :3])
            if art.floating:  # the base where the root link's free prediction puts it
                qa = torch.cat([th_hat.new_zeros(A, 6), th_hat[:, sl.start + 6 : sl.stop]], 1)
                rel = _moving_rows(art, qa, fixed[:, r])  # the links in the base's frame
                Rb = rotation[:, slot]
                pb = t_free[-1][:, 0] - (Rb @ torch.as_tensor(art.com[0], dtype=q_t.dtype, device=dev))
                R_hat = Rb[:, None] @ rotation_matrix(rel[..., 3:].reshape(-1, 3)).reshape(A, -1, 3, 3)
                t_hat = pb[:, None] + (Rb[:, None] @ rel[..., :3, None])[..., 0]
            else:
                rel = _moving_rows(art, th_hat[:, sl], fixed[:, r])
                R_hat = rotation_matrix(rel[..., 3:].reshape(-1, 3)).reshape(A, -1, 3, 3)
                t_hat = rel[..., :3]
            hat_rows.append((t_hat, R_hat))
            slot += art.num_links - lo
        links = slice(nf, slot)
        t_hat = torch.cat([x[0] for x in hat_rows], 1)
        R_hat = torch.cat([x[1] for x in hat_rows], 1)
        d_t = t_hat - torch.cat(t_free, 1)  # (A, M - nf, 3)
        d_R = R_hat - rotation[:, links]
        # per link at q_t (at the rows' rotation vectors as the forward kinematics writes them, its Jacobian's,
        # whatever q_t's are): M (X_hat - X_free) as a pose-space gradient g (the derivative of m t . d_t + tr(R S
        # d_R^T)), the pose-space mass H (m 1, and tr(dR_k S dR_l^T) for the rotation vector), and the Jacobian Jl
        # of its row in the articulations' coordinates (A, L, 6, Qa), block-diagonal over the articulations
        rows = self.bodies[nf:].to(dev)
        L = rows.shape[0]
        at = self.poses(th_t, q_t)[:, rows]
        _, dR, _ = rotation_derivatives(at[..., 3:].reshape(-1, 3), 1)
        g_w = torch.einsum("lijk,lij->lk", dR, (d_R @ S[:, links]).reshape(-1, 3, 3)).reshape(A, L, 3)
        g = torch.cat([mass[:, links, None] * d_t, g_w], -1)  # (A, L, 6)
        H = q_t.new_zeros(A, L, 6, 6)
        H[:, :, :3, :3] = mass[:, links, None, None] * torch.eye(3, dtype=q_t.dtype, device=dev)
        H[:, :, 3:, 3:] = torch.einsum("nijk,njm,niml->nkl", dR, S[:, links].reshape(-1, 3, 3), dR).reshape(
            A, L, 3, 3
        )
        Qa = sum(sl.stop - sl.start for sl in self.coord_slices)
        Jl = q_t.new_zeros(A, L, 6, Qa)
        row = col = 0
        for r0, r1, sl, Ja, _ in self._derivatives(th_t, q_t, None):
            Jl[:, row : row + r1 - r0, :, col : col + sl.stop - sl.start] = Ja.reshape(A, r1 - r0, 6, -1)
            row, col = row + r1 - r0, col + sl.stop - sl.start
        # delta = -(J_t^T M J_t)^-1 J_t^T M (X_hat - X_free) (a ridge of 1e-13 of the trace: J_t^T M J_t is singular
        # where the joints' axes line up, and the right-hand side has no component there)
        G = torch.einsum("alkq,alk->aq", Jl, g)
        Mq = torch.einsum("alkq,alkm,almp->aqp", Jl, H, Jl)
        ridge = (
            1e-13
            * Mq.diagonal(dim1=1, dim2=2).sum(1)[:, None, None]
            * torch.eye(Qa, dtype=Mq.dtype, device=dev)
        )
        delta = -torch.linalg.solve(Mq + ridge, G[..., None])[..., 0]
        move = torch.einsum("alkq,aq->alk", Jl, delta)  # J_t delta, per link row
        dRm = torch.einsum("lijk,lk->lij", dR, move[..., 3:].reshape(-1, 3)).reshape(A, L, 3, 3)
        out_R = torch.cat([rotation[:, :nf], R_hat + dRm], 1)
        shift = torch.cat([d_t.new_zeros(A, nf, 3), d_t + move[..., :3]], 1)
        return out_R, shift

    def carry(self, q: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        out = q.clone()
        nf = 6 * len(self.free)
        f = q[:, :nf].reshape(q.shape[0], -1, 6).clone()
        f[..., :3] += shift[:, None, :]
        out[:, :nf] = f.reshape(q.shape[0], -1)
        for sl, art in zip(self.coord_slices, self.arts, strict=True):
            if art.floating:
                out[:, sl.start : sl.start + 3] += shift
        return out

    # -- joint-space terms
    def joint_terms(self, q, joint, dt: float, order: int):
        """Armature, damping, springs, limits and the actuators' terms of all joints at q (A, Q), for ``joint``
        (:class:`cfd_torch.sim.energy.JointInputs`: the coordinates one and two steps earlier and the actuators'
        :class:`JointDrive`): value (A,), grad (A, Q), Hessian (A, Q, Q) (up to ``order``), and the limit
        barriers' part of the value (A,)."""
        idx = self.joint_index.to(q.device)
        q_t, q_p, torque = joint.q_t, joint.q_p, joint.torque
        d = {k: v.to(dtype=q.dtype, device=q.device) for k, v in self.joint_data.items()}
        d["damping"] = d["damping"] + joint.damping
        d["pd_stiffness"] = joint.stiffness
        th, tt, tp = q[:, idx], q_t[:, idx], q_p[:, idx]
        hinge = self.hinge.to(q.device)
        # a hinge's value is an angle, known from the link poses only up to whole turns: its differences in time are
        # taken mod 2 pi, and so are its spring's and servos' on a hinge without a range (the short way round: a
        # servo past pi pulls back across pi instead of flipping its force there and adding energy; on a limited
        # hinge the range fixes the angle, and the short way could cross the limits)
        turn = lambda x, m: torch.where(m, _wrap(x), x)  # noqa: E731
        acc = turn(th - tt, hinge) - turn(tt - tp, hinge)
        vel = turn(th - tt, hinge)
        free = self.free_hinge.to(q.device)
        spring = turn(th - d["springref"], free)
        # the servos, one term each: kp gear^2 (theta - ctrl / gear)^2 / 2 on the joint it drives
        aj = self.actuator_joint.to(q.device)
        servo = turn(th[:, aj] - joint.servo_target, free[aj])  # (A, U) (motors: zero gain)
        vs = th.new_zeros(th.shape).index_add(1, aj, 0.5 * joint.servo_gain * servo**2)
        gs = th.new_zeros(th.shape).index_add(1, aj, joint.servo_gain * servo)
        vl, gl, hl = _limit_barrier(th - d["lower"], d["limit_width"], order)
        vu, gu, hu = _limit_barrier(d["upper"] - th, d["limit_width"], order)
        inv = 1.0 / (dt * dt)
        value = (
            0.5 * inv * d["armature"] * acc**2 + 0.5 / dt * d["damping"] * vel**2
            + 0.5 * d["stiffness"] * spring**2 + vs + vl + vu - torque * vel
        ).sum(1)  # fmt: skip
        limits = (vl + vu).sum(1)
        if order == 0:
            return value, None, None, limits
        g = (
            inv * d["armature"] * acc + d["damping"] / dt * vel + d["stiffness"] * spring + gs + gl - gu - torque
        )  # fmt: skip
        grad = q.new_zeros(q.shape).index_add(1, idx, g)
        if order == 1:
            return value, grad, None, limits
        h = inv * d["armature"] + d["damping"] / dt + d["stiffness"] + d["pd_stiffness"] + hl + hu
        hess = q.new_zeros(q.shape[0], q.shape[1], q.shape[1])
        hess[:, idx, idx] = h
        return value, grad, hess, limits

    def servo_gains(self, dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        """(U,) kp and (U,) kv: the MJCF's position-actuator gains (zero for motors), ``Params.kp`` / ``kv``'s
        default."""
        return tuple(self.actuator_data[k].to(dtype=dtype, device=device) for k in ("kp", "kv"))

    def drive(self, ctrl: torch.Tensor, kp: torch.Tensor, kv: torch.Tensor) -> JointDrive:
        """The actuators' joint terms for controls ctrl (A, U) and servo gains kp, kv (A, U) (motors' entries
        unused): per joint (A, J) the motors' torque sum gear clip(ctrl) and the servos' stiffness sum kp gear^2
        and damping sum kv gear^2; per actuator (A, U) a servo's gain kp gear^2 and target clip(ctrl) / gear (its
        force kp (ctrl - gear theta), MuJoCo's position actuator). Differentiable in ctrl, kp and kv."""
        d = {k: v.to(dtype=ctrl.dtype, device=ctrl.device) for k, v in self.actuator_data.items()}
        servo = self.actuator_servo.to(ctrl.device)
        on = servo.to(ctrl.dtype)
        c = torch.maximum(torch.minimum(ctrl, d["ctrl_upper"]), d["ctrl_lower"])
        g2 = d["gear"] ** 2
        j = self.actuator_joint.to(ctrl.device)
        zero = ctrl.new_zeros(ctrl.shape[0], len(self.joint_index))
        return JointDrive(
            zero.index_add(1, j, (1.0 - on) * d["gear"] * c),
            zero.index_add(1, j, on * kp * g2),
            zero.index_add(1, j, on * kv * g2),
            on * kp * g2,
            torch.where(servo & (d["gear"] != 0), c / torch.where(d["gear"] != 0, d["gear"], 1.0), 0.0),
        )

    @property
    def num_actuators(self) -> int:
        return sum(a.num_actuators for a in self.arts)

    @property
    def num_joints(self) -> int:
        return len(self.joint_index)
