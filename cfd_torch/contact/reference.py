"""Naive recursive BSH potential between two rigid bodies: the slow, clear oracle of the batched implementation.

The recursion of SPEC section 4 is written literally, one Python call per node pair, with differentiable torch
operations only, so ``torch.autograd`` gives the exact gradient and Hessian with respect to both poses (the blend
weights of every ancestor included). Leaf pairs use :func:`cfd_torch.pair_potential`, which is differentiable to
second order through its implicit derivatives; a third derivative therefore raises wherever a leaf pair is
evaluated. Branch decisions (far / blend band / fine) are taken on values and carry no gradient: they only change
where the potential is C2 (the quintic blend has zero first and second derivatives at both band edges).

For two nodes I, J (world centres c, radii R)::

    P(I, J): r = |c_I - c_J|, d1 = R_I + R_J, s = (r - d1) / max(eps d1, 2 margin)
             s >= 1:  P_c(r)                                   (far: no descent)
             else:    phi P_c(r) + (1 - phi) F,  phi = Phi(s) if s > 0 else 0
             F = pair_potential(tri_I, tri_J)                  both leaves
                 sum of P over child pairs                     otherwise

Splitting rules: ``"both"`` splits both internal nodes (4 child pairs), or the internal one when the other is a
leaf (2 pairs); ``"larger"`` splits the node with the larger radius (ties: I), or the other one if that is a leaf.

Not for production use: the cost is one Python call and a handful of autograd nodes per visited node pair.
"""

from __future__ import annotations

import torch

from .._validate import check_dense, check_positive, check_stiffness
from ..config import DEFAULT_CONTACT
from ..rotation import rotation_matrix
from .bsh import BSH
from .central import band_width, central_potential, smoothstep
from .pair import pair_potential

__all__ = ["mesh_potential_reference", "mesh_traversal_counts_reference"]

_SPLITS = ("both", "larger")


def _check_args(bsh_a, pose_a, bsh_b, pose_b, mu, margin, eps, split) -> None:
    for name, bsh in (("bsh_a", bsh_a), ("bsh_b", bsh_b)):
        if not isinstance(bsh, BSH):
            raise ValueError(f"{name} must be a cfd_torch.BSH, got {type(bsh).__name__}")
    for name, pose in (("pose_a", pose_a), ("pose_b", pose_b)):
        if not isinstance(pose, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(pose).__name__}")
        check_dense(pose, name)
        if pose.shape != (6,):
            raise ValueError(
                f"{name} must have shape (6,) (translation, rotation vector), got {tuple(pose.shape)}"
            )
        if pose.dtype != torch.float64:
            raise ValueError(f"{name} must be float64, got {pose.dtype}")
        if not bool(torch.isfinite(pose).all()):
            raise ValueError(f"{name} contains NaN or inf")
    check_stiffness(mu, "mu")
    check_positive(margin, "margin")
    check_positive(eps, "eps")
    if split not in _SPLITS:
        raise ValueError(f"split must be 'both' or 'larger', got {split!r}")


class _Body:
    """World-frame view of one body at one pose: node centres, radii, children and leaf triangles."""

    def __init__(self, bsh: BSH, pose: torch.Tensor):
        R = rotation_matrix(pose[3:])
        self.centre = bsh.centre.to(pose) @ R.T + pose[:3]  # (M, 3), differentiable in the pose
        self.radius = bsh.radius.tolist()
        self.child = bsh.child.tolist()
        self.tri = bsh.tri.tolist()
        self.triangles = bsh.triangles.to(pose) @ R.T + pose[:3]  # (F, 3, 3) world vertices

    def is_leaf(self, node: int) -> bool:
        return self.child[node][0] < 0


def _child_pairs(a: _Body, i: int, b: _Body, j: int, split: str) -> list[tuple[int, int]]:
    leaf_i, leaf_j = a.is_leaf(i), b.is_leaf(j)
    if split == "both":
        if not leaf_i and not leaf_j:
            return [(ci, cj) for ci in a.child[i] for cj in b.child[j]]
        split_i = not leaf_i
    # "larger": on a tie both non-leaves (symmetric under swapping the bodies), else the larger sphere
    elif a.radius[i] == b.radius[j]:
        if not leaf_i and not leaf_j:
            return [(ci, cj) for ci in a.child[i] for cj in b.child[j]]
        split_i = not leaf_i
    else:  # (unless it is a leaf)
        split_i = a.radius[i] > b.radius[j]
        if (split_i and leaf_i) or (not split_i and leaf_j):
            split_i = not split_i
    if split_i:
        return [(ci, j) for ci in a.child[i]]
    return [(i, cj) for cj in b.child[j]]


