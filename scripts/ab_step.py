"""A/B timing of simulator steps between two revisions, both in fresh processes, alternating.

``bench_step.py --baseline`` times this revision in its own (warm, plotting) process and the baseline in a
subprocess; this script removes that asymmetry: every run is a fresh ``python -c`` with one torch and one numba
thread, the revisions alternate, and the figure is the CPU time per step (``time.process_time``), which a loaded
machine disturbs less than wall time. Scenes: a 320-face ball resting on a 12-triangle box (without and with
friction 0.5), 4 stacked 12-triangle boxes, and Push's reachable variant (``make_core("cfd_torch/Push-v0",
distance=1.5, box_density=50, dt=0.04)``) at rest under zero actions, with ``--potential``'s contact (this
library's, or the baselines' ``ipc`` or ``sdrs`` at their defaults). Uses only the API both revisions share
(``Scene``, ``step``, ``rigid_body``, ``make_core``).

    python scripts/ab_step.py --baseline e5289f1 --runs 3 --out results/ab_step
    python scripts/ab_step.py --baseline bfee8a2 --potential sdrs --steps 10 --warm 3 --out results/ab_step_sdrs
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _provenance import git_commit
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, statistics, time, torch, trimesh
import cfd_torch as c
def scenes():
    ball = c.rigid_body(trimesh.creation.icosphere(subdivisions=2, radius=0.1))
    m = trimesh.creation.box(extents=(1.0, 1.0, 0.1)); m.apply_translation([0, 0, -0.05])
    box = c.rigid_body(m, kind="static")
    q = torch.zeros(2, 6, dtype=torch.float64); q[0, 2] = 0.1 + 2e-3
    yield "ball_box", c.Scene((ball, box), potential=POT), q
    yield "ball_box_friction", c.Scene((ball, box), friction=0.5, potential=POT), q
    cube = c.rigid_body(trimesh.creation.box(extents=(0.2, 0.2, 0.2)))
    q = torch.zeros(5, 6, dtype=torch.float64)
    for k in range(4): q[k + 1, 2] = 0.1 + 1.3e-3 + k * (0.2 + 1.3e-3)
    yield "boxes4", c.Scene((box, cube, cube, cube, cube), potential=POT), q
out = {}
for name, sc, q in scenes():
    st = sc.initial_state(q)
    for _ in range(WARM): st = c.step(sc, st)
    ts = []
    for _ in range(STEPS):
        t0 = time.process_time(); st = c.step(sc, st); ts.append(time.process_time() - t0)
    out[name] = 1e3 * statistics.median(ts)
# cfd_torch.envs is the revision's own envs/ folder (the editable install would map it to this checkout's)
import importlib.util, os, sys
envs = os.path.join(REV, "envs")
spec = importlib.util.spec_from_file_location("cfd_torch.envs", os.path.join(envs, "__init__.py"),
                                              submodule_search_locations=[envs])
sys.modules["cfd_torch.envs"] = mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
here = os.path.realpath
assert here(os.path.dirname(mod.__file__)) == here(envs)
assert here(os.path.dirname(c.__file__)) == here(os.path.join(REV, "cfd_torch"))
from cfd_torch.envs import make_core
core = make_core("cfd_torch/Push-v0", distance=1.5, box_density=50, dt=0.04, potential=POT)
st, a, ts = core.reset(0, 1), torch.zeros(1, 2, dtype=torch.float64), []
with torch.no_grad():
    for _ in range(WARM): st = core.step(st, a).state
    for _ in range(STEPS):
        t0 = time.process_time(); st = core.step(st, a).state; ts.append(time.process_time() - t0)
out["push_at_rest"] = 1e3 * statistics.median(ts)
print(json.dumps(out))
"""


def run(path: Path, steps: int, warm: int, potential: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(path), "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    code = CHILD.replace("WARM", str(warm)).replace("STEPS", str(steps)).replace("POT", repr(potential))
    code = code.replace("REV", repr(str(path.resolve())))
    res = subprocess.run([sys.executable, "-c", code], env=env, cwd=tempfile.gettempdir(), capture_output=True,
                         text=True)  # fmt: skip
    if res.returncode != 0:  # the child's own error, not the script it ran
        raise SystemExit(f"the timing run of {path} failed:\n{res.stderr.strip()}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--baseline", type=git_commit, required=True, help="git revision to compare with (e.g. e5289f1)"
    )
    ap.add_argument("--runs", type=int, default=3, help="runs per revision (alternating)")
    ap.add_argument("--steps", type=int, default=40, help="timed steps per scene and run")
    ap.add_argument("--warm", type=int, default=10, help="untimed steps first")
    ap.add_argument("--potential", default="cfd", choices=("cfd", "ipc", "sdrs"), help="the scenes' contact")
    ap.add_argument("--out", type=Path, default=Path("results/ab_step"))
    args = ap.parse_args()
    if args.runs < 1 or args.steps < 1 or args.warm < 0:
        ap.error(
            f"--runs and --steps must be >= 1 and --warm >= 0, got {args.runs}, {args.steps}, {args.warm}"
        )
    if args.out.is_file():
        ap.error(f"--out {args.out} is a file; give a folder")
    args.out.mkdir(parents=True, exist_ok=True)  # before the runs: a bad --out fails now, not after them
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        added = subprocess.run(["git", "worktree", "add", "--detach", str(base), args.baseline], cwd=ROOT,
                               capture_output=True, text=True)  # fmt: skip
        if added.returncode != 0:
            ap.error(f"--baseline {args.baseline}: {added.stderr.strip()}")
        try:
            runs: dict[str, list[dict]] = {"baseline": [], "head": []}
            for _ in tqdm(range(args.runs), desc="A/B runs"):
                runs["baseline"].append(run(base, args.steps, args.warm, args.potential))
                runs["head"].append(run(ROOT, args.steps, args.warm, args.potential))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, capture_output=True)
    cases = list(runs["head"][0])
    med = {k: {c: statistics.median(r[c] for r in v) for c in cases} for k, v in runs.items()}
    lines = [
        f"CPU ms per step, median over {args.runs} alternating runs of {args.steps} steps (one thread), "
        f"{args.baseline} against {head.stdout.strip()}, potential {args.potential}",
        "",
        f"| case | {args.baseline} | {head.stdout.strip()} | ratio | runs {args.baseline} | runs now |",
        "|---|---:|---:|---:|---|---|",
    ]
    for c in cases:
        b, h = med["baseline"][c], med["head"][c]
        rb = " / ".join(f"{r[c]:.1f}" for r in runs["baseline"])
        rh = " / ".join(f"{r[c]:.1f}" for r in runs["head"])
        lines.append(f"| {c} | {b:.2f} | {h:.2f} | {h / b:.2f} | {rb} | {rh} |")
    table = "\n".join(lines)
    print(table)
    (args.out / "ab_step.json").write_text(json.dumps({"runs": runs, "median": med, "baseline": args.baseline,
                                                        "head": head.stdout.strip(), "potential": args.potential},
                                                       indent=1))  # fmt: skip
    (args.out / "table.md").write_text(table + "\n")


if __name__ == "__main__":
    main()
