"""Cost of one simulator step: forward, forward + backward, Newton iterations, optionally against an older revision.

Scenes (float64, dt = 0.01, the Scene defaults for mu, margin, eps, newton_tol and friction's eps_v unless stated
(``--friction-eps-v`` sets eps_v in every case); every random choice from a fixed seed, so both sides of
``--baseline`` and every run get the same scene). Case names in brackets; the ``--cases`` names are billiards, cubes,
push, boxes, ball, ant.

1. billiards (``billiards{n}``, n = rack balls + cue ball, 16 by default): a break shot, then the balls rolling
   (sliding: friction ``--billiards-friction``, default 0). Balls: icosphere subdivision 2 (320 faces), radius
   ``--ball-radius`` (0.05). A triangle rack of ``--num-balls-rows`` rows (1..5: 1, 3, 6, 10, 15 balls; rows along
   +x, neighbours 2 mm apart) and a cue ball on the -x side moving at ``--cue-speed`` (2 m/s) along +x toward the
   rack's apex, its surface 2 mm + ``--cue-lead-steps`` (4) x 2 cm behind the apex ball's. The set-up (cue ball to
   the rack's last row) is centred on a static 24 r x 12 r x 2 r box table (top face at z = r) refined with
   ``max_edge`` = ``--ground-edge-factor`` (2) x the ball's mean edge length (the same mesh on both sides of
   ``--baseline``). Every ball starts with its lowest vertex 2 mm above the table and lands in the 2 warm-up steps;
   the cue ball hits the apex in step 4 (counted from 0: the third timed step), and the 12 timed steps (3 with
   ``--quick``) cover the impact and all balls moving apart.
2. cubes (``cubes10``): ``--num-cubes`` (10) cubes of ``--cube-size`` (5 cm; trimesh.creation.box, 12 triangles)
   over a static box floor (12 triangles, top face at z = 0; 1 x 1 x 0.1, wider if the cubes' spread needs it),
   friction 0.5. From ``numpy.random.default_rng(0)``: centres uniform in [-s, s]^2, s = ``--cube-spread`` (0.3),
   with footprints (circles of the half diagonal) 5 mm apart (rejection
   sampling), yaw uniform in [-pi, pi], lowest face ``--cube-drop`` (uniform in [5, 20] mm) above the floor,
   horizontal velocities of speed uniform in [0, ``--cube-speed``] (0.5 m/s) and uniform heading. 3 warm-up steps;
   the cubes land in the first timed steps and slide (to rest after ~13 steps), so the default timed window is
   10 steps (3 with ``--quick``).
3. push: a kinematic pole (box 0.1 x 0.1 x 0.8, ``rigid_body(mesh, kind="kinematic")``) pushes a dynamic 0.3 m
   cube along +x over the 1 x 1 x 0.1 floor, friction 0.5. Both start 2 mm above the floor, the pole's +x face
   ``--push-gap`` (15 mm) behind the cube's -x face. The pole moves at ``--push-speed`` (0.3 m/s, 3 mm per step)
   through ``Action(target=...)``: its end-of-step pose start + (t + 1) dt v at step t (a function of t only, so
   no gradient flows through it). The cube lands in the 4 warm-up steps; the pole reaches it in the first timed
   step and pushes it for the rest (20 steps, 3 with ``--quick``).
4. boxes (``boxes4``): 4 boxes (12 triangles each, 0.2 x 0.2 x 0.1) stacked 2 mm apart on the 12-triangle floor,
   timed after they have landed.
5. ball (``ball_box[_refined]_mu{0,0.5}``): one 320-face ball (radius 0.5) resting on a 12-triangle box (4 x 4 x
   0.5; the configuration of ``bench_contact.py`` section 4), the box as-is and refined with ``max_edge`` =
   ``--ground-edge-factor`` x the ball's mean edge length, each with friction off (0) and on (``--friction``).
   Timed after the ball has settled. With ``--obstacle PATH`` (any mesh file trimesh reads, in its own frame:
   z up), two more cases, ``ball_obstacle_mu{0,0.5}``: the same ball on that mesh as a static body, as given (the
   Scene refines it as it would any user's obstacle), centred over the mesh's xy bounds offset by (0.08, 0.04) of
   their extents (over the nearest non-vertical triangle's centroid where nothing lies under that point, e.g. a
   ring's hole), its surface 2 mm above the mesh's highest point under its footprint (``_placement.py``).

6. ant: Gymnasium's Ant (``gymnasium_ant_xml(servos=(100, 5))``: its eight motors as position servos, kp 100
   N m/rad, kv 5 N m s/rad) on a static 3 x 3 x 0.2 m box floor (top face at z = 0; refined to the capsules'
   edges), friction 1, lowest vertex 2 mm above the floor, hips at 0 and ankles mid-range. A gait: each joint's
   target is its stance angle + 0.25 sin(2 pi 1.5 t + phase) rad, phases 0 for the hips, pi / 2 for the ankles,
   legs 1 and 3 opposite to 2 and 4. 10 warm-up steps (landing), 10 timed steps (3 with ``--quick``). Revisions
   before servos existed cannot run it.

A case may act on its steps: ``Case.action(t, state)`` returns the step's :class:`cfd_torch.Action` (push's
kinematic target), t counted from the case's start state; the warm-up, both passes and ``--profile`` pass it.

Every scene first runs ``warmup`` untimed steps (numba compilation, landing), then two passes from the same state:

- forward: ``steps`` consecutive steps ``step(scene, state, action, return_info=True)``. Timed: the forward solve, the
  :class:`cfd_torch.StepInfo`'s ``seconds``, and the whole ``step()`` call (wall time in this script: the solve
  plus input checks and re-centring). Statistics from the StepInfo: Newton iterations, contact evaluations, leaf
  and node pairs, friction contacts, sub-steps.
- forward + backward: one untimed warm-up step with backward, then ``steps`` steps from the same start again, each
  with ``q = state.q.clone().requires_grad_()``, ``step`` (timed: "forward with grad") and ``(w * q_next).sum()
  .backward()`` for a fixed random w (timed around ``.backward()`` here: "backward").

No breakdown of the step into contact / friction / linear solves: earlier versions of this script measured one by
wrapping library internals (``stepper._Problem.contact``, ``lagged_friction``, ``torch.linalg`` functions); that
monkeypatching is gone, and the library reports no such split, so those columns are dropped. ``--profile`` writes
cProfile and torch.profiler tables per scene (``<out>/profile_<case>.txt``), which give the same split by function.

``--baseline REV`` times the git revision REV of the package side by side in the same run: it checks REV out with
``git worktree add`` into a temporary directory and, right after each case at the working tree's package, runs the
same case in a subprocess with PYTHONPATH pointing at that checkout. The subprocess is this script (the working
tree's, so it builds the same scenes, also ones REV's own script lacks) importing REV's package; that API may be
the one before ``StepInfo`` (``step(..., info=dict)``; the forward time compared is then the ``step()`` call's wall
time on both sides), and push needs ``Action.target`` (4b00007 has it). The table gives per case the median
forward and backward ms of both and their ratio (this / REV), and whether the results agree: Newton iterations per
step, end poses of the forward pass, gradient norms.

The machine may be shared: the load average is recorded at the start and end of every scene. ``--threads`` sets
torch's intra-op threads (default: torch's own default); the numba kernels use ``--numba-threads``.

Writes ``<out>/bench_step.json`` (every per-step figure), ``<out>/table.md`` (printed too) and
``<out>/bench_step_breakdown.png`` (forward and backward per case; ``--replot`` rewrites the last two from the JSON).
A case whose step fails (a ``StepError``) is reported in the table and the JSON, and the script then exits with
status 1.

    python scripts/bench_step.py --out results/bench_step --profile       # ~10 min on 2 shared cores
    python scripts/bench_step.py --out results/bench_step_quick --quick   # a few minutes
    python scripts/bench_step.py --quick --cases boxes --baseline e5289f1 # this revision against e5289f1
    python scripts/bench_step.py --quick --cases cubes push --baseline 4b00007
    python scripts/bench_step.py --cases billiards --num-balls-rows 3    # billiards7: 6 rack balls + cue ball
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import io
import json
import math
import os
import platform
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import (  # noqa: E402
    folder_problem,
    int_range,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
)
from _provenance import git_commit, git_revision, json_args  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cfd_torch  # noqa: E402
from cfd_torch import Action, Scene, State, StepError, rigid_body, step  # noqa: E402

F64 = torch.float64
# the authors' C++ on the resting 320-face ball on a 12-triangle box, double precision: per step, per backward
CPP_DOUBLE_S = 0.57
CPP_DOUBLE_BACKWARD_S = 0.06
TARGET_S = CPP_DOUBLE_S / 20.0  # 20x faster than their double-precision step: 28.5 ms
# step(..., return_info=True) -> (State, StepInfo); revisions before it fill a dict: step(..., info=dict)
HAS_STEPINFO = hasattr(cfd_torch, "StepInfo")
STATS = ("newton_iters", "contact_evals", "leaf_pairs", "node_pairs", "friction_contacts", "substeps")


# ------------------------------------------------------------------------------------------------ scenes
class SettingsError(ValueError):
    """Options that cannot make a case's scene (its message names them); ``main`` reports it as a usage error."""


