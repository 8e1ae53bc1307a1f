"""MJCF front end of articulated bodies: MuJoCo XML -> links, joints, collision meshes, mass properties, actuators.
URDF is read as the MJCF MuJoCo's URDF importer makes of it.

`load_mjcf` parses an MJCF file or string with MuJoCo itself (an `MjSpec` for what the compiled model does not keep:
a geom's density or explicit mass, whether a body has an `<inertial>` element; the compiled `MjModel` for
everything else), so that default classes, `fromto`, `angle`, `euler`/`axisangle`/`xyaxes`/`zaxis` orientations,
`limited`/`autolimits` are resolved exactly as MuJoCo resolves them.

Links are the bodies that carry at least one joint, plus the root body; a body without joints is welded into its
parent's link (its geoms, mass and pose composed into that link's frame). A link's pose at joint values q is

    T_link = T_parent @ [quat, pos] @ J_1(q_1) @ J_2(q_2) @ ...     (joints in MJCF order)
    J(q) = translate(pos) @ rotate(axis, q - ref) @ translate(-pos) (hinge: about the line through pos along axis)
    J(q) = translate(axis * (q - ref))                              (slide)

with each joint's pos and axis in the link frame, which is MuJoCo's `mj_kinematics` (it right-multiplies the body
orientation by each joint's local rotation, in order, keeping the joint anchor fixed). A free joint on the root
makes the model floating: the root pose is then a separate floating base, not a joint.

Mass properties are analytic (density x volume of the ideal shape, not of the triangulated mesh) and reproduce
MuJoCo's compiled `body_mass`, `body_ipos` and principal moments `body_inertia` to rounding. A mesh geom's come
from MuJoCo's compiled mesh (float32 vertices: about 1e-8 relative), as its `<mesh inertia>` says: "exact" the
closed mesh, "convex" MuJoCo's hull of it, "legacy" (MuJoCo's default) the closed mesh too, which is MuJoCo's for a
mesh star-shaped about its legacy centre (where MuJoCo's legacy rule counts more, a warning says so); a mesh geom
collides as its own triangles (MuJoCo collides its convex hull). MuJoCo's principal
axes `body_iquat` of a multi-geom body come from its iterative mju_eig3 and agree only to its tolerance (~1e-7
relative where principal moments nearly coincide). Refused with a `ValueError`
naming the element: plane/hfield/sdf geoms in a link that MuJoCo collides or counts the mass of (visual
ones are left out, with a warning, as are visual-only mesh geoms), a mesh whose mass counts that is not a closed,
outward-wound surface (but under `inertia="convex"`), a mesh with `inertia="convex"` that no geom collides with
(MuJoCo 3.2.7's compiler crashes on it), shell inertia, ball joints, free joints below the root,
unnamed joints, actuators other than joint-driven motors and position servos (those acting only outside the root's
subtree are left out; actuator plugins and actuators in a group ``<option actuatorgroupdisable>`` disables are
refused), compiler options that bound masses (`boundmass`, `boundinertia`, `balanceinertia`) or drop
geoms and bodies whose mass counts (`discardvisual`, `fusestatic`), damping, armature or stiffness on the free
root joint, and physics the simulator does not model: joint
`frictionloss` and `actuatorfrcrange`, `<equality>` constraints, tendon limits, stiffness and damping. A link's
collision mesh holds the geoms MuJoCo may collide (`contype` or `conaffinity` nonzero; every geom's mass counts);
a link whose geoms are all visual-only keeps them, and they collide (with a warning). Which geoms collide with
which (the bits themselves) is not modelled. Unnamed bodies are named after their parent and their
place among its children ("aux_1/0"; `MJCFModel.xml` then holds the text with those names and any `<include>`d
files inlined, every attribute as written), and `settotalmass` scales the geoms' masses as MuJoCo does.
"""

from __future__ import annotations

import importlib.resources
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
import trimesh

from .._validate import check_mesh, is_int
from .urdf import claim_name, is_urdf, urdf_as_mjcf

__all__ = [
    "ActuatorSpec",
    "GeomSpec",
    "JointSpec",
    "LinkSpec",
    "MJCFModel",
    "gymnasium_ant_xml",
    "load_mjcf",
]


@dataclass(frozen=True)
class JointSpec:
    """A hinge or slide joint; q is MuJoCo's qpos of the joint (q = ref, the MJCF `ref`, is the pose written in
    the MJCF).

    Attributes:
        name: joint name.
        kind: "hinge" or "slide".
        axis: (3,) unit axis in the link frame.
        pos: (3,) anchor in the link frame; a hinge turns about the line through pos along axis.
        range: (lower, upper) in radians (hinge) or metres (slide) when MuJoCo limits the joint, else None.
        damping: viscous damping [N m s/rad or N s/m].
        armature: rotor inertia added to the joint's diagonal of the mass matrix.
        stiffness: joint spring stiffness toward `springref`, 0 if absent.
        springref: spring rest value of q.
        ref: MuJoCo's qpos0 of the joint (MJCF `ref`): the joint's transform is J(q - ref), so q = ref is the pose
            written in the MJCF.
    """

    name: str
    kind: str
    axis: np.ndarray
    pos: np.ndarray
    range: tuple[float, float] | None
    damping: float
    armature: float
    stiffness: float
    springref: float
    ref: float = 0.0


@dataclass(frozen=True)
class GeomSpec:
    """One MJCF geom, expressed in the frame of the link it belongs to.

    Attributes:
        name: geom name ("" when the MJCF leaves it unnamed).
        body: name of the MuJoCo body it belongs to (the link's body or one welded to it).
        kind: "sphere", "capsule", "box", "cylinder", "ellipsoid" or "mesh".
        size: (3,) MuJoCo's compiled size: radius; radius, half-length; half-sizes; radius, half-height; radii (a
            mesh's: MuJoCo's, unused here).
        pos: (3,) geom centre in the link frame.
        quat: (4,) w, x, y, z: geom frame orientation in the link frame (capsule/cylinder axis = geom z).
        mass: analytic mass [kg] (0 for geoms outside `inertiagrouprange` or in a body with an `<inertial>` used).
        contype: MuJoCo contact type bits.
        conaffinity: MuJoCo contact affinity bits.
        mesh: triangulation in the link frame: closed and outward-wound, inscribed in the ideal shape; a mesh
            geom's, MuJoCo's compiled mesh, its own triangles (open where its mass does not count).
        com: (3,) the geom's centre of mass in the link frame (its centre, but for a mesh).
        second_moment: (3, 3) S about ``com``, link frame axes (zero when ``mass`` is 0).
        friction: MuJoCo's sliding friction coefficient of the geom.
    """

    name: str
    body: str
    kind: str
    size: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    mass: float
    contype: int
    conaffinity: int
    mesh: trimesh.Trimesh
    com: np.ndarray
    second_moment: np.ndarray
    friction: float = 1.0


@dataclass(frozen=True)
class LinkSpec:
    """A rigid link: a body with joints (or the root) plus the joint-less bodies welded to it.

    Attributes:
        name: body name.
        parent: index into `MJCFModel.links` of the parent link, -1 for the root link.
        pos: (3,) link frame origin in the parent link frame at zero joint values (root: in the world frame).
        quat: (4,) w, x, y, z: link frame orientation in the parent link frame (root: in the world frame).
        joints: the link's joints, applied in MJCF order.
        mesh: all the link's geoms (welded bodies included) in the link frame, concatenated; each primitive
            geom's mesh is closed (a mesh geom's where its mass counts), the union need not be.
        mass: link mass [kg].
        com: (3,) centre of mass in the link frame.
        second_moment: (3, 3) S = int rho X X^T dV about the COM, link frame axes (inertia = tr(S) I - S).
        geoms: the geoms making up `mesh`, in MuJoCo order.
        bodies: names of the MuJoCo bodies of the link (the link's own body first, then those welded to it).
    """

    name: str
    parent: int
    pos: np.ndarray
    quat: np.ndarray
    joints: tuple[JointSpec, ...]
    mesh: trimesh.Trimesh
    mass: float
    com: np.ndarray
    second_moment: np.ndarray
    geoms: tuple[GeomSpec, ...]
    bodies: tuple[str, ...]


