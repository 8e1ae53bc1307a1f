from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch
from conftest import F64, feature_pairs
from reference import reference_grad, reference_pair

from cfd_torch import PairSolveError, central_potential, pair_potential, pair_potential_derivatives
from cfd_torch.testing import random_rotations, random_separated_pairs

MARGIN = 1e-3
BACKENDS = ["numba", "torch"]


def _cat(cases: dict) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.stack([a for a, _ in cases.values()]), torch.stack([b for _, b in cases.values()])


def _adversarial(gap: float) -> tuple[torch.Tensor, torch.Tensor]:
    return _cat(feature_pairs(gap))


# ---------------------------------------------------------------- value against the independent reference
@pytest.mark.parametrize("backend", BACKENDS)
def test_value_matches_independent_reference(backend):
    a, b, _ = random_separated_pairs(24, gap=(2e-3, 3.0), seed=3)
    fa, fb = _adversarial(0.05)
    a, b = torch.cat([a, fa]), torch.cat([b, fb])
    val = pair_potential(a, b, mu=1e-8, margin=MARGIN, backend=backend)
    for i in range(a.shape[0]):
        ref, _ = reference_pair(a[i].numpy(), b[i].numpy(), mu=1e-8, margin=MARGIN)
        assert np.isfinite(ref)
        assert abs(val[i].item() - ref) <= 1e-10 * ref, (i, val[i].item(), ref)


def test_gradient_matches_reference_plane():
    fa, fb = _adversarial(0.02)
    d = pair_potential_derivatives(fa, fb, mu=1.0, margin=MARGIN)
    for i in range(fa.shape[0]):
        ref = reference_grad(fa[i].numpy(), fb[i].numpy(), mu=1.0, margin=MARGIN)
        assert np.abs(ref).max() > 0
        np.testing.assert_allclose(d.grad[i].numpy(), ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())


# ---------------------------------------------------------------- autograd: first and second order
@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_and_gradgradcheck(backend):
    a, b, _ = random_separated_pairs(3, gap=(5e-2, 0.5), seed=5)
    fa, fb = _adversarial(0.1)
    a = torch.cat([a, fa[[0, 1, 2]]]).requires_grad_(True)
    b = torch.cat([b, fb[[0, 1, 2]]]).requires_grad_(True)

    def f(x, y):
        return pair_potential(x, y, mu=1.0, margin=MARGIN, backend=backend)

    (g,) = torch.autograd.grad(f(a, b).sum(), a)
    assert g.abs().amax() > 0
    assert torch.autograd.gradcheck(f, (a, b), eps=1e-6, atol=1e-6, rtol=1e-6)
    assert torch.autograd.gradgradcheck(f, (a, b), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_third_derivative_is_refused_loudly():
    a, b, _ = random_separated_pairs(2, seed=7)
    a.requires_grad_(True)
    (g,) = torch.autograd.grad(pair_potential(a, b, mu=1.0).sum(), a, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), a, create_graph=True)
    assert h.abs().amax() > 0
    assert h.requires_grad
    with pytest.raises(RuntimeError, match="pair_potential: third derivatives are not implemented"):
        torch.autograd.grad(h.sum(), a)
    with pytest.raises(RuntimeError, match="third derivatives"):
        torch.autograd.grad(h.sum() + (a**4).sum(), a)


