"""Tests of the batched BSH mesh potential (cfd_torch.mesh_potential and friends) against the naive recursive
reference (cfd_torch.mesh_reference) and against the four properties of SPEC section 1.

Conventions: poses are (6,) or (B, 6) float64, translation then rotation vector; grad / Hessian coordinates are
[t_a, omega_a, t_b, omega_b]. "Gap" is the exact distance between the two triangle meshes (all triangle pairs),
"r" the distance between the two root centres. Most tests use mu = 1 so that tolerances are plain relative ones.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
import trimesh

from cfd_torch import central_potential, contact_potential, mesh_potential, mesh_potential_derivatives
from cfd_torch._geometry import triangle_closest_points
from cfd_torch.contact import _traverse
from cfd_torch.contact.bsh import BSH
from cfd_torch.contact.reference import mesh_potential_reference, mesh_traversal_counts_reference
from cfd_torch.rotation import rotation_derivatives, rotation_matrix, transform_points

F64 = torch.float64
MARGIN = 1e-3
SPLITS = ["both", "larger"]


# ------------------------------------------------------------------------------------------------ meshes
def _cup_and_peg() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """A cup (tube + floor; cavity radius 25 mm) and a peg standing in its cavity, about 5 mm from wall and floor."""
    wall = trimesh.creation.annulus(r_min=0.025, r_max=0.035, height=0.08, sections=12)  # z in [-0.04, 0.04]
    floor = trimesh.creation.cylinder(radius=0.035, height=0.01, sections=12)
    floor.apply_translation([0.0, 0.0, -0.045])  # z in [-0.05, -0.04]
    cup = trimesh.util.concatenate([wall, floor])
    peg = trimesh.creation.cylinder(radius=0.019, height=0.06, sections=12)
    peg.apply_translation([0.0, 0.0, -0.005])  # z in [-0.035, 0.025]: 5 mm above the floor, below the rim
    return cup, peg


@functools.cache
def _mesh(name: str) -> trimesh.Trimesh:
    if name.startswith("ico"):
        return trimesh.creation.icosphere(subdivisions=int(name[3:]), radius=1.0)
    if name == "box":
        return trimesh.creation.box(extents=(1.0, 0.8, 0.6))
    if name == "cube":
        return trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    if name == "rod":  # long and thin: its bounding sphere is far larger than the body
        return trimesh.creation.box(extents=(2.0, 0.2, 0.2))
    if name == "torus":
        return trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=12, minor_sections=6)
    if name == "cup":
        return _cup_and_peg()[0]
    if name == "peg":
        return _cup_and_peg()[1]
    raise KeyError(name)


@functools.cache
def _bsh(name: str) -> BSH:
    return BSH.from_trimesh(_mesh(name))


# ------------------------------------------------------------------------------------------------ poses
def _pose(t=(0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return torch.tensor([*t, *w], dtype=F64)


def _unit(v) -> torch.Tensor:
    v = torch.as_tensor(v, dtype=F64)
    return v / v.norm()


def _random_rotvec(g: torch.Generator) -> torch.Tensor:
    axis = torch.randn(3, generator=g, dtype=F64)
    return axis / axis.norm() * (0.2 + 2.8 * torch.rand((), generator=g, dtype=F64))


def _world_root(bsh: BSH, pose: torch.Tensor) -> torch.Tensor:
    return rotation_matrix(pose[3:]) @ bsh.centre[0] + pose[:3]


def _along(bsh_a: BSH, pose_a: torch.Tensor, bsh_b: BSH, w_b: torch.Tensor, u, r) -> torch.Tensor:
    """Poses of b (rotation vector w_b) whose root centre is r (scalar or (B,)) from a's root centre along u."""
    u = _unit(u)
    r = torch.as_tensor(r, dtype=F64)
    t = _world_root(bsh_a, pose_a) + r[..., None] * u - rotation_matrix(w_b) @ bsh_b.centre[0]
    return torch.cat([t, w_b.expand(t.shape)], -1)


def _mesh_distance(bsh_a: BSH, pose_a: torch.Tensor, bsh_b: BSH, pose_b: torch.Tensor) -> float:
    """Exact distance between two (non-intersecting) triangle meshes, over all triangle pairs."""
    ta = transform_points(pose_a, bsh_a.triangles)
    tb = transform_points(pose_b, bsh_b.triangles)
    fa, fb = ta.shape[0], tb.shape[0]
    ta = ta[:, None].expand(fa, fb, 3, 3).reshape(-1, 3, 3)
    tb = tb[None].expand(fa, fb, 3, 3).reshape(-1, 3, 3)
    return float(triangle_closest_points(ta, tb).dist.min())


def _place(bsh_a: BSH, pose_a: torch.Tensor, bsh_b: BSH, w_b: torch.Tensor, u, gap: float) -> torch.Tensor:
    """Pose of b approaching a along u from afar until the meshes are ``gap`` apart (to 0.1%).

    The mesh distance is 1-Lipschitz in the centre offset, so stepping in by (distance - gap) never overshoots
    (sphere tracing): b stays outside a and the first contact along the ray is found.
    """
    r = float(bsh_a.radius[0] + bsh_b.radius[0]) + gap + 0.1
    for _ in range(500):
        pose_b = _along(bsh_a, pose_a, bsh_b, w_b, u, r)
        d = _mesh_distance(bsh_a, pose_a, bsh_b, pose_b)
        if d - gap <= 1e-3 * gap:
            break
        r -= d - gap
    assert d > MARGIN
    return pose_b


def _random_configs(name_a: str, name_b: str, k: int, seed: int, gap=(2 * MARGIN, 10.0)):
    """k random relative poses of (a, b) with log-uniform mesh gaps; returns pose_a (k, 6), pose_b (k, 6)."""
    g = torch.Generator().manual_seed(seed)
    bsh_a, bsh_b = _bsh(name_a), _bsh(name_b)
    pa, pb = [], []
    lo, hi = math.log(gap[0]), math.log(gap[1])
    for _ in range(k):
        pose_a = torch.cat([torch.randn(3, generator=g, dtype=F64), _random_rotvec(g)])
        u = torch.randn(3, generator=g, dtype=F64)
        gp = math.exp(lo + (hi - lo) * float(torch.rand((), generator=g, dtype=F64)))
        pa.append(pose_a)
        pb.append(_place(bsh_a, pose_a, bsh_b, _random_rotvec(g), u, gp))
    return torch.stack(pa), torch.stack(pb)


def _reference_derivatives(bsh_a, pose_a, bsh_b, pose_b, **kw):
    """Value, autograd gradient (12,) and autograd Hessian (12, 12) of the naive reference."""

    def f(x):
        return mesh_potential_reference(bsh_a, x[:6], bsh_b, x[6:], **kw)

    x = torch.cat([pose_a, pose_b]).detach().requires_grad_(True)
    v = f(x)
    (g,) = torch.autograd.grad(v, x)
    H = torch.autograd.functional.hessian(f, x.detach())
    return v.detach(), g, H


