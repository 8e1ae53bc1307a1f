"""Rigid bodies of the simulator: a contact hierarchy plus exact volumetric mass properties (SPEC section 5).

A dynamic body's frame is its centre of mass: its mesh is shifted by ``-com`` when the body is built, so the pose
(translation, rotation vector) of a dynamic body is the pose of its centre of mass and principal-free second
moment. Static and kinematic bodies keep the mesh's own frame (their poses are given, not solved for).

Inertia of the incremental potential, exact for the body's volume (not lumped at vertices)::

    1/2 int rho |x(q) - x_pred|^2 dV = 1/2 (m |b|^2 + tr(A S A^T)),   x_pred = R_t R_{t-1}^T R_t X + 2 t_t - t_{t-1}
    b = t - 2 t_t + t_{t-1},  A = R - R_t R_{t-1}^T R_t,  S = int rho X X^T dV (body frame, about the COM),

the first moment vanishing because the frame is centred at the COM.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .._geometry import _closest_point_triangle
from .._validate import check_mesh, closed_surface, is_real, miscounted_component, self_intersection
from ..contact.bsh import BSH, edge_lengths, refined_faces
from ._checks import physical_second_moment

__all__ = ["RigidBody", "rigid_body", "refine_obstacles", "KINDS"]

KINDS = ("dynamic", "static", "kinematic")


@dataclass(frozen=True, eq=False)
class RigidBody:
    """One body of a scene.

    Attributes:
        bsh: contact hierarchy in the body frame (the COM frame for dynamic bodies).
        kind: "dynamic" (simulated), "static" (fixed) or "kinematic" (pose prescribed each step by the action).
        mass: total mass [kg] (0 for static and kinematic bodies).
        second_moment: (3, 3) S = int rho X X^T dV about the COM in the body frame [kg m^2]; the inertia tensor
            is tr(S) I - S.
        com: (3,) where the centre of mass was in the original mesh's frame [m] (zeros unless dynamic).
    """

    bsh: BSH
    kind: str
    mass: float
    second_moment: torch.Tensor
    com: torch.Tensor

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"RigidBody.kind must be one of {KINDS}, got {self.kind!r}")
        if not isinstance(self.bsh, BSH):
            raise TypeError(f"RigidBody.bsh must be a cfd_torch.BSH, got {type(self.bsh).__name__}")
        if not (is_real(self.mass) and 0 <= self.mass < float("inf")) or (self.kind == "dynamic") != (
            self.mass > 0
        ):
            raise ValueError(
                f"RigidBody.mass must be finite, > 0 for a dynamic body and 0 otherwise, got {self.mass!r} "
                f"({self.kind})"
            )
        for name, x, shape in (("second_moment", self.second_moment, (3, 3)), ("com", self.com, (3,))):
            if not (isinstance(x, torch.Tensor) and x.is_floating_point()):
                raise TypeError(
                    f"RigidBody.{name} must be a float tensor of shape {shape}, got {type(x).__name__}"
                )
            if tuple(x.shape) != shape or not bool(torch.isfinite(x).all()):
                raise ValueError(
                    f"RigidBody.{name} must be a finite tensor of shape {shape}, got {tuple(x.shape)}"
                )
        if self.kind == "dynamic":
            eps = torch.finfo(self.second_moment.dtype).eps  # symmetric to the rounding of its dtype
            S = self.second_moment.detach().double()
            if float((S - S.T).abs().max()) > 64 * eps * float(S.abs().max()) or not physical_second_moment(
                S
            ):
                raise ValueError(
                    "RigidBody.second_moment must be symmetric positive semi-definite with a positive definite "
                    "inertia tr(S) I - S (a dynamic body)"
                )

    @property
    def inertia(self) -> torch.Tensor:
        """(3, 3) inertia tensor about the COM, body frame [kg m^2]."""
        S = self.second_moment
        return torch.trace(S) * torch.eye(3, dtype=S.dtype) - S


def rigid_body(
    mesh,
    *,
    kind: str = "dynamic",
    density: float = 1000.0,
    max_edge: float | None = None,
) -> RigidBody:
    """Build a body from a ``trimesh.Trimesh``.

    A dynamic body's frame is at its centre of mass (the mesh shifted by -``com``; ``RigidBody.com`` says where
    the centre of mass was in the mesh's frame), so its pose in a state places its centre of mass; a static or
    kinematic body keeps the mesh's own frame.

    Args:
        mesh: closed triangle mesh (watertight, consistently wound; a shell facing inward is a cavity inside an
            outward one) for dynamic bodies; any mesh otherwise. Vertices no face uses are left out, and a
            smallest second moment below zero within the rounding of the mass properties (a thin plate turned
            off the axes) is taken as zero.
        kind: "dynamic", "static" or "kinematic".
        density: [kg/m^3], read for dynamic bodies only (mass = density * volume), checked for every kind.
        max_edge: refine triangles longer than this when building the contact hierarchy (see :class:`BSH`).

    Raises:
        TypeError: ``mesh`` is not a ``trimesh.Trimesh``, or ``density`` is a tensor (mass gradients: ``Params``).
        ValueError: unknown kind, non-positive density, a mesh with NaN/inf vertices or degenerate (zero-area)
            faces, a ``max_edge`` that would split it into more than 2,000,000 triangles, or a dynamic mesh that
            is not a watertight closed volume, that intersects itself, whose shells would miscount its solid
            (one facing outward inside another, one facing inward inside none), or so thin (a needle of aspect
            1e5) that a moment of inertia is lost in the rounding of its mass properties.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    Fc = np.asarray(mesh.faces, dtype=np.int64)
    if Fc.shape[0] == 0:
        raise ValueError("mesh has no faces")
    check_mesh(V, Fc, "mesh.vertices", "mesh.faces")
    used = np.zeros(len(V), dtype=bool)
    used[Fc.ravel()] = True
    if not used.all():  # vertices no face uses would count in the body's extent and bounding box
        mesh = trimesh.Trimesh(V, Fc, process=False)
        mesh.remove_unreferenced_vertices()
        V, Fc = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    if isinstance(density, torch.Tensor):
        raise TypeError(
            "density must be a Python number, got a tensor: a body's mass properties are fixed when it is built; "
            "for gradients with respect to mass pass Params (scene.params(), its mass and second_moment) to step"
        )
    if not (is_real(density) and 0 < density < float("inf")):
        raise ValueError(f"density must be a finite positive number, got {density!r}")
    if kind != "dynamic":
        bsh = BSH.from_trimesh(mesh, max_edge=max_edge)
        z = torch.zeros(3, 3, dtype=torch.float64)
        return RigidBody(bsh, kind, 0.0, z, torch.zeros(3, dtype=torch.float64))
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        hint = ""
        if closed_surface(V, Fc):  # closed once coincident vertices are welded: a triangle soup
            hint = "; it is closed once its coincident vertices are merged: call mesh.merge_vertices() first"
        raise ValueError(
            f"mesh of a dynamic body must be watertight with consistent winding (a closed volume){hint}"
        )
    volume = float(mesh.volume)
    if not volume > 0:
        raise ValueError(
            f"mesh of a dynamic body must enclose a positive volume (outward normals), got {volume}"
            + ("; its faces are wound inward: mesh.invert() turns them out" if volume < 0 else "")
        )
    hit = self_intersection(V, Fc)
    if hit is not None:
        raise ValueError(
            f"mesh of a dynamic body intersects itself: faces {hit[0]} and {hit[1]} (which share no vertex) "
            "intersect or touch; its shells must be disjoint closed surfaces (parts that touch merged into one), "
            "or its volume, mass properties and contact could be wrong"
        )
    if mesh.body_count > 1:
        import trimesh

        labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(Fc))
        found = miscounted_component(V, Fc, labels)
        if found is not None:
            k, inward = found
            where = f"(component {k}, faces {str(np.flatnonzero(labels == k)[:3].tolist())[1:-1]}, ...)"
            raise ValueError(
                f"mesh of a dynamic body has a closed shell facing inward outside every outward one {where}: its "
                "solid would count as negative mass; a shell facing inward is a cavity and must lie inside the "
                "solid it hollows (mesh.invert() the shell if it is a part)"
                if inward
                else f"mesh of a dynamic body has a closed shell inside another, both facing outward {where}: its "
                "volume would be counted twice; a cavity's shell must face inward"
            )
    # the mass properties of the mesh moved to its bounding box's centre: the volume integrals' sums cancel no
    # digits against a far origin
    centre = 0.5 * (V.min(0) + V.max(0))
    m = mesh.copy()
    m.apply_translation(-centre)
    m.density = float(density)
    com_local = np.asarray(m.center_mass, dtype=np.float64)
    inertia = np.asarray(m.moment_inertia, dtype=np.float64)  # about the COM, mesh axes
    S = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    # a thin body's smallest moment can come out of the volume integrals below zero by their rounding (a 1 m x 1 m x
    # 1 um plate turned off the axes: -4e-16 kg m^2, the true one 8e-17): clipped to zero within 1e-9 of the largest
    lam, vec = np.linalg.eigh(0.5 * (S + S.T))
    if -1e-9 * np.abs(S).max() <= lam[0] < 0:
        S = (vec * np.maximum(lam, 0.0)) @ vec.T
    if not physical_second_moment(torch.from_numpy(S)):
        inertia_min = float(np.linalg.eigvalsh(np.trace(S) * np.eye(3) - S)[0])
        raise ValueError(
            f"mesh of a dynamic body is too thin for its mass properties: its smallest moment of inertia "
            f"({inertia_min:.3g} kg m^2) is lost in the rounding of the volume integrals (the largest second "
            f"moment is {np.abs(S).max():.3g} kg m^2); thicken it, or make it a static or kinematic body"
        )
    bsh = BSH.build(
        np.asarray(m.vertices, dtype=np.float64) - com_local, np.asarray(m.faces), max_edge=max_edge
    )
    com = centre + com_local
    return RigidBody(
        bsh, kind, float(m.mass), torch.from_numpy(0.5 * (S + S.T)).clone(), torch.from_numpy(com).clone()
    )