@pytest.mark.parametrize("backend", BACKENDS)
def test_closed_form_derivatives_equal_autograd_and_finite_differences(backend):
    a, b, _ = random_separated_pairs(4, gap=(1e-2, 1.0), seed=11)
    fa, fb = _adversarial(0.03)
    a, b = torch.cat([a, fa]), torch.cat([b, fb])
    K = a.shape[0]
    d = pair_potential_derivatives(a, b, mu=1.0, margin=MARGIN, backend=backend)
    assert (d.grad.abs().amax(-1) > 0).all()
    assert (d.hessian.abs().amax((-1, -2)) > 0).all()
    torch.testing.assert_close(
        d.hessian, d.hessian.transpose(-1, -2), rtol=0, atol=1e-12 * float(d.hessian.abs().max())
    )
    if backend == "numba":
        assert torch.equal(d.hessian, d.hessian.transpose(-1, -2))  # exactly symmetric

    # autograd (first and second order) against the closed forms
    x = torch.cat([a, b], 1).reshape(K, 18).requires_grad_(True)
    val = pair_potential(x[:, :9].reshape(K, 3, 3), x[:, 9:].reshape(K, 3, 3), mu=1.0, margin=MARGIN)
    (g,) = torch.autograd.grad(val.sum(), x, create_graph=True)
    H = torch.stack([torch.autograd.grad(g[:, j].sum(), x, retain_graph=True)[0] for j in range(18)], 1)
    torch.testing.assert_close(d.value, val.detach(), rtol=1e-14, atol=0)
    torch.testing.assert_close(d.grad, g.detach(), rtol=1e-12, atol=1e-12 * float(g.detach().abs().max()))
    torch.testing.assert_close(d.hessian, H, rtol=1e-10, atol=1e-10 * float(H.abs().max()))

    # central finite differences of the value (gradient) and of the closed-form gradient (Hessian)
    h = 1e-6
    x0 = x.detach()
    gfd = torch.zeros(K, 18, dtype=F64)
    hfd = torch.zeros(K, 18, 18, dtype=F64)
    for j in range(18):
        e = torch.zeros(18, dtype=F64)
        e[j] = h
        xp, xm = x0 + e, x0 - e
        dp = pair_potential_derivatives(
            xp[:, :9].reshape(K, 3, 3), xp[:, 9:].reshape(K, 3, 3), mu=1.0, hessian=False
        )
        dm = pair_potential_derivatives(
            xm[:, :9].reshape(K, 3, 3), xm[:, 9:].reshape(K, 3, 3), mu=1.0, hessian=False
        )
        gfd[:, j] = (dp.value - dm.value) / (2 * h)
        hfd[:, :, j] = (dp.grad - dm.grad) / (2 * h)
    scale_g = d.grad.abs().amax(-1, keepdim=True)
    scale_h = d.hessian.abs().amax((-1, -2), keepdim=True)
    assert ((gfd - d.grad).abs() <= 1e-6 * scale_g).all()
    assert ((hfd - d.hessian).abs() <= 1e-5 * scale_h).all()


