"""Exact triangle-pair separating-plane potential (SPEC section 2) with implicit first and second derivatives.

For triangles ta (vertices a_k) and tb (vertices b_k), with p = (n, d) in R^4 (n not unit)::

    P(ta, tb) = mu * min_p E(p),
    E(p) = lam / (1 - |n|)_+ + sum_k 1 / (n.a_k + d - delta/2)_+ + sum_k 1 / (-n.b_k - d - delta/2)_+

with ``1/(y)_+ = +inf`` for y <= 0, so P = +inf when the triangles are within ``delta`` (the margin) or intersect.
E is strictly convex on its feasible set, so the optimal plane p* is unique and smooth in the vertices. With the six
gaps s_k = sg_k (n.x_k + d) - delta/2 (sg = +1 on ta, -1 on tb) at p*:

    grad_x P  = mu dE/dx = -mu sg_k n / s_k^2                       (envelope theorem)
    hess_x P  = mu (E_xx - E_xp E_pp^-1 E_px)                       (implicit function theorem)

The inner minimisation is a damped Newton solve (float64) from a strictly feasible start built from the exact closest
points; it is never differentiated through. Far apart, P -> 12 mu, but its gradient decays only like r^-3/2 and
never vanishes.
"""

from __future__ import annotations

import mmap
import sys
import threading
from typing import NamedTuple

import torch

from .._autograd import (
    VALUES_ONLY,
    forward_mode_error,
    outside_transforms,
    plain,
    refuse_third_order,
    refuse_vmap,
    values_only,
    vmap_error,
)
from .._geometry import frame_origin
from .._threads import parallel_kernels, start_numba_pool
from .._validate import (
    check_alike,
    check_bool,
    check_count,
    check_positive,
    check_stiffness,
    check_tolerance,
    check_triangles,
    narrowed,
    widened,
)
from ..config import DEFAULT_CONTACT
from . import _pair_torch

__all__ = ["pair_potential", "pair_potential_derivatives", "PairDerivatives", "PairSolveError", "LAMBDA"]

LAMBDA = 12.0  # weight of the normal regulariser lam / (1 - |n|)
_HUGEPAGE_MIN_BYTES = 1 << 25


class PairSolveError(RuntimeError):
    """Raised when the inner Newton solve does not converge for some feasible pair."""


class PairDerivatives(NamedTuple):
    """Value and closed-form derivatives of the pair potential.

    Attributes:
        value: (...) P, +inf where the triangles are within the margin or intersect.
        grad: (..., 18) dP / d[a0, a1, a2, b0, b1, b2] (flattened xyz); zero where value is +inf.
        hessian: (..., 18, 18) second derivative, symmetric; zero where value is +inf; None if not requested.
        plane: (..., 4) optimal (n, d) with n.a + d > delta/2 on ta and < -delta/2 on tb; zero where value is +inf.
    """

    value: torch.Tensor
    grad: torch.Tensor
    hessian: torch.Tensor | None
    plane: torch.Tensor


_HESS_POOL: list[mmap.mmap] = []  # recycled huge-page buffers of large outputs (at most _POOL_SIZE)
_POOL_SIZE = 2
_POOL_LOCK = threading.Lock()


def _refs_when_free() -> int:
    """What ``sys.getrefcount`` reports for a pool buffer that no tensor holds, seen as :func:`_empty_cpu`'s loop
    sees it (the pool list, the loop variable, getrefcount's argument: 3 up to Python 3.13). Measured, not assumed:
    an interpreter that borrows references (3.14's) reports fewer, and a fixed 3 would then take a buffer a tensor
    still holds for free."""
    pool = [mmap.mmap(-1, mmap.PAGESIZE)]
    n = 0
    for buf in pool:
        n = sys.getrefcount(buf)
    pool[0].close()
    return n


_FREE_REFS = _refs_when_free()


