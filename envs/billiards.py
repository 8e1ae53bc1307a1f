"""Billiards-v0: strike a 15-ball rack with the cue ball so that one object ball reaches a pocket."""

from __future__ import annotations

import math

import torch
import trimesh

from cfd_torch import Action, Scene, rigid_body
from cfd_torch.sim.feasibility import feasible, infeasible_reason

from .core import (
    EnvState,
    TaskCore,
    _is_int,
    camera_over,
    check_task_arguments,
    check_unused_by_potential,
    disc,
    marker_rows,
)
from .shell import CoreEnv, CoreVectorEnv

__all__ = ["BilliardsCore", "BilliardsEnv", "BilliardsVectorEnv", "POCKETS", "rack_positions"]

# pocket centres of a 1.27 x 2.54 m playing area whose rack apex is at the origin [m]: far corners, sides, near corners
POCKETS = ((-0.635, 0.94), (0.635, 0.94), (-0.635, -0.33), (0.635, -0.33), (-0.635, -1.6), (0.635, -1.6))
_POCKET_RADIUS = 0.08  # the default success radius about a pocket [m]
_BALL_RADIUS = 0.0286  # the default ball radius [m]


def rack_positions(radius: float) -> torch.Tensor:
    """(15, 2) rack centres: the authors' layout, ball j of row i (i + 1 balls, j = 0..i) at
    x = 1.1 u (4 - i) + 2.2 u j, y = 1.6 u i in the unit u = radius / 0.9, shifted so that the apex (row 0) is at the
    origin and the rack opens toward +y. (With u = radius, balls of adjacent rows would overlap: their centres are
    1.94 u apart; with u = radius / 0.9 they are 4.5 mm apart at the default radius, neighbours in a row 12.7 mm.)"""
    u = radius / 0.9
    xy = [[1.1 * u * (4 - i) + 2.2 * u * j - 4.4 * u, 1.6 * u * i] for i in range(5) for j in range(i + 1)]
    return torch.tensor(xy, dtype=torch.float64)