def test_backends_agree():
    a, b, _ = random_separated_pairs(500, gap=(1.1e-3, 10.0), seed=13)
    dn = pair_potential_derivatives(a, b, backend="numba")
    dt = pair_potential_derivatives(a, b, backend="torch")
    torch.testing.assert_close(dn.value, dt.value, rtol=1e-12, atol=0)
    torch.testing.assert_close(dn.plane, dt.plane, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(dn.grad, dt.grad, rtol=1e-8, atol=1e-10 * float(dt.grad.abs().max()))
    torch.testing.assert_close(dn.hessian, dt.hessian, rtol=1e-7, atol=1e-9 * float(dt.hessian.abs().max()))


# ---------------------------------------------------------------- identities and invariances
def test_contracted_triangles_give_the_central_potential():
    g = torch.Generator().manual_seed(17)
    K = 64
    centres_a = torch.randn(K, 3, generator=g, dtype=F64)
    direction = torch.randn(K, 3, generator=g, dtype=F64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    r = torch.logspace(-1, 3, K, dtype=F64)
    centres_b = centres_a + r[:, None] * direction
    shape_a = torch.randn(K, 3, 3, generator=g, dtype=F64)
    shape_b = torch.randn(K, 3, 3, generator=g, dtype=F64)
    size = 1e-7

    def shrink(shape, centre):
        shape = shape - shape.mean(1, keepdim=True)
        return centre[:, None, :] + size * shape / shape.norm(dim=-1).amax(-1)[:, None, None]

    a, b = shrink(shape_a, centres_a), shrink(shape_b, centres_b)
    # P_c is the contracted potential without margin; a margin of 1e-13 changes it by ~1e-13 relative
    val = pair_potential(a, b, mu=1.0, margin=1e-13)
    pc = central_potential((a.mean(1) - b.mean(1)).norm(dim=-1), mu=1.0)
    assert ((val - pc).abs() <= 1e-6 * pc).all(), ((val - pc) / pc).abs().max()


def test_exact_potential_bounds_the_central_potential_from_above():
    a, b, _ = random_separated_pairs(2000, gap=(1.01e-3, 100.0), seed=19)
    val = pair_potential(a, b, mu=1.0, margin=MARGIN)
    pc = central_potential((a.mean(1) - b.mean(1)).norm(dim=-1), mu=1.0)
    assert (val >= pc * (1 - 1e-14)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_symmetric_and_rigid_motion_invariant(backend):
    a, b, _ = random_separated_pairs(300, gap=(1.5e-3, 5.0), seed=23)
    val = pair_potential(a, b, backend=backend)
    torch.testing.assert_close(pair_potential(b, a, backend=backend), val, rtol=1e-12, atol=0)
    g = torch.Generator().manual_seed(29)
    R = random_rotations(300, g)
    t = 3.0 * torch.randn(300, 1, 3, generator=g, dtype=F64)
    moved = pair_potential(a @ R.transpose(1, 2) + t, b @ R.transpose(1, 2) + t, backend=backend)
    torch.testing.assert_close(moved, val, rtol=1e-11, atol=0)
    # the gradient rotates with the bodies
    d0 = pair_potential_derivatives(a, b, hessian=False, backend=backend)
    d1 = pair_potential_derivatives(
        a @ R.transpose(1, 2) + t, b @ R.transpose(1, 2) + t, hessian=False, backend=backend
    )
    rotated = (d0.grad.reshape(300, 6, 3) @ R.transpose(1, 2)).reshape(300, 18)
    torch.testing.assert_close(d1.grad, rotated, rtol=1e-8, atol=1e-9 * float(d0.grad.abs().max()))


def test_batch_equals_per_item_and_broadcasts():
    a, b, _ = random_separated_pairs(12, seed=31)
    batched = pair_potential_derivatives(a, b)
    for i in range(12):
        one = pair_potential_derivatives(a[i], b[i])
        assert one.value.shape == ()
        assert one.grad.shape == (18,) and one.hessian.shape == (18, 18) and one.plane.shape == (4,)
        assert one.value == batched.value[i]
        assert torch.equal(one.grad, batched.grad[i])
        assert torch.equal(one.hessian, batched.hessian[i])
    # (4, 1, 3, 3) x (3, 3, 3) -> (4, 3)
    far = b[:3] + torch.tensor([0.0, 0.0, 50.0], dtype=F64)
    grid = pair_potential(a[:4, None], far)
    assert grid.shape == (4, 3)
    for i in range(4):
        for j in range(3):
            assert grid[i, j] == pair_potential(a[i], far[j])


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba has one thread on this machine")
def test_threaded_pair_solves_equal_one_thread():
    """The numba solver's parallel loop over chunks of pairs gives with two threads exactly what one thread gives
    (the test workers compute on one thread, tests/conftest.py, so this test raises the count itself)."""
    a, b, _ = random_separated_pairs(3000, seed=37)
    before = numba.get_num_threads()
    out = {}
    try:
        for k in (1, 2):
            numba.set_num_threads(k)
            out[k] = pair_potential_derivatives(a, b, backend="numba")
    finally:
        numba.set_num_threads(before)
    one, two = out[1], out[2]
    assert bool(torch.isfinite(one.value).all()) and float(one.grad.abs().max()) > 0
    for x, y in (
        (one.value, two.value),
        (one.grad, two.grad),
        (one.hessian, two.hessian),
        (one.plane, two.plane),
    ):
        assert torch.equal(x, y)


def test_float32_inputs_solve_in_float64_and_return_float32():
    a, b, _ = random_separated_pairs(200, gap=(1e-2, 1.0), seed=37)
    a32, b32 = a.float(), b.float()
    v32 = pair_potential(a32, b32)
    d32 = pair_potential_derivatives(a32, b32)
    assert (
        v32.dtype == torch.float32 and d32.grad.dtype == torch.float32 and d32.hessian.dtype == torch.float32
    )
    v64 = pair_potential(a32.double(), b32.double())  # same (rounded) geometry in float64
    torch.testing.assert_close(v32, v64.float(), rtol=1e-6, atol=0)
    bb = b32.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(pair_potential(a32, bb).sum(), bb)
    assert g.dtype == torch.float32 and g.abs().amax() > 0


# ---------------------------------------------------------------- barrier, far field, sweeps
def test_barrier_grows_without_bound_and_is_infinite_inside_the_margin():
    for name, (a, b) in feature_pairs(0.0).items():
        shift = torch.tensor([1.0, 0.0, 0.0] if name == "coplanar" else [0.0, 0.0, 1.0], dtype=F64)
        gaps = MARGIN * (1 + torch.logspace(-9, 2, 40, dtype=F64))
        vals = pair_potential(a.expand(40, 3, 3), b + gaps[:, None, None] * shift, mu=1.0, margin=MARGIN)
        assert torch.isfinite(vals).all(), name
        assert (vals[:-1] > vals[1:]).all(), name  # strictly decreasing in the gap
        assert vals[0] > 1e8, name  # gap - margin = 1e-12: value ~ 1/(gap - margin)
        inside = MARGIN * torch.tensor([0.999, 0.5, 0.0], dtype=F64)
        vin = pair_potential(a.expand(3, 3, 3), b + inside[:, None, None] * shift, mu=1.0, margin=MARGIN)
        assert torch.isinf(vin).all() and (vin > 0).all(), name


def test_pairs_within_rounding_of_the_margin_are_infinite_in_both_backends():
    """Two faces of 80-face icospheres vertex to vertex, 8.7e-19 m beyond the 1 mm margin (the balls placed exactly
    one margin apart): the numba kernel's separating-axis start was feasible where the closest-point one was not,
    its Newton steps could not decrease E, and it raised PairSolveError, while the torch backend returned +inf. A
    pair closer to the margin than 64 eps of its coordinates is now infeasible in both; from 3e-16 m beyond it both
    give the same finite barrier (to the documented conditioning eps L / (gap - margin))."""
    a = torch.tensor(
        [[-0.0088378860391235, 0.02313788603912348, 0.01429999999999998],
         [0.0088378860391235, 0.02313788603912348, 0.01429999999999998], [0.0, 0.02859999999999996, 0.0]],
        dtype=F64,
    )  # fmt: skip
    b = torch.tensor(
        [[0.015035909806607184, 0.03387138688113156, 0.0],
         [0.0088378860391235, 0.03506211396087644, 0.01429999999999998], [0.0, 0.02959999999999996, 0.0]],
        dtype=F64,
    )  # fmt: skip
    excess = torch.cat([torch.zeros(1, dtype=F64), torch.logspace(-19, -9, 31, dtype=F64)])
    bs = b.expand(len(excess), 3, 3).clone()
    bs[:, :, 1] += excess[:, None]
    vals = {be: pair_potential_derivatives(a.expand_as(bs), bs, backend=be).value for be in BACKENDS}
    v0, v1 = vals[BACKENDS[0]], vals[BACKENDS[1]]
    assert torch.isinf(v0[0]) and torch.isinf(v1[0])
    assert torch.equal(torch.isinf(v0), torch.isinf(v1))
    fin = torch.isfinite(v0)
    assert bool(fin[excess >= 3e-16].all())  # only pairs within rounding of the margin are refused
    gap = excess[fin] + 8.7e-19  # beyond the margin
    rel = (v0[fin] - v1[fin]).abs() / v0[fin]
    assert bool((rel <= 100 * 2.2e-16 * 0.03 / gap + 1e-12).all()), rel


def test_intersecting_triangles_are_infinite_with_zero_derivatives():
    a = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    b = torch.tensor([[0.0, 0.0, -0.5], [0.2, 0.1, 1.0], [-0.2, 0.1, 1.0]], dtype=F64)  # pierces a
    for backend in BACKENDS:
        d = pair_potential_derivatives(a, b, backend=backend)
        assert torch.isinf(d.value)
        assert (d.grad == 0).all() and (d.hessian == 0).all()
        bb = b.clone().requires_grad_(True)
        val = pair_potential(a, bb, backend=backend)
        (g,) = torch.autograd.grad(val, bb)
        assert torch.isinf(val) and (g == 0).all()


@pytest.mark.parametrize("distance", [1e3, 1e4])
def test_gradient_never_vanishes_and_pushes_apart(distance):
    g = torch.Generator().manual_seed(41)
    K = 64
    u = torch.randn(K, 3, generator=g, dtype=F64)
    u = u / u.norm(dim=-1, keepdim=True)
    a = torch.randn(K, 3, 3, generator=g, dtype=F64)
    b = torch.randn(K, 3, 3, generator=g, dtype=F64)
    a = a - a.mean(1, keepdim=True)
    b = b - b.mean(1, keepdim=True) + distance * u[:, None, :]
    for backend in BACKENDS:
        d = pair_potential_derivatives(a, b, mu=1e-8, margin=MARGIN, backend=backend)
        force_on_b = -d.grad[:, 9:].reshape(K, 3, 3).sum(1)  # -(dP/d translation of b)
        force_on_a = -d.grad[:, :9].reshape(K, 3, 3).sum(1)
        assert (force_on_b.norm(dim=-1) > 0).all()
        assert ((force_on_b * u).sum(-1) > 0).all()  # pushes b away from a
        assert ((force_on_a * u).sum(-1) < 0).all()  # and a away from b
        # magnitude close to the central force 12 mu (r^-3/2 + r^-2) at this range
        central = 12e-8 * (distance**-1.5 + distance**-2)
        ratio = force_on_b.norm(dim=-1) / central
        assert ((ratio > 0.9) & (ratio < 1.2)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_sweep_over_feature_cases_and_gaps(backend):
    gaps = [MARGIN * (1 + 1e-9), MARGIN * (1 + 1e-6), 1.5e-3, 1e-2, 0.1, 1.0, 10.0, 1e2, 1e3, 1e4]
    prev = None
    for gap in gaps:
        a, b = _adversarial(gap)
        d = pair_potential_derivatives(a, b, mu=1e-8, margin=MARGIN, backend=backend)
        assert (
            torch.isfinite(d.value).all() and torch.isfinite(d.grad).all() and torch.isfinite(d.hessian).all()
        )
        assert (d.value > 12e-8).all()
        # the upper triangle b is pushed up (+z; +x for the coplanar case), the lower one down
        push = d.grad[:, 9:].reshape(-1, 3, 3).sum(1)
        up = torch.tensor([0.0, 0.0, 1.0], dtype=F64).repeat(push.shape[0], 1)
        up[-1] = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
        assert ((push * up).sum(-1) < 0).all(), (gap, push)
        # the plane separates: n.a + d > delta/2 on a, < -delta/2 on b
        n, dd = d.plane[:, :3], d.plane[:, 3:]
        assert ((a @ n[:, :, None]).squeeze(-1) + dd > MARGIN / 2).all()
        assert ((b @ n[:, :, None]).squeeze(-1) + dd < -MARGIN / 2).all()
        assert (n.norm(dim=-1) < 1).all()
        if prev is not None:
            assert (d.value < prev).all()  # monotone in the gap
        prev = d.value
    # Hessian is positive semidefinite along the separation direction at every gap (convex barrier in the gap)


def test_tiny_and_huge_scales():
    # a tiny well-shaped triangle pair (size 1e-6, gap 1e-5, margin 1e-6) is valid and matches the reference
    tri = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.0]], dtype=F64)
    a = 1e-6 * tri
    b = 1e-6 * tri + torch.tensor([0.0, 0.0, 1e-5], dtype=F64)
    v = pair_potential(a, b, mu=1.0, margin=1e-6)
    ref, _ = reference_pair(a.numpy(), b.numpy(), mu=1.0, margin=1e-6)
    assert abs(v.item() - ref) <= 1e-10 * ref
    # far from the origin (translation 1e3): the same value as near it
    t = torch.tensor([1e3, -2e3, 5e2], dtype=F64)
    a2, b2, _ = random_separated_pairs(50, seed=43)
    torch.testing.assert_close(pair_potential(a2 + t, b2 + t), pair_potential(a2, b2), rtol=1e-9, atol=0)


def test_unconverged_solve_raises():
    a, b, _ = random_separated_pairs(10, seed=47)
    with pytest.raises(PairSolveError, match=r"did not converge for \d+ of 10"):
        pair_potential(a, b, max_iter=1)
    with pytest.raises(PairSolveError, match="did not converge"):
        pair_potential(a, b, max_iter=1, backend="torch")
    # the count is of the feasible pairs: an intersecting pair is not one
    with pytest.raises(PairSolveError, match="did not converge for 1 of 1 feasible pairs"):
        pair_potential(torch.stack([a[0], a[1]]), torch.stack([a[0], b[1]]), max_iter=1)


# ---------------------------------------------------------------- input validation
def _tri(rows):
    return torch.tensor(rows, dtype=F64)


GOOD = _tri([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
FAR = GOOD + torch.tensor([0.0, 0.0, 2.0], dtype=F64)


@pytest.mark.parametrize(
    ("tri_a", "tri_b", "match"),
    [
        (GOOD[:2], FAR, r"tri_a must have shape \(\.\.\., 3, 3\)"),
        (GOOD, FAR[..., :2], r"tri_b must have shape"),
        (GOOD.to(torch.int64), FAR, r"tri_a must be float32 or float64"),
        (GOOD, FAR.to(torch.float16), r"tri_b must be float32 or float64"),
        (GOOD.float(), FAR, r"share a dtype"),
        (
            torch.stack([GOOD, GOOD.clone().fill_(float("nan"))]),
            FAR,
            r"tri_a contains NaN or inf.*index \(1\)",
        ),
        (GOOD, torch.stack([FAR, FAR, FAR + float("inf")]), r"tri_b contains NaN or inf.*index \(2\)"),
        (
            torch.stack([GOOD, _tri([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]])]),
            FAR,
            r"tri_a has degenerate.*index \(1\)",
        ),
        (
            GOOD,
            torch.stack([FAR, _tri([[0, 0, 5], [0, 0, 5], [1, 0, 5.0]])]),
            r"tri_b has degenerate.*index \(1\)",
        ),
        (GOOD.expand(2, 3, 3, 3), FAR.expand(4, 3, 3), r"do not broadcast"),
    ],
)
def test_bad_input_raises_naming_the_argument(tri_a, tri_b, match):
    with pytest.raises(ValueError, match=match):
        pair_potential(tri_a, tri_b)
    with pytest.raises(ValueError, match=match):
        pair_potential_derivatives(tri_a, tri_b)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="mu"):
        pair_potential(GOOD, FAR, mu=-1.0)
    with pytest.raises(ValueError, match="margin"):
        pair_potential(GOOD, FAR, margin=0.0)
    with pytest.raises(ValueError, match="max_iter"):
        pair_potential(GOOD, FAR, max_iter=0)
    with pytest.raises(ValueError, match="backend"):
        pair_potential(GOOD, FAR, backend="cuda")
    with pytest.raises(TypeError, match="tri_a must be a torch.Tensor"):
        pair_potential(GOOD.numpy(), FAR)


def test_tiny_well_shaped_and_needle_triangles():
    tiny = 1e-9 * GOOD
    assert torch.isfinite(pair_potential(tiny, FAR))
    needle = _tri([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-15, 0.0]])
    with pytest.raises(ValueError, match="tri_a has degenerate"):
        pair_potential(needle, FAR)