def _empty_cpu(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """Uninitialised CPU tensor; large ones are backed by recycled transparent-huge-page buffers.

    A fresh (K, 18, 18) float64 Hessian at K = 1e5 is 260 MB; having the kernel fault in and zero that much
    memory costs as much as the arithmetic that fills it. Large outputs therefore live in anonymous mappings
    advised MADV_HUGEPAGE, and up to two such buffers are kept and reused once no tensor refers to them any more
    (the pool holds the two most recently allocated large buffers).
    """
    numel = 1
    for d in shape:
        numel *= d
    nbytes = numel * torch.empty((), dtype=dtype).element_size()
    advice = getattr(mmap, "MADV_HUGEPAGE", None)
    if nbytes < _HUGEPAGE_MIN_BYTES or advice is None:
        return torch.empty(shape, dtype=dtype)
    with _POOL_LOCK:  # (two threads must not both take one free buffer between its check and its tensor)
        for buf in _HESS_POOL:
            # more references than the pool's own (_FREE_REFS) means a tensor holds it
            if nbytes <= len(buf) <= 2 * nbytes and sys.getrefcount(buf) == _FREE_REFS:
                return torch.frombuffer(buf, dtype=dtype, count=numel).view(shape)
        buf = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        try:
            buf.madvise(advice)
        except OSError:
            pass
        _HESS_POOL.append(buf)
        if len(_HESS_POOL) > _POOL_SIZE:
            _HESS_POOL.pop(0)
        return torch.frombuffer(buf, dtype=dtype, count=numel).view(shape)  # the tensor keeps buf alive


def _use_numba(X: torch.Tensor, backend: str) -> bool:
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    if backend == "numba" and X.device.type != "cpu":
        raise ValueError(f"backend='numba' needs CPU tensors, got device {X.device}")
    return backend == "numba" or (backend == "auto" and X.device.type == "cpu")


def _raise_unconverged(status: torch.Tensor, resid: torch.Tensor, max_iter: int, tol: float) -> None:
    bad = status == _pair_torch.NOT_CONVERGED
    if bool(bad.any()):
        worst = float(resid[bad].max())
        idx = int(torch.nonzero(bad)[0])
        feasible = int((status != _pair_torch.INFEASIBLE).sum())
        raise PairSolveError(
            f"pair potential: the plane solve did not converge for {int(bad.sum())} of {feasible} feasible "
            f"pairs (worst relative gradient {worst:.3e} > tol {tol:.1e} after max_iter={max_iter}; first at "
            f"flattened pair index {idx}; a Scene's are pair_tol and pair_max_iter)"
        )


class _Solved(NamedTuple):
    """The solve of K pairs: value (K,), optimal planes (K, 4) in the frame centred at ``centre`` (K, 3) (near the
    pair, see ``_geometry.frame_origin``), the contact frames' origins ``offset`` (K, 3) relative to ``centre``
    (where each pair was solved, see ``_pair_numba._contact_frame``) and the planes there, ``local_plane`` (K, 4)
    (as solved; ``plane`` is rounded from them), grad (K, 18) | None, hess (K, 18, 18) | None (or its low-rank
    factors)."""

    value: torch.Tensor
    plane: torch.Tensor
    centre: torch.Tensor
    offset: torch.Tensor
    local_plane: torch.Tensor
    grad: torch.Tensor | None
    hess: object

    def world_plane(self) -> torch.Tensor:
        """The planes in the input's frame: d - n.c (rounded there, like any plane of a pair far from the origin)."""
        return to_world(self.plane, self.centre)


def to_world(plane: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """Planes (K, 4) given in frames centred at ``centre`` (K, 3), in the frame of the origin."""
    d = plane[:, 3] - (plane[:, :3] * centre).sum(-1)
    return torch.cat([plane[:, :3], d[:, None]], -1)


def _solve(
    X, *, mu, margin, tol, max_iter, want_grad, want_hess, backend, lowrank=False, start=None, serial=False
) -> _Solved:
    """Solve (K, 6, 3) float64 pairs, each in a frame centred near it (``_geometry.frame_origin``; translation-
    invariant: far from the origin, a gap n.x + d computed in the input's frame would cancel its digits away).

    ``lowrank`` (numba backend only): hess is returned as its factors (W^T (K, 4, 18), gaps (K, 6)), see
    ``_pair_numba.solve_pairs``. ``start`` (numba backend only): (P0 (K, 4), has0 (K,) bool) warm-start planes in
    the input's frame, used where set and strictly feasible. ``serial`` (numba backend): solve on the calling
    thread (a pool thread with a share of the work) instead of numba's threads."""
    K = X.shape[0]
    X = X.detach()
    if lowrank and not _use_numba(X, backend):
        raise ValueError("lowrank Hessian factors need the numba backend (CPU float64)")
    if _use_numba(X, backend):
        from ._pair_numba import PARALLEL_MIN_PAIRS, solve_pairs, solve_pairs_serial

        if serial or K < PARALLEL_MIN_PAIRS or not parallel_kernels():
            solve_pairs = solve_pairs_serial  # noqa: F811
        else:
            start_numba_pool()

        Xc = X.contiguous()
        C = torch.empty(K, 3, dtype=X.dtype)  # frame origins, computed by the kernel
        P = torch.empty(K, 4, dtype=X.dtype)
        val = torch.empty(K, dtype=X.dtype)
        status = torch.empty(K, dtype=torch.int8)
        resid = torch.empty(K, dtype=X.dtype)
        grad = torch.empty(K if want_grad else 0, 18, dtype=X.dtype)
        lowrank = bool(lowrank and want_hess)
        hess = _empty_cpu((K, 18, 18) if want_hess and not lowrank else (0, 18, 18), X.dtype)
        WT = torch.empty((K, 4, 18) if lowrank else (0, 4, 18), dtype=X.dtype)
        gaps = torch.empty((K, 6) if lowrank else (0, 6), dtype=X.dtype)
        O = torch.zeros(K, 3, dtype=X.dtype)  # contact-frame origins relative to C, written by the kernel
        if start is None:
            P0, has0 = torch.empty(0, 4, dtype=X.dtype), torch.empty(0, dtype=torch.int8)
        else:
            P0 = start[0].to(X.dtype).contiguous()
            has0 = start[1].to(torch.int8).contiguous()
        if K:
            solve_pairs(
                Xc.numpy(), C.numpy(), float(mu), float(margin), LAMBDA, float(tol), int(max_iter), bool(want_grad),
                bool(want_hess), P.numpy(), val.numpy(), grad.numpy(), hess.numpy(), status.numpy(), resid.numpy(),
                lowrank, WT.numpy(), gaps.numpy(), P0.numpy(), has0.numpy(), O.numpy(),
            )  # fmt: skip
        _raise_unconverged(status, resid, max_iter, tol)
        if lowrank:
            hess = (WT, gaps)
        finite = torch.isfinite(val)
        if not bool(finite.all()):
            O = torch.where(finite[:, None], O, torch.zeros_like(O))
        return _Solved(
            val, to_world(P, O), C, O, P, (grad if want_grad else None), (hess if want_hess else None)
        )
    if start is not None:
        raise ValueError("warm-start planes need the numba backend (CPU float64)")
    C = frame_origin(X)
    Xc = X - C[:, None, :]
    P, E, status, resid, O, Xc = _pair_torch.solve_pairs_torch(Xc, margin, LAMBDA, tol, max_iter)
    _raise_unconverged(status, resid, max_iter, tol)
    feasible = status == _pair_torch.CONVERGED
    P = torch.where(feasible[:, None], P, torch.zeros_like(P))
    O = torch.where(feasible[:, None], O, torch.zeros_like(O))
    grad = hess = None
    zero = torch.zeros((), dtype=X.dtype, device=X.device)
    if want_grad or want_hess:
        Xs, Ps = _safe_rows(Xc, P, feasible)
        if want_grad:
            Ex = _pair_torch.pair_vertex_grad(Xs, Ps, 0.5 * margin)
            grad = torch.where(feasible[:, None], mu * Ex.reshape(-1, 18), zero)
        if want_hess:
            hess = _pair_torch.pair_hessian_torch(Xs, Ps, mu, 0.5 * margin, LAMBDA)
            hess = torch.where(feasible[:, None, None], hess, zero)
    return _Solved(mu * E, to_world(P, O), C, O, P, grad, hess)


def _safe_rows(X: torch.Tensor, P: torch.Tensor, feasible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Swap infeasible rows (value +inf, results masked to zero) for a well-posed pair so that the derivative
    formulas stay finite and the batched Cholesky factorisations succeed: ta at z = +1, tb at z = -1, n = e_z/2."""
    tri = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=X.dtype, device=X.device)
    dummy_x = torch.cat([tri + tri.new_tensor([0.0, 0.0, 1.0]), tri - tri.new_tensor([0.0, 0.0, 1.0])])
    dummy_p = tri.new_tensor([0.0, 0.0, 0.5, 0.0])
    Xs = torch.where(feasible[:, None, None], X, dummy_x)
    Ps = torch.where(feasible[:, None], P, dummy_p)
    return Xs, Ps


def _local(X: torch.Tensor, C: torch.Tensor, O: torch.Tensor) -> torch.Tensor:
    """X (K, 6, 3) in the frames at C (K, 3) (exact), then at C + O (K, 3), the contact frames (rounded as in the
    solve, which formed the same differences)."""
    return (X - C[:, None, :]) - O[:, None, :]


def _hessian_vector(v, X, P, C, O, feasible, mu, margin) -> torch.Tensor:
    """(K, 6, 3) v^T hess_x P at the optimal planes (no graph)."""
    with torch.no_grad():
        Xs, Ps = _safe_rows(_local(X, C, O), P, feasible)
        hv = _pair_torch.pair_hessian_vjp(Xs, Ps, v.reshape(-1, 18), mu, 0.5 * margin, LAMBDA)
        hv = torch.where(feasible[:, None], hv, torch.zeros((), dtype=X.dtype, device=X.device))
    return hv.reshape(-1, 6, 3)


class _PairHessianVectorFn(torch.autograd.Function):
    """v -> v^T hess_x P at fixed X: linear in v with a symmetric matrix, so its backward is itself (the derivative
    in X, a third derivative, is the caller's to refuse). What makes ``torch.autograd.functional.hvp`` work."""

    generate_vmap_rule = True

    @staticmethod
    def forward(v, X, P, C, O, feasible, mu, margin):
        return _hessian_vector(v, X, P, C, O, feasible, mu, margin)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs[1:6])
        ctx.params = inputs[6:]

    @staticmethod
    def backward(ctx, w):
        args = (*ctx.saved_tensors, *ctx.params)
        hw = _PairHessianVectorFn.apply(w, *args) if torch.is_grad_enabled() else _hessian_vector(w, *args)
        return hw, None, None, None, None, None, None, None

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error("pair_potential")


class _PairGradFn(torch.autograd.Function):
    """grad_x P at the optimal plane; its backward is the IFT Hessian-vector product (second order).

    X (K, 6, 3), P (K, 4) the optimal planes in the contact frames at C + O (C (K, 3) near the pair, X - C exact,
    O (K, 3) in the contact region: ``_Solved.local_plane``), feasible (K,) bool; the formulas are evaluated at
    (X - C) - O, so they keep their digits far from the origin and near the margin."""

    @staticmethod
    def forward(X, P, C, O, feasible, mu, margin):
        Xs, Ps = _safe_rows(_local(X, C, O), P, feasible)
        Ex = _pair_torch.pair_vertex_grad(Xs, Ps, 0.5 * margin)
        return torch.where(feasible[:, None, None], mu * Ex, torch.zeros((), dtype=X.dtype, device=X.device))

    @staticmethod
    def setup_context(ctx, inputs, output):
        X, P, C, O, feasible, mu, margin = inputs
        ctx.save_for_backward(X, P, C, O, feasible)
        ctx.params = (mu, margin)

    @staticmethod
    def backward(ctx, v):
        # d/dx (v . grad_x P) = v^T hess_x P; with p*(x) implicit: hess = mu (E_xx - E_xp E_pp^-1 E_px).
        X, P, C, O, feasible = ctx.saved_tensors
        if not torch.is_grad_enabled():
            return _hessian_vector(v, X, P, C, O, feasible, *ctx.params), None, None, None, None, None, None
        # create_graph=True: differentiable in v, the derivative in X (third order) refused
        hv = _PairHessianVectorFn.apply(v, X.detach(), P, C, O, feasible, *ctx.params)
        return refuse_third_order(hv, X, "pair_potential"), None, None, None, None, None, None

    @staticmethod
    def vmap(info, in_dims, *args):
        raise vmap_error("pair_potential")

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error("pair_potential")


class _PairPotentialFn(torch.autograd.Function):
    """(P(X) (K,), optimal planes (K, 4) in the contact frames at C + O, C (K, 3), O (K, 3), feasible (K,) bool) for
    X (K, 6, 3) float64; only P is differentiable. Backward via the envelope theorem, double backward via
    _PairGradFn."""

    @staticmethod
    def forward(X, mu, margin, tol, max_iter, backend):
        sol = _solve(X, mu=mu, margin=margin, tol=tol, max_iter=max_iter, want_grad=False, want_hess=False,
                     backend=backend)  # fmt: skip
        return sol.value, sol.local_plane, sol.centre, sol.offset, torch.isfinite(sol.value)

    @staticmethod
    def setup_context(ctx, inputs, output):
        X, mu, margin = inputs[:3]
        _, P, C, O, feasible = output
        ctx.mark_non_differentiable(P, C, O, feasible)
        ctx.save_for_backward(X, P, C, O, feasible)
        ctx.params = (mu, margin)

    @staticmethod
    def backward(ctx, gout, _gP, _gC, _gO, _gfeasible):
        # dP/dx = mu dE/dx at p* (envelope theorem: dE/dp = 0 there). Computed by a differentiable Function so
        # that create_graph=True gives the exact implicit Hessian on the second pass.
        X, P, C, O, feasible = ctx.saved_tensors
        mu, margin = ctx.params
        g = _PairGradFn.apply(X, P, C, O, feasible, mu, margin)
        return gout[:, None, None] * g, None, None, None, None, None

    @staticmethod
    def vmap(info, in_dims, *args):
        raise vmap_error("pair_potential")

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error("pair_potential")


def _prepare(tri_a, tri_b, mu, margin, tol, max_iter, name):
    check_triangles(tri_a, "tri_a")
    check_triangles(tri_b, "tri_b")
    check_alike(tri_a, tri_b, "tri_a", "tri_b")
    check_stiffness(mu, "mu")
    check_positive(margin, "margin")
    check_tolerance(tol, "tol")
    check_count(max_iter, "max_iter")
    try:
        batch = torch.broadcast_shapes(tri_a.shape[:-2], tri_b.shape[:-2])
    except RuntimeError as err:
        raise ValueError(
            f"tri_a batch shape {tuple(tri_a.shape[:-2])} and tri_b batch shape {tuple(tri_b.shape[:-2])} "
            "do not broadcast"
        ) from err
    a = widened(tri_a, name, "tri_a and tri_b").expand(*batch, 3, 3)
    b = widened(tri_b, name, "tri_a and tri_b").expand(*batch, 3, 3)
    X = torch.cat([a, b], -2).reshape(-1, 6, 3)
    return X, batch


def pair_potential(
    tri_a: torch.Tensor,
    tri_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    tol: float = DEFAULT_CONTACT.pair_tol,
    max_iter: int = DEFAULT_CONTACT.pair_max_iter,
    backend: str = "auto",
) -> torch.Tensor:
    """Exact separating-plane potential of triangle pairs, differentiable to second order.

    Args:
        tri_a: (..., 3, 3) vertices of the first triangles [m] (vertex index, then xyz).
        tri_b: (..., 3, 3) vertices of the second triangles; leading dims broadcast with ``tri_a``.
        mu: contact coefficient (stiffness scale).
        margin: delta, the gap below which the potential is +inf [m].
        tol: relative gradient tolerance of the inner plane solve (max_i |dE/dp_i| / sum |terms of dE/dp_i|).
        max_iter: Newton iteration cap; a feasible pair that does not converge raises ``PairSolveError``.
        backend: 'auto' (fused numba kernel on CPU, batched tensors elsewhere), 'numba' or 'torch'.

    Returns:
        (...) potential in the input dtype (the solve runs in float64), +inf where the triangles are within
        ``margin`` or intersect. ``torch.autograd.grad`` with ``create_graph=True`` gives exact implicit
        Hessians; a third derivative raises. ``torch.func.grad`` and ``jacrev`` work the same way; ``vmap`` and
        forward mode raise ``NotImplementedError``.

    Raises:
        ValueError: bad shapes, dtypes, NaN/inf coordinates or degenerate triangles (naming argument and index).
        TypeError: a triangle argument that is not a tensor, or a setting of the wrong type.
        PairSolveError: the inner solve did not converge for some pair.
    """
    refuse_vmap("pair_potential", tri_a, tri_b)
    X, batch = _prepare(tri_a, tri_b, mu, margin, tol, max_iter, "pair_potential")
    val = _PairPotentialFn.apply(X, float(mu), float(margin), float(tol), int(max_iter), backend)[0]
    return narrowed(val.reshape(batch), tri_a.dtype, "pair_potential's value", "tri_a and tri_b")


def pair_potential_derivatives(
    tri_a: torch.Tensor,
    tri_b: torch.Tensor,
    *,
    mu: float = DEFAULT_CONTACT.stiffness,
    margin: float = DEFAULT_CONTACT.margin,
    hessian: bool = True,
    tol: float = DEFAULT_CONTACT.pair_tol,
    max_iter: int = DEFAULT_CONTACT.pair_max_iter,
    backend: str = "auto",
) -> PairDerivatives:
    """Value, gradient, Hessian and optimal plane in closed form from the converged plane (no autograd graph).

    Args:
        tri_a, tri_b, mu, margin, tol, max_iter, backend: as in :func:`pair_potential`.
        hessian: whether to form the (..., 18, 18) Hessian (skip it to save the work when only forces are needed).

    Returns:
        PairDerivatives(value (...), grad (..., 18), hessian (..., 18, 18) | None, plane (..., 4)), in the input
        dtype. The 18 coordinates are [a0, a1, a2, b0, b1, b2] flattened xyz. Where value is +inf the other
        fields are zero. Values only: where an input requires grad, a backward through a field raises (use
        :func:`pair_potential` under autograd for derivatives of these).
    """
    refuse_vmap("pair_potential_derivatives", tri_a, tri_b)
    check_bool(hessian, "hessian")
    X, batch = _prepare(tri_a, tri_b, mu, margin, tol, max_iter, "pair_potential_derivatives")
    with outside_transforms(), torch.no_grad():  # values only: not connected to autograd or torch.func
        sol = _solve(
            plain(X), mu=float(mu), margin=float(margin), tol=float(tol), max_iter=int(max_iter), want_grad=True,
            want_hess=hessian, backend=backend,
        )  # fmt: skip
    val, P, grad, hess = sol.value, sol.world_plane(), sol.grad, sol.hess
    dt, name, inputs = tri_a.dtype, "pair_potential_derivatives'", "tri_a and tri_b"
    out = PairDerivatives(
        value=narrowed(val.reshape(batch), dt, f"{name} value", inputs),
        grad=narrowed(grad.reshape(*batch, 18), dt, f"{name} grad", inputs),
        hessian=None
        if hess is None
        else narrowed(hess.reshape(*batch, 18, 18), dt, f"{name} hessian", inputs),
        plane=P.reshape(*batch, 4).to(dt),
    )
    message = VALUES_ONLY.format(name="pair_potential_derivatives", diff="pair_potential")
    return values_only(out, out._fields, (tri_a, tri_b), message)
