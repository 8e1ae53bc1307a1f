import pytest
import torch
from conftest import F64, feature_pairs

from cfd_torch import pair_potential
from cfd_torch.baselines import ipc_barrier, ipc_pair_barrier, sdrs_barrier, sdrs_pair_potential


def test_scalar_barriers_match_closed_forms_and_vanish_beyond_dhat():
    x = torch.tensor([0.25, 0.5, 1.0, 2.0], dtype=F64)
    torch.testing.assert_close(ipc_barrier(x, 1.0)[0], torch.tensor(0.7797905781, dtype=F64))  # ipctk value
    assert (ipc_barrier(x, 1.0)[2:] == 0).all() and (sdrs_barrier(x, 1.0)[2:] == 0).all()
    assert (
        not ipc_barrier(x, 1.0)[2:].signbit().any() and not sdrs_barrier(x, 1.0)[2:].signbit().any()
    )  # +0.0
    assert torch.isinf(ipc_barrier(torch.zeros(1, dtype=F64), 1.0)).all()
    torch.testing.assert_close(sdrs_barrier(x[:1], 1.0), ipc_barrier(x[:1], 1.0) / x[:1])


def test_peers_lose_the_gradient_where_ours_keeps_it():
    dhat = 1e-2
    for gap, peers_active in [(3e-3, True), (0.1, False), (10.0, False)]:
        a, b = (t.expand(5, 3, 3) for t in feature_pairs(gap)["vertex-face"])
        b = b.clone().requires_grad_(True)
        models = {
            "ipc": lambda x, y: ipc_pair_barrier(x, y, dhat=dhat),
            "sdrs": lambda x, y: sdrs_pair_potential(x, y, dhat=dhat, margin=1e-3),
            "ours": lambda x, y: pair_potential(x, y, margin=1e-3),
        }
        for name, fn in models.items():
            (g,) = torch.autograd.grad(fn(a, b).sum(), b)
            fz = -g[..., 2].sum(-1)
            if name == "ours" or peers_active:
                assert (fz > 0).all(), (name, gap, fz)  # pushes b up, away from a
            else:
                assert (g == 0).all(), (name, gap)


def test_ipc_pair_barrier_is_infinite_for_intersecting_and_touching_triangles():
    """+inf where an edge of one triangle crosses the other or they touch; two parallel faces on either side of
    each other (no intersection) stay finite."""
    for name in ("vertex-face", "edge-edge"):
        for gap in (0.0, -1e-3, -5e-2):
            a, b = feature_pairs(gap)[name]
            assert torch.isinf(ipc_pair_barrier(a[None], b[None])).all(), (name, gap)
    a, b = feature_pairs(-1e-3)["face-face"]  # parallel planes 1 mm apart, b below a: disjoint
    assert 0 < float(ipc_pair_barrier(a[None], b[None])[0]) < float("inf")


def test_pair_baselines_are_differentiable_once_and_refuse_the_second_derivative():
    a, b = feature_pairs(3e-3)["vertex-face"]
    a, b = a[None].clone().requires_grad_(True), b[None].clone().requires_grad_(True)
    for name, fn in (
        ("ipc_pair_barrier", lambda x, y: ipc_pair_barrier(x, y, dhat=1e-2)),
        ("sdrs_pair_potential", lambda x, y: sdrs_pair_potential(x, y, dhat=1e-2, margin=1e-3)),
    ):
        (g,) = torch.autograd.grad(fn(a, b).sum(), b)
        assert float(g.abs().max()) > 0
        assert torch.autograd.gradcheck(fn, (a, b), eps=1e-7, atol=1e-6, rtol=1e-5)
        (g,) = torch.autograd.grad(fn(a, b).sum(), b, create_graph=True)
        with pytest.raises(RuntimeError, match=f"{name}: second derivatives are not implemented"):
            torch.autograd.grad(g.sum(), b)