# the most triangles automatic refinement gives one obstacle (a larger edge is chosen beyond it, with a warning)
MAX_REFINED_FACES = 200_000


# the 13 directions of a cubic lattice's nearest neighbours (axes, face and body diagonals), unit length
_LATTICE = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1], [0, 1, 1], [0, 1, -1],
     [1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], dtype=np.float64,
)  # fmt: skip
_LATTICE /= np.linalg.norm(_LATTICE, axis=1, keepdims=True)


def thickness(vertices: np.ndarray, faces: np.ndarray) -> float:
    """A body's thickness [m]: the least extent of its vertices (V, 3) along the normals of its (up to 256)
    largest faces (F, 3), its three principal axes and 13 fixed directions. Exact where the thinnest direction is
    one of those (a box's or a plate's face normal, in any frame); otherwise an upper bound of the least width,
    near it for compact bodies (a 320-face icosphere of radius r: 1.96 r)."""
    V = np.asarray(vertices, dtype=np.float64)
    c = V - V.mean(0)
    _, axes = np.linalg.eigh(c.T @ c)
    tri = V[np.asarray(faces)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(n, axis=1)
    big = np.argsort(-area)[:256]
    normals = n[big][area[big] > 0] / area[big][area[big] > 0, None]
    dirs = np.concatenate([normals, axes.T, _LATTICE])
    proj = c @ dirs.T  # (V, D)
    return float((proj.max(0) - proj.min(0)).min())


def inner_radius(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The radius [m] of the largest ball about the frame origin inside a closed, consistently wound surface
    (vertices (V, 3), faces (F, 3)): the origin's distance to the nearest point of the surface where the origin
    lies in the solid (winding number above 1/2), else 0 (an open surface, or an origin outside: a ring's or a
    bowl's centre of mass). A moving body's frame sits at its centre of mass."""
    tri = torch.from_numpy(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)])  # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    la, lb, lc = a.norm(dim=1), b.norm(dim=1), c.norm(dim=1)
    # the solid angle of each triangle seen from the origin (van Oosterom and Strackee)
    num = (a * torch.cross(b, c, dim=1)).sum(1)
    den = la * lb * lc + (a * b).sum(1) * lc + (a * c).sum(1) * lb + (b * c).sum(1) * la
    winding = float(torch.atan2(num, den).sum()) / (2.0 * math.pi)
    if not winding > 0.5:
        return 0.0
    zero = torch.zeros(len(tri), dtype=torch.float64)
    near = _closest_point_triangle((zero, zero, zero), *(tuple(x[:, k] for k in range(3)) for x in (a, b, c)))
    return float(torch.sqrt(near[0] ** 2 + near[1] ** 2 + near[2] ** 2).min())


def refine_obstacles(
    bodies: Sequence[RigidBody], pairs: torch.Tensor, factor: float
) -> tuple[RigidBody, ...]:
    """The bodies with each static or kinematic one refined to the scale of the dynamic bodies it touches.

    An obstacle whose longest edge exceeds twice ``factor`` times the longest edge of its finest dynamic partner
    (the other bodies of its rows in ``pairs`` (P, 2); the finest has the smallest longest edge) gets a hierarchy of
    the same surface split at midpoints until no edge exceeds ``factor`` times that edge
    (``BSH.build(max_edge=...)``); if that would give more than ``MAX_REFINED_FACES`` triangles, the length grows
    by factors of sqrt(2) until it does not (with a warning). The potential of an obstacle therefore depends on the
    finest body it interacts with in the scene, a scale set once when the scene is built. Bodies shared by several
    slots stay shared; dynamic bodies are never changed.
    """
    bodies = tuple(bodies)
    longest_edge = {
        id(b): float(edge_lengths(b.bsh.triangles.numpy()).max()) for b in bodies if b.kind == "dynamic"
    }
    out = list(bodies)
    done: dict[tuple[int, float], RigidBody] = {}
    for k, b in enumerate(bodies):
        if b.kind == "dynamic":
            continue
        rows = pairs[(pairs == k).any(1)]
        partners = torch.unique(rows[rows != k]).tolist()
        scales = [longest_edge[id(bodies[j])] for j in partners if bodies[j].kind == "dynamic"]
        if not scales:
            continue
        edge = factor * min(scales)
        longest = edge_lengths(b.bsh.triangles.numpy()).max(1)
        if not longest.max() > 2.0 * edge:  # not much coarser: one split would give no real saving
            continue
        if refined_faces(longest, edge) > MAX_REFINED_FACES:
            wanted = edge
            while refined_faces(longest, edge) > MAX_REFINED_FACES:
                edge *= math.sqrt(2.0)
            warnings.warn(
                f"body {k}: refining this obstacle to edges of {wanted:.3g} m (refine_obstacles={factor} x its "
                f"finest partner's longest edge) would give more than {MAX_REFINED_FACES} triangles; refined to "
                f"{edge:.3g} m instead",
                stacklevel=3,
            )
        key = (id(b), edge)
        if key not in done:
            bsh = BSH.build(b.bsh.vertices, b.bsh.faces, max_edge=edge)
            done[key] = RigidBody(bsh, b.kind, b.mass, b.second_moment, b.com)
        out[k] = done[key]
    return tuple(out)