@dataclass(frozen=True)
class ActuatorSpec:
    """A joint actuator, with MuJoCo's semantics: the actuator length is l = gear q, its force is
    f = gain ctrl + bias, and the joint receives the generalised force gear f. Hence

        motor:    tau = gear * ctrl
        position: tau = gear * (kp (ctrl - gear q) - kv gear qdot)      (= kp (ctrl - q) - kv qdot for gear 1)

    with ctrl clipped to ctrlrange and f clipped to forcerange where given.

    Attributes:
        name: actuator name ("" when unnamed).
        joint: index into `MJCFModel.joints`.
        kind: "motor" or "position".
        gear: gear[0] of the MJCF.
        ctrlrange: (lower, upper) when MuJoCo limits the control, else None.
        kp: position gain (0 for motors).
        kv: velocity gain (0 for motors).
        forcerange: (lower, upper) clip of f when MuJoCo limits the force, else None.
    """

    name: str
    joint: int
    kind: str
    gear: float
    ctrlrange: tuple[float, float] | None
    kp: float
    kv: float
    forcerange: tuple[float, float] | None


@dataclass(frozen=True)
class MJCFModel:
    """An articulated model read from MJCF.

    Attributes:
        name: MJCF model name.
        links: parents before children; links[0] is the root.
        joints: all joints, in link order then MJCF order.
        link_joint: per link, indices into `joints`.
        actuators: joint actuators in MJCF order.
        floating: the root body had a free joint (kept outside `joints`: a floating base).
        chain: float64 `pytorch_kinematics.Chain` built from `xml` with the root's free joint removed, or None where
            pytorch-kinematics cannot reproduce MuJoCo's kinematics (several joints on one body, or a joint
            anchor pos != 0, which it mis-handles: it translates by pos without translating back).
        xml: the MJCF text actually used (its <include>s inlined and unnamed bodies named; the free joint kept).
        friction: the sliding friction coefficient of the model's geoms (MuJoCo's default 1 where unset) when they
            all share one, else None. The simulator has one coefficient per scene, Scene(friction=...), 0 by
            default: pass this one to simulate the model's.
    """

    name: str
    links: tuple[LinkSpec, ...]
    joints: tuple[JointSpec, ...]
    link_joint: tuple[tuple[int, ...], ...]
    actuators: tuple[ActuatorSpec, ...]
    floating: bool
    chain: object
    xml: str
    friction: float | None = None


_GEOM_KINDS = {
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
}
_JOINT_KINDS = {int(mujoco.mjtJoint.mjJNT_HINGE): "hinge", int(mujoco.mjtJoint.mjJNT_SLIDE): "slide"}
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_MESH = int(mujoco.mjtGeom.mjGEOM_MESH)
# MuJoCo's legacy volume of a mesh within this fraction of the closed mesh's is the same (float32 vertices: about
# 1e-8 apart)
_LEGACY_REL = 1e-6
# a mesh triangle is degenerate when its doubled area is below this many float32 epsilons of its longest edge times
# the mesh's largest coordinate: MuJoCo keeps mesh vertices in float32 and moves them into the mesh's inertial
# frame, so a zero-area triangle of the file comes back with an area of the order of that rounding, which the
# float64 test on the edges alone lets through; a real sliver (a 3 m rod of 1 mm radius in 256 sections: 2.5e-5 m
# wide) stays above it
_MESH_DEGENERACY_EPS32 = 10.0
# Prefix of the private names given to unnamed geoms, to match the spec's geoms with the compiled ones.
_GEOM_TAG = "__cfd_torch_geom_"


def gymnasium_ant_xml(servos: tuple[float, float] | None = None) -> str:
    """Gymnasium's bundled ant.xml with its four unnamed shin bodies named "ankle_1_link" .. "ankle_4_link"
    (pytorch-kinematics keys frames by body name); everything else unchanged, unless ``servos`` = (kp, kv) is
    given: then each of the eight motors (gear 150) becomes a position servo on the same joint, ctrl the target
    angle in radians (unclipped; the joint's limits still hold), torque kp (ctrl - q) - kv q_dot [N m]."""
    text = (importlib.resources.files("gymnasium") / "envs" / "mujoco" / "assets" / "ant.xml").read_text()
    count = iter(range(1, 5))
    patched, n = re.subn(r"<body pos=", lambda _: f'<body name="ankle_{next(count)}_link" pos=', text)
    if n != 4:
        raise ValueError(f"gymnasium's ant.xml changed: expected 4 unnamed bodies, found {n}")
    if servos is not None:
        try:
            kp, kv = (float(x) for x in servos)
        except (TypeError, ValueError):  # (unpacking and conversion errors named nothing)
            raise ValueError(f"servos must be (kp > 0, kv >= 0), got {servos!r}") from None
        if not (kp > 0 and kv >= 0 and math.isfinite(kp) and math.isfinite(kv)):
            raise ValueError(f"servos must be (kp > 0, kv >= 0), got {servos!r}")
        patched, n = re.subn(
            r'<motor ctrllimited="true" ctrlrange="-1.0 1.0" joint="(\w+)" gear="150"/>',
            lambda mt: f'<position ctrllimited="false" joint="{mt.group(1)}" kp="{kp!r}" kv="{kv!r}"/>',
            patched,
        )
        if n != 8:
            raise ValueError(f"gymnasium's ant.xml changed: expected 8 motors, found {n}")
    return patched


def _spec(xml: str, base: str | None) -> mujoco.MjSpec:
    """The MjSpec of the MJCF text ``xml``, its asset files read relative to the folder ``base`` (None: the working
    directory)."""
    spec = mujoco.MjSpec.from_string(xml)
    if base is not None:
        spec.modelfiledir = base
    return spec


