"""Demo: potential and force between two triangles against their distance, ours against the peers' local barriers.

Triangle b (tilted, rotated) hangs above triangle a; we move it along +z and record the potential and the normal
force F = -dP/dz on b. The IPC log barrier and the SDRS-style local plane barrier (both dhat = 1e-2) are scaled so
that their force equals ours at the smallest gap; beyond dhat their force is exactly zero, ours never vanishes.

Writes ``<out>/pair_demo.png`` and ``<out>/pair_demo.json`` and prints a short table.

    python scripts/demo_pair.py --out results/demo
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _cli import positive_float  # noqa: E402
from _provenance import git_revision  # noqa: E402

from cfd_torch import central_potential, pair_potential  # noqa: E402
from cfd_torch.baselines import ipc_pair_barrier, sdrs_pair_potential  # noqa: E402


def _rot(axis: list[float], angle: float) -> torch.Tensor:
    k = torch.tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def triangles(gaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(K, 3, 3) pairs whose closest distance equals ``gaps`` (vertex of b above the face of a)."""
    base = torch.tensor([[-0.5, -0.4, 0.0], [0.6, -0.3, 0.0], [0.0, 0.6, 0.0]], dtype=torch.float64)
    tb = torch.tensor([[0.0, 0.0, 0.0], [0.7, 0.2, 0.5], [-0.3, 0.6, 0.4]], dtype=torch.float64)
    tb = tb @ _rot([0.0, 0.0, 1.0], 0.5).T + torch.tensor([0.05, 0.02, 0.0], dtype=torch.float64)
    tb = tb - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) * tb[:, 2].min()
    K = gaps.shape[0]
    ta = base.expand(K, 3, 3)
    tbk = tb.expand(K, 3, 3) + gaps[:, None, None] * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return ta, tbk


def normal_force(fn, gaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Value (K,) and F = -dP/dz (K,) of triangle b's translation."""
    ta, tb = triangles(gaps)
    tb = tb.clone().requires_grad_(True)
    val = fn(ta, tb)
    (g,) = torch.autograd.grad(val.sum(), tb)
    return val.detach(), -g[..., 2].sum(-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/demo"), help="output folder")
    ap.add_argument("--mu", type=positive_float, default=1e-8, help="our potential's mu")
    ap.add_argument(
        "--margin", type=positive_float, default=1e-3, help="contact margin [m]; gaps start at 1.5 x margin"
    )
    ap.add_argument(
        "--dhat", type=positive_float, default=1e-2, help="the local barriers' activation distance [m]"
    )
    ap.add_argument(
        "--points", type=int, default=200, help="gaps sampled, log-spaced up to 1e4 m (at least 2)"
    )
    args = ap.parse_args()
    if args.points < 2:
        ap.error(f"argument --points: must be an integer >= 2, got {args.points}")
    if args.margin >= 1e3:
        ap.error(
            f"argument --margin: must be < 1e3 m (the gaps run from 1.5 x margin to 1e4 m), got {args.margin:g}"
        )
    if (
        args.dhat <= 1.5 * args.margin
    ):  # the peers are scaled to our force at the smallest gap: theirs must act there
        ap.error(
            f"argument --dhat: must exceed 1.5 x --margin = {1.5 * args.margin:g} m (the smallest gap, where the "
            f"local barriers are scaled to our force), got {args.dhat:g}"
        )
    args.out.mkdir(parents=True, exist_ok=True)

    gaps = torch.logspace(math.log10(args.margin * 1.5), 4, args.points, dtype=torch.float64)
    ours_v, ours_f = normal_force(lambda a, b: pair_potential(a, b, mu=args.mu, margin=args.margin), gaps)
    ipc_v, ipc_f = normal_force(lambda a, b: ipc_pair_barrier(a, b, dhat=args.dhat), gaps)
    sdrs_v, sdrs_f = normal_force(
        lambda a, b: sdrs_pair_potential(a, b, dhat=args.dhat, margin=args.margin), gaps
    )
    # Scale the peers so that their force equals ours at the smallest gap.
    k_ipc = float(ours_f[0] / ipc_f[0])
    k_sdrs = float(ours_f[0] / sdrs_f[0])
    ipc_v, ipc_f, sdrs_v, sdrs_f = k_ipc * ipc_v, k_ipc * ipc_f, k_sdrs * sdrs_v, k_sdrs * sdrs_f
    ta, tb = triangles(gaps)  # reference curve: the central potential of the centroid distance
    centroid_dist = (ta.mean(1) - tb.mean(1)).norm(dim=-1)
    pc = central_potential(centroid_dist, mu=args.mu)

    assert bool((ours_f > 0).all()), (
        "the long-range potential must push the triangles apart at every distance"
    )
    last_ipc = float(gaps[ipc_f > 0].max())
    last_sdrs = float(gaps[sdrs_f > 0].max())

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax1.loglog(gaps, ours_v, label="ours (exact plane potential)")
    ax1.loglog(gaps, pc, "k:", label="central potential P_c(centroid distance)")
    ax1.loglog(gaps, ipc_v.clamp(min=1e-300), label="IPC log barrier (scaled)")
    ax1.loglog(gaps, sdrs_v.clamp(min=1e-300), label="SDRS local plane barrier (scaled)")
    ax1.set_ylim(float(ours_v.min()) * 1e-3, float(ours_v.max()) * 10)
    ax1.set_xlabel("gap between the triangles [m]")
    ax1.set_ylabel("potential")
    ax1.legend(fontsize=8)
    ax2.loglog(gaps, ours_f, label="ours")
    m_ipc, m_sdrs = ipc_f > 0, sdrs_f > 0
    ax2.loglog(gaps[m_ipc], ipc_f[m_ipc], label=f"IPC: exactly 0 beyond {last_ipc:.3g} m")
    ax2.loglog(gaps[m_sdrs], sdrs_f[m_sdrs], label=f"SDRS: exactly 0 beyond {last_sdrs:.3g} m")
    ax2.axvline(args.dhat, color="gray", ls="--", lw=0.8)
    ax2.set_xlabel("gap between the triangles [m]")
    ax2.set_ylabel("normal force -dP/dz on the upper triangle")
    ax2.legend(fontsize=8)
    ax2.set_title("the long-range force never vanishes", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out / "pair_demo.png", dpi=120)

    record = {
        "commit": git_revision(),
        "mu": args.mu,
        "margin": args.margin,
        "dhat": args.dhat,
        "gap": gaps.tolist(),
        "ours": {"value": ours_v.tolist(), "force": ours_f.tolist()},
        "ipc": {
            "value": ipc_v.tolist(),
            "force": ipc_f.tolist(),
            "scale": k_ipc,
            "last_nonzero_gap": last_ipc,
        },
        "sdrs": {
            "value": sdrs_v.tolist(),
            "force": sdrs_f.tolist(),
            "scale": k_sdrs,
            "last_nonzero_gap": last_sdrs,
        },
    }
    (args.out / "pair_demo.json").write_text(json.dumps(record))
    print(f"{'gap [m]':>10} {'ours F':>12} {'IPC F':>12} {'SDRS F':>12}")
    for i in torch.linspace(0, args.points - 1, 9).round().long().tolist():
        print(f"{gaps[i]:10.3g} {ours_f[i]:12.4g} {ipc_f[i] + 0.0:12.4g} {sdrs_f[i] + 0.0:12.4g}")
    print(f"wrote {args.out / 'pair_demo.png'} and {args.out / 'pair_demo.json'}")


if __name__ == "__main__":
    main()