@dataclass
class Case:
    """A scene with its start state, how many steps to run before and while timing, and what acts on each step:
    ``action(t, state)`` gives the step's :class:`cfd_torch.Action` (or None) for the step from ``state`` at step
    index t (counted from the case's start state, warm-up included); None: nothing acts."""

    name: str
    scene: Scene
    state: State
    warmup: int
    steps: int
    meta: dict = field(default_factory=dict)
    action: Callable[[int, State], Action | None] | None = None

    def act(self, t: int, state: State) -> Action | None:
        return None if self.action is None else self.action(t, state)


def _ball(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=2, radius=radius)


def _mean_edge(mesh: trimesh.Trimesh) -> float:
    return float(mesh.edges_unique_length.mean())


def billiards(args) -> Case:
    """A break shot: a triangle rack of ``--num-balls-rows`` rows (1..5: 1, 3, 6, 10, 15 balls, 2 mm apart) and a cue
    ball moving at ``--cue-speed`` along +x toward the rack's apex, on a static table refined with ``max_edge``."""
    r, gap, rows = args.ball_radius, 2e-3, args.num_balls_rows
    if not 1 <= rows <= 5:
        raise SettingsError(f"argument --num-balls-rows: must be in 1..5, got {rows}")
    ball = _ball(r)
    max_edge = args.ground_edge_factor * _mean_edge(ball)
    extents = (24 * r, 12 * r, 2 * r)
    table = trimesh.creation.box(extents=extents)  # at the origin: top face at z = r
    ball_body = rigid_body(ball)
    z = r - float(ball.vertices[:, 2].min()) + gap  # lowest vertex gap above the table's top face
    d = 2 * r + gap  # centre distance of neighbours in the rack
    h = d * math.sqrt(3) / 2  # distance of the rack's rows
    # the cue ball's surface starts gap + cue_speed * dt * cue_lead_steps behind the apex ball's; x is shifted so
    # that the set-up (cue ball to the rack's last row) is centred on the table
    cue_x = -d - args.cue_speed * 0.01 * args.cue_lead_steps
    shift = -0.5 * (cue_x + (rows - 1) * h)
    rack = [[row * h, (k - row / 2) * d] for row in range(rows) for k in range(row + 1)]
    poses = [[0.0] * 6] + [[x + shift, y, z, 0.0, 0.0, 0.0] for x, y in rack]
    poses.append([cue_x + shift, 0.0, z, 0.0, 0.0, 0.0])
    n = len(poses) - 1
    bodies = [rigid_body(table, kind="static", max_edge=max_edge)] + [ball_body] * n
    vel = torch.zeros(len(poses), 6, dtype=F64)
    vel[-1, 0] = args.cue_speed
    scene = Scene(bodies, friction=args.billiards_friction)
    state = scene.initial_state(torch.tensor(poses, dtype=F64), vel)
    meta = {
        "balls": n, "rack_rows": rows, "ball_radius": r, "ball_faces": ball_body.bsh.num_faces,
        "ground_faces": bodies[0].bsh.num_faces, "ground_max_edge": max_edge, "ground_extents": list(extents),
        "rack_gap": gap, "drop_gap": gap, "cue_speed": args.cue_speed, "cue_start_x": cue_x + shift,
        "apex_x": shift, "friction": args.billiards_friction,
        "note": f"the cue ball reaches the rack's apex after about {args.cue_lead_steps} steps",
    }  # fmt: skip
    return Case(f"billiards{n}", scene, state, args.warmup_billiards, args.steps_billiards, meta)


def boxes(args) -> Case:
    """4 boxes 0.2 x 0.2 x 0.1 (12 triangles each) stacked 2 mm apart on a 12-triangle 1 x 1 x 0.1 ground."""
    gap, h = 2e-3, 0.1
    box = trimesh.creation.box(extents=(0.2, 0.2, h))
    ground = trimesh.creation.box(extents=(1.0, 1.0, 0.1))  # at z = -0.05: top face at z = 0
    bodies = [rigid_body(ground, kind="static")] + [rigid_body(box)] * args.num_boxes
    poses = [[0.0, 0.0, -0.05, 0.0, 0.0, 0.0]]
    poses += [[0.0, 0.0, h / 2 + gap + k * (h + gap), 0.0, 0.0, 0.0] for k in range(args.num_boxes)]
    scene = Scene(bodies)
    state = scene.initial_state(torch.tensor(poses, dtype=F64))
    meta = {
        "boxes": args.num_boxes,
        "box_extents": [0.2, 0.2, h],
        "box_faces": 12,
        "ground_faces": 12,
        "gap": gap,
    }
    return Case(f"boxes{args.num_boxes}", scene, state, args.warmup_boxes, args.steps_boxes, meta)