def load_mjcf(
    source: str | os.PathLike,
    *,
    root: str | None = None,
    meshdir: str | os.PathLike | None = None,
    mesh_masses: bool = True,
    sphere_subdivisions: int = 2,
    capsule_count: tuple[int, int] = (12, 6),
    cylinder_sections: int = 16,
) -> MJCFModel:
    """Read an articulated model from MJCF or URDF.

    Args:
        source: path of an MJCF file, or the MJCF text itself (anything starting with "<"); or URDF (a root
            element ``<robot>``), read through MuJoCo's URDF importer (:func:`cfd_torch.sim.urdf.urdf_as_mjcf`).
        meshdir: the folder of the model's mesh files, relative to the model file's folder (the working directory
            for text) or absolute, in place of the model's ``<compiler meshdir>``: for example ``"../meshes"`` for a
            URDF's ``package://`` meshes (MuJoCo looks them up by their file names alone) in a ROS package's
            ``meshes/`` beside its ``urdf/`` folder.
        mesh_masses: False leaves the masses of mesh geoms out (0), for a robot whose masses play no part
            (``articulation(..., kinematic=True)`` passes it): an open mesh whose mass would count loads.
        root: name of the root body; default: the single top-level body of the worldbody. Its subtree is the
            model; the worldbody's own geoms (floors) and other top-level bodies are ignored, and so are the
            actuators that act on them only.
        sphere_subdivisions: icosphere subdivisions of sphere and ellipsoid meshes.
        capsule_count: (longitude, latitude) counts of capsule meshes (trimesh.creation.capsule).
        cylinder_sections: sections of cylinder meshes.

    Returns:
        The model; see `MJCFModel`.

    Raises:
        ValueError: for an MJCF feature outside the supported set (see the module docstring), naming it, or a
            model MuJoCo cannot read.
        TypeError: ``source`` or ``meshdir`` is not text or a path.
    """
    if not (is_int(sphere_subdivisions) and 0 <= sphere_subdivisions <= 6):
        raise ValueError(f"sphere_subdivisions must be an int in 0..6, got {sphere_subdivisions!r}")
    if not (
        isinstance(capsule_count, (tuple, list))
        and len(capsule_count) == 2
        and all(is_int(c) for c in capsule_count)
        and capsule_count[0] >= 3
        and capsule_count[1] >= 3
    ):
        raise ValueError(
            f"capsule_count must be two ints (longitude, latitude), each >= 3 (fewer give an open mesh), got "
            f"{capsule_count!r}"
        )
    if not isinstance(mesh_masses, bool):
        raise TypeError(f"mesh_masses must be a bool, got {type(mesh_masses).__name__}")
    if not (is_int(cylinder_sections) and cylinder_sections >= 3):
        raise ValueError(f"cylinder_sections must be an int >= 3, got {cylinder_sections!r}")
    # the model file's folder: asset files (meshes) and <include>d files are read from it, as MuJoCo does
    base = None
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(
            f"source must be MJCF text or a path to an MJCF file (str or os.PathLike), got {type(source).__name__}"
        )
    if isinstance(source, os.PathLike) or not source.lstrip("\ufeff \t\r\n").startswith("<"):
        with open(source) as f:
            xml = f.read()
        base = os.path.dirname(os.path.abspath(source))
    else:
        xml = source.lstrip("\ufeff")
    if meshdir is not None and not isinstance(meshdir, (str, os.PathLike)):
        raise TypeError(f"meshdir must be a folder path (str or os.PathLike), got {type(meshdir).__name__}")
    meshdir = None if meshdir is None else os.fspath(meshdir)
    urdf = is_urdf(xml)
    if urdf:
        xml = urdf_as_mjcf(xml, base, meshdir)
    xml, tree = _prepared_xml(xml, base)
    if meshdir is not None and not urdf:  # (after the includes are inlined: theirs are overridden too)
        xml = _with_meshdir(xml, meshdir)
        tree = ET.fromstring(xml)
    spec = _spec(xml, base)
    unnamed = _unnamed_bodies(spec.worldbody)
    if unnamed:
        raise ValueError(
            f"{len(unnamed)} unnamed bodies made by <attach> (children of {sorted(set(unnamed))[:4]}):"
            " name them in the MJCF"
        )
    root = _root_name(spec, root)
    _check_spec(spec)
    geom_source = _tag_geoms(spec)
    mass_scale = 1.0
    if spec.compiler.settotalmass > 0:  # MuJoCo scales every mass and inertia by one factor
        unscaled = _spec(xml, base)
        unscaled.compiler.settotalmass = -1
        mass_scale = spec.compiler.settotalmass / float(unscaled.compile().body_mass.sum())
    explicit_inertial = {b.name: bool(b.explicitinertial) for b in spec.bodies}
    inertiafromgeom = mujoco.mjtInertiaFromGeom(spec.compiler.inertiafromgeom)
    group_lo, group_hi = (int(g) for g in spec.compiler.inertiagrouprange)
    mesh_inertia = [int(mesh.inertia) for mesh in spec.meshes]  # (compiled in this order: by mesh id)
    m = spec.compile()

    root_id = m.body(root).id
    floating, root_pos, root_quat = _root_pose(m, root_id)

    # Bodies of the root's subtree; MuJoCo numbers bodies depth-first, so parents come before children.
    in_tree = {root_id}
    for b in range(root_id + 1, m.nbody):
        if int(m.body_parentid[b]) in in_tree:
            in_tree.add(b)
    bodies = sorted(in_tree)
    _check_model(m, in_tree)
    if spec.compiler.degree and not any(c.get("angle") for c in tree.iter("compiler")):
        _warn_if_radians_in_degrees(m, in_tree)

    link_of: dict[int, int] = {}  # body id -> link index
    T_in_link: dict[int, np.ndarray] = {}  # body id -> (4, 4) body frame in its link frame
    link_bodies: list[list[int]] = []
    link_parent: list[int] = []
    link_pose: list[np.ndarray] = []
    joints: list[JointSpec] = []
    joint_index: dict[int, int] = {}  # MuJoCo joint id -> index into joints
    link_joint: list[tuple[int, ...]] = []
    for b in bodies:
        parent = int(m.body_parentid[b])
        jids = list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]))
        if b == root_id:
            jids = [j for j in jids if m.jnt_type[j] != _FREE]
            pose = _transform(root_pos, root_quat)
        else:
            pose = T_in_link[parent] @ _transform(m.body_pos[b], m.body_quat[b])
        if b == root_id or jids:
            link_of[b] = len(link_bodies)
            T_in_link[b] = np.eye(4)
            link_bodies.append([b])
            link_parent.append(-1 if b == root_id else link_of[parent])
            link_pose.append(pose)
            link_joint.append(tuple(range(len(joints), len(joints) + len(jids))))
            for j in jids:
                joint_index[j] = len(joints)
                joints.append(_joint_spec(m, j))
        else:
            link_of[b] = link_of[parent]
            T_in_link[b] = pose
            link_bodies[link_of[b]].append(b)

    links = []
    frictions: set[float] = set()  # of the geoms in collision meshes
    # the geoms MuJoCo never collides that stay in a collision mesh (their link has no other)
    visual_only: list[str] = []
    left_out: list[str] = []  # the visual-only geoms of types kept only where they collide or have mass
    for k, group in enumerate(link_bodies):
        geoms: list[GeomSpec] = []
        # (mass, COM, second moment about the COM) of each body's <inertial> or each geom, link frame
        parts: list[tuple[float, np.ndarray, np.ndarray]] = []
        for b in group:
            T = T_in_link[b]
            # MuJoCo's rule: inertiafromgeom "false" takes every body's <inertial> (none: massless), "auto" the
            # <inertial> where there is one, "true" always the geoms.
            inertial = inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE or (
                inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO
                and explicit_inertial[m.body(b).name]
            )
            if inertial:
                R = T[:3, :3] @ quat_to_matrix(m.body_iquat[b])
                inertia = R @ np.diag(m.body_inertia[b]) @ R.T
                parts.append(
                    (float(m.body_mass[b]), T[:3, :3] @ m.body_ipos[b] + T[:3, 3], _inertia_to_S(inertia))
                )
            for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b]):
                # MuJoCo infers masses from the geoms in inertiagrouprange only.
                counts = (
                    not inertial
                    and group_lo <= m.geom_group[g] <= group_hi
                    and (mesh_masses or int(m.geom_type[g]) != _MESH)
                )
                name, density, explicit_mass, _ = geom_source[m.geom(g).name]
                massless = explicit_mass == 0 or (math.isnan(explicit_mass) and density == 0)
                if int(m.geom_type[g]) not in _GEOM_KINDS and not (
                    (counts and not massless) or m.geom_contype[g] or m.geom_conaffinity[g]
                ):  # a visual mesh (or plane, ...): no mass, no contact, nothing the step needs
                    left_out.append(name or f"{m.body(b).name}/#{g - m.body_geomadr[b]}")
                    continue
                geom = _geom_spec(
                    m,
                    g,
                    T,
                    geom_source,
                    sphere_subdivisions,
                    capsule_count,
                    cylinder_sections,
                    counts,
                    massless,
                    mass_scale,
                    mesh_inertia,
                )
                if counts:
                    parts.append((geom.mass, geom.com, geom.second_moment))
                geoms.append(geom)
        mass, com, S = _combine(parts)
        pose = link_pose[k]
        # the collision mesh: the geoms MuJoCo may collide (contype or conaffinity nonzero); a link with none keeps
        # all of its geoms (a body needs a mesh), and they collide
        colliding = [g for g in geoms if g.contype or g.conaffinity]
        frictions.update(g.friction for g in colliding or geoms)
        if geoms and not colliding:
            visual_only += [g.name or f"{m.body(group[0]).name}/#{i}" for i, g in enumerate(geoms)]
        links.append(
            LinkSpec(
                name=m.body(group[0]).name,
                parent=link_parent[k],
                pos=pose[:3, 3].copy(),
                quat=matrix_to_quat(pose[:3, :3]),
                joints=tuple(joints[i] for i in link_joint[k]),
                mesh=trimesh.util.concatenate([g.mesh for g in colliding or geoms])
                if geoms
                else trimesh.Trimesh(),
                mass=mass,
                com=com,
                second_moment=S,
                geoms=tuple(geoms),
                bodies=tuple(m.body(b).name for b in group),
            )
        )

    if left_out:
        warnings.warn(
            f"geoms {left_out[:8]}{' ...' if len(left_out) > 8 else ''} are left out: visual only (contype = "
            "conaffinity = 0 and no mass counted), of a type kept only where it collides or has mass (mesh) or "
            "never (plane, hfield, sdf)",
            UserWarning,
            stacklevel=3,
        )
    if visual_only:
        warnings.warn(
            f"geoms {visual_only[:8]}{' ...' if len(visual_only) > 8 else ''} have contype = conaffinity = 0 "
            "(MuJoCo never collides them) but are all their link has: they are its collision mesh here, and collide",
            UserWarning,
            stacklevel=3,
        )
    actuators = tuple(_actuator_spec(m, a, joint_index) for a in range(m.nu) if _acts_in_tree(m, a, in_tree))
    if len(frictions) > 1:
        warnings.warn(
            f"MJCF geom friction differs between the model's colliding geoms ({', '.join(map(repr, sorted(frictions)))}"
            "): ignored; one coefficient, Scene(friction=...), applies to every contact",
            stacklevel=2,
        )
    pk_ok = all(len(ids) <= 1 for ids in link_joint) and all(not np.any(j.pos) and j.ref == 0 for j in joints)
    return MJCFModel(
        name=spec.modelname,
        links=tuple(links),
        joints=tuple(joints),
        link_joint=tuple(link_joint),
        actuators=actuators,
        floating=floating,
        chain=_build_chain(xml, root, _asset_files(spec, base)) if pk_ok else None,
        xml=xml,
        friction=frictions.pop() if len(frictions) == 1 else None,
    )


