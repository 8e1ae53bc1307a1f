"""The custom autograd Functions: float64 gradcheck of each, gradgradcheck or an asserted refusal of the next
order, and the torch.func transforms (grad and jacrev work; vmap and forward mode raise saying so); the closed-form
derivatives' results refuse a backward; the plain-torch functions run under vmap; torch.compile traces around the
numba input checks.

Functions and where their checks are: ClosedFormPotential, ClosedFormGrad, refuse_third_order (cfd_torch/_autograd.py),
_KnownGradPotential (contact/scene.py) and _PairGradFn (contact/pair.py) here, on their own; _PairPotentialFn through
pair_potential in test_pair_potential.py; the closed-form ones also through mesh_potential and contact_potential in
test_mesh_potential.py.

Small inputs throughout: the whole file runs in a few seconds.
"""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys

import pytest
import torch
import trimesh

from cfd_torch import (
    contact_potential,
    mesh_potential,
    mesh_potential_derivatives,
    pair_potential,
    pair_potential_derivatives,
)
from cfd_torch._autograd import ClosedFormGrad, ClosedFormPotential, refuse_third_order
from cfd_torch.contact import mesh as mesh_module
from cfd_torch.contact import pair as pair_module
from cfd_torch.contact import scene as scene_module
from cfd_torch.contact.bsh import BSH
from cfd_torch.testing import random_separated_pairs

F64 = torch.float64
BACKENDS = ["numba", "torch"]


@functools.cache
def _ico() -> BSH:
    return BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=0, radius=1.0))


@functools.cache
def _box() -> BSH:
    return BSH.from_trimesh(trimesh.creation.box(extents=(1.0, 0.8, 0.6)))


def _near_poses() -> tuple[torch.Tensor, torch.Tensor]:
    """An icosahedron and a box close enough for the traversal to reach leaf pairs."""
    pa = torch.tensor([0.0, 0.1, 0.0, 0.2, -0.4, 0.3], dtype=F64)
    pb = torch.tensor([0.25, 1.7, 0.15, 0.5, 0.1, -0.2], dtype=F64)
    return pa, pb


def _pairs() -> tuple[torch.Tensor, torch.Tensor]:
    a, b, _ = random_separated_pairs(3, gap=(5e-2, 0.5), seed=5)
    return a, b


def _assert_close(actual: torch.Tensor, expected: torch.Tensor, rtol: float, what: str = "") -> None:
    scale = float(expected.abs().max())
    assert scale > 0, f"{what}: the reference is zero"
    err = float((actual - expected).abs().max())
    assert err <= rtol * scale, f"{what}: max error {err:.3e} > {rtol:.1e} * {scale:.3e}"


# ------------------------------------------------------------------------------------------------ the Functions
_C = torch.tensor([0.3, -0.5, 0.2, 0.7], dtype=F64)


def _evaluate(q: torch.Tensor, order: int):
    """Closed-form f(q) = exp(c.q) + sum sin(q) for q (B, 4): value (B,), grad (B, 4), Hessian (B, 4, 4)."""
    e = torch.exp(q @ _C)
    v = e + torch.sin(q).sum(-1)
    g = _C * e[:, None] + torch.cos(q) if order >= 1 else None
    h = _C[:, None] * _C * e[:, None, None] - torch.diag_embed(torch.sin(q)) if order >= 2 else None
    return v, g, h


def _q() -> torch.Tensor:
    return torch.tensor([[0.1, -0.4, 0.8, 0.3], [1.2, 0.5, -0.7, -0.2]], dtype=F64, requires_grad=True)


def _third(f, q: torch.Tensor) -> None:
    (g,) = torch.autograd.grad(f(q).sum(), q, create_graph=True)
    (h,) = torch.autograd.grad(g[:, 0].sum(), q, create_graph=True)
    assert h.abs().max() > 0 and h.requires_grad
    torch.autograd.grad(h.sum() + (q**4).sum(), q)


def test_closed_form_potential_gradcheck_gradgradcheck_and_refused_third_order():
    def f(q):
        return ClosedFormPotential.apply(q, _evaluate, "test_potential")

    q = _q()
    _assert_close(f(q), _evaluate(q.detach(), 0)[0], 0.0, "value")
    assert torch.autograd.gradcheck(f, (q,))
    assert torch.autograd.gradgradcheck(f, (q,))
    with pytest.raises(RuntimeError, match="test_potential: third derivatives are not implemented"):
        _third(f, q)


