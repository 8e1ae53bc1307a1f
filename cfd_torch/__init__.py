"""cfd_torch: differentiable contact with long-range influence (Ye et al., ICLR 2026) in PyTorch.

Shape letters used throughout: B batch, T time, N bodies, V vertices, F faces, K pairs, Q generalised coordinates.
Triangles are ``(..., 3, 3)`` tensors: vertex index, then xyz. float64 is the reference path; float32 inputs are
solved in float64 and returned in float32.

Public API:
    pair_potential(tri_a, tri_b, *, mu, margin)              exact separating-plane potential, 2nd-order autograd
    pair_potential_derivatives(tri_a, tri_b, *, mu, margin)  value, grad (..., 18), Hessian (..., 18, 18), plane
    central_potential(r, *, mu)                              closed form 12 mu (1 + r^-1/2)^2
    smoothstep(s), blend_weight(r, d1, eps)                  quintic C2 blend
    BSH.build(vertices, faces) / BSH.from_trimesh(mesh)      bounding sphere hierarchy of a rigid body
    mesh_potential(bsh_a, pose_a, bsh_b, pose_b)             BSH potential of two bodies, 2nd-order autograd
    mesh_potential_derivatives(...)                          value, grad (..., 12), Hessian (..., 12, 12)
    mesh_potential_reference(...)                            naive recursive oracle of the same potential
    contact_potential(bshes, poses, static=, exclude=)       scene sum over body pairs, grad (N, 6), Hessian
    cfd_torch.baselines: ipc_pair_barrier, sdrs_pair_potential  the peers' local barriers

Simulator (rigid bodies, SPEC section 5):
    rigid_body(mesh, kind=, density=, max_edge=)             body with exact volumetric mass properties
    Scene(bodies, dt=, gravity=, mu=, margin=, friction=...) one config object for a simulation
    step(scene, State(q, q_prev), Action(force, torque, target), params) -> State   differentiable step
    rollout(scene, state, actions)                           T steps (ordinary autograd through all of them)

Poses are (..., 6): translation then rotation vector; a body-frame point X is at R(omega) X + t.
"""

from .contact.bsh import BSH
from .contact.central import blend_weight, central_potential, smoothstep
from .contact.mesh import MeshDerivatives, mesh_potential, mesh_potential_derivatives
from .contact.pair import (
    LAMBDA,
    PairDerivatives,
    PairSolveError,
    pair_potential,
    pair_potential_derivatives,
)
from .contact.reference import mesh_potential_reference
from .contact.scene import ContactPotential, contact_potential
from .friction import LaggedFriction, friction_terms, lagged_friction
from .sim.bodies import RigidBody, rigid_body
from .stepper import Action, Params, Scene, State, StepError, recentre_rotation, rollout, step

__all__ = [
    "Action",
    "LaggedFriction",
    "Params",
    "RigidBody",
    "Scene",
    "State",
    "StepError",
    "friction_terms",
    "lagged_friction",
    "recentre_rotation",
    "rigid_body",
    "rollout",
    "step",
    "BSH",
    "ContactPotential",
    "LAMBDA",
    "MeshDerivatives",
    "contact_potential",
    "mesh_potential",
    "mesh_potential_derivatives",
    "mesh_potential_reference",
    "PairDerivatives",
    "PairSolveError",
    "blend_weight",
    "central_potential",
    "pair_potential",
    "pair_potential_derivatives",
    "smoothstep",
]