def _with_meshdir(xml: str, meshdir: str) -> str:
    """The MJCF text with every ``<compiler>``'s meshdir set to ``meshdir`` (a compiler element added first where
    there is none)."""
    tree = ET.fromstring(xml)
    compilers = list(tree.iter("compiler"))
    if not compilers:
        compilers = [ET.Element("compiler")]
        tree.insert(0, compilers[0])
    for c in compilers:
        c.set("meshdir", meshdir)
    return ET.tostring(tree, encoding="unicode")


def _prepared_xml(xml: str, base: str | None) -> tuple[str, ET.Element]:
    """The MJCF text with its <include> elements replaced by the included files' elements and every unnamed body
    named after its parent and its place among the parent's child bodies ("torso/2"; pytorch-kinematics keys frames
    by body name), the text itself where it has neither; and its element tree. Attributes are kept as written:
    MuJoCo's own rewrite (``MjSpec.to_xml``) would drop compiler options such as settotalmass and round numbers to 6
    digits."""
    try:
        tree = ET.fromstring(xml)
    except ET.ParseError as e:
        raise ValueError(f"the model (MJCF or URDF) is not well-formed XML: {e}") from None
    here = base or os.getcwd()
    changed = _inline_includes(tree, here, here, set())
    # the <worldbody> sections (a model and the files it includes may each have one) are one world, as in MuJoCo
    taken = {b.get("name") for b in tree.iter("body") if b.get("name")}
    changed = _name_body_elements(list(tree.iter("worldbody")), "", taken) or changed
    return (ET.tostring(tree, encoding="unicode") if changed else xml), tree


def _inline_includes(element: ET.Element, base: str, folder: str, seen: set[str]) -> bool:
    """Replace each <include file="..."/> below ``element`` by the children of the included file's root,
    recursively, as MuJoCo does: the file is looked for relative to the main model's folder ``base``, then to the
    including file's ``folder``; a file included twice is refused (``seen``: the files included so far). Whether
    any was found."""
    found = False
    for parent in list(element.iter()):
        children = list(parent)
        if not any(c.tag == "include" for c in children):
            continue
        found = True
        for i in reversed(range(len(children))):
            include = children[i]
            if include.tag != "include":
                continue
            name = include.get("file")
            if not name:
                raise ValueError("MJCF <include> without a file attribute")
            path = os.path.normpath(os.path.join(base, name))
            if not os.path.isfile(path) and os.path.isfile(os.path.join(folder, name)):
                path = os.path.normpath(os.path.join(folder, name))
            if path in seen:
                raise ValueError(
                    f"MJCF <include file={name!r}>: {path} is already included (MuJoCo refuses it)"
                )
            seen.add(path)
            try:
                with open(path) as f:
                    included = ET.fromstring(f.read())
            except OSError as e:
                raise ValueError(f"MJCF <include file={name!r}>: cannot read {path}: {e.strerror}") from None
            except ET.ParseError as e:
                raise ValueError(f"MJCF <include file={name!r}>: not well-formed XML: {e}") from None
            _inline_includes(included, base, os.path.dirname(path), seen)
            parent.remove(include)
            for k, child in enumerate(list(included)):
                parent.insert(i + k, child)
    return found


def _child_bodies(element: ET.Element) -> list[ET.Element]:
    """The <body> elements directly below ``element``, looking through <frame> and <replicate> elements (MuJoCo
    suffixes a replicated body's name), in document order."""
    out = []
    for child in element:
        if child.tag == "body":
            out.append(child)
        elif child.tag in ("frame", "replicate"):
            out += _child_bodies(child)
    return out


def _name_body_elements(parents: list[ET.Element], prefix: str, taken: set[str]) -> bool:
    """Name every unnamed <body> below the ``parents`` (the elements of one body, or the worldbody sections) after
    their body and its place among that body's child bodies, with "_" appended while the name is ``taken``;
    whether any was unnamed."""
    named = False
    for k, body in enumerate(b for p in parents for b in _child_bodies(p)):
        if not body.get("name"):
            claim_name(body, f"{prefix or 'world'}/{k}", taken)
            named = True
        named = _name_body_elements([body], body.get("name"), taken) or named
    return named


def _unnamed_bodies(parent, prefix: str = "world") -> list[str]:
    """The names of the parents of the spec's unnamed bodies (none once `_prepared_xml` has named them, unless
    <attach> made them)."""
    out = []
    for body in parent.bodies:
        if not body.name:
            out.append(prefix)
        out += _unnamed_bodies(body, body.name or f"{prefix}/?")
    return out


def _root_name(spec: mujoco.MjSpec, root: str | None) -> str:
    if root is not None and not isinstance(root, str):
        raise TypeError(f"root must be the name of a body (a str), got {type(root).__name__}")
    if root == "world":
        raise ValueError("root must name a body inside the worldbody, not 'world' itself")
    top = [b.name for b in spec.worldbody.bodies]
    if root is None:
        if len(top) != 1:
            raise ValueError(f"the worldbody has {len(top)} top-level bodies {top}: pass root=")
        root = top[0]
    if spec.find_body(root) is None:
        raise ValueError(f"no body named '{root}'")
    return root


