"""cfd_torch: differentiable contact with long-range influence (Ye et al., ICLR 2026) in PyTorch.

Shape letters used throughout: B batch (of scenes or pairs), T time, N bodies, Nd dynamic bodies, K kinematic
bodies, V vertices, F faces, P body pairs, C friction contacts, Q generalised coordinates. Triangles are
``(..., 3, 3)`` tensors: vertex index, then xyz. float64 is the reference path; float32 inputs to the pair, mesh
and scene potentials and to the simulator are solved in float64 and returned in float32 (the closed forms
``central_potential``, ``smoothstep`` and ``blend_weight`` compute in their inputs' dtype;
``mesh_potential_reference``, a test oracle, takes float64 only).

Contact (``cfd_torch.contact``):
    pair_potential(tri_a, tri_b, *, mu, margin)              exact separating-plane potential, 2nd-order autograd
    pair_potential_derivatives(tri_a, tri_b, *, mu, margin)  value, grad (..., 18), Hessian (..., 18, 18), plane
    central_potential(r, *, mu)                              closed form 12 mu (1 + r^-1/2)^2
    smoothstep(s), blend_weight(r, d1, eps, margin)          quintic C2 blend
    BSH.build(vertices, faces) / BSH.from_trimesh(mesh)      bounding sphere hierarchy of a rigid body
    mesh_potential(bsh_a, pose_a, bsh_b, pose_b)             BSH potential of two bodies, 2nd-order autograd
    mesh_potential_derivatives(...)                          value, grad (..., 12), Hessian (..., 12, 12)
    mesh_potential_reference(...)                            naive recursive oracle of the same potential
    contact_potential(bshes, poses, static=, exclude=)       scene sum over body pairs, grad (N, 6), Hessian
    ContactModel, CfdContact                                 what the stepper needs of a contact model; the paper's
    ContactConfig                                            the potential's settings (stiffness mu, margin, eps)
    cfd_torch.baselines: ipc_pair_barrier, sdrs_pair_potential  the peers' local barriers

Simulator (``cfd_torch.sim``, SPEC section 5):
    rigid_body(mesh, kind=, density=, max_edge=)             body with exact volumetric mass properties
    Scene(bodies, dt=, gravity=, contact=, friction=, solver=)  bodies and settings of a simulation
    rest_gap(body), stiffness_for_rest_gap(body, gap)        how high a body rests; the stiffness for a gap
    FrictionConfig, SolverConfig                             Coulomb friction; the Newton solve
    step(scene, State(q, q_prev), Action(force, torque, target, ctrl, joints), Params(...)) -> State
                                                             differentiable step, batched over a leading
                                                             dimension of scenes
    rollout(scene, state, actions) -> Trajectory            T steps (ordinary autograd through all of them)
    pair_forces(scene, q)                                    contact force of every body on every other
    recentre_rotation(q)                                     rotation vectors wrapped back to |omega| <= pi
    articulation(source, mount=, kinematic=)                 a robot from MJCF or URDF (Scene(..., articulations=))
    FreeBodies, Kinematics                                   the kinematics seam (q -> poses and derivatives)
    StepInfo, StepError                                      step(..., return_info=True)'s statistics; a failed solve

Also exported: PairSolveError (a pair's plane solve failed), LAMBDA (the weight 12 of the plane's normal
regulariser lam / (1 - |n|)) and the result types PairDerivatives, MeshDerivatives, ContactPotential, ContactEval,
LaggedContacts, RigidBody.

Poses are (..., 6): translation then rotation vector; a body-frame point X is at R(omega) X + t.
"""

import ctypes.util as _ctypes_util
import os as _os
import sys as _sys

# Headless rendering (cfd_torch.envs) needs MuJoCo's EGL backend, chosen when mujoco is first imported; this
# package's MJCF loader and pytorch_kinematics import mujoco, so the choice is made here (an explicit MUJOCO_GL or a
# display wins; without an EGL library mujoco would fail to import with it, so it is left alone; once mujoco is
# imported its backend is chosen, and setting the variable would only misreport it)
if (
    "MUJOCO_GL" not in _os.environ
    and "mujoco" not in _sys.modules
    and not _os.environ.get("DISPLAY")
    and _ctypes_util.find_library("EGL")
):
    _os.environ["MUJOCO_GL"] = "egl"

from .config import ContactConfig, FrictionConfig, SolverConfig  # noqa: E402
from .contact.bsh import BSH  # noqa: E402
from .contact.central import blend_weight, central_potential, smoothstep  # noqa: E402
from .contact.cfd import CfdContact  # noqa: E402
from .contact.mesh import MeshDerivatives, mesh_potential, mesh_potential_derivatives  # noqa: E402
from .contact.model import ContactEval, ContactModel, LaggedContacts  # noqa: E402
from .contact.pair import LAMBDA, PairDerivatives, PairSolveError, pair_potential, pair_potential_derivatives  # noqa: E402
from .contact.reference import mesh_potential_reference  # noqa: E402
from .contact.scene import ContactPotential, contact_potential  # noqa: E402
from .sim.articulation import Articulation, articulation  # noqa: E402
from .sim.bodies import RigidBody, rigid_body  # noqa: E402
from .sim.kinematics import FreeBodies, Kinematics  # noqa: E402
from .sim.rest import RestGapWarning, rest_gap, stiffness_for_rest_gap  # noqa: E402
from .sim.scene import Scene  # noqa: E402
from .sim.stepper import pair_forces, recentre_rotation, rollout, step  # noqa: E402
from .sim.types import Action, Params, State, StepError, StepInfo, Trajectory, allow_in_torch_load  # noqa: E402

# torch.load's default (weights_only=True) rebuilds the plain containers a user keeps: hierarchies, bodies, configs
allow_in_torch_load(BSH, RigidBody, ContactConfig, FrictionConfig, SolverConfig)

__all__ = [
    "BSH",
    "LAMBDA",
    "Action",
    "Articulation",
    "CfdContact",
    "ContactConfig",
    "ContactEval",
    "ContactModel",
    "ContactPotential",
    "FreeBodies",
    "FrictionConfig",
    "Kinematics",
    "LaggedContacts",
    "MeshDerivatives",
    "PairDerivatives",
    "PairSolveError",
    "Params",
    "RestGapWarning",
    "RigidBody",
    "Scene",
    "SolverConfig",
    "State",
    "StepError",
    "StepInfo",
    "Trajectory",
    "articulation",
    "blend_weight",
    "central_potential",
    "contact_potential",
    "mesh_potential",
    "mesh_potential_derivatives",
    "mesh_potential_reference",
    "pair_forces",
    "pair_potential",
    "pair_potential_derivatives",
    "recentre_rotation",
    "rest_gap",
    "rigid_body",
    "rollout",
    "smoothstep",
    "step",
    "stiffness_for_rest_gap",
]