def _default_margin() -> float:
    """The scenes' contact margin (Scene's default; 1 mm in revisions before ContactConfig)."""
    config = getattr(cfd_torch, "ContactConfig", None)
    return config().margin if config is not None else 1e-3


def cubes(args) -> Case:
    """``--num-cubes`` cubes of ``--cube-size`` (12 triangles each) dropped onto a 12-triangle box floor (top face
    at z = 0; at least 1 x 1 x 0.1), sliding: random positions within ``--cube-spread``, yaw, drop heights and
    horizontal velocities from ``default_rng(0)``."""
    a, n, friction, spread = args.cube_size, args.num_cubes, 0.5, args.cube_spread
    if a <= 0 or spread < 0:
        raise SettingsError(f"argument --cube-size/--cube-spread: must be > 0 and >= 0, got {a} and {spread}")
    lo, hi = args.cube_drop
    margin = _default_margin()
    if not margin < lo <= hi:
        raise SettingsError(
            f"argument --cube-drop: LO must exceed the contact margin {margin:g} m (a cube within it starts in "
            f"contact) and be <= HI, got {lo:g} {hi:g}"
        )
    rng = np.random.default_rng(0)
    half_diag = a * math.sqrt(2) / 2  # the cube's footprint lies within this radius whatever its yaw
    min_dist = 2 * half_diag + 5e-3  # centres in [-spread, spread]^2, footprints 5 mm apart
    xy: list[np.ndarray] = []
    tries = 0
    while len(xy) < n:  # rejection sampling: no two footprints overlap
        p = rng.uniform(-spread, spread, 2)
        if all(np.linalg.norm(p - o) >= min_dist for o in xy):
            xy.append(p)
        tries += 1
        if tries > 100_000:
            raise SettingsError(
                f"argument --cube-spread: {spread} is too small for --num-cubes {n} cubes of --cube-size {a} "
                "5 mm apart: widen the spread"
            )
    yaw = rng.uniform(-math.pi, math.pi, n)
    drop = rng.uniform(*args.cube_drop, n)  # lowest face above the floor [m]
    speed = rng.uniform(0.0, args.cube_speed, n)
    heading = rng.uniform(-math.pi, math.pi, n)
    cube = trimesh.creation.box(extents=(a, a, a))
    side = max(1.0, 2 * (spread + a) + 0.2)  # the cubes slide a few cm: 0.1 m of floor around them at least
    floor = trimesh.creation.box(extents=(side, side, 0.1))
    bodies = [rigid_body(floor, kind="static")] + [rigid_body(cube)] * n
    poses = [[0.0, 0.0, -0.05, 0.0, 0.0, 0.0]]
    poses += [[*xy[i], a / 2 + drop[i], 0.0, 0.0, yaw[i]] for i in range(n)]
    vel = torch.zeros(n + 1, 6, dtype=F64)
    vel[1:, 0] = torch.from_numpy(speed * np.cos(heading))
    vel[1:, 1] = torch.from_numpy(speed * np.sin(heading))
    scene = Scene(bodies, friction=friction)
    state = scene.initial_state(torch.tensor(poses, dtype=F64), vel)
    meta = {
        "cubes": n, "cube_extents": [a, a, a], "box_faces": 12, "ground_faces": 12,
        "friction": friction, "seed": 0, "drop_heights": drop.tolist(), "speeds": speed.tolist(),
        "max_speed": args.cube_speed, "spread": spread, "floor_extents": [side, side, 0.1],
    }  # fmt: skip
    return Case(f"cubes{n}", scene, state, args.warmup_cubes, args.steps_cubes, meta)


def push(args) -> Case:
    """A kinematic pole (0.1 x 0.1 x 0.8) moving at ``--push-speed`` along +x pushes a dynamic 0.3 m cube, both
    2 mm above a 12-triangle 1 x 1 x 0.1 floor (top face at z = 0), friction 0.5."""
    gap, side, friction, v = 2e-3, 0.3, 0.5, args.push_speed
    floor = trimesh.creation.box(extents=(1.0, 1.0, 0.1))
    pole = trimesh.creation.box(extents=(0.1, 0.1, 0.8))
    box = trimesh.creation.box(extents=(side, side, side))
    bodies = [
        rigid_body(floor, kind="static"),
        rigid_body(pole, kind="kinematic"),
        rigid_body(box),
    ]
    margin = _default_margin()
    if args.push_gap <= margin:
        raise SettingsError(
            f"argument --push-gap: must exceed the contact margin {margin:g} m (the pole would start in contact "
            f"with the box), got {args.push_gap:g}"
        )
    box_x = 0.0
    pole_x = box_x - side / 2 - args.push_gap - 0.05  # the pole's +x face push_gap behind the box's -x face
    poses = torch.tensor(
        [
            [0.0, 0.0, -0.05, 0, 0, 0],
            [pole_x, 0.0, 0.4 + gap, 0, 0, 0],
            [box_x, 0.0, side / 2 + gap, 0, 0, 0],
        ],
        dtype=F64,
    )
    scene = Scene(bodies, friction=friction)
    start = poses[scene.kinematic].clone()
    delta = torch.zeros(6, dtype=F64)
    delta[0] = v * scene.dt

    def action(t: int, state: State) -> Action:
        # the pole's pose at the end of step t: constant velocity from its start pose (independent of the state,
        # so that the backward pass sees no gradient through it)
        return Action(target=start + (t + 1) * delta)

    meta = {
        "pole_extents": [0.1, 0.1, 0.8], "box_extents": [side] * 3, "box_faces": 12, "pole_faces": 12,
        "ground_faces": 12, "floor_extents": [1.0, 1.0, 0.1], "friction": friction, "push_speed": v,
        "push_gap": args.push_gap, "drop_gap": gap,
        "note": f"the pole reaches the box after about {args.push_gap / (v * scene.dt):.0f} steps",
    }  # fmt: skip
    return Case("push", scene, scene.initial_state(poses), args.warmup_push, args.steps_push, meta, action)


def ball_on_box(args, refined: bool, friction: float) -> Case:
    """A 320-face ball (radius 0.5) 2 mm above a 4 x 4 x 0.5 box (top face at z = 0), off the box's centre."""
    ball = _ball(0.5)
    box = trimesh.creation.box(extents=(4.0, 4.0, 0.5))
    max_edge = args.ground_edge_factor * _mean_edge(ball) if refined else None
    bodies = [rigid_body(ball), rigid_body(box, kind="static", max_edge=max_edge)]
    z = 2e-3 - float(ball.vertices[:, 2].min())
    poses = torch.tensor([[0.31, 0.17, z, 0, 0, 0], [0.0, 0.0, -0.25, 0, 0, 0]], dtype=F64)
    scene = Scene(bodies, friction=friction)
    name = f"ball_box{'_refined' if refined else ''}_mu{friction:g}"
    meta = {
        "ball_radius": 0.5, "ball_faces": bodies[0].bsh.num_faces, "box_faces": bodies[1].bsh.num_faces,
        "box_max_edge": max_edge, "ball_mean_edge": _mean_edge(ball), "friction": friction,
    }  # fmt: skip
    return Case(name, scene, scene.initial_state(poses), args.warmup_ball, args.steps_ball, meta)


