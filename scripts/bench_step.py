"""Cost of one simulator step: forward, forward + backward, Newton iterations, optionally against an older revision.

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

- forward: ``steps`` consecutive steps ``step(scene, state, return_info=True)``. Timed: the forward solve, the
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
same case in a subprocess with PYTHONPATH pointing at that checkout (its API may be the one before ``StepInfo``:
``step(..., info=dict)``; the forward time compared is then the ``step()`` call's wall time on both sides). The
table gives per case the median forward and backward ms of both and their ratio (this / REV), and whether the
results agree: Newton iterations per step, end poses of the forward pass, gradient norms.

The machine may be shared: the load average is recorded at the start and end of every scene. ``--threads`` sets
torch's intra-op threads (default: torch's own default); the numba kernels use ``--numba-threads``.

Writes ``<out>/bench_step.json`` (every per-step figure), ``<out>/table.md`` (printed too) and
``<out>/bench_step_breakdown.png`` (forward and backward per case; ``--replot`` rewrites the last two from the JSON).

    python scripts/bench_step.py --out results/bench_step --profile       # ~10 min on 2 shared cores
    python scripts/bench_step.py --out results/bench_step_quick --quick   # a few minutes
    python scripts/bench_step.py --quick --cases boxes --baseline e5289f1 # this revision against e5289f1
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
from dataclasses import asdict, dataclass, field, is_dataclass
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

import cfd_torch  # noqa: E402
from cfd_torch import Scene, State, StepError, rigid_body, step  # noqa: E402

F64 = torch.float64
# the authors' C++ on the resting 320-face ball on a 12-triangle box, double precision: per step, per backward
CPP_DOUBLE_S = 0.57
CPP_DOUBLE_BACKWARD_S = 0.06
TARGET_S = CPP_DOUBLE_S / 20.0  # 20x faster than their double-precision step: 28.5 ms
# step(..., return_info=True) -> (State, StepInfo); revisions before it fill a dict: step(..., info=dict)
HAS_STEPINFO = hasattr(cfd_torch, "StepInfo")
STATS = ("newton_iters", "contact_evals", "leaf_pairs", "node_pairs", "friction_contacts", "substeps")


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


# ------------------------------------------------------------------------------------------------ passes
def timed_step(scene: Scene, state: State) -> tuple[State, dict]:
    """One step; returns the next state and a row: ``call_s`` (wall time of the ``step()`` call), ``total_s`` (the
    forward solve's time from the StepInfo; the call's time on revisions without StepInfo) and the statistics."""
    t0 = time.perf_counter()
    if HAS_STEPINFO:
        nxt, si = step(scene, state, return_info=True)
        call = time.perf_counter() - t0
        info = {k: getattr(si, k) for k in STATS}
        solve = si.seconds
    else:
        info = {}
        nxt = step(scene, state, info=info)
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


def forward_pass(case: Case, state: State, steps: int, desc: str) -> tuple[list[dict], State]:
    rows = []
    for _ in tqdm(range(steps), desc=desc, leave=False):
        state, row = timed_step(case.scene, state)
        rows.append(row)
    return rows, state


def backward_pass(case: Case, state: State, steps: int, w: torch.Tensor, desc: str) -> list[dict]:
    rows = []
    for _ in tqdm(range(steps), desc=desc, leave=False):
        q = state.q.clone().requires_grad_()
        out, fwd = timed_step(case.scene, State(q, state.q_prev))
        loss = (w * out.q).sum()
        t0 = time.perf_counter()
        loss.backward()
        bwd = {"total_s": time.perf_counter() - t0, "grad_norm": float(q.grad.norm())}
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
        for _ in tqdm(range(case.warmup), desc=f"{case.name} warm-up", leave=False):
            state = step(case.scene, state)
        res["warmup_s"] = time.perf_counter() - t0
        start = _detach(state)
        res["max_speed_start"] = _max_speed(case, start)
        fwd, end = forward_pass(case, start, case.steps, f"{case.name} forward")
        res["max_speed_end"] = _max_speed(case, end)
        res["velocity_end"] = ((end.q - end.q_prev)[case.scene.dynamic] / case.scene.dt).tolist()
        res["q_end"] = end.q.tolist()
        w = torch.randn(start.q.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
        # the first backward compiles kernels: one untimed step
        backward_pass(case, start, 1, w, f"{case.name} fwd+bwd warm-up")
        bwd = backward_pass(case, start, case.steps, w, f"{case.name} fwd+bwd")
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


# ------------------------------------------------------------------------------------------------ baseline
class Baseline:
    """An older revision of the package checked out in a temporary git worktree; runs one case at a time in a
    subprocess (this script in worker mode, PYTHONPATH at the checkout)."""

    def __init__(self, rev: str) -> None:
        root = Path(__file__).resolve().parent.parent
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
        spec = Path(self._tmp.name) / "spec.json"
        result = Path(self._tmp.name) / f"{case_name}.json"
        spec.write_text(json.dumps({"args": _jsonable(vars(args)), "case": case_name, "result": str(result)}))
        path = [str(self.dir)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(path))
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--worker", str(spec)], cwd=self.dir, env=env,
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
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.numba_threads:
        numba.set_num_threads(args.numba_threads)
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

    qa, qb = torch.tensor(head["q_end"]), torch.tensor(base["q_end"])
    ga, gb = torch.tensor(head["grad_norms"]), torch.tensor(base["grad_norms"])
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


def _jsonable(d: dict) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


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
        "Forward + backward: forward with q requiring grad, backward of (w * q_next).sum()",
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
    if "ball_faces" in m and "box_faces" in m:
        return f"{m['ball_faces']} + {m['box_faces']}"
    if "ground_faces" in m and "ball_faces" in m:
        return f"16 x {m['ball_faces']} + {m['ground_faces']}"
    if "boxes" in m:
        return f"{m['boxes']} x {m['box_faces']} + {m['ground_faces']}"
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
    ap.add_argument(
        "--only", nargs="+", default=None, metavar="NAME",
        help="run only these case names (e.g. ball_box_mu0 boxes4) of the selected --cases",
    )  # fmt: skip
    ap.add_argument(
        "--baseline", metavar="REV", default=None,
        help="also time git revision REV of the package, case by case in a subprocess (e.g. e5289f1)",
    )  # fmt: skip
    ap.add_argument("--profile", action="store_true", help="cProfile + torch.profiler tables per case")
    ap.add_argument("--profile-steps", type=int, default=5)
    ap.add_argument(
        "--replot", action="store_true", help="rewrite table.md and the plot from <out>/bench_step.json"
    )
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)  # a --baseline subprocess
    args = ap.parse_args()
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
            "args": _jsonable(vars(args)),
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
    cases = make_cases(args)
    if args.only:
        cases = [c for c in cases if c.name in args.only]
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


def _threading_layer() -> str | None:
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel numba kernel ran
        return None


if __name__ == "__main__":
    main()
