"""SDRS's local plane barrier between rigid bodies as a contact model: the experiments' ``sdrs`` baseline.

The separating-plane construction of this library's exact pair potential with every term replaced by the locally
supported barrier B(y) = -(y - dhat)^2 ln(y / dhat) / y (0 for y >= dhat, :func:`cfd_torch.baselines.sdrs_barrier`),
summed over the triangle pairs of two bodies with no hierarchy, no blend and no central term::

    P = kappa sum_(ta, tb) min_p [ B(1 - |n|) + sum_k B(sg_k (n . x_k + d) - delta / 2) ]

A triangle pair contributes exactly zero once some plane with |n| <= 1 - dhat leaves its six vertices dhat + delta / 2
away, in particular whenever the triangles are farther apart than 2 (dhat + delta / 2) / (1 - dhat): only pairs closer
than that are evaluated (the bodies' boxes, then the triangles' distances), and no force or gradient reaches bodies
farther apart. A pair within the margin delta (or intersecting) is +inf, as for this library's potential (the margin
widened by 1e-6 of itself: at the margin the optimal plane's gaps round to zero).

Derivatives by the implicit function theorem at each pair's optimal plane p*(x) (x: its 18 vertex coordinates):
grad = f_x and Hessian f_xx - f_xp f_pp^-1 f_px of f(p, x), in closed form, chained to the two bodies' poses.
Lagged friction: one contact per active triangle pair, this library's construction (the vertex forces
kappa |B'(s_k)| |n| along the plane normal, their sum on one triangle the normal force, their centres the contact
points).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .._geometry import triangle_closest_points
from .._validate import check_positive
from ..baselines import (
    _SIDES,
    _sdrs_barrier_derivatives,
    _sdrs_plane_derivatives,
    _sdrs_plane_rows,
    sdrs_barrier,
    sdrs_energy,
    sdrs_planes,
)
from ..config import DEFAULT_CONTACT
from ..rotation import rotation_matrix
from ._primitives import CollisionQuery, Meshes, chain_to_poses, grouped_cross, near_pairs, primitives
from .bsh import BSH
from .model import ContactEval, LaggedContacts

__all__ = ["SdrsContact"]

_SIDE = torch.tensor([0, 0, 0, 1, 1, 1])  # a triangle pair's six vertices: three of body i, three of body j


class SdrsContact:
    """SDRS's local plane barrier between N bodies (a :class:`cfd_torch.contact.ContactModel`; module docstring).

    Args:
        bshes: the N bodies' hierarchies (their triangles).
        dhat: the barrier's support [m].
        stiffness: kappa [N m^-1 per unit B'; B is in m]: a vertex dhat / 2 from the plane pushes with about
            3 kappa.
        margin: delta [m], as this library's potential.
    """

    warm_start = False

    def __init__(
        self,
        bshes: Sequence[BSH],
        dhat: float = DEFAULT_CONTACT.dhat,
        stiffness: float = 10.0,
        margin: float = DEFAULT_CONTACT.margin,
    ):
        if not bshes or not all(isinstance(b, BSH) for b in bshes):
            raise ValueError("bshes must be a non-empty sequence of cfd_torch.BSH")
        for name, v in (("dhat", dhat), ("stiffness", stiffness), ("margin", margin)):
            check_positive(v, name)
        if not dhat < 1.0:
            raise ValueError(f"dhat must be below 1 (the plane's normal has |n| <= 1 - dhat), got {dhat}")
        self.dhat, self.stiffness, self.margin = float(dhat), float(stiffness), float(margin)
        # pairs closer than this are infeasible: the margin, widened by 1e-6 of it so that every feasible pair's
        # optimal plane keeps its gaps positive in float64 (at the margin itself they round to 0: +inf)
        self._infeasible_within = self.margin * (1.0 + 1e-6)
        self.num_bodies = len(bshes)
        self.bshes = tuple(bshes)  # one per body, in the scene's order
        self._meshes = Meshes.build(bshes)
        self._query = CollisionQuery(bshes, self._infeasible_within)

    @property
    def reach(self) -> float:
        """Triangles farther apart than this contribute exactly zero [m]."""
        return 2.0 * (self.dhat + 0.5 * self.margin) / (1.0 - self.dhat)

    def infeasible(
        self, poses: torch.Tensor, pairs: torch.Tensor, scale: torch.Tensor | None = None
    ) -> torch.Tensor:
        return self._query(poses, pairs, scale)

    def _triangle_pairs(self, poses: torch.Tensor, pairs: torch.Tensor):
        """The near body pairs (Q,), and the feasible triangle pairs within reach: their body pair (C,), body-frame
        and world vertices (C, 6, 3)."""
        m = self._meshes
        dev = poses.device
        near = near_pairs(m, poses, pairs, self.reach)
        Fv = m.F.to(dev)
        ga, fa = primitives(near, near.i, m.fstart, Fv)
        gb, fb = primitives(near, near.j, m.fstart, Fv)
        ia, ib = grouped_cross(ga, gb, len(near.pair))
        g = ga[ia]
        ids = torch.cat([Fv[fa[ia]], Fv[fb[ib]]], 1)  # (C, 6)
        x = near.W[near.s[g][:, None], ids]
        dist = triangle_closest_points(x[:, :3], x[:, 3:]).dist if len(g) else x.new_zeros(0)
        keep = (dist < self.reach) & (dist > self._infeasible_within)
        return near.pair, near.pair[g[keep]], m.X.to(dev)[ids[keep]], x[keep]

    def evaluate(
        self,
        poses: torch.Tensor,
        pairs: torch.Tensor,
        order: int,
        ids: torch.Tensor | None = None,
        warm: object | None = None,
    ) -> ContactEval:
        P = pairs.shape[0]
        poses = poses.detach().to(torch.float64)
        value = poses.new_zeros(P)
        grad = poses.new_zeros(P, 12) if order >= 1 else None
        hess = poses.new_zeros(P, 12, 12) if order >= 2 else None
        if P == 0:
            return ContactEval(value, grad, hess, 0, 0)
        near, pair, X, x = self._triangle_pairs(poses, pairs)
        h, dl = self.dhat, self.margin
        C = 0
        if len(pair):
            p = sdrs_planes(x, h, dl)
            e = self.stiffness * sdrs_energy(p, x, h, dl)
            on = e > 0  # the others are exactly zero, with their derivatives
            pair, X, x, p, e = pair[on], X[on], x[on], p[on], e[on]
            C = len(pair)
            value.index_add_(0, pair, e)
        if order >= 1 and C:
            kappa = self.stiffness
            # f(p, x) = kappa [B(1 - |n|) + sum_k B(s_k)], s_k = sg_k (n . x_k + d) - delta / 2:
            # f_x_k = kappa B'(s_k) sg_k n (f_p = 0 at the optimum)
            n, sg = p[:, :3], _SIDES.to(x)
            s_k = sg * ((x * n[:, None]).sum(-1) + p[:, 3:]) - 0.5 * dl
            b1, b2 = _sdrs_barrier_derivatives(s_k, h)  # (C, 6)
            gx = kappa * (b1 * sg)[..., None] * n[:, None]
            Hx = None
            if order >= 2:
                # f_xx: kappa B''(s_k) n n^T on the diagonal blocks; f_x_k p = kappa sg_k (B''(s_k) n a_k^T +
                # B'(s_k) [I 0]), a_k = sg_k [x_k, 1]; f_pp the plane solve's Hessian
                _, Hpp = _sdrs_plane_derivatives(p, x, h, dl)
                a = _sdrs_plane_rows(x)  # (C, 6, 4)
                Hxp = (b2 * sg)[..., None, None] * n[:, None, :, None] * a[:, :, None, :]  # (C, 6, 3, 4)
                Hxp[..., :3] += (b1 * sg)[..., None, None] * torch.eye(3, dtype=x.dtype, device=x.device)
                Hxp = kappa * Hxp.reshape(C, 18, 4)
                # (a pseudo-inverse: where few barrier terms are active the energy is flat along some planes)
                Hinv = torch.linalg.pinv(kappa * Hpp, hermitian=True, rtol=1e-12)
                Hx = -(Hxp @ Hinv @ Hxp.transpose(1, 2)).reshape(C, 6, 3, 6, 3)
                diag = kappa * b2[..., None, None] * n[:, None, :, None] * n[:, None, None, :]  # (C, 6, 3, 3)
                k6 = torch.arange(6, device=x.device)
                Hx[:, k6, :, k6, :] += diag.transpose(0, 1)
            N = poses.shape[1]
            side = _SIDE.to(poses.device).expand(C, 6)
            rows = pairs[pair][:, :1] * N + pairs[pair][:, 1:].gather(1, side)
            g, H = chain_to_poses(gx, Hx, X, side, rows, poses)
            grad.index_add_(0, pair, g)
            if H is not None:
                hess.index_add_(0, pair, H)
        if len(near):  # within the margin or intersecting: +inf (as ``infeasible``)
            bad = self.infeasible(poses, pairs[near])
            inf = near[bad]
            value[inf] = float("inf")
            for d in (grad, hess):  # no force from an infeasible pair, as this library's potential
                if d is not None:
                    d[inf] = 0.0
        return ContactEval(value, grad, hess, 0, C)

    def lagged(
        self, poses: torch.Tensor, pairs: torch.Tensor, active: float, create_graph: bool = False
    ) -> LaggedContacts:
        S, N = poses.shape[:2]
        h, dl = self.dhat, self.margin
        with torch.no_grad():
            _, pair, X, xd = self._triangle_pairs(poses.detach().to(torch.float64), pairs)
            p = sdrs_planes(xd, h, dl) if len(pair) else xd.new_zeros(0, 4)
            on = sdrs_energy(p, xd, h, dl) > 0 if len(pair) else torch.zeros(0, dtype=torch.bool)
            pair, X, xd, p = pair[on], X[on], xd[on], p[on]
        side = _SIDE.to(poses.device).expand(len(pair), 6)
        rows = pairs[pair][:, :1] * N + pairs[pair][:, 1:].gather(1, side)
        table = poses.reshape(S * N, 6) if create_graph else poses.reshape(S * N, 6).detach()
        R = rotation_matrix(table[:, 3:])
        x = torch.einsum("cvij,cvj->cvi", R[rows], X) + table[rows, :3]
        if create_graph and len(pair):  # the plane as a differentiable function of the vertices: one implicit
            # Newton step from the optimum (its value is the optimum, its first derivative dp*/dx)
            gp, Hp = _sdrs_plane_derivatives(p, x, h, dl)
            Hinv = torch.linalg.pinv(Hp.detach(), hermitian=True, rtol=1e-12)
            p = p - (Hinv @ (gp - gp.detach())[..., None])[..., 0]
        n = p[:, :3]
        sg = _SIDES.to(x)
        s = sg * ((x * n[:, None]).sum(-1) + p[:, 3:]) - 0.5 * dl
        with torch.enable_grad():
            y = s.detach().requires_grad_(True)
            (dB,) = torch.autograd.grad(sdrs_barrier(y, h).sum(), y)
        # B'(s) as a function of s: exact at s, and first-order in s through B'' (for the adjoint)
        if create_graph:
            y = s.detach().requires_grad_(True)
            with torch.enable_grad():
                (b1,) = torch.autograd.grad(sdrs_barrier(y, h).sum(), y, create_graph=True)
                (b2,) = torch.autograd.grad(b1.sum(), y)
            dB = dB + b2 * (s - s.detach())
        f = (
            self.stiffness * dB.abs() * torch.linalg.vector_norm(n, dim=-1, keepdim=True)
        )  # (C, 6) vertex forces
        fa, fb = f[:, :3], f[:, 3:]
        sa, sb = fa.sum(1, keepdim=True), fb.sum(1, keepdim=True)
        # a contact needs force on both triangles (one side's terms may vanish or underflow): the others are
        # dropped below, and divide by 1 here so that no NaN enters the graph
        loaded = (sa[:, 0] > 0) & (sb[:, 0] > 0)
        lam = fa.sum(1)
        Xa = (fa[..., None] * X[:, :3]).sum(1) / torch.where(sa > 0, sa, torch.ones_like(sa))
        Xb = (fb[..., None] * X[:, 3:]).sum(1) / torch.where(sb > 0, sb, torch.ones_like(sb))
        pc = pairs[pair]
        bi, bj = pc[:, 0] * N + pc[:, 1], pc[:, 0] * N + pc[:, 2]
        xa = torch.einsum("cij,cj->ci", R[bi], Xa) + table[bi, :3]
        xb = torch.einsum("cij,cj->ci", R[bj], Xb) + table[bj, :3]
        u = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
        T = torch.eye(3, dtype=u.dtype, device=u.device) - u[:, :, None] * u[:, None, :]
        keep = loaded
        if active > 0 and len(lam):
            top = lam.new_zeros(pairs.shape[0]).scatter_reduce(0, pair, lam.detach(), "amax")
            keep = keep & (lam.detach() >= active * top[pair])
        return LaggedContacts(
            pair[keep], torch.stack([Xa, Xb], 1)[keep], torch.stack([xa, xb], 1)[keep], T[keep], lam[keep]
        )