def ball_on_obstacle(args, friction: float) -> Case:
    """A 320-face ball (radius 0.5) 2 mm above the static mesh ``--obstacle`` (as given: the Scene refines it)."""
    from _placement import ball_over, load_obstacle

    ball = _ball(0.5)
    obstacle = load_obstacle(args.obstacle)
    start = ball_over(obstacle, 0.5, 2e-3)
    scene = Scene([rigid_body(ball), rigid_body(obstacle, kind="static")], friction=friction)
    poses = torch.tensor([[*start, 0, 0, 0], [0.0] * 6], dtype=F64)
    meta = {
        "obstacle": str(args.obstacle), "ball_radius": 0.5, "ball_faces": scene.bodies[0].bsh.num_faces,
        "obstacle_faces": len(obstacle.faces), "obstacle_faces_simulated": scene.bodies[1].bsh.num_faces,
        "friction": friction, "ball_start": list(start),
    }  # fmt: skip
    state = scene.initial_state(poses)
    return Case(f"ball_obstacle_mu{friction:g}", scene, state, args.warmup_ball, args.steps_ball, meta)


def ant(args) -> Case:
    """Gymnasium's Ant on position servos walking a sinusoidal gait on a 3 x 3 m floor (see the module docstring)."""
    from cfd_torch.rotation import rotation_matrix
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.mjcf import gymnasium_ant_xml

    robot = articulation(gymnasium_ant_xml(servos=(100.0, 5.0)))
    floor = trimesh.creation.box(extents=(3.0, 3.0, 0.2))
    floor.apply_translation((0.0, 0.0, -0.1))
    scene = Scene([rigid_body(floor, kind="static")], articulations=[robot], friction=1.0)
    lo, hi = torch.as_tensor(robot.lower), torch.as_tensor(robot.upper)
    stance = torch.where((lo < 0) & (hi > 0), torch.zeros_like(lo), 0.5 * (lo + hi))
    rows = robot.poses(stance)
    low = min(
        float((b.bsh.vertices.double() @ rotation_matrix(r[None, 3:])[0].T + r[:3])[:, 2].min())
        for b, r in zip(robot.bodies, rows, strict=True)
    )
    base = torch.tensor([0.0, 0.0, 2e-3 - low, 0.0, 0.0, 0.0], dtype=F64)
    poses = torch.cat([torch.zeros(1, 6, dtype=F64), robot.poses(stance, base)])
    # joints in link order: hip_1, ankle_1, .., hip_4, ankle_4; the actuators in MJCF order address them
    leg = torch.arange(8) // 2
    phase = torch.where(torch.arange(8) % 2 == 1, math.pi / 2, 0.0) + math.pi * (leg % 2)
    order = torch.as_tensor(robot.actuator_joint)

    def action(t: int, state: State) -> Action:
        target = stance + 0.25 * torch.sin(2 * math.pi * 1.5 * t * scene.dt + phase)
        return Action(ctrl=target[order])

    meta = {
        "servos": [100.0, 5.0], "floor_extents": [3.0, 3.0, 0.2], "friction": 1.0, "drop_gap": 2e-3,
        "link_faces": [b.bsh.num_faces for b in robot.bodies], "floor_faces": scene.bodies[0].bsh.num_faces,
        "gait": "stance + 0.25 sin(2 pi 1.5 t + phase) rad",
    }  # fmt: skip
    return Case("ant", scene, scene.initial_state(poses), args.warmup_ant, args.steps_ant, meta, action)


def make_cases(args) -> list[Case]:
    cases = []
    for name in args.cases:
        if name == "billiards":
            cases.append(billiards(args))
        elif name == "cubes":
            cases.append(cubes(args))
        elif name == "push":
            cases.append(push(args))
        elif name == "boxes":
            cases.append(boxes(args))
        elif name == "ant":
            cases.append(ant(args))
        elif name == "ball":
            for refined in (False, True):
                for mu_f in (0.0, args.friction):
                    cases.append(ball_on_box(args, refined, mu_f))
            if args.obstacle is not None:
                cases += [ball_on_obstacle(args, mu_f) for mu_f in (0.0, args.friction)]
    if getattr(args, "friction_eps_v", None) is not None:
        for case in cases:
            case.scene = case.scene.replace(friction_eps_v=args.friction_eps_v)
    return cases


# ------------------------------------------------------------------------------------------------ passes
def timed_step(scene: Scene, state: State, action: Action | None = None) -> tuple[State, dict]:
    """One step with ``action`` (None: nothing acts); returns the next state and a row: ``call_s`` (wall time of the
    ``step()`` call), ``total_s`` (the forward solve's time from the StepInfo; the call's time on revisions without
    StepInfo) and the statistics."""
    t0 = time.perf_counter()
    if HAS_STEPINFO:
        nxt, si = step(scene, state, action, return_info=True)
        call = time.perf_counter() - t0
        info = {k: getattr(si, k) for k in STATS}
        solve = si.seconds
    else:
        info = {}
        nxt = step(scene, state, action, info=info)
        call = time.perf_counter() - t0
        solve = call
    stats = {k: int(info[k]) for k in STATS if k in info}
    return nxt, {"total_s": solve, "call_s": call, "info": stats}


def _max_speed(case: Case, state: State) -> float:
    """Largest |(q - q_prev) / dt| entry of the dynamic bodies [m/s or rad/s]."""
    v = (state.q - state.q_prev)[case.scene.dynamic] / case.scene.dt
    return float(v.abs().max())


def _detach(state: State) -> State:
    return State(state.q.detach(), state.q_prev.detach())


def forward_pass(case: Case, state: State, t0: int, steps: int, desc: str) -> tuple[list[dict], State]:
    """``steps`` timed steps from ``state`` at step index ``t0`` (the index the case's action reads)."""
    rows = []
    for i in tqdm(range(steps), desc=desc, leave=False):
        state, row = timed_step(case.scene, state, case.act(t0 + i, state))
        rows.append(row)
    return rows, state


def backward_pass(case: Case, state: State, t0: int, steps: int, w: torch.Tensor, desc: str) -> list[dict]:
    rows = []
    for i in tqdm(range(steps), desc=desc, leave=False):
        q = state.q.clone().requires_grad_()
        out, fwd = timed_step(case.scene, State(q, state.q_prev), case.act(t0 + i, state))
        loss = (w * out.q).sum()
        tic = time.perf_counter()  # (t0 is the step index the actions are taken at)
        loss.backward()
        bwd = {"total_s": time.perf_counter() - tic, "grad_norm": float(q.grad.norm())}
        rows.append({"forward": fwd, "backward": bwd})
        state = _detach(out)
    return rows