class BilliardsCore(TaskCore):
    """Billiards: push the cue ball so that a chosen object ball of a 15-ball rack reaches a target pocket.

    Scene: 16 balls (icosphere meshes, ``subdivisions`` 2: 320 faces) of radius ``ball_radius`` (0.0286 m) and mass
    ``ball_mass`` (0.17 kg) on the plane z = 0, gravity off and no table mesh: a frictionless table top (the balls
    slide, they do not roll). The scene is planar (``Scene(planar=True)``): each ball moves in x, y and turns about
    z only, so no impact lifts it off the table. Bodies 0-14 are the rack (``rack_positions``: apex at the origin,
    rows toward +y; its rows 0.157 ``ball_radius`` apart, so ``ball_radius`` must lie between about margin / 0.157
    (6.4 mm at this library's 1 mm margin) and 0.2 m, where the cue ball's nearest start touches the apex ball),
    body 15 the cue ball. dt = 0.01 s; a step the Newton solve cannot converge is retried as up
    to 8 sub-steps.

    Action: (2,) in [-1, 1], the planar force on the cue ball's centre, ``max_force`` (5 N) per unit.

    Observation (70,): the 16 balls' xy positions [m] (32), their xy velocities [m/s] (32), the pocket's xy (2),
    the object ball's xy position and velocity (4; which ball counts is drawn per reset, and the reward is its
    distance to the pocket).

    Reward: ``distance`` = -|xy of the object ball - pocket| [m] after the step, plus ``action`` =
    -``action_cost`` |a|^2 (1e-3). Terminated when the object ball's centre is within ``pocket_radius``
    (0.08 m) of the pocket. Horizon 100 steps (1 s at the default dt; the
    time limit counts steps).

    Initial state: rack at rest; cue ball at rest at x ~ U(-0.1, 0.1), y ~ U(-0.6, -0.4) m (the trivial start:
    40-61 cm from the apex centre to centre, 34-55 cm between the surfaces; nothing touching, every contact force
    tiny but non-zero); the object ball (``target_ball``, default drawn uniformly from the 15) and the pocket
    (``pocket``: an index of ``POCKETS``,
    default drawn from the far corners and the sides, 0-3) are drawn per reset unless fixed. Task variables:
    ``state.task["target"]`` (int64 index), ``state.task["pocket"]`` (xy).

    Baselines (``potential`` "ipc" or "sdrs"): their activation distance is ``dhat`` (1 mm here, not the models'
    1 cm), under the rack's smallest gap (0.157 ``ball_radius``, 4.5 mm: SDRS acts out to 2 (dhat + 0.5 mm) = 3 mm),
    so that the rack stays in place at zero action; with this library's potential the far field pushes the balls
    apart slowly (the rack spreads by about 0.4 mm in 1 s, the object ball's distance to its pocket changes by a
    fraction of a millimetre), the baselines' exactly-zero force leaves it still. With 1 cm both barriers span
    the gaps and blow the rack apart in the first step (at zero actions IPC then sent ball 14 into its far-right pocket,
    seed 2).
    """

    action_dim = 2
    obs_dim = 70
    action_body = 15
    horizon = 100

    def __init__(
        self,
        *,
        ball_radius: float = _BALL_RADIUS,
        ball_mass: float = 0.17,
        subdivisions: int = 2,
        max_force: float = 5.0,
        action_cost: float = 1e-3,
        pocket_radius: float = _POCKET_RADIUS,
        target_ball: int | None = None,
        pocket: int | None = None,
        potential: str = "cfd",
        dhat: float = 1e-3,
        eps: float = 0.01,
        dt: float = 0.01,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if target_ball is not None and not (_is_int(target_ball) and 0 <= target_ball < 15):
            raise ValueError(f"target_ball must be a rack ball index in 0..14 or None, got {target_ball!r}")
        if pocket is not None and not (_is_int(pocket) and 0 <= pocket < len(POCKETS)):
            raise ValueError(
                f"pocket must be an index of POCKETS (0..{len(POCKETS) - 1}) or None, got {pocket!r}"
            )
        if not (_is_int(subdivisions) and 0 <= subdivisions <= 6):
            raise ValueError(
                f"subdivisions must be an int in 0..6 (an icosphere of 20 * 4**subdivisions faces), "
                f"got {subdivisions!r}"
            )
        check_unused_by_potential(potential, "eps", eps, 0.01)
        check_unused_by_potential(potential, "dhat", dhat, 1e-3)
        check_task_arguments(
            action_cost=action_cost, ball_radius=ball_radius, ball_mass=ball_mass, max_force=max_force,
            pocket_radius=pocket_radius,
        )  # fmt: skip
        mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=ball_radius)
        ball = rigid_body(mesh, density=ball_mass / mesh.volume)
        scene = Scene(
            [ball] * 16,
            dt=dt,
            gravity=(0.0, 0.0, 0.0),
            substeps=8,
            planar=True,
            potential=potential,
            **({} if potential == "cfd" else {"dhat": dhat}),
            pair_eps={(15, k): eps for k in range(15)} if potential == "cfd" else None,
        )
        # the starts' closest pairs: the rack's rows (0.157 ball_radius apart) and the cue ball's nearest start to
        # the apex ball (0.4 m between centres)
        closest = torch.zeros(16, 6, dtype=torch.float64)
        closest[:15, :2] = rack_positions(ball_radius)
        closest[15, 1] = -0.4
        if not bool(feasible(scene, closest[None])[0]):
            margin = getattr(scene.contact_model, "margin", 0.0)
            raise ValueError(
                f"ball_radius={ball_radius!r} puts the starting balls {infeasible_reason(scene)} of each other (the "
                f"rack's rows are 0.157 ball_radius apart, the cue ball starts 0.4 m from the apex ball): "
                f"ball_radius must lie between about {margin / 0.157:.3g} and {(0.4 - margin) / 2:.3g} m"
            )
        super().__init__(scene, device=device, dtype=dtype)
        self.ball_radius = ball_radius
        self.max_force = max_force
        self.action_cost = action_cost
        self.pocket_radius = pocket_radius
        self.target_ball = target_ball
        self.pocket = pocket
        self.rack = rack_positions(ball_radius)

    def _initial(self, gen: torch.Generator):
        u = torch.rand(4, generator=gen, dtype=torch.float64)
        q = torch.zeros(16, 6, dtype=torch.float64)
        q[:15, :2] = self.rack
        q[15, 0] = -0.1 + 0.2 * u[0]
        q[15, 1] = -0.6 + 0.2 * u[1]
        target = int(u[2] * 15) if self.target_ball is None else self.target_ball  # (u < 1)
        pocket = int(u[3] * 4) if self.pocket is None else self.pocket
        task = {
            "target": torch.tensor(target, dtype=torch.long),
            "pocket": torch.tensor(POCKETS[pocket], dtype=torch.float64),
        }
        return q, q.clone(), task

    def _action(self, state: EnvState, action: torch.Tensor) -> Action:
        B = state.batch_size
        f = torch.cat([self.max_force * action, action.new_zeros(B, 1)], 1)  # (B, 3) on the cue ball
        return Action(force=torch.cat([action.new_zeros(B, 15, 3), f[:, None, :]], 1))

    def check_task(self, task: dict[str, torch.Tensor]) -> None:
        bad = (task["target"] < 0) | (task["target"] > 14)
        if bool(bad.any()):
            raise ValueError(
                f"state.task['target'] must be a rack ball's index in 0..14, got {task['target'][bad][0].item()} "
                f"(environment {int(torch.nonzero(bad)[0])})"
            )

    def object_ball(self, state: EnvState) -> torch.Tensor:
        """(B, 2) xy of each environment's object ball."""
        B = state.batch_size
        return state.q[torch.arange(B, device=state.q.device), state.task["target"], :2]

    def observe(self, state: EnvState) -> torch.Tensor:
        B = state.batch_size
        v = self.velocity(state)[..., :2]
        rows = torch.arange(B, device=state.q.device)
        target = state.task["target"]
        return torch.cat(
            [
                state.q[..., :2].reshape(B, 32),
                v.reshape(B, 32),
                state.task["pocket"],
                state.q[rows, target, :2],
                v[rows, target],
            ],
            1,
        )

    def reward_terms(
        self, state: EnvState, action: torch.Tensor, next_state: EnvState
    ) -> dict[str, torch.Tensor]:
        d = (self.object_ball(next_state) - next_state.task["pocket"]).norm(dim=1)
        return self._distance_terms(d, action)

    def terminated(self, state: EnvState) -> torch.Tensor:
        return (self.object_ball(state) - state.task["pocket"]).norm(dim=1) < self.pocket_radius

    def observation_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        # the balls' positions and velocities are unbounded (the table has no edge; an episode may run past the
        # horizon); the pocket is one of POCKETS
        high = torch.full((self.obs_dim,), math.inf, dtype=torch.float64)
        high[64:66] = 2.0
        return -high, high

    def render_camera(self, aspect: float = 1.0) -> dict:
        """Over the rack, the cue ball's start region and the pockets that can be drawn: for the far corners and
        the sides (0-3, the default draw) with the default pocket radius and balls no larger than the default, in a
        square or landscape image, a fixed view that holds them all; otherwise (a near-corner ``pocket`` 4 or 5,
        below that view; a wider pocket; a larger rack; a portrait image) a view derived from the discs
        (:func:`~cfd_torch.envs.core.camera_over`)."""
        drawn = range(4) if self.pocket is None else (self.pocket,)
        fixed_view = self.pocket_radius <= _POCKET_RADIUS and self.ball_radius <= _BALL_RADIUS
        if max(drawn) < 4 and fixed_view and aspect >= 1.0:
            return {"lookat": (0.0, 0.05, 0.0), "distance": 2.5, "azimuth": 90.0, "elevation": -70.0}
        r = self.ball_radius
        discs = [(float(x), float(y), r) for x, y in self.rack]
        discs.append((0.0, -0.5, math.hypot(0.1, 0.1) + r))  # the cue ball's start region
        discs += [(*POCKETS[k], self.pocket_radius) for k in drawn]
        return camera_over(discs, azimuth=90.0, elevation=-70.0, aspect=aspect)

    def render_floor(self) -> float:
        return -self.ball_radius

    def render_markers(self):
        return [(*disc(self.pocket_radius), (0.1, 0.1, 0.1, 0.6))]  # the target pocket's success disc

    def marker_poses(self, task: dict[str, torch.Tensor]) -> torch.Tensor:
        return marker_rows(task["pocket"], z=-self.ball_radius)  # on the drawn table

    def render_colours(self, task: dict[str, torch.Tensor]) -> list[tuple[float, ...]]:
        """The object ball black, like the pocket's disc."""
        colours = self.construction_colours()
        colours[int(task["target"])] = (0.08, 0.08, 0.08, 1.0)
        return colours

    def _colour(self, i: int, body) -> tuple[float, float, float, float]:
        if i == 15:
            return (0.95, 0.95, 0.9, 1.0)
        hue = (i * 0.618) % 1.0
        return (*_hsv(hue, 0.75, 0.85), 1.0)


def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    i = math.floor(h * 6)
    f = h * 6 - i
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i % 6]


class BilliardsEnv(CoreEnv):
    __doc__ = "Gymnasium face of :class:`BilliardsCore` (its docstring is the manual).\n\n" + CoreEnv.__doc__
    core_class = BilliardsCore


class BilliardsVectorEnv(CoreVectorEnv):
    __doc__ = "Native vector face of :class:`BilliardsCore`.\n\n" + CoreVectorEnv.__doc__
    core_class = BilliardsCore
