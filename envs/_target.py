"""What Push and AntPush share: the goal is body 0, a box, at a target point."""

from __future__ import annotations

import torch

from .core import EnvState, TaskCore, disc, marker_rows

__all__ = ["BoxToTargetCore"]


class BoxToTargetCore(TaskCore):
    """A task whose goal is body 0 (a box) with its centre within ``success_radius`` of ``state.task["target"]``
    (xy); reward terms: the box's distance to the target after the step, the action cost."""

    success_radius: float

    def box_distance(self, state: EnvState) -> torch.Tensor:
        """(B,) horizontal distance of the box's centre to the target [m]."""
        return (state.q[:, 0, :2] - state.task["target"]).norm(dim=1)

    def reward_terms(
        self, state: EnvState, action: torch.Tensor, next_state: EnvState
    ) -> dict[str, torch.Tensor]:
        return self._distance_terms(self.box_distance(next_state), action)

    def terminated(self, state: EnvState) -> torch.Tensor:
        return self.box_distance(state) < self.success_radius

    def render_markers(self):
        # the target's success disc, on a fainter halo some pixels wide in any image (the disc alone is a few
        # pixels in a small image of a wide view: 4 at 64 x 64 in Push's default one, none with distance=8)
        halo = max(3.0 * self.success_radius, 0.05 * self.render_camera()["distance"])
        return [
            (*disc(halo, 5e-4), (0.2, 0.75, 0.3, 0.3)),
            (*disc(self.success_radius), (0.2, 0.75, 0.3, 0.6)),
        ]

    def marker_poses(self, task: dict[str, torch.Tensor]) -> torch.Tensor:
        return marker_rows(task["target"]).repeat(2, 1)  # the halo and the disc