def summarise(rows: list[dict]) -> dict:
    """Medians over the timed steps of the time, Newton iterations and traversal counts."""
    t = [r["total_s"] for r in rows]
    s = {"total_s": statistics.median(t), "min_s": min(t), "max_s": max(t), "mean_s": statistics.fmean(t)}
    if all("call_s" in r for r in rows):
        s["call_s"] = statistics.median(r["call_s"] for r in rows)
    infos = [r["info"] for r in rows if r.get("info")]
    if infos:
        for k in STATS:
            if all(k in i for i in infos):
                s[f"{k}_median"] = statistics.median(i[k] for i in infos)
        if all(i.get("contact_evals") for i in infos):
            s["leaf_pairs_per_eval"] = statistics.median(i["leaf_pairs"] / i["contact_evals"] for i in infos)
            s["node_pairs_per_eval"] = statistics.median(i["node_pairs"] / i["contact_evals"] for i in infos)
        s["newton_iters_all"] = [i.get("newton_iters") for i in infos]
    return s


def scene_settings(scene: Scene) -> dict:
    """The scene's settings: its config objects, or the flat fields of revisions before them."""
    out: dict = {"dt": scene.dt}
    for name in ("contact", "friction", "solver"):
        cfg = getattr(scene, name, None)
        if is_dataclass(cfg):
            out[name] = asdict(cfg)
    if len(out) == 1:  # the flat Scene dataclass
        for k in ("mu", "margin", "eps", "split", "friction", "newton_tol", "max_newton_iter"):
            out[k] = getattr(scene, k)
    return out


def run_case(case: Case, args) -> dict:
    res: dict = {"meta": case.meta, "bodies": case.scene.num_bodies, "body_pairs": int(len(case.scene.pairs))}
    res["scene"] = scene_settings(case.scene)
    res["loadavg_start"] = os.getloadavg()
    state = case.state
    try:
        t0 = time.perf_counter()
        for t in tqdm(range(case.warmup), desc=f"{case.name} warm-up", leave=False):
            state = step(case.scene, state, case.act(t, state))
        res["warmup_s"] = time.perf_counter() - t0
        start = _detach(state)
        res["max_speed_start"] = _max_speed(case, start)
        fwd, end = forward_pass(case, start, case.warmup, case.steps, f"{case.name} forward")
        res["max_speed_end"] = _max_speed(case, end)
        res["velocity_end"] = ((end.q - end.q_prev)[case.scene.dynamic] / case.scene.dt).tolist()
        res["q_end"] = end.q.tolist()
        w = torch.randn(start.q.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
        # the first backward compiles kernels: one untimed step
        backward_pass(case, start, case.warmup, 1, w, f"{case.name} fwd+bwd warm-up")
        bwd = backward_pass(case, start, case.warmup, case.steps, w, f"{case.name} fwd+bwd")
    except StepError as err:
        res["error"] = f"{type(err).__name__}: {err}"
        res["loadavg_end"] = os.getloadavg()
        return res
    res["loadavg_end"] = os.getloadavg()
    res["forward"] = summarise(fwd)
    res["forward_with_grad"] = summarise([r["forward"] for r in bwd])
    res["backward"] = summarise([r["backward"] for r in bwd])
    res["forward_backward_s"] = statistics.median(
        r["forward"]["total_s"] + r["backward"]["total_s"] for r in bwd
    )
    res["grad_norms"] = [r["backward"]["grad_norm"] for r in bwd]
    res["steps"] = {"forward": fwd, "forward_backward": bwd}
    if args.profile:
        res["profile"] = profile_case(case, start, args)
    return res


def profile_case(case: Case, state: State, args) -> str:
    """cProfile (by own time) and torch.profiler (aten ops by self CPU time) over ``--profile-steps`` steps."""
    from torch.profiler import ProfilerActivity, profile

    n = args.profile_steps
    pr = cProfile.Profile()
    s = state
    t0 = case.warmup
    pr.enable()
    for i in range(n):
        s = step(case.scene, s, case.act(t0 + i, s))
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(20)
    pstats.Stats(pr, stream=buf).sort_stats("cumulative").print_stats(25)
    s = state
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for i in range(n):
            s = step(case.scene, s, case.act(t0 + i, s))
    w = torch.randn(state.q.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    s, pr_b = state, cProfile.Profile()
    for i in range(n):
        q = s.q.clone().requires_grad_()
        out = step(case.scene, State(q, s.q_prev), case.act(t0 + i, s))
        pr_b.enable()
        (w * out.q).sum().backward()
        pr_b.disable()
        s = _detach(out)
    buf_b = io.StringIO()
    pstats.Stats(pr_b, stream=buf_b).sort_stats("tottime").print_stats(20)
    text = (
        f"{case.name}: {n} forward steps from the timed start state, torch threads {torch.get_num_threads()}, "
        f"numba threads {numba.get_num_threads()}, load average {os.getloadavg()}\n\n"
        + buf.getvalue()
        + f"\n\nbackward only ({n} steps, cProfile)\n"
        + buf_b.getvalue()
        + "\n\ntorch.profiler (aten ops; numba kernels appear as the self time of the calling Python frame)\n"
        + prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20)
    )
    path = args.out / f"profile_{case.name}.txt"
    path.write_text(text)
    return str(path)


# ------------------------------------------------------------------------------------------------ baseline
class Baseline:
    """An older revision of the package checked out in a temporary git worktree; runs one case at a time in a
    subprocess (``script``, default this one, in worker mode: ``--worker SPEC``, PYTHONPATH at the checkout)."""

    def __init__(self, rev: str, script: Path | None = None) -> None:
        root = Path(__file__).resolve().parent.parent
        self.script = Path(__file__).resolve() if script is None else Path(script).resolve()
        self.rev = rev
        self.commit = subprocess.run(
            ["git", "rev-parse", "--short", f"{rev}^{{commit}}"], cwd=root, capture_output=True, text=True,
            check=True,
        ).stdout.strip()  # fmt: skip
        self._tmp = tempfile.TemporaryDirectory(prefix=f"bench_step_{self.commit}_")
        self.dir = Path(self._tmp.name) / "src"
        self._root = root
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(self.dir), self.commit], cwd=root, check=True,
            capture_output=True,
        )  # fmt: skip

    def run(self, case_name: str, args) -> dict:
        return self.run_spec({"args": json_args(args), "case": case_name}, case_name)

    def run_spec(self, spec: dict, name: str) -> dict:
        """Run the worker on ``spec`` (a JSON-able dict, to which the result file's path is added as "result") and
        return the dict it wrote there, or {"error": ...}."""
        path = Path(self._tmp.name) / "spec.json"
        result = Path(self._tmp.name) / f"{name}.json"
        path.write_text(json.dumps({**spec, "result": str(result)}))
        pp = [str(self.dir)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(pp))
        proc = subprocess.run(
            [sys.executable, str(self.script), "--worker", str(path)], cwd=self.dir, env=env,
            capture_output=True, text=True,
        )  # fmt: skip
        if proc.returncode != 0:
            return {"error": f"baseline worker failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}"}
        return json.loads(result.read_text())

    def close(self) -> None:
        subprocess.run(
            ["git", "worktree", "remove", "--force", str(self.dir)], cwd=self._root, capture_output=True
        )
        self._tmp.cleanup()


