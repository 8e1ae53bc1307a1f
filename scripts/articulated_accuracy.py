"""Accuracy of articulated bodies: joint trajectories of fast chains against MuJoCo's RK4, as dt shrinks.

What is measured. Robots without gravity, contact or actuation, started with fast joint (and base) velocities, are
simulated for ``--duration`` (1 s) at each dt of ``--dts`` (0.02, 0.01, 0.005 s) by the library's step, and by
MuJoCo (the same MJCF, as the library's loader writes it) with its RK4 integrator at ``--ref-dt`` (0.25 ms), its
contacts off. The error at the end: the largest joint-angle difference [rad] (hinges mod 2 pi) and, for a floating
base, its position [m] and the angle between its orientations [rad]. The library's step is implicit Euler with
the contact model's energy, so the error falls at first order in dt; how fast it falls from where is what this
measures. ``--baseline REV`` runs the same cases on an older revision of the package in a git worktree (this script
in worker mode, PYTHONPATH at the checkout), side by side in the same run.

Cases (the MJCF in this file):

- bar: a 0.5 m capsule bar on a hinge about y, spinning at 5 rad/s (its centre of mass circles the axis; the exact
  motion is a constant rate);
- tilted box: a 0.4 x 0.2 x 0.1 m box tilted 30 degrees on a z hinge, 0.15 m out, at 5 rad/s (the hinge is none of
  its principal axes; a constant rate too);
- gimbal: a yaw hinge at 5 rad/s carrying a pitch hinge with an asymmetric box at 0.3 rad (the pitch accelerates
  from the gyroscopic and centrifugal terms);
- double pendulum: two capsules on parallel hinges swung at 6 and -2 rad/s;
- ant: Gymnasium's Ant floating free, its base turning at (0.5, 1, 2) rad/s and moving at 0.3 m/s, its hips at 0
  and ankles at the middle of their ranges with rates of 0.2 rad/s (alternating signs); joints' damping and
  armature as in its MJCF.

Writes ``<out>/articulated_accuracy.json`` (every point, both revisions, the git revision), ``.md`` (a table) and
``.png`` (error against dt per case, log-log, one line per revision, a first-order slope dashed).

    python scripts/articulated_accuracy.py --out results/articulated_accuracy --baseline 6527370   # about 4 min
    python scripts/articulated_accuracy.py --out results/articulated_accuracy_quick --quick
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cli import positive_float  # noqa: E402
from _provenance import git_commit, git_revision  # noqa: E402

F64 = torch.float64

BAR = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="bar"><joint name="spin" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/></body></body></worldbody></mujoco>"""
TILTED_BOX = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="box"><joint name="spin" type="hinge" axis="0 0 1"/>
  <geom type="box" size="0.2 0.1 0.05" pos="0.15 0 0" euler="30 0 0"/></body></body></worldbody></mujoco>"""
GIMBAL = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="outer"><joint name="yaw" type="hinge" axis="0 0 1"/><geom type="box" size="0.3 0.02 0.02" pos="0 0 0.1"/>
  <body name="inner" pos="0 0 0.1"><joint name="pitch" type="hinge" axis="1 0 0"/>
  <geom type="box" size="0.2 0.1 0.03" pos="0.05 0 0.08" euler="10 20 30"/></body></body></body></worldbody></mujoco>"""
DOUBLE_PENDULUM = """<mujoco><worldbody><body name="base" pos="0 0 1"><geom type="sphere" size="0.05"/>
  <body name="upper"><joint name="j1" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03"/>
  <body name="lower" pos="0 0 -0.5"><joint name="j2" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0.1 0 -0.4" size="0.03"/></body></body></body></worldbody></mujoco>"""
CASES = ("bar", "tilted box", "gimbal", "double pendulum", "ant")


def case_spec(name: str) -> dict:
    """The case's MJCF, joint values and rates, and (floating) base velocity: linear (world) and angular (world,
    the base starts unrotated)."""
    if name == "ant":
        from cfd_torch.sim.mjcf import gymnasium_ant_xml

        # hips at 0, ankles at the middle of their ranges (+-50 degrees; the order of the Ant's joints: hip, ankle
        # of each leg), rates that keep them within their ranges
        a = math.radians(50.0)
        th = [0.0, a, 0.0, -a, 0.0, -a, 0.0, a]
        rate = [0.2 * (-1) ** k for k in range(8)]
        return {
            "xml": gymnasium_ant_xml(),
            "th": th,
            "rate": rate,
            "v": [0.3, 0.0, 0.0],
            "w": [0.5, 1.0, 2.0],
        }
    xml, th, rate = {
        "bar": (BAR, [0.0], [5.0]),
        "tilted box": (TILTED_BOX, [0.0], [5.0]),
        "gimbal": (GIMBAL, [0.0, 0.3], [5.0, 0.0]),
        "double pendulum": (DOUBLE_PENDULUM, [0.0, 0.7], [6.0, -2.0]),
    }[name]
    return {"xml": xml, "th": th, "rate": rate, "v": None, "w": None}


