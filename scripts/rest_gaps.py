"""Where bodies come to rest on a floor at a contact stiffness: settled rollouts against ``cfd_torch.rest_gap``.

Each body (a cube or a 320-face icosphere of a given size and density; ``--shapes``, ``--sizes``, ``--densities``)
is released at rest 2 mm above a static ``--floor`` m x ``--floor`` m x 0.1 m box (its lowest vertex), friction
0.5, and stepped ``--steps`` times at dt = 0.01; its rest gap is the height of its lowest vertex at the end (the
mesh's own lowest vertex carried by the body's pose; the spread over the last 20 steps says whether it came to
rest). Beside it: ``rest_gap(body, mu, floor=that box, start=the rollout's highest gap)``, and ``rest_gap`` on its
default floor (a box three times the body's footprint), which the Scene's ``RestGapWarning`` uses; and whether the
Scene warned.

Writes ``rest_gaps.json``, ``rest_gaps.md`` (printed too) and ``rest_gaps.png`` (predicted against settled) under
``--out``.

    python scripts/rest_gaps.py --out results/rest_gaps            # about 2 minutes
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import folder_problem, positive_float, positive_int  # noqa: E402
from _provenance import git_revision  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cfd_torch import RestGapWarning, Scene, rest_gap, rigid_body, rollout  # noqa: E402
from cfd_torch.rotation import rotation_matrix  # noqa: E402

F64 = torch.float64
DROP = 2e-3


def mesh(shape: str, size: float) -> trimesh.Trimesh:
    if shape == "cube":
        return trimesh.creation.box(extents=(size, size, size))
    return trimesh.creation.icosphere(subdivisions=2, radius=size / 2)


def settle(shape: str, size: float, density: float, floor_side: float, mu: float, steps: int) -> dict:
    """One body released 2 mm above the floor: its settled gap, the predictions, whether the Scene warned."""
    body = rigid_body(mesh(shape, size), density=density)
    floor = rigid_body(trimesh.creation.box(extents=(floor_side, floor_side, 0.1)), kind="static")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RestGapWarning)
        scene = Scene([body, floor], friction=0.5, mu=mu)
    warned = any(issubclass(w.category, RestGapWarning) for w in caught)
    v = body.bsh.vertices
    z0 = DROP - float(v[:, 2].min())
    q = torch.tensor([[0.0, 0.0, z0, 0.0, 0.0, 0.0], [0.0, 0.0, -0.05, 0.0, 0.0, 0.0]], dtype=F64)
    traj = rollout(scene, scene.initial_state(q), steps)
    # the lowest vertex of the posed mesh at every state
    R = rotation_matrix(traj.q[:, 0, 3:])
    low = ((v @ R.transpose(1, 2))[..., 2] + traj.q[:, 0, 2:3]).amin(1)
    start = max(float(low.max()), 2 * scene.contact.margin)
    return {
        "shape": shape, "size": size, "density": density, "mass": body.mass, "mu": mu,
        "settled": float(low[-1]), "spread_last_20": float(low[-20:].max() - low[-20:].min()),
        "highest": float(low.max()), "predicted": rest_gap(body, mu, floor=floor, start=start),
        "predicted_default_floor": rest_gap(body, mu), "warned": warned,
    }  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/rest_gaps"), help="output folder")
    ap.add_argument("--shapes", nargs="+", choices=("cube", "ball"), default=["cube", "ball"])
    ap.add_argument(
        "--sizes", type=positive_float, nargs="+", default=[0.01, 0.02, 0.05, 0.1, 0.3], help="[m]"
    )
    ap.add_argument("--densities", type=positive_float, nargs="+", default=[200.0, 1000.0], help="[kg/m^3]")
    ap.add_argument("--floor", type=positive_float, default=1.0, help="the floor box's side [m]")
    ap.add_argument("--mu", type=positive_float, default=1e-8, help="the contact stiffness")
    ap.add_argument(
        "--steps", type=positive_int, default=150, help="steps of dt = 0.01 to settle (at least 20)"
    )
    args = ap.parse_args(argv)
    if args.steps < 20:
        ap.error(f"argument --steps: at least 20 (the rest test looks at the last 20), got {args.steps}")
    if problem := folder_problem(args.out):
        ap.error(f"argument --out: {problem}")
    if not args.floor > 3 * max(args.sizes):
        ap.error(
            f"argument --floor: must exceed 3 x the largest --sizes ({3 * max(args.sizes):g} m), got {args.floor}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    cases = [(s, a, d) for s in args.shapes for a in args.sizes for d in args.densities]
    rows = [settle(s, a, d, args.floor, args.mu, args.steps) for s, a, d in tqdm(cases, desc="bodies")]
    lines = [
        f"Rest gaps at mu = {args.mu:g} on a {args.floor:g} m floor box, released 2 mm up, friction 0.5, "
        f"{args.steps} steps of 0.01 s (cfd_torch at {git_revision()}); gaps of the lowest vertex in mm",
        "",
        "| body | mass [kg] | settled | spread of the last 20 steps | predicted, that floor | predicted, default "
        "floor | Scene warned |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shape']} {100 * r['size']:g} cm, {r['density']:g} kg/m^3 | {r['mass']:.4g} | "
            f"{1e3 * r['settled']:.3f} | {1e3 * r['spread_last_20']:.1e} | {1e3 * r['predicted']:.3f} | "
            f"{1e3 * r['predicted_default_floor']:.3f} | {'yes' if r['warned'] else 'no'} |"
        )
    text = "\n".join(lines)
    print(text)
    (args.out / "rest_gaps.md").write_text(text + "\n")
    meta = vars(args) | {"out": str(args.out), "git": git_revision(), "torch": torch.__version__}
    (args.out / "rest_gaps.json").write_text(json.dumps({"settings": meta, "rows": rows}, indent=1))
    fig, ax = plt.subplots(figsize=(5, 5))
    for shape, marker in (("cube", "s"), ("ball", "o")):
        sel = [r for r in rows if r["shape"] == shape]
        if sel:
            ax.loglog(
                [1e3 * r["settled"] for r in sel], [1e3 * r["predicted"] for r in sel], marker, label=shape
            )
    lim = [1e3 * min(r["settled"] for r in rows) / 1.5, 1e3 * max(r["settled"] for r in rows) * 1.5]
    ax.plot(lim, lim, "k:", lw=1)
    ax.set_xlabel("settled gap in a rollout [mm]")
    ax.set_ylabel("rest_gap(body, mu, floor=) [mm]")
    ax.set_title(f"mu = {args.mu:g}, {args.floor:g} m floor")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "rest_gaps.png", dpi=120)
    print(f"wrote {args.out}/rest_gaps.json, rest_gaps.md and rest_gaps.png")


if __name__ == "__main__":
    main()