def worker(spec_path: Path) -> None:
    """Run one case of a spec written by :class:`Baseline` with the cfd_torch on PYTHONPATH; write its result."""
    if not Path(cfd_torch.__file__).resolve().is_relative_to(Path.cwd().resolve()):
        raise SystemExit(f"the worker imported {cfd_torch.__file__}, not the checkout {Path.cwd()}")
    spec = json.loads(spec_path.read_text())
    args = argparse.Namespace(**spec["args"])
    args.out, args.profile = Path(args.out), False
    if args.numba_threads:  # first: starting numba's pool resets the OpenMP thread count torch shares
        numba.set_num_threads(args.numba_threads)
    if args.threads:
        torch.set_num_threads(args.threads)
    (case,) = [c for c in make_cases(args) if c.name == spec["case"]]
    res = run_case(case, args)
    res["cfd_torch_file"] = cfd_torch.__file__
    res["git"] = git_revision()
    res["api"] = "StepInfo" if HAS_STEPINFO else "info dict"
    Path(spec["result"]).write_text(json.dumps(res))


def compare(head: dict, base: dict) -> dict:
    """Median times of both revisions, their ratios (this / baseline) and whether the results agree. The forward
    compared is the ``step()`` call's wall time (the only forward time a revision without StepInfo has)."""
    if "error" in head or "error" in base:
        return {"error": head.get("error") or base.get("error")}

    def fwd(r: dict) -> float:
        return r["forward"].get("call_s", r["forward"]["total_s"])

    qa, qb = torch.tensor(head["q_end"], dtype=F64), torch.tensor(base["q_end"], dtype=F64)
    ga, gb = torch.tensor(head["grad_norms"], dtype=F64), torch.tensor(base["grad_norms"], dtype=F64)
    return {
        "forward_s": fwd(head),
        "forward_baseline_s": fwd(base),
        "forward_ratio": fwd(head) / fwd(base),
        "backward_s": head["backward"]["total_s"],
        "backward_baseline_s": base["backward"]["total_s"],
        "backward_ratio": head["backward"]["total_s"] / base["backward"]["total_s"],
        "newton_iters_equal": head["forward"].get("newton_iters_all")
        == base["forward"].get("newton_iters_all"),
        "q_end_max_abs_diff": float((qa - qb).abs().max()),
        "grad_norm_max_rel_diff": float(((ga - gb).abs() / gb.abs().clamp_min(1e-300)).max()),
    }


