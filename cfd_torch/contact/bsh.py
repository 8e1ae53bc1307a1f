"""Bounding Sphere Hierarchy (BSH) of a rigid body, built once in the body frame (SPEC section 4).

Binary tree, one leaf per triangle. Leaf: centre = triangle centroid, radius = max vertex distance to it. Internal
node: centre = mean of the distinct vertices below it (so it lies inside their convex hull, which keeps the blend
repulsive), radius = max distance from that centre to them (the sphere contains the node's hull). Built top-down by
median splits of the triangle centroids along the axis of largest extent: balanced (depth ceil(log2 F)), so a
traversal visits O(F) node pairs for quasi-uniform meshes.

Large triangles: with d1 = R_I + R_J a leaf whose sphere is much larger than the partner's triangles makes every
partner leaf inside it a near pair. ``max_edge`` refines the mesh when the BSH is built (trimesh's
``subdivide_to_size``: midpoint splits, same surface) so coarse obstacles (floors, boxes, pushers) come in triangles
comparable to those of the bodies they touch.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .._validate import check_dense, check_mesh, check_not_meta, is_real

__all__ = ["BSH"]


def _numpy(x):
    """A tensor as a NumPy array (bfloat16, which NumPy lacks, widened exactly to float64); anything else as it is."""
    if not isinstance(x, torch.Tensor):
        return x
    x = x.detach().cpu()
    return (x.double() if x.dtype == torch.bfloat16 else x).numpy()


@dataclass(frozen=True, eq=False)
class BSH:
    """A body's sphere hierarchy. All tensors are float64 / int64 on the CPU, in the body frame.

    Attributes:
        vertices: (V, 3) body-frame vertices [m] (after refinement).
        faces: (F, 3) vertex indices.
        centre: (M, 3) node centres, M = 2F - 1; node 0 is the root.
        radius: (M,) node radii.
        child: (M, 2) children of internal nodes, -1 for leaves.
        tri: (M,) triangle index of leaves, -1 for internal nodes.
        depth: (M,) depth of each node (root 0).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    centre: torch.Tensor
    radius: torch.Tensor
    child: torch.Tensor
    tri: torch.Tensor
    depth: torch.Tensor

    def __post_init__(self) -> None:
        _check_fields(self)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_nodes(self) -> int:
        return int(self.centre.shape[0])

    @property
    def triangles(self) -> torch.Tensor:
        """(F, 3, 3) body-frame triangle vertices."""
        return self.vertices[self.faces]

    @classmethod
    def from_trimesh(cls, mesh, *, max_edge: float | None = None) -> BSH:
        """Build from a ``trimesh.Trimesh`` (its vertices and faces)."""
        if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
            raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
        return cls.build(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_edge=max_edge)

    @classmethod
    def build(cls, vertices, faces, *, max_edge: float | None = None) -> BSH:
        """Build the hierarchy of a triangle mesh.

        Args:
            vertices: (V, 3) body-frame vertices (array-like or tensor).
            faces: (F, 3) integer vertex indices.
            max_edge: if given, triangles with an edge longer than this are split (midpoints) until none is.

        Raises:
            ValueError: bad shapes, NaN/inf vertices, out-of-range indices or degenerate faces (naming the face),
                non-integer face indices, or a ``max_edge`` that is not a finite positive number or would split the
                mesh into more than 2,000,000 triangles.
            TypeError: vertices that are not real numbers.
        """
        if isinstance(vertices, torch.Tensor) and vertices.requires_grad:
            warnings.warn(
                "BSH.build: vertices require grad, but the hierarchy holds their values: no gradient flows back to "
                "a mesh's vertices (only to body poses)",
                stacklevel=2,
            )
        for x, name in ((vertices, "vertices"), (faces, "faces")):
            if isinstance(x, torch.Tensor):
                check_not_meta(x, name)
                check_dense(x, name)
        # copies: the hierarchy must not change when the caller later writes into its arrays
        try:
            V = np.array(_numpy(vertices))
        except ValueError as err:  # ragged rows
            raise ValueError(f"vertices must be a (V, 3) array of real numbers: {err}") from None
        if V.dtype.kind not in "iuf":
            raise TypeError(f"vertices must be an array of real numbers, got dtype {V.dtype}")
        V = V.astype(np.float64)
        Fc = np.array(_numpy(faces))
        if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < 3:
            raise ValueError(f"vertices must have shape (V, 3) with V >= 3, got {V.shape}")
        if Fc.ndim != 2 or Fc.shape[1] != 3 or Fc.shape[0] < 1:
            raise ValueError(f"faces must have shape (F, 3) with F >= 1, got {Fc.shape}")
        if not np.issubdtype(Fc.dtype, np.integer):
            given = faces.dtype if isinstance(faces, torch.Tensor) else Fc.dtype
            raise ValueError(f"faces must hold integer vertex indices, got dtype {given}")
        Fc = Fc.astype(np.int64)
        check_mesh(V, Fc, "vertices", "faces")
        if max_edge is not None:
            if not (is_real(max_edge) and 0 < max_edge < float("inf")):
                raise ValueError(f"max_edge must be a finite number > 0 (or None), got {max_edge!r}")
            count = refined_faces(edge_lengths(V[Fc]).max(1), float(max_edge))
            if count > MAX_FACES:
                raise ValueError(
                    f"max_edge={max_edge!r} would split the mesh's {len(Fc)} triangles into about {count:.3g} (more "
                    f"than {MAX_FACES:,}, memory and time to match): choose a longer max_edge"
                )
            import trimesh.remesh

            V, Fc = trimesh.remesh.subdivide_to_size(V, Fc, max_edge=max_edge, max_iter=64)
            Fc = np.asarray(Fc, dtype=np.int64)
        return cls(**_build_tree(np.asarray(V, dtype=np.float64), Fc))