def _check_spec(spec: mujoco.MjSpec) -> None:
    """Refusals that MuJoCo's compiler would report less precisely, or that would change the masses."""
    top = {b.name for b in spec.worldbody.bodies}
    for body in spec.bodies:
        for joint in body.joints:
            if joint.type == mujoco.mjtJoint.mjJNT_FREE and body.name not in top:
                raise ValueError(
                    f"free joint '{joint.name}' in body '{body.name}': only the root body may have a free joint"
                )
    colliding = {
        g.meshname
        for g in spec.geoms
        if g.type == mujoco.mjtGeom.mjGEOM_MESH and (g.contype or g.conaffinity)
    }
    for mesh in spec.meshes:
        name = mesh.name or os.path.splitext(os.path.basename(mesh.file))[0]
        if mesh.inertia == mujoco.mjtMeshInertia.mjINERTIA_CONVEX and name not in colliding:
            raise ValueError(
                f"mesh '{name}': inertia=\"convex\" on a mesh that no geom collides with crashes MuJoCo "
                f'{mujoco.__version__}\'s compiler (a segmentation fault): use inertia="exact", or leave the mesh out'
            )
    c = spec.compiler
    if c.boundmass > 0 or c.boundinertia > 0 or c.balanceinertia:
        raise ValueError("compiler boundmass/boundinertia/balanceinertia are not supported")
    for option in ("discardvisual", "fusestatic"):
        if getattr(c, option):
            raise ValueError(
                f'compiler {option}="true" is not supported (the compiled model loses geoms or bodies that the '
                f"links' mass properties here are computed from): remove it (bodies without joints are welded into "
                "their link here anyway)"
            )


def _warn_if_radians_in_degrees(m: mujoco.MjModel, in_tree: set[int]) -> None:
    """Warn where the model leaves <compiler angle> at MuJoCo's default, degrees, and every limited hinge of the
    subtree has a range within +-2 pi "degrees": most likely a range written in radians (range="-2.8 2.8" is
    +-0.049 rad)."""
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    limited = [
        j
        for j in range(m.njnt)
        if int(m.jnt_bodyid[j]) in in_tree and int(m.jnt_type[j]) == hinge and bool(m.jnt_limited[j])
    ]
    degrees = [np.degrees(m.jnt_range[j]) for j in limited]
    if limited and all(float(np.abs(r).max()) <= 2 * math.pi + 1e-9 for r in degrees):
        j = limited[0]
        lo, hi = (float(x) for x in degrees[0])
        warnings.warn(
            f"every limited hinge's range is within +-2 pi degrees (joint '{m.joint(j).name}': {lo:g} .. {hi:g} "
            'degrees): MJCF angles are in degrees unless <compiler angle="radian"/> says otherwise; add it if the '
            "ranges are radians",
            UserWarning,
            stacklevel=3,
        )


def _check_model(m: mujoco.MjModel, in_tree: set[int]) -> None:
    """Refuse the physics the simulator does not model (it would be silently absent) where it touches the loaded
    subtree (the bodies ``in_tree``): joint friction loss and actuator force ranges, gravity compensation, equality
    constraints, and tendons with limits, stiffness or damping; warn of fluid forces (the options density,
    viscosity and wind) and limited joints' margins, which the step leaves out too."""
    for b in sorted(in_tree):
        if float(m.body_gravcomp[b]) != 0:
            raise ValueError(f"body '{m.body(b).name}': gravcomp is not supported (gravity compensation)")
    margins = [
        f"'{m.joint(j).name}' ({float(m.jnt_margin[j]):g})"
        for j in range(m.njnt)
        if int(m.jnt_bodyid[j]) in in_tree and bool(m.jnt_limited[j]) and float(m.jnt_margin[j]) != 0
    ]
    if margins:
        warnings.warn(
            f"MJCF joint margin of {', '.join(margins)}: ignored; the step's joint limits are barriers at the range "
            "itself",
            stacklevel=4,
        )
    off = [
        name
        for name in ("gravity", "contact", "constraint", "limit", "passive", "actuation", "clampctrl")
        if int(m.opt.disableflags) & int(getattr(mujoco.mjtDisableBit, f"mjDSBL_{name.upper()}"))
    ]
    if off:
        flags = " ".join(n + '="disable"' for n in off)
        raise ValueError(
            f"MJCF <flag {flags}>: the step always models these (gravity is Scene(gravity=...)'s: give (0, 0, 0) "
            "for none); remove the flags"
        )
    if not np.allclose(m.opt.gravity, (0.0, 0.0, -9.81)):
        warnings.warn(
            f"MJCF <option gravity={tuple(float(g) for g in m.opt.gravity)}>: ignored; the step's gravity is "
            "Scene(gravity=...)'s",
            stacklevel=4,
        )
    if m.npair or m.nexclude:
        warnings.warn(
            f"MJCF <contact>: {m.npair} <pair> and {m.nexclude} <exclude> elements ignored; the Scene's contact model "
            "acts between every two bodies it pairs, with one friction coefficient",
            stacklevel=4,
        )
    fluid = [f"{k}={getattr(m.opt, k)}" for k in ("density", "viscosity") if float(getattr(m.opt, k)) != 0]
    fluid += [f"wind={tuple(float(w) for w in m.opt.wind)}"] if bool(np.any(m.opt.wind != 0)) else []
    if fluid:
        warnings.warn(
            f"MJCF <option {' '.join(fluid)}>: fluid forces are not modelled by the step (ignored)",
            stacklevel=4,
        )
    joints = {j for j in range(m.njnt) if int(m.jnt_bodyid[j]) in in_tree}
    for j in sorted(joints):
        name = m.joint(j).name
        if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE):  # the base moves as a free body
            dofs = range(int(m.jnt_dofadr[j]), int(m.jnt_dofadr[j]) + 6)
            if any(float(m.dof_damping[d]) > 0 or float(m.dof_armature[d]) > 0 for d in dofs) or (
                float(m.jnt_stiffness[j]) > 0
            ):
                raise ValueError(
                    f"free joint '{name}': damping, armature and stiffness on a free joint are not supported"
                )
        if float(m.dof_frictionloss[m.jnt_dofadr[j]]) > 0:
            raise ValueError(f"joint '{name}': frictionloss is not supported (dry joint friction)")
        if bool(m.jnt_actfrclimited[j]):
            raise ValueError(
                f"joint '{name}': actuatorfrcrange is not supported (clamp the actuators' ctrlrange)"
            )

    for t in range(m.ntendon):
        if (
            bool(m.tendon_limited[t])
            or float(m.tendon_stiffness[t]) > 0
            or float(m.tendon_damping[t]) > 0
            or float(m.tendon_frictionloss[t]) > 0
        ) and _tendon_touches(m, t, in_tree):
            raise ValueError(
                f"tendon '{m.tendon(t).name}': tendon limits, stiffness, damping and frictionloss are not supported"
            )
    for e in range(m.neq):
        kind, site = int(m.eq_type[e]), int(m.eq_objtype[e]) == int(mujoco.mjtObj.mjOBJ_SITE)
        touches = False
        for obj in (int(m.eq_obj1id[e]), int(m.eq_obj2id[e])):
            if obj < 0:
                continue
            if kind == int(mujoco.mjtEq.mjEQ_JOINT):
                touches |= obj in joints
            elif kind == int(mujoco.mjtEq.mjEQ_TENDON):
                touches |= _tendon_touches(m, obj, in_tree)
            elif kind in (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)):
                touches |= (int(m.site_bodyid[obj]) if site else obj) in in_tree
            else:  # flex and other kinds: refused outright
                touches = True
        if touches:
            raise ValueError(f"<equality> constraint {m.equality(e).name or e!r} is not supported")


def _tendon_touches(m: mujoco.MjModel, t: int, in_tree: set[int]) -> bool:
    """Whether tendon t wraps a joint or a site of the bodies ``in_tree``."""
    adr, num = int(m.tendon_adr[t]), int(m.tendon_num[t])
    for w in range(adr, adr + num):
        obj = int(m.wrap_objid[w])
        if int(m.wrap_type[w]) == int(mujoco.mjtWrap.mjWRAP_JOINT) and int(m.jnt_bodyid[obj]) in in_tree:
            return True
        if int(m.wrap_type[w]) == int(mujoco.mjtWrap.mjWRAP_SITE) and int(m.site_bodyid[obj]) in in_tree:
            return True
    return False