def test_central_potential_and_its_derivatives():
    r = torch.logspace(-3, 4, 50, dtype=F64).requires_grad_(True)
    pc = central_potential(r, mu=1.0)
    torch.testing.assert_close(pc, 12 * (1 + 1 / r.sqrt()) ** 2)
    (d1,) = torch.autograd.grad(pc.sum(), r, create_graph=True)
    assert (d1 < 0).all()
    torch.testing.assert_close(d1, -12 * (r**-1.5 + r**-2))
    (d2,) = torch.autograd.grad(d1.sum(), r)
    torch.testing.assert_close(d2, 12 * (1.5 * r**-2.5 + 2 * r**-3))
    assert math.isinf(central_potential(torch.zeros(1, dtype=F64)).item())
    with pytest.raises(ValueError, match="r must be >= 0"):
        central_potential(torch.tensor([1.0, -1.0]))
    with pytest.raises(ValueError, match="r contains NaN"):
        central_potential(torch.tensor([float("nan")]))


def test_badly_conditioned_pair_from_a_toppling_stack_converges():
    """A board's top triangle against a neighbour's tilted side triangle (from a 20-board stack at mu = 1e-10,
    margin 1e-5): Newton's endgame kept accepting steps that changed E by less than its rounding while the relative
    gradient stayed at 1.2e-10 > tol 1e-12, and 100 iterations raised PairSolveError. Below the stall tolerance
    (1e-8) that is converged, in both backends, and they agree."""
    a = [
        [0.19000720401659071, -0.09891460625193393, 0.20219767346037437],
        [0.19005035745478910, 0.10108538476787449, 0.20215608190682413],
        [-0.80752719316456290, -0.09868477680592863, 0.27237654220915364],
    ]
    b = [
        [0.22833757378500186, -0.09892582053297974, 0.19951623315134301],
        [-0.76709116053010595, -0.09867819348027260, 0.29962404293991679],
        [-0.76919661529536432, -0.09868323818123015, 0.26969801689597900],
    ]
    ta, tb = torch.tensor(a, dtype=F64), torch.tensor(b, dtype=F64)
    kw = {"mu": 1e-10, "margin": 1e-5, "tol": 1e-12, "max_iter": 100}
    v = {be: pair_potential_derivatives(ta, tb, backend=be, **kw) for be in ("numba", "torch")}
    assert math.isfinite(float(v["numba"].value)) and float(v["numba"].grad.abs().max()) > 0
    torch.testing.assert_close(v["numba"].value, v["torch"].value, rtol=1e-9, atol=0)
    torch.testing.assert_close(v["numba"].grad, v["torch"].grad, rtol=1e-6, atol=0)


