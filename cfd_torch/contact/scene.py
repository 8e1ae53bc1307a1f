"""Scene-level contact potential: the BSH potential summed over body pairs (SPEC section 4).

Every pair of bodies contributes, however far apart (the non-vanishing property), except pairs of two static
bodies and pairs the caller excludes (e.g. bodies joined by a joint). All included pairs are traversed in one
batch: a far pair costs a single root check (its roots are outside each other's blend band, so it is one central
term), near pairs descend together level by level.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from .._autograd import (
    VALUES_ONLY,
    ClosedFormGrad,
    forward_mode_error,
    outside_transforms,
    plain,
    refuse_vmap,
    tracked,
    values_only,
    vmap_error,
)
from .._validate import (
    FLOATS,
    check_bool,
    check_dense,
    check_not_meta,
    check_rotation_length,
    check_translation_range,
    is_int,
    max_coord,
    narrowed,
    widened,
)
from ..config import DEFAULT_CONTACT
from ._traverse import forest_of, traverse
from .bsh import BSH
from .mesh import _check_params
from .model import sum_pairs

__all__ = ["ContactPotential", "contact_potential", "body_pairs"]


class ContactPotential(NamedTuple):
    """Scene contact potential.

    Attributes:
        value: () total potential, +inf on penetration; differentiable in ``poses`` (autograd, torch.func.grad and
            jacrev) to second order.
        grad: (N, 6) d value / d poses with the rows of static bodies set to zero (the forces that move bodies),
            or None when not computed. Autograd through ``value`` gives the full derivative instead, static
            poses included. A value: where ``poses`` requires grad, a backward through it raises.
        hessian: (N * 6, N * 6) second derivative over the flattened poses, rows and columns of static bodies set
            to zero, or None unless asked for (a value, as ``grad``).
        stats: traversal counts ("body_pairs", "node_pairs", "leaf_pairs", "levels": as in
            :class:`cfd_torch.contact.mesh.MeshDerivatives`, -1 from the depth-first CPU kernel).
    """

    value: torch.Tensor
    grad: torch.Tensor | None
    hessian: torch.Tensor | None
    stats: dict


class _KnownGradPotential(torch.autograd.Function):
    """Attach an already evaluated value (and its gradient over all poses, static ones included, if computed) to
    autograd: backward reuses the gradient; under create_graph the Hessian comes from ClosedFormGrad."""

    @staticmethod
    def forward(q, value, grad, evaluate):
        return value.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        q, _, grad, ctx.evaluate = inputs
        ctx.save_for_backward(q, grad)

    @staticmethod
    def backward(ctx, gout):
        # d (gout . value) / dq = gout g(q); g from the forward's evaluation when it was computed there
        q, g = ctx.saved_tensors
        if torch.is_grad_enabled():
            g, _ = ClosedFormGrad.apply(q, ctx.evaluate, "contact_potential")
        elif g is None:
            _, g, _ = ctx.evaluate(q, 1)
        return gout[:, None] * g, None, None, None

    @staticmethod
    def vmap(info, in_dims, *args):
        raise vmap_error("contact_potential")

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error("contact_potential")


def body_pairs(n: int, static: torch.Tensor, exclude: Sequence[tuple[int, int]] = ()) -> torch.Tensor:
    """(P, 2) pairs i < j that interact: not both static and not excluded."""
    i, j = torch.triu_indices(n, n, offset=1)
    keep = ~(static[i] & static[j])
    if exclude is None:
        exclude = ()
    if not isinstance(exclude, (Sequence, np.ndarray, torch.Tensor)):
        try:
            exclude = list(exclude)  # another iterable of pairs (a generator, a set)
        except TypeError:
            raise ValueError(f"exclude must hold pairs (i, j) of int body indices, got {exclude!r}") from None
    if isinstance(exclude, torch.Tensor):
        if exclude.dim() != 2 or exclude.shape[1] != 2:
            raise ValueError(
                f"exclude must hold pairs (i, j) of int body indices, got shape {tuple(exclude.shape)}"
            )
        exclude = exclude.tolist()
    if len(exclude):
        if isinstance(exclude, np.ndarray):  # rows of a (E, 2) integer array, as Scene takes them
            exclude = exclude.tolist()
        if not all(
            isinstance(e, (tuple, list)) and len(e) == 2 and all(is_int(x) for x in e) for e in exclude
        ):
            raise ValueError(f"exclude must hold pairs (i, j) of int body indices, got {list(exclude)!r}")
        ex = torch.tensor([(min(a, b), max(a, b)) for a, b in exclude], dtype=torch.long)
        if bool(((ex < 0) | (ex >= n)).any()) or bool((ex[:, 0] == ex[:, 1]).any()):
            raise ValueError(f"exclude holds invalid body pairs for {n} bodies: {list(exclude)}")
        hit = ((i[:, None] == ex[None, :, 0]) & (j[:, None] == ex[None, :, 1])).any(1)
        keep &= ~hit
    return torch.stack([i[keep], j[keep]], 1)


def contact_potential(
    bshes: Sequence[BSH],
    poses: torch.Tensor,
    *,
    static: Sequence[bool] | torch.Tensor | None = None,
    exclude: Sequence[tuple[int, int]] = (),
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    eps: float = DEFAULT_CONTACT.eps,
    split: str = DEFAULT_CONTACT.split,
    grad: bool | None = None,
    hessian: bool = False,
    tol: float = DEFAULT_CONTACT.pair_tol,
    max_iter: int = DEFAULT_CONTACT.pair_max_iter,
) -> ContactPotential:
    """Total contact potential of N rigid bodies and, on request, its gradient and Hessian in closed form.

    Args:
        bshes: N hierarchies (the same BSH may serve several bodies).
        poses: (N, 6) poses, translation [m] then rotation vector [rad].
        static: (N,) which bodies are static (default: none). Static-static pairs are skipped.
        exclude: body pairs (i, j) to skip.
        mu, margin, eps, split, tol, max_iter: as in :func:`cfd_torch.mesh_potential`.
        grad: compute the (N, 6) gradient field; default: only when ``poses.requires_grad`` and autograd is
            enabled, i.e. when the value is attached to autograd (its backward then reuses this gradient).
        hessian: compute the (6N, 6N) Hessian (implies the gradient).

    Returns:
        ContactPotential(value, grad, hessian, stats); value +inf when some pair of bodies is within the margin
        (or intersecting), and then zero derivatives (not those of the other pairs: check ``isinf(value)``).

    Raises:
        TypeError: ``poses`` not a tensor, ``bshes`` not a sequence of :class:`cfd_torch.BSH`, or a setting of the
            wrong type.
        ValueError: ``poses`` not (N, 6) (one scene: no batch dimension), not float32/float64, with NaN/inf, far
            translations or long rotation vectors; ``bshes`` or ``static`` not of length N; ``exclude`` holding
            invalid body pairs (out of range, or a body with itself); a setting out of range.
        PairSolveError: a leaf pair's plane solve did not converge.
        NotImplementedError: under ``vmap`` or forward-mode AD.
    """
    if not isinstance(poses, torch.Tensor):
        raise TypeError(f"poses must be a (N, 6) torch.Tensor, got {type(poses).__name__}")
    check_dense(poses, "poses")
    if poses.dim() != 2 or poses.shape[1] != 6:
        raise ValueError(f"poses must be a (N, 6) tensor, got {getattr(poses, 'shape', type(poses))}")
    refuse_vmap("contact_potential", poses)
    check_not_meta(poses, "poses")
    check_bool(hessian, "hessian")
    if grad is not None and not isinstance(grad, bool):
        raise TypeError(f"grad must be a bool or None, got {grad!r}")
    N = poses.shape[0]
    if N == 0:
        raise ValueError("poses must hold at least one body, got a (0, 6) tensor")
    if not isinstance(bshes, Sequence):
        raise TypeError(
            f"bshes must be a sequence of BSH objects (a list or tuple), got {type(bshes).__name__}"
        )
    if len(bshes) != N:
        raise ValueError(
            f"bshes must be a sequence of N = {N} BSH objects (one per row of poses), got {len(bshes)}"
        )
    for i, b in enumerate(bshes):
        if not isinstance(b, BSH):
            raise TypeError(f"bshes[{i}] must be a cfd_torch.BSH, got {type(b).__name__}")
    if poses.dtype not in FLOATS:
        raise ValueError(f"poses must be float32 or float64, got {poses.dtype}")
    with outside_transforms():
        bad = ~torch.isfinite(plain(poses)).all(1)
        if bool(bad.any()):
            raise ValueError(f"poses contains NaN or inf (first at body {int(torch.nonzero(bad)[0])})")
    check_translation_range(
        poses, "poses", lambda m: f"body {int(torch.nonzero(m)[0])}", max_coord(poses.dtype)
    )
    check_rotation_length(poses, "poses", lambda m: f"body {int(torch.nonzero(m)[0])}")
    _check_params(mu, margin, eps, split, tol, max_iter)
    if grad is None:
        grad = poses.requires_grad and torch.is_grad_enabled()
    order = 2 if hessian else (1 if grad else 0)
    q64 = widened(poses, "contact_potential", "poses")
    dev = poses.device

    # Everything but the autograd attachment runs on plain tensors: the traversal's kernels need storage, and the
    # forest cache must not keep tensors wrapped by a torch.func transform.
    with outside_transforms():
        if static is None:
            static_t = torch.zeros(N, dtype=torch.bool)
        else:
            try:
                static_t = torch.as_tensor(static)
            except (TypeError, ValueError, RuntimeError):
                raise ValueError(f"static must be N = {N} booleans, got {static!r}") from None
            if static_t.dtype != torch.bool and not (
                static_t.dtype in (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)
                and bool(((static_t == 0) | (static_t == 1)).all())
            ):
                raise ValueError(f"static must be N = {N} booleans (or 0/1), got {static!r}")
            static_t = static_t.to(device="cpu", dtype=torch.bool)
        if static_t.shape != (N,):
            raise ValueError(f"static must have shape ({N},), got {tuple(static_t.shape)}")
        unique: dict[int, int] = {}
        for b in bshes:
            unique.setdefault(id(b), len(unique))
        uniq = tuple({id(b): b for b in bshes}.values())
        forest = forest_of(uniq, torch.float64, dev)
        which = torch.tensor([unique[id(b)] for b in bshes], device=dev)
        pairs = body_pairs(N, static_t, exclude).to(dev)
        pair_root = (
            forest.roots[which[pairs]] if len(pairs) else torch.zeros(0, 2, dtype=torch.long, device=dev)
        )
        moving = (~static_t).to(dtype=torch.float64, device=dev)[:, None]
    params = {"mu": mu, "margin": margin, "eps": eps, "split": split, "tol": tol, "max_iter": max_iter}
    # (every key present when no pair is traversed: zeros)
    stats: dict = {"body_pairs": int(len(pairs)), "node_pairs": 0, "leaf_pairs": 0, "levels": 0}

    def evaluate(q: torch.Tensor, order_: int):
        """q (1, 6N) plain -> value (1,), grad (1, 6N), hess (1, 6N, 6N): the derivatives over all poses, static
        ones included (the value depends on a static pose through the pairs it forms with moving bodies)."""
        if len(pairs) == 0:
            z = q.new_zeros(1)
            return (
                z,
                (q.new_zeros(1, 6 * N) if order_ >= 1 else None),
                (q.new_zeros(1, 6 * N, 6 * N) if order_ >= 2 else None),
            )
        v, g, h, st = traverse(forest, pairs, pair_root, q.detach().reshape(N, 6), order=order_, **params)
        stats.update(st)
        value = v.sum()[None]
        rows = torch.cat([torch.zeros_like(pairs[:, :1]), pairs], 1)  # (P, 3): one pose set
        G, H = sum_pairs(1, N, rows, g, h)
        # a pair within the margin: +inf with zero derivatives, as for one pair
        if bool(torch.isinf(value).any()):
            G = torch.zeros_like(G) if G is not None else None
            H = torch.zeros_like(H) if H is not None else None
        return value, (G.reshape(1, 6 * N) if G is not None else None), H

    with outside_transforms(), torch.no_grad():
        value, G, H = evaluate(plain(q64).detach().reshape(1, 6 * N), order)
        # the fields hold the derivatives over the moving bodies' poses: static rows (and columns) are zero
        G_field = G.reshape(N, 6) * moving if G is not None else None
        if H is not None:
            mask = moving.reshape(N, 1, 1, 1) * moving.reshape(1, 1, N, 1)
            H = (H.reshape(N, 6, N, 6) * mask).reshape(6 * N, 6 * N)
    if tracked(poses):
        value = _KnownGradPotential.apply(q64.reshape(1, 6 * N), value, G, evaluate)
    value = value[0]
    dt = poses.dtype
    out = ContactPotential(
        narrowed(value, dt, "contact_potential's value", "poses"),
        narrowed(G_field, dt, "contact_potential's grad", "poses") if G_field is not None else None,
        narrowed(H, dt, "contact_potential's hessian", "poses") if H is not None else None,
        stats,
    )
    message = VALUES_ONLY.format(name="contact_potential", diff="its value (create_graph=True for a Hessian)")
    return values_only(out, ("grad", "hessian"), (poses,), message)