def _acts_in_tree(m: mujoco.MjModel, a: int, in_tree: set[int]) -> bool:
    """Whether actuator a's transmission reaches the bodies ``in_tree`` (its joint's, site's or body's body, or
    its tendon's joints and sites); an actuator of another top-level body is left out with that body."""
    kind, target = int(m.actuator_trntype[a]), int(m.actuator_trnid[a, 0])
    if kind in (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
        return int(m.jnt_bodyid[target]) in in_tree
    if kind in (int(mujoco.mjtTrn.mjTRN_SITE), int(mujoco.mjtTrn.mjTRN_SLIDERCRANK)):
        return int(m.site_bodyid[target]) in in_tree
    if kind == int(mujoco.mjtTrn.mjTRN_BODY):
        return target in in_tree
    if kind == int(mujoco.mjtTrn.mjTRN_TENDON):
        return _tendon_touches(m, target, in_tree)
    return True  # (any other kind is refused by name)


def _tag_geoms(spec: mujoco.MjSpec) -> dict[str, tuple[str, float, float, bool]]:
    """Name the unnamed geoms privately; return compiled name -> (MJCF name, density, explicit mass or nan,
    shell inertia)."""
    source = {}
    for k, geom in enumerate(spec.geoms):
        name = geom.name
        if not name:
            geom.name = f"{_GEOM_TAG}{k}"
        shell = geom.typeinertia == mujoco.mjtGeomInertia.mjINERTIA_SHELL
        source[geom.name] = (name, float(geom.density), float(geom.mass), shell)
    return source


def _root_pose(m: mujoco.MjModel, root_id: int) -> tuple[bool, np.ndarray, np.ndarray]:
    """Whether the root is floating, and its world pose at qpos0 (its ancestors must be joint-less)."""
    jids = range(m.body_jntadr[root_id], m.body_jntadr[root_id] + m.body_jntnum[root_id])
    free = [j for j in jids if m.jnt_type[j] == _FREE]
    if free and m.body_jntnum[root_id] > 1:
        raise ValueError(f"body '{m.body(root_id).name}' has a free joint and other joints")
    T = _transform(m.body_pos[root_id], m.body_quat[root_id])
    b = int(m.body_parentid[root_id])
    while b != 0:
        if m.body_jntnum[b]:
            raise ValueError(
                f"root body '{m.body(root_id).name}' has an ancestor with joints, '{m.body(b).name}'"
            )
        T = _transform(m.body_pos[b], m.body_quat[b]) @ T
        b = int(m.body_parentid[b])
    return bool(free), T[:3, 3].copy(), matrix_to_quat(T[:3, :3])


def _joint_spec(m: mujoco.MjModel, j: int) -> JointSpec:
    joint = m.joint(j)
    kind = _JOINT_KINDS.get(int(m.jnt_type[j]))
    where = f"joint '{joint.name}' of body '{m.body(m.jnt_bodyid[j]).name}'"
    if kind is None:
        type_name = mujoco.mjtJoint(int(m.jnt_type[j])).name.removeprefix("mjJNT_").lower()
        raise ValueError(f"{where}: {type_name} joints are not supported (hinge and slide only)")
    if not joint.name:
        raise ValueError(f"unnamed {kind} joint of body '{m.body(m.jnt_bodyid[j]).name}'")
    qadr, dadr = int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])
    for what, value in (
        ("damping", m.dof_damping[dadr]),
        ("armature", m.dof_armature[dadr]),
        ("stiffness", m.jnt_stiffness[j]),
    ):  # negative values add energy: the step's joint terms would have no minimum
        if not 0 <= float(value) < math.inf:
            raise ValueError(f"joint '{joint.name}': {what} must be finite and >= 0, got {float(value):g}")
    for what, value in (
        ("range", m.jnt_range[j] if m.jnt_limited[j] else np.zeros(2)),  # (NaN read as no limit at all)
        ("axis", m.jnt_axis[j]),
        ("pos", m.jnt_pos[j]),
        ("ref", m.qpos0[qadr : qadr + 1]),
        ("springref", m.qpos_spring[qadr : qadr + 1]),
    ):
        if not np.isfinite(value).all():
            raise ValueError(f"joint '{joint.name}': {what} must be finite, got {np.asarray(value).tolist()}")
    return JointSpec(
        name=joint.name,
        kind=kind,
        axis=m.jnt_axis[j].copy(),
        pos=m.jnt_pos[j].copy(),
        range=(float(m.jnt_range[j, 0]), float(m.jnt_range[j, 1])) if m.jnt_limited[j] else None,
        damping=float(m.dof_damping[dadr]),
        armature=float(m.dof_armature[dadr]),
        stiffness=float(m.jnt_stiffness[j]),
        springref=float(m.qpos_spring[qadr]),
        ref=float(m.qpos0[qadr]),
    )


def _geom_spec(
    m: mujoco.MjModel,
    g: int,
    T_link_body: np.ndarray,
    source: dict[str, tuple[str, float, float, bool]],
    sphere_subdivisions: int,
    capsule_count: tuple[int, int],
    cylinder_sections: int,
    counts: bool,
    massless: bool,
    mass_scale: float,
    mesh_inertia: list[int],
) -> GeomSpec:
    compiled_name = m.geom(g).name
    name, density, explicit_mass, shell = source[compiled_name]
    kind = "mesh" if int(m.geom_type[g]) == _MESH else _GEOM_KINDS.get(int(m.geom_type[g]))
    label = f"'{name}'" if name else f"#{g - m.body_geomadr[m.geom_bodyid[g]]} (unnamed)"
    if shell and counts:
        raise ValueError(
            f"geom {label} of body '{m.body(m.geom_bodyid[g]).name}': shell inertia is not supported"
        )
    if kind is None:
        type_name = mujoco.mjtGeom(int(m.geom_type[g])).name.removeprefix("mjGEOM_").lower()
        raise ValueError(
            f"geom {label} of body '{m.body(m.geom_bodyid[g]).name}' has unsupported type {type_name} (left out "
            "only when visual: contype = conaffinity = 0 and no mass counted)"
        )
    size = m.geom_size[g].copy()
    T = T_link_body @ _transform(m.geom_pos[g], m.geom_quat[g])
    if kind == "mesh":
        where = f"geom {label} of body '{m.body(m.geom_bodyid[g]).name}'"
        mesh, volume, com, S_unit = _mesh_geom(m, g, T, where, counts and not massless, mesh_inertia)
        mass = mass_scale * (explicit_mass if not math.isnan(explicit_mass) else density * volume)
        S = S_unit * (mass / volume if counts else 0.0)
    else:
        mass = mass_scale * (
            explicit_mass if not math.isnan(explicit_mass) else density * _volume(kind, size)
        )
        mesh = _primitive_mesh(kind, size, sphere_subdivisions, capsule_count, cylinder_sections)
        mesh.apply_transform(T)
        com = T[:3, 3].copy()
        R = T[:3, :3]
        S = R @ _shape_second_moment(kind, size, mass) @ R.T
    return GeomSpec(
        name=name,
        body=m.body(m.geom_bodyid[g]).name,
        kind=kind,
        size=size,
        pos=T[:3, 3].copy(),
        quat=matrix_to_quat(T[:3, :3]),
        mass=float(mass) if counts else 0.0,
        contype=int(m.geom_contype[g]),
        conaffinity=int(m.geom_conaffinity[g]),
        mesh=mesh,
        friction=float(m.geom_friction[g, 0]),
        com=com,
        second_moment=S if counts else np.zeros((3, 3)),
    )


