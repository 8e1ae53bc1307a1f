"""The peers' locally supported contact potentials between two triangles, as baselines.

Both vanish identically, with their gradients, beyond their activation distance ``dhat``; that is the failure the
long-range potential of this library fixes (SPEC sections 1-2).

- IPC (Li et al. 2020; ipc-toolkit ``BarrierPotential``): the scalar barrier on the squared distance,
  ``kappa * b(d^2; dhat^2)``, ``b(x; xh) = -(x - xh)^2 ln(x / xh)`` for 0 < x < xh, 0 beyond, +inf at x <= 0.
- SDRS-style local plane barrier: the separating-plane construction of the exact potential with every term replaced
  by ``B(y) = -(y - dhat)^2 ln(y / dhat) / y`` (0 for y >= dhat), normal weight 1::

      P_sdrs = kappa * min_p [ B(1 - |n|) + sum_k B(sg_k (n.x_k + d) - delta/2) ]

  Once some plane leaves every vertex more than dhat + delta/2 away (and |n| <= 1 - dhat) the minimum is exactly 0:
  for two parallel faces, beyond a gap of (2 dhat + delta) / (1 - dhat), about 2.1 dhat.

Both pair functions are differentiable once, in reverse mode (a second derivative raises: autograd through them
would hold the closest points or the plane fixed, which is exact to first order only; forward mode raises, and
``torch.func.vmap`` of their gradients and of ``sdrs_pair_potential``); the simulator's contact models
(``contact/ipc.py``, ``contact/sdrs.py``) have the exact Hessians. ``ipc_pair_barrier`` is the barrier of the
pair's distance, ``b(d^2)`` of the closest points: ipc-toolkit sums the barrier over the pair's 6 point-triangle
and 9 edge-edge distances (and mollifies nearly parallel edges), which ``IpcContact`` does; the two agree where one
feature pair is within ``dhat`` and differ by up to several times where more are (parallel faces, edges on faces).
"""

from __future__ import annotations

import torch

from ._autograd import forward_mode_error, has_tangent, refuse_derivative, refuse_vmap, vmap_error
from ._geometry import segment_hits_triangle, triangle_closest_points
from ._validate import check_count, check_positive, check_triangles
from .config import DEFAULT_CONTACT

__all__ = [
    "ipc_barrier",
    "ipc_pair_barrier",
    "sdrs_barrier",
    "sdrs_energy",
    "sdrs_pair_potential",
    "sdrs_planes",
]


# the sides of a triangle pair's separating plane its six vertices lie on (three of a, then three of b)
_SIDES = torch.tensor([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])


def ipc_barrier(x: torch.Tensor, xhat: float) -> torch.Tensor:
    """IPC scalar barrier ``-(x - xhat)^2 ln(x / xhat)`` on (0, xhat), 0 beyond, +inf at x <= 0 (C2 at xhat);
    NaN stays NaN."""
    check_positive(xhat, "xhat")
    inside = (x > 0) & (x < xhat)
    xs = torch.where(inside, x, torch.full_like(x, xhat))
    b = -((xs - xhat) ** 2) * torch.log(xs / xhat)
    b = torch.where(inside, b, torch.zeros_like(x))  # +0.0 beyond xhat (b is -0.0 there)
    return torch.where(x <= 0, torch.full_like(x, float("inf")), torch.where(torch.isnan(x), x, b))


def sdrs_barrier(y: torch.Tensor, dhat: float) -> torch.Tensor:
    """SDRS barrier ``-(y - dhat)^2 ln(y / dhat) / y`` on (0, dhat), 0 beyond, +inf at y <= 0 (C2 at dhat); NaN
    stays NaN."""
    check_positive(dhat, "dhat")
    inside = (y > 0) & (y < dhat)
    ys = torch.where(inside, y, torch.full_like(y, dhat))
    b = -((ys - dhat) ** 2) * torch.log(ys / dhat) / ys
    b = torch.where(inside, b, torch.zeros_like(y))  # +0.0 beyond dhat (b is -0.0 there)
    return torch.where(y <= 0, torch.full_like(y, float("inf")), torch.where(torch.isnan(y), y, b))


def _first_order(tri_a: torch.Tensor, tri_b: torch.Tensor, f, name: str) -> torch.Tensor:
    """``f(tri_a, tri_b)`` (K,), differentiable once (:class:`_FirstOrder`) where a gradient is wanted; forward mode
    (a tangent on either input, which ``torch.no_grad`` does not stop) is refused there."""
    wanted = torch.is_grad_enabled() and (tri_a.requires_grad or tri_b.requires_grad)
    if wanted or has_tangent(tri_a) or has_tangent(tri_b):
        return _FirstOrder.apply(tri_a, tri_b, f, name)[0]
    with torch.no_grad():
        return f(tri_a, tri_b)