def _assert_close(actual, expected, rtol, what=""):
    actual, expected = torch.as_tensor(actual), torch.as_tensor(expected)
    scale = float(expected.abs().max())
    err = float((actual - expected).abs().max())
    assert err <= rtol * scale, f"{what}: max error {err:.3e} > {rtol:.1e} * {scale:.3e}"


# ------------------------------------------------------------------------------------------------ 1. value
VALUE_PAIRS = [
    ("ico1", "ico1"),
    ("box", "ico0"),
    ("ico2", "box"),
    ("torus", "ico0"),
    ("torus", "box"),
    ("cup", "ico0"),
    ("rod", "rod"),
]


@pytest.mark.parametrize("names", VALUE_PAIRS, ids=lambda n: f"{n[0]}-{n[1]}")
def test_value_matches_reference(names):
    bsh_a, bsh_b = _bsh(names[0]), _bsh(names[1])
    pa, pb = _random_configs(*names, k=6, seed=sum(map(ord, "".join(names))))
    for split in SPLITS:
        val = mesh_potential(bsh_a, pa, bsh_b, pb, mu=1.0, margin=MARGIN, split=split)
        assert val.shape == (pa.shape[0],) and val.dtype == F64
        for i in range(pa.shape[0]):
            ref = float(
                mesh_potential_reference(bsh_a, pa[i], bsh_b, pb[i], mu=1.0, margin=MARGIN, split=split)
            )
            assert math.isfinite(ref)
            assert abs(float(val[i]) - ref) <= 1e-10 * ref, (split, i, float(val[i]), ref)


def test_value_peg_in_cup_matches_reference():
    cup, peg = _bsh("cup"), _bsh("peg")
    pa = _pose()
    pb = torch.stack([_pose(), _pose((0.002, -0.001, 0.001), (0.0, 0.0, 0.3)), _pose((0.0, 0.0, 0.003))])
    for split in SPLITS:
        val = mesh_potential(cup, pa, peg, pb, mu=1.0, margin=MARGIN, split=split)
        for i in range(pb.shape[0]):
            ref = float(mesh_potential_reference(cup, pa, peg, pb[i], mu=1.0, margin=MARGIN, split=split))
            assert abs(float(val[i]) - ref) <= 1e-10 * ref, (split, i)


def test_batch_broadcasting_and_scalar_pose():
    bsh_a, bsh_b = _bsh("ico0"), _bsh("box")
    pa = _pose((0.1, 0.0, 0.0), (0.1, 0.2, 0.3))
    pb = _along(
        bsh_a,
        pa,
        bsh_b,
        torch.tensor([0.0, 0.4, 0.0], dtype=F64),
        (1.0, 0.3, 0.2),
        torch.tensor([1.9, 2.5, 4.0]),
    )
    batched = mesh_potential(bsh_a, pa, bsh_b, pb, mu=1.0)
    assert batched.shape == (3,)
    for i in range(3):
        single = mesh_potential(bsh_a, pa, bsh_b, pb[i], mu=1.0)
        assert single.shape == ()
        assert abs(float(single) - float(batched[i])) <= 1e-12 * float(single)
    swapped = mesh_potential(bsh_a, pa.expand(3, 6), bsh_b, pb, mu=1.0)
    _assert_close(swapped, batched, 1e-12, "broadcast (6,) vs (B, 6)")


def test_traversal_stats():
    bsh_a, bsh_b = _bsh("ico1"), _bsh("ico0")
    pa = _pose((0.0, 0.0, 0.0), (0.3, -0.2, 0.1))
    far = _along(bsh_a, pa, bsh_b, torch.zeros(3, dtype=F64), (0.0, 0.0, 1.0), 10.0)
    d = mesh_potential_derivatives(bsh_a, pa, bsh_b, far, mu=1.0)
    assert set(d.stats) >= {"node_pairs", "leaf_pairs"}
    assert all(isinstance(d.stats[k], int) for k in ("node_pairs", "leaf_pairs"))
    assert d.stats["node_pairs"] == 1 and d.stats["leaf_pairs"] == 0
    near = _place(bsh_a, pa, bsh_b, torch.tensor([0.1, 0.2, 0.3], dtype=F64), (0.2, 0.1, 1.0), 0.02)
    for split in SPLITS:
        d = mesh_potential_derivatives(bsh_a, pa, bsh_b, near, mu=1.0, split=split)
        ref = mesh_traversal_counts_reference(bsh_a, pa, bsh_b, near, mu=1.0, split=split)
        assert d.stats["leaf_pairs"] > 0
        assert d.stats["node_pairs"] == ref["node_pairs"] and d.stats["leaf_pairs"] == ref["leaf_pairs"], (
            split,
            d.stats,
            ref,
        )


# ------------------------------------------------------------------------------------------------ 2. derivatives
DERIV_CASES = [  # (mesh a, mesh b, mesh gap, seed)
    ("ico0", "box", 0.05, 1),
    ("ico0", "box", 0.3, 2),
    ("ico1", "ico0", 0.1, 3),
    ("rod", "ico0", 0.02, 4),
]


@pytest.mark.parametrize("split", SPLITS)
@pytest.mark.parametrize("case", DERIV_CASES, ids=lambda c: f"{c[0]}-{c[1]}-{c[2]}")
def test_derivatives_match_reference_autograd(case, split):
    name_a, name_b, gap, seed = case
    bsh_a, bsh_b = _bsh(name_a), _bsh(name_b)
    pa, pb = _random_configs(name_a, name_b, 1, seed, gap=(gap, gap))
    pa, pb = pa[0], pb[0]
    assert pa[3:].norm() > 0.1 and pb[3:].norm() > 0.1
    d = mesh_potential_derivatives(bsh_a, pa, bsh_b, pb, mu=1.0, margin=MARGIN, split=split)
    assert d.value.shape == () and d.grad.shape == (12,) and d.hessian.shape == (12, 12)
    v, g, H = _reference_derivatives(bsh_a, pa, bsh_b, pb, mu=1.0, margin=MARGIN, split=split)
    assert g.abs().max() > 0
    assert abs(float(d.value) - float(v)) <= 1e-10 * float(v)
    _assert_close(d.grad, g, 1e-8, "grad vs autograd of reference")
    _assert_close(d.hessian, H, 1e-8, "Hessian vs autograd of reference")
    _assert_close(d.hessian, d.hessian.T, 1e-12, "Hessian symmetry")
    # translation invariance of a pair: dP/dt_a = -dP/dt_b
    _assert_close(d.grad[:3], -d.grad[6:9], 1e-10, "action-reaction")


