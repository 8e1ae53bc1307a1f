"""Stacked books (paper, section "experiments"; SPEC section 6): a harmonic overhang at the stability limit.

Scene. ``--boards`` (20) identical boards (boxes ``--length`` x ``--width`` x ``--thickness``, density
``--density``, 12-triangle boxes unless ``--max-edge``) on a static table (a box of the boards' length and width,
top face z = 0, right edge x = 0). Board k from the top overhangs the body below it (board k + 1, or the table for
the bottom board) by (1 - ``--retract``) L / (2k): the harmonic stack at its theoretical limit, every overhang
retracted by 0.1 %. In rigid-body statics the centre of mass of the top k boards then lies ``retract`` L / 2 inside
the edge of the body below them, for every k: 0.5 mm for L = 1 m.

Initial gaps. Each board starts level, the gap under it set to where the two-body potential of that interface alone
(``mesh_potential_derivatives`` of the board and the body below, nothing else) carries the weight of the boards on
it (bisection on the gap). This only shortens the settling; the rest state is the simulator's.

Simulation. ``cfd_torch.step``, gravity -9.81 z, Coulomb friction ``--friction`` = 0.5 (eps_v = 1e-4 m/s),
eps = 0.01, newton_tol = 1e-8 m (0.1 % of the smallest gap measured; at 1e-9 the solve stalls on rounding in some
steps), and a quasi-static step ``--dt`` = 0.1 s: implicit Euler at that step damps the fast contact modes, so the
kinetic energy of the initial settling does not throw a board past its equilibrium tilt (a single board on the table
edge at mu = 1e-9 overshoots and topples at dt = 0.01 s but settles at dt = 0.1 s). The question asked is whether
the stack has a static equilibrium that the model reaches from the placement, not how a dropped stack bounces.
A step whose Newton solve fails is retried by the library as 2, 4, ... up to ``--substeps`` = 16 steps of dt / k
(``SolverConfig.substeps``: same model, shorter step, the velocity carried over).

Definitions (every figure in the outputs is one of these):

- **stable**: the run reaches rest before ``--t-max`` = 20 s: every board's largest vertex speed
  (|v| + |omega| R, R the board's half-diagonal) below ``--rest-speed`` = 1e-5 m/s for ``--rest-time`` = 1 s, at
  t >= ``--t-min`` = 2 s. The run fails (unstable) as soon as a board is tilted by more than ``--tilt-fail`` =
  0.1 rad relative to the body below it, or the centre of mass of the boards above some interface lies more than
  ``--topple-fail`` = 1 cm beyond the supporting edge, measured in the frame of the body below (no support force
  inside the contact can hold that: it is toppling), or a step fails even when sub-stepped (StepError). A run that
  neither rests nor fails by t_max is unstable ("not at rest"). The rest speed sits above the creep that the lagged
  IPC-style friction allows (below eps_v its force is a stiff viscous law, so a board held by friction creeps at
  ~1e-6 m/s).
- **margin** [m]: the rest gap between touching bodies. For each of the ``--boards`` interfaces (board on board,
  bottom board on table), the minimum distance between the two surfaces over every vertex of one body against every
  triangle of the other and vice versa (exact vertex-face distances, ``trimesh.triangles.closest_point``; for two
  nearly aligned boxes this is their surface distance). Headline: the mean over the interfaces (min, max and each
  interface are in the JSON). The full gap, delta included; delta = ``--margin`` = 1e-5 m is below every gap.
- **contact-force error** [N]: rigid-body statics says interface c carries the weight of the boards above it and
  that bodies which do not touch exert no force on each other. The model's potential acts between every pair of
  bodies, so the force through interface c deviates from statics by the resultant of the forces that the bodies
  below the interface exert on the bodies above it, except the touching pair:
  ``e_c = | sum_{i below c, j above c, (i, j) != (c - 1, c)} F_ij |``, F_ij the force of body i on body j from
  their two-body potential (``cfd_torch.pair_forces``, ``-grad`` of that pair's potential). At rest (no inertia)
  this is |F_contact,c + F_friction,c - F_statics,c|; friction does not vanish at rest (5 boards at mu = 1e-10:
  its vertical part 1.1e-2 to 1.5e-2 N per interface, 100x e_c), so e_c is not |F_contact,c - F_statics,c| of
  the pair force alone. The contact force itself is not
  differenced against the weight because at rest the tilted contact planes give it a horizontal part that friction
  carries: that is not a long-range effect. Headline: the largest e_c over the interfaces (each e_c, the top board's
  value, which is the long-range force on the top board, and the long-range resultant on every board, from every
  body but its two neighbours, are in the JSON). Linear in mu (every term of the potential carries mu) up to how
  the rest geometry moves with mu.

Unstable runs have no rest state: their margin and force error are taken at the quietest state seen (smallest
largest-vertex-speed) before the run failed, and flagged (``measured_at_rest`` false, * in the table).

Settings chosen (the paper gives none of them). Boards 1 m x 0.2 m x 0.03 m of pine (600 kg/m^3, 3.6 kg) as
12-triangle boxes: refined boards (``--max-edge``) spread the support over more, smaller triangle pairs, which in
this model needs a larger tilt to bring the centre of pressure to the supporting edge (a refined single board on a
table edge topples where the 12-triangle one rests), and cost far more (2,800 triangles per board: over 10 min for
one step). delta = 1e-5 m: the paper's margin at mu = 1e-10, 3.13e-5 m, is below the library default delta = 1e-3 m,
so their delta must be smaller; the gap beyond delta hardly depends on delta (the barrier terms are functions of the
gap minus delta), so the measured margin minus delta is what delta = 1e-3 would add to 1e-3. Friction 0.5 (wood on
wood). mu in {1e-5, 1e-6, 1e-7, 1e-8, 1e-10} as in the paper.

Stability margin (``--bisect-retract``). The criterion above gives a yes/no per mu at one retraction; this mode
measures, per mu, how far the stack must be pulled back from the harmonic limit to stand. **stability margin** [m]:
the smallest retraction in metres, r L / 2 (how far inside its supporting edge the centre of mass of every sub-stack
lies in the rigid placement), at which the run is stable, each probe a full settle-and-watch run (``run``, the
criterion above, nothing else changed). Search in r: the first probe at ``--retract``; while unstable, r grows by
``--bisect-grow`` = 4 up to r = 1 (no overhang at all); while stable, it shrinks by 4 down to ``--bisect-min``; then
bisection at the geometric mean until the bracket (largest unstable r, smallest stable r) is within
``--bisect-rel-width`` = 25 % (hi <= 1.25 lo). Reported: the smallest stable retraction (the bracket's top) with its
bracket, the rest margin (gap) of that stable run, and the paper's margin column beside it. The table also gives,
from the probes, the largest retraction at which the stack toppled (tilt, support or a failed step) and the smallest
at which it stood (at rest, or still creeping above the rest speed at t_max): below the stability margin the verdict
is often 'not at rest', a stack that stands but creeps. The search assumes the verdict is monotone in r; every
probe's verdict is in the JSON. The scaling exponent is the least-squares slope of log(stability margin) against
log(mu), the margin taken as the bracket's geometric mean, over the mus with a closed bracket. Outputs:
``stability_margin_n<boards>.json`` (settings, per mu the bracket, every probe and the full record of the smallest
stable run; a later run with the same settings and other mus adds to it), and ``stability_margin.md`` /
``stability_margin.png`` (log-log, with a sqrt(mu) guide) built from every ``stability_margin_n*.json`` in
``--out``, so runs with different ``--boards`` into one directory share one table and plot.

Outputs under ``--out`` (default results/stacked_books): ``stacked_books.json`` (settings, definitions, and per mu:
stable and why, margin, force error, steps, wall time, solver statistics, per-interface data, the speed / tilt /
support-margin history), ``stacked_books.md`` (our figures beside the paper's) and ``stacked_books.png`` (margin and
force error vs mu, log-log, ours and the paper's), and per mu ``stacked_books_mu<mu>.gif`` (the run seen from the
side, one frame per step; ``--no-gif`` skips them: they need MuJoCo's headless EGL renderer).

    python scripts/stacked_books.py                                             # full run
    python scripts/stacked_books.py --quick --out results/stacked_books_quick   # 5 boards (~30 s)
    python scripts/stacked_books.py --bisect-retract --quick --out results/stacked_books_margin  # stability margin
    python scripts/stacked_books.py --bisect-retract --mu 1e-6 1e-8 1e-10 --out results/stacked_books_margin
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import (  # noqa: E402
    apply_preset,
    folder_problem,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
)
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cfd_torch  # noqa: E402
from cfd_torch import (  # noqa: E402
    RestGapWarning,
    Scene,
    StepError,
    mesh_potential_derivatives,
    rigid_body,
    step,
)

# the paper's sweep of mu rests the boards millimetres to centimetres up on purpose: the Scene's warning of it
# would repeat what the table measures
warnings.filterwarnings("ignore", category=RestGapWarning)
from cfd_torch.rotation import rotation_matrix, transform_points  # noqa: E402

# mu: (margin [m], contact-force error [N], stable) from the paper's table
PAPER = {
    1e-5: (1.82e-2, 6.38e-3, False),
    1e-6: (5.67e-3, 6.40e-4, True),
    1e-7: (1.47e-3, 6.42e-5, True),
    1e-8: (4.12e-4, 6.42e-6, True),
    1e-10: (3.13e-5, 6.42e-8, True),
}
GRAVITY = (0.0, 0.0, -9.81)


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("results/stacked_books"), help="output folder")
    p.add_argument("--quick", action="store_true", help="5 boards (where --boards is not given): a smoke run")
    p.add_argument(
        "--mu",
        type=positive_float,
        nargs="+",
        default=sorted(PAPER, reverse=True),
        help="the potential's mu values",
    )
    p.add_argument("--boards", type=positive_int, default=20, help="number of boards")
    p.add_argument(
        "--length", type=positive_float, default=1.0, help="board length L [m] (along the overhang)"
    )
    p.add_argument("--width", type=positive_float, default=0.2, help="board width [m]")
    p.add_argument("--thickness", type=positive_float, default=0.03, help="board thickness [m]")
    p.add_argument("--density", type=positive_float, default=600.0, help="[kg/m^3]")
    p.add_argument("--table-thickness", type=positive_float, default=0.1, help="[m]")
    p.add_argument(
        "--max-edge", type=positive_float, default=None, help="refine the boxes' triangles to this edge [m]"
    )
    p.add_argument("--retract", type=float, default=1e-3, help="relative retraction of every overhang")
    p.add_argument("--margin", type=positive_float, default=1e-5, help="delta, the barrier's margin [m]")
    p.add_argument("--eps", type=positive_float, default=0.01, help="relative blend width of the hierarchy")
    p.add_argument("--friction", type=nonnegative_float, default=0.5, help="Coulomb coefficient (0: none)")
    p.add_argument("--friction-eps-v", type=positive_float, default=1e-4, help="friction's eps_v [m/s]")
    p.add_argument("--dt", type=positive_float, default=0.1, help="time step [s]")
    p.add_argument("--newton-tol", type=positive_float, default=1e-8, help="[m, rad]")
    p.add_argument(
        "--t-min", type=nonnegative_float, default=2.0, help="no rest verdict before this time [s]"
    )
    p.add_argument(
        "--t-max", type=positive_float, default=20.0, help="end of a run that neither rests nor fails [s]"
    )
    p.add_argument(
        "--rest-speed", type=positive_float, default=1e-5, help="largest vertex speed at rest [m/s]"
    )
    p.add_argument(
        "--rest-time", type=nonnegative_float, default=1.0, help="how long the speed must stay below it [s]"
    )
    p.add_argument(
        "--tilt-fail", type=positive_float, default=0.1, help="a board tilted more than this fails [rad]"
    )
    p.add_argument(
        "--topple-fail", type=positive_float, default=0.01,
        help="fails when a sub-stack's centre of mass is this far beyond its supporting edge [m]",
    )  # fmt: skip
    p.add_argument("--max-newton-iter", type=positive_int, default=50, help="Newton iterations per step")
    p.add_argument(
        "--substeps", type=nonnegative_int, default=16,
        help="a step whose Newton solve fails is retried as 2, 4, ... up to this many steps of dt / k "
        "(SolverConfig.substeps; 0 or 1: no retry)",
    )  # fmt: skip
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--no-gif", dest="gif", action="store_false", help="skip the per-mu GIFs")
    p.add_argument(
        "--bisect-retract", action="store_true",
        help="per mu, bisect the smallest --retract at which the stack is stable (the stability margin); "
        "each probe a full run, starting at --retract",
    )  # fmt: skip
    p.add_argument(
        "--bisect-grow", type=positive_float, default=4.0,
        help="factor by which the retraction grows (or shrinks) until the first probe's verdict flips",
    )  # fmt: skip
    p.add_argument(
        "--bisect-rel-width", type=positive_float, default=0.25,
        help="bisect (in log r) until the bracket's upper end is within this fraction of its lower end",
    )  # fmt: skip
    p.add_argument(
        "--bisect-min", type=positive_float, default=1e-6, help="smallest retraction probed when shrinking"
    )
    a = p.parse_args()
    if a.quick:  # unless --boards is given
        apply_preset(p, a, {"boards": 5})
    if not math.isfinite(a.retract):
        p.error(f"argument --retract: must be a finite number, got {a.retract}")
    if a.t_max < a.dt:
        p.error(f"argument --t-max: must be at least --dt ({a.dt:g} s), got {a.t_max:g}")
    # a run can only come to rest at some t with t_min <= t <= t_max, after rest_time of quiet: else every run
    # would be reported unstable ("not at rest by t_max") whatever the stack does
    if a.t_min > a.t_max:
        p.error(f"argument --t-min: must be at most --t-max ({a.t_max:g} s), got {a.t_min:g}")
    if a.rest_time > a.t_max:
        p.error(f"argument --rest-time: must be at most --t-max ({a.t_max:g} s), got {a.rest_time:g}")
    problem = folder_problem(a.out)
    if problem:
        p.error(f"argument --out: {problem}")
    if a.bisect_retract:
        if not 0 < a.retract <= 1:
            p.error(f"argument --retract: with --bisect-retract it must lie in (0, 1], got {a.retract:g}")
        if a.bisect_grow <= 1:
            p.error(f"argument --bisect-grow: must be above 1, got {a.bisect_grow:g}")
    return a


# ------------------------------------------------------------------------------------------------ scene set-up
def overhang_edges(n: int, length: float, retract: float) -> list[float]:
    """x of the right edge of board k = 1..n from the top (index k - 1); the table's edge is x = 0."""
    edges = [0.0] * (n + 2)
    for k in range(n, 0, -1):
        edges[k] = edges[k + 1] + (1.0 - retract) * length / (2 * k)
    return edges[1 : n + 1]


