"""The contact-model protocol of the simulator: what a contact model gives the stepper, and nothing more.

A contact model is built once for a scene's N bodies (their geometry and its settings) and then evaluated on batches
of configurations: ``poses`` (S, N, 6) are S sets of the N bodies' poses (one per scene of a batch, or per sample of a
path), and ``pairs`` (P, 3) are rows (s, i, j): bodies i and j of pose set s. The stepper never looks inside a model,
so a baseline contact (IPC's log barrier, SDRS's local plane barrier) is a new class and no change to the stepper.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import torch

__all__ = ["ContactEval", "LaggedContacts", "ContactModel", "sum_pairs"]


class ContactEval(NamedTuple):
    """A contact model's potential over P body pairs.

    Attributes:
        value: (P,) potential of each pair, +inf where the pair is infeasible (within the margin), its
            derivatives zero there (the built-in models).
        grad: (P, 12) d value / d [q_i, q_j] (pose coordinates: translation, rotation vector), or None.
        hess: (P, 12, 12), or None.
        node_pairs: work done: node pairs visited (0 for models without a hierarchy).
        leaf_pairs: work done: exact primitive pairs evaluated.
        warm: the model's warm-start data for a later evaluation at nearby poses (see ``ContactModel``), or None.
    """

    value: torch.Tensor
    grad: torch.Tensor | None
    hess: torch.Tensor | None
    node_pairs: int
    leaf_pairs: int
    warm: object | None = None


class LaggedContacts(NamedTuple):
    """The C contacts of lagged friction, taken at the start-of-step poses (SPEC section 5).

    Attributes:
        pair: (C,) index of each contact's body pair in the ``pairs`` the model was asked about.
        X: (C, 2, 3) body-frame contact points on bodies i and j (material points: they move rigidly).
        x_t: (C, 2, 3) their world positions at the start-of-step poses.
        tangent: (C, 3, 3) projector I - n n^T onto the contact plane.
        normal_force: (C,) lambda_c, the lagged normal force magnitude [N].
        warm: with ``ids``, the model's warm-start data of the start-of-step poses (as ``ContactEval.warm``), for
            the step's first evaluation at nearby poses; else None.
    """

    pair: torch.Tensor
    X: torch.Tensor
    x_t: torch.Tensor
    tangent: torch.Tensor
    normal_force: torch.Tensor
    warm: object | None = None


@runtime_checkable
class ContactModel(Protocol):
    """What the stepper needs of a contact model (all batched over pose sets, float64).

    ``evaluate(poses, pairs, order, ids=None, warm=None)``: the potential of each pair at order 0 (value), 1
    (+ gradient) or 2 (+ Hessian), in closed form (not connected to autograd). Optional warm start: ``ids`` (P,)
    identify the pair rows stably across calls, ``warm`` is the ``ContactEval.warm`` of an earlier call; the
    simulator passes them only to a model whose attribute ``warm_start`` is True (a model with the plain
    three-argument ``evaluate`` works unchanged), and the result must not depend on them beyond its tolerances.
    Optional partial Hessians: ``hessian_of`` (P, 2) bool, whose 6 x 6 blocks of each pair's Hessian the caller
    reads; where exactly one body of a pair is True, the model may leave the other's rows and columns zero. The
    simulator's Newton iterations pass it, naming the bodies that move, only to a model whose attribute
    ``partial_hessian`` is True.

    ``infeasible(poses, pairs, scale=None)``: (P,) bool, the pairs whose potential is +inf; ``scale`` (N,) scales
    each body about its frame origin first (the reachability check shrinks moving bodies). Must agree exactly with
    ``evaluate``'s +inf.

    ``lagged(poses, pairs, active, create_graph=False[, ids])``: the lagged friction contacts at ``poses``; with
    ``create_graph`` the returned tensors are differentiable functions of ``poses`` (the step's adjoint needs how
    friction depends on the previous state); ``active`` in [0, 1) drops contacts carrying less than that fraction
    of their pair's largest normal force. ``ids`` (P,), passed (as to ``evaluate``) only to a model whose
    ``warm_start`` is True: the result's ``warm`` carries warm-start data for the step's first evaluation.
    """

    def evaluate(
        self,
        poses: torch.Tensor,
        pairs: torch.Tensor,
        order: int,
        ids: torch.Tensor | None = None,
        warm: object | None = None,
    ) -> ContactEval: ...

    def infeasible(
        self, poses: torch.Tensor, pairs: torch.Tensor, scale: torch.Tensor | None = None
    ) -> torch.Tensor: ...

    def lagged(
        self, poses: torch.Tensor, pairs: torch.Tensor, active: float, create_graph: bool = False
    ) -> LaggedContacts: ...


def sum_pairs(
    num_sets: int, num_bodies: int, pairs: torch.Tensor, g: torch.Tensor | None, h: torch.Tensor | None
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Per-pair derivatives over [q_i, q_j] summed into per-pose-set ones.

    Args:
        num_sets: S; num_bodies: N.
        pairs: (P, 3) rows (s, i, j).
        g: (P, 12) pair gradients, or None.
        h: (P, 12, 12) pair Hessians, or None.

    Returns:
        (S, N, 6) gradients and (S, 6N, 6N) Hessians (None where the input is None).

    Rows often repeat a pair (friction has a row per contact), and scattering small blocks costs per index on the
    CPU, so repeated rows are first summed per distinct pair (s, i, j), by one ``index_add_`` of whole rows (which
    sums them in another order than a row-by-row scatter: the same up to rounding). The U distinct rows are then
    scattered: gradients as rows of 6, Hessians as (4U, 36) blocks by one ``index_add_`` into the (S N N, 36)
    blocks (s, a, b) of the result, all (i, i) blocks first, then (i, j), (j, i), (j, j) (with distinct pairs,
    the sums of a block-by-block scatter, bit for bit). On the CPU in float64 with no autograd wanted, one numba loop
    adds the rows in order instead (``_scatter_numba.scatter_pairs``; equal up to rounding).
    """
    if g is None and h is None:
        return None, None
    S, N, P = num_sets, num_bodies, pairs.shape[0]
    x = g if g is not None else h
    graph = torch.is_grad_enabled() and any(y is not None and y.requires_grad for y in (g, h))
    if x.device.type == "cpu" and x.dtype == torch.float64 and not graph:
        from ._scatter_numba import scatter_pairs

        z = x.new_zeros(0, 12, 12)
        G, H = scatter_pairs(
            S, N, pairs.contiguous().numpy(), (g if g is not None else z[:, 0]).contiguous().numpy(),
            (h if h is not None else z).contiguous().numpy(), g is not None, h is not None,
        )  # fmt: skip
        return (torch.from_numpy(G) if g is not None else None), (
            torch.from_numpy(H) if h is not None else None
        )
    row = pairs[:, :1] * N + pairs[:, 1:]  # (P, 2) rows of bodies i and j among the S N poses
    key, inverse = torch.unique(row[:, 0] * N + pairs[:, 2], return_inverse=True)  # block (s, i, j) of each
    U = key.shape[0]
    if U < P:  # sum the rows of each pair first
        g = None if g is None else g.new_zeros(U, 12).index_add_(0, inverse, g)
        h = None if h is None else h.new_zeros(U, 144).index_add_(0, inverse, h.reshape(P, 144))
        pairs = pairs.new_empty(U, 3).index_copy_(0, inverse, pairs)  # the distinct pairs
        row = pairs[:, :1] * N + pairs[:, 1:]
    G = H = None
    if g is not None:
        G = g.new_zeros(S * N, 6)
        G.index_put_((row[:, 0],), g[:, :6], accumulate=True)
        G.index_put_((row[:, 1],), g[:, 6:], accumulate=True)
        G = G.view(S, N, 6)
    if h is not None:
        blocks = h.reshape(U, 2, 6, 2, 6).permute(1, 3, 0, 2, 4).reshape(4 * U, 36)  # (i|j, i|j, U) blocks
        block = row.T[:, None] * N + pairs[:, 1:].T  # (2, 2, U): their blocks (s, i|j, i|j) among the S N N
        H = h.new_zeros(S * N * N, 36).index_add_(0, block.reshape(4 * U), blocks)
        H = H.view(S, N, N, 6, 6).permute(0, 1, 3, 2, 4).reshape(S, 6 * N, 6 * N)
    return G, H