@pytest.mark.parametrize("case", DERIV_CASES, ids=lambda c: f"{c[0]}-{c[1]}-{c[2]}")
def test_derivatives_match_finite_differences(case):
    name_a, name_b, gap, seed = case
    bsh_a, bsh_b = _bsh(name_a), _bsh(name_b)
    pa, pb = _random_configs(name_a, name_b, 1, seed, gap=(gap, gap))
    x0 = torch.cat([pa[0], pb[0]])
    d = mesh_potential_derivatives(bsh_a, x0[:6], bsh_b, x0[6:], mu=1.0)
    assert d.grad.abs().max() > 0
    h = 1e-6 * max(1.0, gap)
    X = torch.cat(
        [x0 + h * torch.eye(12, dtype=F64), x0 - h * torch.eye(12, dtype=F64)]
    )  # (24, 12) in one batch
    v = mesh_potential(bsh_a, X[:, :6], bsh_b, X[:, 6:], mu=1.0)
    _assert_close((v[:12] - v[12:]) / (2 * h), d.grad, 1e-5, "grad vs central differences")
    dx = mesh_potential_derivatives(bsh_a, X[:, :6], bsh_b, X[:, 6:], mu=1.0)
    fd_h = (dx.grad[:12] - dx.grad[12:]) / (2 * h)  # row k = d grad / d x_k
    _assert_close(fd_h, d.hessian, 1e-5, "Hessian vs central differences of grad")


# ------------------------------------------------------------------------------------------------ 3. autograd
def test_gradcheck_gradgradcheck_and_no_third_derivative():
    bsh_a, bsh_b = _bsh("ico0"), _bsh("box")
    pa0 = _pose((0.0, 0.1, 0.0), (0.2, -0.4, 0.3))
    pb0 = _place(bsh_a, pa0, bsh_b, torch.tensor([0.5, 0.1, -0.2], dtype=F64), (0.3, 1.0, 0.2), 0.08)
    pb1 = _place(bsh_a, pa0, bsh_b, torch.tensor([-0.3, 0.6, 0.1], dtype=F64), (1.0, -0.2, 0.4), 0.4)
    pa = pa0.clone().requires_grad_(True)
    pb = torch.stack([pb0, pb1]).requires_grad_(True)

    def f(x, y):
        return mesh_potential(bsh_a, x, bsh_b, y, mu=1.0)

    assert torch.autograd.gradcheck(f, (pa, pb), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradgradcheck(f, (pa, pb), eps=1e-6, atol=1e-5, rtol=1e-4)

    v = f(pa, pb[0])
    (g,) = torch.autograd.grad(v, pb, create_graph=True)
    assert g[0].abs().max() > 0
    (h,) = torch.autograd.grad(g[0, 0], pb, create_graph=True)
    assert h[0].abs().max() > 0
    assert h.requires_grad
    with pytest.raises(RuntimeError, match="mesh_potential: third derivatives are not implemented"):
        torch.autograd.grad(h.sum(), pb)


def test_third_derivative_is_refused_even_beside_a_differentiable_term():
    # the Hessian must stay connected to the poses: a third derivative through it raises instead of silently
    # contributing zero next to a term that does depend on the poses
    bsh_a, bsh_b = _bsh("ico0"), _bsh("box")
    pa = _pose((0.0, 0.1, 0.0), (0.2, -0.4, 0.3)).requires_grad_(True)
    pb = _place(bsh_a, pa.detach(), bsh_b, torch.tensor([0.5, 0.1, -0.2], dtype=F64), (0.3, 1.0, 0.2), 0.08)
    (g,) = torch.autograd.grad(mesh_potential(bsh_a, pa, bsh_b, pb, mu=1.0), pa, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), pa, create_graph=True)
    assert h.abs().max() > 0
    with pytest.raises(RuntimeError, match="third derivatives"):
        torch.autograd.grad(h.sum() + (pa**4).sum(), pa)


# ------------------------------------------------------------------------------------------------ 4. far field
@pytest.mark.parametrize("r", [10.0, 1e2, 1e3])
def test_non_vanishing_and_repulsive_far_away(r):
    bsh_a, bsh_b = _bsh("ico1"), _bsh("box")
    pa = _pose((0.3, -0.2, 0.5), (0.4, 0.1, -0.7))
    u = _unit((0.4, -1.0, 0.3))
    pb = _along(bsh_a, pa, bsh_b, torch.tensor([1.0, 0.5, 0.2], dtype=F64), u, r)
    d = mesh_potential_derivatives(bsh_a, pa, bsh_b, pb)  # default mu = 1e-8
    force_b = -d.grad[6:9]
    assert float(force_b @ u) > 0 and float(d.grad[0:3] @ u) > 0  # b pushed away from a, a away from b
    assert float(force_b.norm()) > 0 and float(d.grad[0:3].norm()) > 0
    # beyond the root band the potential is the central one of the two root spheres
    rr = torch.tensor(r, dtype=F64)
    assert abs(float(d.value) - float(central_potential(rr, mu=1e-8))) <= 1e-12 * float(d.value)
    dpc = -12e-8 * (r**-1.5 + r**-2)
    _assert_close(d.grad[6:9], dpc * u, 1e-9, "far-field force")
    assert d.stats["node_pairs"] == 1


# ------------------------------------------------------------------------------------------------ 5. barrier
def test_barrier_grows_without_bound_and_is_infinite_within_margin():
    cube = _bsh("cube")
    pa = _pose()
    for w_b, half in [
        ((0.0, 0.0, 0.0), 0.5),
        ((math.pi / 4, 0.0, 0.0), 0.5 * math.sqrt(2.0)),
    ]:  # face, edge down
        gaps = [MARGIN * (1.0 + 10.0**-k) for k in range(0, 7)]
        pb = torch.stack([_pose((0.1, -0.2, 0.5 + half + g), w_b) for g in gaps])
        v = mesh_potential(cube, pa, cube, pb, mu=1.0, margin=MARGIN)
        assert bool(torch.isfinite(v).all())
        assert bool((v[1:] > v[:-1]).all()), v
        assert float(v[-1]) > 1e5 * float(v[0])
        inside = torch.stack(
            [_pose((0.1, -0.2, 0.5 + half + g), w_b) for g in (0.999 * MARGIN, 0.5 * MARGIN, -0.05)]
        )
        v_in = mesh_potential(cube, pa, cube, inside, mu=1.0, margin=MARGIN)
        assert bool(torch.isposinf(v_in).all()), v_in


# ------------------------------------------------------------------------------------------------ 6. C2 blend
def _max_step(q: torch.Tensor, stride: int) -> float:
    """Largest change of q (samples along dim 0, any trailing shape) between samples ``stride`` apart."""
    s = q[::stride]
    return float((s[1:] - s[:-1]).abs().max())


def _assert_continuous(quantities: dict[str, torch.Tensor], window: int = 16):
    """No jumps: in every window, the largest change between neighbouring samples is well below the largest
    change between samples four times further apart (ratio ~1/4 for a continuous quantity, ~1 at a jump)."""
    for name, q in quantities.items():
        assert bool(torch.isfinite(q).all()), name
        floor = 1e-9 * float(q.abs().max())
        for start in range(0, q.shape[0] - window, window):
            w = q[start : start + window + 1]
            fine, coarse = _max_step(w, 1), _max_step(w, 4)
            assert fine <= 0.6 * coarse + floor, (name, start, fine, coarse)


