"""BSH contact potential between rigid meshes, with closed-form pose-space gradients and Hessians.

For two bodies with hierarchies a and b at poses q_a, q_b (translation, rotation vector), the potential is the
recursion of SPEC section 4, started at the two roots::

    P(I, J) = P_c(r)                                  if s >= 1       (far: no descent)
            = phi P_c(r) + (1 - phi) F(I, J)          otherwise, phi = Phi(s) for s > 0 else 0
    F(I, J) = P_exact(tri_I, tri_J)                   if both are leaves
            = sum of P over the child pairs           otherwise (split both, or the larger)

with r = |c_I - c_J| (world centres), d1 = R_I + R_J, s = (r - d1) / w, w = max(eps d1, 2 margin) (``band_width``).

Unrolled, P is a sum of terms ``w * V`` where V is P_c(r) or P_exact and w is the node pair's own phi (central
terms) times the (1 - phi) of all its ancestors. The traversal is breadth-first and batched: the frontier of node
pairs of all body pairs is a set of tensors, classified per level; each frontier element carries its inherited
weight W with its gradient and Hessian in the 12 pose coordinates of its body pair, so the weights' derivatives
enter the result exactly (product rule). Leaf pairs of all levels are solved in one batch at the end
(``pair_potential_derivatives``) and chained to pose space with the second-order rotation terms::

    grad_q = J^T grad_x,   hess_q = J^T hess_x J + sum_k grad_x_k . d2x_k/dq2,   x_k = R(omega) X_k + t.

Coordinates of a body pair's derivatives: [t_a, omega_a, t_b, omega_b].
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._autograd import VALUES_ONLY, ClosedFormPotential, outside_transforms, plain, refuse_vmap, values_only
from .._validate import (
    FLOATS,
    check_alike,
    check_bool,
    check_count,
    check_dense,
    check_not_meta,
    check_positive,
    check_rotation_length,
    check_stiffness,
    check_tolerance,
    check_translation_range,
    max_coord,
    narrowed,
    widened,
)
from ..config import DEFAULT_CONTACT, SPLIT_RULES
from ._traverse import forest_of, traverse
from .bsh import BSH

__all__ = ["MeshDerivatives", "mesh_potential", "mesh_potential_derivatives"]


class MeshDerivatives(NamedTuple):
    """Value and pose-space derivatives of the BSH potential of a body pair.

    Attributes:
        value: (...) potential, +inf when some leaf pair is within the margin.
        grad: (..., 12) d value / d [t_a, omega_a, t_b, omega_b] (zero where value is +inf).
        hessian: (..., 12, 12), or None (``hessian=False``).
        stats: counts of the traversal: "node_pairs" (all node pairs visited), "leaf_pairs" (exact solves),
            "levels" (the breadth-first traversal's levels, on other devices or with ``backend="torch"``; -1
            where the depth-first CPU kernel ran, which does not count them).
    """

    value: torch.Tensor
    grad: torch.Tensor
    hessian: torch.Tensor | None
    stats: dict


# ---------------------------------------------------------------------------------------------- public API
def _check_pose_kind(pose: object, name: str) -> None:
    """A pose must be a (..., 6) float32 or float64 tensor."""
    if not isinstance(pose, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(pose).__name__}")
    check_dense(pose, name)
    if pose.dim() < 1 or pose.shape[-1] != 6:
        raise ValueError(
            f"{name} must have shape (..., 6) (translation, rotation vector), got {tuple(pose.shape)}"
        )
    if pose.dtype not in FLOATS:
        raise ValueError(f"{name} must be float32 or float64, got {pose.dtype}")


def _check_pose_values(pose: torch.Tensor, name: str) -> None:
    """A pose's values: on a device that has them, finite, translations within the dtype's limit, rotation vectors
    no longer than MAX_ROTATION."""
    check_not_meta(pose, name)
    with outside_transforms():
        bad = ~torch.isfinite(plain(pose)).all(-1)
        if bool(bad.any()):
            raise ValueError(f"{name} contains NaN or inf (first at batch index {_first_index(bad)})")
    check_translation_range(pose, name, lambda m: f"batch index {_first_index(m)}", max_coord(pose.dtype))
    check_rotation_length(pose, name, lambda m: f"batch index {_first_index(m)}")


def _first_index(mask: torch.Tensor) -> tuple[int, ...]:
    """The index of the first True of ``mask`` (() for a 0-d one)."""
    return tuple(int(i) for i in torch.nonzero(mask)[0]) if mask.dim() else ()


def _check_params(mu, margin, eps, split, tol, max_iter):
    check_stiffness(mu, "mu")
    for v, n in ((margin, "margin"), (eps, "eps")):
        check_positive(v, n)
    check_tolerance(tol, "tol")
    check_count(max_iter, "max_iter")
    if split not in SPLIT_RULES:
        raise ValueError(f"split must be one of {SPLIT_RULES}, got {split!r}")


def _pair_batch(bsh_a, pose_a, bsh_b, pose_b):
    if not isinstance(bsh_a, BSH) or not isinstance(bsh_b, BSH):
        bad = "bsh_a" if not isinstance(bsh_a, BSH) else "bsh_b"
        raise TypeError(
            f"{bad} must be a cfd_torch.BSH, got {type(bsh_a if bad == 'bsh_a' else bsh_b).__name__}"
        )
    _check_pose_kind(pose_a, "pose_a")
    _check_pose_kind(pose_b, "pose_b")
    check_alike(pose_a, pose_b, "pose_a", "pose_b")
    _check_pose_values(pose_a, "pose_a")
    _check_pose_values(pose_b, "pose_b")
    try:
        batch = torch.broadcast_shapes(pose_a.shape[:-1], pose_b.shape[:-1])
    except RuntimeError as err:
        raise ValueError(
            f"pose_a {tuple(pose_a.shape)} and pose_b {tuple(pose_b.shape)} do not broadcast"
        ) from err
    return batch


def _derivs(bsh_a, bsh_b, qa, qb, *, order, mu, margin, eps, split, tol, max_iter):
    """Closed-form value/grad/Hessian for (B, 6) float64 pose batches."""
    B = qa.shape[0]
    forest = forest_of((bsh_a, bsh_b), qa.dtype, qa.device)
    pose = torch.cat([qa, qb])  # bodies: a copies then b copies
    ar = torch.arange(B, device=qa.device)
    pair_body = torch.stack([ar, ar + B], 1)
    pair_root = forest.roots[None, :].expand(B, 2)
    return traverse(
        forest, pair_body, pair_root, pose.detach(), mu=mu, margin=margin, eps=eps, split=split, order=order,
        tol=tol, max_iter=max_iter,
    )  # fmt: skip


def mesh_potential_derivatives(
    bsh_a: BSH,
    pose_a: torch.Tensor,
    bsh_b: BSH,
    pose_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    eps: float = DEFAULT_CONTACT.eps,
    split: str = DEFAULT_CONTACT.split,
    hessian: bool = True,
    tol: float = DEFAULT_CONTACT.pair_tol,
    max_iter: int = DEFAULT_CONTACT.pair_max_iter,
) -> MeshDerivatives:
    """Value, pose gradient and pose Hessian of the BSH potential of two bodies, in closed form.

    Args:
        bsh_a, bsh_b: the bodies' hierarchies.
        pose_a, pose_b: (..., 6) poses (translation [m], rotation vector [rad]); leading dims broadcast.
        mu: contact coefficient. margin: delta [m]. eps: relative width of the blend band.
        split: "both" (descend both nodes of a pair) or "larger" (only the larger sphere; both on a tie).
        hessian: form the (..., 12, 12) Hessian.
        tol, max_iter: inner plane-solve settings of the leaf pairs (see ``pair_potential``).

    Returns:
        MeshDerivatives(value (...), grad (..., 12), hessian (..., 12, 12) | None, stats), float64 inside, in
        the poses' dtype. Values only: where a pose requires grad, a backward through a field raises (use
        :func:`mesh_potential` under autograd for derivatives of these).

    Raises:
        TypeError: a hierarchy that is not a :class:`cfd_torch.BSH`, a pose that is not a tensor, or a setting of
            the wrong type.
        ValueError: poses not (..., 6) float32/float64 on one device, not broadcasting, with NaN/inf, translations
            beyond the dtype's limit or rotation vectors beyond 1e6 rad; a setting out of range (``split`` not
            "both" or "larger").
        PairSolveError: a leaf pair's plane solve did not converge in ``max_iter`` iterations.
        NotImplementedError: under ``vmap`` or forward-mode AD.
    """
    refuse_vmap("mesh_potential_derivatives", pose_a, pose_b)
    check_bool(hessian, "hessian")
    batch = _pair_batch(bsh_a, pose_a, bsh_b, pose_b)
    _check_params(mu, margin, eps, split, tol, max_iter)
    dt = pose_a.dtype
    with outside_transforms(), torch.no_grad():  # values only: not connected to autograd or torch.func
        qa = plain(pose_a).detach().to(torch.float64).expand(*batch, 6).reshape(-1, 6)
        qb = plain(pose_b).detach().to(torch.float64).expand(*batch, 6).reshape(-1, 6)
        v, g, h, stats = _derivs(
            bsh_a, bsh_b, qa, qb, order=2 if hessian else 1, mu=mu, margin=margin, eps=eps, split=split, tol=tol,
            max_iter=max_iter,
        )  # fmt: skip
    name, inputs = "mesh_potential_derivatives'", "pose_a and pose_b"
    out = MeshDerivatives(
        narrowed(v.reshape(batch), dt, f"{name} value", inputs),
        narrowed(g.reshape(*batch, 12), dt, f"{name} grad", inputs),
        narrowed(h.reshape(*batch, 12, 12), dt, f"{name} hessian", inputs) if h is not None else None,
        stats,
    )
    message = VALUES_ONLY.format(name="mesh_potential_derivatives", diff="mesh_potential")
    return values_only(out, ("value", "grad", "hessian"), (pose_a, pose_b), message)


def mesh_potential(
    bsh_a: BSH,
    pose_a: torch.Tensor,
    bsh_b: BSH,
    pose_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    eps: float = DEFAULT_CONTACT.eps,
    split: str = DEFAULT_CONTACT.split,
    tol: float = DEFAULT_CONTACT.pair_tol,
    max_iter: int = DEFAULT_CONTACT.pair_max_iter,
) -> torch.Tensor:
    """BSH contact potential of two rigid bodies, differentiable in both poses to first and second order.

    Args: as :func:`mesh_potential_derivatives` (all but ``hessian``: autograd forms what is asked for).

    Returns:
        (...) potential in the poses' dtype; +inf when the bodies are within the margin. The backward pass uses
        the closed-form pose gradient; ``create_graph=True`` then gives the closed-form Hessian; a third
        derivative raises. ``torch.func.grad`` and ``jacrev`` work the same way; ``vmap`` and forward mode raise
        ``NotImplementedError``.

    Raises: as :func:`mesh_potential_derivatives`.
    """
    refuse_vmap("mesh_potential", pose_a, pose_b)
    batch = _pair_batch(bsh_a, pose_a, bsh_b, pose_b)
    _check_params(mu, margin, eps, split, tol, max_iter)
    qa = widened(pose_a, "mesh_potential", "pose_a and pose_b").expand(*batch, 6).reshape(-1, 6)
    qb = widened(pose_b, "mesh_potential", "pose_a and pose_b").expand(*batch, 6).reshape(-1, 6)
    params = {"mu": mu, "margin": margin, "eps": eps, "split": split, "tol": tol, "max_iter": max_iter}

    def evaluate(q: torch.Tensor, order: int):
        v, g, h, _ = _derivs(bsh_a, bsh_b, q[:, :6], q[:, 6:], order=order, **params)
        return v, g, h

    v = ClosedFormPotential.apply(torch.cat([qa, qb], -1), evaluate, "mesh_potential")
    return narrowed(v.reshape(batch), pose_a.dtype, "mesh_potential's value", "pose_a and pose_b")
