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
        value: (P,) potential of each pair, +inf where the pair is infeasible (within the margin).
        grad: (P, 12) d value / d [q_i, q_j] (pose coordinates: translation, rotation vector), or None.
        hess: (P, 12, 12), or None.
        node_pairs: work done: node pairs visited (0 for models without a hierarchy).
        leaf_pairs: work done: exact primitive pairs evaluated.
    """

    value: torch.Tensor
    grad: torch.Tensor | None
    hess: torch.Tensor | None
    node_pairs: int
    leaf_pairs: int


class LaggedContacts(NamedTuple):
    """The C contacts of lagged friction, taken at the start-of-step poses (SPEC section 5).

    Attributes:
        pair: (C,) index of each contact's body pair in the ``pairs`` the model was asked about.
        X: (C, 2, 3) body-frame contact points on bodies i and j (material points: they move rigidly).
        x_t: (C, 2, 3) their world positions at the start-of-step poses.
        tangent: (C, 3, 3) projector I - n n^T onto the contact plane.
        normal_force: (C,) lambda_c, the lagged normal force magnitude [N].
    """

    pair: torch.Tensor
    X: torch.Tensor
    x_t: torch.Tensor
    tangent: torch.Tensor
    normal_force: torch.Tensor


@runtime_checkable
class ContactModel(Protocol):
    """What the stepper needs of a contact model (all batched over pose sets, float64).

    ``evaluate(poses, pairs, order)``: the potential of each pair at order 0 (value), 1 (+ gradient) or 2
    (+ Hessian), in closed form (not connected to autograd).

    ``infeasible(poses, pairs, scale=None)``: (P,) bool, the pairs whose potential is +inf; ``scale`` (N,) scales
    each body about its frame origin first (the reachability check shrinks moving bodies). Must agree exactly with
    ``evaluate``'s +inf.

    ``lagged(poses, pairs, active, create_graph=False)``: the lagged friction contacts at ``poses``; with
    ``create_graph`` the returned tensors are differentiable functions of ``poses`` (the step's adjoint needs how
    friction depends on the previous state); ``active`` in [0, 1) drops contacts carrying less than that fraction
    of their pair's largest normal force.
    """

    def evaluate(self, poses: torch.Tensor, pairs: torch.Tensor, order: int) -> ContactEval: ...

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
    """
    G = H = None
    s, i, j = pairs[:, 0], pairs[:, 1], pairs[:, 2]
    if g is not None:
        G = g.new_zeros(num_sets, num_bodies, 6)
        G.index_put_((s, i), g[:, :6], accumulate=True)
        G.index_put_((s, j), g[:, 6:], accumulate=True)
    if h is not None:
        Hb = h.new_zeros(num_sets, num_bodies, num_bodies, 6, 6)
        Hb.index_put_((s, i, i), h[:, :6, :6], accumulate=True)
        Hb.index_put_((s, i, j), h[:, :6, 6:], accumulate=True)
        Hb.index_put_((s, j, i), h[:, 6:, :6], accumulate=True)
        Hb.index_put_((s, j, j), h[:, 6:, 6:], accumulate=True)
        H = Hb.permute(0, 1, 3, 2, 4).reshape(num_sets, 6 * num_bodies, 6 * num_bodies)
    return G, H