class _FirstOrder(torch.autograd.Function):
    """(``f(tri_a, tri_b)`` (K,), its gradients): the backward is autograd's gradient of ``f`` (exact), and its own
    derivative in the triangles raises (autograd's second derivative of ``f`` is not the exact one). New style:
    the forward runs on plain tensors, so torch.func.grad works too; forward mode and vmap raise (forward over
    forward through ``f`` would hold the closest points or the plane fixed, as autograd's second derivative)."""

    @staticmethod
    def forward(tri_a, tri_b, f, name):
        with torch.enable_grad():
            a, b = tri_a.detach().requires_grad_(True), tri_b.detach().requires_grad_(True)
            value = f(a, b)
            ga, gb = torch.autograd.grad(value.sum(), (a, b), allow_unused=True, materialize_grads=True)
        return value.detach(), ga, gb

    @staticmethod
    def setup_context(ctx, inputs, output):
        tri_a, tri_b, _, ctx.name = inputs
        _, ga, gb = output
        ctx.mark_non_differentiable(ga, gb)
        ctx.save_for_backward(tri_a, tri_b, ga, gb)

    @staticmethod
    def backward(ctx, gout, _ga, _gb):
        tri_a, tri_b, ga, gb = ctx.saved_tensors
        w = gout[:, None, None]
        da, db = w * ga, w * gb
        if torch.is_grad_enabled():  # create_graph: linear in gout, its derivative in the triangles refused
            message = (
                f"{ctx.name}: second derivatives are not implemented (autograd through it holds the closest "
                "points or the plane fixed, exact to first order only); the simulator's contact model has the "
                "exact Hessian"
            )
            da, db = refuse_derivative(da, tri_a, message), refuse_derivative(db, tri_b, message)
        return da, db, None, None

    @staticmethod
    def jvp(ctx, *_):
        raise forward_mode_error(ctx.name, "first order")

    @staticmethod
    def vmap(info, in_dims, tri_a, tri_b, f, name):
        raise vmap_error(name)


def _check_pair(tri_a: torch.Tensor, tri_b: torch.Tensor, dhat: float, kappa: float) -> None:
    check_triangles(tri_a, "tri_a")
    check_triangles(tri_b, "tri_b")
    if tri_a.dim() != 3 or tri_a.shape != tri_b.shape:
        raise ValueError(
            f"tri_a and tri_b must both be (K, 3, 3), got {tuple(tri_a.shape)} and {tuple(tri_b.shape)}"
        )
    if tri_a.dtype != tri_b.dtype or tri_a.device != tri_b.device:
        raise ValueError(
            f"tri_a and tri_b must share dtype and device, got {tri_a.dtype} on {tri_a.device} and "
            f"{tri_b.dtype} on {tri_b.device}"
        )
    check_positive(dhat, "dhat")
    check_positive(kappa, "kappa")


