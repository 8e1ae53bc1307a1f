"""The custom autograd Functions: float64 gradcheck of each, gradgradcheck or an asserted refusal of the next
order, and the torch.func transforms (grad and jacrev work; vmap and forward mode raise saying so).

Small inputs throughout: the whole file runs in a few seconds.
"""

from __future__ import annotations

import functools

import pytest
import torch
import trimesh

from cfd_torch import contact_potential, mesh_potential, pair_potential
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
    cases = {
        "pair_potential": (lambda x: pair_potential(x, b, mu=1.0).sum(), a),
        "mesh_potential": (lambda x: mesh_potential(_ico(), x, _box(), pb, mu=1.0), pa),
        "contact_potential": (
            lambda p: contact_potential([_ico(), _box()], p, mu=1.0).value,
            torch.stack([pa, pb]),
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