def test_pair_baselines_refuse_forward_mode_and_sdrs_refuses_vmap():
    """Forward mode ran past the first-order Function (a tangent does not require grad, and torch.no_grad does not
    stop it): jacfwd(jacfwd(sdrs)) gave a Hessian 2.5x off, unannounced. Now every forward-mode use raises by name;
    vmap of sdrs (whose plane search loops on values) raises by name; vmap of ipc's value works."""
    a, b = feature_pairs(3e-3)["vertex-face"]
    a, b = a[None], b[None]
    for name, fn in (
        ("ipc_pair_barrier", lambda x, y: ipc_pair_barrier(x, y, dhat=1e-2)),
        ("sdrs_pair_potential", lambda x, y: sdrs_pair_potential(x, y, dhat=1e-2, margin=1e-3)),
    ):
        s = lambda y, fn=fn: fn(a, y).sum()  # noqa: E731
        assert float(s(b)) > 0
        refusal = f"{name} does not support forward-mode AD"
        with pytest.raises(NotImplementedError, match=refusal):
            torch.func.jvp(s, (b,), (torch.ones_like(b),))
        with pytest.raises(NotImplementedError, match=refusal):
            torch.func.jacfwd(torch.func.jacfwd(s))(b)
        with pytest.raises(NotImplementedError, match=refusal):
            torch.func.hessian(s)(b)
        with torch.autograd.forward_ad.dual_level(), torch.no_grad():
            with pytest.raises(NotImplementedError, match=refusal):
                s(torch.autograd.forward_ad.make_dual(b, torch.ones_like(b)))
        with pytest.raises(NotImplementedError, match=f"{name} does not support torch.func.vmap"):
            torch.func.vmap(torch.func.grad(s))(b[None])
        x = b.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(s(x), x)
        assert float(g.abs().max()) > 0
        torch.testing.assert_close(torch.func.grad(s)(b), g, rtol=1e-12, atol=0)
    with pytest.raises(NotImplementedError, match="sdrs_pair_potential does not support torch.func.vmap"):
        torch.func.vmap(lambda y: sdrs_pair_potential(a, y))(b[None])
    torch.testing.assert_close(
        torch.func.vmap(lambda y: ipc_pair_barrier(a, y))(b[None])[0], ipc_pair_barrier(a, b)
    )


def test_baselines_check_their_arguments():
    a, b = feature_pairs(3e-3)["vertex-face"]
    a, b = a[None], b[None]
    for fn in (ipc_pair_barrier, sdrs_pair_potential):
        with pytest.raises(ValueError, match="kappa must be a finite positive number"):
            fn(a, b, kappa=0.0)
        with pytest.raises(ValueError, match="dhat must be a finite positive number"):
            fn(a, b, dhat=float("nan"))
        with pytest.raises(ValueError, match="tri_a and tri_b must both be"):
            fn(a.expand(2, 3, 3), b)
        with pytest.raises(ValueError, match="must share dtype and device"):
            fn(a, b.float())
    with pytest.raises(ValueError, match="dhat must be below 1"):
        sdrs_pair_potential(a, b, dhat=1.5)
    with pytest.raises(ValueError, match="margin must be a finite positive number"):
        sdrs_pair_potential(a, b, margin=0.0)
    with pytest.raises(ValueError, match="iters must be a positive int"):
        sdrs_pair_potential(a, b, iters=0)
    with pytest.raises(ValueError, match="xhat must be a finite positive number"):
        ipc_barrier(torch.ones(1, dtype=F64), 0.0)
    nan = torch.tensor([float("nan")], dtype=F64)
    assert torch.isnan(ipc_barrier(nan, 1.0)).all() and torch.isnan(sdrs_barrier(nan, 1.0)).all()


def test_sdrs_pair_potential_is_exactly_zero_beyond_its_reach():
    """Parallel faces beyond (2 dhat + margin) / (1 - dhat) apart: value and gradient exactly 0 (the plane search
    starts in the zero region, |n| <= 1 - dhat)."""
    dhat, margin = 1e-2, 1e-3
    reach = (2 * dhat + margin) / (1 - dhat)
    for gap in (1.01 * reach, 0.1, 10.0):
        a, b = feature_pairs(gap)["face-face"]
        b = b[None].clone().requires_grad_(True)
        v = sdrs_pair_potential(a[None], b, dhat=dhat, margin=margin, kappa=1e6)
        (g,) = torch.autograd.grad(v.sum(), b)
        assert float(v[0]) == 0.0 and float(g.abs().max()) == 0.0, gap
    a, b = feature_pairs(0.9 * reach)["face-face"]
    assert float(sdrs_pair_potential(a[None], b[None], dhat=dhat, margin=margin)[0]) > 0


def test_pair_baselines_under_inference_mode_and_torch_func_grad():
    """Value-only calls (no_grad, inference_mode) compute no gradient and agree with the differentiable call;
    torch.func.grad equals autograd's gradient."""
    a, b = feature_pairs(3e-3)["vertex-face"]
    a, b = a[None].expand(3, 3, 3).clone(), b[None].expand(3, 3, 3).clone()
    for fn in (ipc_pair_barrier, sdrs_pair_potential):
        x = b.clone().requires_grad_(True)
        v = fn(a, x)
        (g,) = torch.autograd.grad(v.sum(), x)
        assert float(g.abs().max()) > 0
        with torch.inference_mode():
            torch.testing.assert_close(fn(a, b), v.detach(), rtol=0, atol=0)
        torch.testing.assert_close(torch.func.grad(lambda y, f=fn: f(a, y).sum())(b), g, rtol=1e-12, atol=0)
