"""Run time against trajectory error of the simulator step, as a function of newton_tol, pair_tol and dt.

What is measured. Two scenes, each simulated forward only (``torch.no_grad()``, float64) with one setting changed at
a time from the library's defaults (``SolverConfig.newton_tol`` 1e-9, ``ContactConfig.pair_tol`` 1e-12, ``Scene``'s
dt 0.01 s; read from the library, not written here):

- newton_tol in {1e-5, ..., 1e-11}, pair_tol in {1e-6, 1e-8, 1e-10, 1e-12, 1e-14}, dt in {0.02, 0.01, 0.005,
  0.0025} s (``--quick``: two values each, a few steps).
- Per run: the wall time of every step (``StepInfo.seconds``, the forward solve; median reported, and median / dt =
  wall time per simulated second, the cost that makes different dt comparable), Newton iterations per step
  (median, mean, max) and two errors against a reference, of the dynamic bodies: the distance between the centres of
  mass [m] and the angle between the orientations [rad] (``2 asin(|R - R_ref|_F / (2 sqrt 2))``, exact for small
  angles too).

  * trajectory error: the run from the common start, compared at each of its steps; the largest over time and
    bodies (and the time it occurs, and the value at the last step).
  * one-step error: from every state of the reference at the run's step times, one step with the run's settings,
    against the reference one run step later; the largest and the median over the steps (what one step adds,
    without the amplification along the trajectory; the median also without the one step that lands in another
    local minimum, below).

- Reference of the tolerance sweeps: the same dt (0.01) at newton_tol 1e-12 and pair_tol 1e-14 (if 1e-12 raises,
  1e-11, recorded). Reference of the dt sweep: those tolerances at dt = (smallest swept dt) / ``--ref-dt-factor``
  (4: 0.000625 s), compared at every step time of the run (each is a reference step time). The dt error is the
  discretisation error of implicit Euler (first order) and dominates the tolerance errors by orders of magnitude.
- Round-off floor: the tolerance reference again from a start moved by ``--perturb`` (1e-15) x N(0, 1) in every
  pose coordinate of the dynamic bodies; its trajectory error is what no tolerance can go below. In the break shot
  this floor is not small: the impact step's incremental potential has several local minima (the faceted balls'
  orientations), and which one Newton reaches changes with round-off-sized differences of the state.
- A run that raises ``StepError`` (or ``PairSolveError``) is a failure point: recorded with the step it failed at
  and the message, its error taken over the steps it completed.

Scenes (built by ``bench_step.py``'s builders, imported):

1. billiards: ``bench_step.billiards`` with ``--rack-rows`` rows (default 2: a rack of 3 balls + the cue ball, to
   keep the sweeps affordable on 2 shared cores; bench_step's billiards16 has 5 rows), 320-face balls of radius
   5 cm, cue ball at 2 m/s, frictionless refined table as in bench_step (the balls slide); 0.4 s (the balls land,
   the cue ball hits the apex at about 0.05 s, the rack breaks and the balls slide apart).
2. stack: ``bench_step.boxes``, ``--stack-boxes`` (4) boxes 0.2 x 0.2 x 0.1 (12 triangles) stacked on a static
   floor, friction 0.5; first settled for ``--settle`` (0.3 s) at the default settings (they start 2 mm apart),
   then every run starts at rest from those poses and runs 0.5 s.

Writes ``<out>/step_accuracy.json`` (every point, the references, the scenes, the git revision),
``<out>/step_accuracy.md`` (tables) and ``<out>/step_accuracy.png`` (error against wall time per simulated second,
one column per scene; rows: trajectory position error, trajectory rotation error, median one-step position error;
one curve per swept parameter, points labelled with the value, the defaults ringed, failures crossed and listed, the
round-off floor dashed). ``--replot`` rewrites the table and figure from the JSON.

    python scripts/step_accuracy.py --out results/step_accuracy           # about 15 min on 2 shared cores
    python scripts/step_accuracy.py --out results/step_accuracy_quick --quick   # about 1 min
    python scripts/step_accuracy.py --out results/step_accuracy --replot  # table and figure from the JSON
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _provenance import git_revision, json_args  # noqa: E402
from bench_step import billiards, boxes, parse_args  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch import ContactConfig, PairSolveError, Scene, SolverConfig, State, StepError, step  # noqa: E402
from cfd_torch.rotation import rotation_matrix  # noqa: E402

F64 = torch.float64
DEFAULTS = {
    "newton_tol": SolverConfig().newton_tol,
    "pair_tol": ContactConfig().pair_tol,
    "dt": inspect.signature(Scene.__init__).parameters["dt"].default,
}
TIGHT = {
    "newton_tol": (1e-12, 1e-11),
    "pair_tol": 1e-14,
}  # reference tolerances (newton_tol: first that runs)
SWEEPS = {
    "newton_tol": [1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11],
    "pair_tol": [1e-6, 1e-8, 1e-10, 1e-12, 1e-14],
    "dt": [0.02, 0.01, 0.005, 0.0025],
}
QUICK_SWEEPS = {"newton_tol": [1e-6, 1e-9], "pair_tol": [1e-8, 1e-12], "dt": [0.02, 0.01]}
STACK_FRICTION = 0.5


@dataclass
class Setup:
    """A scene at the default settings, its start (poses and velocities, (N, 6)) and the simulated time [s]."""

    name: str
    scene: Scene
    q0: torch.Tensor
    v0: torch.Tensor
    duration: float
    meta: dict = field(default_factory=dict)


def billiards_setup(rows: int, duration: float) -> Setup:
    case = billiards(parse_args(["--num-balls-rows", str(rows)]))
    v0 = (case.state.q - case.state.q_prev) / case.scene.dt
    meta = dict(case.meta, bench_step_case=case.name)
    return Setup("billiards", case.scene, case.state.q.clone(), v0, duration, meta)


def stack_setup(num_boxes: int, settle: float, duration: float) -> Setup:
    case = boxes(parse_args(["--num-boxes", str(num_boxes)]))
    scene = case.scene.replace(friction=STACK_FRICTION)
    state = case.state
    n = round(settle / scene.dt)
    with torch.no_grad():
        for _ in tqdm(range(n), desc="stack: settling", leave=False):
            state = step(scene, state)
    speed = float(((state.q - state.q_prev)[scene.dynamic] / scene.dt).abs().max())
    meta = dict(
        case.meta, bench_step_case=case.name, friction=STACK_FRICTION, settle_s=settle, settle_steps=n,
        settle_end_max_speed=speed, start="at rest at the settled poses",
    )  # fmt: skip
    return Setup("stack", scene, state.q.clone(), torch.zeros_like(state.q), duration, meta)


# ------------------------------------------------------------------------------------------------ runs
def simulate(setup: Setup, settings: dict, desc: str, perturb: float = 0.0) -> dict:
    """The setup run for its duration with ``settings`` (newton_tol, pair_tol, dt): poses and previous poses
    (T + 1, N, 6), per-step times and Newton iterations, and the failure if a step raised. ``perturb``: the dynamic
    bodies' start poses moved by this times a seeded standard normal (a round-off-sized change of the start)."""
    scene = setup.scene.replace(**settings)
    q0 = setup.q0.clone()
    if perturb:
        noise = torch.randn(q0.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
        q0[scene.dynamic] += perturb * noise[scene.dynamic]
    state = scene.initial_state(q0, setup.v0)
    steps = round(setup.duration / scene.dt)
    traj, prev, seconds, iters, failure = [state.q], [state.q_prev], [], [], None
    t0 = time.perf_counter()
    with torch.no_grad():
        for k in tqdm(range(steps), desc=desc, leave=False):
            try:
                state, info = step(scene, state, return_info=True)
            except (StepError, PairSolveError) as err:
                failure = {"step": k, "time": k * scene.dt, "error": f"{type(err).__name__}: {err}"}
                break
            traj.append(state.q)
            prev.append(state.q_prev)
            seconds.append(info.seconds)
            iters.append(int(info.newton_iters))
    return {
        "settings": dict(settings),
        "steps": steps,
        "steps_done": len(seconds),
        "traj": torch.stack(traj),
        "prev": torch.stack(prev),
        "seconds": seconds,
        "iters": iters,
        "wall_s": time.perf_counter() - t0,
        "failure": failure,
    }


def pose_errors(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance of the centres [m] and angle between the orientations [rad] of poses a and b (..., 6): (...)."""
    pos = (a[..., :3] - b[..., :3]).norm(dim=-1)
    dR = (rotation_matrix(a[..., 3:]) - rotation_matrix(b[..., 3:])).flatten(-2).norm(dim=-1)
    return pos, 2 * torch.asin((dR / (2 * math.sqrt(2))).clamp(max=1.0))


def _stride(dt: float, ref: dict) -> int:
    stride = dt / ref["settings"]["dt"]
    if abs(stride - round(stride)) > 1e-9:
        raise ValueError(f"the reference dt does not divide {dt}")
    return round(stride)


def trajectory_error(run: dict, ref: dict, dynamic: torch.Tensor) -> dict:
    """Largest and last position [m] and rotation [rad] errors of the dynamic bodies against ``ref`` over the run's
    step times (every one a step time of the reference, whose dt divides the run's)."""
    stride = _stride(run["settings"]["dt"], ref)
    n = min(len(run["traj"]), (len(ref["traj"]) - 1) // stride + 1)
    pos, rot = pose_errors(run["traj"][:n, dynamic], ref["traj"][: (n - 1) * stride + 1 : stride, dynamic])
    pos, rot = pos.amax(-1), rot.amax(-1)  # (T,) the worst body at each time
    return {
        "pos_err_max": float(pos.max()),
        "pos_err_max_time": int(pos.argmax()) * run["settings"]["dt"],
        "pos_err_final": float(pos[-1]),
        "rot_err_max": float(rot.max()),
        "rot_err_final": float(rot[-1]),
        "compared_steps": n - 1,
    }


def local_error(setup: Setup, settings: dict, ref: dict, desc: str) -> dict:
    """One-step error: from every state of the reference at the run's step times, one step with ``settings``,
    against the reference's state one run step later; the largest over the steps and dynamic bodies."""
    scene = setup.scene.replace(**settings)
    stride = _stride(settings["dt"], ref)
    traj, dyn = ref["traj"], scene.dynamic
    start = scene.initial_state(setup.q0, setup.v0)
    pos, rot, failed = [], [], 0
    with torch.no_grad():
        for k in tqdm(range((len(traj) - 1) // stride), desc=desc, leave=False):
            i = k * stride
            if stride == 1:
                q_prev = ref["prev"][i]
            else:
                q_prev = traj[i - stride] if i else start.q_prev
            try:
                nxt = step(scene, State(traj[i], q_prev))
            except (StepError, PairSolveError):
                failed += 1
                continue
            p, r = pose_errors(nxt.q[dyn], traj[i + stride, dyn])
            pos.append(float(p.max()))
            rot.append(float(r.max()))
    return {
        "local_pos_err_max": max(pos, default=None),
        "local_rot_err_max": max(rot, default=None),
        "local_pos_err_median": statistics.median(pos) if pos else None,
        "local_failed_steps": failed,
    }


def summary(run: dict) -> dict:
    s, it = run["seconds"], run["iters"]
    dt = run["settings"]["dt"]
    med = statistics.median(s) if s else None
    return {
        "settings": run["settings"],
        "ok": run["failure"] is None,
        "failure": run["failure"],
        "steps": run["steps"],
        "steps_done": run["steps_done"],
        "step_s_median": med,
        "step_s_mean": statistics.fmean(s) if s else None,
        "sim_s_per_s": med / dt
        if med is not None
        else None,  # wall time per simulated second, from the median
        "newton_iters_median": statistics.median(it) if it else None,
        "newton_iters_mean": statistics.fmean(it) if it else None,
        "newton_iters_max": max(it, default=None),
        "wall_s": run["wall_s"],
    }


def reference(setup: Setup, dt: float, label: str) -> dict:
    """The tight-tolerance run at ``dt``: newton_tol the first of TIGHT's that runs through."""
    last = None
    for tol in TIGHT["newton_tol"]:
        run = simulate(
            setup, {"newton_tol": tol, "pair_tol": TIGHT["pair_tol"], "dt": dt}, f"{setup.name}: {label}"
        )
        if run["failure"] is None:
            return run
        tqdm.write(f"{setup.name}: reference at newton_tol {tol:g} failed: {run['failure']['error']}")
        last = run
    raise RuntimeError(f"{setup.name}: no reference tolerance ran through: {last['failure']}")


def run_scene(setup: Setup, sweeps: dict, ref_dt_factor: int, perturb: float) -> dict:
    dynamic = setup.scene.dynamic
    out: dict = {"meta": setup.meta, "duration_s": setup.duration, "bodies": setup.scene.num_bodies}
    ref = reference(setup, DEFAULTS["dt"], "reference")
    ref_dt = min(sweeps["dt"]) / ref_dt_factor
    ref_small = reference(setup, ref_dt, f"reference dt={ref_dt:g}")
    out["reference"] = summary(ref)
    out["reference_dt"] = summary(ref_small)
    out["reference_dt"]["error_of_reference_vs_small_dt"] = trajectory_error(ref, ref_small, dynamic)
    # the round-off floor: the reference run again from a start moved by ~1e-15 m
    shaken = simulate(setup, ref["settings"], f"{setup.name}: start perturbed", perturb=perturb)
    out["roundoff_floor"] = {
        "perturb_m": perturb,
        **summary(shaken),
        **trajectory_error(shaken, ref, dynamic),
    }
    floor = out["roundoff_floor"]["pos_err_max"]
    tqdm.write(f"{setup.name}: round-off floor (start moved by {perturb:g}): {floor:.2e} m")
    runs: dict = {}  # settings -> run (the defaults occur in every sweep)
    local: dict = {}  # (settings, reference) -> one-step errors
    points = []
    for param, values in sweeps.items():
        for value in values:
            settings = dict(DEFAULTS, **{param: value})
            key = tuple(sorted(settings.items()))
            if key not in runs:
                runs[key] = simulate(setup, settings, f"{setup.name}: {param}={value:g}")
            run = runs[key]
            against = ref_small if param == "dt" else ref
            if (key, param == "dt") not in local:
                desc = f"{setup.name}: {param}={value:g}, one step"
                local[key, param == "dt"] = local_error(setup, settings, against, desc)
            p = {"param": param, "value": value, "default": value == DEFAULTS[param], **summary(run)}
            p["reference"] = "small dt" if param == "dt" else "tight tolerances, same dt"
            p.update(trajectory_error(run, against, dynamic))
            p.update(local[key, param == "dt"])
            points.append(p)
            tqdm.write(
                f"{setup.name}: {param}={value:g}: {'ok' if p['ok'] else 'FAILED'}, {_g(p['step_s_median'], '.3f')} "
                f"s/step, Newton {_g(p['newton_iters_mean'], '.1f')}/step, pos err {p['pos_err_max']:.2e} m, rot err "
                f"{p['rot_err_max']:.2e} rad, one-step pos err {_g(p['local_pos_err_max'])} m"
            )
    out["points"] = points
    return out


# ------------------------------------------------------------------------------------------------ output
def _g(x, fmt: str = ".2e") -> str:
    return "-" if x is None else format(x, fmt)


def tables(out: dict) -> str:
    m = out["meta"]
    lines = [
        f"# Step accuracy (cfd_torch {m['git']}{', quick' if m['quick'] else ''})",
        "",
        f"Defaults: newton_tol {DEFAULTS['newton_tol']:g}, pair_tol {DEFAULTS['pair_tol']:g}, dt "
        f"{DEFAULTS['dt']:g} s. Errors: largest over the steps and dynamic bodies, against the tight-tolerance "
        "reference at the same dt (newton_tol, pair_tol rows) or the small-dt reference (dt rows). Time: median "
        "forward solve per step; per simulated second = that / dt. Load average "
        f"{m['loadavg_start'][0]:.1f} at the start, {m['loadavg_end'][0]:.1f} at the end (2 cores).",
    ]
    for name, sc in out["scenes"].items():
        r, rs = sc["reference"], sc["reference_dt"]
        e, f = rs["error_of_reference_vs_small_dt"], sc["roundoff_floor"]
        lines += [
            "",
            f"## {name} ({sc['duration_s']:g} s, {sc['bodies']} bodies)",
            "",
            f"References: newton_tol {r['settings']['newton_tol']:g}, pair_tol {r['settings']['pair_tol']:g} at dt "
            f"{r['settings']['dt']:g} ({r['step_s_median'] * 1e3:.1f} ms/step, Newton {r['newton_iters_mean']:.1f}"
            f"/step) and at dt {rs['settings']['dt']:g} ({rs['step_s_median'] * 1e3:.1f} ms/step, Newton "
            f"{rs['newton_iters_mean']:.1f}/step); the first against the second: {e['pos_err_max']:.2e} m, "
            f"{e['rot_err_max']:.2e} rad. Round-off floor (the reference from a start moved by "
            f"{f['perturb_m']:g} x N(0, 1)): {f['pos_err_max']:.2e} m, {f['rot_err_max']:.2e} rad.",
            "",
            "| parameter | value | outcome | ms / step | s / simulated s | Newton / step (median, mean, max) "
            "| max pos err [m] | at t [s] | final pos err [m] | max rot err [rad] "
            "| one-step pos err, max / median [m] |",
            "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for p in sc["points"]:
            outcome = "ok" if p["ok"] else f"failed at step {p['failure']['step']}"
            lines.append(
                f"| {p['param']} | {p['value']:g}{' (default)' if p['default'] else ''} | {outcome} | "
                f"{_g(p['step_s_median'] and p['step_s_median'] * 1e3, '.1f')} | {_g(p['sim_s_per_s'], '.1f')} | "
                f"{_g(p['newton_iters_median'], 'g')}, {_g(p['newton_iters_mean'], '.1f')}, "
                f"{_g(p['newton_iters_max'], 'd')} | {_g(p['pos_err_max'])} | {_g(p['pos_err_max_time'], '.2f')} | "
                f"{_g(p['pos_err_final'])} | {_g(p['rot_err_max'])} | "
                f"{_g(p['local_pos_err_max'])} / {_g(p['local_pos_err_median'])} |"
            )
        fails = [p for p in sc["points"] if not p["ok"]]
        if fails:
            lines += ["", "Failures:"]
            lines += [f"- {p['param']} = {p['value']:g}: {p['failure']['error']}" for p in fails]
    return "\n".join(lines)


FLOOR = 1e-16  # errors of exactly 0 (the same trajectory bit for bit) are drawn here


def plot(out: dict, path: Path) -> None:
    names = list(out["scenes"])
    rows = (
        ("pos_err_max", "trajectory position error (max over t, bodies) [m]"),
        ("rot_err_max", "trajectory rotation error [rad]"),
        ("local_pos_err_median", "one-step position error (median over steps) [m]"),
    )
    fig, axes = plt.subplots(len(rows), len(names), figsize=(6.5 * len(names), 13), squeeze=False)
    colors = {"newton_tol": "tab:blue", "pair_tol": "tab:orange", "dt": "tab:green"}
    markers = {"newton_tol": "o", "pair_tol": "s", "dt": "^"}
    for j, name in enumerate(names):
        sc = out["scenes"][name]
        for i, (key, ylabel) in enumerate(rows):
            ax = axes[i, j]
            for param in colors:
                pts = [
                    p for p in sc["points"] if p["param"] == param and p["sim_s_per_s"] and p[key] is not None
                ]
                if not pts:
                    continue
                x = [p["sim_s_per_s"] for p in pts]
                y = [max(p[key], FLOOR) for p in pts]
                ax.plot(x, y, marker=markers[param], color=colors[param], label=param, lw=1.2)
                for p, xi, yi in zip(pts, x, y, strict=True):
                    ax.annotate(f"{p['value']:g}", (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7,
                                color=colors[param])  # fmt: skip
                    if p["default"]:
                        ax.plot(xi, yi, "o", ms=13, mfc="none", mec="k", mew=1.2)
                    if not p["ok"]:
                        ax.plot(xi, yi, "x", ms=12, color="red", mew=2)
            ax.plot([], [], "o", ms=10, mfc="none", mec="k", label="default")
            if i < 2:  # the trajectory error of a round-off-sized change of the start
                floor = max(sc["roundoff_floor"][key], FLOOR)
                ax.axhline(floor, color="gray", ls="--", lw=1, label="round-off floor")
            ax.set(xscale="log", yscale="log", xlabel="wall time per simulated second [s] (median step / dt)",
                   ylabel=ylabel)  # fmt: skip
            ax.grid(True, which="both", alpha=0.3)
            fails = [f"{p['param']}={p['value']:g}" for p in sc["points"] if not p["ok"]]
            title = f"{name} ({sc['duration_s']:g} s)"
            if fails:
                title += "\nfailed (red x, error over the completed steps): " + ", ".join(fails)
            ax.set_title(title, fontsize=10)
            ax.legend(fontsize=8, loc="best")
    fig.suptitle(
        f"Trajectory error against a tight-tolerance reference (tolerances: same dt; dt: dt = "
        f"{out['meta']['ref_dt']:g} s), cfd_torch {out['meta']['git']}",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _positive(x: float | None) -> bool:
    """An unset option, or a finite positive number."""
    return x is None or (math.isfinite(x) and x > 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/step_accuracy"))
    ap.add_argument("--quick", action="store_true", help="a smoke run: few steps, two values per sweep")
    ap.add_argument("--scenes", nargs="+", choices=("billiards", "stack"), default=["billiards", "stack"])
    ap.add_argument("--rack-rows", type=int, default=None, help="billiards rack rows (default 2)")
    ap.add_argument("--billiards-duration", type=float, default=None, help="[s] (default 0.4, quick 0.06)")
    ap.add_argument("--stack-boxes", type=int, default=4)
    ap.add_argument("--settle", type=float, default=0.3, help="stack: settling time before the runs [s]")
    ap.add_argument("--stack-duration", type=float, default=None, help="[s] (default 0.5, quick 0.06)")
    ap.add_argument("--ref-dt-factor", type=int, default=4, help="reference dt = smallest swept dt / this")
    ap.add_argument(
        "--perturb",
        type=float,
        default=1e-15,
        help="round-off floor: start poses moved by this x N(0, 1) [m, rad]",
    )
    ap.add_argument("--replot", action="store_true", help="rewrite the table and figure from the JSON")
    args = ap.parse_args()
    bad = [
        f"{flag} must be {what}, got {value}"
        for flag, value, ok, what in (
            ("--rack-rows", args.rack_rows, args.rack_rows is None or 1 <= args.rack_rows <= 5, "in 1..5"),
            ("--billiards-duration", args.billiards_duration, _positive(args.billiards_duration), "> 0"),
            ("--stack-duration", args.stack_duration, _positive(args.stack_duration), "> 0"),
            ("--stack-boxes", args.stack_boxes, args.stack_boxes >= 1, ">= 1"),
            ("--settle", args.settle, math.isfinite(args.settle) and args.settle >= 0, "finite and >= 0"),
            ("--ref-dt-factor", args.ref_dt_factor, args.ref_dt_factor >= 1, ">= 1"),
            ("--perturb", args.perturb, math.isfinite(args.perturb) and args.perturb >= 0, "finite and >= 0"),
        )
        if not ok
    ]
    sweeps = QUICK_SWEEPS if args.quick else SWEEPS
    b_dur = (0.06 if args.quick else 0.4) if args.billiards_duration is None else args.billiards_duration
    s_dur = (0.06 if args.quick else 0.5) if args.stack_duration is None else args.stack_duration
    longest = max(sweeps["dt"])
    for flag, dur, scene in (
        ("--billiards-duration", b_dur, "billiards"),
        ("--stack-duration", s_dur, "stack"),
    ):
        if scene in args.scenes and dur < longest:  # every swept dt takes one step at least
            bad.append(f"{flag} must be at least the largest swept dt, {longest:g} s, got {dur:g}")
    if bad:
        ap.error("; ".join(bad))
    path = args.out / "step_accuracy.json"
    if args.replot and not path.is_file():
        ap.error(f"argument --replot: {path} does not exist")
    if args.replot:
        out = json.loads(path.read_text())
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        rows = 2 if args.rack_rows is None else args.rack_rows
        out = {
            "meta": {
                "git": git_revision(), "torch": torch.__version__, "python": platform.python_version(),
                "cpus": os.cpu_count(), "quick": args.quick, "args": json_args(args),
                "defaults": DEFAULTS, "reference_tolerances": TIGHT, "sweeps": sweeps,
                "ref_dt": min(sweeps["dt"]) / args.ref_dt_factor, "loadavg_start": os.getloadavg(),
                "timed": "StepInfo.seconds (forward solve) of every step under torch.no_grad(); medians per run",
            },
            "scenes": {},
        }  # fmt: skip
        t0 = time.perf_counter()
        for name in tqdm(args.scenes, desc="scenes"):
            if name == "billiards":
                setup = billiards_setup(rows, b_dur)
            else:
                setup = stack_setup(args.stack_boxes, args.settle, s_dur)
            out["scenes"][name] = run_scene(setup, sweeps, args.ref_dt_factor, args.perturb)
        out["meta"]["loadavg_end"] = os.getloadavg()
        out["meta"]["run_s"] = time.perf_counter() - t0
        path.write_text(json.dumps(out, indent=1))
    text = tables(out)
    (args.out / "step_accuracy.md").write_text(text + "\n")
    plot(out, args.out / "step_accuracy.png")
    print(text)
    print(f"\nwrote {path}, step_accuracy.md and step_accuracy.png")


if __name__ == "__main__":
    main()