# the most triangles ``max_edge`` may split a mesh into (393k took 16 s to build; 2e8 ran a 23 GB machine out of
# memory)
MAX_FACES = 2_000_000


def edge_lengths(tri: np.ndarray) -> np.ndarray:
    """(F, 3) edge lengths of triangles ``tri`` (F, 3, 3)."""
    return np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1)


def refined_faces(longest: np.ndarray, edge: float) -> int:
    """Faces after midpoint splits of faces whose longest edges are ``longest`` (F,) until no edge exceeds ``edge``
    (each split level quarters a face)."""
    levels = np.ceil(np.log2(np.maximum(longest / edge, 1.0)))
    return int((4.0**levels).sum())


_DTYPES = {
    "vertices": torch.float64, "faces": torch.int64, "centre": torch.float64, "radius": torch.float64,
    "child": torch.int64, "tri": torch.int64, "depth": torch.int64,
}  # fmt: skip


def _check_fields(b: BSH) -> None:
    """Refuse a hierarchy whose fields do not form one (e.g. restored from saved arrays that do not belong together):
    types, shapes and dtypes, a mesh as ``build`` accepts it, a binary tree over all M = 2F - 1 nodes with one leaf
    per triangle, depths that count from the root, and spheres that contain the vertices below them."""
    for name, dtype in _DTYPES.items():
        x = getattr(b, name)
        if not isinstance(x, torch.Tensor):
            raise TypeError(
                f"BSH.{name} must be a torch.Tensor, got {type(x).__name__} (BSH.build makes a hierarchy from a mesh; "
                f"to restore saved fields, pass torch.as_tensor(x, dtype={dtype}))"
            )
        if x.dtype != dtype or x.device.type != "cpu":
            raise ValueError(f"BSH.{name} must be a {dtype} tensor on the CPU, got {x.dtype} on {x.device}")
    V, Fc = b.vertices.numpy(), b.faces.numpy()
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < 3:
        raise ValueError(f"BSH.vertices must have shape (V, 3) with V >= 3, got {tuple(V.shape)}")
    if Fc.ndim != 2 or Fc.shape[1] != 3 or Fc.shape[0] < 1:
        raise ValueError(f"BSH.faces must have shape (F, 3) with F >= 1, got {tuple(Fc.shape)}")
    F = Fc.shape[0]
    M = 2 * F - 1
    for name, shape in (
        ("centre", (M, 3)),
        ("radius", (M,)),
        ("child", (M, 2)),
        ("tri", (M,)),
        ("depth", (M,)),
    ):
        if tuple(getattr(b, name).shape) != shape:
            raise ValueError(
                f"BSH.{name} must have shape {shape} (M = 2F - 1 nodes for the F = {F} faces of BSH.faces), got "
                f"{tuple(getattr(b, name).shape)}"
            )
    check_mesh(V, Fc, "BSH.vertices", "BSH.faces")
    centre, radius = b.centre.numpy(), b.radius.numpy()
    child, tri, depth = b.child.numpy(), b.tri.numpy(), b.depth.numpy()
    if not np.isfinite(centre).all():
        raise ValueError("BSH.centre contains NaN or inf")
    if not (np.isfinite(radius).all() and (radius >= 0).all()):
        raise ValueError("BSH.radius must be finite and >= 0")
    inner = child[:, 0] >= 0
    node = np.arange(M)
    kids = child[inner]
    if (
        ((child[:, 1] >= 0) != inner).any()
        or (kids <= node[inner, None]).any()
        or (kids >= M).any()
        or (np.bincount(kids.ravel(), minlength=M) != (node > 0)).any()
    ):
        raise ValueError(
            "BSH.child must make a binary tree of the M nodes rooted at node 0: each internal node's two children "
            "after it, each other node the child of exactly one, leaves (-1, -1)"
        )
    leaves = tri[~inner]
    if (
        (tri[inner] != -1).any()
        or leaves.shape[0] != F
        or (np.bincount(leaves.clip(0, F), minlength=F + 1)[:F] != 1).any()
    ):
        raise ValueError(
            "BSH.tri must give each leaf a distinct triangle (each of the F faces once), -1 elsewhere"
        )
    if depth[0] != 0 or (depth[kids] != depth[node[inner], None] + 1).any():
        raise ValueError("BSH.depth must count from 0 at the root, one more at each child")
    # every sphere holds the vertices below it: each leaf's triangle is walked up through its ancestors
    parent = np.full(M, -1)
    parent[kids.ravel()] = np.repeat(node[inner], 2)
    pts = V[Fc[leaves]]  # (F, 3, 3)
    at = node[~inner]
    reach = np.zeros(M)
    while at.size:
        np.maximum.at(reach, at, np.sqrt(((pts - centre[at, None]) ** 2).sum(-1)).max(1))
        keep = parent[at] >= 0
        at, pts = parent[at][keep], pts[keep]
    scale = np.abs(V).max() + radius.max()
    bad = reach > radius + 1e-9 * scale
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"BSH.radius does not contain the vertices below node {i} ({int(bad.sum())} nodes in all): radius "
            f"{radius[i]:.6g}, farthest vertex {reach[i]:.6g} from its centre"
        )


