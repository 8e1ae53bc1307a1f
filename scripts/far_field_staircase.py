"""The far field of Push's pole and box against their distance, for several blend widths eps.

The potential of a body pair is a staircase: a node pair far apart is one central term (12 mu (1 + r^-1/2)^2); inside
its blend band, between the spheres' touching distance d1 and d1 + eps d1, it gives way to its children's sum, which
holds many such terms. So the force between bands is the faint pull of the central terms' slope, and inside a band it
is the step's height over the band's width. This script places the pole beside the box (as Push's trivial start
does: on the side, at the box's height) at distances from 0.21 to 1.5 m (0.2: touching) and evaluates the pair's
potential and the force on the box, for each eps, with the library's contact model, and lists the force's humps:
the distances where a closer pole pushes more weakly (the band's rise peaks, then the children's slope is weaker).
Writes ``staircase.json`` and ``staircase.png`` under ``--out``.

    python scripts/far_field_staircase.py --out results/far_field_staircase
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _cli import positive_float, positive_int  # noqa: E402
from _provenance import git_revision  # noqa: E402

from cfd_torch import Scene, pair_forces  # noqa: E402
from cfd_torch.envs import make_core  # noqa: E402


def humps(r: torch.Tensor, force: torch.Tensor, rel: float = 0.05) -> list[dict]:
    """Where the force fails to grow as the pole approaches: each local maximum of |force| over the distances ``r``
    (ascending) followed, closer in, by a dip more than ``rel`` below it, with the distance at which the force is
    back at the peak's value. Between that distance and the peak a closer pole pushes more weakly."""
    f = force.tolist()
    x = r.tolist()
    out = []
    for i in range(1, len(f) - 1):
        if not (f[i] >= f[i - 1] and f[i] > f[i + 1]):
            continue
        j = i
        while j > 0 and f[j - 1] <= f[j]:  # walk in (to smaller distances) while the force keeps falling
            j -= 1
        if f[j] < (1 - rel) * f[i]:
            k = j
            while k > 0 and f[k] < f[i]:
                k -= 1
            out.append({"peak_distance": x[i], "peak_force": f[i], "dip_distance": x[j], "dip_force": f[j],
                        "recovered_at": x[k]})  # fmt: skip
    return out


def profile(core, r: torch.Tensor, eps_values: list[float]) -> dict[str, dict]:
    """Per eps: the pair's potential, the pole's force on the box (its y component and norm) and the force's humps,
    with the Push ``core``'s pole beside its box (on the side, at the box's height) at the centre distances ``r``."""
    box, pole = core.scene.bodies[:2]
    s0 = core.reset(0, 1)
    q = s0.q[0, :2].expand(len(r), -1, -1).clone()  # (R, 2, 6): the box as it starts, the pole beside it
    q[:, 1, 0], q[:, 1, 1] = 0.0, -r
    pairs = torch.stack(
        [torch.arange(len(r)), torch.zeros(len(r), dtype=torch.long), torch.ones(len(r), dtype=torch.long)], 1
    )
    rows = {}
    for eps in eps_values:
        scene = Scene([box, pole], dt=core.scene.dt, eps=eps)
        value = scene.contact_model.evaluate(q, pairs, 0).value
        force = pair_forces(scene, q)[:, 1, 0, :3]  # the pole's force on the box
        norm = force.norm(dim=1)
        rows[str(eps)] = {"potential": value.tolist(), "force_y": force[:, 1].tolist(),
                          "force_norm": norm.tolist(), "force_humps": humps(r, norm)}  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--eps",
        type=positive_float,
        nargs="+",
        default=[0.01, 0.1, 1.0, 4.0],
        help="blend widths eps to compare",
    )
    ap.add_argument("--points", type=positive_int, default=261, help="distances between 0.21 and 1.5 m")
    ap.add_argument("--out", type=Path, default=Path("results/far_field_staircase"), help="output folder")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    core = make_core("cfd_torch/Push-v0")
    r = torch.linspace(0.21, 1.5, args.points, dtype=torch.float64)
    rows = profile(core, r, args.eps)
    result = {
        "commit": git_revision(),
        "distance": r.tolist(),
        "mu": core.scene.contact.stiffness,
        "eps": rows,
    }
    (args.out / "staircase.json").write_text(json.dumps(result, indent=1))
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for eps, row in rows.items():
        ax[0].plot(r, row["potential"], label=f"eps {eps}")
        ax[1].plot(r, row["force_norm"], label=f"eps {eps}")
    ax[0].set(xlabel="pole-box centre distance [m]", ylabel="potential [J]", yscale="log",
              title="Push: pole beside the box")  # fmt: skip
    ax[1].set(xlabel="pole-box centre distance [m]", ylabel="|force on the box| [N]", yscale="log")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(args.out / "staircase.png", dpi=120)
    for eps, row in rows.items():
        f = torch.tensor(row["force_norm"])
        print(f"eps {eps}: force on the box {float(f.min()):.2e} .. {float(f.max()):.2e} N, "
              f"max/min {float(f.max() / f.min()):.1e}")  # fmt: skip
        for h in row["force_humps"]:
            print(f"    hump: {h['peak_force']:.2e} N at {h['peak_distance']:.3f} m, down to {h['dip_force']:.2e} N at "
                  f"{h['dip_distance']:.3f} m, back to the peak's force at {h['recovered_at']:.3f} m")  # fmt: skip
    print("wrote", args.out / "staircase.json", args.out / "staircase.png")


if __name__ == "__main__":
    main()
