"""AntPush-v0: the Gymnasium Ant pushing a box. Registered; not available yet (see the class docstring)."""

from __future__ import annotations

from .shell import CoreEnv, CoreVectorEnv

__all__ = ["AntPushCore", "AntPushEnv", "AntPushVectorEnv"]

_WHY = (
    "AntPush-v0 is registered but not available yet: the articulated Ant steps in the simulator "
    "(cfd_torch.sim.articulation) but at ~0.6 s per step and without PD actuators; the task lands with them"
)


class AntPushCore:
    """AntPush: the Gymnasium Ant (8 hinge motors) pushes a box to a target. Not available yet: constructing it
    raises NotImplementedError saying why."""

    def __init__(self, **kwargs) -> None:
        raise NotImplementedError(_WHY)


class AntPushEnv(CoreEnv):
    """Gymnasium face of :class:`AntPushCore` (raises NotImplementedError)."""

    core_class = AntPushCore  # type: ignore[assignment]


class AntPushVectorEnv(CoreVectorEnv):
    """Native vector face of :class:`AntPushCore` (raises NotImplementedError)."""

    core_class = AntPushCore  # type: ignore[assignment]