def _build_tree(V: np.ndarray, Fc: np.ndarray) -> dict:
    F = Fc.shape[0]
    tris = V[Fc]  # (F, 3, 3)
    # each vertex index mapped to the first index of its position: a node's distinct vertices are distinct points
    # (a triangle soup, as read from STL, repeats each point in every face that has it)
    _, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    Fp = first[inverse.reshape(-1)][Fc]
    centroids = tris.mean(1)
    M = 2 * F - 1
    centre = np.zeros((M, 3))
    radius = np.zeros(M)
    child = -np.ones((M, 2), dtype=np.int64)
    tri = -np.ones(M, dtype=np.int64)
    depth = np.zeros(M, dtype=np.int64)
    # explicit stack: (node id, face indices, depth); ids are handed out in creation order
    next_id = 1
    stack = [(0, np.arange(F), 0)]
    while stack:
        node, idx, dep = stack.pop()
        depth[node] = dep
        if idx.shape[0] == 1:
            f = int(idx[0])
            c = centroids[f]
            centre[node] = c
            radius[node] = np.sqrt(((tris[f] - c) ** 2).sum(1)).max()
            tri[node] = f
            continue
        verts = V[np.unique(Fp[idx].ravel())]
        c = verts.mean(0)
        centre[node] = c
        radius[node] = np.sqrt(((verts - c) ** 2).sum(1)).max()
        pts = centroids[idx]
        axis = int(np.argmax(pts.max(0) - pts.min(0)))
        order = np.argsort(pts[:, axis], kind="stable")
        half = idx.shape[0] // 2
        left, right = idx[order[:half]], idx[order[half:]]
        child[node] = (next_id, next_id + 1)
        stack.append((next_id, left, dep + 1))
        stack.append((next_id + 1, right, dep + 1))
        next_id += 2
    return {
        "vertices": torch.from_numpy(V),
        "faces": torch.from_numpy(Fc),
        "centre": torch.from_numpy(centre),
        "radius": torch.from_numpy(radius),
        "child": torch.from_numpy(child),
        "tri": torch.from_numpy(tri),
        "depth": torch.from_numpy(depth),
    }


def unique_hierarchies(bshes) -> tuple[tuple[BSH, ...], torch.Tensor]:
    """The distinct hierarchies of ``bshes`` (by identity, first-seen order) and (len(bshes),) the index of each
    body's among them: bodies sharing a mesh share one hierarchy in a forest."""
    uniq: dict[int, int] = {}
    for b in bshes:
        uniq.setdefault(id(b), len(uniq))
    return tuple({id(b): b for b in bshes}.values()), torch.tensor(
        [uniq[id(b)] for b in bshes], dtype=torch.long
    )