def _hull(m: mujoco.MjModel, mid: int, V: np.ndarray) -> trimesh.Trimesh:
    """The convex hull MuJoCo made of mesh ``mid`` (``maxhullvert`` honoured), over its vertices ``V``: the faces of
    its ``mesh_graph`` (numvert, numface, vert_edgeadr, vert_globalid, edge_localid, face_globalid). MuJoCo makes
    one for every mesh a geom collides with, and a convex-inertia mesh that none collides with is refused
    (``_check_spec``)."""
    graph = m.mesh_graph[int(m.mesh_graphadr[mid]) :]
    nv, nf = int(graph[0]), int(graph[1])
    start = 2 + 2 * nv + nv + 3 * nf
    faces = graph[start : start + 3 * nf].reshape(nf, 3).astype(np.int64)
    hull = trimesh.Trimesh(V, faces, process=False)
    hull.remove_unreferenced_vertices()
    trimesh.repair.fix_normals(hull)  # (outward, whatever MuJoCo's orientation)
    return hull


def _mesh_geom(
    m: mujoco.MjModel, g: int, T: np.ndarray, where: str, counts: bool, mesh_inertia: list[int]
) -> tuple[trimesh.Trimesh, float, np.ndarray, np.ndarray]:
    """A mesh geom's triangles in the link frame (MuJoCo's compiled mesh, placed by the geom frame ``T``: link <-
    geom), and where its mass counts, the volume, centre of volume (link frame) and second moment per unit density
    about it (link frame axes), from the mesh as MuJoCo's ``<mesh inertia>`` (``mesh_inertia``, by compiled mesh
    id) says: "exact" and "legacy" the closed mesh itself (where MuJoCo's legacy rule counts more, on a mesh not
    star-shaped about its legacy centre, a warning says so), "convex" MuJoCo's convex hull of it. Else volume 1 and zero
    moments."""
    mid = int(m.geom_dataid[g])
    name = m.mesh(mid).name
    v0, nv = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
    f0, nf = int(m.mesh_faceadr[mid]), int(m.mesh_facenum[mid])
    own = m.mesh_vert[v0 : v0 + nv].astype(np.float64)  # (the float32 values, in the mesh's frame)
    V = own @ T[:3, :3].T + T[:3, 3]
    F = m.mesh_face[f0 : f0 + nf].astype(np.int64)
    check_mesh(V, F, f"mesh '{name}' of {where}: vertices", f"mesh '{name}' of {where}: faces")
    tri = own[F]
    twice_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    eps = _MESH_DEGENERACY_EPS32 * float(np.finfo(np.float32).eps) * float(np.abs(own).max())
    bad = twice_area < eps * longest
    if bad.any():
        raise ValueError(
            f"mesh '{name}' of {where}: faces has degenerate triangles (zero area, up to the rounding of MuJoCo's "
            f"float32 vertices): first face {int(np.argmax(bad))}, {int(bad.sum())} in all"
        )
    mesh = trimesh.Trimesh(V, F, process=False)
    if not counts:
        return mesh, 1.0, T[:3, 3].copy(), np.zeros((3, 3))
    mode = mesh_inertia[mid]
    # (the closed surface with the copies of a vertex merged: MuJoCo keeps an OBJ's per-face vertices)
    solid = mesh.copy()
    solid.merge_vertices()
    if mode == int(mujoco.mjtMeshInertia.mjINERTIA_CONVEX):
        solid = _hull(m, mid, V)
    elif not (solid.is_watertight and solid.is_winding_consistent and solid.volume > 0):
        raise ValueError(
            f"mesh '{name}' of {where} is not a closed, outward-wound surface, so its mass properties are undefined: "
            'give its body an <inertial>, the geom mass="0" (where other geoms of its body have mass), or the mesh '
            'inertia="convex" (its convex hull\'s)'
        )
    elif mode == int(mujoco.mjtMeshInertia.mjINERTIA_LEGACY):
        legacy = _legacy_volume(solid)
        if legacy > (1.0 + _LEGACY_REL) * solid.volume:
            warnings.warn(
                f"mesh '{name}' of {where}: its mass properties here are the closed mesh's (volume "
                f"{solid.volume:.6g}); MuJoCo's default legacy rule counts {legacy:.6g} for it (a mesh not "
                f'star-shaped about its legacy centre): in MJCF, set inertia="exact" on the <mesh> for MuJoCo to agree',
                UserWarning,
                stacklevel=5,
            )
    props = solid.mass_properties  # (density 1)
    return mesh, float(props["volume"]), np.asarray(props["center_mass"]), _inertia_to_S(props["inertia"])


def _legacy_volume(mesh: trimesh.Trimesh) -> float:
    """The volume MuJoCo's legacy mesh inertia counts (MuJoCo 3.2's two passes): the tetrahedra from the
    area-weighted centre of the faces to each face give, weighted by their magnitudes, a centre c (their own
    centroids averaged); the tetrahedra from c to each face, their magnitudes summed, are the volume (the closed
    mesh's where the mesh is star-shaped about c, more elsewhere)."""
    tri = mesh.triangles
    centroid = tri.mean(1)
    area = mesh.area_faces
    fc = (centroid * area[:, None]).sum(0) / area.sum()

    def magnitudes(c: np.ndarray) -> np.ndarray:
        a, b, d = tri[:, 0] - c, tri[:, 1] - c, tri[:, 2] - c
        return np.abs(np.einsum("ij,ij->i", a, np.cross(b, d))) / 6.0

    v = magnitudes(fc)
    c = (v[:, None] * (0.75 * centroid + 0.25 * fc)).sum(0) / v.sum()
    return float(magnitudes(c).sum())


def _volume(kind: str, size: np.ndarray) -> float:
    r = float(size[0])
    if kind == "sphere":
        return 4.0 / 3.0 * math.pi * r**3
    if kind == "capsule":
        return math.pi * r * r * (4.0 / 3.0 * r + 2.0 * float(size[1]))
    if kind == "cylinder":
        return math.pi * r * r * 2.0 * float(size[1])
    if kind == "box":
        return 8.0 * float(np.prod(size))
    return 4.0 / 3.0 * math.pi * float(np.prod(size))  # ellipsoid


def _shape_second_moment(kind: str, s: np.ndarray, m: float) -> np.ndarray:
    """(3, 3) S = int rho X X^T dV about the centre of a primitive geom of kind ``kind``, size ``s`` and mass ``m``,
    geom frame (diagonal for these shapes)."""
    if kind == "sphere":
        return np.eye(3) * m * s[0] ** 2 / 5.0
    if kind == "ellipsoid":
        return np.diag(m * s**2 / 5.0)
    if kind == "box":
        return np.diag(m * s**2 / 3.0)
    r, h = float(s[0]), float(s[1])  # radius, half-length
    if kind == "cylinder":
        return np.diag([m * r * r / 4.0, m * r * r / 4.0, m * h * h / 3.0])
    # capsule: a cylinder of length 2h plus two hemispheres of mass m_sph / 2 each (mass split by volume). About
    # its flat face a hemisphere has int z dm = (3 r / 8) m_sph / 2 and int z^2 dm = (r^2 / 5) m_sph / 2, so about
    # the centre: S_zz = m_cyl h^2 / 3 + m_sph (r^2 / 5 + 3 h r / 4 + h^2), S_xx = S_yy = m_cyl r^2/4 + m_sph r^2/5.
    v_cyl, v_sph = math.pi * r * r * 2.0 * h, 4.0 / 3.0 * math.pi * r**3
    m_cyl, m_sph = m * v_cyl / (v_cyl + v_sph), m * v_sph / (v_cyl + v_sph)
    sxx = m_cyl * r * r / 4.0 + m_sph * r * r / 5.0
    szz = m_cyl * h * h / 3.0 + m_sph * (r * r / 5.0 + 0.75 * h * r + h * h)
    return np.diag([sxx, sxx, szz])