# ---------------------------------------------------------------- warm-started plane solves
def test_warm_started_solve_finds_the_same_optimum():
    """The simulator starts each leaf pair's plane solve from its plane at nearby vertices: the optimum must not
    depend on the start. Warm planes from slightly moved triangles, an infeasible one (falls back to the cold start)
    and a feasible but poor one (a scaled-down plane) all give the cold solve's value, plane and gradient."""
    from cfd_torch.contact.pair import _prepare, _solve

    a, b, _ = random_separated_pairs(200, gap=(2e-3, 0.5), seed=11)
    kw = {"mu": 1e-8, "margin": MARGIN, "tol": 1e-12, "max_iter": 100}
    X, _ = _prepare(a, b, **kw, name="pair_potential")
    solve = dict(kw)
    sol = _solve(X, want_grad=True, want_hess=False, backend="numba", **solve)
    v0, P0, g0 = sol.value, sol.world_plane(), sol.grad
    moved = X + 1e-4 * torch.randn(X.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    P_near = _solve(moved, want_grad=False, want_hess=False, backend="numba", **solve).world_plane()
    bad = torch.zeros_like(P0)  # n = 0: infeasible, the cold start is used
    poor = 0.3 * P0  # a poor start where still feasible (infeasible ones fall back to the cold start)
    on = torch.ones(X.shape[0], dtype=torch.bool)
    for start in (P_near, bad, poor):
        sol = _solve(X, want_grad=True, want_hess=False, backend="numba", start=(start, on), **solve)
        v, P, g = sol.value, sol.world_plane(), sol.grad
        assert float(g0.abs().max()) > 0
        torch.testing.assert_close(v, v0, rtol=1e-13, atol=0)
        torch.testing.assert_close(P, P0, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(g, g0, rtol=1e-8, atol=1e-8 * float(g0.abs().max()))


def test_large_hessians_live_in_recycled_buffers_that_are_reused_only_once_free():
    """Large (K, 18, 18) Hessians are backed by a pool of two huge-page buffers, reused once no tensor refers to
    them: a held Hessian, a view of it or a tensor set on its storage is never overwritten by later large calls,
    and a freed buffer is reused (the 'free' reference count is measured at import, not assumed to be 3)."""
    from cfd_torch.contact import pair as pair_mod

    ta, tb, _ = random_separated_pairs(13_000, seed=1)
    ta2, tb2, _ = random_separated_pairs(13_000, seed=2)
    d = pair_potential_derivatives(ta, tb)
    assert d.hessian.numel() * 8 >= pair_mod._HUGEPAGE_MIN_BYTES  # (the recycled path)
    ref = d.hessian.clone()
    assert bool((ref != 0).any())
    view = d.hessian[5:7]
    on_storage = torch.empty(0, dtype=F64).set_(d.hessian.untyped_storage(), 0, ref.shape)
    del d
    for _ in range(3):  # more large calls than the pool has buffers
        other = pair_potential_derivatives(ta2, tb2)
    assert torch.equal(view, ref[5:7]) and torch.equal(on_storage, ref)
    del view, on_storage, other
    pooled = {torch.frombuffer(b, dtype=torch.uint8, count=1).data_ptr() for b in pair_mod._HESS_POOL}
    again = pair_potential_derivatives(ta, tb).hessian
    assert again.data_ptr() in pooled and torch.equal(again, ref)