# ------------------------------------------------------------------------------------------------ the library
def simulate(name: str, dt: float, duration: float) -> dict:
    """The library's rollout of case ``name``: its end coordinates (base pose, joints) and wall time."""
    from cfd_torch import Scene, State
    from cfd_torch.sim.articulation import articulation
    from cfd_torch.sim.stepper import rollout

    spec = case_spec(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the MJCF's options the step does not use
        art = articulation(spec["xml"])
    scene = Scene([], articulations=[art], dt=dt, gravity=(0.0, 0.0, 0.0))
    th = torch.tensor(spec["th"], dtype=F64)
    th_prev = th - dt * torch.tensor(spec["rate"], dtype=F64)
    if spec["w"] is None:
        q, q_prev = art.poses(th), art.poses(th_prev)
    else:
        base = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
        back = torch.cat([-dt * torch.tensor(spec["v"], dtype=F64), -dt * torch.tensor(spec["w"], dtype=F64)])
        q, q_prev = art.poses(th, base), art.poses(th_prev, base + back)
    t0 = time.perf_counter()
    with torch.no_grad():
        traj = rollout(scene, State(q, q_prev), round(duration / dt))
    seconds = time.perf_counter() - t0
    coords = scene.kinematics.coords(traj.q[-1:])[0]
    return {"coords": coords.tolist(), "floating": bool(art.floating), "seconds": seconds}


# ------------------------------------------------------------------------------------------------ MuJoCo
def reference(name: str, duration: float, ref_dt: float) -> dict:
    """MuJoCo's RK4 at ``ref_dt``, contacts and gravity off: the end qpos (free joint: position, quaternion)."""
    import mujoco

    from cfd_torch.sim.mjcf import load_mjcf

    spec = case_spec(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = mujoco.MjModel.from_xml_string(load_mjcf(spec["xml"]).xml)
    model.opt.gravity[:] = 0.0
    model.opt.timestep = ref_dt
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    data = mujoco.MjData(model)
    free = spec["w"] is not None
    if free:
        data.qpos[:7] = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]
        data.qvel[:6] = (
            spec["v"] + spec["w"]
        )  # the base starts unrotated: its local angular velocity is the world's
    data.qpos[7 if free else 0 :] = spec["th"]
    data.qvel[6 if free else 0 :] = spec["rate"]
    for _ in range(round(duration / ref_dt)):
        mujoco.mj_step(model, data)
    return {"qpos": data.qpos.tolist()}


def errors(sim: dict, ref: dict) -> dict:
    """End-of-run errors: joints [rad] (hinges mod 2 pi), and a floating base's position [m] and rotation [rad]."""
    from scipy.spatial.transform import Rotation

    c, qpos = np.asarray(sim["coords"]), np.asarray(ref["qpos"])
    out = {}
    if sim["floating"]:
        out["base_position"] = float(np.linalg.norm(c[:3] - qpos[:3]))
        r_sim = Rotation.from_rotvec(c[3:6])
        r_ref = Rotation.from_quat(qpos[[4, 5, 6, 3]])  # MuJoCo: w, x, y, z
        out["base_rotation"] = float((r_sim.inv() * r_ref).magnitude())
        c, qpos = c[6:], qpos[7:]
    d = np.remainder(c - qpos + math.pi, 2 * math.pi) - math.pi  # (all the cases' joints are hinges)
    out["joints"] = float(np.abs(d).max())
    out["error"] = max(out["joints"], out.get("base_rotation", 0.0))
    return out


def measure(cases, dts, duration) -> dict:
    """{case: {dt: simulate's result}} for this process's cfd_torch."""
    out = {}
    with tqdm(total=len(cases) * len(dts), desc="steps", file=sys.stderr) as bar:
        for name in cases:
            out[name] = {}
            for dt in dts:
                out[name][str(dt)] = simulate(name, dt, duration)
                bar.update()
    return out


# ------------------------------------------------------------------------------------------------ output
def write(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    revs = list(out["revisions"].items())
    lines = [
        f"Joint-angle (and base-rotation) error after {out['duration']} s against MuJoCo's RK4 at "
        f"{out['ref_dt']} s, no gravity ([rad]; `{out.get('command', 'python scripts/articulated_accuracy.py')}`, "
        f"this revision {out['git']}).",
        "",
        "| case | dt | " + " | ".join(f"error {label} ({rev})" for label, rev in revs) + " | wall s (this) |",
        "|---|---:|" + "---:|" * len(revs) + "---:|",
    ]
    for name in out["cases"]:
        for dt in out["dts"]:
            errs = [out[label]["errors"][name][str(dt)]["error"] for label, _ in revs]
            wall = out["this"]["results"][name][str(dt)]["seconds"]
            lines.append(f"| {name} | {dt} | " + " | ".join(f"{e:.3g}" for e in errs) + f" | {wall:.1f} |")
    path.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    n = len(out["cases"])
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.2), squeeze=False)
    for ax, name in zip(axes[0], out["cases"], strict=True):
        dts = np.asarray(out["dts"])
        for (label, rev), style in zip(revs, ("o-", "s--"), strict=False):
            e = [out[label]["errors"][name][str(dt)]["error"] for dt in out["dts"]]
            ax.loglog(dts, np.maximum(e, 1e-16), style, label=rev)
        e0 = max(out[label]["errors"][name][str(out["dts"][0])]["error"] for label, _ in revs)
        ax.loglog(dts, e0 * dts / dts[0], ":", color="grey", label="first order")  # through the largest error
        ax.set_title(name)
        ax.set_xlabel("dt [s]")
    axes[0, 0].set_ylabel(f"error after {out['duration']} s [rad]")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path.with_suffix(".png"), dpi=110)
    path.with_suffix(".json").write_text(json.dumps(out, indent=1))
    print(f"wrote {path.with_suffix('.json')}, .md and .png")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/articulated_accuracy"), help="output folder")
    ap.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES), help="cases to run")
    ap.add_argument(
        "--dts", nargs="+", type=positive_float, default=None, help="[s] (default 0.02 0.01 0.005)"
    )
    ap.add_argument("--duration", type=positive_float, default=None, help="[s] (default 1; quick 0.2)")
    ap.add_argument("--ref-dt", type=positive_float, default=2.5e-4, help="MuJoCo RK4's step [s]")
    ap.add_argument(
        "--baseline",
        type=git_commit,
        metavar="REV",
        default=None,
        help="also run the package at git revision REV",
    )
    ap.add_argument("--quick", action="store_true", help="a smoke run: 0.2 s, dt 0.02 and 0.01")
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)  # a --baseline subprocess
    args = ap.parse_args(argv)
    if args.dts is None:
        args.dts = [0.02, 0.01] if args.quick else [0.02, 0.01, 0.005]
    if args.duration is None:
        args.duration = 0.2 if args.quick else 1.0
    if any(dt > args.duration for dt in args.dts):
        ap.error(f"argument --dts: each must be at most the duration ({args.duration:g} s), got {args.dts}")
    if not args.ref_dt < min(args.dts):
        ap.error(
            f"argument --ref-dt: must be below the smallest of --dts ({min(args.dts):g} s), got {args.ref_dt:g}"
        )
    return args