def settled_gap(
    lower, pose_lower: torch.Tensor, upper, pose_upper: torch.Tensor, load: float, *, mu: float, margin: float,
    eps: float,
) -> float:  # fmt: skip
    """Gap under ``upper`` (translated vertically) at which the two-body potential's vertical force on it equals
    ``load`` [N]; bisection in log(gap - delta). ``pose_upper`` is given at gap 0 (faces touching)."""

    def lift(gap: float) -> float:
        q = pose_upper.clone()
        q[2] += gap
        d = mesh_potential_derivatives(
            lower.bsh, pose_lower, upper.bsh, q, mu=mu, margin=margin, eps=eps, hessian=False
        )
        f = float(-d.grad[8])
        return f if math.isfinite(f) else math.inf

    lo, hi = math.log(1e-12), math.log(1.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if lift(margin + math.exp(mid)) > load:
            lo = mid
        else:
            hi = mid
    return margin + math.exp(hi)


def build(args, mu: float):
    """Scene, initial poses (N, 6) (body 0 the table, 1..n boards bottom to top), board and weight."""
    n, L, W, h = args.boards, args.length, args.width, args.thickness
    board = rigid_body(
        trimesh.creation.box((L, W, h)), kind="dynamic", density=args.density, max_edge=args.max_edge
    )
    table = rigid_body(
        trimesh.creation.box((L, W, args.table_thickness)), kind="static", max_edge=args.max_edge
    )
    weight = board.mass * abs(GRAVITY[2])
    edges = overhang_edges(n, L, args.retract)  # edges[k - 1]: board k from the top
    poses = torch.zeros(n + 1, 6, dtype=torch.float64)
    poses[0, 0], poses[0, 2] = -L / 2, -args.table_thickness / 2
    top_of_below = 0.0
    for i in range(1, n + 1):  # body i is board k = n + 1 - i from the top
        k = n + 1 - i
        poses[i, 0] = edges[k - 1] - L / 2
        poses[i, 2] = top_of_below + h / 2
        lower = table if i == 1 else board
        gap = settled_gap(
            lower, poses[i - 1], board, poses[i], k * weight, mu=mu, margin=args.margin, eps=args.eps
        )
        poses[i, 2] += gap
        top_of_below = float(poses[i, 2]) + h / 2
    scene = Scene(
        [table] + [board] * n, dt=args.dt, gravity=GRAVITY, mu=mu, margin=args.margin, eps=args.eps,
        friction=args.friction, friction_eps_v=args.friction_eps_v, newton_tol=args.newton_tol,
        max_newton_iter=args.max_newton_iter, substeps=max(1, args.substeps),
    )  # fmt: skip
    return scene, poses, board, weight


# ------------------------------------------------------------------------------------------------ measurements
def world_mesh(body, pose: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) world vertices and (F, 3, 3) world triangles of a body at ``pose``."""
    v = transform_points(pose, body.bsh.vertices).numpy()
    return v, v[body.bsh.faces.numpy()]


def surface_gap(body_a, pose_a, body_b, pose_b) -> float:
    """Minimum vertex-face distance between two bodies, both ways [m]."""
    best = math.inf
    for (va, _), (_, tb) in (
        (world_mesh(body_a, pose_a), world_mesh(body_b, pose_b)),
        (world_mesh(body_b, pose_b), world_mesh(body_a, pose_a)),
    ):
        pts = np.repeat(va, len(tb), axis=0)
        tris = np.tile(tb, (len(va), 1, 1))
        d = np.linalg.norm(trimesh.triangles.closest_point(tris, pts) - pts, axis=1)
        best = min(best, float(d.min()))
    return best


def measure(scene: Scene, poses: torch.Tensor, weight: float, args) -> dict:
    """Margins, pair forces and contact-force errors at ``poses`` (see the module docstring)."""
    bodies, n = scene.bodies, args.boards
    N = n + 1
    F = cfd_torch.pair_forces(scene, poses)[..., :3]  # (N, N, 3) F[i, j]: force of body i on body j [N]
    gaps, cut, pair, statics = [], [], [], []
    for c in range(1, N):  # interface c: body c - 1 below, body c above
        gaps.append(surface_gap(bodies[c - 1], poses[c - 1], bodies[c], poses[c]))
        s = F[:c, c:].sum((0, 1)) - F[c - 1, c]
        cut.append(s)
        pair.append(F[c - 1, c])
        statics.append((n - c + 1) * weight)
    longrange = []
    for b in range(1, N):
        others = [j for j in range(N) if abs(j - b) > 1]
        longrange.append(F[others, b].sum(0))
    err = [float(torch.linalg.vector_norm(s)) for s in cut]
    grav = torch.tensor([0.0, 0.0, -weight], dtype=torch.float64)
    resid = [float(torch.linalg.vector_norm(F[:, b].sum(0) + grav)) / weight for b in range(1, N)]
    return {
        "margin": float(np.mean(gaps)),
        "margin_min": float(np.min(gaps)),
        "margin_max": float(np.max(gaps)),
        "force_error": max(err),
        "force_error_mean": float(np.mean(err)),
        "force_error_top": err[-1],
        "interfaces_bottom_to_top": {
            "gap": gaps,
            "force_error": err,
            "longrange_across": [s.tolist() for s in cut],
            "pair_force": [p.tolist() for p in pair],
            "statics_load": statics,
        },
        "board_longrange_force_bottom_to_top": [f.tolist() for f in longrange],
        "potential_force_residual_over_weight": resid,
    }


def support(q: torch.Tensor, masses: torch.Tensor, length: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per interface c (body c - 1 below, c..N-1 above): the support margin [m], i.e. how far inside the supporting
    edge (x = +L/2 in the frame of the body below) the centre of mass of everything above lies, and the tilt of
    body c relative to body c - 1 [rad]. q: (N, 6) poses, masses: (N,) (the table's unused)."""
    R = rotation_matrix(q[:, 3:])  # (N, 3, 3)
    m = masses[1:]
    above = (
        torch.flip(torch.cumsum(torch.flip(m[:, None] * q[1:, :3], [0]), 0), [0])
        / torch.flip(torch.cumsum(torch.flip(m, [0]), 0), [0])[:, None]
    )  # (N-1, 3): centre of mass of bodies c..N-1
    local = torch.einsum("cji,cj->ci", R[:-1], above - q[:-1, :3])  # in the frame of body c - 1
    rel = R[:-1].transpose(1, 2) @ R[1:]
    cos = ((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return length / 2 - local[:, 0], torch.arccos(cos)


# ------------------------------------------------------------------------------------------------ one run
def board_radius(args) -> float:
    return 0.5 * math.sqrt(args.length**2 + args.width**2 + args.thickness**2)


def run(args, mu: float) -> tuple[dict, torch.Tensor]:
    """One settle-and-watch run at ``mu``: its record (JSON-ready) and the poses (steps + 1, n + 1, 6) of every step
    from the start."""
    t0 = time.perf_counter()
    scene, poses0, board, weight = build(args, mu)
    setup_s = time.perf_counter() - t0
    n, dt, R = args.boards, args.dt, board_radius(args)
    state = scene.initial_state(poses0)
    masses = torch.tensor([b.mass for b in scene.bodies], dtype=torch.float64)
    max_steps = int(round(args.t_max / dt))
    rest_needed = max(1, int(round(args.rest_time / dt)))
    quiet, stable, reason = 0, None, f"not at rest by t_max = {args.t_max} s"
    best = (math.inf, poses0.clone(), 0)  # quietest state: (largest vertex speed, poses, step)
    stats = {"newton_iters": 0, "contact_evals": 0, "leaf_pairs": 0, "substepped": 0}
    hist = []
    poses = [poses0]
    steps = 0
    bar = tqdm(range(max_steps), desc=f"mu={mu:.0e}", leave=False)
    t1 = time.perf_counter()
    for s in bar:
        try:
            state, info = step(scene, state, return_info=True)
        except StepError as e:
            stable, reason = False, f"StepError at t = {(s + 1) * dt:.2f} s: {e}"
            break
        steps = s + 1
        poses.append(state.q.detach())
        stats["newton_iters"] += int(info.newton_iters)
        stats["contact_evals"] += info.contact_evals
        stats["leaf_pairs"] += info.leaf_pairs
        stats["substepped"] += int(info.substeps > 1)
        v = (state.q - state.q_prev)[1:] / dt
        speed = float((v[:, :3].norm(dim=1) + v[:, 3:].norm(dim=1) * R).max())
        sup, rel = support(state.q, masses, args.length)
        tilt, sup_min = float(rel.max()), float(sup.min())
        hist.append((steps * dt, speed, tilt, sup_min))
        bar.set_postfix(v=f"{speed:.1e}", tilt=f"{tilt:.1e}", it=int(info.newton_iters))
        if tilt > args.tilt_fail or sup_min < -args.topple_fail:
            stable = False
            reason = (
                f"t = {steps * dt:.2f} s: largest tilt of a board on the body below {tilt:.3f} rad, smallest "
                f"support margin {sup_min:.4f} m"
            )
            break
        if speed < best[0]:
            best = (speed, state.q.detach().clone(), steps)
        quiet = quiet + 1 if speed < args.rest_speed else 0
        if quiet >= rest_needed and steps * dt >= args.t_min:
            stable, reason = True, f"at rest at t = {steps * dt:.2f} s"
            break
    if stable is None:
        stable = False
    sim_s = time.perf_counter() - t1
    at = state.q.detach() if stable else best[1]
    m = measure(scene, at, weight, args)
    record = {
        "mu": mu,
        "stable": bool(stable),
        "reason": reason,
        "measured_at_rest": bool(stable),
        "measured_at_t": (steps if stable else best[2]) * dt,
        # None (JSON null) where no step ran to be measured
        "measured_state_largest_speed": hist[-1][1] if stable and hist else _finite_or_none(best[0]),
        **m,
        "steps": steps,
        "sim_time_s": steps * dt,
        "wall_s": time.perf_counter() - t0,
        "setup_wall_s": setup_s,
        "sim_wall_s": sim_s,
        "solver": stats,
        "largest_tilt_rad": max((h[2] for h in hist), default=0.0),
        "smallest_support_margin_m": min((h[3] for h in hist), default=None),
        "history_t_speed_reltilt_supportmargin": hist,
        "initial_gaps_bottom_to_top": [
            float(poses0[i, 2] - poses0[i - 1, 2])
            - (args.thickness if i > 1 else (args.thickness + args.table_thickness) / 2)
            for i in range(1, n + 1)
        ],
        "board_mass_kg": board.mass,
    }
    return record, torch.stack(poses)


# ------------------------------------------------------------------------------------------------ outputs
def fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2e}"


def table_md(results: list[dict], args) -> str:
    lines = [
        f"Stacked books: {args.boards} boards {args.length} x {args.width} x {args.thickness} m, "
        f"{args.density} kg/m^3, delta {args.margin}, friction {args.friction}, dt {args.dt} s. "
        "margin = mean over interfaces of the rest surface gap; force error = largest |long-range force across "
        "an interface| (see scripts/stacked_books.py). Values of unstable runs (*) are at their quietest state.",
        "",
        "| mu | margin (m) ours | paper | force error (N) ours | paper | stable ours | paper | steps | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        pm, pf, ps = PAPER.get(r["mu"], (None, None, None))
        star = "" if r["measured_at_rest"] else "*"
        lines.append(
            f"| {r['mu']:.0e} | {fmt(r['margin'])}{star} | {fmt(pm)} | {fmt(r['force_error'])}{star} | {fmt(pf)} "
            f"| {'yes' if r['stable'] else 'no'} | {'-' if ps is None else ('yes' if ps else 'no')} "
            f"| {r['steps']} | {r['wall_s']:.0f} |"
        )
    lines += ["", "Reasons: " + "; ".join(f"mu={r['mu']:.0e}: {r['reason']}" for r in results), ""]
    return "\n".join(lines)


def write_stack_gif(args, mu: float, poses: torch.Tensor, path: Path) -> None:
    """A GIF of a run's poses (T, n + 1, 6), seen from the side (+x, the overhang, to the right; +z up), one frame
    per step played in real time; the table grey, the boards in alternating colours."""
    from cfd_torch.envs.render import MeshRenderer, write_gif

    board = trimesh.creation.box((args.length, args.width, args.thickness))
    table = trimesh.creation.box((args.length, args.width, args.table_thickness))
    meshes = [(table.vertices, table.faces)] + [(board.vertices, board.faces)] * args.boards
    colours = [(0.5, 0.5, 0.5, 1.0)] + [
        (0.75, 0.45, 0.2, 1.0) if i % 2 else (0.3, 0.5, 0.75, 1.0) for i in range(args.boards)
    ]
    r = MeshRenderer(meshes, colours, width=640, height=320, camera={"azimuth": 90.0, "elevation": -10.0})
    try:
        frames = [r.render(q) for q in poses.cpu()]
    finally:
        r.close()
    write_gif(frames, path, fps=1.0 / args.dt)


def plot(results: list[dict], path: Path) -> None:
    mus = [r["mu"] for r in results]
    pm = sorted(PAPER)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, idx, label in (
        (axes[0], "margin", 0, "margin [m]"),
        (axes[1], "force_error", 1, "force error [N]"),
    ):
        ax.loglog(pm, [PAPER[m][idx] for m in pm], "s--", color="gray", label="paper")
        ax.loglog(mus, [r[key] for r in results], "o-", color="C0", label="ours")
        bad = [r for r in results if not r["stable"]]
        if bad:
            ax.loglog(
                [r["mu"] for r in bad], [r[key] for r in bad], "x", color="C3", ms=10, label="ours, unstable"
            )
        ax.set_xlabel("mu")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("Stacked books: rest gap and contact-force error vs mu")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


# ------------------------------------------------------------------------------------------------ stability margin
def probe_summary(r: float, res: dict, length: float) -> dict:
    return {
        "retract": r,
        "retraction_m": r * length / 2,
        "stable": res["stable"],
        "reason": res["reason"],
        "margin": res["margin"],
        "measured_at_rest": res["measured_at_rest"],
        "force_error": res["force_error"],
        "steps": res["steps"],
        "wall_s": res["wall_s"],
        "largest_tilt_rad": res["largest_tilt_rad"],
        "smallest_support_margin_m": res["smallest_support_margin_m"],
        "final_largest_speed": res["history_t_speed_reltilt_supportmargin"][-1][1]
        if res["history_t_speed_reltilt_supportmargin"]
        else None,
    }


def bisect_retract(args, mu: float) -> dict:
    """Smallest stable retraction at ``mu``: grow or shrink r from ``args.retract`` until the verdict flips, then
    bisect in log r (see the module docstring)."""
    t0 = time.perf_counter()
    probes: list[dict] = []
    runs: dict[float, dict] = {}

    def stable_at(r: float) -> bool:
        res, _ = run(argparse.Namespace(**{**vars(args), "retract": r}), mu)
        runs[r] = res
        probes.append(probe_summary(r, res, args.length))
        tqdm.write(
            f"  mu={mu:.0e} r={r:.3e} ({r * args.length / 2:.2e} m): {'stable' if res['stable'] else 'unstable'} "
            f"({res['reason']}), {res['steps']} steps, {res['wall_s']:.0f} s"
        )
        return res["stable"]

    lo: float | None = None  # largest unstable r
    hi: float | None = None  # smallest stable r
    r = args.retract
    if stable_at(r):
        hi = r
        while lo is None and r / args.bisect_grow >= args.bisect_min:
            r /= args.bisect_grow
            if stable_at(r):
                hi = r
            else:
                lo = r
    else:
        lo = r
        while hi is None and r < 1.0:
            r = min(1.0, r * args.bisect_grow)
            if stable_at(r):
                hi = r
            else:
                lo = r
    while lo is not None and hi is not None and hi > (1.0 + args.bisect_rel_width) * lo:
        r = math.sqrt(lo * hi)
        if stable_at(r):
            hi = r
        else:
            lo = r
    half = args.length / 2
    return {
        "mu": mu,
        "retract_lo_unstable": lo,
        "retract_hi_stable": hi,
        "stability_margin_m": None if hi is None else hi * half,
        "bracket_m": [None if lo is None else lo * half, None if hi is None else hi * half],
        "estimate_m": None if lo is None or hi is None else math.sqrt(lo * hi) * half,
        "rest_margin_at_stable": None if hi is None else runs[hi]["margin"],
        "force_error_at_stable": None if hi is None else runs[hi]["force_error"],
        "probes": probes,
        "stable_run": None if hi is None else runs[hi],
        "wall_s": time.perf_counter() - t0,
    }


def loglog_slope(rows: list[dict]) -> float | None:
    pts = [(r["mu"], r["estimate_m"]) for r in rows if r["estimate_m"] is not None]
    if len(pts) < 2:
        return None
    x, y = np.log10([p[0] for p in pts]), np.log10([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def margin_md(sets: list[dict]) -> str:
    lines = [
        "Stacked books, stability margin: per mu, the smallest retraction from the harmonic limit (r L / 2 [m], "
        "how far inside its supporting edge every sub-stack's centre of mass lies) at which the stack is stable, "
        "each probe a full settle-and-watch run; bracket = (largest unstable, smallest stable), bisected in log r "
        "to hi <= (1 + w) lo. Rest margin = mean rest gap of that stable run. Topples / stands: the largest probed "
        "retraction at which the stack toppled (tilt, support or failed step) and the smallest at which it stood "
        "(at rest, or still creeping above the rest speed at t_max). See scripts/stacked_books.py.",
        "",
    ]
    for d in sets:
        a, rows = d["settings"], d["results"]
        lines += [
            f"{a['boards']} boards {a['length']} x {a['width']} x {a['thickness']} m, friction {a['friction']}, "
            f"delta {a['margin']}, dt {a['dt']} s, w = {a['bisect_rel_width']}:",
            "",
            "| mu | stability margin (m) | bracket (m) | r | paper margin (m) | rest margin ours (m) "
            "| topples / stands (m) | probes | wall (s) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            pm = PAPER.get(r["mu"], (None,))[0]
            lo, hi = r["bracket_m"]
            sm = fmt(hi) if hi is not None else "none up to r = 1"
            br = f"({fmt(lo) if lo is not None else '< ' + fmt(hi)}, {fmt(hi)}]" if hi is not None else "-"
            # toppling (tilt, support or StepError) versus standing (at rest, or still creeping at t_max)
            stands = [p["retraction_m"] for p in r["probes"] if "at rest" in p["reason"]]
            topples = [p["retraction_m"] for p in r["probes"] if "at rest" not in p["reason"]]
            ts = f"{fmt(max(topples) if topples else None)} / {fmt(min(stands) if stands else None)}"
            lines.append(
                f"| {r['mu']:.0e} | {sm} | {br} | {fmt(r['retract_hi_stable'])} | {fmt(pm)} "
                f"| {fmt(r['rest_margin_at_stable'])} | {ts} | {len(r['probes'])} | {r['wall_s']:.0f} |"
            )
        k = loglog_slope(rows)
        lines += [
            "",
            f"log-log slope of the stability margin (bracket mid) vs mu: {'-' if k is None else f'{k:.2f}'} "
            "(paper's margin column: 0.56).",
            "",
        ]
    return "\n".join(lines)


def margin_plot(sets: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 4.5))
    pm = sorted(PAPER)
    ax.loglog(pm, [PAPER[m][0] for m in pm], "s--", color="gray", label="paper: margin column (rest gap)")
    allmu = []
    for i, d in enumerate(sets):
        rows = [r for r in d["results"] if r["stability_margin_m"] is not None]
        mus = [r["mu"] for r in rows]
        allmu += mus
        hi = np.array([r["stability_margin_m"] for r in rows])
        lo = np.array([r["bracket_m"][0] if r["bracket_m"][0] is not None else np.nan for r in rows])
        err = np.vstack([np.nan_to_num(hi - lo, nan=0.0), np.zeros_like(hi)])
        ax.errorbar(
            mus, hi, yerr=err, fmt="o-", color=f"C{i}", capsize=3,
            label=f"ours, {d['settings']['boards']} boards: smallest stable retraction",
        )  # fmt: skip
    if allmu:  # through the smallest mu's smallest stable retraction
        m = np.array(sorted(set(allmu + pm)))
        ref = min((r for d in sets for r in d["results"] if r["stability_margin_m"]), key=lambda r: r["mu"])
        ax.loglog(
            m, ref["stability_margin_m"] * np.sqrt(m / ref["mu"]), ":", color="k", label="sqrt(mu) guide"
        )
    ax.set_xlabel("mu")
    ax.set_ylabel("[m]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Stacked books: stability margin vs mu")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_margin(args, rows: list[dict], t0: float) -> str:
    """Write ``stability_margin_n<boards>.json`` (merged with an earlier run's other mus at the same settings) and
    the table and plot over every ``stability_margin_n*.json`` in ``args.out``; returns the table."""
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    path = args.out / f"stability_margin_n{args.boards}.json"
    rows = list(rows)
    commit = git_revision()
    if path.exists():  # keep the other mus of an earlier run with the same settings at the same commit
        old = json.loads(path.read_text())
        same = ("mu", "out", "threads")
        if old.get("cfd_torch_commit") == commit and {
            k: v for k, v in old["settings"].items() if k not in same
        } == {k: v for k, v in settings.items() if k not in same}:
            done = {r["mu"] for r in rows}
            rows += [r for r in old["results"] if r["mu"] not in done]
        else:
            tqdm.write(f"{path}: replaced (its settings or commit, {old.get('cfd_torch_commit')}, differ)")
    rows.sort(key=lambda r: -r["mu"])
    settings["mu"] = [r["mu"] for r in rows]
    out = {
        "settings": settings,
        "definitions": {
            "stability_margin_m": "smallest retraction r L / 2 [m] at which the run is stable (bracket top)",
            "bracket_m": "(largest unstable, smallest stable) retraction [m]",
            "estimate_m": "geometric mean of the bracket; used for the log-log slope",
            "rest_margin_at_stable": "mean rest surface gap over the interfaces in the smallest stable run",
        },
        "paper_margin": {f"{m:.0e}": v[0] for m, v in PAPER.items()},
        "results": rows,
        "loglog_slope": loglog_slope(rows),
        "total_wall_s": time.perf_counter() - t0,
        "machine": {
            "platform": platform.platform(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
        },
        "cfd_torch_commit": commit,
    }
    path.write_text(json.dumps(out, indent=1, allow_nan=False))
    sets = [json.loads(f.read_text()) for f in args.out.glob("stability_margin_n*.json")]
    sets.sort(key=lambda d: d["settings"]["boards"])
    md = margin_md(sets)
    (args.out / "stability_margin.md").write_text(md)
    margin_plot(sets, args.out / "stability_margin.png")
    return md


def main_bisect(args) -> None:
    t0 = time.perf_counter()
    rows = []
    md = ""
    for mu in tqdm(args.mu, desc="mu (bisect retract)"):
        rows.append(bisect_retract(args, mu))
        r = rows[-1]
        tqdm.write(
            f"mu={mu:.0e}: stability margin {fmt(r['stability_margin_m'])} m, bracket {r['bracket_m']}, "
            f"{len(r['probes'])} probes, {r['wall_s']:.0f} s"
        )
        md = write_margin(args, rows, t0)  # after every mu, so that a cut-short run keeps what it has
    print(md)


def main() -> None:
    args = parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.bisect_retract:
        main_bisect(args)
        return
    t0 = time.perf_counter()
    results = []
    for mu in tqdm(args.mu, desc="mu"):
        r, poses = run(args, mu)
        results.append(r)
        if args.gif:
            write_stack_gif(args, mu, poses, args.out / f"stacked_books_mu{mu:.0e}.gif")
        tqdm.write(
            f"mu={mu:.0e}: stable={r['stable']} ({r['reason']}), margin {r['margin']:.3e} m, force error "
            f"{r['force_error']:.3e} N, {r['steps']} steps, {r['wall_s']:.0f} s"
        )
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    out = {
        "settings": settings,
        "definitions": {
            "stable": "rest (largest vertex speed < rest_speed for rest_time, t >= t_min) before t_max; fails on a "
            "board tilted > tilt_fail on the body below, a sub-stack's centre of mass > topple_fail beyond its "
            "supporting edge, or a StepError (after sub-stepping)",
            "margin": "mean over interfaces of the minimum vertex-face distance between the touching bodies",
            "force_error": "max over interfaces of |sum of forces of bodies below on bodies above, except the "
            "touching pair| (deviation of the interface force from rigid statics)",
        },
        "paper": {
            f"{m:.0e}": {"margin": v[0], "force_error": v[1], "stable": v[2]} for m, v in PAPER.items()
        },
        "results": results,
        "total_wall_s": time.perf_counter() - t0,
        "machine": {
            "platform": platform.platform(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
        },
        "cfd_torch_commit": git_revision(),
        "cfd_torch_file": cfd_torch.__file__,
    }
    (args.out / "stacked_books.json").write_text(json.dumps(out, indent=1, allow_nan=False))
    md = table_md(results, args) + f"\nTotal wall time {out['total_wall_s']:.0f} s.\n"
    (args.out / "stacked_books.md").write_text(md)
    plot(results, args.out / "stacked_books.png")
    print(md)


if __name__ == "__main__":
    main()