def test_closed_form_grad_gradcheck_and_refused_second_backward():
    def f(q):
        g, h = ClosedFormGrad.apply(q, _evaluate, "test_potential")
        assert not h.requires_grad  # the Hessian output is what backward uses, not differentiable
        return g

    q = _q()
    _assert_close(f(q), _evaluate(q.detach(), 1)[1], 0.0, "grad")
    assert torch.autograd.gradcheck(f, (q,))
    with pytest.raises(RuntimeError, match="test_potential: third derivatives"):
        torch.autograd.gradgradcheck(f, (q,))


@pytest.mark.parametrize("known_grad", [True, False], ids=["grad-given", "grad-lazy"])
def test_known_grad_potential_gradcheck_gradgradcheck_and_refused_third_order(known_grad):
    def f(q):
        v, g, _ = _evaluate(q.detach(), 1 if known_grad else 0)
        return scene_module._KnownGradPotential.apply(q, v, g, _evaluate)

    q = _q()
    assert torch.autograd.gradcheck(f, (q,))
    assert torch.autograd.gradgradcheck(f, (q,))
    with pytest.raises(RuntimeError, match="contact_potential: third derivatives"):
        _third(f, q)


def test_pair_grad_fn_gradcheck_and_refused_second_backward():
    # _PairGradFn(X, P, C, O, feasible) is grad_x P at the optimal plane P = p*(X); its backward is the implicit
    # Hessian, the derivative of the whole map X -> grad_x P(X, p*(X)), so the check re-solves the plane at every X
    a, b = _pairs()
    X0 = torch.cat([a, b], -2)  # (K, 6, 3)

    def f(X):
        with torch.no_grad():
            sol = pair_module._solve(
                X.detach(), mu=1.0, margin=1e-3, tol=1e-14, max_iter=100, want_grad=False, want_hess=False,
                backend="numba",
            )  # fmt: skip
        feasible = torch.isfinite(sol.value)
        return pair_module._PairGradFn.apply(X, sol.local_plane, sol.centre, sol.offset, feasible, 1.0, 1e-3)

    X = X0.clone().requires_grad_(True)
    assert f(X).abs().max() > 0
    assert torch.autograd.gradcheck(f, (X,), eps=1e-6, atol=1e-6, rtol=1e-5)
    with pytest.raises(RuntimeError, match="pair_potential: third derivatives"):
        torch.autograd.gradgradcheck(f, (X,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_refuse_third_order_is_the_identity_passes_the_vectors_gradient_and_refuses_the_points():
    hv = torch.randn(2, 4, dtype=F64, requires_grad=True)
    x = _q()
    out = refuse_third_order(hv, x, "test_potential")
    assert torch.equal(out, hv)
    w = torch.randn(2, 4, dtype=F64)
    (g,) = torch.autograd.grad(out, hv, w, retain_graph=True)  # the product's own derivative passes
    assert torch.equal(g, w)
    with pytest.raises(RuntimeError, match="test_potential: third derivatives are not implemented"):
        torch.autograd.grad(out, x, w)


def _pair_flat(x: torch.Tensor) -> torch.Tensor:
    return pair_potential(x[:9].reshape(3, 3), x[9:].reshape(3, 3), mu=1.0)


def _mesh_flat(x: torch.Tensor) -> torch.Tensor:
    return mesh_potential(_ico(), x[:6], _box(), x[6:])


def _scene_flat(x: torch.Tensor) -> torch.Tensor:
    return contact_potential([_ico(), _box()], x.reshape(2, 6)).value


def _flat_inputs(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """A point where the potential is not trivial, and its closed-form Hessian."""
    if name == "pair":
        a, b = _pairs()
        d = pair_potential_derivatives(a[0], b[0], mu=1.0)
        return torch.cat([a[0].reshape(9), b[0].reshape(9)]), d.hessian.reshape(18, 18)
    x = torch.tensor(
        [0.0, 0.0, 0.0, 0.2, -0.1, 0.3, 1.5, 0.1, -0.05, -0.2, 0.4, 0.1], dtype=F64
    )  # leaf pairs in play
    d = mesh_potential_derivatives(_ico(), x[:6], _box(), x[6:])
    return x, d.hessian


@pytest.mark.parametrize("name", ["pair", "mesh", "scene"])
def test_hessian_vector_products_and_vectorized_hessians_of_autograd_functional(name):
    """torch.autograd.functional's hvp (a double backward: the product differentiated in its vector), vhp and
    hessian(vectorize=True) (batched gradients) give the closed-form Hessian; a third derivative is still refused."""
    f = {"pair": _pair_flat, "mesh": _mesh_flat, "scene": _scene_flat}[name]
    x, H = _flat_inputs(name)
    assert float(H.abs().max()) > 0
    v = torch.linspace(-1.0, 1.0, x.numel(), dtype=F64)
    for fn in (torch.autograd.functional.hvp, torch.autograd.functional.vhp):
        _assert_close(fn(f, x, v)[1], H @ v, 1e-10, fn.__name__)
    _assert_close(
        torch.autograd.functional.hessian(f, x, vectorize=True), H, 1e-10, "hessian(vectorize=True)"
    )
    x = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(f(x), x, create_graph=True)
    (hv,) = torch.autograd.grad(g, x, v, create_graph=True)
    with pytest.raises(RuntimeError, match="third derivatives are not implemented"):
        torch.autograd.grad(hv.sum(), x)


# ------------------------------------------------------------------------------------------------ torch.func
@pytest.mark.parametrize("backend", BACKENDS)
def test_func_grad_and_jacrev_of_pair_potential_equal_autograd(backend):
    a, b = _pairs()

    def f(x):
        return pair_potential(x, b, mu=1.0, backend=backend)

    x = a.clone().requires_grad_(True)
    (g_ref,) = torch.autograd.grad(f(x).sum(), x)
    _assert_close(torch.func.grad(lambda y: f(y).sum())(a), g_ref, 1e-12, "func.grad")
    J_ref = torch.autograd.functional.jacobian(f, a)  # (K, K, 3, 3)
    _assert_close(torch.func.jacrev(f)(a), J_ref, 1e-12, "func.jacrev")
    # both arguments at once
    y = b.clone().requires_grad_(True)
    ga_ref, gb_ref = torch.autograd.grad(pair_potential(x, y, mu=1.0, backend=backend).sum(), (x, y))
    ga, gb = torch.func.grad(
        lambda u, w: pair_potential(u, w, mu=1.0, backend=backend).sum(), argnums=(0, 1)
    )(a, b)
    _assert_close(ga, ga_ref, 1e-12, "func.grad argnums 0")
    _assert_close(gb, gb_ref, 1e-12, "func.grad argnums 1")


@pytest.mark.parametrize("backend", BACKENDS)
def test_func_grad_of_grad_of_pair_potential_equals_double_backward_and_third_order_raises(backend):
    a, b = _pairs()

    def f(x):
        return pair_potential(x, b, mu=1.0, backend=backend).sum()

    x = a.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(f(x), x, create_graph=True)
    (hv_ref,) = torch.autograd.grad(g.sum(), x)
    hv = torch.func.grad(lambda y: torch.func.grad(f)(y).sum())(a)
    _assert_close(hv, hv_ref, 1e-12, "func.grad of func.grad")
    with pytest.raises(RuntimeError, match="pair_potential: third derivatives"):
        torch.func.grad(lambda y: torch.func.grad(lambda z: torch.func.grad(f)(z).sum())(y).sum())(a)


def test_func_grad_of_mesh_and_contact_potentials_equals_autograd():
    pa, pb = _near_poses()

    def f(x):
        return mesh_potential(_ico(), x, _box(), pb, mu=1.0)

    x = pa.clone().requires_grad_(True)
    (g_ref,) = torch.autograd.grad(f(x), x)
    _assert_close(torch.func.grad(f)(pa), g_ref, 1e-12, "mesh func.grad")
    _assert_close(torch.func.jacrev(f)(pa), g_ref, 1e-12, "mesh func.jacrev")

    poses = torch.stack([pa, pb])

    def c(p):
        return contact_potential([_ico(), _box()], p, static=[False, True], mu=1.0).value

    y = poses.clone().requires_grad_(True)
    (gc_ref,) = torch.autograd.grad(c(y), y)
    _assert_close(gc_ref[0], g_ref, 1e-10, "contact vs mesh")
    _assert_close(torch.func.grad(c)(poses), gc_ref, 1e-12, "contact func.grad")


def test_func_jacrev_of_jacrev_equals_the_autograd_hessian():
    a, b = _pairs()

    def f(x):
        return pair_potential(x, b, mu=1.0).sum()

    H_ref = torch.autograd.functional.hessian(f, a)
    _assert_close(torch.func.jacrev(torch.func.jacrev(f))(a), H_ref, 1e-12, "pair")
    pa, pb = _near_poses()

    def g(x):
        return mesh_potential(_ico(), x, _box(), pb, mu=1.0)

    H_ref = torch.autograd.functional.hessian(g, pa)
    _assert_close(torch.func.jacrev(torch.func.jacrev(g))(pa), H_ref, 1e-12, "mesh")


def test_func_third_derivatives_of_mesh_and_contact_potentials_raise():
    pa, pb = _near_poses()

    def g(x):
        return mesh_potential(_ico(), x, _box(), pb, mu=1.0)

    def c(p):
        return contact_potential([_ico(), _box()], p, static=[False, True], mu=1.0).value

    def third(fn):
        return torch.func.grad(lambda y: torch.func.grad(lambda z: torch.func.grad(fn)(z).sum())(y).sum())

    with pytest.raises(RuntimeError, match="mesh_potential: third derivatives"):
        third(g)(pa)
    with pytest.raises(RuntimeError, match="contact_potential: third derivatives"):
        third(c)(torch.stack([pa, pb]))


def test_kernels_and_caches_see_plain_tensors_under_func_grad(monkeypatch):
    # inside a Function's forward the inputs are plain tensors with no transform active (the numba kernels need
    # storage); contact_potential evaluates outside the transforms and must not cache wrapped tensors
    seen = []

    def spy(fn):
        def wrapped(*args, **kwargs):
            tensors = [x for x in (*args, *kwargs.values()) if isinstance(x, torch.Tensor)]
            wrapped_inputs = any(torch._C._functorch.is_functorch_wrapped_tensor(x) for x in tensors)
            seen.append((fn.__name__, wrapped_inputs, torch._C._are_functorch_transforms_active()))
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(pair_module, "_solve", spy(pair_module._solve))
    monkeypatch.setattr(mesh_module, "_derivs", spy(mesh_module._derivs))
    monkeypatch.setattr(scene_module, "traverse", spy(scene_module.traverse))
    a, b = _pairs()
    torch.func.grad(lambda x: pair_potential(x, b, mu=1.0, backend="numba").sum())(a)
    pa, pb = _near_poses()
    torch.func.grad(lambda x: mesh_potential(_ico(), x, _box(), pb, mu=1.0))(pa)
    fresh = [BSH.from_trimesh(trimesh.creation.icosphere(subdivisions=0, radius=1.0)), _box()]  # new forest

    def c(p):
        return contact_potential(fresh, p, static=[False, True], mu=1.0).value

    poses = torch.stack([pa, pb])
    g = torch.func.grad(c)(poses)
    assert {name for name, _, _ in seen} == {"_solve", "_derivs", "traverse"}
    assert not any(w or active for _, w, active in seen), seen
    # the forest built under the transform serves a plain call afterwards
    x = poses.clone().requires_grad_(True)
    (g_ref,) = torch.autograd.grad(c(x), x)
    _assert_close(g, g_ref, 1e-12, "contact after func.grad")


def test_forward_mode_is_refused_with_a_clear_message():
    a, b = _pairs()
    pa, pb = _near_poses()
    for dt in (
        torch.float64,
        torch.float32,
    ):  # (float32 inputs are widened first: the refusal must pass that cast)
        cases = {
            "pair_potential": (lambda x, dt=dt: pair_potential(x, b.to(dt), mu=1.0).sum(), a.to(dt)),
            "mesh_potential": (
                lambda x, dt=dt: mesh_potential(_ico(), x, _box(), pb.to(dt), mu=1.0),
                pa.to(dt),
            ),
            "contact_potential": (
                lambda p: contact_potential([_ico(), _box()], p, mu=1.0).value,
                torch.stack([pa, pb]).to(dt),
            ),
        }
        for name, (f, x) in cases.items():
            with pytest.raises(NotImplementedError, match=f"{name} does not support forward-mode AD"):
                torch.func.jvp(f, (x,), (torch.ones_like(x),))
            with pytest.raises(NotImplementedError, match=f"{name} does not support forward-mode AD"):
                torch.func.hessian(f)(x)


def test_vmap_is_refused_with_a_clear_message():
    a, b = _pairs()
    with pytest.raises(NotImplementedError, match="pair_potential does not support torch.func.vmap"):
        torch.func.vmap(lambda x: pair_potential(x, b[0], mu=1.0))(a)
    with pytest.raises(NotImplementedError, match="pair_potential does not support torch.func.vmap"):
        torch.func.vmap(torch.func.grad(lambda x: pair_potential(x, b[0], mu=1.0)))(a)
    pa, pb = _near_poses()
    with pytest.raises(NotImplementedError, match="mesh_potential does not support torch.func.vmap"):
        torch.func.vmap(lambda x: mesh_potential(_ico(), x, _box(), pb))(torch.stack([pa, pa]))
    with pytest.raises(NotImplementedError, match="contact_potential does not support torch.func.vmap"):
        torch.func.vmap(lambda p: contact_potential([_ico(), _box()], p).value)(torch.stack([pa, pb])[None])


# ----------------------------------------------------------------------- values-only results, plain-torch functions
def test_closed_form_derivatives_refuse_a_backward_instead_of_acting_as_constants():
    """The *_derivatives results and contact_potential's grad/hessian are values: a loss through them raises under
    autograd and torch.func.grad (as constants they would drop their part of the gradient silently), while the
    values themselves are unchanged and a detached call builds no graph."""
    a, b = _pairs()
    pa, pb = _near_poses()
    ref = pair_potential_derivatives(a, b, mu=1.0)
    assert float(ref.grad.abs().max()) > 0
    cases = {
        "pair_potential_derivatives(...).grad": (lambda x: pair_potential_derivatives(x, b, mu=1.0).grad, a),
        "pair_potential_derivatives(...).value": (
            lambda x: pair_potential_derivatives(x, b, mu=1.0).value,
            a,
        ),
        "mesh_potential_derivatives(...).hessian": (
            lambda x: mesh_potential_derivatives(_ico(), x, _box(), pb, mu=1.0).hessian,
            pa,
        ),
        "contact_potential(...).grad": (
            lambda p: contact_potential([_ico(), _box()], p, mu=1.0, grad=True).grad,
            torch.stack([pa, pb]),
        ),
    }
    for what, (f, x) in cases.items():
        xg = x.clone().requires_grad_(True)
        y = f(xg)
        assert y.requires_grad and float(y.detach().abs().max()) > 0
        torch.testing.assert_close(y.detach(), f(x), rtol=0, atol=0)  # the same values
        with pytest.raises(RuntimeError, match=re.escape(what) + " carries no gradient"):
            torch.autograd.grad(y.sum(), xg)
        with pytest.raises(RuntimeError, match="carries no gradient"):
            torch.func.grad(lambda x_, f=f: f(x_).sum())(x)
        assert not f(x).requires_grad and not f(xg.detach()).requires_grad
    # contact_potential's value stays differentiable next to its refusing grad field
    poses = torch.stack([pa, pb]).requires_grad_(True)
    c = contact_potential([_ico(), _box()], poses, mu=1.0, grad=True)
    (g,) = torch.autograd.grad(c.value, poses)
    assert float(g.abs().max()) > 0


def test_plain_torch_functions_run_under_vmap_and_check_values_there():
    from cfd_torch import blend_weight, central_potential, recentre_rotation

    r = torch.tensor([[0.5, 2.0], [1e3, 0.1]], dtype=F64)
    torch.testing.assert_close(torch.func.vmap(central_potential)(r), central_potential(r))
    torch.testing.assert_close(
        torch.func.vmap(lambda x: blend_weight(x, 0.6, 0.5))(r), blend_weight(r, 0.6, 0.5)
    )
    q = torch.tensor([[[0.0, 0, 0, 4.0, 0, 0]], [[1.0, 2, 3, 0.1, -5.0, 0.2]]], dtype=F64)
    torch.testing.assert_close(torch.func.vmap(recentre_rotation)(q), recentre_rotation(q))
    assert float(recentre_rotation(q)[0, 0, 3]) == pytest.approx(4.0 - 2 * torch.pi)
    with pytest.raises(ValueError, match="r must be >= 0"):
        torch.func.vmap(central_potential)(-r)
    with pytest.raises(ValueError, match="q contains NaN or inf"):
        torch.func.vmap(recentre_rotation)(q.clone().index_fill_(0, torch.tensor([1]), float("nan")))
    with pytest.raises(ValueError, match="d1 is torch.float64 on cpu but r is torch.float32"):
        blend_weight(r.float(), torch.tensor(0.6, dtype=F64), 0.5)


def test_rotation_matrix_carries_forward_mode_tangents_and_runs_under_vmap():
    """The (N, 3) float64 CPU input took the numba kernel whenever it did not require grad, dropping a forward-mode
    tangent (a zero derivative, unannounced) and failing under jacfwd and vmap (no storage)."""
    from cfd_torch.rotation import rotation_derivatives, rotation_matrix

    w = torch.tensor([[0.3, -0.2, 0.9], [1e-3, 2.0, -0.5]], dtype=F64)
    t = torch.tensor([[1.0, 0.5, -0.25], [0.2, -1.0, 0.7]], dtype=F64)
    J = torch.autograd.functional.jacobian(rotation_matrix, w)  # (2, 3, 3, 2, 3)
    ref = torch.einsum("aijbk,bk->aij", J, t)
    assert float(ref.abs().max()) > 0.1
    with torch.autograd.forward_ad.dual_level():
        tan = torch.autograd.forward_ad.unpack_dual(
            rotation_matrix(torch.autograd.forward_ad.make_dual(w, t))
        ).tangent
    assert tan is not None
    torch.testing.assert_close(tan, ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(torch.func.jacfwd(rotation_matrix)(w), J, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(torch.func.vmap(rotation_matrix)(w[:, None])[:, 0], rotation_matrix(w))
    dR = torch.func.vmap(lambda x: rotation_derivatives(x, 1)[1])(w[:, None])[:, 0]
    torch.testing.assert_close(dR, rotation_derivatives(w, 1)[1])


def test_float32_batched_gradients_are_refused_by_name():
    """A float32 input's gradient is cast back from the float64 solve with an overflow check, which cannot read
    autograd's batched gradients (jacobian/hessian(vectorize=True), is_grads_batched): a clear refusal instead of
    torch's internal "Batching rule not implemented for aten::detach"; float64 and vectorize=False work."""
    a, b = _pairs()
    x = a[:2].float()
    f = functools.partial(lambda y, b: pair_potential(y, b, mu=1.0), b=b[:2].float())
    with pytest.raises(
        NotImplementedError, match=r"pair_potential's gradient in torch.float32: autograd's batched"
    ):
        torch.autograd.functional.jacobian(f, x, vectorize=True)
    y = x.clone().requires_grad_(True)
    v = f(y)
    with pytest.raises(NotImplementedError, match="pass tri_a and tri_b as float64, or use vectorize=False"):
        torch.autograd.grad(v, y, torch.eye(2), is_grads_batched=True)
    J = torch.autograd.functional.jacobian(f, x)
    J64 = torch.autograd.functional.jacobian(
        lambda y: pair_potential(y, b[:2], mu=1.0), a[:2], vectorize=True
    )
    assert float(J64.abs().max()) > 0
    torch.testing.assert_close(J.double(), J64, rtol=1e-5, atol=1e-5 * float(J64.abs().max()))
    pa, pb = _near_poses()
    with pytest.raises(NotImplementedError, match="mesh_potential's gradient in torch.float32"):
        torch.autograd.functional.jacobian(
            lambda p: mesh_potential(_ico(), p, _box(), pb.float(), mu=1.0), pa.float(), vectorize=True
        )


def test_compile_traces_around_the_numba_input_checks_on_a_cold_first_call(tmp_path):
    """torch.compile of a function calling pair_potential, first call in a fresh process: dynamo failed on numba's
    first-call compilation inside the triangle check ("exception table entry start instruction has no offset")."""
    code = (
        "import torch, cfd_torch\n"
        "a = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)\n"
        "b = a + torch.tensor([0.0, 0, 0.5], dtype=torch.float64)\n"
        "f = torch.compile(lambda x, y: cfd_torch.pair_potential(x, y, mu=1.0) * 2.0, backend='eager')\n"
        "v = f(a, b)\n"
        "assert torch.equal(v, 2.0 * cfd_torch.pair_potential(a, b, mu=1.0)), v\n"
        "print('ok', float(v))\n"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.startswith("ok ")


def test_importing_the_library_does_not_import_dynamo():
    """``import cfd_torch`` (and its environments) leaves torch.compile's dynamo unimported: the decorator that keeps
    the triangle check out of compiled graphs imported it at once, 1.3-1.4 s of every script's and worker's start."""
    code = (
        "import sys, torch\n"
        "alone = 'torch._dynamo' in sys.modules\n"
        "import cfd_torch, cfd_torch.envs\n"
        "print(alone, 'torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    alone, with_library = out.stdout.split()
    if alone == "True":
        pytest.skip("this torch imports dynamo itself")
    assert with_library == "False"