# ------------------------------------------------------------------------------------------------ output
def _ms(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{1e3 * x:.{digits}f}"


def _n(x) -> str:
    if x is None:
        return "-"
    return f"{x:.0f}" if abs(x - round(x)) < 1e-9 or x >= 100 else f"{x:.1f}"


def tables(out: dict) -> str:
    lines = [
        f"Step time [ms per step], medians over the timed steps (cfd_torch at {out['meta']['git']}); torch "
        f"threads {out['meta']['torch_threads']}, "
        f"numba threads {out['meta']['numba_threads']}, load average at start {_load(out['meta']['loadavg_start'])}"
        f", at end {_load(out['meta']['loadavg_end'])} ({out['meta']['cpus']} cores). Target: < {_ms(TARGET_S)} ms "
        f"per step (20x the authors' C++ double precision, {_ms(CPP_DOUBLE_S, 0)} ms / step, "
        f"{_ms(CPP_DOUBLE_BACKWARD_S, 0)} ms / backward, for ball_box).",
        "",
        "Forward (no grad): fwd = the forward solve (StepInfo.seconds), call = the whole step() call",
        "",
        "| case | faces | fwd | (min) | call | Newton it | evals/step | leaf pairs/eval | node pairs/eval "
        "| sub-steps | < 28.5 ms | vs C++ 570 ms | load |",
        "|" + "---|" * 13,
    ]
    for name, r in out["cases"].items():
        faces = _faces(r)
        if "error" in r:
            lines.append(f"| {name} | {faces} | failed: {r['error'][:120]} |" + " |" * 10)
            continue
        f = r["forward"]
        lines.append(
            f"| {name} | {faces} | {_ms(f['total_s'])} | {_ms(f['min_s'])} | {_ms(f.get('call_s'))} "
            f"| {_n(f.get('newton_iters_median'))} "
            f"| {_n(f.get('contact_evals_median'))} | {_n(f.get('leaf_pairs_per_eval'))} "
            f"| {_n(f.get('node_pairs_per_eval'))} | {_n(f.get('substeps_median'))} "
            f"| {'yes' if f['total_s'] < TARGET_S else 'no'} "
            f"| {CPP_DOUBLE_S / f['total_s']:.2f}x | {_load(r['loadavg_start'])} |"
        )
    lines += [
        "",
        "Forward + backward: forward with q requiring grad, backward of (w * q_next).sum(); medians over the steps "
        "(fwd + bwd: the median of each step's sum, not the sum of the two medians)",
        "",
        "| case | fwd (grad) | bwd | fwd + bwd | bwd vs C++ 60 ms |",
        "|" + "---|" * 5,
    ]
    for name, r in out["cases"].items():
        if "error" in r:
            continue
        f, b = r["forward_with_grad"], r["backward"]
        lines.append(
            f"| {name} | {_ms(f['total_s'])} | {_ms(b['total_s'], 2)} | {_ms(r['forward_backward_s'])} "
            f"| {CPP_DOUBLE_BACKWARD_S / b['total_s']:.1f}x |"
        )
    base = out.get("baseline")
    if base:
        rev = f"{base['rev']} ({base['commit']})"
        lines += [
            "",
            f"Against {rev}, each case run right after this revision's, in a subprocess: medians of the step() "
            "call (forward, no grad) and of backward(); ratio = this / baseline. Same results: Newton iterations "
            "of every forward step equal, largest |difference| of the end poses, largest relative difference of "
            "the gradient norms.",
            "",
            f"| case | fwd {base['commit']} | fwd this | ratio | bwd {base['commit']} | bwd this | ratio "
            "| Newton its equal | max abs dq_end | max rel d|grad| |",
            "|" + "---|" * 10,
        ]
        for name, c in base["cases"].items():
            if "error" in c:
                lines.append(f"| {name} | failed: {c['error'][:160]} |" + " |" * 8)
                continue
            lines.append(
                f"| {name} | {_ms(c['forward_baseline_s'])} | {_ms(c['forward_s'])} | {c['forward_ratio']:.2f} "
                f"| {_ms(c['backward_baseline_s'], 2)} | {_ms(c['backward_s'], 2)} | {c['backward_ratio']:.2f} "
                f"| {'yes' if c['newton_iters_equal'] else 'no'} | {c['q_end_max_abs_diff']:.1e} "
                f"| {c['grad_norm_max_rel_diff']:.1e} |"
            )
    lines += [
        "",
        "No contact / friction / linear-solve breakdown: it needed wrappers around library internals (see the "
        "script's docstring); --profile gives the split by function.",
    ]
    return "\n".join(lines)


def _load(x) -> str:
    return "/".join(f"{v:.1f}" for v in x)


def _faces(r: dict) -> str:
    m = r["meta"]
    if "obstacle_faces" in m:
        return f"{m['ball_faces']} + {m['obstacle_faces']} ({m['obstacle_faces_simulated']} simulated)"
    if "ball_faces" in m and "box_faces" in m:
        return f"{m['ball_faces']} + {m['box_faces']}"
    if "ground_faces" in m and "ball_faces" in m:
        return f"{m.get('balls', 16)} x {m['ball_faces']} + {m['ground_faces']}"
    if "boxes" in m:
        return f"{m['boxes']} x {m['box_faces']} + {m['ground_faces']}"
    if "cubes" in m:
        return f"{m['cubes']} x {m['box_faces']} + {m['ground_faces']}"
    if "pole_faces" in m:
        return f"{m['box_faces']} + {m['pole_faces']} + {m['ground_faces']}"
    return "?"


def plot(out: dict, path: Path) -> None:
    """Per case: forward (the solve, and the rest of the step() call) and backward medians; the baseline's beside
    them when there is one."""
    cases = {k: r for k, r in out["cases"].items() if "error" not in r}
    if not cases:
        return
    base = (out.get("baseline") or {}).get("cases", {})
    n = len(cases)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.4 * rows), squeeze=False)
    for ax, (name, r) in zip(axes.flat, cases.items(), strict=False):
        solve, call = r["forward"]["total_s"], r["forward"].get("call_s", r["forward"]["total_s"])
        bars = [
            (0, [(solve, "C0", "forward solve"), (call - solve, "C7", "rest of step()")]),
            (1, [(r["backward"]["total_s"], "C3", "backward")]),
        ]
        b = base.get(name, {})
        if "error" not in b and b:
            bars += [
                (0.45, [(b["forward_baseline_s"], "C0", None)]),
                (1.45, [(b["backward_baseline_s"], "C3", None)]),
            ]
        top = 1e3 * TARGET_S
        for x, parts in bars:
            baseline = x % 1 != 0
            bottom = 0.0
            for v, color, label in parts:
                h = 1e3 * max(v, 0.0)
                ax.bar(
                    x, h, bottom=bottom, color=color, label=label, width=0.4, alpha=0.4 if baseline else 1.0,
                    hatch="//" if baseline else None,
                )  # fmt: skip
                bottom += h
            ax.annotate(f"{bottom:.1f}", (x, bottom), ha="center", va="bottom", fontsize=7)
            top = max(top, bottom)
        ax.axhline(1e3 * TARGET_S, ls="--", lw=0.8, color="k", label="28.5 ms target")
        ticks = ([0, 1], ["forward", "backward"])
        if b and "error" not in b:
            ticks = ([0, 0.45, 1, 1.45], ["fwd", out["baseline"]["commit"], "bwd", out["baseline"]["commit"]])
        ax.set_xticks(*ticks)
        ax.set_title(name, fontsize=9)
        ax.set_ylabel("ms per step (medians)")
        ax.set_ylim(0, 1.15 * top)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(
        f"step time (torch threads {out['meta']['torch_threads']}, load {_load(out['meta']['loadavg_start'])})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _source_hash() -> str:
    """sha256 of the library's sources (the working tree may be dirty while the benchmark runs)."""
    h = hashlib.sha256()
    root = Path(cfd_torch.__file__).parent
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


CUE_LEAD_STEPS = 4
CASES = ("billiards", "cubes", "push", "boxes", "ball", "ant")


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser (``parse_args`` adds the checks that involve several options); ``prog`` names the
    program in its messages (default: the script's name)."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/bench_step"), help="output folder")
    ap.add_argument("--quick", action="store_true", help="fewer warm-up and timed steps (a smoke test)")
    ap.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES), help="case families to run")
    ap.add_argument(
        "--steps", type=positive_int, default=None,
        help="timed steps of the cubes, push, boxes and ball cases (default 20, cubes 10; quick 3)",
    )  # fmt: skip
    ap.add_argument(
        "--billiards-steps",
        type=positive_int,
        default=None,
        help="timed billiards steps (default 12, quick 3)",
    )
    ap.add_argument(
        "--threads", type=positive_int, default=None, help="torch intra-op threads (default: torch's default)"
    )
    ap.add_argument(
        "--numba-threads", type=positive_int, default=None, help="numba threads (default: numba's default)"
    )
    ap.add_argument("--ball-radius", type=positive_float, default=0.05, help="billiard ball radius [m]")
    ap.add_argument("--cue-speed", type=nonnegative_float, default=2.0, help="[m/s]")
    ap.add_argument(
        "--cue-lead-steps", type=nonnegative_int, default=CUE_LEAD_STEPS,
        help=f"steps before the cue ball reaches the rack (default {CUE_LEAD_STEPS})",
    )  # fmt: skip
    ap.add_argument(
        "--num-balls-rows", type=int_range(1, 5), default=5,
        help="rows of the billiards rack, 1..5 (1, 3, 6, 10, 15 balls; plus the cue ball; default 5)",
    )  # fmt: skip
    ap.add_argument(
        "--billiards-friction",
        type=nonnegative_float,
        default=0.0,
        help="friction coefficient of billiards (default 0)",
    )
    ap.add_argument("--num-cubes", type=positive_int, default=10, help="cubes: how many (default 10)")
    ap.add_argument(
        "--cube-size", type=positive_float, default=0.05, help="cubes: edge length [m] (default 0.05)"
    )
    ap.add_argument(
        "--cube-spread",
        type=nonnegative_float,
        default=0.3,
        help="cubes: centres uniform in [-s, s]^2 [m] (default 0.3)",
    )
    ap.add_argument(
        "--cube-speed",
        type=nonnegative_float,
        default=0.5,
        help="cubes: largest random horizontal speed [m/s]",
    )
    ap.add_argument(
        "--cube-drop", type=positive_float, nargs=2, default=[0.005, 0.02], metavar=("LO", "HI"),
        help="cubes: random drop heights of the lowest face above the floor [m] (default 0.005 0.02)",
    )  # fmt: skip
    ap.add_argument(
        "--push-speed", type=positive_float, default=0.3, help="push: the pole's speed along +x [m/s]"
    )
    ap.add_argument(
        "--push-gap",
        type=positive_float,
        default=0.015,
        help="push: the pole's start distance behind the box [m]",
    )
    ap.add_argument("--num-boxes", type=positive_int, default=4, help="boxes: how many (default 4)")
    ap.add_argument(
        "--ground-edge-factor",
        type=positive_float,
        default=2.0,
        help="refined ground: max_edge = this x ball mean edge",
    )
    ap.add_argument(
        "--friction", type=nonnegative_float, default=0.5, help="friction coefficient of the 'on' ball case"
    )
    ap.add_argument(
        "--friction-eps-v", type=positive_float, default=None, metavar="V",
        help="every case's friction slip threshold FrictionConfig.eps_v [m/s] (default: the Scene's, 1e-4); a "
        "larger one takes fewer Newton iterations at sticking contacts and lets them creep faster",
    )  # fmt: skip
    ap.add_argument(
        "--obstacle", type=Path, default=None, metavar="PATH",
        help="ball: also rest the ball on this mesh file (a static obstacle, as given; see the docstring)",
    )  # fmt: skip
    ap.add_argument(
        "--only", nargs="+", default=None, metavar="NAME",
        help="run only these case names (e.g. ball_box_mu0 boxes4) of the selected --cases",
    )  # fmt: skip
    ap.add_argument(
        "--baseline", type=git_commit, metavar="REV", default=None,
        help="also time git revision REV of the package, case by case in a subprocess (e.g. e5289f1)",
    )  # fmt: skip
    ap.add_argument("--profile", action="store_true", help="cProfile + torch.profiler tables per case")
    ap.add_argument(
        "--profile-steps", type=positive_int, default=5, help="steps profiled per case (default 5)"
    )
    ap.add_argument(
        "--replot", action="store_true", help="rewrite table.md and the plot from <out>/bench_step.json"
    )
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)  # a --baseline subprocess
    return ap