@pytest.mark.parametrize("edge", ["d1", "d2"])
def test_c2_across_root_band_edges(edge):
    rod = _bsh("rod")  # two parallel rods side by side: the root band lies far from contact
    eps = 0.01
    pa = _pose()
    d1 = 2.0 * float(rod.radius[0])
    r_edge = d1 if edge == "d1" else (1.0 + eps) * d1
    r = r_edge + d1 * eps * torch.linspace(-0.2, 0.2, 129, dtype=F64)  # step = band width / 320
    pb = _along(rod, pa, rod, torch.zeros(3, dtype=F64), (0.0, 1.0, 0.0), r)
    assert _mesh_distance(rod, pa, rod, pb[0]) > 1.0
    d = mesh_potential_derivatives(rod, pa, rod, pb, mu=1.0, eps=eps)
    _assert_continuous({"value": d.value, "grad": d.grad, "hessian": d.hessian})
    # the potential changes shape across the edge: the root pair is refined on one side only
    s = (r - d1) / (eps * d1)
    assert float(s.min()) < (0.0 if edge == "d1" else 1.0) < float(s.max())


@pytest.mark.parametrize("split", SPLITS)
def test_c2_generic_sweep(split):
    """Sweep the gap of two icospheres through many inner node pairs' band edges (eps = 0.1: wide bands)."""
    ico = _bsh("ico0")
    pa = _pose((0.0, 0.0, 0.0), (0.3, 0.5, -0.2))
    w_b = torch.tensor([-0.7, 0.2, 0.4], dtype=F64)
    u = _unit((0.3, 0.2, 1.0))
    r = torch.linspace(1.9, 2.3, 257, dtype=F64)  # leaf bands are ~0.12 wide: ~80 samples per band
    pb = _along(ico, pa, ico, w_b, u, r)
    assert _mesh_distance(ico, pa, ico, pb[0]) > 5 * MARGIN
    d = mesh_potential_derivatives(ico, pa, ico, pb, mu=1.0, eps=0.1, split=split)
    _assert_continuous({"value": d.value, "grad": d.grad, "hessian": d.hessian})


