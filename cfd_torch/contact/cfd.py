"""The paper's contact model for the simulator: the BSH potential of every interacting body pair (SPEC sections 2-4),
its collision query, and lagged friction contacts on its exact leaf pairs.

Lagged friction data, from the start-of-step configuration q_t, for every exact leaf pair c (triangles ta of body a
and tb of body b, inherited blend weight w_c = product of the ancestors' (1 - phi))::

    f_k      = |dP/dx_k|  for the six vertices (the pair potential's vertex forces, all along the plane normal)
    lambda_c = w_c sum_{k in ta} f_k            normal force magnitude [N] (equal on both sides at the optimum)
    n_c      = unit normal of the force on ta;  T_c = I - n_c n_c^T  (projector onto the contact plane)
    X_a      = sum_{k in ta} (f_k / sum f) X_k  body-frame force centre on ta (same on tb): one material point per
                                                side, so the contact point moves rigidly with its body.

The lagged data are differentiable functions of q_t on request (the pair potential's second-order autograd for the
vertex forces, the blend weights' closed-form gradient), so the step's adjoint sees how friction depends on the
previous state; only the discrete leaf set is fixed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from .._validate import check_pair_eps, check_pair_mu
from ..config import ContactConfig
from ..rotation import rotation_matrix
from ._traverse import Forest, build_forest, penetrating, traverse
from .bsh import BSH, unique_hierarchies
from .model import ContactEval, LaggedContacts
from .pair import pair_potential, pair_potential_derivatives

__all__ = ["CfdContact"]


class CfdContact:
    """The long-range contact potential of N bodies (a :class:`cfd_torch.contact.ContactModel`).

    Args:
        bshes: the N bodies' hierarchies, in body order (one BSH may serve several bodies).
        config: the potential's settings (default ``ContactConfig()``).
        pair_eps: body pairs (i, j) whose blend width is not ``config.eps``, with their own (a positive number):
            e.g. a wide band between a pusher and the objects it should find, a narrow one between the objects
            and the floor they rest on.
        pair_mu: body pairs (i, j) whose stiffness is not ``config.stiffness``, with their own: the potential is
            linear in it, so their values, derivatives and lagged normal forces are scaled by mu_ij /
            ``config.stiffness`` (e.g. a lower stiffness for a small, light body on a floor, which the default
            leaves hovering, beside decimetre bodies that keep it: :func:`cfd_torch.stiffness_for_rest_gap`).
    """

    warm_start = True  # evaluate() takes ids / warm: the leaf pairs' plane solves start from earlier planes
    partial_hessian = (
        True  # evaluate() takes hessian_of: the blocks of the bodies that do not move are skipped
    )

    def __init__(
        self,
        bshes: Sequence[BSH],
        config: ContactConfig | None = None,
        pair_eps: Mapping[tuple[int, int], float] | None = None,
        pair_mu: Mapping[tuple[int, int], float] | None = None,
    ) -> None:
        if not all(isinstance(b, BSH) for b in bshes):
            raise ValueError("bshes must be a sequence of cfd_torch.BSH")
        self.config = ContactConfig() if config is None else config
        #: the gap below which the potential is +inf
        self.margin = self.config.margin
        self._bshes, self._which = unique_hierarchies(bshes)
        self.num_bodies = N = len(bshes)
        self.bshes = tuple(bshes)  # one per body, in the scene's order
        self._forests: dict[torch.device, tuple[Forest, torch.Tensor]] = {}  # built once per device
        self._eps = None  # (N, N) blend width of each body pair, when some pair has its own
        pair_eps = check_pair_eps(pair_eps, N)
        if pair_eps:
            table = torch.full((N, N), float(self.config.eps), dtype=torch.float64)
            for (i, j), e in pair_eps.items():
                table[i, j] = table[j, i] = e
            self._eps = table
        self._mu = None  # (N, N) each body pair's stiffness over config.stiffness, when some pair has its own
        pair_mu = check_pair_mu(pair_mu, N)
        if pair_mu:
            table = torch.ones((N, N), dtype=torch.float64)
            for (i, j), mu in pair_mu.items():
                table[i, j] = table[j, i] = mu / self.config.stiffness
            self._mu = table

    def __getstate__(self) -> dict:
        # the per-device forests are a cache (concatenations of the hierarchies): a pickle carries no device's tensors
        return {**self.__dict__, "_forests": {}}

    def _pair_eps(self, pairs: torch.Tensor) -> float | torch.Tensor:
        """The blend width of each pair row (s, i, j): ``config.eps`` for all, or (P,) from ``pair_eps``."""
        if self._eps is None:
            return self.config.eps
        eps = self._eps.to(pairs.device)
        return eps[pairs[:, 1], pairs[:, 2]]

    def _pair_scale(self, pairs: torch.Tensor) -> torch.Tensor | None:
        """Each pair row's (s, i, j) stiffness over ``config.stiffness`` (P,), or None where none has its own."""
        if self._mu is None:
            return None
        return self._mu.to(pairs.device)[pairs[:, 1], pairs[:, 2]]

    def _forest(self, device: torch.device) -> tuple[Forest, torch.Tensor]:
        """The concatenated float64 hierarchies on ``device`` and each body's root node (N,)."""
        if device not in self._forests:
            forest = build_forest(self._bshes, torch.float64, device)
            self._forests[device] = (forest, forest.roots[self._which.to(device)])
        return self._forests[device]

    def _rows(self, poses: torch.Tensor, pairs: torch.Tensor):
        """Pose table (S N, 6), pair rows (P, 2) into it, root nodes (P, 2)."""
        S, N = poses.shape[:2]
        forest, roots = self._forest(poses.device)
        rows = pairs[:, :1] * N + pairs[:, 1:]
        return forest, poses.reshape(S * N, 6), rows, roots[pairs[:, 1:]]

    def evaluate(
        self,
        poses: torch.Tensor,
        pairs: torch.Tensor,
        order: int,
        ids: torch.Tensor | None = None,
        warm: object | None = None,
        hessian_of: torch.Tensor | None = None,
    ) -> ContactEval:
        """The potential of each pair; with ``ids``, the leaf pairs' plane solves start from the planes in ``warm``
        (an earlier ContactEval's ``warm``: sorted keys (W,) of (id, leaf, leaf) and planes (W, 4)) and the
        result carries this call's planes (CPU kernels; elsewhere ``warm`` stays None). ``hessian_of`` (P, 2)
        bool: whose Hessian blocks to form (the CPU kernels leave the others zero; see ``traverse``)."""
        c = self.config
        if pairs.shape[0] == 0:
            z = poses.new_zeros(0)
            return ContactEval(
                z,
                poses.new_zeros(0, 12) if order else None,
                poses.new_zeros(0, 12, 12) if order > 1 else None,
                0,
                0,
            )
        forest, table, rows, roots = self._rows(poses, pairs)
        use_warm = ids is not None and poses.device.type == "cpu" and c.backend != "torch"
        if use_warm:
            keys, planes = warm if warm is not None else (ids.new_zeros(0), poses.new_zeros(0, 4))
        out = traverse(
            forest, rows, roots, table.detach(), mu=c.stiffness, margin=c.margin, eps=self._pair_eps(pairs),
            split=c.split,
            order=order, tol=c.pair_tol, max_iter=c.pair_max_iter, backend=c.backend,
            warm=(ids, keys, planes) if use_warm else None, hessian_of=hessian_of,
        )  # fmt: skip
        v, g, h, st = out[:4]
        scale = self._pair_scale(pairs)
        if scale is not None:  # the potential is linear in its stiffness
            scale = scale.to(v)
            v = v * scale
            g = None if g is None else g * scale[:, None]
            h = None if h is None else h * scale[:, None, None]
        return ContactEval(v, g, h, st["node_pairs"], st["leaf_pairs"], out[4] if use_warm else None)

    def infeasible(
        self, poses: torch.Tensor, pairs: torch.Tensor, scale: torch.Tensor | None = None
    ) -> torch.Tensor:
        c, cpu = self.config, torch.device("cpu")
        if pairs.shape[0] == 0:
            return torch.zeros(0, dtype=torch.bool, device=poses.device)
        # the collision query runs on the CPU (numba; (S N, 6) poses travel)
        forest, table, rows, roots = self._rows(poses.detach().to(cpu, torch.float64), pairs.to(cpu))
        sc = None if scale is None else scale.to(cpu, torch.float64).repeat(poses.shape[0])
        out = penetrating(
            forest, rows, roots, table, margin=c.margin, eps=self._pair_eps(pairs.to(cpu)), split=c.split,
            tol=c.pair_tol,
            max_iter=c.pair_max_iter, scale=sc,
        )  # fmt: skip
        return out.to(poses.device)

    def lagged(
        self,
        poses: torch.Tensor,
        pairs: torch.Tensor,
        active: float,
        create_graph: bool = False,
        ids: torch.Tensor | None = None,
    ) -> LaggedContacts:
        """The lagged friction contacts (see ``ContactModel``); with ``ids`` (P,), on the numba kernels, also the
        warm-start data of every feasible leaf pair (keys of (id, leaf, leaf) and planes in the pair's frame, as
        :meth:`evaluate` makes them)."""
        c = self.config
        kw = {"mu": c.stiffness, "margin": c.margin, "tol": c.pair_tol, "max_iter": c.pair_max_iter}
        forest, table, rows, roots = self._rows(poses, pairs)
        fused = poses.device.type == "cpu" and poses.dtype == torch.float64 and c.backend != "torch"
        warm = None
        with torch.no_grad():
            LI, LJ, lp, lw, dlw = traverse(
                forest, rows, roots, table.detach(), eps=self._pair_eps(pairs), split=c.split,
                order=1 if create_graph else 0,
                leaves_only=True, backend=c.backend, **kw,
            )  # fmt: skip
            ba, bb = rows[lp, 0], rows[lp, 1]

            def world(q):  # the contacts' triangles at poses q (S N, 6), and the rotations
                R = rotation_matrix(q[:, 3:])
                return (
                    Xa @ R[ba].transpose(1, 2) + q[ba, None, :3],
                    Xb @ R[bb].transpose(1, 2) + q[bb, None, :3],
                    R,
                )

            if fused:  # the numba kernels: leaf inputs in one pass, the plane solves without input checks
                from ._traverse_numba import leaf_inputs, warm_table
                from .pair import _solve

                R = rotation_matrix(table[:, 3:].detach())
                e = lp[:0]
                Xa, Xb, X, *_ = (
                    torch.from_numpy(x)
                    for x in leaf_inputs(
                        forest.tris.numpy(), forest.tri.numpy(), LI.numpy(), LJ.numpy(), lp.numpy(),
                        rows.contiguous().numpy(), R.contiguous().numpy(),
                        table[:, :3].detach().contiguous().numpy(), e.numpy(), e.numpy(),
                        table.new_zeros(0, 4).numpy(), 0,
                    )
                )  # fmt: skip
                sol = _solve(X, want_grad=True, want_hess=False, backend="numba", **kw)
                g = sol.grad.reshape(-1, 2, 3, 3)
                planes = (sol.local_plane, sol.centre, sol.offset, torch.isfinite(sol.value))
                # with ids, the planes (in frames at the solve's centres C) in the frames at body a: d - n.(C - t_a)
                if ids is not None:
                    M = forest.centre.shape[0]
                    keys = (ids.to(lp.device)[lp] * M + LI) * M + LJ
                    warm = tuple(
                        torch.from_numpy(x)
                        for x in warm_table(
                            keys.numpy(), sol.value.numpy(), sol.plane.contiguous().numpy(),
                            (sol.centre - table[ba, :3].detach()).contiguous().numpy(),
                        )
                    )  # fmt: skip
            else:
                planes = None
                Xa, Xb = forest.tris[forest.tri[LI]], forest.tris[forest.tri[LJ]]  # (C, 3, 3) body frame
                wa, wb, R = world(table.detach())
                # vertex forces in closed form (envelope theorem; no autograd)
                g = pair_potential_derivatives(wa, wb, hessian=False, backend=c.backend, **kw).grad.reshape(
                    -1, 2, 3, 3
                )
            if fused and not create_graph:  # the contact data in one numba pass
                from ._lagged_numba import lagged_contacts

                keep, X, x, T, lam = (
                    torch.from_numpy(v)
                    for v in lagged_contacts(
                        g.contiguous().numpy(), lw.contiguous().numpy(), lp.numpy(), Xa.numpy(), Xb.numpy(),
                        R.contiguous().numpy(), table[:, :3].detach().contiguous().numpy(), ba.contiguous().numpy(),
                        bb.contiguous().numpy(), float(active), pairs.shape[0],
                    )
                )  # fmt: skip
                return LaggedContacts(lp[keep], X, x, T, self._scaled(lam, pairs, lp[keep]), warm)
            ga, gb = g[:, 0], g[:, 1]
            if active > 0 and lp.numel():
                lam = lw * torch.linalg.vector_norm(ga, dim=-1).sum(1)
                top = torch.zeros(pairs.shape[0], dtype=lam.dtype, device=lam.device)
                top = top.scatter_reduce(0, lp, lam, "amax")
                keep = lam >= active * top[lp]
                LI, LJ, lp, lw, ba, bb, Xa, Xb, ga, gb = (
                    x[keep] for x in (LI, LJ, lp, lw, ba, bb, Xa, Xb, ga, gb)
                )
                dlw = dlw[keep] if dlw is not None else None
                planes = None if planes is None else tuple(x[keep] for x in planes)
        if create_graph:
            # the same data as differentiable functions of the poses: blend weights to first order (exact gradient,
            # as the adjoint needs), vertex forces by the pair potential's implicit second-order autograd
            dq = torch.cat([table[ba], table[bb]], 1)
            lw = lw + ((dq - dq.detach()) * dlw).sum(1)
            with torch.enable_grad():
                wa, wb, R = world(table)
                if (
                    planes is not None
                ):  # at the optimal planes solved above: the gradient Function, no second solve
                    from .pair import _PairGradFn

                    gv = _PairGradFn.apply(
                        torch.cat([wa, wb], 1), *planes, float(c.stiffness), float(c.margin)
                    )
                    ga, gb = gv[:, :3], gv[:, 3:]
                else:
                    P = pair_potential(wa, wb, backend=c.backend, **kw)
                    ga, gb = torch.autograd.grad(P.sum(), (wa, wb), create_graph=True)
        fa = torch.linalg.vector_norm(ga, dim=-1)  # (C, 3)
        fb = torch.linalg.vector_norm(gb, dim=-1)
        sa, sb = fa.sum(1), fb.sum(1)
        lam = lw * sa
        pa = ((fa / sa[:, None])[:, :, None] * Xa).sum(1)
        pb = ((fb / sb[:, None])[:, :, None] * Xb).sum(1)
        n = -ga.sum(1)
        n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
        T = torch.eye(3, dtype=n.dtype, device=n.device) - n[:, :, None] * n[:, None, :]
        t = table[:, :3] if create_graph else table[:, :3].detach()
        xa = torch.einsum("cij,cj->ci", R[ba], pa) + t[ba]
        xb = torch.einsum("cij,cj->ci", R[bb], pb) + t[bb]
        lam = self._scaled(lam, pairs, lp)
        return LaggedContacts(lp, torch.stack([pa, pb], 1), torch.stack([xa, xb], 1), T, lam, warm)

    def _scaled(self, lam: torch.Tensor, pairs: torch.Tensor, lp: torch.Tensor) -> torch.Tensor:
        """The contacts' normal forces ``lam`` (C,) of the pair rows ``lp`` scaled by their pairs' stiffness."""
        scale = self._pair_scale(pairs)
        return lam if scale is None else lam * scale.to(lam)[lp]
