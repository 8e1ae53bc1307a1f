"""Cost of the BSH contact potential of two meshes: scaling, ipctk side by side, run time vs error, large triangles.

Every timing is the median of ``--repeats`` runs after one warm-up, on the CPU, float64 unless stated.

1. scaling: two icospheres of radius 1 (subdivisions 1..5 = 80..20480 faces each), (a) near contact (surface gap
   2 x margin, two faces parallel and facing each other) and (b) apart (gap 1.0). Ours:
   ``mesh_potential_derivatives`` (value, 12-gradient, 12 x 12 Hessian in the two poses). Brute force: the pair
   potential of all T_a x T_b triangle pairs with their 18-gradients and 18 x 18 Hessians
   (``pair_potential_derivatives``, chunked), summed value; it is not reduced to the 12 pose coordinates, so it is
   a lower bound on a brute-force evaluation. Brute force is skipped at a size whose extrapolated time (T^2 from
   the previous size) exceeds ``--brute-max-s``. Fitted exponent of time vs T (log-log least squares): ours on
   T >= ``--fit-min-faces``, brute force on all its sizes.
2. ipctk (IPC Toolkit 1.6.1) on the same near-contact meshes, dhat = 1e-2, kappa = 1, only inter-body pairs
   (``make_connected_components_filter``): ``NormalCollisions().build`` (LBVH broad phase + narrow phase) + barrier
   value + vertex gradient + sparse vertex Hessian (no PSD projection). ``CollisionMesh`` construction is set-up and
   not timed. The chain rule from ipctk's vertex derivatives to the 12 pose coordinates (J^T g, J^T H J + second-order
   rotation term) is timed separately. Ratio ours / ipctk per size.
3. run time vs error: subdivision-3 spheres in near contact at looser plane-solve tolerances, float64 and float32
   poses, against a float64 reference at the tightest tolerance accepted (1e-14 first). Rows with eps in
   {0.01, 0.1, 1.0} are a different potential each: their cost only.
4. large triangles: a 320-face ball (radius 0.5) 2e-3 above a 12-triangle box (extents 4 x 4 x 0.5, top face at
   z = 0) vs two 320-face balls 2e-3 apart; the box's BSH without refinement, as a ``Scene`` refines it with no
   tuning argument (``refine_obstacles``), and with ``max_edge`` = k x the ball's mean edge length
   (``--edge-factors``); each row's time also as a ratio to the two balls' (the cases timed in turn, round after
   round, at least 9 rounds: the ratios see the same machine load). ``--obstacle PATH`` adds the ball 2 mm
   above that mesh (any file trimesh reads; placed as in ``bench_step.py``'s obstacle case), as given and as a
   Scene refines it.

Writes ``<out>/bench_contact.json``, ``<out>/bench_contact_scaling.png``, ``<out>/bench_contact_error.png`` and prints
tables.

    python scripts/bench_contact.py --out results/bench_contact            # ~10 min on 2 cores
    python scripts/bench_contact.py --out results/bench_contact_quick --quick   # ~1 min
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from _cli import nonnegative_int, positive_float, positive_int  # noqa: E402

try:
    import ipctk
except ModuleNotFoundError as err:  # the baseline this script times against
    raise SystemExit(f"{err}: scripts/bench_contact.py needs IPC Toolkit: pip install '.[bench]'") from None
from _provenance import git_revision, json_args  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cfd_torch  # noqa: E402
from cfd_torch import BSH, Scene, mesh_potential_derivatives, pair_potential_derivatives, rigid_body  # noqa: E402
from cfd_torch.rotation import rotation_derivatives, transform_points  # noqa: E402

TIMED = {
    "ours": "mesh_potential_derivatives(bsh_a, pose_a, bsh_b, pose_b, hessian=True): BSH traversal, leaf pair "
    "solves, value + gradient (12,) + Hessian (12, 12) in the two poses [t_a, omega_a, t_b, omega_b]. The BSHs are "
    "built once beforehand (set-up, not timed).",
    "brute_force": "all T_a x T_b leaf pairs: world triangles (transform_points) + pair_potential_derivatives in "
    "chunks of --brute-chunk pairs (value, per-pair 18-gradient and 18 x 18 Hessian) + sum of the values. The "
    "per-pair derivatives are NOT reduced to the 12 pose coordinates (that would only add cost): a lower bound.",
    "ipctk": "NormalCollisions().build(mesh, V, dhat) (default LBVH broad phase + narrow phase) + "
    "BarrierPotential(dhat, 1.0)(C, mesh, V) + .gradient (3V,) + .hessian (3V x 3V scipy CSC, "
    "PSDProjectionMethod.NONE). CollisionMesh construction (with the connected-components filter) and the world "
    "vertices V are set-up, not timed.",
    "ipctk_rigid_map": "chain rule from ipctk's vertex gradient/Hessian to the 12 pose coordinates: rotation "
    "derivatives of both poses, J (3V x 12), J^T g, J^T (H J) on H's non-zero rows, plus the second-order rotation "
    "term sum_v g_v . d2x_v/domega2. Reported separately (column 'map').",
}


# ------------------------------------------------------------------------------------------------ geometry set-up
def sphere_pair(
    subdivisions: int, radius: float, gap: float
) -> tuple[trimesh.Trimesh, torch.Tensor, torch.Tensor]:
    """An icosphere and two poses whose surfaces are exactly ``gap`` apart, two faces parallel and facing.

    The mesh is rotated so that the face whose normal is closest to +x has normal +x (plane x = h). Body a sits at
    the origin; body b is the same mesh turned by pi about z (that face now has normal -x) at x = 2 h + gap. Both
    meshes are convex, so the distance between them is the distance between those two planes.

    Returns:
        mesh (body frame), pose_a (6,), pose_b (6,) float64 (translation, rotation vector).
    """
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    f = int(np.argmax(mesh.face_normals[:, 0]))
    mesh.apply_transform(trimesh.geometry.align_vectors(mesh.face_normals[f], [1.0, 0.0, 0.0]))
    h = float(mesh.vertices[mesh.faces[f], 0].mean())
    assert mesh.vertices[:, 0].max() <= h + 1e-12 * radius, "the aligned face must be the support in +x"
    pose_a = torch.zeros(6, dtype=torch.float64)
    pose_b = torch.tensor([2.0 * h + gap, 0.0, 0.0, 0.0, 0.0, math.pi], dtype=torch.float64)
    return mesh, pose_a, pose_b


def ball_on_box(gap: float) -> tuple[trimesh.Trimesh, torch.Tensor, trimesh.Trimesh, torch.Tensor]:
    """A 320-face ball (radius 0.5) whose lowest vertex is ``gap`` above a 4 x 4 x 0.5 box's top face (z = 0).

    The ball is off the box's centre (x, y = 0.31, 0.17) so that it does not sit on the top face's diagonal.
    """
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    box = trimesh.creation.box(extents=(4.0, 4.0, 0.5))
    pose_ball = torch.tensor(
        [0.31, 0.17, gap - float(ball.vertices[:, 2].min()), 0, 0, 0], dtype=torch.float64
    )
    pose_box = torch.tensor([0.0, 0.0, -float(box.vertices[:, 2].max()), 0, 0, 0], dtype=torch.float64)
    return ball, pose_ball, box, pose_box


# ------------------------------------------------------------------------------------------------ timing
def timed(fn, repeats: int, budget_s: float = math.inf, warmup: bool = True) -> dict:
    """Median wall time of ``fn()`` over ``repeats`` runs (fewer once ``budget_s`` is spent; at least one)."""
    out = fn() if warmup else None
    times: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if sum(times) > budget_s:
            break
    return {"median_s": statistics.median(times), "times_s": times, "out": out}


def ours_fn(bsh_a, pose_a, bsh_b, pose_b, **kw):
    return lambda: mesh_potential_derivatives(bsh_a, pose_a, bsh_b, pose_b, **kw)


def brute_force(bsh_a: BSH, pose_a, bsh_b: BSH, pose_b, *, mu: float, margin: float, chunk: int) -> float:
    """Sum over all leaf pairs of the exact pair potential, with per-pair 18-gradients and 18 x 18 Hessians."""
    ta = transform_points(pose_a, bsh_a.vertices)[bsh_a.faces]  # (Ta, 3, 3)
    tb = transform_points(pose_b, bsh_b.vertices)[bsh_b.faces]  # (Tb, 3, 3)
    rows = max(1, chunk // tb.shape[0])
    total = 0.0
    for i in range(0, ta.shape[0], rows):
        d = pair_potential_derivatives(ta[i : i + rows, None], tb[None], mu=mu, margin=margin, hessian=True)
        total += float(d.value.sum())
    return total


# ------------------------------------------------------------------------------------------------ ipctk
class IpcScene:
    """Two copies of one mesh at two poses as one ipctk collision mesh (inter-body pairs only)."""

    def __init__(self, mesh: trimesh.Trimesh, pose_a: torch.Tensor, pose_b: torch.Tensor, dhat: float):
        self.X = np.asarray(mesh.vertices, dtype=np.float64)  # (n, 3) body frame
        self.poses = torch.stack([pose_a, pose_b])
        X = torch.from_numpy(self.X)
        self.V = torch.cat([transform_points(pose_a, X), transform_points(pose_b, X)]).numpy()  # (2n, 3)
        F = np.asarray(mesh.faces, dtype=np.int32)
        F = np.concatenate([F, F + self.X.shape[0]]).astype(np.int32)
        self.mesh = ipctk.CollisionMesh(self.V, ipctk.edges(F), F)
        self.mesh.can_collide = ipctk.make_connected_components_filter(F)
        self.dhat = dhat
        self.B = ipctk.BarrierPotential(dhat, 1.0)

    def evaluate(self) -> dict:
        """One build + value + gradient + Hessian; wall time of each stage."""
        t0 = time.perf_counter()
        C = ipctk.NormalCollisions()
        C.build(self.mesh, self.V, self.dhat)
        t1 = time.perf_counter()
        value = self.B(C, self.mesh, self.V)
        t2 = time.perf_counter()
        g = self.B.gradient(C, self.mesh, self.V)
        t3 = time.perf_counter()
        H = self.B.hessian(C, self.mesh, self.V, ipctk.PSDProjectionMethod.NONE)
        t4 = time.perf_counter()
        return {
            "build": t1 - t0, "value": t2 - t1, "grad": t3 - t2, "hess": t4 - t3, "total": t4 - t0,
            "C": C, "energy": value, "g": g, "H": H,
        }  # fmt: skip

    def to_rigid(self, g: np.ndarray, H) -> tuple[np.ndarray, np.ndarray]:
        """Chain rule to the 12 pose coordinates: J^T g and J^T H J + sum_v g_v . d2x_v / d omega2.

        Only the active vertices (non-zero rows of the symmetric H, a superset of the non-zero entries of g) enter.
        """
        _, dR, d2R = rotation_derivatives(self.poses[:, 3:])
        dR, d2R = dR.numpy(), d2R.numpy()  # (2, 3, 3, 3), (2, 3, 3, 3, 3); last indices = omega components
        n = self.X.shape[0]
        act = np.unique(np.flatnonzero(np.diff(H.indptr)) // 3)  # active vertices of both bodies
        body, X = act // n, self.X[act % n]  # (A,), (A, 3)
        J = np.zeros((act.size, 3, 12))
        ga = g.reshape(-1, 3)[act]  # (A, 3)
        Hq_rot = np.zeros((12, 12))
        for b in range(2):
            m = body == b
            J[m, :, 6 * b : 6 * b + 3] = np.eye(3)
            J[m, :, 6 * b + 3 : 6 * b + 6] = np.einsum("imk,vm->vik", dR[b], X[m])
            rot = np.einsum("imkl,im->kl", d2R[b], ga[m].T @ X[m])
            Hq_rot[6 * b + 3 : 6 * b + 6, 6 * b + 3 : 6 * b + 6] = rot
        dofs = (3 * act[:, None] + np.arange(3)).reshape(-1)
        J = J.reshape(-1, 12)  # (3A, 12)
        gq = J.T @ g[dofs]
        Hq = J.T @ (H[dofs][:, dofs] @ J) + Hq_rot
        return gq, Hq


# ------------------------------------------------------------------------------------------------ sections
def section_scaling(args, cache: dict) -> dict:
    rows, skipped = [], []
    jobs = [
        (s, name, gap) for s in args.subdivisions for name, gap in (("near", 2 * args.margin), ("apart", 1.0))
    ]
    brute_last: dict[str, tuple[int, float]] = {}
    for s, name, gap in tqdm(jobs, desc="1 scaling"):
        mesh, pa, pb = sphere_pair(s, 1.0, gap)
        bsh = BSH.from_trimesh(mesh)
        T = bsh.num_faces
        r = timed(ours_fn(bsh, pa, bsh, pb, mu=args.mu, margin=args.margin, eps=args.eps), args.repeats)
        d = r.pop("out")
        row = {
            "subdivisions": s, "faces": T, "config": name, "gap": gap, "ours_s": r["median_s"],
            "ours_times_s": r["times_s"], "node_pairs": d.stats["node_pairs"], "leaf_pairs": d.stats["leaf_pairs"],
            "value": float(d.value), "grad_norm": float(d.grad.norm()),
        }  # fmt: skip
        cache[(s, name)] = row
        last = brute_last.get(name)
        predicted = None if last is None else last[1] * (T / last[0]) ** 2
        if predicted is not None and predicted > args.brute_max_s:
            row["brute_s"] = None
            row["brute_skipped"] = f"extrapolated {predicted:.0f} s > --brute-max-s {args.brute_max_s:g}"
            skipped.append({"faces": T, "config": name, "reason": row["brute_skipped"]})
        else:
            b = timed(
                lambda bsh=bsh, pa=pa, pb=pb: brute_force(
                    bsh, pa, bsh, pb, mu=args.mu, margin=args.margin, chunk=args.brute_chunk
                ),
                args.repeats, budget_s=2 * args.brute_max_s, warmup=False,
            )  # fmt: skip
            row.update(
                brute_s=b["median_s"], brute_times_s=b["times_s"], brute_value=b["out"], brute_pairs=T * T
            )
            brute_last[name] = (T, b["median_s"])
        rows.append(row)

    fits = {}
    for name in ("near", "apart"):
        sel = [r for r in rows if r["config"] == name]
        for method, key, lo in (("ours", "ours_s", args.fit_min_faces), ("brute_force", "brute_s", 0)):
            pts = [(r["faces"], r[key]) for r in sel if r.get(key) is not None and r["faces"] >= lo]
            if len(pts) >= 2:
                slope, _ = np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)
                fits[f"{method}/{name}"] = {"exponent": float(slope), "faces": [p[0] for p in pts]}
            else:
                fits[f"{method}/{name}"] = {
                    "exponent": None,
                    "faces": [p[0] for p in pts],
                    "why": "< 2 sizes",
                }
    return {"rows": rows, "brute_skipped": skipped, "fits": fits}


def section_ipctk(args, cache: dict) -> dict:
    rows = []
    for s in tqdm(args.ipc_subdivisions, desc="2 ipctk"):
        mesh, pa, pb = sphere_pair(s, 1.0, 2 * args.margin)
        scene = IpcScene(mesh, pa, pb, args.dhat)
        e = scene.evaluate()  # warm-up
        scene.to_rigid(e["g"], e["H"])
        runs, maps = [], []
        for _ in range(args.repeats):
            e = scene.evaluate()
            t0 = time.perf_counter()
            scene.to_rigid(e["g"], e["H"])
            maps.append(time.perf_counter() - t0)
            runs.append(e)
        med = {k: statistics.median(e[k] for e in runs) for k in ("build", "value", "grad", "hess", "total")}
        e = runs[-1]
        ours = cache.get((s, "near"))
        if ours is None:
            bsh = BSH.from_trimesh(mesh)
            r = timed(ours_fn(bsh, pa, bsh, pb, mu=args.mu, margin=args.margin, eps=args.eps), args.repeats)
            ours = {"ours_s": r["median_s"]}
        map_s = statistics.median(maps)
        min_dist = math.sqrt(e["C"].compute_minimum_distance(scene.mesh, scene.V))  # ipctk returns it squared
        rows.append(
            {
                "subdivisions": s, "faces": len(mesh.faces), "vertices_total": scene.V.shape[0],
                "collisions": len(e["C"]), "min_distance": min_dist,
                "hessian_nnz": int(e["H"].nnz), "energy": float(e["energy"]),
                "grad_norm": float(np.linalg.norm(e["g"])),
                **{f"ipc_{k}_s": v for k, v in med.items()}, "ipc_map_s": map_s,
                "ours_s": ours["ours_s"], "ratio_ours_over_ipc": ours["ours_s"] / med["total"],
                "ratio_ours_over_ipc_with_map": ours["ours_s"] / (med["total"] + map_s),
            }
        )  # fmt: skip
    return {"dhat": args.dhat, "kappa": 1.0, "threads": ipctk.get_num_threads(), "rows": rows}


def _errors(d, ref) -> dict:
    v, g, H = (float(d.value), d.grad.double(), d.hessian.double())
    return {
        "value_rel_err": abs(v - float(ref.value)) / abs(float(ref.value)),
        "grad_rel_err": float((g - ref.grad).norm() / ref.grad.norm()),
        "hess_rel_err": float((H - ref.hessian).norm() / ref.hessian.norm()),
    }


def section_error(args) -> dict:
    mesh, pa, pb = sphere_pair(args.error_subdivisions, 1.0, 2 * args.margin)
    bsh = BSH.from_trimesh(mesh)
    kw = {"mu": args.mu, "margin": args.margin}
    ref, ref_tol, refused = None, None, []
    for tol in (1e-14, 1e-13, 1e-12):
        try:
            ref = mesh_potential_derivatives(bsh, pa, bsh, pb, eps=0.01, tol=tol, **kw)
            ref_tol = tol
            break
        except (ValueError, cfd_torch.PairSolveError) as err:
            refused.append({"tol": tol, "error": f"{type(err).__name__}: {err}"})
    tol_rows, eps_rows, f32_note = [], [], None
    jobs = [("tol", tol, dt) for tol in args.tols for dt in ("float64", "float32")]
    jobs += [("eps", eps, "float64") for eps in args.eps_values]
    for kind, x, dt in tqdm(jobs, desc="3 error"):
        qa, qb = pa.to(getattr(torch, dt)), pb.to(getattr(torch, dt))
        params = {"eps": 0.01, "tol": x} if kind == "tol" else {"eps": x, "tol": 1e-12}
        try:
            r = timed(ours_fn(bsh, qa, bsh, qb, **kw, **params), args.repeats)
        except (TypeError, ValueError) as err:  # an API that refuses float32 poses
            f32_note = f"{dt} refused: {type(err).__name__}: {err}"
            continue
        except cfd_torch.PairSolveError as err:
            tol_rows.append({"tol": x, "dtype": dt, "error": str(err)})
            continue
        d = r.pop("out")
        row = {"dtype": dt, **params, "time_s": r["median_s"], "times_s": r["times_s"], **d.stats}
        if kind == "tol":
            tol_rows.append({**row, **_errors(d, ref)})
        else:
            eps_rows.append({**row, "value": float(d.value), "grad_norm": float(d.grad.norm())})
    return {
        "subdivisions": args.error_subdivisions, "faces": bsh.num_faces, "gap": 2 * args.margin,
        "reference": {"tol": ref_tol, "eps": 0.01, "dtype": "float64", "value": float(ref.value),
                      "grad_norm": float(ref.grad.norm()), "refused": refused},
        "float32": f32_note or "float32 poses accepted (BSH stays float64; the solve runs in float64)",
        "errors": "relative: |v - v_ref| / |v_ref|, ||g - g_ref||_2 / ||g_ref||_2, ||H - H_ref||_F / ||H_ref||_F",
        "tol_rows": tol_rows,
        "eps_rows_note": "each eps is a different potential (blend band width); cost only, no error",
        "eps_rows": eps_rows,
    }  # fmt: skip


def section_large(args) -> dict:
    gap = 2e-3
    ball, p_ball, box, p_box = ball_on_box(gap)
    mean_edge = float(ball.edges_unique_length.mean())
    kw = {"mu": args.mu, "margin": args.margin, "eps": args.eps}
    # (case, obstacle mesh, its pose, max_edge factor: None as given, "scene" as a Scene refines it with no tuning)
    cases = [
        ("ball-ball", None, None, None),
        ("ball-box", box, p_box, None),
        ("ball-box", box, p_box, "scene"),
    ]
    cases += [("ball-box", box, p_box, k) for k in args.edge_factors]
    poses = {"ball-box": p_ball}
    if args.obstacle is not None:
        from _placement import ball_over, load_obstacle

        obstacle = load_obstacle(args.obstacle)
        poses["ball-obstacle"] = torch.tensor([*ball_over(obstacle, 0.5, gap), 0, 0, 0], dtype=torch.float64)
        p_obs = torch.zeros(6, dtype=torch.float64)
        cases += [("ball-obstacle", obstacle, p_obs, None), ("ball-obstacle", obstacle, p_obs, "scene")]
    bsh_ball = BSH.from_trimesh(ball)
    rows, fns = [], []
    for name, mesh, pb, k in cases:
        t0 = time.perf_counter()
        if name == "ball-ball":
            mesh, pa, pb = sphere_pair(2, 0.5, gap)
            bsh_a = bsh_b = BSH.from_trimesh(mesh)
        else:
            bsh_a, pa = bsh_ball, poses[name]
            if k == "scene":  # what a user gets: the Scene's automatic refinement of a static body
                sc = Scene([rigid_body(ball), rigid_body(mesh, kind="static")])
                bsh_b = sc.bodies[1].bsh
            else:
                bsh_b = BSH.from_trimesh(mesh, max_edge=None if k is None else k * mean_edge)
        build_s = time.perf_counter() - t0
        fns.append(ours_fn(bsh_a, pa, bsh_b, pb, **kw))
        d = fns[-1]()  # also the warm-up
        rows.append(
            {
                "case": name, "max_edge_factor": k,
                "max_edge": k * mean_edge if isinstance(k, float) else None,
                "faces_a": bsh_a.num_faces, "faces_b": bsh_b.num_faces, "bsh_b_build_s": build_s, "times_s": [],
                **d.stats, "value": float(d.value), "grad_norm": float(d.grad.norm()),
            }
        )  # fmt: skip
    # the cases in turn, round after round: the ratios to the two balls see the same machine load
    for _ in tqdm(range(max(args.repeats, 9)), desc="4 large triangles (rounds)"):
        for row, fn in zip(rows, fns, strict=True):
            t0 = time.perf_counter()
            fn()
            row["times_s"].append(time.perf_counter() - t0)
    for r in rows:
        r["time_s"] = statistics.median(r["times_s"])
        r["vs_ball_ball"] = r["time_s"] / rows[0]["time_s"]
    return {"gap": gap, "ball_mean_edge": mean_edge, "obstacle": args.obstacle, "rows": rows}


# ------------------------------------------------------------------------------------------------ output
def plot_scaling(res: dict, ipc: dict | None, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, name in zip(axes, ("near", "apart"), strict=True):
        rows = [r for r in res["rows"] if r["config"] == name]
        for key, label, style in (
            ("ours_s", "ours (BSH)", "o-"),
            ("brute_s", "brute force (all leaf pairs)", "s--"),
        ):
            pts = [(r["faces"], r[key]) for r in rows if r.get(key) is not None]
            method = "ours" if key == "ours_s" else "brute_force"
            p = res["fits"][f"{method}/{name}"]["exponent"]
            if pts:
                ax.loglog(*zip(*pts, strict=True), style, label=label + (f", slope {p:.2f}" if p else ""))
        if name == "near" and ipc:
            pts = [(r["faces"], r["ipc_total_s"]) for r in ipc["rows"]]
            ax.loglog(
                *zip(*pts, strict=True), "^:", label=f"ipctk build+value+grad+hess (dhat {ipc['dhat']:g})"
            )
        ax.set_title(f"{name} ({'gap 2 x margin' if name == 'near' else 'gap 1.0'})")
        ax.set_xlabel("faces per body T")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("value + gradient + Hessian [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_error(res: dict, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for dt, marker in (("float64", "o"), ("float32", "s")):
        rows = [r for r in res["tol_rows"] if r.get("dtype") == dt and "time_s" in r]
        for key, color in (("value_rel_err", "C0"), ("grad_rel_err", "C1")):
            if rows:
                err = [max(r[key], 1e-17) for r in rows]
                mfc = "none" if dt == "float32" else color
                label = f"{key.split('_')[0]} error, {dt}"
                ax.semilogy(  # the times span less than a decade: a linear axis labels them
                    [1e3 * r["time_s"] for r in rows],
                    err,
                    marker + "-",
                    lw=0.7,
                    color=color,
                    mfc=mfc,
                    label=label,
                )
        for r in rows:
            ax.annotate(f"{r['tol']:.0e}", (1e3 * r["time_s"], max(r["grad_rel_err"], 1e-17)), fontsize=7)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel(f"relative error vs tol={res['reference']['tol']:.0e} float64 (0 drawn at 1e-17)")
    ax.set_title(f"plane-solve tol, subdivision {res['subdivisions']}, near contact")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[1]
    eps = res["eps_rows"]
    ax.bar([f"eps={r['eps']:g}" for r in eps], [r["time_s"] for r in eps], color="C2")
    for i, r in enumerate(eps):
        ax.annotate(
            f"{r['leaf_pairs']} leaf\n{r['node_pairs']} node", (i, r["time_s"]), ha="center", fontsize=7
        )
    ax.set_ylabel("time [s]")
    ax.set_title("blend width eps (different potential each): cost")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _ms(x: float | None) -> str:
    return "skipped" if x is None else f"{1e3 * x:.2f}"


def print_tables(out: dict) -> None:
    if "scaling" in out:
        res = out["scaling"]
        print("\n1. scaling: value + gradient + Hessian [ms] (median)")
        print(
            f"| {'T':>6} | {'config':6} | {'ours':>9} | {'node pairs':>10} | {'leaf pairs':>10} | {'brute':>10} |"
        )
        print("|" + "-" * 70 + "|")
        for r in res["rows"]:
            print(
                f"| {r['faces']:>6} | {r['config']:6} | {_ms(r['ours_s']):>9} | {r['node_pairs']:>10} "
                f"| {r['leaf_pairs']:>10} | {_ms(r.get('brute_s')):>10} |"
            )
        for k, f in res["fits"].items():
            e = f["exponent"]
            shown = f"n/a ({f.get('why', '')})" if e is None else f"{e:.2f}"
            print(f"  exponent {k}: {shown} over T={f['faces']}")
    if "ipctk" in out:
        res = out["ipctk"]
        print(
            f"\n2. ipctk (dhat {res['dhat']:g}, {res['threads']} threads) vs ours, near contact [ms] (median)"
        )
        hdr = ("T", "coll", "build", "value", "grad", "hess", "ipc tot", "map", "ours", "ours/ipc", "+map")
        print("| " + " | ".join(f"{h:>8}" for h in hdr) + " |")
        print("|" + "-" * (11 * len(hdr) - 1) + "|")
        for r in res["rows"]:
            cells = [f"{r['faces']}", f"{r['collisions']}"]
            cells += [_ms(r[f"ipc_{k}_s"]) for k in ("build", "value", "grad", "hess", "total", "map")]
            cells += [
                _ms(r["ours_s"]),
                f"{r['ratio_ours_over_ipc']:.1f}",
                f"{r['ratio_ours_over_ipc_with_map']:.1f}",
            ]
            print("| " + " | ".join(f"{c:>8}" for c in cells) + " |")
    if "error" in out:
        res = out["error"]
        print(
            f"\n3. run time vs error (subdivision {res['subdivisions']}, reference tol {res['reference']['tol']:g})"
        )
        print(f"   {res['float32']}")
        print(
            f"| {'tol':>7} | {'dtype':7} | {'time ms':>8} | {'value err':>9} | {'grad err':>9} | {'hess err':>9} |"
        )
        print("|" + "-" * 67 + "|")
        for r in res["tol_rows"]:
            if "error" in r:
                print(f"| {r['tol']:>7.0e} | {r['dtype']:7} | failed: {r['error'][:60]}")
                continue
            print(
                f"| {r['tol']:>7.0e} | {r['dtype']:7} | {_ms(r['time_s']):>8} | {r['value_rel_err']:>9.1e} "
                f"| {r['grad_rel_err']:>9.1e} | {r['hess_rel_err']:>9.1e} |"
            )
        print("   eps (a different potential each; cost only):")
        for r in res["eps_rows"]:
            print(
                f"   eps={r['eps']:<5g} {_ms(r['time_s']):>8} ms  node pairs {r['node_pairs']:>7}  "
                f"leaf pairs {r['leaf_pairs']:>6}  value {r['value']:.4e}"
            )
    if "large_triangles" in out:
        res = out["large_triangles"]
        print(f"\n4. large triangles (gap {res['gap']:g}, ball mean edge {res['ball_mean_edge']:.4f})")
        print(
            f"| {'case':13} | {'max_edge':>12} | {'faces b':>7} | {'node pairs':>10} | {'leaf pairs':>10} | {'ms':>8} "
            f"| {'/ ball-ball':>6} |"
        )
        print("|" + "-" * 90 + "|")
        for r in res["rows"]:
            k = r["max_edge_factor"]
            me = "none" if k is None else "Scene" if k == "scene" else f"{k:g}x={r['max_edge']:.3f}"
            print(
                f"| {r['case']:13} | {me:>12} | {r['faces_b']:>7} | {r['node_pairs']:>10} | {r['leaf_pairs']:>10} "
                f"| {_ms(r['time_s']):>8} | {r.get('vs_ball_ball', float('nan')):>6.2f} |"
            )


SECTIONS = ("scaling", "ipctk", "error", "large")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/bench_contact"), help="output folder")
    ap.add_argument("--quick", action="store_true", help="small sizes, 3 repeats (under a minute)")
    ap.add_argument(
        "--repeats", type=positive_int, default=None, help="timed runs per case (default 5, quick 3)"
    )
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS), help="sections to run")
    ap.add_argument("--mu", type=positive_float, default=1e-8, help="the potential's mu")
    ap.add_argument("--margin", type=positive_float, default=1e-3, help="contact margin; near gap 2 x margin")
    ap.add_argument("--eps", type=positive_float, default=0.01, help="the potential's eps")
    ap.add_argument("--dhat", type=positive_float, default=1e-2, help="ipctk activation distance")
    ap.add_argument(
        "--brute-max-s", type=float, default=None, help="skip brute force above this (default 20, quick 2)"
    )
    ap.add_argument(
        "--brute-chunk",
        type=positive_int,
        default=1 << 15,
        help="leaf pairs per pair_potential_derivatives call",
    )
    ap.add_argument(
        "--fit-min-faces",
        type=nonnegative_int,
        default=1000,
        help="fit our exponent on sizes of this many faces up",
    )
    ap.add_argument(
        "--edge-factors",
        type=positive_float,
        nargs="+",
        default=[2.0, 1.0],
        help="large: max_edge / ball's edge",
    )
    ap.add_argument(
        "--obstacle", default=None, metavar="PATH",
        help="large: also the ball 2 mm above this mesh file (as given, and as a Scene refines it)",
    )  # fmt: skip
    args = ap.parse_args()
    if args.brute_max_s is not None and not args.brute_max_s > 0:  # inf: never skip
        ap.error(f"argument --brute-max-s: must be a number > 0, got {args.brute_max_s!r}")
    if args.obstacle is not None and not Path(args.obstacle).is_file():
        ap.error(f"argument --obstacle: no such file: {args.obstacle}")
    if args.obstacle is not None and "large" not in args.sections:
        ap.error("argument --obstacle: only the 'large' section uses it; add it to --sections")
    if args.obstacle is not None:  # a mesh the ball cannot be placed on is refused before any section runs
        from _placement import ball_over, load_obstacle

        try:
            ball_over(load_obstacle(args.obstacle), 0.5, 2e-3)
        except ValueError as err:
            ap.error(f"argument {err}")
    if args.repeats is None:
        args.repeats = 3 if args.quick else 5
    if args.brute_max_s is None:
        args.brute_max_s = 2.0 if args.quick else 20.0
    args.subdivisions = [1, 2, 3, 4] if args.quick else [1, 2, 3, 4, 5]
    args.ipc_subdivisions = [3, 4] if args.quick else [3, 4, 5]
    args.error_subdivisions = 3
    args.tols = [1e-4, 1e-8, 1e-12] if args.quick else [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
    args.eps_values = [0.01, 0.1, 1.0]
    args.out.mkdir(parents=True, exist_ok=True)

    # JIT compile the pair kernels outside every timing
    tiny, qa, qb = sphere_pair(1, 1.0, 2 * args.margin)
    tb = BSH.from_trimesh(tiny)
    mesh_potential_derivatives(tb, qa, tb, qb, mu=args.mu, margin=args.margin)
    brute_force(tb, qa, tb, qb, mu=args.mu, margin=args.margin, chunk=args.brute_chunk)

    out: dict = {
        "meta": {
            "torch": torch.__version__, "torch_threads": torch.get_num_threads(), "ipctk": ipctk.__version__,
            "ipctk_threads": ipctk.get_num_threads(), "numpy": np.__version__, "trimesh": trimesh.__version__,
            "machine": platform.processor() or platform.machine(), "git": git_revision(), "repeats": args.repeats,
            "quick": args.quick, "mu": args.mu, "margin": args.margin, "eps": args.eps, "split": "both",
            "loadavg_start": os.getloadavg(),
            "args": json_args(args),
        },
        "timed": TIMED,
    }  # fmt: skip
    cache: dict = {}
    if "scaling" in args.sections:
        out["scaling"] = section_scaling(args, cache)
    if "ipctk" in args.sections:
        out["ipctk"] = section_ipctk(args, cache)
    if "error" in args.sections:
        out["error"] = section_error(args)
    if "large" in args.sections:
        out["large_triangles"] = section_large(args)

    out["meta"]["loadavg_end"] = os.getloadavg()  # > torch threads means the timings shared the CPU
    (args.out / "bench_contact.json").write_text(json.dumps(out, indent=1))
    if "scaling" in out:
        plot_scaling(out["scaling"], out.get("ipctk"), args.out / "bench_contact_scaling.png")
    if "error" in out:
        plot_error(out["error"], args.out / "bench_contact_error.png")
    print_tables(out)
    print(f"wrote {args.out / 'bench_contact.json'} and plots next to it")


if __name__ == "__main__":
    main()