def _recurse(a: _Body, i: int, b: _Body, j: int, kw: dict, counts: dict | None) -> torch.Tensor:
    if counts is not None:
        counts["node_pairs"] += 1
    diff = a.centre[i] - b.centre[j]
    d1 = a.radius[i] + b.radius[j]
    r_val = float(diff.detach().norm())
    width = band_width(d1, kw["eps"], kw["margin"])
    s_val = (r_val - d1) / width
    if s_val >= 1.0:
        return central_potential(diff.norm(), mu=kw["mu"])
    if a.is_leaf(i) and b.is_leaf(j):
        if counts is not None:
            counts["leaf_pairs"] += 1
        fine = pair_potential(a.triangles[a.tri[i]], b.triangles[b.tri[j]], mu=kw["mu"], margin=kw["margin"])
    else:
        fine = sum(_recurse(a, ci, b, cj, kw, counts) for ci, cj in _child_pairs(a, i, b, j, kw["split"]))
    if s_val <= 0.0:  # phi = 0 with zero derivatives: the fine potential alone (r may be 0 here)
        return fine
    r = diff.norm()
    phi = smoothstep((r - d1) / width)
    return phi * central_potential(r, mu=kw["mu"]) + (1.0 - phi) * fine


def mesh_potential_reference(
    bsh_a: BSH,
    pose_a: torch.Tensor,
    bsh_b: BSH,
    pose_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    eps: float = DEFAULT_CONTACT.eps,
    split: str = DEFAULT_CONTACT.split,
) -> torch.Tensor:
    """BSH contact potential of two rigid bodies by naive recursion (the oracle for the batched version).

    Args:
        bsh_a, bsh_b: the bodies' sphere hierarchies (body frame).
        pose_a, pose_b: (6,) float64 poses, translation then rotation vector; a body point X is at
            ``R(omega) X + t``.
        mu: contact coefficient (stiffness scale).
        margin: delta; the potential is +inf when two triangles come within it.
        eps: relative width of the blend band, ``d2 = d1 + max(eps d1, 2 margin)``.
        split: ``"both"`` or ``"larger"`` (which node(s) of an internal pair to descend into).

    Returns:
        () float64 potential, +inf on (near-)penetration (with zero derivatives). Differentiable by autograd to
        second order with respect to both poses (a third derivative raises where a leaf pair is evaluated).

    Raises:
        ValueError: on a bad argument (naming it).
    """
    _check_args(bsh_a, pose_a, bsh_b, pose_b, mu, margin, eps, split)
    kw = {"mu": float(mu), "margin": float(margin), "eps": float(eps), "split": split}
    value = _recurse(_Body(bsh_a, pose_a), 0, _Body(bsh_b, pose_b), 0, kw, None)
    # +inf with zero derivatives, as mesh_potential (not the finite node pairs' derivatives)
    return torch.where(torch.isinf(value), value.detach(), value)


def mesh_traversal_counts_reference(
    bsh_a: BSH,
    pose_a: torch.Tensor,
    bsh_b: BSH,
    pose_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    eps: float = DEFAULT_CONTACT.eps,
    split: str = DEFAULT_CONTACT.split,
) -> dict[str, int]:
    """Traversal statistics of :func:`mesh_potential_reference` at one pose pair.

    Returns:
        ``{"node_pairs": number of P(I, J) calls (root pair and far pairs included),
        "leaf_pairs": number of leaf pairs evaluated with the exact pair potential (s < 1)}``.
    """
    _check_args(bsh_a, pose_a, bsh_b, pose_b, mu, margin, eps, split)
    kw = {"mu": float(mu), "margin": float(margin), "eps": float(eps), "split": split}
    counts = {"node_pairs": 0, "leaf_pairs": 0}
    with torch.no_grad():
        _recurse(_Body(bsh_a, pose_a.detach()), 0, _Body(bsh_b, pose_b.detach()), 0, kw, counts)
    return counts