# ------------------------------------------------------------------------------------------------ 7. invariance
def _rotvec_of(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _body_angular_grad(pose: torch.Tensor, g_omega: torch.Tensor) -> torch.Tensor:
    """dP/d delta for the body-frame perturbation R exp([delta]x): J_r^-T dP/d omega, J_r from dR/d omega."""
    R, dR, _ = rotation_derivatives(pose[None, 3:])
    RtdR = R[0].T @ dR[0].permute(2, 0, 1)  # (3, 3, 3): R^T dR/d omega_i = [J_r e_i]x
    J = torch.stack([RtdR[:, 2, 1], RtdR[:, 0, 2], RtdR[:, 1, 0]], 0)  # column i = vee(R^T dR_i)
    return torch.linalg.solve(J.T, g_omega)


def test_invariance_under_common_rigid_motion():
    bsh_a, bsh_b = _bsh("ico1"), _bsh("box")
    pa, pb = _random_configs("ico1", "box", 1, seed=11, gap=(0.05, 0.05))
    pa, pb = pa[0], pb[0]
    Q = rotation_matrix(torch.tensor([0.7, -1.1, 0.4], dtype=F64))
    p = torch.tensor([3.0, -1.0, 2.5], dtype=F64)

    def moved(pose):
        R = Q @ rotation_matrix(pose[3:])
        return torch.cat([Q @ pose[:3] + p, torch.from_numpy(_rotvec_of(R.numpy()))])

    pa2, pb2 = moved(pa), moved(pb)
    for split in SPLITS:
        d = mesh_potential_derivatives(bsh_a, pa, bsh_b, pb, mu=1.0, split=split)
        d2 = mesh_potential_derivatives(bsh_a, pa2, bsh_b, pb2, mu=1.0, split=split)
        assert abs(float(d2.value) - float(d.value)) <= 1e-10 * float(d.value)
        _assert_close(d2.grad[0:3], Q @ d.grad[0:3], 1e-8, "t_a gradient rotates")
        _assert_close(d2.grad[6:9], Q @ d.grad[6:9], 1e-8, "t_b gradient rotates")
        for k, (x, x2) in enumerate([(pa, pa2), (pb, pb2)]):
            h = _body_angular_grad(x, d.grad[6 * k + 3 : 6 * k + 6])
            h2 = _body_angular_grad(x2, d2.grad[6 * k + 3 : 6 * k + 6])
            _assert_close(h2, h, 1e-8, f"body-frame torque of body {k}")
        # a pure translation changes nothing at all
        shift = torch.cat([p, torch.zeros(3, dtype=F64)])
        d3 = mesh_potential_derivatives(bsh_a, pa + shift, bsh_b, pb + shift, mu=1.0, split=split)
        assert abs(float(d3.value) - float(d.value)) <= 1e-10 * float(d.value)
        _assert_close(d3.grad, d.grad, 1e-8, "translation invariance")


# ------------------------------------------------------------------------------------------------ 8. repulsive
@pytest.mark.parametrize("names", [("ico1", "ico1"), ("box", "ico0"), ("cube", "box")], ids="-".join)
def test_repulsive_through_the_blend_bands(names):
    bsh_a, bsh_b = _bsh(names[0]), _bsh(names[1])
    g = torch.Generator().manual_seed(17)
    for _ in range(2):
        pa = torch.cat([torch.zeros(3, dtype=F64), _random_rotvec(g)])
        w_b = _random_rotvec(g)
        u = torch.randn(3, generator=g, dtype=F64)
        near = _place(bsh_a, pa, bsh_b, w_b, u, 3 * MARGIN)
        r0 = float((_world_root(bsh_b, near) - _world_root(bsh_a, pa)).norm())
        r = r0 + torch.cat([torch.logspace(-4, 0, 120, dtype=F64), torch.linspace(1.1, 4.0, 40, dtype=F64)])
        pb = _along(bsh_a, pa, bsh_b, w_b, u, r)
        d = mesh_potential_derivatives(bsh_a, pa, bsh_b, pb, mu=1.0)
        uu = _unit(u)
        assert bool(torch.isfinite(d.value).all())
        assert bool((-d.grad[:, 6:9] @ uu > 0).all()), "force on b must push it away from a"
        assert bool((d.grad[:, 0:3] @ uu > 0).all()), "force on a must push it away from b"


# ------------------------------------------------------------------------------------------------ 9. non-convex
def test_peg_in_cup_cavity():
    cup_mesh, peg_mesh = _cup_and_peg()
    hull = cup_mesh.convex_hull  # peg inside the cup's hull: on the inner side of every hull face plane
    origin = hull.vertices[hull.faces[:, 0]]
    side = np.einsum("vfi,fi->vf", peg_mesh.vertices[:, None, :] - origin[None], hull.face_normals)
    assert bool((side < 0).all())  # every peg vertex inside the cup's hull: a hull shortcut would see contact
    cup, peg = _bsh("cup"), _bsh("peg")
    pa = _pose()
    centred = _pose()
    gap = _mesh_distance(cup, pa, peg, centred)
    assert 4e-3 < gap < 6e-3
    toward_wall = _pose((0.002, 0.0, 0.0))
    toward_floor = _pose((0.0, 0.0, -0.002))
    v = mesh_potential(cup, pa, peg, torch.stack([centred, toward_wall, toward_floor]), mu=1.0, margin=MARGIN)
    assert bool(torch.isfinite(v).all())
    assert float(v[1]) > float(v[0]) and float(v[2]) > float(v[0])
    d = mesh_potential_derivatives(cup, pa, peg, toward_wall, mu=1.0, margin=MARGIN)
    assert float(d.grad[6]) > 0  # force on the peg pushes it back from the wall (-x)
    # further down the value keeps growing until the floor gap reaches the margin (5 mm - 4.5 mm < 1 mm)
    deeper = torch.stack([_pose((0.0, 0.0, -0.0038)), _pose((0.0, 0.0, -0.0045))])
    v_deep = mesh_potential(cup, pa, peg, deeper, mu=1.0, margin=MARGIN)
    assert float(v[2]) < float(v_deep[0]) < math.inf and torch.isposinf(v_deep[1])


# ------------------------------------------------------------------------------------------------ 10. scene
def _scene():
    names = ["ico0", "box", "ico1", "cube", "ico0"]
    bshes = [_bsh(n) for n in names]
    poses = torch.stack(
        [
            _pose((0.0, 0.0, 0.0), (0.1, 0.2, 0.3)),
            _pose(
                (0.9, 0.1, 0.0), (0.0, 0.3, 0.0)
            ),  # overlaps body 0: only allowed because (0, 1) is excluded
            _pose((0.2, 2.15, 0.1), (0.5, -0.2, 0.1)),
            _pose((0.0, 0.0, -2.5), (0.0, 0.0, 0.2)),  # static
            _pose((0.3, 0.2, -2.6), (0.0, 0.0, 0.0)),  # static, overlapping the static cube: never evaluated
        ]
    )
    static = [False, False, False, True, True]
    exclude = [(0, 1)]
    return bshes, poses, static, exclude


def _included_pairs(n, static, exclude):
    ex = {tuple(sorted(e)) for e in exclude}
    return [
        (i, j)
        for i in range(n)
        for j in range(i + 1, n)
        if not (static[i] and static[j]) and (i, j) not in ex
    ]


def test_contact_potential_sums_included_pairs():
    bshes, poses, static, exclude = _scene()
    kw = {"mu": 1.0, "margin": MARGIN, "eps": 0.01, "split": "both"}
    pairs = _included_pairs(len(bshes), static, exclude)
    assert (0, 1) not in pairs and (3, 4) not in pairs
    x = poses.clone().requires_grad_(True)
    total = sum(mesh_potential(bshes[i], x[i], bshes[j], x[j], **kw) for i, j in pairs)
    assert math.isfinite(float(total.detach()))
    (g_ref,) = torch.autograd.grad(total, x)
    total = total.detach()
    g_ref[torch.tensor(static)] = 0.0

    res = contact_potential(bshes, poses, static=static, exclude=exclude, grad=True, **kw)
    assert res.hessian is None
    assert res.value.shape == () and res.grad.shape == (5, 6)
    assert abs(float(res.value) - float(total)) <= 1e-10 * float(total)
    _assert_close(res.grad, g_ref, 1e-8, "contact_potential grad vs autograd")
    assert bool((res.grad[3:] == 0).all())
    res_t = contact_potential(bshes, poses, static=torch.tensor(static), exclude=exclude, **kw)
    assert float(res_t.value) == float(res.value)
    # without the exclusion the overlapping pair (0, 1) makes the potential infinite
    assert torch.isposinf(contact_potential(bshes, poses, static=static, **kw).value)


def test_contact_potential_hessian_matches_finite_differences():
    bshes, poses, static, exclude = _scene()
    kw = {"mu": 1.0, "margin": MARGIN, "eps": 0.01, "split": "both"}
    res = contact_potential(bshes, poses, static=static, exclude=exclude, hessian=True, **kw)
    n = len(bshes)
    H = res.hessian
    assert H.shape == (6 * n, 6 * n)
    _assert_close(H, H.T, 1e-12, "symmetry")
    dyn = torch.tensor([not s for s in static]).repeat_interleave(6)
    assert bool((H[~dyn] == 0).all()) and bool((H[:, ~dyn] == 0).all())
    h = 1e-6
    idx = torch.nonzero(dyn)[:, 0].tolist()
    fd = torch.zeros(len(idx), 6 * n, dtype=F64)
    for row, k in enumerate(idx):
        e = torch.zeros(6 * n, dtype=F64)
        e[k] = h
        gp = contact_potential(
            bshes, poses + e.reshape(n, 6), static=static, exclude=exclude, grad=True, **kw
        ).grad
        gm = contact_potential(
            bshes, poses - e.reshape(n, 6), static=static, exclude=exclude, grad=True, **kw
        ).grad
        fd[row] = ((gp - gm) / (2 * h)).reshape(-1)
    _assert_close(H[idx][:, idx], fd[:, idx], 1e-5, "Hessian vs finite differences of grad")


def test_contact_potential_autograd_differentiates_static_poses_too():
    # the returned grad/hessian fields zero the static rows, but the autograd path is the true derivative of the
    # value: a static body's pose enters the value through its pairs with moving bodies
    bshes, poses, static, exclude = _scene()
    kw = {"mu": 1.0, "margin": MARGIN, "eps": 0.01, "split": "both"}
    pairs = _included_pairs(len(bshes), static, exclude)
    x = poses.clone().requires_grad_(True)
    total = sum(mesh_potential(bshes[i], x[i], bshes[j], x[j], **kw) for i, j in pairs)
    (g_ref,) = torch.autograd.grad(total, x)
    assert g_ref[3].abs().max() > 0  # the static cube feels the moving bodies

    def f(p):
        return contact_potential(bshes, p, static=static, exclude=exclude, **kw).value

    (g,) = torch.autograd.grad(f(x), x)
    _assert_close(g, g_ref, 1e-8, "autograd grad (static rows included) vs sum of mesh potentials")
    # the fields keep their documented meaning
    res = contact_potential(bshes, x, static=static, exclude=exclude, **kw)
    assert bool((res.grad[3:] == 0).all())
    _assert_close(res.grad[:3], g_ref[:3], 1e-8, "grad field")
    # first and second order, with the static cube and a static sphere that interacts with no moving body
    two = [bshes[2], bshes[3]]
    y = torch.stack([poses[2], poses[3].new_tensor([0.2, 0.3, 0.1, 0.1, 0.0, 0.2])]).requires_grad_(True)

    def f2(p):
        return contact_potential(two, p, static=[False, True], **kw).value

    (g2,) = torch.autograd.grad(f2(y), y)
    assert g2[1].abs().max() > 0
    assert torch.autograd.gradcheck(f2, (y,), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradgradcheck(f2, (y,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_contact_potential_refuses_third_derivatives():
    bshes, poses, static, exclude = _scene()
    x = poses.clone().requires_grad_(True)
    v = contact_potential(bshes, x, static=static, exclude=exclude, mu=1.0, margin=MARGIN).value
    (g,) = torch.autograd.grad(v, x, create_graph=True)
    (h,) = torch.autograd.grad(g[0, 0], x, create_graph=True)
    assert h.abs().max() > 0
    with pytest.raises(RuntimeError, match="contact_potential: third derivatives are not implemented"):
        torch.autograd.grad(h.sum() + (x**4).sum(), x)


def test_contact_potential_computes_the_gradient_only_when_it_is_needed():
    bshes, poses, static, exclude = _scene()
    kw = {"static": static, "exclude": exclude, "mu": 1.0, "margin": MARGIN}
    assert contact_potential(bshes, poses, **kw).grad is None  # poses do not require grad
    x = poses.clone().requires_grad_(True)
    assert contact_potential(bshes, x, **kw).grad is not None
    with torch.no_grad():
        assert contact_potential(bshes, x, **kw).grad is None  # the value is not attached to autograd
    assert contact_potential(bshes, poses, grad=True, **kw).grad is not None
    assert contact_potential(bshes, x, grad=False, **kw).grad is None
    res = contact_potential(bshes, x, grad=False, **kw)  # the backward computes it then
    (g,) = torch.autograd.grad(res.value, x)
    _assert_close(g[:3], contact_potential(bshes, poses, grad=True, **kw).grad[:3], 1e-12, "lazy backward")


# ------------------------------------------------------------------------------------------------ validation
def test_argument_validation():
    bsh = _bsh("ico0")
    p0, p1 = _pose(), _pose((3.0, 0.0, 0.0))
    for fn in (mesh_potential, mesh_potential_reference):
        with pytest.raises(ValueError, match="split"):
            fn(bsh, p0, bsh, p1, split="smaller")
        with pytest.raises(ValueError, match="pose_b"):
            fn(bsh, p0, bsh, p1[:5])
        with pytest.raises(ValueError, match="eps"):
            fn(bsh, p0, bsh, p1, eps=0.0)
        with pytest.raises(ValueError, match="mu"):
            fn(bsh, p0, bsh, p1, mu=-1.0)
    with pytest.raises(ValueError, match="bsh_a"):
        mesh_potential_reference(None, p0, bsh, p1)
    with pytest.raises(ValueError, match="pose_a"):
        mesh_potential_reference(bsh, p0.float(), bsh, p1)


# ------------------------------------------------------------------------------------------------ 11. backends
@pytest.mark.parametrize("split", SPLITS)
def test_numba_depth_first_and_tensor_breadth_first_traversals_agree(split):
    bsh_a, bsh_b = _bsh("ico1"), _bsh("box")
    pa, pb = _random_configs("ico1", "box", 3, seed=5, gap=(2e-3, 0.3))
    pose = torch.cat([pa, pb])
    forest = _traverse.forest_of((bsh_a, bsh_b), F64, torch.device("cpu"))
    pair_body = torch.stack([torch.arange(3), torch.arange(3) + 3], 1)
    pair_root = forest.roots[None].expand(3, 2)
    kw = {"mu": 1.0, "margin": MARGIN, "eps": 0.01, "split": split, "tol": 1e-12, "max_iter": 100}
    for order in (0, 1, 2):
        fast = _traverse.traverse(forest, pair_body, pair_root, pose, order=order, backend="auto", **kw)
        ref = _traverse.traverse(forest, pair_body, pair_root, pose, order=order, backend="torch", **kw)
        assert fast[3]["node_pairs"] == ref[3]["node_pairs"] and fast[3]["leaf_pairs"] == ref[3]["leaf_pairs"]
        assert ref[3]["leaf_pairs"] > 0
        torch.testing.assert_close(fast[0], ref[0], rtol=1e-12, atol=0)
        for k in (1, 2)[:order]:
            assert ref[k].abs().amax() > 0
            torch.testing.assert_close(fast[k], ref[k], rtol=1e-10, atol=1e-12 * float(ref[k].abs().max()))


@pytest.mark.parametrize("split", SPLITS)
def test_partial_hessians_equal_the_whole_ones_in_the_blocks_asked_for(split):
    """``hessian_of`` (the simulator's Newton iterations name the bodies that move): where one body of a pair is
    asked for, the CPU kernels form only its 6 x 6 block, bit for bit the whole Hessian's, and leave the other rows
    and columns zero; values and gradients are unchanged. Pairs in contact (blend bands, leaf pairs, weights
    inherited through the band) and far apart (the far pairs' moments), with either body the asked one."""
    bsh_a, bsh_b = _bsh("ico1"), _bsh("box")
    near = _random_configs("ico1", "box", 4, seed=7, gap=(1.5 * MARGIN, 3 * MARGIN))
    far = _random_configs("ico1", "box", 2, seed=8, gap=(20 * MARGIN, 0.5))
    pose = torch.cat([near[0], far[0], near[1], far[1]])
    forest = _traverse.forest_of((bsh_a, bsh_b), F64, torch.device("cpu"))
    pair_body = torch.stack([torch.arange(6), torch.arange(6) + 6], 1)
    pair_root = forest.roots[None].expand(6, 2)
    kw = {"mu": 1.0, "margin": MARGIN, "eps": 0.01, "split": split, "tol": 1e-12, "max_iter": 100, "order": 2}
    whole = _traverse.traverse(forest, pair_body, pair_root, pose, **kw)
    assert whole[3]["leaf_pairs"] > 0
    ask = torch.tensor(
        [[True, False], [False, True], [True, True], [True, False], [True, False], [False, True]]
    )
    part = _traverse.traverse(forest, pair_body, pair_root, pose, hessian_of=ask, **kw)
    assert torch.equal(part[0], whole[0]) and torch.equal(part[1], whole[1])
    for p in range(6):
        lo, hi = (0 if ask[p, 0] else 6), (12 if ask[p, 1] else 6)
        block = whole[2][p, lo:hi, lo:hi]
        assert float(block.abs().max()) > 0
        assert torch.equal(part[2][p, lo:hi, lo:hi], block)
        rest = part[2][p].clone()
        rest[lo:hi, lo:hi] = 0.0
        assert float(rest.abs().max()) == 0.0
    with pytest.raises(ValueError, match="hessian_of"):
        _traverse.traverse(forest, pair_body, pair_root, pose, hessian_of=ask[:5], **kw)


@pytest.mark.parametrize("split", SPLITS)
def test_numba_kernels_grow_their_buffers_without_changing_the_result(split):
    """The CPU kernels start with fixed buffers (stack, leaves, weight table) and, when one fills up, grow it and
    traverse the body pair again from its saved rows: started at capacity 1 (every buffer grows, mid-pair, many
    times) they return exactly what the default capacities return."""
    from cfd_torch.contact._traverse_numba import (
        LEAF_CAP,
        STACK_CAP,
        TABLE_CAP,
        penetrating_pairs,
        traverse_nodes,
    )

    n = 6
    bsh_a, bsh_b = _bsh("ico1"), _bsh("box")
    near = _random_configs("ico1", "box", n // 2, seed=5, gap=(1.5 * MARGIN, 3 * MARGIN))
    far = _random_configs("ico1", "box", n // 2, seed=6, gap=(20 * MARGIN, 40 * MARGIN))
    pose = torch.cat([near[0], far[0], near[1], far[1]])
    forest = _traverse.forest_of((bsh_a, bsh_b), F64, torch.device("cpu"))
    pair_body = torch.stack([torch.arange(n), torch.arange(n) + n], 1).numpy()
    pair_root = forest.roots[None].expand(n, 2).contiguous().numpy()
    R, dR, d2R = (x.contiguous().numpy() for x in rotation_derivatives(pose[:, 3:], 2))
    t = pose[:, :3].contiguous().numpy()
    geo = (forest.centre.numpy(), forest.radius.numpy(), forest.child.numpy())
    eps = np.full(n, 0.01)
    for order in (0, 1, 2):
        runs = []
        for caps in ((STACK_CAP, TABLE_CAP, LEAF_CAP), (1, 1, 1)):
            out = (np.zeros(n), np.zeros((n, 12)), np.zeros((n, 12, 12)))
            res = traverse_nodes(*geo, pair_body, pair_root, R, dR, d2R, t, 1.0, eps, 2 * MARGIN, split == "both",
                                 order, *out, np.zeros(n, np.int64), *caps)  # fmt: skip
            runs.append((res, out))
        (res0, out0), (res1, out1) = runs
        n_leaf = res0[7]
        assert (
            n_leaf > 8 and res0[8] > 8 and res0[4].shape[0] == TABLE_CAP
        )  # leaves, node pairs, the first table
        assert (res1[7], res1[8]) == (n_leaf, res0[8])
        for a, b in zip(res0[:4], res1[:4], strict=True):  # leaf node ids, body pairs, weight entries
            assert np.array_equal(a[:n_leaf], b[:n_leaf])
        used = int(res0[3][:n_leaf].max()) + 1
        assert used > 1  # some leaf inherits a blended weight
        assert np.array_equal(res0[4][:used], res1[4][:used])
        for a, b in zip(out0[: order + 1], out1[: order + 1], strict=True):
            assert np.abs(a).max() > 0 and np.array_equal(a, b)
    flags = []
    for caps in ((STACK_CAP,), (1,)):
        out = np.zeros(n, np.int8)
        # (a query margin of 10 mm: the near pairs are within it)
        penetrating_pairs(*geo, forest.tri.numpy(), forest.tris.numpy(), pair_body, pair_root, R, t, np.ones(2 * n),
                          10 * MARGIN, eps, 2 * MARGIN, split == "both", out, *caps)  # fmt: skip
        flags.append(out)
    assert flags[0].tolist() == [1] * (n // 2) + [0] * (n // 2) and np.array_equal(flags[0], flags[1])


@pytest.mark.parametrize("split", SPLITS)
def test_swapping_the_bodies_changes_nothing(split):
    """The potential of two bodies does not depend on their order, whichever split rule (identical meshes tie at
    every level of their hierarchies: "larger" splits both nodes on a tie); the reference agrees."""
    ball = _bsh("ico1")
    qa = torch.tensor([0.0, 0.0, 0.0, 0.2, -0.1, 0.3], dtype=F64)
    qb = torch.tensor(
        [2.01, 0.01, -0.01, -0.3, 0.5, 0.1], dtype=F64
    )  # 1 cm apart, blends open at every level
    kw = {"split": split, "eps": 0.01}
    ab = mesh_potential_derivatives(ball, qa, ball, qb, **kw)
    ba = mesh_potential_derivatives(ball, qb, ball, qa, **kw)
    assert ab.stats["leaf_pairs"] > 0
    torch.testing.assert_close(ba.value, ab.value, rtol=1e-13, atol=0)
    torch.testing.assert_close(
        torch.cat([ba.grad[6:], ba.grad[:6]]), ab.grad, rtol=1e-10, atol=1e-13 * float(ab.grad.abs().max())
    )
    ref = mesh_potential_reference(ball, qb, ball, qa, **kw)
    torch.testing.assert_close(ref, ab.value, rtol=1e-10, atol=0)


def test_both_traversals_agree_where_node_centres_coincide():
    """Node pairs whose centres coincide (r = 0: a part centred inside a closed housing, or two bodies on top of
    each other) lie on the blend's near side: both traversals give the same finite potential and derivatives for
    the nested part and +inf (no NaN) for the coincident bodies, and the collision query flags only the latter."""
    housing = BSH.from_trimesh(trimesh.creation.box(extents=(2.0, 2.0, 2.0)))
    part = BSH.from_trimesh(trimesh.creation.box(extents=(0.5, 0.5, 0.5)))
    ball = _bsh("ico1")
    forest = _traverse.forest_of((housing, part, ball), F64, torch.device("cpu"))
    pose = torch.zeros(4, 6, dtype=F64)  # housing, part, ball, ball: all centred at the origin
    pair_body = torch.tensor([[0, 1], [2, 3]])
    pair_root = forest.roots[torch.tensor([[0, 1], [2, 2]])]
    kw = {"margin": MARGIN, "eps": 0.01, "split": "both", "tol": 1e-12, "max_iter": 100}
    for order in (0, 1, 2):
        fast = _traverse.traverse(
            forest, pair_body, pair_root, pose, mu=1.0, order=order, backend="auto", **kw
        )
        ref = _traverse.traverse(
            forest, pair_body, pair_root, pose, mu=1.0, order=order, backend="torch", **kw
        )
        assert 0 < float(ref[0][0]) < float("inf") and float(ref[0][1]) == float("inf")
        torch.testing.assert_close(fast[0], ref[0], rtol=1e-12, atol=0)
        for k in (1, 2)[:order]:
            assert not bool(torch.isnan(ref[k]).any()) and not bool(torch.isnan(fast[k]).any())
        if order >= 1:  # centred by symmetry: no net force or torque, to rounding
            assert float(ref[1][0].abs().max()) < 1e-6 * float(ref[0][0])
            assert float(fast[1][0].abs().max()) < 1e-6 * float(ref[0][0])
        if order == 2:
            h = float(ref[2][0].abs().max())
            assert h > 0
            torch.testing.assert_close(fast[2][0], ref[2][0], rtol=1e-10, atol=1e-10 * h)
    flags = _traverse.penetrating(forest, pair_body, pair_root, pose, **kw)
    assert flags.tolist() == [False, True]


@pytest.mark.parametrize("names", [("ico1", "box"), ("box", "box")])
def test_collision_query_marks_exactly_the_infinite_pairs(names):
    """The simulator's feasibility check (``_penetrating``: a sphere-pruned collision query) flags exactly the body
    pairs whose potential is +inf, for gaps on both sides of the margin."""
    bsh_a, bsh_b = _bsh(names[0]), _bsh(names[1])
    n = 24
    pa, pb = _random_configs(*names, n, seed=11, gap=(1.01 * MARGIN, 3 * MARGIN))
    u = pb[:, :3] - pa[:, :3]
    pb = pb.clone()
    pb[:, :3] -= (
        2
        * MARGIN
        * torch.rand(n, 1, generator=torch.Generator().manual_seed(0), dtype=F64)
        * (u / u.norm(dim=1, keepdim=True))
    )  # some now within the margin, some not
    pose = torch.cat([pa, pb])
    forest = _traverse.forest_of((bsh_a, bsh_b), F64, torch.device("cpu"))
    pair_body = torch.stack([torch.arange(n), torch.arange(n) + n], 1)
    pair_root = forest.roots[None].expand(n, 2)
    kw = {"margin": MARGIN, "eps": 0.01, "split": "both", "tol": 1e-12, "max_iter": 100}
    flags = _traverse.penetrating(forest, pair_body, pair_root, pose, **kw)
    value = _traverse.traverse(forest, pair_body, pair_root, pose, mu=1.0, order=0, **kw)[0]
    assert 0 < int(flags.sum()) < n  # both kinds present
    assert torch.equal(flags, torch.isinf(value))


def test_collision_query_finds_an_edge_piercing_a_face():
    """A pusher's face triangle and a box's triangle whose edge pierces it (from a step that crashed): their
    closest-feature distance is positive (over 3 mm; the 15 features miss a piercing), but they intersect. The potential
    is +inf (no plane separates them) and the collision query must say so too."""
    a = [[-0.115, 0.3, 0.31], [-0.115, -0.3, 0.31], [-0.115, 0.3, 0.01]]
    b = [[-0.12380294813784068, 0.017885539273256187, 0.20250005412528382],
         [0.051747612373261594, 0.11370825282880186, 0.2025909996566044],
         [-0.12373169786979982, 0.017849916464029274, 0.10250008585321502]]  # fmt: skip
    ta, tb = torch.tensor(a, dtype=F64), torch.tensor(b, dtype=F64)
    qa, qb = triangle_closest_points(ta[None], tb[None])[:2]
    assert float((qa - qb).norm()) > 3 * MARGIN

    def one(tri):
        return BSH.from_trimesh(trimesh.Trimesh(vertices=tri, faces=[[0, 1, 2]], process=False))

    forest = _traverse.forest_of((one(a), one(b)), F64, torch.device("cpu"))
    pose = torch.stack([_pose(), _pose(), _pose((0.0, 0.0, 1.0))])
    pair_body = torch.tensor([[0, 1], [0, 2]])  # piercing; the same triangle 1 m higher
    pair_root = forest.roots[None].expand(2, 2)
    kw = {"margin": MARGIN, "eps": 0.01, "split": "both", "tol": 1e-12, "max_iter": 100}
    flags = _traverse.penetrating(forest, pair_body, pair_root, pose, **kw)
    value = _traverse.traverse(forest, pair_body, pair_root, pose, mu=1.0, order=0, **kw)[0]
    assert torch.isinf(value[0]) and torch.isfinite(value[1])
    assert flags.tolist() == [True, False]


def test_collision_query_follows_the_potentials_blend_band():
    """Two thin cones tip to tip (found by review): the query descends only where the potential does (same band,
    same split rule) and agrees with it at every gap. With eps d1 below the margin the band is 2 margins wide
    (``central.band_width``), so tips within the margin are +inf (before: finite, the roots' far field)."""
    m = trimesh.creation.cone(radius=0.002, height=0.02, sections=6)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    tip = v[v[:, 2].argmax()]
    a, b = BSH.build(v - tip, f), BSH.build(tip - v, f[:, ::-1])
    forest = _traverse.forest_of((a, b), F64, torch.device("cpu"))
    gaps = [2e-4, 5e-4, 9e-4, 1.2e-3]
    pose = torch.zeros(1 + len(gaps), 6, dtype=F64)
    pose[1:, 2] = torch.tensor(gaps, dtype=F64)
    n = len(gaps)
    pair_body = torch.stack([torch.zeros(n, dtype=torch.int64), torch.arange(1, n + 1)], 1)
    pair_root = forest.roots[None].expand(n, 2)
    for split in SPLITS:
        kw = {"margin": MARGIN, "eps": 0.01, "split": split, "tol": 1e-12, "max_iter": 100}
        flags = _traverse.penetrating(forest, pair_body, pair_root, pose, **kw)
        value = _traverse.traverse(forest, pair_body, pair_root, pose, mu=1e-8, order=0, **kw)[0]
        assert bool(torch.isinf(value[:3]).all()) and bool(
            torch.isfinite(value[3:]).all()
        )  # within the margin: inf
        assert torch.equal(flags, torch.isinf(value))


@pytest.mark.parametrize("threads", [2, 3])
def test_threaded_node_traversal_equals_one_thread(monkeypatch, threads):
    """Body pairs dealt to several threads (the kernel is serial within a body pair) give one thread's value,
    gradient and Hessian: the same terms, summed per body pair in the same order."""
    from cfd_torch.contact.cfd import CfdContact

    n = 9  # 36 body pairs, above the threads' threshold
    bshes = [_bsh("ico1")] * n
    reach = float(_bsh("ico1").vertices[:, 0].max())
    poses = torch.zeros(1, n, 6, dtype=F64)
    poses[0, :, 0] = (2.0 * reach + 5e-3) * torch.arange(n, dtype=F64)  # a row, neighbours 5 mm apart
    pairs = torch.tensor([[0, i, j] for i in range(n) for j in range(i + 1, n)])
    model = CfdContact(bshes)
    out = {}
    for k in (1, threads):
        monkeypatch.setattr(_traverse, "_node_threads", lambda P, leaves=None, k=k: k)
        out[k] = model.evaluate(poses, pairs, 2)
    one, many = out[1], out[threads]
    assert one.leaf_pairs > 0 and one.node_pairs == many.node_pairs and one.leaf_pairs == many.leaf_pairs
    assert float(one.grad.abs().max()) > 0
    for a, b in ((one.value, many.value), (one.grad, many.grad), (one.hess, many.hess)):
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12 * float(a.abs().max()))


def test_contact_potential_is_inf_with_zero_derivatives_when_a_pair_penetrates():
    """Bodies 0 and 1 overlap, 1 and 2 are 3.5 mm apart: the total is +inf and its derivatives are zero (as a pair's
    and a body pair's are), not the derivatives of the finite pair (1, 2), which would read as a force field that
    ignores the penetration."""
    ball = BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=0.5))
    poses = torch.tensor(
        [[0, 0, 0, 0, 0, 0], [0.9, 0, 0, 0, 0, 0], [1.9035, 0, 0, 0, 0, 0]], dtype=torch.float64
    )
    finite = contact_potential([ball, ball], poses[1:], hessian=True)
    assert torch.isfinite(finite.value) and float(finite.grad.abs().max()) > 0  # the pair (1, 2) alone
    sc = contact_potential([ball, ball, ball], poses, hessian=True)
    assert torch.isinf(sc.value)
    assert float(sc.grad.abs().max()) == 0 and float(sc.hessian.abs().max()) == 0
    p = poses.clone().requires_grad_()
    (g,) = torch.autograd.grad(contact_potential([ball, ball, ball], p).value, p)
    assert float(g.abs().max()) == 0
    # the oracle too (its autograd gradient was the finite node pairs')
    v = mesh_potential_reference(ball, p[0], ball, p[1])
    (g,) = torch.autograd.grad(v, p)
    assert torch.isinf(v) and float(g.abs().max()) == 0