def _intersecting(tri_a: torch.Tensor, tri_b: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """(K,) bool: the triangles intersect or touch (an edge of one crosses the other, or their distance is within
    rounding of 0: coplanar overlaps too)."""
    edges = torch.cat([tri_a, tri_b], 1)  # (K, 6, 3): the 3 edges of a, then of b, as (start, end)
    ends = torch.cat([tri_a.roll(-1, 1), tri_b.roll(-1, 1)], 1)
    other = torch.stack([tri_b] * 3 + [tri_a] * 3, 1)  # (K, 6, 3, 3): the triangle each edge may cross
    hit = segment_hits_triangle(edges, ends, other).any(1)
    size = torch.cat([tri_a, tri_b], 1).abs().amax((1, 2))  # the coordinates' rounding scale
    return hit | (dist <= 64 * torch.finfo(dist.dtype).eps * size)


def ipc_pair_barrier(
    tri_a: torch.Tensor, tri_b: torch.Tensor, *, dhat: float = 1e-2, kappa: float = 1.0
) -> torch.Tensor:
    """IPC barrier on the triangle-triangle distance, ``kappa b(d^2; dhat^2)`` (module docstring: the closest
    points' distance, not ipc-toolkit's sum over the pair's features); differentiable once, in reverse mode.

    Args:
        tri_a, tri_b: (K, 3, 3) triangles [m], same dtype and device.
        dhat: activation distance [m]; value and gradient are exactly 0 for d >= dhat.
        kappa: stiffness, > 0.

    Returns:
        (K,) barrier values, +inf for intersecting or touching triangles.
    """
    _check_pair(tri_a, tri_b, dhat, kappa)
    with torch.no_grad():
        dist, qa, qb = triangle_closest_points(tri_a.detach(), tri_b.detach())
        hit = _intersecting(tri_a.detach(), tri_b.detach(), dist)

    def barrier(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        # the distance as a function of the vertices: the closest points by their barycentric coordinates (held
        # fixed: first-order exact, since the distance is stationary in them)
        pa = torch.einsum("kv,kvc->kc", _barycentric(a.detach(), qa), a)
        pb = torch.einsum("kv,kvc->kc", _barycentric(b.detach(), qb), b)
        value = kappa * ipc_barrier(((pa - pb) ** 2).sum(-1), dhat * dhat)
        return torch.where(hit, torch.full_like(value, float("inf")), value)

    return _first_order(tri_a, tri_b, barrier, "ipc_pair_barrier")


def _barycentric(tri: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(K, 3) barycentric coordinates of points q (K, 3) in the planes of triangles tri (K, 3, 3)."""
    e1, e2, w = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], q - tri[:, 0]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    dw1, dw2 = (w * e1).sum(-1), (w * e2).sum(-1)
    den = d11 * d22 - d12 * d12
    v = (d22 * dw1 - d12 * dw2) / den
    t = (d11 * dw2 - d12 * dw1) / den
    return torch.stack([1 - v - t, v, t], -1)


def sdrs_energy(p: torch.Tensor, X: torch.Tensor, dhat: float, margin: float) -> torch.Tensor:
    """(K,) the SDRS energy (kappa 1) of triangle pairs X (K, 6, 3) for planes p (K, 4)."""
    sg = _SIDES.to(X)
    s = sg * (torch.einsum("kvc,kc->kv", X, p[:, :3]) + p[:, 3:]) - margin / 2
    r = torch.linalg.vector_norm(p[:, :3], dim=-1)
    return sdrs_barrier(1.0 - r, dhat) + sdrs_barrier(s, dhat).sum(-1)


def sdrs_pair_potential(
    tri_a: torch.Tensor,
    tri_b: torch.Tensor,
    *,
    dhat: float = 1e-2,
    margin: float = DEFAULT_CONTACT.margin,
    kappa: float = 1.0,
    iters: int = 60,
) -> torch.Tensor:
    """SDRS-style local plane barrier, minimised over the plane by damped Newton (closed-form derivatives).

    The value's gradient with respect to the vertices follows from the envelope theorem: the plane is detached
    at the optimum and the energy re-evaluated, so autograd gives ``kappa sum_k B'(s_k) sg_k n``.

    Args:
        tri_a, tri_b: (K, 3, 3) triangles [m], same dtype and device, separated by more than ``margin``.
        dhat: support of the barrier [m], in (0, 1); the value and gradient are exactly zero once a plane leaves
            every vertex dhat + margin / 2 away at |n| <= 1 - dhat (module docstring: two parallel faces beyond a
            gap of about 2.1 dhat).
        margin: delta, as in the exact potential, > 0.
        kappa: stiffness, > 0.
        iters: Newton iterations, >= 1 (the demo's configurations converge in far fewer).

    Returns:
        (K,) values; differentiable once in the vertices (reverse mode; forward mode and ``torch.func.vmap``
        raise).
    """
    refuse_vmap("sdrs_pair_potential", tri_a, tri_b)  # (its plane search loops on the values)
    _check_pair(tri_a, tri_b, dhat, kappa)
    if not dhat < 1:
        raise ValueError(f"dhat must be below 1 (|n| <= 1 - dhat), got {dhat!r}")
    check_positive(margin, "margin")
    check_count(iters, "iters")
    p = sdrs_planes(torch.cat([tri_a, tri_b], 1).detach().to(torch.float64), dhat, margin, iters)

    def potential(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return kappa * sdrs_energy(p, torch.cat([a, b], 1).to(torch.float64), dhat, margin).to(a.dtype)

    return _first_order(tri_a, tri_b, potential, "sdrs_pair_potential")


def sdrs_planes(Xd: torch.Tensor, dhat: float, margin: float, iters: int = 60) -> torch.Tensor:
    """(K, 4) the planes (n, d) minimising the SDRS energy of triangle pairs Xd (K, 6, 3) (float64, vertices of a
    then b), by damped Newton from this library's feasible start, enlarged toward |n| = 1 - dhat so that far
    pairs start where the energy is exactly zero. Raises ValueError if a pair is within the margin."""
    from .contact._pair_torch import start_planes

    p, dist = start_planes(Xd, margin)
    if bool((dist <= margin).any()):
        raise ValueError("sdrs_pair_potential: some triangle pairs are within the margin")
    # The start has |n| < 1 and all gaps > 0; enlarge |n| toward 1 - dhat (just inside, against rounding), where
    # B(1 - |n|) = 0, so that far pairs start in the zero region.
    reach = (1.0 - dhat) * (1.0 - 1e-12)
    p = p * (reach / torch.linalg.vector_norm(p[:, :3], dim=-1)).clamp(min=1.0)[:, None]
    p = torch.where(torch.isfinite(sdrs_energy(p, Xd, dhat, margin))[:, None], p, start_planes(Xd, margin)[0])

    done = torch.zeros(
        p.shape[0], dtype=torch.bool, device=p.device
    )  # each pair stops at its own convergence
    for _ in range(iters):
        e = sdrs_energy(p, Xd, dhat, margin)
        done = done | (e == 0)
        if bool(done.all()):
            break
        g, H = _sdrs_plane_derivatives(p, Xd, dhat, margin)
        H = (
            H
            + 1e-12
            * torch.eye(4, dtype=Xd.dtype, device=Xd.device)
            * H.diagonal(dim1=-2, dim2=-1).abs().amax(-1)[:, None, None]
        )
        step = torch.linalg.solve(
            H + 1e-30 * torch.eye(4, dtype=Xd.dtype, device=Xd.device), -g[..., None]
        ).squeeze(-1)
        a = torch.ones_like(e)
        for _ls in range(40):
            e_new = sdrs_energy(p + a[:, None] * step, Xd, dhat, margin)
            bad = ~(e_new <= e)
            if not bool(bad.any()):
                break
            a = torch.where(bad, 0.5 * a, a)
        ok = (e_new <= e) & ~done
        p = torch.where(ok[:, None], p + a[:, None] * step, p)
        # converged: Newton steps at rounding level, or the energy falls no more (the value and its vertex gradient
        # are stationary in the plane, so a plane off by 1e-10 changes them at that order); a converged pair's
        # plane is kept, so that its result does not depend on the other pairs of the batch
        small = step.abs().amax(-1) <= 1e-10 * (1.0 + p.abs().amax(-1))
        done = done | small | ~ok | (e - e_new <= 1e-15 * e.abs())
        if bool(done.all()):
            break
    return p


def _sdrs_barrier_derivatives(y: torch.Tensor, dhat: float) -> tuple[torch.Tensor, torch.Tensor]:
    """B'(y) and B''(y) of :func:`sdrs_barrier` on (0, dhat), 0 elsewhere (also at y <= 0, where B is +inf)."""
    inside = (y > 0) & (y < dhat)
    ys = torch.where(inside, y, torch.full_like(y, dhat))
    u, L = ys - dhat, torch.log(ys / dhat)
    # B = -u^2 L / y
    d1 = -(2 * u * L / ys + u * u / ys**2 - u * u * L / ys**2)
    d2 = -(2 * L / ys + 4 * u / ys**2 - 4 * u * L / ys**2 - 3 * u * u / ys**3 + 2 * u * u * L / ys**3)
    zero = torch.zeros((), dtype=y.dtype, device=y.device)
    return torch.where(inside, d1, zero), torch.where(inside, d2, zero)


def _sdrs_plane_rows(X: torch.Tensor) -> torch.Tensor:
    """(K, 6, 4) a_k = sg_k [x_k, 1] of triangle pairs X (K, 6, 3): vertex k's gap to plane p is a_k . p."""
    return _SIDES.to(X)[:, None] * torch.cat([X, torch.ones_like(X[..., :1])], -1)


def _sdrs_plane_derivatives(
    p: torch.Tensor, X: torch.Tensor, dhat: float, margin: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(K, 4) gradient and (K, 4, 4) Hessian in the plane p (K, 4) of :func:`sdrs_energy` of triangle pairs X
    (K, 6, 3): sum_k B(a_k . p - delta/2) + B(1 - |n|), a_k = sg_k [x_k, 1]."""
    A = _sdrs_plane_rows(X)
    b1, b2 = _sdrs_barrier_derivatives((A * p[:, None]).sum(-1) - margin / 2, dhat)
    r = torch.linalg.vector_norm(p[:, :3], dim=-1)
    c1, c2 = _sdrs_barrier_derivatives(1.0 - r, dhat)
    u = p[:, :3] / r[:, None]
    g = (b1[..., None] * A).sum(1)
    g[:, :3] -= c1[:, None] * u
    H = torch.einsum("kv,kvi,kvj->kij", b2, A, A)
    uu = u[:, :, None] * u[:, None, :]
    eye = torch.eye(3, dtype=X.dtype, device=X.device)
    H[:, :3, :3] += c2[:, None, None] * uu - (c1 / r)[:, None, None] * (eye - uu)
    return g, H