def main() -> None:
    args = parse_args()
    if args.worker is not None:
        spec = json.loads(args.worker.read_text())
        res = measure(spec["cases"], spec["dts"], spec["duration"])
        Path(spec["result"]).write_text(json.dumps(res))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    rev = git_revision()
    out = {
        "git": rev, "cases": args.cases, "dts": args.dts, "duration": args.duration, "ref_dt": args.ref_dt,
        "command": shlex.join(["python", "scripts/articulated_accuracy.py", *sys.argv[1:]]),
        "revisions": {"this": rev},
        "reference": {name: reference(name, args.duration, args.ref_dt) for name in args.cases},
    }  # fmt: skip
    runs = [("this", measure(args.cases, args.dts, args.duration))]
    if args.baseline:
        from bench_step import Baseline

        base = Baseline(args.baseline, Path(__file__))
        try:
            res = base.run_spec({"cases": args.cases, "dts": args.dts, "duration": args.duration}, "accuracy")
        finally:
            base.close()
        if "error" in res:
            raise SystemExit(res["error"])
        out["revisions"]["baseline"] = base.commit
        runs.append(("baseline", res))
    for label, res in runs:
        out[label] = {
            "results": res,
            "errors": {
                name: {str(dt): errors(res[name][str(dt)], out["reference"][name]) for dt in args.dts}
                for name in args.cases
            },
        }
    write(out, args.out / "articulated_accuracy")


if __name__ == "__main__":
    main()
