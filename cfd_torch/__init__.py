"""cfd_torch: differentiable contact with long-range influence (Ye et al., ICLR 2026) in PyTorch.

Shape letters used throughout: B batch, T time, N bodies, V vertices, F faces, K pairs, Q generalised coordinates.
Triangles are ``(..., 3, 3)`` tensors: vertex index, then xyz. float64 is the reference path; float32 inputs are
solved in float64 and returned in float32.

Public API:
    pair_potential(tri_a, tri_b, *, mu, margin)              exact separating-plane potential, 2nd-order autograd
    pair_potential_derivatives(tri_a, tri_b, *, mu, margin)  value, grad (..., 18), Hessian (..., 18, 18), plane
    central_potential(r, *, mu)                              closed form 12 mu (1 + r^-1/2)^2
    smoothstep(s), blend_weight(r, d1, eps)                  quintic C2 blend
    ipc_pair_barrier, sdrs_pair_potential                    the peers' local barriers (baselines)
"""

from .central import blend_weight, central_potential, smoothstep
from .pair_potential import (
    LAMBDA,
    PairDerivatives,
    PairSolveError,
    pair_potential,
    pair_potential_derivatives,
)

__all__ = [
    "LAMBDA",
    "PairDerivatives",
    "PairSolveError",
    "blend_weight",
    "central_potential",
    "pair_potential",
    "pair_potential_derivatives",
    "smoothstep",
]
