"""The differentiable simulator: bodies, kinematics, the incremental potential, Newton, feasibility, the step.

Its public names are re-exported by :mod:`cfd_torch` (``cfd_torch.step``, ``cfd_torch.Scene``, ...) and here.
"""

from .bodies import RigidBody, rigid_body
from .kinematics import FreeBodies, Kinematics
from .scene import Scene
from .stepper import pair_forces, recentre_rotation, rollout, step
from .types import Action, Params, State, StepError, StepInfo, Trajectory

__all__ = [
    "Action", "FreeBodies", "Kinematics", "Params", "RigidBody", "Scene", "State", "StepError", "StepInfo",
    "Trajectory", "pair_forces", "recentre_rotation", "rigid_body", "rollout", "step",
]  # fmt: skip
