"""Cost of one simulator step: forward, forward + backward, breakdown, Newton iterations.

Scenes (float64, dt = 0.01, the Scene defaults for mu, margin, eps, newton_tol unless stated):

1. billiards: 16 balls (icosphere subdivision 2 = 320 faces, radius ``--ball-radius``), a 15-ball triangle rack
   (neighbours 2 mm apart) and a cue ball moving at ``--cue-speed`` m/s toward the rack's apex, on a static
   12-triangle box ground refined with ``max_edge`` = ``--ground-edge-factor`` x the ball's mean edge length. The
   timed window covers the cue ball's approach and its impact on the rack.
2. boxes: 4 boxes (trimesh.creation.box, 12 triangles each, 0.2 x 0.2 x 0.1) stacked 2 mm apart on a 12-triangle box
   ground, timed after they have landed.
3. ball on box: one 320-face ball (radius 0.5) resting on a 12-triangle box (4 x 4 x 0.5; the configuration of
   ``bench_contact.py`` section 4), the box as-is and refined with ``max_edge`` = ``--ground-edge-factor`` x the
   ball's mean edge length, each with friction off (0) and on (``--friction``). Timed after the ball has settled.

Every scene first runs ``warmup`` untimed steps (numba compilation, landing), then two passes from the same state:

- forward: ``steps`` consecutive steps, each timed, with ``info`` (Newton iterations, contact evaluations, leaf and
  node pairs).
- forward + backward: one untimed warm-up step with backward, then ``steps`` steps from the same start again, each
  with ``q = state.q.clone().requires_grad_()``, ``step`` (timed: "forward with grad") and ``(w * q_next).sum()
  .backward()`` for a fixed random w (timed separately: "backward").

Breakdown (wrappers installed by this script only, around what ``cfd_torch.stepper`` calls): contact =
``_Problem.contact`` (BSH traversal, leaf-pair solves, scatter; split by derivative order: 2 = value + gradient +
Hessian, 0 = value only), friction = ``lagged_friction`` + ``friction_terms``, linear solves =
``torch.linalg.cholesky_ex`` + ``torch.cholesky_solve`` + ``torch.linalg.solve``, other = total - those. Each is
summed per step; the tables give medians over the timed steps (medians of the parts do not add up exactly).

The machine may be shared: the load average is recorded at the start and end of every scene. ``--threads`` sets
torch's intra-op threads (default: torch's own default); the numba kernels use ``--numba-threads``.

Writes ``<out>/bench_step.json`` (every per-step figure), ``<out>/table.md`` (printed too) and
``<out>/bench_step_breakdown.png`` (``--replot`` rewrites the last two from the JSON); ``--profile`` adds cProfile
and torch.profiler tables per scene (``<out>/profile_<case>.txt``).

    python scripts/bench_step.py --out results/bench_step --profile       # ~10 min on 2 shared cores
    python scripts/bench_step.py --out results/bench_step_quick --quick   # a few minutes
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
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cfd_torch.stepper as stepper  # noqa: E402
from cfd_torch import Scene, State, StepError, rigid_body, step  # noqa: E402

F64 = torch.float64
# the authors' C++ on the resting 320-face ball on a 12-triangle box, double precision: per step, per backward
CPP_DOUBLE_S = 0.57
CPP_DOUBLE_BACKWARD_S = 0.06
TARGET_S = CPP_DOUBLE_S / 20.0  # 20x faster than their double-precision step: 28.5 ms
CATEGORIES = ("contact", "friction", "solve", "other")


# ------------------------------------------------------------------------------------------------ scenes
@dataclass
class Case:
    """A scene with its start state and how many steps to run before and while timing."""

    name: str
    scene: Scene
    state: State
    warmup: int
    steps: int
    meta: dict = field(default_factory=dict)


def _ball(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=2, radius=radius)


def _mean_edge(mesh: trimesh.Trimesh) -> float:
    return float(mesh.edges_unique_length.mean())


def billiards(args) -> Case:
    """16 balls: a 15-ball rack (rows of 1..5 along +x, 2 mm apart) and a cue ball on the -x side moving at +x."""
    r, gap = args.ball_radius, 2e-3
    ball = _ball(r)
    max_edge = args.ground_edge_factor * _mean_edge(ball)
    ground = trimesh.creation.box(extents=(24 * r, 12 * r, 2 * r))  # top face at z = r
    bodies = [rigid_body(ground, kind="static", max_edge=max_edge)]
    ball_body = rigid_body(ball)
    z = r - float(ball.vertices[:, 2].min()) + gap  # lowest vertex gap above the ground's top face
    d = 2 * r + gap  # centre distance of touching neighbours in the rack
    apex = 2 * r
    poses = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]
    for row in range(5):
        for k in range(row + 1):
            poses.append([apex + row * d * math.sqrt(3) / 2, (k - row / 2) * d, z, 0.0, 0.0, 0.0])
    cue_x = apex - d - args.cue_speed * 0.01 * args.cue_lead_steps
    poses.append([cue_x, 0.0, z, 0.0, 0.0, 0.0])
    bodies += [ball_body] * 16
    vel = torch.zeros(len(poses), 6, dtype=F64)
    vel[-1, 0] = args.cue_speed
    scene = Scene(bodies)
    state = scene.initial_state(torch.tensor(poses, dtype=F64), vel)
    meta = {
        "ball_radius": r, "ball_faces": ball_body.bsh.num_faces, "ground_faces": bodies[0].bsh.num_faces,
        "ground_max_edge": max_edge, "ground_extents": [24 * r, 12 * r, 2 * r], "rack_gap": gap,
        "cue_speed": args.cue_speed, "cue_start_x": cue_x,
        "note": f"the cue ball reaches the rack after about {args.cue_lead_steps} steps",
    }  # fmt: skip
    return Case("billiards16", scene, state, args.warmup_billiards, args.steps_billiards, meta)


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


def make_cases(args) -> list[Case]:
    cases = []
    for name in args.cases:
        if name == "billiards":
            cases.append(billiards(args))
        elif name == "boxes":
            cases.append(boxes(args))
        elif name == "ball":
            for refined in (False, True):
                for mu_f in (0.0, args.friction):
                    cases.append(ball_on_box(args, refined, mu_f))
    return cases


# ------------------------------------------------------------------------------------------------ timers
class Timers:
    """Wall time and call counts per key, accumulated by wrapped functions."""

    def __init__(self) -> None:
        self.t: dict[str, float] = defaultdict(float)
        self.n: dict[str, int] = defaultdict(int)
        self.hooks: list[str] = []

    def reset(self) -> None:
        self.t.clear()
        self.n.clear()

    def wrap(self, key, fn):
        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.t[key] += time.perf_counter() - t0
                self.n[key] += 1

        return timed

    def wrap_contact(self, fn):
        """``_Problem.contact(self, poses, order)``: keyed by derivative order."""

        def timed(prob, *a, **k):
            order = k.get("order", a[1] if len(a) > 1 else "?")
            t0 = time.perf_counter()
            try:
                return fn(prob, *a, **k)
            finally:
                self.t[f"contact_o{order}"] += time.perf_counter() - t0
                self.n[f"contact_o{order}"] += 1

        return timed

    def snapshot(self) -> dict:
        """Per-category seconds (contact, friction, solve) and the raw keys with their call counts."""
        cat = {
            "contact": sum(v for k, v in self.t.items() if k.startswith("contact")),
            "friction": sum(v for k, v in self.t.items() if k.startswith("friction")),
            "solve": sum(v for k, v in self.t.items() if k.startswith("solve")),
        }
        return {**cat, "raw_s": dict(self.t), "calls": dict(self.n)}


@contextmanager
def instrumented(timers: Timers):
    """Install the timing wrappers on what the stepper calls; restore the originals on exit."""
    patches = []  # (owner, attribute, original)

    def patch(owner, attr, make):
        orig = getattr(owner, attr, None)
        if orig is None:
            return
        patches.append((owner, attr, orig))
        setattr(owner, attr, make(orig))
        timers.hooks.append(f"{getattr(owner, '__name__', owner)}.{attr}")

    timers.hooks = []
    patch(stepper._Problem, "contact", timers.wrap_contact)
    patch(stepper, "lagged_friction", lambda f: timers.wrap("friction_lagged", f))
    patch(stepper, "friction_terms", lambda f: timers.wrap("friction_terms", f))
    patch(torch.linalg, "cholesky_ex", lambda f: timers.wrap("solve_cholesky_ex", f))
    patch(torch, "cholesky_solve", lambda f: timers.wrap("solve_cholesky_solve", f))
    patch(torch.linalg, "solve", lambda f: timers.wrap("solve_linalg_solve", f))
    try:
        yield timers
    finally:
        for owner, attr, orig in reversed(patches):
            setattr(owner, attr, orig)


# ------------------------------------------------------------------------------------------------ passes
def _max_speed(case: Case, state: State) -> float:
    """Largest |(q - q_prev) / dt| entry of the dynamic bodies [m/s or rad/s]."""
    v = (state.q - state.q_prev)[case.scene.dynamic] / case.scene.dt
    return float(v.abs().max())


def _detach(state: State) -> State:
    return State(state.q.detach(), state.q_prev.detach())


def _record(total: float, timers: Timers, info: dict) -> dict:
    snap = timers.snapshot()
    row = {"total_s": total, **{k: snap[k] for k in ("contact", "friction", "solve")}}
    row["other"] = total - row["contact"] - row["friction"] - row["solve"]
    row.update({"raw_s": snap["raw_s"], "calls": snap["calls"]})
    row["info"] = {k: (v if isinstance(v, (int, float)) else str(v)) for k, v in info.items()}
    return row


def forward_pass(case: Case, state: State, steps: int, timers: Timers, desc: str) -> tuple[list[dict], State]:
    rows = []
    for _ in tqdm(range(steps), desc=desc, leave=False):
        info: dict = {}
        timers.reset()
        t0 = time.perf_counter()
        state = step(case.scene, state, info=info)
        rows.append(_record(time.perf_counter() - t0, timers, info))
    return rows, state


def backward_pass(
    case: Case, state: State, steps: int, timers: Timers, w: torch.Tensor, desc: str
) -> list[dict]:
    rows = []
    for _ in tqdm(range(steps), desc=desc, leave=False):
        info: dict = {}
        q = state.q.clone().requires_grad_()
        timers.reset()
        t0 = time.perf_counter()
        out = step(case.scene, State(q, state.q_prev), info=info)
        fwd = _record(time.perf_counter() - t0, timers, info)
        loss = (w * out.q).sum()
        timers.reset()
        t0 = time.perf_counter()
        loss.backward()
        bwd = _record(time.perf_counter() - t0, timers, {})
        bwd["grad_norm"] = float(q.grad.norm())
        rows.append({"forward": fwd, "backward": bwd})
        state = _detach(out)
    return rows


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def summarise(rows: list[dict]) -> dict:
    """Medians over the timed steps of the total, the parts, Newton iterations and traversal counts."""
    s = {"total_s": _median(rows, "total_s")} | {f"{c}_s": _median(rows, c) for c in CATEGORIES}
    s["min_s"] = min(r["total_s"] for r in rows)
    s["max_s"] = max(r["total_s"] for r in rows)
    s["mean_s"] = statistics.fmean(r["total_s"] for r in rows)
    infos = [r["info"] for r in rows if r["info"]]
    if infos:
        for k in ("newton_iters", "contact_evals", "leaf_pairs", "node_pairs", "friction_contacts"):
            if all(k in i for i in infos):
                s[f"{k}_median"] = statistics.median(i[k] for i in infos)
        if all("contact_evals" in i and i["contact_evals"] for i in infos):
            s["leaf_pairs_per_eval"] = statistics.median(i["leaf_pairs"] / i["contact_evals"] for i in infos)
            s["node_pairs_per_eval"] = statistics.median(i["node_pairs"] / i["contact_evals"] for i in infos)
        s["newton_iters_all"] = [i.get("newton_iters") for i in infos]
    for key in ("contact_o2", "contact_o1", "contact_o0"):
        if any(key in r["raw_s"] for r in rows):
            s[f"{key}_s"] = statistics.median(r["raw_s"].get(key, 0.0) for r in rows)
            s[f"{key}_calls"] = statistics.median(r["calls"].get(key, 0) for r in rows)
    return s


def run_case(case: Case, args, timers: Timers) -> dict:
    res: dict = {"meta": case.meta, "bodies": case.scene.num_bodies, "body_pairs": int(len(case.scene.pairs))}
    res["scene"] = {
        k: getattr(case.scene, k)
        for k in ("dt", "mu", "margin", "eps", "split", "friction", "newton_tol", "max_newton_iter")
    }
    res["loadavg_start"] = os.getloadavg()
    state = case.state
    try:
        t0 = time.perf_counter()
        with instrumented(timers):
            for _ in tqdm(range(case.warmup), desc=f"{case.name} warm-up", leave=False):
                state = step(case.scene, state)
            res["warmup_s"] = time.perf_counter() - t0
            start = _detach(state)
            res["max_speed_start"] = _max_speed(case, start)
            fwd, end = forward_pass(case, start, case.steps, timers, f"{case.name} forward")
            res["max_speed_end"] = _max_speed(case, end)
            res["velocity_end"] = ((end.q - end.q_prev)[case.scene.dynamic] / case.scene.dt).tolist()
            w = torch.randn(start.q.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
            # the first backward compiles kernels: one untimed step
            backward_pass(case, start, 1, timers, w, f"{case.name} fwd+bwd warm-up")
            bwd = backward_pass(case, start, case.steps, timers, w, f"{case.name} fwd+bwd")
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
    pr.enable()
    for _ in range(n):
        s = step(case.scene, s)
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(20)
    pstats.Stats(pr, stream=buf).sort_stats("cumulative").print_stats(25)
    s = state
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            s = step(case.scene, s)
    w = torch.randn(state.q.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    s, pr_b = state, cProfile.Profile()
    for _ in range(n):
        q = s.q.clone().requires_grad_()
        out = step(case.scene, State(q, s.q_prev))
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
        f", at end {_load(out['meta']['loadavg_end'])} (2 cores). Target: < {_ms(TARGET_S)} ms per step (20x the "
        f"authors' C++ double precision, {_ms(CPP_DOUBLE_S, 0)} ms / step, {_ms(CPP_DOUBLE_BACKWARD_S, 0)} ms / "
        "backward, for ball_box).",
        "",
        "Forward (no grad): total and breakdown",
        "",
        "| case | faces | fwd | (min) | contact | (o2 / o0 calls) | friction | solves | other | Newton it "
        "| evals/step | leaf pairs/eval | node pairs/eval | < 28.5 ms | vs C++ 570 ms | load |",
        "|" + "---|" * 16,
    ]
    for name, r in out["cases"].items():
        faces = _faces(r)
        if "error" in r:
            lines.append(f"| {name} | {faces} | failed: {r['error'][:120]} |" + " |" * 13)
            continue
        f = r["forward"]
        calls = f"{_n(f.get('contact_o2_calls'))} / {_n(f.get('contact_o0_calls'))}"
        lines.append(
            f"| {name} | {faces} | {_ms(f['total_s'])} | {_ms(f['min_s'])} | {_ms(f['contact_s'])} | {calls} "
            f"| {_ms(f['friction_s'])} "
            f"| {_ms(f['solve_s'], 2)} | {_ms(f['other_s'])} | {_n(f.get('newton_iters_median'))} "
            f"| {_n(f.get('contact_evals_median'))} | {_n(f.get('leaf_pairs_per_eval'))} "
            f"| {_n(f.get('node_pairs_per_eval'))} | {'yes' if f['total_s'] < TARGET_S else 'no'} "
            f"| {CPP_DOUBLE_S / f['total_s']:.2f}x | {_load(r['loadavg_start'])} |"
        )
    lines += [
        "",
        "Forward + backward: forward with q requiring grad, backward of (w * q_next).sum()",
        "",
        "| case | fwd (grad) | bwd | bwd solves | bwd friction | bwd other | fwd + bwd | bwd vs C++ 60 ms |",
        "|" + "---|" * 8,
    ]
    for name, r in out["cases"].items():
        if "error" in r:
            continue
        f, b = r["forward_with_grad"], r["backward"]
        lines.append(
            f"| {name} | {_ms(f['total_s'])} | {_ms(b['total_s'], 2)} | {_ms(b['solve_s'], 2)} "
            f"| {_ms(b['friction_s'], 2)} | {_ms(b['other_s'], 2)} | {_ms(r['forward_backward_s'])} "
            f"| {CPP_DOUBLE_BACKWARD_S / b['total_s']:.1f}x |"
        )
    lines += [
        "",
        "contact = `_Problem.contact` (o2: value + gradient + Hessian, o0: value only, median calls per step); "
        "friction = `lagged_friction` + `friction_terms`; solves = `cholesky_ex` + `cholesky_solve` + "
        "`linalg.solve`; other = total - those (body terms, Hessian assembly, Python). Medians of the parts need "
        "not add up to the median total.",
    ]
    return "\n".join(lines)


def _load(x) -> str:
    return "/".join(f"{v:.1f}" for v in x)


def _faces(r: dict) -> str:
    m = r["meta"]
    if "ball_faces" in m and "box_faces" in m:
        return f"{m['ball_faces']} + {m['box_faces']}"
    if "ground_faces" in m and "ball_faces" in m:
        return f"16 x {m['ball_faces']} + {m['ground_faces']}"
    if "boxes" in m:
        return f"{m['boxes']} x {m['box_faces']} + {m['ground_faces']}"
    return "?"


def plot(out: dict, path: Path) -> None:
    cases = {k: r for k, r in out["cases"].items() if "error" not in r}
    if not cases:
        return
    n = len(cases)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.4 * rows), squeeze=False)
    colors = {"contact": "C0", "friction": "C2", "solve": "C3", "other": "C7"}
    for ax, (name, r) in zip(axes.flat, cases.items(), strict=False):
        for x, key in ((0, "forward"), (1, "backward")):
            bottom = 0.0
            for c in CATEGORIES:
                h = 1e3 * max(r[key][f"{c}_s"], 0.0)
                ax.bar(x, h, bottom=bottom, color=colors[c], label=c if x == 0 else None, width=0.6)
                bottom += h
            ax.annotate(f"{1e3 * r[key]['total_s']:.1f}", (x, bottom), ha="center", va="bottom", fontsize=8)
        ax.axhline(1e3 * TARGET_S, ls="--", lw=0.8, color="k", label="28.5 ms target")
        ax.set_xticks([0, 1], ["forward", "backward"])
        ax.set_title(name, fontsize=9)
        ax.set_ylabel("ms per step (medians)")
        ax.set_ylim(
            0, 1.15 * max(1e3 * r["forward"]["total_s"], 1e3 * r["backward"]["total_s"], 1e3 * TARGET_S)
        )
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(
        f"step breakdown (torch threads {out['meta']['torch_threads']}, load {_load(out['meta']['loadavg_start'])})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _source_hash() -> str:
    """sha256 of the library's sources (the working tree may be dirty while the benchmark runs)."""
    h = hashlib.sha256()
    for p in sorted(Path(stepper.__file__).parent.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


CASES = ("billiards", "boxes", "ball")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/bench_step"))
    ap.add_argument("--quick", action="store_true", help="fewer warm-up and timed steps (a smoke test)")
    ap.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    ap.add_argument(
        "--steps", type=int, default=None, help="timed steps per ball/boxes pass (default 20, quick 3)"
    )
    ap.add_argument(
        "--billiards-steps", type=int, default=None, help="timed billiards steps (default 12, quick 3)"
    )
    ap.add_argument(
        "--threads", type=int, default=None, help="torch intra-op threads (default: torch's default)"
    )
    ap.add_argument(
        "--numba-threads", type=int, default=None, help="numba threads (default: numba's default)"
    )
    ap.add_argument("--ball-radius", type=float, default=0.05, help="billiard ball radius [m]")
    ap.add_argument("--cue-speed", type=float, default=2.0, help="[m/s]")
    ap.add_argument(
        "--cue-lead-steps", type=int, default=4, help="steps before the cue ball reaches the rack"
    )
    ap.add_argument("--num-boxes", type=int, default=4)
    ap.add_argument(
        "--ground-edge-factor",
        type=float,
        default=2.0,
        help="refined ground: max_edge = this x ball mean edge",
    )
    ap.add_argument("--friction", type=float, default=0.5, help="friction coefficient of the 'on' ball case")
    ap.add_argument("--profile", action="store_true", help="cProfile + torch.profiler tables per case")
    ap.add_argument("--profile-steps", type=int, default=5)
    ap.add_argument(
        "--replot", action="store_true", help="rewrite table.md and the plot from <out>/bench_step.json"
    )
    args = ap.parse_args()
    if args.replot:
        out = json.loads((args.out / "bench_step.json").read_text())
        text = tables(out)
        (args.out / "table.md").write_text(text + "\n")
        plot(out, args.out / "bench_step_breakdown.png")
        print(text)
        return
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.numba_threads:
        numba.set_num_threads(args.numba_threads)
    steps = args.steps or (3 if args.quick else 20)
    args.steps_ball = args.steps_boxes = steps
    args.steps_billiards = args.billiards_steps or (3 if args.quick else 12)
    args.warmup_ball = 10 if args.quick else 30  # the ball lands and settles
    args.warmup_boxes = 10 if args.quick else 20  # the stack lands (2 Newton iterations per step after ~10)
    args.warmup_billiards = 2  # contact with the ground; the cue ball then approaches and hits the rack
    args.out.mkdir(parents=True, exist_ok=True)

    out: dict = {
        "meta": {
            "torch": torch.__version__, "numba": numba.__version__, "numpy": np.__version__,
            "trimesh": trimesh.__version__, "python": platform.python_version(),
            "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
            "git": git_revision(), "cfd_torch_sources_sha256": _source_hash(), "quick": args.quick,
            "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
            "loadavg_start": os.getloadavg(),
            "target_s": TARGET_S, "cpp_double_step_s": CPP_DOUBLE_S, "cpp_double_backward_s": CPP_DOUBLE_BACKWARD_S,
        },
        "timed": {
            "forward": "wall time of step(scene, state, info=info) (state not requiring grad)",
            "forward_with_grad": "wall time of step() with state.q requiring grad",
            "backward": "wall time of (w * q_next).sum().backward(), w fixed random (N, 6)",
            "contact": "cfd_torch.stepper._Problem.contact (traversal + leaf solves + scatter), all orders",
            "friction": "cfd_torch.stepper.lagged_friction + friction_terms",
            "solve": "torch.linalg.cholesky_ex + torch.cholesky_solve + torch.linalg.solve",
            "other": "total - contact - friction - solve",
        },
        "cases": {},
    }  # fmt: skip
    timers = Timers()
    cases = make_cases(args)
    for case in tqdm(cases, desc="scenes"):
        out["cases"][case.name] = run_case(case, args, timers)
        out["meta"]["hooks"] = timers.hooks
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


def _threading_layer() -> str | None:
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel numba kernel ran
        return None


if __name__ == "__main__":
    main()
