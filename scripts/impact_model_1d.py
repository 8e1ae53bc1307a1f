"""Why restitution depends on the impact phase: the head-on impact of two cubes, reduced to one coordinate.

The one coordinate is stepped by the simulator's implicit Euler under several sub-stepping schemes.

Model. Two 0.1 m cubes (1 kg each, ``rigid_body`` of ``trimesh.creation.box``) face to face along x, translating
only: the gap g between the facing faces is the one coordinate, P(g) the library's mesh potential of the pair
(``mesh_potential_derivatives``: value, dP/dg, d2P/dg2; default stiffness, margin and blend band), the reduced mass
m_r = m / 2. A step of length h minimises the incremental potential m_r / (2 h^2) (g - g~)^2 + P(g),
g~ = g_n + h v_n, by a safeguarded Newton solve to 1e-13 m: the stepper's implicit Euler on this one coordinate (no
rotation, no friction, no far-field pull on the bodies' own motion beyond P). The striker closes the gap at ``v``;
the gap at phase 0 is ``gap0``, and ``gap0 + phase v dt`` sweeps the impact through one step. Restitution
e = (relative velocity at ``duration``) / v. If e depended on the phase p, the rollout gradient of the struck body's
final position in the striker's start would carry (T - t_impact) / (2 dt) de/dp (see ``impact_phase.py``): the
bias this script predicts from its e(p), max over p of |de/dp| times (T - t_impact) / (2 dt).

Schemes (``--schemes``; each writes e per phase, its range, the predicted largest bias and the Newton iterations
spent; de/dphase is a finite difference over the phase grid, a lower bound where e varies within one grid cell):

- ``plain``: one step per dt (the stepper as it is);
- ``sub:K``: every step as K sub-steps of dt / K (what a failed step is retried with); its phases span one
  sub-step, the period of e;
- ``impact:K``: only the steps that start or are predicted to end within ``--contact-gap`` of contact as K
  sub-steps (adaptive sub-stepping of the impact steps);
- ``aligned:G:K``: the step in which the free-flight gap crosses G (metres) split at the crossing time, the rest of
  it in sub-steps of dt / K from there (a time-of-impact split: the contact always starts a sub-step at gap G);
- ``resolved:K``: the impact steps as K sub-steps, K large: the continuous model's impact (its contact lasts
  about a millisecond; e approaches 1, the potential being conservative).

Writes ``<out>/impact_model_1d.json``, ``.md`` (table) and ``.png`` (e against phase per scheme).

    python scripts/impact_model_1d.py --out results/impact_model_1d            # about 6 min on 2 cores
    python scripts/impact_model_1d.py --out results/impact_model_1d --quick    # 8 phases, 3 schemes
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from _cli import (
    apply_preset,
    folder_problem,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
)
from _provenance import git_revision, json_args
from tqdm import tqdm

from cfd_torch import ContactConfig, mesh_potential_derivatives, rigid_body

F64 = torch.float64
_SIDE = 0.1


class GapPotential:
    """P(g) and its first two derivatives for two face-to-face cubes of side 0.1 m with gap g."""

    def __init__(self) -> None:
        self.cube = rigid_body(trimesh.creation.box((_SIDE, _SIDE, _SIDE)))
        self.margin = ContactConfig().margin
        self.calls = 0

    def __call__(self, g: float) -> tuple[float, float, float]:
        self.calls += 1
        pa = torch.zeros(6, dtype=F64)
        pb = torch.zeros(6, dtype=F64)
        pb[0] = _SIDE + g
        d = mesh_potential_derivatives(self.cube.bsh, pa, self.cube.bsh, pb)
        return float(d.value), float(d.grad[6]), float(d.hessian[6, 6])


def implicit_step(P: GapPotential, g: float, v: float, h: float, mr: float) -> tuple[float, int]:
    """One implicit Euler step of length h from gap g closing at -v: the new gap and Newton iterations."""
    gt = g + h * v
    lo = P.margin * (1.0 + 1e-9)
    x = max(gt, g) if gt > lo else g  # a feasible start: the prediction when it is clear of the margin
    for it in range(1, 201):
        val, d1, d2 = P(x)
        f0 = mr / (2 * h * h) * (x - gt) ** 2 + val
        r = mr / (h * h) * (x - gt) + d1
        dx = -r / (mr / (h * h) + max(d2, 0.0) + 1e-12)
        a = 1.0
        while a > 1e-20:
            xn = x + a * dx
            if xn > lo:
                fn = mr / (2 * h * h) * (xn - gt) ** 2 + P(xn)[0]
                if fn <= f0 + 1e-4 * a * r * dx + 1e-15 * abs(f0):
                    break
            a *= 0.5
        x = xn
        if abs(a * dx) < 1e-13:
            return x, it
    raise RuntimeError(f"implicit step did not converge (g = {g:.6g}, v = {v:.6g}, h = {h:.3g})")


def schedule(scheme: str, g: float, v: float, dt: float, contact_gap: float) -> list[float]:
    """The sub-step lengths of one step of length dt from gap g with gap velocity v."""
    kind, *arg = scheme.split(":")
    if kind == "plain":
        return [dt]
    if kind == "sub":
        k = int(arg[0])
        return [dt / k] * k
    if kind in ("impact", "resolved"):
        k = int(arg[0])
        near = g < contact_gap or g + dt * v < contact_gap
        return [dt / k] * k if near else [dt]
    if kind == "aligned":
        G, k = float(arg[0]), int(arg[1])
        if g > G and g + dt * v < G:  # the free-flight gap crosses G in this step
            s = (g - G) / (-v)
            hs, rest, h = [s], dt - s, dt / k
            while rest > h * (1.0 + 1e-12):
                hs.append(h)
                rest -= h
            return hs + [rest]
        return [dt]
    raise ValueError(f"unknown scheme {scheme!r}")


def run(P: GapPotential, scheme: str, *, phase: float, v: float, dt: float, duration: float, gap0: float,
        contact_gap: float, mr: float) -> dict:  # fmt: skip
    """One impact: restitution, sub-steps and Newton iterations spent."""
    g, vel = gap0 + phase * v * dt, -v
    subs = iters = 0
    for _ in range(int(round(duration / dt))):
        for h in schedule(scheme, g, vel, dt, contact_gap):
            gn, it = implicit_step(P, g, vel, h, mr)
            vel, g = (gn - g) / h, gn
            subs, iters = subs + 1, iters + it
    return {"restitution": vel / v, "substeps": subs, "newton_iters": iters}


def scheme_arg(text: str) -> str:
    """An argparse ``type=`` for ``--schemes``: ``plain``, ``sub:K``, ``impact:K``, ``resolved:K`` or
    ``aligned:G:K`` (K an integer > 0, G a gap > 0 in metres), returned as given."""
    kind, *arg = text.split(":")
    try:
        if kind == "plain" and not arg:
            return text
        if kind in ("sub", "impact", "resolved") and len(arg) == 1:
            positive_int(arg[0])
            return text
        if kind == "aligned" and len(arg) == 2:
            positive_float(arg[0])
            positive_int(arg[1])
            return text
    except argparse.ArgumentTypeError:
        pass
    raise argparse.ArgumentTypeError(
        f"must be plain, sub:K, impact:K, resolved:K or aligned:G:K (K an integer > 0, G a number > 0), got {text!r}"
    )


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("results/impact_model_1d"), help="output folder")
    p.add_argument(
        "--schemes", nargs="+", type=scheme_arg, help="sub-stepping schemes (see the module docstring)",
        default=["plain", "sub:2", "sub:4", "sub:8", "impact:16", "impact:64", "aligned:0.002:1",
                 "aligned:0.008:1", "aligned:0.004:2"],
    )  # fmt: skip
    p.add_argument(
        "--phases", type=positive_int, default=16, help="phases per step, evenly spread over [0, 1)"
    )
    p.add_argument("--speed", type=positive_float, default=1.0, help="closing speed [m/s]")
    p.add_argument("--dt", type=positive_float, default=0.01, help="time step [s]")
    p.add_argument("--duration", type=positive_float, default=0.3, help="rollout length [s]")
    p.add_argument("--gap0", type=positive_float, default=0.01, help="gap at phase 0 [m]")
    p.add_argument(
        "--contact-gap", type=nonnegative_float, default=0.004, help="impact:K sub-steps below this gap [m]"
    )
    p.add_argument(
        "--resolved", type=nonnegative_int, default=1000, help="sub-steps of the resolved reference (0: skip)"
    )
    p.add_argument(
        "--quick", action="store_true", help="8 phases, plain / sub:4 / aligned:0.008:1 (where not given)"
    )
    args = p.parse_args(argv)
    if args.quick:  # its values for the settings not given
        apply_preset(
            p, args, {"phases": 8, "schemes": ["plain", "sub:4", "aligned:0.008:1"], "resolved": 0}, argv
        )
    if args.duration < args.dt:
        p.error(f"argument --duration: {args.duration:g} s is shorter than --dt {args.dt:g} s")
    margin = ContactConfig().margin  # GapPotential's
    if args.gap0 <= margin:
        p.error(
            f"argument --gap0: must exceed the contact margin {margin:g} m (the cubes start apart), got {args.gap0:g}"
        )
    # the latest phase reaches contact in free flight at gap0 / v + dt; a step more resolves it (else e is read
    # before the impact, e = -1, or after a far-field bounce, and the amplification T - t_impact is negative)
    late = args.gap0 / args.speed + 2 * args.dt
    if late > args.duration:
        p.error(
            f"argument --duration: {args.duration:g} s ends before the impact is over (gap0 / speed + 2 dt = "
            f"{late:g} s); give a longer --duration, a smaller --gap0 or a faster --speed"
        )
    for scheme in args.schemes:
        if scheme.startswith("aligned:") and float(scheme.split(":")[1]) >= args.gap0:
            p.error(
                f"argument --schemes: {scheme}: the gap G must lie below --gap0 ({args.gap0:g} m), else the "
                "phases that start below G never cross it and are stepped plain"
            )
    problem = folder_problem(args.out)
    if problem:
        p.error(f"argument --out: {problem}")
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    P = GapPotential()
    mr = 0.5 * float(P.cube.mass)
    t_impact = args.gap0 / args.speed  # (about: the impact at phase 0)
    amplification = (args.duration - t_impact) / (2.0 * args.dt)
    rows, t0 = [], time.time()
    bar = tqdm(total=len(args.schemes) * args.phases, desc="schemes x phases")
    for scheme in args.schemes:
        # uniform sub-steps of dt / K are steps of dt / K: e is periodic in the phase with period 1 / K, which the
        # phases then span (else a phase grid of 1 / phases would alias it)
        span = 1.0 / int(scheme.split(":")[1]) if scheme.startswith("sub:") else 1.0
        phases = [span * i / args.phases for i in range(args.phases)]
        rs = []
        for ph in phases:
            rs.append(run(
                P, scheme, phase=ph, v=args.speed, dt=args.dt, duration=args.duration, gap0=args.gap0,
                contact_gap=args.contact_gap, mr=mr,
            ))  # fmt: skip
            bar.update()
        e = np.array([r["restitution"] for r in rs])
        de = np.abs(np.diff(np.append(e, e[0]))) * args.phases / span  # e is periodic in the phase
        rows.append({
            "scheme": scheme, "phases": phases, "e": e.tolist(), "e_min": float(e.min()), "e_max": float(e.max()),
            "e_range": float(e.max() - e.min()), "max_de_dphase": float(de.max()),
            "predicted_max_bias": float(amplification * de.max()),
            "substeps_per_run": float(np.mean([r["substeps"] for r in rs])),
            "newton_iters_per_run": float(np.mean([r["newton_iters"] for r in rs])),
        })  # fmt: skip
    bar.close()
    resolved = None
    if args.resolved:  # the continuous model's impact: one phase, only the contact resolved finely
        r = run(
            P, f"resolved:{args.resolved}", phase=0.0, v=args.speed, dt=args.dt, duration=args.duration,
            gap0=args.gap0, contact_gap=args.contact_gap, mr=mr,
        )  # fmt: skip
        resolved = {"substeps_per_impact_step": args.resolved, **r}
    plain = next((r for r in rows if r["scheme"] == "plain"), None)
    for r in rows:
        r["cost_vs_plain"] = r["newton_iters_per_run"] / plain["newton_iters_per_run"] if plain else None
    result = {
        "revision": git_revision(), "args": json_args(args),
        "reduced_mass": mr, "amplification": amplification, "wall_s": time.time() - t0,
        "schemes": rows, "resolved": resolved,
    }  # fmt: skip
    (args.out / "impact_model_1d.json").write_text(json.dumps(result, indent=1))
    lines = [
        f"v = {args.speed:g} m/s, dt = {args.dt:g} s, T = {args.duration:g} s: predicted bias = "
        f"{amplification:.1f} x max |de/dphase|",
        "",
        "| scheme | e range | e spread | max abs de/dphase | predicted max abs bias | Newton iterations (x plain) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        cost = f"{r['cost_vs_plain']:.1f}" if r["cost_vs_plain"] is not None else "-"
        lines.append(
            f"| {r['scheme']} | {r['e_min']:.4f}-{r['e_max']:.4f} | {r['e_range']:.4f} | {r['max_de_dphase']:.4f} "
            f"| {r['predicted_max_bias']:.3f} | {cost} |"
        )
    if resolved:
        lines += ["", f"resolved ({args.resolved} sub-steps per impact step, phase 0): e = "
                      f"{resolved['restitution']:.4f}"]  # fmt: skip
    table = "\n".join(lines)
    (args.out / "impact_model_1d.md").write_text(f"revision {result['revision']}\n\n{table}\n")
    print(table)
    _plot(rows, args.out / "impact_model_1d.png")
    return result


def _plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in rows:
        e = np.array(r["e"])
        ax.plot(r["phases"], e - e.mean(), "o-", ms=3, label=f"{r['scheme']} (mean e {e.mean():.3f})")
    ax.set_xlabel("impact phase (fraction of a step; sub:K over one sub-step, 1 / K)")
    ax.set_ylabel("restitution minus its mean over phases")
    ax.set_title("1-D cube impact under implicit Euler: e against phase")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