def _primitive_mesh(
    kind: str,
    size: np.ndarray,
    sphere_subdivisions: int,
    capsule_count: tuple[int, int],
    cylinder_sections: int,
) -> trimesh.Trimesh:
    """Closed, outward-wound triangulation centred at the origin, axis z for capsules and cylinders."""
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=sphere_subdivisions, radius=float(size[0]))
    if kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=sphere_subdivisions, radius=1.0)
        mesh.apply_scale(size)
        return mesh
    if kind == "capsule":
        return trimesh.creation.capsule(
            height=2.0 * float(size[1]), radius=float(size[0]), count=list(capsule_count)
        )
    if kind == "cylinder":
        return trimesh.creation.cylinder(
            radius=float(size[0]), height=2.0 * float(size[1]), sections=cylinder_sections
        )
    return trimesh.creation.box(extents=2.0 * size)


def _combine(parts: list[tuple[float, np.ndarray, np.ndarray]]) -> tuple[float, np.ndarray, np.ndarray]:
    """Total mass, COM and second moment about the COM (parallel-axis theorem) of (mass, com, S) parts."""
    mass = float(sum(p[0] for p in parts))
    if mass <= 0.0:
        return mass, np.zeros(3), np.zeros((3, 3))
    com = sum(p[0] * p[1] for p in parts) / mass
    S = sum(p[2] + p[0] * np.outer(p[1] - com, p[1] - com) for p in parts)
    return mass, com, 0.5 * (S + S.T)


def _inertia_to_S(inertia: np.ndarray) -> np.ndarray:
    """S = tr(I)/2 Id - I, the inverse of I = tr(S) Id - S."""
    return 0.5 * np.trace(inertia) * np.eye(3) - inertia


def _actuator_spec(m: mujoco.MjModel, a: int, joint_index: dict[int, int]) -> ActuatorSpec:
    name = m.actuator(a).name
    label = f"actuator '{name}'" if name else f"actuator #{a} (unnamed)"
    if int(m.actuator_plugin[a]) >= 0:
        raise ValueError(f"{label}: actuator plugins (such as mujoco.pid) are not supported")
    group = int(m.actuator_group[a])
    if 0 <= group < 31 and (int(m.opt.disableactuator) >> group) & 1:
        raise ValueError(
            f"{label}: its group {group} is disabled by <option actuatorgroupdisable> (MuJoCo applies no force from "
            "it), which the step does not model: remove the actuator or the option"
        )
    if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
        raise ValueError(f"{label}: only joint transmissions are supported")
    j = int(m.actuator_trnid[a, 0])
    if j not in joint_index:
        raise ValueError(f"{label}: joint '{m.joint(j).name}' is not a hinge or slide joint of the model")
    gain, bias = m.actuator_gainprm[a], m.actuator_biasprm[a]
    fixed = (
        m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
        and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
    )
    if fixed and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE and gain[0] == 1.0:
        kind, kp, kv = "motor", 0.0, 0.0
    elif (
        fixed
        and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE
        and bias[0] == 0
        and bias[1] == -gain[0]
    ):
        kind, kp, kv = "position", float(gain[0]), float(-bias[2])
    else:
        raise ValueError(
            f"{label}: only motor and position actuators (without activation dynamics) are supported"
        )
    if not (0 <= kp < math.inf and 0 <= kv < math.inf):  # a negative gain adds energy: no minimum
        raise ValueError(f"{label}: kp and kv must be finite and >= 0, got kp={kp:g}, kv={kv:g}")
    if not math.isfinite(float(m.actuator_gear[a, 0])):
        raise ValueError(f"{label}: gear must be finite, got {float(m.actuator_gear[a, 0]):g}")
    return ActuatorSpec(
        name=name,
        joint=joint_index[j],
        kind=kind,
        gear=float(m.actuator_gear[a, 0]),
        ctrlrange=tuple(float(c) for c in m.actuator_ctrlrange[a]) if m.actuator_ctrllimited[a] else None,
        kp=kp,
        kv=kv,
        forcerange=tuple(float(c) for c in m.actuator_forcerange[a]) if m.actuator_forcelimited[a] else None,
    )


def _asset_files(spec: mujoco.MjSpec, base: str | None) -> dict[str, bytes] | None:
    """The model's asset files (meshes, height fields, textures) by the names the MJCF gives them, read relative to
    the model file's folder ``base`` as MuJoCo reads them (None without a folder or files)."""
    if base is None:
        return None
    out = {}
    for items, folder in (
        (spec.meshes, spec.meshdir),
        (spec.hfields, spec.meshdir),
        (spec.textures, spec.texturedir),
    ):
        for item in items:
            if item.file:
                path = os.path.join(base, folder or "", item.file)
                if os.path.isfile(path):
                    with open(path, "rb") as f:
                        out[item.file] = f.read()
    return out or None


def _build_chain(xml: str, root: str, assets: dict[str, bytes] | None = None) -> object:
    """float64 pytorch-kinematics chain of the root's subtree, built by `pk.build_chain_from_mjcf`.

    ``assets``: the asset files by name (the MJCF read from text finds them in the working directory otherwise).
    The root's free joint is removed first: pytorch-kinematics maps hinge and slide joints only (no free joints),
    so the floating base is kept outside the chain. pk builds every offset and axis as a float32 Transform3d /
    tensor (its default dtype), which rounds them to ~1e-8; they are reset here from the same compiled model in
    float64 and the Chain is rebuilt over the same frame tree, so that it reproduces MuJoCo to rounding.
    """
    import pytorch_kinematics as pk
    from pytorch_kinematics.transforms import Transform3d

    tree = ET.fromstring(xml)
    for keyframes in tree.findall(
        "keyframe"
    ):  # their qpos is the model's with the free joint: now the wrong size
        tree.remove(keyframes)
    for body in tree.iter("body"):
        if body.get("name") == root:
            for child in list(body):
                if child.tag == "freejoint" or (child.tag == "joint" and child.get("type") == "free"):
                    body.remove(child)
    stripped = ET.tostring(tree, encoding="unicode")
    chain = pk.build_chain_from_mjcf(stripped, body=root, assets=assets)
    m = mujoco.MjModel.from_xml_string(stripped, assets=assets)
    f64 = torch.float64
    for name in chain.get_frame_names(exclude_fixed=False):
        frame = chain.find_frame(name)
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if b >= 0:
            if name == root:  # in the world frame: its joint-less ancestors' transforms composed
                _, pos, quat = _root_pose(m, b)
            else:
                pos, quat = m.body_pos[b], m.body_quat[b]
            frame.link.offset = Transform3d(rot=quat, pos=pos, dtype=f64)
            if frame.joint.joint_type != "fixed":
                j = int(m.body_jntadr[b])
                frame.joint.offset = Transform3d(pos=m.jnt_pos[j], dtype=f64)
                frame.joint.axis = torch.tensor(m.jnt_axis[j], dtype=f64)
        elif (site := mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)) >= 0:
            frame.link.offset = Transform3d(rot=m.site_quat[site], pos=m.site_pos[site], dtype=f64)
        frame.joint.axis = frame.joint.axis.to(f64)
        # pk copies the range of unlimited joints too, (0, 0): theirs are none
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, frame.joint.name or "")
        if frame.joint.joint_type != "fixed" and j >= 0:
            frame.joint.limits = tuple(float(x) for x in m.jnt_range[j]) if m.jnt_limited[j] else None
    return pk.Chain(chain.find_frame(root), dtype=f64)


def _transform(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat)
    T[:3, 3] = pos
    return T


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z), MuJoCo's convention."""
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, dtype=np.float64))
    return out.reshape(3, 3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).reshape(9))
    return q if q[0] >= 0 else -q