def parse_args(argv: list[str] | None = None, prog: str | None = None) -> argparse.Namespace:
    """The command line, with the per-case step counts derived from it (``prog``: as for ``build_parser``)."""
    ap = build_parser(prog)
    args = ap.parse_args(argv)
    if args.obstacle is not None:  # a --baseline worker runs in its checkout's directory
        args.obstacle = args.obstacle.resolve()
        if not args.obstacle.is_file():
            ap.error(f"argument --obstacle: no such file: {args.obstacle}")
    if problem := folder_problem(args.out):
        ap.error(f"argument --out: {problem}")
    if args.numba_threads and args.numba_threads > numba.config.NUMBA_NUM_THREADS:
        ap.error(
            f"argument --numba-threads: at most {numba.config.NUMBA_NUM_THREADS} (numba's NUMBA_NUM_THREADS), got "
            f"{args.numba_threads}"
        )
    if args.friction_eps_v is not None and not args.friction_eps_v >= 1e-30:
        ap.error(
            f"argument --friction-eps-v: must be at least 1e-30 m/s (FrictionConfig.eps_v), got {args.friction_eps_v}"
        )
    if args.replot and not (args.out / "bench_step.json").is_file():
        ap.error(f"argument --replot: {args.out / 'bench_step.json'} does not exist")
    steps = args.steps or (3 if args.quick else 20)
    args.steps_ball = args.steps_boxes = args.steps_push = steps
    args.steps_cubes = args.steps or (3 if args.quick else 10)  # landing and sliding; at rest after ~13 steps
    args.steps_billiards = args.billiards_steps or (3 if args.quick else 12)
    args.warmup_ball = 10 if args.quick else 30  # the ball lands and settles
    args.warmup_boxes = 10 if args.quick else 20  # the stack lands (2 Newton iterations per step after ~10)
    args.warmup_billiards = 2  # the balls land on the table; the cue ball then approaches and hits the rack
    args.warmup_cubes = 3  # compilation; the cubes land in the first timed steps, then slide
    args.warmup_push = 4  # the box lands (~3 steps); the pole reaches it in the first timed step
    args.steps_ant = args.steps or (3 if args.quick else 10)
    args.warmup_ant = 10  # the Ant lands on its feet and starts its gait
    return args


def main() -> None:
    args = parse_args()
    if args.worker:
        worker(args.worker)
        return
    if args.replot:
        out = json.loads((args.out / "bench_step.json").read_text())
        text = tables(out)
        (args.out / "table.md").write_text(text + "\n")
        plot(out, args.out / "bench_step_breakdown.png")
        print(text)
        return
    if args.numba_threads:  # first: starting numba's pool resets the OpenMP thread count torch shares
        numba.set_num_threads(args.numba_threads)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        cases = make_cases(args)
    except SettingsError as err:
        build_parser().error(str(err))
    except ValueError as err:  # an --obstacle file that holds no mesh to rest the ball on
        if not str(err).startswith("--obstacle"):
            raise
        build_parser().error(f"argument {err}")
    if args.only:
        unknown = sorted(set(args.only) - {c.name for c in cases})
        if unknown:
            build_parser().error(
                f"argument --only: no case {', '.join(unknown)} among --cases {' '.join(args.cases)} (they make: "
                f"{', '.join(c.name for c in cases)})"
            )
        cases = [c for c in cases if c.name in args.only]
    args.out.mkdir(parents=True, exist_ok=True)

    out: dict = {
        "meta": {
            "torch": torch.__version__, "numba": numba.__version__, "numpy": np.__version__,
            "trimesh": trimesh.__version__, "python": platform.python_version(),
            "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
            "git": git_revision(), "cfd_torch_sources_sha256": _source_hash(), "quick": args.quick,
            "args": json_args(args),
            "loadavg_start": os.getloadavg(),
            "target_s": TARGET_S, "cpp_double_step_s": CPP_DOUBLE_S, "cpp_double_backward_s": CPP_DOUBLE_BACKWARD_S,
        },
        "timed": {
            "forward": "StepInfo.seconds of step(scene, state, return_info=True), the forward solve (state not "
            "requiring grad); call_s: wall time of the whole step() call",
            "forward_with_grad": "the same with state.q requiring grad",
            "backward": "wall time of (w * q_next).sum().backward(), w fixed random (N, 6)",
            "baseline": "step() call (forward, no grad) and backward() wall times of --baseline REV, same cases",
        },
        "cases": {},
    }  # fmt: skip
    baseline = Baseline(args.baseline) if args.baseline else None
    if baseline:
        out["baseline"] = {"rev": args.baseline, "commit": baseline.commit, "cases": {}, "results": {}}
    try:
        for case in tqdm(cases, desc="scenes"):
            out["cases"][case.name] = run_case(case, args)
            if baseline:
                res = baseline.run(case.name, args)
                out["baseline"]["results"][case.name] = res
                out["baseline"]["cases"][case.name] = compare(out["cases"][case.name], res)
    finally:
        if baseline:
            baseline.close()
    out["meta"]["numba_threading_layer"] = _threading_layer()
    # the run used the code imported at the start; a different hash here means the files changed meanwhile
    out["meta"]["cfd_torch_sources_sha256_end"] = _source_hash()
    out["meta"]["loadavg_end"] = os.getloadavg()  # above the thread count means the timings shared the CPU

    (args.out / "bench_step.json").write_text(json.dumps(out, indent=1))
    text = tables(out)
    (args.out / "table.md").write_text(text + "\n")
    plot(out, args.out / "bench_step_breakdown.png")
    print(text)
    print(f"\nwrote {args.out / 'bench_step.json'}, table.md and bench_step_breakdown.png")
    failed = [name for name, r in out["cases"].items() if "error" in r]
    if failed:  # (an older --baseline that cannot run a case is reported in the table, not here)
        raise SystemExit(f"bench_step: {len(failed)} case(s) failed in this checkout: {', '.join(failed)}")


def _threading_layer() -> str | None:
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel numba kernel ran
        return None


if __name__ == "__main__":
    main()
